"""The twin service: Zenoh in, latest state per robot, snapshot and preview queryables, rerun out.

Threads (all named; Zenoh callbacks only queue):
- ``twin-ingest``: decodes control-rate streams of every robot (``iorthand/*/state/**``, ``markers``) into the
  :class:`TwinStore`, derives events, feeds the visualiser.
- ``twin-video``: the same for ``video/*`` on a separate small drop-oldest inbox, so big frames never delay
  poses and safety states.
- ``twin-snapshot``: answers ``iorthand/_twin/<robot>/snapshot`` (fast, from memory).
- ``twin-preview``: answers ``iorthand/_twin/<robot>/preview`` by forwarding to the edge's ``plan/preview``
  (the edge is the safety authority and plans), drawing the returned path as a ghost and returning the edge's
  verdict unchanged. Separate from snapshots: a preview may wait seconds for the edge.
- ``twin-viz``: every rerun call (see viz.py).
- ``twin-foxglove``, ``twin-foxglove-video`` (with ``foxglove.enabled``): the live view in the Foxglove app
  (see foxglove.py), on subscribers of its own.

Offline detection: a liveliness subscriber on ``iorthand/*/alive/edge`` (with history, so edges already up are
seen at start). A killed edge's token vanishes within milliseconds; a frozen or cut-off one after the Zenoh
lease (``zenoh.lease_ms``). In addition, a snapshot says when no robot state arrived for ``state_timeout``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import signal
import threading
import time
import uuid
from pathlib import Path
from typing import TYPE_CHECKING, Any

import rerun as rr
import zenoh

from iorthand import keys
from iorthand.protocol import ControlReply, ControlRequest, DecodeError
from iorthand.transport import Inbox, Worker, open_session

from .config import TwinConfig
from .server import ViewerServer
from .state import TwinStore
from .viz import Visualizer

if TYPE_CHECKING:
    from .foxglove import FoxgloveLive

log = logging.getLogger("iorthand.twin")

# The streams the twin draws or keeps: everything an edge publishes except the command echo at 60 Hz
# (state/applied is kept too: refusals are safety events).
STATE_SUFFIXES = (
    keys.STATE_ROBOT, keys.STATE_SAFETY, keys.STATE_APPLIED, keys.STATE_FORCE, keys.STATE_FORCE_LEVEL,
    keys.STATE_SERVO, keys.STATE_TORCH, keys.MARKERS, keys.SENSOR_VITAL,
)
VIDEO_SUFFIXES = (keys.VIDEO_CAMERA, keys.VIDEO_ULTRASOUND)
LAZY_SUFFIX = "/" + keys.STATE_ROBOT
REFUSED_ROBOTS_LOG_S = 10.0  # a flood of new robot ids is logged once per this, not once per sample


def _param(query: zenoh.Query, name: str) -> str:
    params = str(query.parameters)
    for part in params.split(";"):
        k, _, v = part.partition("=")
        if k == name:
            return v or "1"
    return ""


class TwinService:
    def __init__(self, config: TwinConfig, save: Path | None = None, log_dir: Path | None = None) -> None:
        self.config = config
        self.store = TwinStore(max_robots=config.max_robots, configured=config.robots)
        self.stop_event = threading.Event()
        self.session: zenoh.Session | None = None
        self._state_inbox = Inbox(4096, keep="newest")
        self._video_inbox = Inbox(8, keep="newest")
        self._snap_inbox = Inbox(256, keep="oldest")
        self._preview_inbox = Inbox(32, keep="oldest")
        self._workers: list[Worker] = []
        self._declared: list[Any] = []
        self.viz: Visualizer | None = None
        self.server: ViewerServer | None = None
        v = config.viewer
        save = save if save is not None else v.save
        if v.enabled and (v.serve or save is not None):
            # Without a sink a recording stream buffers everything in memory: no viewer, no rerun at all.
            self.rec = rr.RecordingStream("iorthand-twin", recording_id=uuid.uuid4())
            self.server = ViewerServer(v, save=save, log_dir=log_dir)
            self.viz = Visualizer(config, self.rec, on_drawn=self.store.set_q_drawn)
        self.foxglove: FoxgloveLive | None = None  # with foxglove.enabled (foxglove-sdk is imported only then)
        self.ingested = 0
        self._refused_logged, self._refused_logged_at = 0, -REFUSED_ROBOTS_LOG_S
        self.previews = 0
        self.snapshots = 0

    @property
    def url(self) -> str:
        return self.server.url if self.server is not None else ""

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        if self.server is not None and self.viz is not None:
            from .viz import blueprint

            self.server.start(self.rec, default_blueprint=blueprint([]))
            self.viz.start()
        self.session = s = open_session(self.config.zenoh, stop=self.stop_event)
        state_inbox, video_inbox = self._state_inbox, self._video_inbox

        def on_state(sample: zenoh.Sample) -> None:
            state_inbox.put((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

        def on_video(sample: zenoh.Sample) -> None:
            video_inbox.put((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

        for suffix in STATE_SUFFIXES:
            self._declared.append(s.declare_subscriber(keys.all_robots(suffix), on_state))
        for suffix in VIDEO_SUFFIXES:
            self._declared.append(s.declare_subscriber(keys.all_robots(suffix), on_video))
        self._declared.append(s.declare_queryable(keys.service_key(keys.TWIN, "*", keys.TWIN_SNAPSHOT), self._snap_inbox.put))
        self._declared.append(s.declare_queryable(keys.service_key(keys.TWIN, "*", keys.TWIN_PREVIEW), self._preview_inbox.put))
        self._declared.append(s.liveliness().declare_subscriber(keys.all_robots(keys.ALIVE_EDGE), self._on_alive, history=True))
        if self.config.foxglove.enabled:
            from .foxglove import FoxgloveLive

            self.foxglove = FoxgloveLive(self.config.foxglove)
            self.foxglove.start(s)
        for name, fn in (
            ("ingest", lambda stop: self._ingest_loop(stop, self._state_inbox)),
            ("video", lambda stop: self._ingest_loop(stop, self._video_inbox)),
            ("snapshot", self._snapshot_loop),
            ("preview", self._preview_loop),
        ):
            w = Worker(f"twin-{name}", fn, self.stop_event)
            w.start()
            self._workers.append(w)
        log.info("twin up: %s; viewer %s", ", ".join(self.config.zenoh.connect) or self.config.zenoh.mode,
                 self.url or ("file only" if self.viz else "off"))

    def run_forever(self) -> int:
        """Serve until SIGINT/SIGTERM (0) or until a worker crashes (1: a supervisor such as systemd's
        ``Restart=on-failure`` must start the twin again, not take the crash for a requested stop)."""
        self.start()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: self.stop_event.set())
        if self.url:
            print(f"twin viewer: {self.url}", flush=True)
        if self.foxglove is not None:
            print(f"twin foxglove: {self.foxglove.url}", flush=True)
        print("twin ready", flush=True)
        self.stop_event.wait()
        self.shutdown()
        crashed = [w.name for w in self._workers if w.error is not None]
        if crashed:
            log.error("twin stopped because %s crashed (see above)", ", ".join(crashed))
        return 1 if crashed else 0

    def shutdown(self) -> None:
        self.stop_event.set()
        for inbox in (self._state_inbox, self._video_inbox, self._snap_inbox, self._preview_inbox):
            inbox.close()
        for w in self._workers:
            w.join(timeout=3.0)
        if self.foxglove is not None:
            self.foxglove.stop()
        if self.session is not None:
            for d in self._declared:
                with contextlib.suppress(zenoh.ZError):
                    d.undeclare()
            self.session.close()
            self.session = None
        if self.viz is not None:
            self.viz.stop()
        if self.server is not None:
            self.server.stop()
        log.info("twin stopped")

    # ------------------------------------------------------------------ ingest

    def _on_alive(self, sample: zenoh.Sample) -> None:
        # Runs on the Zenoh callback: only a store update under a short lock and a queue put.
        try:
            robot, _ = keys.split_key(str(sample.key_expr))
        except keys.KeyExprError:
            return
        online = sample.kind == zenoh.SampleKind.PUT
        ev, new = self.store.set_online(robot, online, "" if online else "edge liveliness token gone (edge stopped, killed or cut off)")
        if self.viz is not None:
            if new:
                twin = self.store.get(robot)
                self.viz.feeder.robot_added(robot, twin.index if twin else 0)
            if ev is not None:
                self.viz.feeder.event(ev)
                self.viz.feeder.online(robot, online)
        if ev is not None:
            (log.info if online else log.warning)("robot %s: %s", robot, ev.text)

    def _ingest_loop(self, stop: threading.Event, inbox: Inbox) -> None:
        store, viz = self.store, self.viz
        while not stop.is_set():
            item = inbox.get(timeout=0.2)
            if item is None:
                continue
            batch = [item, *inbox.drain()]
            now = time.monotonic()
            for key, payload, recv_ns in batch:
                # state/robot is the bulk of the traffic (125 Hz per robot): decode it only when it will be
                # drawn (pose_hz) or asked for (snapshot); store.ingest_lazy keeps the newest payload.
                if key.endswith(LAZY_SUFFIX) and (viz is None or not viz.feeder.pose_due(key, now)) \
                        and store.ingest_lazy(key, payload, recv_ns):
                    self.ingested += 1
                    continue
                robot, suffix, msg, events, new = store.ingest(key, payload, recv_ns)
                self.ingested += 1
                if viz is None or msg is None:
                    continue
                if new:
                    twin = store.get(robot)
                    viz.feeder.robot_added(robot, twin.index if twin else 0)
                for ev in events:
                    viz.feeder.event(ev)
                viz.feeder.offer(robot, suffix, msg, now)
            self._warn_of_refused_robots(now)

    def _warn_of_refused_robots(self, now: float) -> None:
        """Log, at most every REFUSED_ROBOTS_LOG_S, that samples of robots beyond ``max_robots`` were refused."""
        refused = self.store.refused_robots
        if refused > self._refused_logged and now - self._refused_logged_at >= REFUSED_ROBOTS_LOG_S:
            log.warning("twin follows %d robots besides the configured ones (max_robots): %d samples of other robots "
                        "refused so far, the last of robot %r", self.store.max_robots, refused,
                        self.store.last_refused)
            self._refused_logged, self._refused_logged_at = refused, now

    # ------------------------------------------------------------------ queries

    def _snapshot_loop(self, stop: threading.Event) -> None:
        while not stop.is_set():
            query = self._snap_inbox.get(timeout=0.2)
            if query is None:
                continue
            try:
                robot = str(query.key_expr).split("/")[2]
                images = self.config.snapshot_images or _param(query, "images") not in ("", "0", "false")
                snap = self.store.snapshot(robot, include_images=images, state_timeout=self.config.state_timeout)
                query.reply(query.key_expr, snap.encode())
                self.snapshots += 1
            except (zenoh.ZError, ValueError, IndexError) as exc:
                log.warning("snapshot query %s failed: %s", query.key_expr, exc)
                with contextlib.suppress(zenoh.ZError):
                    query.reply_err(f"snapshot failed: {exc}".encode())
            finally:
                query.drop()

    def _preview_loop(self, stop: threading.Event) -> None:
        while not stop.is_set():
            query = self._preview_inbox.get(timeout=0.2)
            if query is None:
                continue
            try:
                self._preview(query)
            finally:
                query.drop()

    def _preview(self, query: zenoh.Query) -> None:
        robot = str(query.key_expr).split("/")[2]
        payload = query.payload.to_bytes() if query.payload is not None else b""
        try:
            keys.check_robot_id(robot)
            req = ControlRequest.decode(payload)
        except keys.KeyExprError as exc:  # the key's robot segment: anyone may query any of them
            self._reply(query, ControlReply(ok=False, reason=f"preview refused: {exc}"))
            return
        except DecodeError as exc:
            self._reply(query, ControlReply(ok=False, reason=f"malformed preview request: {exc}"))
            return
        reply = self.forward_preview(robot, req)
        self._reply(query, reply)

    def forward_preview(self, robot: str, req: ControlRequest) -> ControlReply:
        """Ask the edge of ``robot`` to plan ``req.name``; draw and return its verdict."""
        assert self.session is not None
        key = keys.RobotKeys(robot).key(keys.PLAN_PREVIEW)
        reply: ControlReply | None = None
        reason = ""
        asked = time.monotonic()  # the edge issues the token after this: its ghost is drawn until asked + ttl
        try:
            for r in self.session.get(key, payload=req.encode(), timeout=self.config.preview_timeout):
                if r.ok is not None:
                    try:
                        reply = ControlReply.decode(r.ok.payload.to_bytes())
                    except DecodeError as exc:
                        reason = f"the edge answered a malformed preview: {exc}"
                    break
                reason = f"the edge refused the preview query: {r.err.payload.to_bytes().decode(errors='replace')[:150]}"
        except zenoh.ZError as exc:
            reason = f"preview query failed: {exc}"
        if reply is None:
            reply = ControlReply(ok=False, reason=reason or f"no answer from {robot}'s edge within {self.config.preview_timeout:g} s"
                                 " (edge offline, or its preview is not available)")
        self.previews += 1
        detail: dict[str, Any] = {}
        if reply.detail:
            try:
                detail = json.loads(reply.detail)
            except ValueError:
                detail = {}
        verdict = "accepted" if reply.ok else "REFUSED"
        text = f"preview {req.name!r} {verdict}: {reply.reason}"[:200]
        ev = self.store.add_event(robot, "INFO" if reply.ok else "WARN", text)
        if self.viz is not None and ev is not None:  # (None: a robot beyond max_robots, never drawn)
            self.viz.feeder.event(ev)
            if detail:
                self.viz.feeder.preview(robot, detail, sent_mono=asked)
        log.info("robot %s: %s", robot, text)
        return reply

    @staticmethod
    def _reply(query: zenoh.Query, reply: ControlReply) -> None:
        try:
            query.reply(query.key_expr, reply.stamp(0).encode())
        except zenoh.ZError as exc:
            log.warning("could not answer %s: %s", query.key_expr, exc)


def run(config: TwinConfig, save: Path | None = None) -> int:
    return TwinService(config, save=save).run_forever()


__all__ = ["TwinService", "run"]
