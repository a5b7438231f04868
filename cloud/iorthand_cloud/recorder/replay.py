"""``iorthand replay SESSION``: republish a recording into Zenoh with its original timing (or faster).

Messages go out on their original keys, with their original bytes (sequence numbers and source times
included), spaced by their original receive times divided by ``speed``: the twin and any client see the
session as if it were live. The recorder's own keys are not replayed; malformed payloads only on request.
Each key is published with its QoS from :data:`iorthand.transport.QOS_BY_KEY` (video on the video profile).

Operator commands (``iorthand/*/cmd/**``) are recorded but never replayed: replayed into a live deployment,
the recorded twists of an operator who owns a robot again would drive it. They are counted instead.

A replay never publishes as a robot that is live (its edge's liveliness token is present): every console and
the twin would mix the recording's state with the real robot's, e.g. show a recorded force level 0 while the
probe presses at level 2. It refuses before the first message, and stops if such an edge comes online while
it runs. ``rename`` (``--as sim1=sim1-replay``) replays a robot under another id, beside the live one.
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
from iorthand_cloud.recorder.manifest import Manifest
from iorthand_cloud.recorder.reader import Record, iter_records

log = logging.getLogger("iorthand.replay")

LIVE_QUERY_S = 1.0  # how long the replay asks the network which edges are online before it publishes anything


@dataclass
class ReplayStats:
    published: int = 0
    skipped: int = 0
    commands_withheld: int = 0  # operator commands in the recording, never republished
    loops: int = 0
    max_late_ms: float = 0.0
    per_key: dict[str, int] = field(default_factory=dict)
    stopped: str = ""  # why the replay refused or stopped early ("" = it ran to the end or was asked to stop)


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
        on_publish: Callable[[Record], None] | None = None, rename: dict[str, str] | None = None,
    ) -> None:
        if speed <= 0:
            raise ValueError("speed must be > 0")
        self.rename = dict(rename or {})
        for old, new in self.rename.items():
            for robot in (old, new):
                try:
                    keys.check_robot_id(robot)
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
        self._recorder_prefix = keys.service_key(keys.RECORDER) + "/"
        self._target: dict[str, tuple[str, str]] = {}  # recorded key → (robot, key) it is published as
        self._live: set[str] = set()  # robots whose edge is online
        self._live_lock = threading.Lock()

    def _wants(self, rec: Record) -> bool:
        if keys.is_command_key(rec.key):
            self.stats.commands_withheld += 1
            return False
        if rec.malformed and not self.include_malformed:
            return False
        return self._wants_key(rec.key)

    def _wants_key(self, key: str) -> bool:
        """Whether messages on ``key`` are replayed at all: not operator commands, not the recorder's own, and
        inside ``key_filter``."""
        ok = self._wanted.get(key)
        if ok is None:
            ok = not keys.is_command_key(key) and not key.startswith(self._recorder_prefix)
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

    def _published_as(self, key: str) -> tuple[str, str]:
        """The robot and the key a recorded message goes out as (``rename`` applied); a key outside any robot
        goes out unchanged, as robot ""."""
        target = self._target.get(key)
        if target is None:
            try:
                robot, suffix = keys.split_key(key)
            except keys.KeyExprError:
                target = ("", key)
            else:
                robot = self.rename.get(robot, robot)
                target = (robot, keys.RobotKeys(robot).key(suffix))
            self._target[key] = target
        return target

    def _recorded_robots(self) -> set[str]:
        """Robots the replay will publish as, from the manifest (empty if it cannot be read: then the check
        happens message by message)."""
        try:
            recorded = Manifest.read(self.folder).keys
        except (OSError, ValueError, KeyError, TypeError):
            return set()
        return {self._published_as(key)[0] for key in recorded if self._wants_key(key)}

    def _on_edge_alive(self, sample: zenoh.Sample) -> None:
        robot = keys.split_key(str(sample.key_expr))[0]
        with self._live_lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._live.add(robot)
            else:
                self._live.discard(robot)

    def _stop_for_live(self, robots: set[str]) -> bool:
        with self._live_lock:
            live = sorted(robots & self._live)
        if live:
            self.stats.stopped = (
                f"robot {', '.join(live)} is live (its edge's liveliness token is present): its recorded state would "
                f"mix with the live state on every console and in the twin; replay it under another id, "
                f"e.g. --as {live[0]}={live[0]}-replay"
            )
            log.error("replay stopped: %s", self.stats.stopped)
            self.stop_event.set()
        return bool(live)

    def run(self) -> ReplayStats:
        watch = self.session.liveliness().declare_subscriber(keys.all_robots(keys.ALIVE_EDGE), self._on_edge_alive)
        try:
            for reply in self.session.liveliness().get(keys.all_robots(keys.ALIVE_EDGE), timeout=LIVE_QUERY_S):
                if reply.ok is not None:
                    self._on_edge_alive(reply.ok)
            if not self._stop_for_live(self._recorded_robots()):
                start, end = self._window()
                while not self.stop_event.is_set():
                    self._once(start, end)
                    self.stats.loops += 1
                    if not self.loop:
                        break
        finally:
            watch.undeclare()
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
            robot, key = self._published_as(rec.key)
            if self._stop_for_live({robot}):
                return
            pub = self._pubs.get(key)
            if pub is None:
                pub = self._pubs[key] = _publisher(self.session, key)
            pub.put(rec.data)
            self.stats.published += 1
            self.stats.per_key[key] = self.stats.per_key.get(key, 0) + 1
            if self.on_publish is not None:
                self.on_publish(rec)
