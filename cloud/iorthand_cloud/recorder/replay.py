"""``iorthand replay SESSION``: republish a recording into Zenoh with its original timing (or faster).

Messages go out with their original bytes (sequence numbers and source times included), spaced by their
original receive times divided by ``speed``, on their keys with the robot's replay id (below): the twin and any
client see the session as if it were live. Malformed payloads are replayed only on request.
Each key is published with its QoS from :data:`iorthand.transport.QOS_BY_KEY` (video on the video profile).

Operator commands (``iorthand/*/cmd/**``) are recorded but never replayed: replayed into a live deployment,
the recorded twists of an operator who owns a robot again would drive it. They are counted instead.

A replay never publishes as a robot: every recorded robot goes out as ``<robot>-replay``
(:func:`iorthand.keys.replay_id`), an id no edge may take, so consoles and the twin show a replay as one and the
router's access control can confine the replay identity to those ids. ``rename`` (``--as sim1=lyon-replay``)
picks another replay id. Keys outside a robot (the cloud services' own) are not replayed: a replay must not
speak for the twin or the recorder either.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from iorthand import keys
from iorthand.transport import QOS_BY_KEY
from iorthand_cloud.recorder.reader import Record, iter_records

log = logging.getLogger("iorthand.replay")

# A silence in the recording longer than this (the edge was off, or a file's times jump) is shortened to it, and
# said: a replay that waits in silence for hours (or years, for a crafted file) looks hung.
MAX_GAP_S = 5.0


@dataclass
class ReplayStats:
    published: int = 0
    skipped: int = 0
    commands_withheld: int = 0  # operator commands in the recording, never republished
    loops: int = 0
    max_late_ms: float = 0.0
    gaps_shortened: float = 0.0  # s of recorded silence not waited for (MAX_GAP_S)
    per_key: dict[str, int] = field(default_factory=dict)  # messages per key they went out on


def _publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    try:
        _, suffix = keys.split_key(key)
        qos = QOS_BY_KEY.get(suffix)
    except keys.KeyExprError:
        qos = None
    if qos is None:
        return session.declare_publisher(key)
    # BLOCK for replay: a file has no reason to drop its own frames; the live path's policy does that.
    return session.declare_publisher(key, priority=qos.priority, congestion_control=zenoh.CongestionControl.BLOCK,
                                     express=qos.express)


class NothingToReplay(RuntimeError):
    """A pass over the replay's window published nothing (looping on it would only spin)."""


class Replayer:
    def __init__(
        self, session: zenoh.Session, folder: str | Path, speed: float = 1.0, loop: bool = False,
        key_filter: list[str] | None = None, include_malformed: bool = False,
        start: float | None = None, end: float | None = None,
        on_publish: Callable[[Record], None] | None = None, rename: dict[str, str] | None = None,
    ) -> None:
        if speed <= 0:
            raise ValueError("speed must be > 0")
        if start is not None and end is not None and end <= start:
            raise ValueError(f"--end {end:g} s is not after --start {start:g} s: the window holds nothing")
        self.rename = dict(rename or {})
        for old, new in self.rename.items():
            try:
                keys.check_robot_id(old)
                if keys.replay_id(new) != new:
                    raise keys.KeyExprError(f"{new!r} does not end in {keys.REPLAY_SUFFIX!r}: a replay never "
                                            f"publishes as a robot (e.g. {keys.replay_id(new)!r})")
            except keys.KeyExprError as exc:
                raise ValueError(f"rename {old}={new}: {exc}") from None
        self.session = session
        self.folder = Path(folder)
        self.speed = speed
        self.loop = loop
        self.filters = [zenoh.KeyExpr(k) for k in key_filter or []]
        commands = zenoh.KeyExpr(keys.ALL_COMMANDS)
        for f in self.filters:
            if commands.includes(f):
                raise ValueError(f"--keys {f}: a replay never publishes operator commands ({keys.ALL_COMMANDS}), "
                                 "so that it cannot drive a robot; replay state/**, markers or video/** instead")
        self.include_malformed = include_malformed
        self.start_s, self.end_s = start, end
        self.on_publish = on_publish
        self.stats = ReplayStats()
        self.stop_event = threading.Event()
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._wanted: dict[str, bool] = {}
        self._target: dict[str, str | None] = {}  # recorded key → the key it goes out on (None: not replayed)

    def _wants(self, rec: Record) -> bool:
        if keys.is_command_key(rec.key):
            self.stats.commands_withheld += self.stats.loops == 0  # (counted once, not again at each pass)
            return False
        if rec.malformed and not self.include_malformed:
            return False
        return self._wants_key(rec.key)

    def _wants_key(self, key: str) -> bool:
        """Whether messages on ``key`` are replayed at all: a robot's key, not an operator command, and inside
        ``key_filter``."""
        ok = self._wanted.get(key)
        if ok is None:
            ok = self._published_as(key) is not None and not keys.is_command_key(key)
            if ok and self.filters:
                ke = zenoh.KeyExpr(key)
                ok = any(f.intersects(ke) for f in self.filters)
            self._wanted[key] = ok
        return ok

    def _window(self) -> tuple[int | None, int | None]:
        first = next(iter_records(self.folder), None)
        if first is None:
            return None, None
        t0 = first.log_time
        start = t0 + int(self.start_s * 1e9) if self.start_s is not None else None
        end = t0 + int(self.end_s * 1e9) if self.end_s is not None else None
        return start, end

    def _published_as(self, key: str) -> str | None:
        """The key a recorded message goes out on: its robot's replay id in place of the robot's; None for a
        key outside any robot."""
        if key not in self._target:
            try:
                robot, suffix = keys.split_key(key)
            except keys.KeyExprError:
                self._target[key] = None
            else:
                try:
                    self._target[key] = keys.RobotKeys(self.rename.get(robot) or keys.replay_id(robot)).key(suffix)
                except keys.KeyExprError as exc:  # a recording made on an open router may hold anyone's keys
                    log.warning("messages on %s are not replayed: %s", key[:120], exc)
                    self._target[key] = None
        return self._target[key]

    def run(self) -> ReplayStats:
        try:
            start, end = self._window()
            while not self.stop_event.is_set():
                before = self.stats.published
                self._once(start, end)
                if self.stats.published == before and not self.stop_event.is_set():
                    raise NothingToReplay(
                        f"nothing to replay in this window ({self.stats.skipped} recorded messages in it not "
                        f"replayed, {self.stats.commands_withheld} of them operator commands)")
                self.stats.loops += 1
                if not self.loop:
                    break
        finally:
            for p in self._pubs.values():
                p.undeclare()
        return self.stats

    def _once(self, start: int | None, end: int | None) -> None:
        t0_rec: int | None = None
        t0_wall = 0.0
        first = last = 0
        for rec in iter_records(self.folder, start, end):
            if self.stop_event.is_set():
                return
            if not self._wants(rec):
                self.stats.skipped += self.stats.loops == 0
                continue
            if t0_rec is None:
                t0_rec, t0_wall = rec.log_time, time.monotonic()
                first = rec.log_time
            elif (gap := (rec.log_time - last) / 1e9) > MAX_GAP_S:
                t0_rec += int((gap - MAX_GAP_S) * 1e9)  # the rest keeps its timing, from MAX_GAP_S on
                self.stats.gaps_shortened += gap - MAX_GAP_S
                log.warning("the recording is silent for %.1f s, %.1f s into it: replayed as %g s",
                            gap, (last - first) / 1e9, MAX_GAP_S)
            last = rec.log_time
            due = t0_wall + (rec.log_time - t0_rec) / 1e9 / self.speed
            delay = due - time.monotonic()
            if delay > 0:
                self.stop_event.wait(delay)
            else:
                self.stats.max_late_ms = max(self.stats.max_late_ms, -delay * 1000)
            key = self._published_as(rec.key)
            assert key is not None  # _wants() passed only robot keys
            pub = self._pubs.get(key)
            if pub is None:
                pub = self._pubs[key] = _publisher(self.session, key)
            pub.put(rec.data)
            self.stats.published += 1
            self.stats.per_key[key] = self.stats.per_key.get(key, 0) + 1
            if self.on_publish is not None:
                self.on_publish(rec)
