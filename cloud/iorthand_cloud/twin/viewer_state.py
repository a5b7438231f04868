"""Where a rerun web viewer's time cursor stands: how far behind live a browser showing the twin is. Pure.

The served viewer keeps its ``WebHandle`` as ``window._handle``; ``viewer_state()`` returns a protobuf message
(rerun 0.41) with, per open recording, each timeline's data range, the time cursor and the play state. The
schema is rerun's own and not published with the wheel, so this reads the wire format directly for the few
fields it needs and says so when they are not where 0.41 puts them:

    3: recording { 1: id, 2: timeline { 1: { 1: name } 3: data range { 1: min, 2: max } },
                   3: time cursor { 1: { 1: timeline name } 3: { 1: time } }, 5: play state }

Play state 3 is "following" (the viewer shows the newest data as it arrives).
"""

from __future__ import annotations

from dataclasses import dataclass

FOLLOWING = 3


@dataclass(frozen=True)
class Cursor:
    recording: str
    timeline: str
    time_ns: int
    play_state: int
    newest_ns: int | None  # the newest data the viewer holds on that timeline


def _fields(buf: bytes) -> list[tuple[int, int, int | bytes]]:
    """(field, wire type, value) of one protobuf message: varints as ints, length-delimited as bytes."""
    out: list[tuple[int, int, int | bytes]] = []
    i = 0

    def varint() -> int:
        nonlocal i
        value = shift = 0
        while True:
            b = buf[i]
            i += 1
            value |= (b & 0x7F) << shift
            shift += 7
            if not b & 0x80:
                return value

    while i < len(buf):
        key = varint()
        field, wire = key >> 3, key & 7
        if wire == 0:
            out.append((field, wire, varint()))
        elif wire == 2:
            n = varint()
            out.append((field, wire, buf[i:i + n]))
            i += n
        elif wire in (1, 5):
            size = 8 if wire == 1 else 4
            out.append((field, wire, int.from_bytes(buf[i:i + size], "little")))
            i += size
        else:
            raise ValueError(f"unexpected protobuf wire type {wire}")
    return out


def _sub(fields: list[tuple[int, int, int | bytes]], number: int) -> list[bytes]:
    return [v for f, w, v in fields if f == number and w == 2 and isinstance(v, bytes)]


def cursors(state: bytes) -> list[Cursor]:
    """Every recording's time cursor in a ``viewer_state()`` (ValueError if the layout is not rerun 0.41's)."""
    out: list[Cursor] = []
    for rec in _sub(_fields(state), 3):
        fields = _fields(rec)
        ids = _sub(fields, 1)
        play = next((v for f, w, v in fields if f == 5 and w == 0 and isinstance(v, int)), 0)
        newest: dict[str, int] = {}
        for timeline in _sub(fields, 2):
            tf = _fields(timeline)
            names = [_sub(_fields(t), 1) for t in _sub(tf, 1)]
            ranges = [next((v for f, w, v in _fields(r) if f == 2 and w == 0), None) for r in _sub(tf, 3)]
            if names and names[0] and ranges and isinstance(ranges[0], int):
                newest[names[0][0].decode()] = ranges[0]
        for cursor in _sub(fields, 3):
            cf = _fields(cursor)
            names = [_sub(_fields(t), 1) for t in _sub(cf, 1)]
            times = [next((v for f, w, v in _fields(t) if f == 1 and w == 0), None) for t in _sub(cf, 3)]
            if names and names[0] and times and isinstance(times[0], int):
                name = names[0][0].decode()
                out.append(Cursor(ids[0].decode() if ids else "", name, times[0], play, newest.get(name)))
    return out


def lag_seconds(state: bytes, timeline: str, now_ns: int) -> float | None:
    """How far the newest recording's cursor on ``timeline`` is behind ``now_ns`` (None: no cursor there)."""
    found = [c for c in cursors(state) if c.timeline == timeline]
    if not found:
        return None
    return (now_ns - max(c.time_ns for c in found)) / 1e9


__all__ = ["FOLLOWING", "Cursor", "cursors", "lag_seconds"]
