"""``iorthand replay SESSION``: republish a recording into Zenoh with its original timing (or faster).

Messages go out on their original keys, with their original bytes (sequence numbers and source times
included), spaced by their original receive times divided by ``speed``: the twin and any client see the
session as if it were live. The recorder's own keys are not replayed; malformed payloads only on request.
Each key is published with its QoS from :data:`iorthand.transport.QOS_BY_KEY` (video on the video profile).

Operator commands (``iorthand/*/cmd/**``) are recorded but never replayed: replayed into a live deployment,
the recorded twists of an operator who owns a robot again would drive it. They are counted instead.
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


@dataclass
class ReplayStats:
    published: int = 0
    skipped: int = 0
    commands_withheld: int = 0  # operator commands in the recording, never republished
    loops: int = 0
    max_late_ms: float = 0.0
    per_key: dict[str, int] = field(default_factory=dict)


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


class Replayer:
    def __init__(
        self, session: zenoh.Session, folder: str | Path, speed: float = 1.0, loop: bool = False,
        key_filter: list[str] | None = None, include_malformed: bool = False,
        start: float | None = None, end: float | None = None,
        on_publish: Callable[[Record], None] | None = None,
    ) -> None:
        if speed <= 0:
            raise ValueError("speed must be > 0")
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
        self._recorder_prefix = keys.service_key(keys.RECORDER) + "/"

    def _wants(self, rec: Record) -> bool:
        if keys.is_command_key(rec.key):
            self.stats.commands_withheld += 1
            return False
        if rec.malformed and not self.include_malformed:
            return False
        ok = self._wanted.get(rec.key)
        if ok is None:
            ok = not rec.key.startswith(self._recorder_prefix)
            if ok and self.filters:
                ke = zenoh.KeyExpr(rec.key)
                ok = any(f.intersects(ke) for f in self.filters)
            self._wanted[rec.key] = ok
        return ok

    def _window(self) -> tuple[int | None, int | None]:
        first = next(iter_records(self.folder), None)
        if first is None:
            return None, None
        t0 = first.log_time
        start = t0 + int(self.start_s * 1e9) if self.start_s is not None else None
        end = t0 + int(self.end_s * 1e9) if self.end_s is not None else None
        return start, end

    def run(self) -> ReplayStats:
        start, end = self._window()
        while not self.stop_event.is_set():
            self._once(start, end)
            self.stats.loops += 1
            if not self.loop:
                break
        for p in self._pubs.values():
            p.undeclare()
        return self.stats

    def _once(self, start: int | None, end: int | None) -> None:
        t0_rec: int | None = None
        t0_wall = 0.0
        for rec in iter_records(self.folder, start, end):
            if self.stop_event.is_set():
                return
            if not self._wants(rec):
                self.stats.skipped += 1
                continue
            if t0_rec is None:
                t0_rec, t0_wall = rec.log_time, time.monotonic()
            due = t0_wall + (rec.log_time - t0_rec) / 1e9 / self.speed
            delay = due - time.monotonic()
            if delay > 0:
                self.stop_event.wait(delay)
            else:
                self.stats.max_late_ms = max(self.stats.max_late_ms, -delay * 1000)
            pub = self._pubs.get(rec.key)
            if pub is None:
                pub = self._pubs[rec.key] = _publisher(self.session, rec.key)
            pub.put(rec.data)
            self.stats.published += 1
            self.stats.per_key[rec.key] = self.stats.per_key.get(rec.key, 0) + 1
            if self.on_publish is not None:
                self.on_publish(rec)
