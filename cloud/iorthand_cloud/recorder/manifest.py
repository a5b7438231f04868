"""The session manifest (``manifest.json``) and the per-key statistics it carries.

:class:`KeyStats` is pure logic (counting messages, bytes, malformed payloads and sequence gaps); the manifest
is written atomically (temporary file + rename) so a crash leaves either the previous or the new version.

The process that writes a manifest saying ``recording`` holds the session's writer lock (an advisory ``flock`` on
``.writer.lock`` in its folder) until the recording ends, whether or not its final manifest could be written: :func:`writer_alive` tells a reader (``iorthand
report``, ``export``, a recorder starting up) whether the session is still being written or its recorder died
(the kernel releases a killed process's locks at once), so a crashed session is repaired by whoever reads it
first and a live one is never touched.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import os
import platform
import stat
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO

try:
    import fcntl
except ImportError:  # not POSIX: no writer locks; readers judge by the files' age (writer_alive)
    fcntl = None  # type: ignore[assignment]

MANIFEST = "manifest.json"
WRITER_LOCK = ".writer.lock"
FORMAT_VERSION = 1

# Session status values.
RECORDING = "recording"  # being written, or the recorder died while writing (repair on next start)
COMPLETE = "complete"
RECOVERED = "recovered"  # the recorder died; the readable part of its segments was repaired
FAILED = "failed"  # stopped by an error (full disk, unwritable folder); what was written is kept


@dataclass
class KeyStats:
    """Statistics of one key. ``missing`` counts sequence numbers never received, ``gaps`` the holes they make;
    a sequence number at or below the last one is a publisher restart or a duplicate (``resets``)."""

    type: str = ""
    messages: int = 0
    bytes: int = 0
    malformed: int = 0
    gaps: int = 0
    missing: int = 0
    resets: int = 0
    first_seq: int | None = None
    last_seq: int | None = None
    first_t: int | None = None  # receive time, ns
    last_t: int | None = None

    def observe(self, size: int, recv_ns: int, seq: int | None, malformed: bool = False) -> None:
        """One message of ``size`` bytes. ``seq`` is None when there is none to check: a malformed payload, or a
        key without a message type whose payload carries no ``seq``."""
        self.messages += 1
        self.bytes += size
        if self.first_t is None:
            self.first_t = recv_ns
        self.last_t = recv_ns
        if malformed:
            self.malformed += 1
        if seq is None:
            return
        if self.last_seq is None:
            self.first_seq = seq
        elif seq > self.last_seq + 1:
            self.gaps += 1
            self.missing += seq - self.last_seq - 1
        elif seq <= self.last_seq:
            self.resets += 1
        self.last_seq = seq

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> KeyStats:
        return cls(**_fields(cls, data, "a key's statistics"))


def totals(stats: dict[str, KeyStats]) -> dict[str, int]:
    return {
        "messages": sum(s.messages for s in stats.values()),
        "bytes": sum(s.bytes for s in stats.values()),
        "malformed": sum(s.malformed for s in stats.values()),
        "gaps": sum(s.gaps for s in stats.values()),
        "missing": sum(s.missing for s in stats.values()),
    }


@dataclass
class SegmentInfo:
    file: str
    stream: str  # "telemetry" or "video"
    compression: str
    opened_t: int
    closed_t: int | None = None
    messages: int = 0
    bytes: int = 0
    status: str = "open"  # open, closed, repaired, unreadable, refused (set aside: not written by the recorder)
    recovered_messages: int | None = None
    lost_bytes: int | None = None


@dataclass
class Manifest:
    session_id: str
    status: str = RECORDING
    operator: str = ""
    robots: list[str] = field(default_factory=list)
    note: str = ""
    start_t: int = 0
    stop_t: int | None = None
    start_iso: str = ""
    stop_iso: str = ""
    keys: dict[str, KeyStats] = field(default_factory=dict)
    segments: list[SegmentInfo] = field(default_factory=list)
    attachments: list[str] = field(default_factory=list)
    annotations: int = 0
    dropped: int = 0
    error: str = ""
    repaired: bool = False
    software: dict[str, str] = field(default_factory=dict)
    config: dict[str, Any] = field(default_factory=dict)
    format_version: int = FORMAT_VERSION

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["totals"] = totals(self.keys)
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Manifest:
        """A manifest from its JSON; raises :class:`ManifestError` naming the first value that is not of its
        field's type (a manifest copied from elsewhere may hold anything)."""
        known = _fields(cls, data, "the manifest")  # ("totals" is computed: not a field)
        keys = {k: KeyStats.from_dict(_of(dict, v, f"keys[{k!r}]")) for k, v in known.pop("keys", {}).items()}
        segs = [SegmentInfo(**_fields(SegmentInfo, _of(dict, s, "segments[]"), "a segment"))
                for s in known.pop("segments", [])]
        return cls(keys=keys, segments=segs, **known)

    def write(self, folder: Path, fsync: bool = True, opener: Callable[[Path], BinaryIO] | None = None) -> None:
        """Write atomically. ``opener`` opens the temporary file (the recorder's, so that a test's full disk is
        full for the manifest too). A failed write leaves no temporary file behind, and the writer lock as it
        was: whoever writes a final status releases it (:func:`release_writer_lock`) whether or not it could."""
        if self.status == RECORDING:
            _hold_writer_lock(folder)
        path = folder / MANIFEST
        tmp = folder / (MANIFEST + ".tmp")
        data = json.dumps(self.to_dict(), indent=1, sort_keys=False).encode()
        try:
            tmp.unlink(missing_ok=True)  # one left by an earlier failure: the opener creates the file afresh
            f = opener(tmp) if opener else tmp.open("xb")
            try:
                f.write(data)
                f.flush()
                if fsync:
                    os.fsync(f.fileno())
            finally:
                f.close()
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
            raise
        if self.status != RECORDING:
            release_writer_lock(folder)

    @classmethod
    def read(cls, folder: Path) -> Manifest:
        """Raises FileNotFoundError (not a session), :class:`ManifestError` (a manifest that is no JSON, one far
        larger than the recorder writes, or a value of the wrong type: the message names the file)."""
        path = folder / MANIFEST
        try:
            with path.open("rb") as f:
                if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                    raise ManifestError(f"{path}: not a regular file")
                data = f.read(MAX_MANIFEST_BYTES + 1)
        except FileNotFoundError:
            raise FileNotFoundError(f"{folder} is not a recorded session: it has no {MANIFEST}") from None
        if len(data) > MAX_MANIFEST_BYTES:
            raise ManifestError(f"{path}: larger than the {MAX_MANIFEST_BYTES // 2**20} MiB of any manifest the "
                                "recorder writes: not read")
        try:
            return cls.from_dict(json.loads(data))
        except ManifestError as exc:
            raise ManifestError(f"{path}: {exc}") from None
        except (ValueError, RecursionError) as exc:  # (not JSON, not UTF-8, nested beyond the parser's depth)
            raise ManifestError(f"{path}: not a manifest ({type(exc).__name__}: {str(exc)[:120]})") from None


class ManifestError(ValueError):
    """A manifest that cannot be read as one; the message names the file and what was wrong."""


# The recorder's manifest: a line of statistics (~300 bytes) for each of at most 4 000 keys, one per segment.
MAX_MANIFEST_BYTES = 32 * 2**20
# JSON types each field type accepts (bool is no number here, though Python makes it an int).
_JSON = {"int": (int,), "str": (str,), "bool": (bool,), "float": (int, float)}


def _of(kind: type, value: Any, what: str) -> Any:
    if not isinstance(value, kind):
        raise ManifestError(f"{what} is {type(value).__name__}, not {kind.__name__}")
    return value


def _fields(cls: type, data: Any, what: str) -> dict[str, Any]:
    """The known fields of ``data`` (a JSON object), each checked against ``cls``'s type for it."""
    _of(dict, data, what)
    out = {}
    for name, value in data.items():
        f = cls.__dataclass_fields__.get(name)  # type: ignore[attr-defined]
        if f is None:
            continue
        hint = str(f.type)
        base = hint.removesuffix(" | None")
        ok = (value is None and hint.endswith("| None")) or (
            base in _JSON and isinstance(value, _JSON[base]) and (base == "bool" or not isinstance(value, bool)))
        if base.startswith("list["):
            ok = isinstance(value, list) and (base != "list[str]" or all(isinstance(v, str) for v in value))
        elif base.startswith("dict["):
            ok = isinstance(value, dict) and (base != "dict[str, str]" or all(isinstance(v, str)
                                                                              for v in value.values()))
        if not ok:
            raise ManifestError(f"in {what}, {name} is a JSON {type(value).__name__}, not {hint}")
        out[name] = value
    missing = [f.name for f in dataclasses.fields(cls) if f.name not in out and f.default is dataclasses.MISSING
               and f.default_factory is dataclasses.MISSING]
    if missing:
        raise ManifestError(f"{what} has no {', '.join(missing)}")
    return out


# The writer locks this process holds: session folder → the lock file's descriptor (kept open: closing it would
# release the lock).
_writer_locks: dict[Path, int] = {}

# The lock file also carries the reason a recording failed when its manifest could not say so (a full disk):
# written in place into bytes reserved when the lock is taken, because a full disk has no room for a new file.
FAILURE_NOTE_BYTES = 1024


def _hold_writer_lock(folder: Path) -> None:
    key = Path(folder).resolve()
    if key in _writer_locks:
        return
    if fcntl is None:
        return
    fd = os.open(key / WRITER_LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.ftruncate(fd, 0)
        os.pwrite(fd, b" " * FAILURE_NOTE_BYTES, 0)  # the reserve (blank: no failure)
    except BlockingIOError:
        os.close(fd)
        raise RuntimeError(f"{folder}: another process is recording this session") from None
    except OSError:
        os.close(fd)
        raise
    _writer_locks[key] = fd


def release_writer_lock(folder: Path) -> None:
    """Release this process's writer lock on ``folder`` (nothing if it holds none): the session is no longer
    being written, so a reader may repair it."""
    fd = _writer_locks.pop(Path(folder).resolve(), None)
    if fd is not None:
        os.close(fd)  # closing the descriptor releases the flock


def note_failure(folder: Path, reason: str) -> None:
    """Keep ``reason`` in the session's lock file, for a later repair (:func:`failure_note`) when the manifest
    could not be written with it. Raises OSError when even that is impossible."""
    data = reason.encode()[:FAILURE_NOTE_BYTES].ljust(FAILURE_NOTE_BYTES, b" ")
    fd = _writer_locks.get(Path(folder).resolve())
    if fd is not None:  # over the reserved bytes: needs no new room on the disk
        os.pwrite(fd, data, 0)
        return
    with (Path(folder) / WRITER_LOCK).open("r+b" if (Path(folder) / WRITER_LOCK).exists() else "wb") as f:
        f.write(data)


def failure_note(folder: Path) -> str:
    """The reason :func:`note_failure` kept for this session, "" when there is none."""
    try:
        data = (Path(folder) / WRITER_LOCK).read_bytes()[:FAILURE_NOTE_BYTES]
    except OSError:
        return ""
    return data.decode(errors="replace").strip()


def writer_alive(folder: Path, quiet_for: float = 10.0) -> bool:
    """Whether a live process is still writing this session. By its lock where the session has one; a session
    written before locks existed counts as live while its files changed within ``quiet_for`` s."""
    folder = Path(folder)
    if Path(folder).resolve() in _writer_locks:
        return True
    lock = folder / WRITER_LOCK
    if lock.exists() and fcntl is not None:
        fd = os.open(lock, os.O_RDWR)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        finally:
            os.close(fd)  # releases the probe's lock, if it got it
        return False
    newest = max((p.stat().st_mtime for p in folder.iterdir() if p.is_file()), default=0.0)
    return time.time() - newest < quiet_for


def iso(ns: int | None) -> str:
    return "" if not ns else datetime.fromtimestamp(ns / 1e9, UTC).isoformat(timespec="milliseconds")


@functools.cache
def software_versions() -> dict[str, str]:
    """Versions for the manifest (cached: the first metadata lookup costs ~0.2 s, too much for a start)."""
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": platform.python_version(), "host": platform.node()}
    for dist in ("iorthand", "iorthand-cloud", "eclipse-zenoh", "mcap"):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:
            out[dist] = "not installed"
    return out
