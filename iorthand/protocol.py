"""Wire messages: one typed class per key, msgpack maps, validated on decode.

Every message carries ``v`` (schema version), ``seq`` (per-publisher counter) and ``t`` (source time, ns
since the epoch). Each field's type and bounds are declared once, next to the field, with :func:`spec`;
:meth:`Message.decode` checks all of them and raises :class:`DecodeError` naming the offending field. A
receiver never acts on a message that failed to decode: it counts the reject (see :class:`RejectCounter`).

Units are SI on the wire: metres, seconds, radians, newtons. Poses are ``[x, y, z, rx, ry, rz]`` (metres and
a rotation vector, UR's convention) or 4×4 row-major matrices flattened to 16 numbers — never Euler angles.

Two decoders share the declarations. The fast one is a typed ``msgspec`` schema derived from each class's
fields and bounds (:func:`_wire_struct`): it checks a well-formed payload in compiled code, which matters on the
60 Hz command path where a cold CPU makes every Python bytecode count. Whatever it does not accept goes to the
checked decoder, which names the offending field (or accepts what the schema was stricter about, such as a
version sent as ``1.0``): the fast decoder never accepts what the checked one refuses (a differential test).
Messages are encoded with ``msgspec`` too, ``v`` first and the fields in declaration order, so a signed
message's ``mac`` is its last entry (:mod:`iorthand.security.auth` signs the bytes before it).

Releases of different ages meet: a hospital updates its edges, its consoles and its cloud at different times.
What each end does about it (decided here, once):

- **Revisions.** :data:`REVISION` numbers the protocol: each release that adds a field bumps it and lists the
  field in :data:`ADDED_IN` (and in its class's ``ADDED_FIELDS``, so that a newer receiver reads an older
  payload with the field's default). Revision 1 is the release that said none (339ec9f).
- **Said before control, at both ends.** A console's acquire says the revision it speaks (``params``
  ``{"revision": N}``; revision 1 ignored ``params`` there); the edge's answer says its own (``detail``, which
  revision 1 ignored there too), granted or not. The edge refuses control to a console that cannot read a message
  the edge sends (:func:`unreadable_by`), naming both revisions and what to update: such a console would drive
  with part of the picture silently missing (revision 1 dropped every servo and torch state of revision 2: the
  camera's angles and the light were blank, counted as malformed, and said nowhere). The console refuses to go on
  with an edge that cannot read a command it sends, and refuses to ask for control while it cannot read what
  safety needs (a robot, safety, force-level or echo message refused as from a newer sender).
- **Which messages may be read in part.** From revision 2 on, a receiver reads a *display-only* message
  (``DISPLAY_ONLY``: servo and torch states, the wrench, markers, video, vital signs, the twin's and recorder's
  status) that carries fields it does not know, without them: they are extras for the eye, and dropping the whole
  message hid what the receiver does understand. So the next field added to one of them does not cost the console
  of the release before its picture. ``msg.ignored`` names what was left out, each field once, by its path in the
  message: ``zoom`` for one of its own, ``markers[].zoom`` for one of a nested map (the list field, ``[]`` for
  whichever of its elements carried it, the field); the console shows them after the class ("Markers shown without
  markers[].zoom"). A field added there must not change what the fields already there mean (a new meaning is a new
  field or a new key). Every other message is refused whole when it carries a field the receiver does not know, in a
  nested map of it too: commands (an edge never acts on part of an order), control requests and replies, and the state
  safety rests on (robot state, safety status, force level, command echo) — a field added there may be the one that
  says why the robot stopped, and reading the rest as if complete would be reading a different message. A field added
  to them makes the edge refuse control to the consoles of the releases before, clearly;
  the stop is the exception that needs none of this (any payload on ``cmd/stop`` stops the edge).
- **Said once per key.** A refusal or an ignored field that a newer sender explains names the message, the
  field and says "the sender is newer: update this program"; :class:`RejectCounter` logs it once per key (not at
  the message rate), and the operator's console shows it once in its log.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import logging
import math
import sys
import threading
import time
import types
import typing
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from enum import IntEnum, StrEnum
from operator import attrgetter
from typing import Annotated, Any, ClassVar, Literal, Self

import msgpack
import msgspec

from iorthand import channels, keys

MAX_PAYLOAD = 64 * 1024  # default size limit of one message, bytes
MAX_VIDEO_PAYLOAD = 8 * 1024 * 1024
_MAX_INT = 2**63 - 1
_FAR_FUTURE_NS = 2**62  # about year 2116: any later source time is garbage
MAC_MAX = 32  # bytes of a command's signature field (iorthand.security.auth uses 16)
KEY_MAX = 64  # bytes of a grant's key in the acquire reply (iorthand.security.auth uses 32)
_MAX_IGNORED = 8  # names of unknown fields a display-only message keeps in ``ignored`` (the sender chose them)

log = logging.getLogger("iorthand.protocol")

# The protocol's revision (see the module's docstring): bump it in a release that adds a field, listed in ADDED_IN.
REVISION = 2
# The fields each revision added, by class (each also in its class's ADDED_FIELDS: checked at import). Revision 1
# is the first that shipped: what it has, all its receivers know.
ADDED_IN: dict[int, dict[str, frozenset[str]]] = {
    2: {"ServoState": frozenset({"period"}), "TorchState": frozenset({"period"})},
}
# The first revision whose receivers read a display-only message without the fields they do not know (before it,
# every receiver refused every message that carried one).
TOLERANT_SINCE = 2
# What a refusal or an ignored field says when the likely cause is a sender of a later release.
NEWER_SENDER = "the sender is newer: update this program"


class DecodeError(ValueError):
    """A payload that is not a valid message. ``field`` names what was wrong (``payload`` for the whole)."""

    def __init__(self, message_type: str, field_name: str, problem: str) -> None:
        super().__init__(f"{message_type}.{field_name}: {problem}")
        self.message_type = message_type
        self.field = field_name
        self.problem = problem

    @property
    def newer(self) -> bool:
        """Whether a sender of a later release explains it (a field or a schema version this build does not know)."""
        return NEWER_SENDER in self.problem


def _unknown_field(mtype: str, name: Any) -> DecodeError:
    return DecodeError(mtype, str(name)[:40], f"unknown field: {NEWER_SENDER} (this program speaks "
                                              f"protocol revision {REVISION})")


def spec(
    default: Any = dataclasses.MISSING,
    *,
    lo: float | None = None,
    hi: float | None = None,
    length: int | None = None,
    max_len: int | None = None,
    default_factory: Any = dataclasses.MISSING,
) -> Any:
    """A message field with its bounds: ``lo``/``hi`` for numbers (and each element of a vector),
    ``length`` for fixed-size vectors, ``max_len`` for strings, bytes and lists."""
    meta = {"lo": lo, "hi": hi, "length": length, "max_len": max_len}
    if default_factory is not dataclasses.MISSING:
        return field(default_factory=default_factory, metadata=meta)
    return field(default=default, metadata=meta)


def vec(n: int, *, lo: float | None = None, hi: float | None = None) -> Any:
    """A fixed-length vector of finite floats, zero by default."""
    return spec(default_factory=lambda: [0.0] * n, length=n, lo=lo, hi=hi)


def printable(text: str) -> str:
    """Text from the wire as it may be shown (a terminal, a report): every character Python does not call
    printable (controls, C1, DEL, format characters such as bidirectional overrides, separators other than the
    space) written as its escape (``\\x1b``, ``\\n``, ``\\u202e``). Shown raw, they would steer a terminal
    (clear the screen, move the cursor, set the window title) or draw lines of their own."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def now_ns() -> int:
    return time.time_ns()


# ---------------------------------------------------------------------------------------------------------
# Validation machinery


Checker = Callable[[str, str, Any], Any]  # (message type, field name, raw value) -> checked value, or DecodeError


def _compile(hint: Any, meta: dict[str, Any]) -> Checker:
    """The checker of one field type, built once per class: decoding runs on every command, so the type
    dispatch happens here rather than for each value (a cold CPU after an idle gap makes every bytecode count)."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        inner = _compile(args[0], meta)
        return lambda mtype, name, value: None if value is None else inner(mtype, name, value)
    if hint is bool:

        def check_bool(mtype: str, name: str, value: Any) -> Any:
            if value.__class__ is not bool:
                raise DecodeError(mtype, name, f"expected bool, got {type(value).__name__}")
            return value

        return check_bool
    if hint in (int, float):
        return _number_checker(hint, meta)
    if hint in (str, bytes):
        max_len = meta.get("max_len")

        def check_text(mtype: str, name: str, value: Any) -> Any:
            if not isinstance(value, hint):
                raise DecodeError(mtype, name, f"expected {hint.__name__}, got {type(value).__name__}")
            if max_len is not None and len(value) > max_len:
                raise DecodeError(mtype, name, f"length {len(value)} exceeds {max_len}")
            return value

        return check_text
    if origin is list:
        (item,) = typing.get_args(hint)
        length, max_len = meta.get("length"), meta.get("max_len")
        if dataclasses.is_dataclass(item):
            each: Checker = lambda mtype, name, v: item._from_map(v, f"{mtype}.{name}")  # noqa: E731
        else:
            each = _compile(item, meta)  # elements share the field's bounds
        fast_floats = item is float

        def check_list(mtype: str, name: str, value: Any) -> Any:
            if not isinstance(value, (list, tuple)):
                raise DecodeError(mtype, name, f"expected a list, got {type(value).__name__}")
            if length is not None and len(value) != length:
                raise DecodeError(mtype, name, f"expected {length} elements, got {len(value)}")
            if max_len is not None and len(value) > max_len:
                raise DecodeError(mtype, name, f"{len(value)} elements exceed {max_len}")
            if fast_floats and _plain_floats(value, meta):
                return list(value)
            return [each(mtype, f"{name}[{i}]", v) for i, v in enumerate(value)]

        return check_list
    raise TypeError(f"unsupported field type {hint!r}")  # a programming error, found at the first decode


def _plain_floats(values: Any, meta: dict[str, Any]) -> bool:
    """True if every value is a finite float within the field's bounds (the common case, checked in one
    pass); anything else goes through the per-element checker, which names what is wrong."""
    lo, hi = meta.get("lo"), meta.get("hi")
    lo = -math.inf if lo is None else lo
    hi = math.inf if hi is None else hi
    return all(v.__class__ is float and lo <= v <= hi for v in values)  # NaN fails both comparisons


def _number_checker(kind: type, meta: dict[str, Any]) -> Checker:
    lo, hi = meta.get("lo"), meta.get("hi")

    def check_number(mtype: str, name: str, value: Any) -> Any:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise DecodeError(mtype, name, f"expected {kind.__name__}, got {type(value).__name__}")
        if kind is int:
            if not isinstance(value, int):
                raise DecodeError(mtype, name, f"expected int, got {type(value).__name__}")
            if not -_MAX_INT <= value <= _MAX_INT:
                raise DecodeError(mtype, name, "integer out of the 64-bit range")
        else:
            value = float(value)
            if not math.isfinite(value):
                raise DecodeError(mtype, name, f"must be finite, got {value}")
        if lo is not None and value < lo:
            raise DecodeError(mtype, name, f"{value} is below the minimum {lo}")
        if hi is not None and value > hi:
            raise DecodeError(mtype, name, f"{value} is above the maximum {hi}")
        return value

    return check_number


_PLAIN = frozenset({str, int, float, bool, bytes, type(None)})


def _to_wire(value: Any) -> Any:
    if value.__class__ in _PLAIN:
        return value
    if isinstance(value, Struct):
        return value._to_map()
    if hasattr(value, "tolist"):  # numpy arrays and scalars → plain Python values (lists, floats, ints, bools)
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [_to_wire(v) for v in value]
    return value


def _encode_hook(value: Any) -> Any:
    """What msgspec cannot encode itself: numpy arrays and scalars, as plain Python values."""
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"cannot encode a {type(value).__name__} in a message")


_ENCODER = msgspec.msgpack.Encoder(enc_hook=_encode_hook)


def _wire_type(hint: Any, meta: dict[str, Any]) -> Any:
    """The msgspec type of one field: the declared type with its bounds (the same the checkers apply)."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        (inner,) = [a for a in typing.get_args(hint) if a is not type(None)]
        return _wire_type(inner, meta) | None
    lo, hi = meta.get("lo"), meta.get("hi")
    if hint is int:
        return Annotated[int, msgspec.Meta(ge=max(-_MAX_INT, -_MAX_INT if lo is None else math.ceil(lo)),
                                           le=min(_MAX_INT, _MAX_INT if hi is None else math.floor(hi)))]
    if hint is float:  # finite: NaN fails both bounds, ±inf one of them
        return Annotated[float, msgspec.Meta(ge=-sys.float_info.max if lo is None else float(lo),
                                             le=sys.float_info.max if hi is None else float(hi))]
    if hint in (str, bytes):
        max_len = meta.get("max_len")
        return hint if max_len is None else Annotated[hint, msgspec.Meta(max_length=max_len)]
    if origin is list:
        (item,) = typing.get_args(hint)
        each = item._wire_struct() if dataclasses.is_dataclass(item) else _wire_type(item, meta)
        length, max_len = meta.get("length"), meta.get("max_len")
        if length is not None:
            return Annotated[list[each], msgspec.Meta(min_length=length, max_length=length)]  # type: ignore[valid-type]
        if max_len is not None:
            return Annotated[list[each], msgspec.Meta(max_length=max_len)]  # type: ignore[valid-type]
        return list[each]  # type: ignore[valid-type]
    return hint  # bool


@dataclass(kw_only=True)
class Struct:
    """A nested map inside a message (no version or sequence of its own)."""

    # Fields added after a schema version was released: a payload without one (an older edge, a recording made
    # before) decodes with the field's default. Every other field must be present.
    ADDED_FIELDS: ClassVar[frozenset[str]] = frozenset()
    # A message only shown (see the module's docstring): decoded without the fields this build does not know,
    # which it names in ``ignored``. Every other message carrying one is refused whole. A nested map is read without
    # them only when its class and its message's are both display-only.
    DISPLAY_ONLY: ClassVar[bool] = False
    # Set on an instance decoded without some fields (DISPLAY_ONLY): their paths, ``zoom`` or ``markers[].zoom``.
    ignored: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def max_len(cls, field_name: str) -> int | None:
        """The most characters, bytes or elements the field carries (None: no bound)."""
        return {name: meta.get("max_len") for name, _, meta in cls._fields()}[field_name]

    @classmethod
    def fit(cls, field_name: str, text: str) -> str:
        """``text`` cut to what the field carries (ending in "…" when cut): for a text built from others, a
        planner's reasons say, which must still reach its reader rather than make the message malformed."""
        limit = cls.max_len(field_name)
        return text if limit is None or len(text) <= limit else text[: limit - 1] + "…"

    @classmethod
    def _fields(cls) -> list[tuple[str, Any, dict[str, Any]]]:
        cache = cls.__dict__.get("_field_cache")
        if cache is None:
            hints = typing.get_type_hints(cls)
            cache = [(f.name, hints[f.name], dict(f.metadata)) for f in dataclasses.fields(cls)]
            cls._field_cache = cache  # type: ignore[attr-defined]
        return cache

    @classmethod
    def _checkers(cls) -> tuple[frozenset[str], list[tuple[str, Checker]]]:
        cache = cls.__dict__.get("_checker_cache")
        if cache is None:
            known = frozenset(name for name, _, _ in cls._fields()) | {"v", "seq", "t"}
            cache = known, [(name, _compile(hint, meta)) for name, hint, meta in cls._fields()]
            cls._checker_cache = cache  # type: ignore[attr-defined]
        return cache

    def _to_map(self) -> dict[str, Any]:
        return {name: _to_wire(getattr(self, name)) for name, _, _ in self._fields()}

    @classmethod
    def _wire_struct(cls) -> type[msgspec.Struct]:
        """The fast decoder's schema of this class (built once): every field required but those in
        ``ADDED_FIELDS`` (with the class's default), no unknown field, each value within its bounds."""
        cache = cls.__dict__.get("_wire_cache")
        if cache is None:
            if hasattr(cls, "__post_init__"):
                raise TypeError(f"{cls.__name__}: the fast decoder builds instances without __init__")
            defaults = {f.name: f for f in dataclasses.fields(cls)}
            spec_: list[Any] = [("v", Literal[cls.VERSION])] if issubclass(cls, Message) else []
            for name, hint, meta in cls._fields():
                wire = _wire_type(hint, meta)
                if name not in cls.ADDED_FIELDS:
                    spec_.append((name, wire))
                elif defaults[name].default_factory is not dataclasses.MISSING:
                    spec_.append((name, wire, msgspec.field(default_factory=defaults[name].default_factory)))
                else:
                    spec_.append((name, wire, defaults[name].default))
            cache = msgspec.defstruct(f"{cls.__name__}Wire", spec_, kw_only=True, forbid_unknown_fields=True)
            cls._wire_cache = cache  # type: ignore[attr-defined]
        return cache

    @classmethod
    def _from_wire(cls, wire: msgspec.Struct) -> Self:
        """An instance from the fast decoder's checked values (no second check; nested maps become their class)."""
        values = msgspec.structs.asdict(wire)
        values.pop("v", None)
        for name, item in cls._nested():
            values[name] = [item._from_wire(v) for v in values[name]]
        msg = cls.__new__(cls)
        msg.__dict__.update(values)
        return msg

    @classmethod
    def _nested(cls) -> list[tuple[str, type[Struct]]]:
        """The fields that hold lists of nested maps, with their class."""
        cache = cls.__dict__.get("_nested_cache")
        if cache is None:
            cache = [(name, typing.get_args(hint)[0]) for name, hint, _ in cls._fields()
                     if typing.get_origin(hint) is list and dataclasses.is_dataclass(typing.get_args(hint)[0])]
            cls._nested_cache = cache  # type: ignore[attr-defined]
        return cache

    @classmethod
    def _from_map(cls, data: Any, mtype: str | None = None) -> Self:
        mtype = mtype or cls.__name__
        if not isinstance(data, dict):
            raise DecodeError(mtype, "payload", f"expected a map, got {type(data).__name__}")
        known, checkers = cls._checkers()
        # What this map is read without, named to say so: a dict as an ordered set, bounded (the sender chose them).
        ignored: dict[str, None] = {}
        if not known.issuperset(data):
            unknown = [k for k in data if k not in known]
            if not cls.DISPLAY_ONLY:
                raise _unknown_field(mtype, unknown[0])
            ignored.update((str(k)[:40], None) for k in unknown[:_MAX_IGNORED])
        values: dict[str, Any] = {}
        for name, check in checkers:
            if name in data:
                values[name] = check(mtype, name, data[name])
            elif name not in cls.ADDED_FIELDS:
                raise DecodeError(mtype, name, "missing field")
        # A nested map read without some fields (its class display-only) is part of this message: named here by its
        # path, once for all the elements that lack it; a message read whole is refused for it as for its own.
        for name, _ in cls._nested():
            for i, item in enumerate(values.get(name, ())):
                if not item.ignored:
                    continue
                if not cls.DISPLAY_ONLY:
                    raise _unknown_field(f"{mtype}.{name}[{i}]", item.ignored[0])
                for path in item.ignored:
                    if len(ignored) < _MAX_IGNORED:
                        ignored[f"{name}[].{path}"] = None
                # Named by the message now. Left on the map, msgspec would encode it as one of its fields where the
                # map is passed on (the twin's snapshot carries the markers it received).
                del item.ignored
        msg = cls(**values)
        if ignored:
            msg.ignored = tuple(ignored)  # type: ignore[misc]
        return msg

    def validate(self) -> Self:
        """Check this instance against its declared bounds (as decode would); raise DecodeError if bad."""
        return type(self)._from_map(msgpack.unpackb(msgpack.packb(self._to_map(), use_bin_type=True)))


@dataclass(kw_only=True)
class Message(Struct):
    """Base of every wire message. Subclasses set ``KEY`` (the suffix under ``iorthand/<robot>/``)."""

    KEY: ClassVar[str] = ""
    VERSION: ClassVar[int] = 1
    MAX_BYTES: ClassVar[int] = MAX_PAYLOAD

    seq: int = spec(0, lo=0)
    t: int = spec(0, lo=0, hi=_FAR_FUTURE_NS)

    def stamp(self, seq: int, t: int | None = None) -> Self:
        self.seq = seq
        self.t = now_ns() if t is None else t
        return self

    # The signed messages (a ``mac`` field, its last): decode keeps the payload as received, the bytes that
    # iorthand.security.auth verifies. Set per class by __init_subclass__.
    SIGNED: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        annotations = inspect.get_annotations(cls)
        cls.SIGNED = any("mac" in inspect.get_annotations(b) for b in cls.__mro__)
        if "mac" in annotations and list(annotations)[-1] != "mac":
            raise TypeError(f"{cls.__name__}: mac must be the last field (a signature covers the bytes before it)")

    @classmethod
    def _encoding(cls) -> tuple[tuple[str, ...], Callable[[Any], tuple[Any, ...]]]:
        cache = cls.__dict__.get("_encoding_cache")
        if cache is None:
            names = tuple(name for name, _, _ in cls._fields())
            cache = ("v", *names), attrgetter(*names)
            cls._encoding_cache = cache  # type: ignore[attr-defined]
        return cache

    def encode(self) -> bytes:
        names, values = self._encoding()
        payload = _ENCODER.encode(dict(zip(names, (self.VERSION, *values(self)), strict=True)))
        if len(payload) > self.MAX_BYTES:
            raise ValueError(f"{type(self).__name__}: encoded size {len(payload)} exceeds {self.MAX_BYTES} bytes")
        return payload

    @classmethod
    def _decoder(cls) -> msgspec.msgpack.Decoder:
        cache = cls.__dict__.get("_decoder_cache")
        if cache is None:
            cache = msgspec.msgpack.Decoder(cls._wire_struct())
            cls._decoder_cache = cache  # type: ignore[attr-defined]
        return cache

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> Self:
        if len(payload) > cls.MAX_BYTES:
            raise DecodeError(cls.__name__, "payload",
                              f"size {len(payload)} exceeds the limit of {cls.MAX_BYTES} bytes")
        try:
            msg = cls._from_wire(cls._decoder().decode(payload))
        except Exception:  # not valid for the schema, invalid UTF-8, nested too deep, ...: the checked decoder decides
            msg = cls._decode_checked(payload)
        if cls.SIGNED:
            msg._wire = bytes(payload)  # type: ignore[attr-defined]  # what auth.verify checks
        return msg

    @classmethod
    def _decode_checked(cls, payload: bytes | bytearray | memoryview) -> Self:
        """The checked decoder: the first problem, by field name, as a DecodeError."""
        name = cls.__name__
        try:
            data = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=True, use_list=True)
        except Exception as exc:  # msgpack raises many kinds on garbage; all mean the same to us
            raise DecodeError(name, "payload", f"not valid msgpack ({type(exc).__name__})") from None
        if not isinstance(data, dict):
            raise DecodeError(name, "payload", f"expected a map, got {type(data).__name__}")
        if "v" not in data:
            raise DecodeError(name, "v", "missing field")
        if data["v"] != cls.VERSION or isinstance(data["v"], bool):
            newer = f": {NEWER_SENDER}" if type(data["v"]) is int and data["v"] > cls.VERSION else ""
            raise DecodeError(name, "v", f"unknown schema version {data['v']!r} (this build reads {cls.VERSION}){newer}")
        return cls._from_map(data)


class Sequencer:
    """Per-publisher sequence numbers: thread-safe, starting at 1."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._n = 0

    def next(self) -> int:
        with self._lock:
            self._n += 1
            return self._n


class RejectCounter:
    """Counts rejected payloads, in total and per key; keeps the last reason for each key (to show and log once).

    The key is the sender's choice: an attacker who publishes on ``cmd/twist/<random>`` makes a new one with
    every message, and a table with a row per key grows for as long as the flood lasts (and never shrinks).
    So only the ``max_keys`` keys rejected most recently keep a row; ``total`` counts every reject, also those
    of keys whose row was dropped.

    A reject that a newer sender explains (:attr:`DecodeError.newer`) is also logged, once per key: a receiver of
    an older release sees every message of that key refused, at the message's rate."""

    def __init__(self, max_keys: int = 256, max_reason: int = 200) -> None:
        self._lock = threading.Lock()
        self.max_keys = max_keys
        self.max_reason = max_reason
        self.counts: OrderedDict[str, int] = OrderedDict()  # least recently rejected first
        self.last_reason: dict[str, str] = {}
        self._total = 0
        # Keys whose sender is newer, with what was said: the first max_keys (a flood of made-up keys logs no more).
        self.newer: dict[str, str] = {}

    def add(self, key: str, reason: str) -> int:
        """Count one reject on ``key``; returns how many that key has had while it kept its row."""
        with self._lock:
            self._total += 1
            n = self.counts.pop(key, 0) + 1
            self.counts[key] = n
            self.last_reason[key] = reason[: self.max_reason]
            while len(self.counts) > self.max_keys:
                oldest, _ = self.counts.popitem(last=False)
                del self.last_reason[oldest]
        if NEWER_SENDER in reason:
            self.note_newer(key, f"refused: {reason}")
        return n

    def note_newer(self, key: str, what: str) -> bool:
        """Log that ``key``'s sender is newer than this program (``what`` it caused), the first time for that key;
        True then."""
        with self._lock:
            if key in self.newer or len(self.newer) >= self.max_keys:
                return False
            self.newer[key] = what[: self.max_reason]
        log.warning("%s: %s", printable(key)[:200], printable(what)[: self.max_reason])
        return True

    @property
    def total(self) -> int:
        with self._lock:
            return self._total


# ---------------------------------------------------------------------------------------------------------
# Codes shared between edge and clients. Defined once; the console, twin and recorder read them from here.


class ForceLevel(IntEnum):
    """Contact-force warning levels. 0 is safe: the reference system shipped these inverted once."""

    SAFE = 0  # green
    CAUTION = 1  # yellow
    DANGER = 2  # red


FORCE_LEVEL_COLOURS = {ForceLevel.SAFE: "green", ForceLevel.CAUTION: "yellow", ForceLevel.DANGER: "red"}


class Status(StrEnum):
    """Supervisor status codes: one for every state and every reason a command is refused or motion halts.

    Each member is its wire string (``Status.OK == "ok"``) and carries ``message``, what it means to an
    operator; ``halts`` says whether the robot is held stopped in that state (a previewed move ends there)."""

    def __new__(cls, value: str, message: str, halts: bool = False) -> Status:
        member = str.__new__(cls, value)
        member._value_ = value
        member.message = message  # type: ignore[attr-defined]
        member.halts = halts  # type: ignore[attr-defined]
        return member

    message: str
    halts: bool

    OK = "ok", "moving as commanded"
    IDLE = "idle", "armed, waiting for an operator's command"
    DISARMED = "disarmed", "not armed: arming is confirmed on the robot's side", True
    NOT_OWNER = "not_owner", "the command does not come from the session that holds control"
    NO_DEADMAN = "deadman_released", "the deadman is released: no motion"
    COMMAND_TIMEOUT = "command_timeout", "no fresh command within the timeout: the robot stopped", True
    STALE_COMMAND = "stale_command", "the command is too old (or from the future: check clock sync)"
    OUT_OF_ORDER = "out_of_order", "the command's sequence is not after the last one, or jumps absurdly"
    SPEED_LIMITED = "speed_limited", "the speed was clipped to the profile's limit"
    WORKSPACE = "workspace_limit", "velocity leaving the workspace box was removed"
    FORCE_CAUTION = "force_caution", "caution-level force: the approach is slowed"
    FORCE_DANGER = "force_danger", "danger-level force: motion pressing harder removed", True
    FORCE_STALE = "force_stale", ("the force sensor went silent: the robot stopped; release the deadman and press it "
                                  "again; motion toward contact is refused until it is back"), True
    STOPPED = "stopped", "stopped: release the deadman and press it again to move", True
    FAULT = "fault", "a robot fault: the robot stopped", True
    OWNER_LOST = "owner_lost", "the owner's session was lost: acquire control again", True
    NOT_ALLOWED = "operator_not_allowed", "this operator may not command this robot"
    BAD_COMMAND = "bad_command", "the command asks for something this edge does not do (a frame, a mode)"
    NEAR_SINGULARITY = "near_singularity", "near a singularity: motion toward it is slowed"
    SINGULARITY = "singularity", "at a singularity's margin: motion toward it halted; move away from it"
    NEAR_JOINT_LIMIT = "near_joint_limit", "a joint is near its limit: motion toward it is slowed"
    JOINT_LIMIT = "joint_limit", "a joint is at its limit's margin: motion toward it halted; move away from it"
    NEAR_REACH = "near_reach_limit", "near the edge of the arm's reach: motion outward is slowed"
    REACH_LIMIT = "reach_limit", "at the edge of the arm's reach: motion outward halted"
    CONTACT = "contact", "contact mode: the edge holds the force along the probe; the operator steers along the surface"
    LINK_GAP = "link_gap", "commands resumed after a long gap: release the deadman and press it again", True
    STALE_VIEW = "stale_view", "the operator's picture of the robot is too old to act on", True

    @classmethod
    def halting(cls, code: str) -> bool:
        """Whether a status code from the wire holds the robot stopped (an unknown code counts as one: a newer
        edge's new reason to stop must not read as all clear)."""
        try:
            return cls(code).halts
        except ValueError:
            return True


# Halts the edge ends on a fresh press of the deadman (released, then pressed): nothing resumes by itself.
RESUME_ON_PRESS = frozenset({Status.STOPPED, Status.LINK_GAP, Status.FORCE_STALE})
# Halts that end the grant: control is acquired again, and then a fresh press.
RESUME_ON_ACQUIRE = frozenset({Status.OWNER_LOST, Status.FAULT})


# ---------------------------------------------------------------------------------------------------------
# Messages. Bounds are generous sanity limits; safety limits live in the supervisor's configuration.

_SPEED = 10.0  # m/s or rad/s: nothing legitimate on the wire is faster
_POSITION = 100.0  # m


@dataclass(kw_only=True)
class TwistCommand(Message):
    """Operator → edge at a fixed rate: tool velocity in the base frame, with the deadman flag."""

    KEY: ClassVar[str] = keys.CMD_TWIST
    ADDED_FIELDS: ClassVar[frozenset[str]] = frozenset({"state_age", "frame", "view_t", "mac"})
    operator: str = spec("", max_len=64)
    linear: list[float] = vec(3, lo=-_SPEED, hi=_SPEED)  # m/s
    angular: list[float] = vec(3, lo=-_SPEED, hi=_SPEED)  # rad/s
    deadman: bool = False
    # Age (s) of the newest robot state the operator's screen showed when this was sent; -1: none seen yet.
    state_age: float = spec(-1.0, lo=-1.0, hi=1e9)
    # That state's own stamp (RobotState.t, ns: the edge's clock); 0: none. The edge measures the view's age on
    # its own clock from it, where no operator's clock comes in (state_age is the operator's clock minus the edge's).
    view_t: int = spec(0, lo=0, hi=_FAR_FUTURE_NS)
    # The frame of linear and angular: "base" (the robot's base frame) or "tool" (the probe's frame, about its tip:
    # forward, sideways and along the probe; tilt, rock and turn about the tip). One of TWIST_FRAMES.
    frame: str = spec("base", max_len=8)
    mac: bytes = spec(b"", max_len=MAC_MAX)  # iorthand.security.auth: signed with the key of the acquire


TWIST_FRAMES = ("base", "tool")


# How the edge's safety reason begins when a stop command holds the robot ("stop from 'nurse': …"): a client
# that recovers from halts by itself (a headless move) ends its motion on it instead.
STOP_FROM = "stop from "


@dataclass(kw_only=True)
class StopCommand(Message):
    KEY: ClassVar[str] = keys.CMD_STOP
    operator: str = spec("", max_len=64)
    reason: str = spec("operator stop", max_len=200)


@dataclass(kw_only=True)
class ServoCommand(Message):
    """Absolute pan/tilt angles (rad). A missing axis (None) keeps its current target."""

    KEY: ClassVar[str] = keys.CMD_SERVO
    ADDED_FIELDS: ClassVar[frozenset[str]] = frozenset({"mac"})
    operator: str = spec("", max_len=64)
    pan: float | None = spec(None, lo=-2 * math.pi, hi=2 * math.pi)
    tilt: float | None = spec(None, lo=-2 * math.pi, hi=2 * math.pi)
    mac: bytes = spec(b"", max_len=MAC_MAX)


@dataclass(kw_only=True)
class TorchCommand(Message):
    KEY: ClassVar[str] = keys.CMD_TORCH
    ADDED_FIELDS: ClassVar[frozenset[str]] = frozenset({"mac"})
    operator: str = spec("", max_len=64)
    on: bool = False
    brightness: float = spec(1.0, lo=0.0, hi=1.0)
    mac: bytes = spec(b"", max_len=MAC_MAX)


@dataclass(kw_only=True)
class RobotState(Message):
    """Edge → all at the control rate. ``cmd_seq``/``cmd_recv_t`` echo the last applied command (latency)."""

    KEY: ClassVar[str] = keys.STATE_ROBOT
    ADDED_FIELDS: ClassVar[frozenset[str]] = frozenset({"mac"})
    tcp_pose: list[float] = vec(6, lo=-_POSITION, hi=_POSITION)  # [x,y,z,rx,ry,rz]
    tcp_speed: list[float] = vec(6, lo=-_SPEED, hi=_SPEED)
    q: list[float] = vec(6, lo=-4 * math.pi, hi=4 * math.pi)
    commanded: list[float] = vec(6, lo=-_SPEED, hi=_SPEED)  # the twist sent to the robot this cycle
    mode: str = spec("", max_len=40)
    connected: bool = True
    fault: str = spec("", max_len=200)
    robot_time: float = spec(0.0, lo=0.0)  # the robot's own clock, s
    cmd_seq: int = spec(0, lo=0)
    cmd_recv_t: int = spec(0, lo=0)
    mac: bytes = spec(b"", max_len=MAC_MAX)  # signed with the owner's key while someone holds control (auth)


@dataclass(kw_only=True)
class AppliedCommand(Message):
    """Edge → all for every received twist: what the supervisor did with it, at once (the command echo)."""

    KEY: ClassVar[str] = keys.STATE_APPLIED
    ADDED_FIELDS: ClassVar[frozenset[str]] = frozenset({"mac"})
    operator: str = spec("", max_len=64)
    cmd_seq: int = spec(0, lo=0)
    cmd_t: int = spec(0, lo=0)
    recv_t: int = spec(0, lo=0)
    applied: list[float] = vec(6, lo=-_SPEED, hi=_SPEED)
    accepted: bool = False
    status: str = spec(Status.OK, max_len=40)
    reason: str = spec("", max_len=200)
    mac: bytes = spec(b"", max_len=MAC_MAX)  # signed with the owner's key while someone holds control (auth)


@dataclass(kw_only=True)
class SafetyStatus(Message):
    """Edge → all at 20 Hz and on change: the supervisor's state and why it is what it is."""

    KEY: ClassVar[str] = keys.STATE_SAFETY
    ADDED_FIELDS: ClassVar[frozenset[str]] = frozenset({"forged", "contact_target", "task", "mac"})
    armed: bool = False
    arm_requested: bool = False
    owner: str = spec("", max_len=64)
    deadman: bool = False
    profile: str = spec("", max_len=32)
    linear_limit: float = spec(0.0, lo=0.0, hi=_SPEED)
    angular_limit: float = spec(0.0, lo=0.0, hi=_SPEED)
    limits_hit: list[str] = spec(default_factory=list, max_len=16)
    command_age: float = spec(-1.0, lo=-1.0)  # s since the last accepted command; -1 = none yet
    status: str = spec(Status.IDLE, max_len=40)
    reason: str = spec("", max_len=200)
    force_level: int = spec(0, lo=0, hi=2)
    force_stale: bool = True
    received: int = spec(0, lo=0)
    applied: int = spec(0, lo=0)
    rejected: int = spec(0, lo=0)
    malformed: int = spec(0, lo=0)
    superseded: int = spec(0, lo=0)  # twists dropped unread: newer ones queued behind them while the edge was busy
    stops: int = spec(0, lo=0)
    forged: int = spec(0, lo=0)  # commands in the owner's name without the owner's signature, refused unanswered
    contact_target: float = spec(-1.0, lo=-1.0, hi=1000.0)  # N held along the probe in contact mode; -1: off
    task: str = spec("", max_len=200)  # a motion primitive under way and its progress ("" when none)
    mac: bytes = spec(b"", max_len=MAC_MAX)  # signed with the owner's key while someone holds control (auth)


def superseded_news(before: int, now: int) -> str | None:
    """What the operator and the twin say when SafetyStatus.superseded grows from ``before`` to ``now``."""
    if now <= before:
        return None
    return f"the edge dropped {now - before} commands unread: newer ones arrived while it was busy"


@dataclass(kw_only=True)
class ForceSample(Message):
    """Edge → all with each robot state (a sensor read from it) or at ``force.rate_hz`` (one with a stream of its
    own): the wrench at the tool, N and N·m, in the sensor frame."""

    KEY: ClassVar[str] = keys.STATE_FORCE
    DISPLAY_ONLY: ClassVar[bool] = True
    force: list[float] = vec(3, lo=-1e5, hi=1e5)
    torque: list[float] = vec(3, lo=-1e5, hi=1e5)


@dataclass(kw_only=True)
class ForceLevelState(Message):
    """Edge → all on change and at 10 Hz. ``stale`` overrides ``level``: no fresh sample, no colour."""

    KEY: ClassVar[str] = keys.STATE_FORCE_LEVEL
    ADDED_FIELDS: ClassVar[frozenset[str]] = frozenset({"mac"})
    level: int = spec(0, lo=0, hi=2)
    stale: bool = True
    value: float = spec(0.0, lo=-1e5, hi=1e5)  # the quantity compared with the thresholds, N
    quantity: str = spec("fz", max_len=16)
    caution: float = spec(6.0, lo=0.0)
    danger: float = spec(8.0, lo=0.0)
    mac: bytes = spec(b"", max_len=MAC_MAX)  # signed with the owner's key while someone holds control (auth)


@dataclass(kw_only=True)
class ServoState(Message):
    """Sent on every change and as a heartbeat every ``period`` s (the edge's servos.publish_hz)."""

    KEY: ClassVar[str] = keys.STATE_SERVO
    DISPLAY_ONLY: ClassVar[bool] = True
    ADDED_FIELDS: ClassVar[frozenset[str]] = frozenset({"period"})
    pan: float = spec(0.0, lo=-2 * math.pi, hi=2 * math.pi)  # rad, current
    tilt: float = spec(0.0, lo=-2 * math.pi, hi=2 * math.pi)
    pan_target: float = spec(0.0, lo=-2 * math.pi, hi=2 * math.pi)
    tilt_target: float = spec(0.0, lo=-2 * math.pi, hi=2 * math.pi)
    clamped: bool = False
    reason: str = spec("", max_len=200)
    # s between two heartbeats: a receiver calls the state old after a few of them missed. 0: not said (an older
    # edge, an older recording): the receiver falls back to the default rate's.
    period: float = spec(0.0, lo=0.0, hi=3600.0)


@dataclass(kw_only=True)
class TorchState(Message):
    """Sent on every change and as a heartbeat every ``period`` s (the edge's torch.publish_hz)."""

    KEY: ClassVar[str] = keys.STATE_TORCH
    DISPLAY_ONLY: ClassVar[bool] = True
    ADDED_FIELDS: ClassVar[frozenset[str]] = frozenset({"period"})
    on: bool = False
    brightness: float = spec(0.0, lo=0.0, hi=1.0)
    reason: str = spec("", max_len=200)
    period: float = spec(0.0, lo=0.0, hi=3600.0)  # s between two heartbeats; 0: not said (as ServoState.period)


@dataclass(kw_only=True)
class MarkerPose(Struct):
    DISPLAY_ONLY: ClassVar[bool] = True
    id: int = spec(0, lo=0, hi=10_000)
    pose: list[float] = vec(16, lo=-1e3, hi=1e3)  # filtered T_base_marker, 4×4 row-major
    raw: list[float] = vec(16, lo=-1e3, hi=1e3)  # this frame's unfiltered estimate
    reprojection_error: float = spec(0.0, lo=0.0)  # px
    pixel_size: float = spec(0.0, lo=0.0)  # mean side length, px


@dataclass(kw_only=True)
class Markers(Message):
    """Every marker seen in one camera frame, in the robot base frame. ``t`` is the frame's capture time."""

    KEY: ClassVar[str] = keys.MARKERS
    DISPLAY_ONLY: ClassVar[bool] = True
    markers: list[MarkerPose] = spec(default_factory=list, max_len=256)
    frames: int = spec(0, lo=0)
    fps: float = spec(0.0, lo=0.0)
    processing_ms: float = spec(0.0, lo=0.0)
    # Empty while the camera delivers. Otherwise why perception has no frames: the edge then publishes this
    # (with no markers) at every attempt to reopen the camera, so silence never reads as "nothing in view".
    failure: str = spec("", max_len=256)

    ADDED_FIELDS: ClassVar[frozenset[str]] = frozenset({"failure"})


@dataclass(kw_only=True)
class VideoFrame(Message):
    """A JPEG image. ``t`` is the capture time; ``seq`` counts captured frames (gaps = dropped)."""

    KEY: ClassVar[str] = keys.VIDEO_CAMERA
    DISPLAY_ONLY: ClassVar[bool] = True
    MAX_BYTES: ClassVar[int] = MAX_VIDEO_PAYLOAD
    source: str = spec("camera", max_len=32)
    width: int = spec(0, lo=1, hi=8192)
    height: int = spec(0, lo=1, hi=8192)
    encoding: str = spec("jpeg", max_len=16)
    data: bytes = spec(b"", max_len=MAX_VIDEO_PAYLOAD)
    # Empty in an image. Otherwise why the source gives no frames: the edge then sends this (with no data, the
    # configured size) at every attempt to reopen it, so a frozen picture never reads as a live one.
    failure: str = spec("", max_len=256)
    # encoding h264: one access unit (Annex B) per frame; a keyframe (IDR, with SPS/PPS) is where a viewer that
    # joins or lost a frame starts decoding. Always true for a JPEG picture's meaning, unused there.
    keyframe: bool = False

    ADDED_FIELDS: ClassVar[frozenset[str]] = frozenset({"failure", "keyframe"})


@dataclass(kw_only=True)
class VideoFeedback(Message):
    """Viewer → edge, about once a second per stream and at once when it needs a keyframe: how the frames reach
    it. The edge lowers the bitrate for the worst viewer (iorthand_edge.video.bitrate) and sends a keyframe on
    request (a viewer that joined, or lost a frame of an H.264 stream)."""

    KEY: ClassVar[str] = keys.CMD_VIDEO_FEEDBACK
    operator: str = spec("", max_len=64)  # who reports (with bound keys, the name in the key)
    stream: str = spec("camera", max_len=32)
    keyframe: bool = False
    received: int = spec(0, lo=0, hi=100_000)  # frames since the previous report
    lost: int = spec(0, lo=0, hi=100_000)  # frames missing by sequence since the previous report
    delay_p90: float = spec(-1.0, lo=-1.0, hi=3600.0)  # s from capture to arrival; -1: unknown


def source_news(what: str, before: str, now: str) -> str | None:
    """What the operator and the twin say when the ``failure`` of a source (perception, a video stream)
    changes from ``before`` to ``now``."""
    if now == before:
        return None
    if not now:
        return f"{what} back: frames flow again"
    return f"{what} has no frames: {now} (the edge retries)"


@dataclass(kw_only=True)
class ControlRequest(Message):
    """Payload of a ``control/*`` query. The owner's requests (renewing, releasing, moving to a pose, zeroing the
    force sensor) are signed with the key its acquire returned (``mac``); a first acquire is not."""

    ADDED_FIELDS: ClassVar[frozenset[str]] = frozenset({"mac", "params"})
    operator: str = spec("", max_len=64)
    profile: str = spec("", max_len=32)  # acquire: the speed profile asked for ("" = the edge's default)
    name: str = spec("", max_len=64)  # goto/preview: the named pose or primitive; contact: "on" or "off"
    token: str = spec("", max_len=128)  # goto: the preview token
    # preview of a primitive: its parameters; contact: the force to hold ({"force": 4.0}). A JSON object.
    params: str = spec("", max_len=1024)
    mac: bytes = spec(b"", max_len=MAC_MAX)


@dataclass(kw_only=True)
class ControlReply(Message):
    """Edge → the querier alone: the answer to a ``control/<verb>`` query. Its ``seq`` is the request's; while
    someone holds control it is signed with the owner's key (iorthand.security.auth.reply_context)."""

    ADDED_FIELDS: ClassVar[frozenset[str]] = frozenset({"key", "mac"})
    ok: bool = False
    reason: str = spec("", max_len=200)
    owner: str = spec("", max_len=64)
    lease: float = spec(0.0, lo=0.0)
    detail: str = spec("", max_len=4096)  # JSON text for richer answers (pose lists, previews)
    # acquire: the secret that signs this owner's commands. A query's reply goes to the querier alone.
    key: bytes = spec(b"", max_len=KEY_MAX)
    mac: bytes = spec(b"", max_len=MAC_MAX)


@dataclass(kw_only=True)
class Annotation(Message):
    author: str = spec("", max_len=64)
    text: str = spec("", max_len=4000)
    tags: list[str] = spec(default_factory=list, max_len=32)
    score: float | None = spec(None, lo=-1e6, hi=1e6)


@dataclass(kw_only=True)
class RecorderRequest(Message):
    """Payload of ``iorthand/_recorder/start`` and ``.../stop`` queries."""

    operator: str = spec("", max_len=64)
    session: str = spec("", max_len=64)  # start: the session id asked for ("" = the recorder names it)
    robots: list[str] = spec(default_factory=list, max_len=32)
    note: str = spec("", max_len=4000)


@dataclass(kw_only=True)
class RecorderStatus(Message):
    """The recorder's state: the reply to every recorder query and the ``iorthand/_recorder/status`` stream.
    ``error`` is set when a recording stopped on its own (full disk, unwritable folder)."""

    DISPLAY_ONLY: ClassVar[bool] = True
    ok: bool = True
    reason: str = spec("", max_len=1000)
    recording: bool = False
    session: str = spec("", max_len=64)
    path: str = spec("", max_len=4096)
    error: str = spec("", max_len=1000)
    messages: int = spec(0, lo=0)
    bytes: int = spec(0, lo=0)
    malformed: int = spec(0, lo=0)
    gaps: int = spec(0, lo=0)  # sequence numbers missing, all keys
    dropped: int = spec(0, lo=0)  # samples the recorder itself could not queue
    started_t: int = spec(0, lo=0)  # ns: the start query was handled
    first_message_t: int = spec(0, lo=0)  # ns: the first message of the session was flushed to its file
    closed_t: int = spec(0, lo=0)  # ns: the files were closed (stop)


@dataclass(kw_only=True)
class StreamInfo(Struct):
    """How fresh one stream of a robot is, as seen by the twin."""

    DISPLAY_ONLY: ClassVar[bool] = True
    key: str = spec("", max_len=64)  # suffix under iorthand/<robot>/
    age: float = spec(-1.0, lo=-1.0)  # s since the twin received the latest sample; -1 = never
    latency: float = spec(-1.0)  # s between the sample's source time and its arrival; -1 = unknown
    count: int = spec(0, lo=0)
    rejected: int = spec(0, lo=0)


@dataclass(kw_only=True)
class ImageInfo(Struct):
    DISPLAY_ONLY: ClassVar[bool] = True
    source: str = spec("", max_len=32)
    seq: int = spec(0, lo=0)
    t: int = spec(0, lo=0)
    age: float = spec(-1.0, lo=-1.0)
    width: int = spec(0, lo=0, hi=8192)
    height: int = spec(0, lo=0, hi=8192)
    encoding: str = spec("", max_len=16)
    data: bytes = spec(b"", max_len=MAX_VIDEO_PAYLOAD)  # empty unless images were asked for, or on failure
    failure: str = spec("", max_len=256)  # the source's VideoFrame.failure: why there is no picture

    ADDED_FIELDS: ClassVar[frozenset[str]] = frozenset({"failure"})


@dataclass(kw_only=True)
class TwinSnapshot(Message):
    """Reply of ``iorthand/_twin/<robot>/snapshot``: the twin's latest view of one robot and how old it is.

    ``online`` follows the edge's liveliness token ``alive/edge``; ``age`` is the time since the latest robot
    state arrived (the pose itself was taken at ``robot_t``, the edge's source time). ``t`` is when the
    snapshot was made."""

    MAX_BYTES: ClassVar[int] = MAX_VIDEO_PAYLOAD
    DISPLAY_ONLY: ClassVar[bool] = True
    robot: str = spec("", max_len=64)
    known: bool = False  # the twin has heard of this robot at all
    online: bool = False
    reason: str = spec("", max_len=200)  # why offline or stale
    age: float = spec(-1.0, lo=-1.0)
    robot_seq: int = spec(0, lo=0)
    robot_t: int = spec(0, lo=0)
    tcp_pose: list[float] = vec(6, lo=-_POSITION, hi=_POSITION)
    tcp_speed: list[float] = vec(6, lo=-_SPEED, hi=_SPEED)
    q: list[float] = vec(6, lo=-4 * math.pi, hi=4 * math.pi)  # reported joint angles
    q_drawn: list[float] = vec(6, lo=-4 * math.pi, hi=4 * math.pi)  # joints drawn (IK of the TCP pose)
    mode: str = spec("", max_len=40)
    fault: str = spec("", max_len=200)
    armed: bool = False
    owner: str = spec("", max_len=64)
    safety_status: str = spec("", max_len=40)
    safety_reason: str = spec("", max_len=200)
    profile: str = spec("", max_len=32)
    limits_hit: list[str] = spec(default_factory=list, max_len=16)
    force: list[float] = vec(3, lo=-1e5, hi=1e5)
    torque: list[float] = vec(3, lo=-1e5, hi=1e5)
    force_level: int = spec(0, lo=0, hi=2)
    force_stale: bool = True
    force_value: float = spec(0.0, lo=-1e5, hi=1e5)
    servo_pan: float = spec(0.0, lo=-2 * math.pi, hi=2 * math.pi)
    servo_tilt: float = spec(0.0, lo=-2 * math.pi, hi=2 * math.pi)
    torch_on: bool = False
    markers: list[MarkerPose] = spec(default_factory=list, max_len=256)
    markers_t: int = spec(0, lo=0)
    images: list[ImageInfo] = spec(default_factory=list, max_len=8)
    streams: list[StreamInfo] = spec(default_factory=list, max_len=32)
    events: list[str] = spec(default_factory=list, max_len=200)  # latest safety events, newest last (≤ 200 chars each)


@dataclass(kw_only=True)
class SensorReading(Message):
    """A sensor outside the robot (a patient's heart rate, SpO2, temperature), brought in from MQTT by
    ``iorthand bridge mqtt``. ``t`` is the sensor's time when it sent one, else when the bridge received it.
    The bounds are sanity limits only: a plausible range per sensor is the bridge mapping's (``bounds``)."""

    KEY: ClassVar[str] = keys.SENSOR_VITAL
    DISPLAY_ONLY: ClassVar[bool] = True
    name: str = spec("", max_len=64)  # what is measured, e.g. "heart_rate"
    value: float = spec(0.0, lo=-1e9, hi=1e9)
    unit: str = spec("", max_len=16)  # e.g. "bpm", "%", "degC"
    source: str = spec("", max_len=64)  # the device (or bridge mapping) it came from


def message_class(name: str) -> type[Message]:
    """A message class of this module by its name (the table of channels names them: it imports nothing)."""
    cls = globals().get(name)
    if not (isinstance(cls, type) and issubclass(cls, Message)):
        raise LookupError(f"{name!r} is not a message class of iorthand.protocol")
    return cls


def messages_by_key(table: Iterable[channels.Channel] = channels.TABLE) -> dict[str, type[Message]]:
    """The decoder of every stream of the table of channels, by key suffix (puts: what is recorded and replayed)."""
    return {c.suffix: message_class(c.message) for c in table if c.kind is channels.Kind.PUT}


MESSAGES_BY_KEY: dict[str, type[Message]] = messages_by_key()

# ---------------------------------------------------------------------------------------------------------
# Releases of different ages (see the module's docstring)

# What a console may read of the edge only if it knows every field (a receiver refuses the others whole, and a
# console that cannot read them must not ask for control), and what it sends the edge.
SAFETY_STATE: tuple[type[Message], ...] = (RobotState, SafetyStatus, AppliedCommand, ForceLevelState)
CONSOLE_SENDS: tuple[type[Message], ...] = (TwistCommand, StopCommand, ServoCommand, TorchCommand, VideoFeedback,
                                            ControlRequest)


def _check_revisions() -> None:
    """Refuse an ADDED_IN that decoders would get wrong: a field added later must decode when absent."""
    for revision, added in ADDED_IN.items():
        if not 1 < revision <= REVISION:
            raise ValueError(f"ADDED_IN: revision {revision} is not one after the first and up to {REVISION}")
        for name, fields in added.items():
            cls = globals()[name]
            if not fields <= cls.ADDED_FIELDS:
                raise ValueError(f"{name}: {sorted(fields - cls.ADDED_FIELDS)} added in revision {revision} must "
                                 "be in its ADDED_FIELDS")


_check_revisions()


def unreadable_by(revision: int, classes: Iterable[type[Struct]]) -> list[str]:
    """The fields (``Class.field``) of ``classes``, as this build sends them, for which a receiver speaking
    protocol ``revision`` refuses the whole message: those added after its revision, in the classes it reads whole
    (before TOLERANT_SINCE all of them; since, those that are not display-only). Nested maps count with their
    message: read in part only when both are display-only (in every message of ``classes`` that carries them)."""
    tolerant: dict[str, bool] = {}  # by class name: whether a receiver since TOLERANT_SINCE reads it in part
    for cls in classes:
        tolerant[cls.__name__] = cls.DISPLAY_ONLY
        for _, item in cls._nested():
            tolerant[item.__name__] = tolerant.get(item.__name__, True) and item.DISPLAY_ONLY and cls.DISPLAY_ONLY
    out = []
    for added_in, added in sorted(ADDED_IN.items()):
        for name, fields in added.items():
            if added_in > revision and name in tolerant and (revision < TOLERANT_SINCE or not tolerant[name]):
                out.extend(f"{name}.{f}" for f in sorted(fields))
    return out


def revision_json() -> str:
    """What an acquire (ControlRequest.params) and its answer (ControlReply.detail) carry: this build's revision."""
    return json.dumps({"revision": REVISION})


def said_revision(text: str) -> int:
    """The protocol revision an acquire's ``params`` or its answer's ``detail`` says; 1 when it says none (the
    first release said none)."""
    try:
        said = json.loads(text) if text else {}
    except ValueError:
        return 1
    revision = said.get("revision") if isinstance(said, dict) else None
    return revision if type(revision) is int and revision >= 1 else 1


def update_the_console(console: int, fields: list[str]) -> str:
    """The edge's refusal of control to a console that cannot read ``fields`` it sends (the instruction first:
    a reply's reason is cut at 200 characters)."""
    return (f"update this console: it speaks protocol revision {console}, this edge {REVISION}, and it cannot read "
            f"{', '.join(fields)}")


def update_the_edge(edge: int, fields: list[str]) -> str:
    """A console's refusal to drive an edge that cannot read ``fields`` the console sends."""
    return (f"update the edge: it speaks protocol revision {edge}, this console {REVISION}, and it cannot read "
            f"{', '.join(fields)}")


def message_type_for(key: str) -> type[Message] | None:
    """The message class of a robot key (``iorthand/<robot>/<suffix>``, an operator's own key included:
    ``.../cmd/twist/<operator>``), or None if it has none."""
    try:
        _, suffix = keys.split_key(key)
    except keys.KeyExprError:
        return None
    return MESSAGES_BY_KEY.get(keys.channel_suffix(suffix))
