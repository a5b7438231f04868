"""Configuration: YAML files validated into dataclasses at start-up.

:func:`load` reads a file into a dataclass; :func:`from_dict` does the same for an in-memory mapping. A bad
file fails with :class:`ConfigError`, which names the file, the key (dotted path) and what was expected.

Dataclass fields may carry bounds with :func:`setting` (``lo``, ``hi``, ``choices``, ``length``). A field
whose type is a base class with a ``VARIANTS`` mapping is a tagged union chosen by its ``kind`` key (one config
dataclass per kind of device, as the robot and sensor drivers do).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

T = TypeVar("T")


class ConfigError(ValueError):
    def __init__(self, source: str, key: str, problem: str) -> None:
        super().__init__(f"{source}: {key or '<top level>'}: {problem}")
        self.source = source
        self.key = key
        self.problem = problem


def cli_number(kind: type[int] | type[float] = float, lo: float | None = None,
               hi: float | None = None) -> typing.Callable[[str], float]:
    """An argparse ``type``: a number within [lo, hi], so that the command line gets the checks a YAML setting
    gets (argparse prints the message as a usage error naming the option)."""
    def parse(text: str) -> float:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a {'whole number' if kind is int else 'number'}") from None
        if math.isnan(value) or (lo is not None and value < lo) or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(
                f"{text!r} is not within {'-inf' if lo is None else f'{lo:g}'}..{'inf' if hi is None else f'{hi:g}'}")
        return value
    return parse


def setting(
    default: Any = dataclasses.MISSING,
    *,
    lo: float | None = None,
    hi: float | None = None,
    choices: typing.Iterable[Any] | None = None,
    length: int | None = None,
    default_factory: Any = dataclasses.MISSING,
    help: str = "",
) -> Any:
    meta = {"lo": lo, "hi": hi, "choices": tuple(choices) if choices else None, "length": length, "help": help}
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def _expected(hint: Any) -> str:
    return getattr(hint, "__name__", None) or str(hint).replace("typing.", "")


def _convert(source: str, key: str, value: Any, hint: Any, meta: dict[str, Any], base_dir: Path | None) -> Any:
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if value is None:
            if type(None) in typing.get_args(hint):
                return None
            raise ConfigError(source, key, f"expected {_expected(hint)}, got nothing")
        return _convert(source, key, value, args[0], meta, base_dir)
    if dataclasses.is_dataclass(hint):
        return _build(source, key, value, hint, base_dir)
    if hint is Any:
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(source, key, f"expected true or false, got {value!r}")
        return value
    if hint in (int, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (hint is int and isinstance(value, float)):
            raise ConfigError(source, key, f"expected {'an integer' if hint is int else 'a number'}, got {value!r}")
        value = hint(value)
        if not math.isfinite(value):
            raise ConfigError(source, key, f"expected a finite number, got {value!r}")
        if meta.get("lo") is not None and value < meta["lo"]:
            raise ConfigError(source, key, f"expected at least {meta['lo']}, got {value}")
        if meta.get("hi") is not None and value > meta["hi"]:
            raise ConfigError(source, key, f"expected at most {meta['hi']}, got {value}")
    elif hint is str:
        if not isinstance(value, str):
            raise ConfigError(source, key, f"expected a string, got {value!r}")
    elif hint is Path:
        if not isinstance(value, str):
            raise ConfigError(source, key, f"expected a file path, got {value!r}")
        p = Path(os.path.expanduser(value))
        value = p if p.is_absolute() or base_dir is None else (base_dir / p)
    elif origin is list or origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(source, key, f"expected a list, got {value!r}")
        if meta.get("length") is not None and len(value) != meta["length"]:
            raise ConfigError(source, key, f"expected {meta['length']} values, got {len(value)}")
        item_meta = {k: meta.get(k) for k in ("lo", "hi")}
        item = args[0] if args else Any
        value = [_convert(source, f"{key}[{i}]", v, item, item_meta, base_dir) for i, v in enumerate(value)]
        return tuple(value) if origin is tuple else value
    elif origin is dict:
        kt, vt = typing.get_args(hint)
        if not isinstance(value, dict):
            raise ConfigError(source, key, f"expected a mapping, got {value!r}")
        return {
            _convert(source, f"{key}.{k}", k, kt, {}, base_dir): _convert(source, f"{key}.{k}", v, vt, {}, base_dir)
            for k, v in value.items()
        }
    else:
        raise TypeError(f"unsupported config type {hint!r} at {key}")  # a programming error
    if meta.get("choices") and value not in meta["choices"]:
        raise ConfigError(source, key, f"expected one of {list(meta['choices'])}, got {value!r}")
    return value


def _build(source: str, key: str, data: Any, cls: type[T], base_dir: Path | None) -> T:
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(source, key, f"expected a mapping for {cls.__name__}, got {data!r}")
    variants: dict[str, type] | None = getattr(cls, "VARIANTS", None)
    if variants:
        kind = data.get("kind")
        if kind not in variants:
            raise ConfigError(source, f"{key}.kind" if key else "kind", f"expected one of {sorted(variants)}, got {kind!r}")
        cls = variants[kind]  # type: ignore[assignment]
        data = {k: v for k, v in data.items() if k != "kind"}
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    for k in data:
        if k not in fields:
            raise ConfigError(source, f"{key}.{k}" if key else str(k), f"unknown key (known: {', '.join(sorted(fields))})")
    values = {}
    for name, f in fields.items():
        sub = f"{key}.{name}" if key else name
        if name in data:
            values[name] = _convert(source, sub, data[name], hints[name], dict(f.metadata), base_dir)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(source, sub, f"missing (expected {_expected(hints[name])})")
    try:
        obj = cls(**values)
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        raise ConfigError(source, key, str(exc)) from None
    check = getattr(obj, "check", None)
    if check is not None:
        try:
            check()
        except ValueError as exc:
            if isinstance(exc, ConfigError):
                raise
            raise ConfigError(source, key, str(exc)) from None
    return obj


def from_dict(data: Any, cls: type[T], source: str = "<config>", base_dir: Path | None = None) -> T:
    return _build(source, "", data, cls, base_dir)


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing a mapping that names a key twice: the plain loader keeps the last one and says
    nothing (``duration: 1`` then ``duration: 100`` in one step ran for 100 s)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, Any] = {}
        for key_node, _value in node.value:
            key = self.construct_object(key_node, deep=deep)  # type: ignore[no-untyped-call]
            try:
                first = seen.setdefault(key, key_node.start_mark)
            except TypeError:  # an unhashable key: the base loader says so
                break
            if first is not key_node.start_mark:
                raise yaml.constructor.ConstructorError(
                    None, None, f"the key {key!r} appears twice (first at line {first.line + 1}): which one is meant?",
                    key_node.start_mark)
        return super().construct_mapping(node, deep=deep)


def read_yaml(path: str | os.PathLike[str]) -> Any:
    """A YAML file's data; ConfigError naming the file when it cannot be read or is not YAML."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(path), "", f"cannot read the file ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(str(path), "", f"not UTF-8 text (byte {exc.start}): a YAML file is expected") from None
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # a SafeLoader: no Python objects
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        raise ConfigError(str(path), "", f"not valid YAML ({where}{getattr(exc, 'problem', exc)})") from None


def load(path: str | os.PathLike[str], cls: type[T]) -> T:
    """Read a YAML file into ``cls``. Relative paths inside the file are relative to the file."""
    path = Path(path)
    return _build(str(path), "", read_yaml(path), cls, path.parent)


def to_dict(obj: Any) -> Any:
    """A config dataclass → plain data (for manifests and snapshots)."""
    if dataclasses.is_dataclass(obj):
        out = {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
        kind = getattr(type(obj), "KIND", None)
        if kind:
            out["kind"] = kind
        return out
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    if isinstance(obj, Path):
        return str(obj)
    return obj
