"""rerun logging of the twin, in its own thread, behind a bounded queue that drops the oldest items.

``rr.log`` blocks when a connected viewer lags (FACTS.md): nothing here may run on a Zenoh callback or the
ingest thread. The ingest side calls :meth:`VizFeeder.offer` (cheap: rate gates and a force batcher decide
what is worth drawing) which queues items; the ``twin-viz`` thread turns them into rerun calls. When the
viewer or the machine is slow, the queue drops the oldest items (a newer pose supersedes an older one anyway)
and counts them.

Entity paths (one subtree per robot, in the robot's base frame under ``robots/<id>``):

- ``robots/<id>``: the base in the world; ``scene/*``, ``workspace``: static boxes
- ``robots/<id>/arm``: link capsules; ``robots/<id>/tcp``: the tool frame, with ``probe``, ``force`` (arrow
  coloured by level, grey when stale) and ``camera`` (frustum from intrinsics and the servo chain, + image)
- ``robots/<id>/markers/m<k>``: labelled marker frames; ``robots/<id>/preview``: the ghost trajectory and arm
- ``robots/<id>/force_plot/*``: force series and threshold lines; ``robots/<id>/ultrasound``: the image
- ``robots/<id>/events``: text log of safety events

Nothing stale is shown as current: a picture or the markers not renewed for ``viewer.media_stale_after`` are
cleared (and the events say so), everything the edge draws is cleared or greyed when the edge goes offline, a
preview ghost goes when its token expires, and failure notices pass every rate gate.

One timeline, and whose clock: data are logged at the time the edge stamped them (``t``, the edge's clock), so a
force plot keeps the edge's own timing. What the twin makes itself (stale/offline greying, clears, previews, its own
events) has no edge time; logged at this machine's clock it would land before the data when the edge's clock runs
ahead (the viewer, which follows the newest time, keeps showing the live-looking item) or after the next data when
it runs behind (a live sensor looks stale). So a twin-made item is logged at this machine's clock moved by the
robot's clock offset (edge ``t`` minus our clock at the newest edge item: the edge's clock less a latency, so later
data from the edge always come after it), and never earlier than the newest time already logged on the entities it
touches (:meth:`Visualizer._set_twin_time`).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from iorthand import geometry, keys, kinematics
from iorthand.protocol import (
    ForceLevelState,
    ForceSample,
    Markers,
    Message,
    RobotState,
    SensorReading,
    ServoState,
    VideoFrame,
)
from iorthand.transport import Inbox, Worker

from . import model
from .config import RobotView, TwinConfig
from .state import Event

log = logging.getLogger("iorthand.twin.viz")

FORCE_SCALE = 0.01  # m of arrow per N
TIMELINE = "time"
MAX_VITALS = 16  # vital signs plotted per robot (as many as the consoles show)
# How long a refused preview's ghost stays (a refused plan has no token, hence no ttl): the edge's default token_ttl.
REFUSED_GHOST_S = 10.0


# ---------------------------------------------------------------------------------------------------------
# Pure helpers: rate gates and force batches (decided on the ingest side, before the queue)


class RateGate:
    """At most ``hz`` items per key: ``due`` is True when the key's next slot has come."""

    def __init__(self, hz: float) -> None:
        self.period = 1.0 / hz
        self._next: dict[Any, float] = {}

    def due(self, key: Any, now: float) -> bool:
        nxt = self._next.get(key, -math.inf)
        if now < nxt:
            return False
        # Schedule from the slot, not from now, so the mean rate is exact; resync after a gap.
        self._next[key] = nxt + self.period if now - nxt < self.period else now + self.period
        return True


@dataclass
class ForceBatch:
    robot: str
    t_ns: list[int] = field(default_factory=list)
    force: list[list[float]] = field(default_factory=list)


class ForceBatcher:
    """Collects force samples per robot and hands them over every ``period`` seconds as one batch."""

    def __init__(self, period: float) -> None:
        self.period = period
        self._batches: dict[str, ForceBatch] = {}
        self._started: dict[str, float] = {}

    def add(self, robot: str, t_ns: int, force: list[float], now: float) -> ForceBatch | None:
        b = self._batches.get(robot)
        if b is None:
            b = self._batches[robot] = ForceBatch(robot)
            self._started[robot] = now
        b.t_ns.append(t_ns)
        b.force.append(force)
        if now - self._started[robot] >= self.period:
            del self._batches[robot]
            return b
        return None


# ---------------------------------------------------------------------------------------------------------
# The queue and the feeder


@dataclass
class VizItem:
    kind: str
    robot: str
    t_ns: int
    data: Any = None  # t_ns 0: made by the twin, no edge time (see the module's docstring)


class VizFeeder:
    """Decides what reaches the viewer (rate limits per stream) and queues it. Called from ingest threads."""

    def __init__(self, config: TwinConfig, queue: Inbox) -> None:
        v = config.viewer
        self.queue = queue
        self._pose = RateGate(v.pose_hz)
        self._image = RateGate(v.image_fps)
        self._markers = RateGate(v.markers_hz)
        self._forces = ForceBatcher(v.force_batch_s)
        self._lock = threading.Lock()  # state and video arrive on different threads
        self._granted: set[str] = set()  # robots whose next state passes (see pose_due)
        self._failed: dict[tuple[str, str], bool] = {}  # (robot, stream): whether its last message was a failure

    def _news(self, robot: str, suffix: str, msg: Message) -> bool:
        """Whether ``msg`` is a failure notice or changes the stream's failure state (the first picture after a
        failure): such a message always passes its rate gate. A notice 20 ms after a good frame must not be
        thinned out like a frame, or the frozen picture stays until the next notice (1–30 s later)."""
        failed = bool(getattr(msg, "failure", ""))
        changed = self._failed.get((robot, suffix), False) != failed
        self._failed[(robot, suffix)] = failed
        return failed or changed

    def pose_due(self, key: str, now: float) -> bool:
        """Whether the robot state on ``key`` will be drawn (so it must be decoded now). Consumes the slot:
        the following :meth:`offer` of that state passes its gate."""
        robot = key.split("/", 2)[1]
        with self._lock:
            due = self._pose.due(robot, now)
            if due:
                self._granted.add(robot)
            return due

    def robot_added(self, robot: str, index: int) -> None:
        self.queue.put(VizItem("robot", robot, 0, index))

    def offer(self, robot: str, suffix: str, msg: Message, now: float) -> None:
        with self._lock:
            if suffix == keys.STATE_ROBOT:
                if robot in self._granted or self._pose.due(robot, now):
                    self._granted.discard(robot)
                    self.queue.put(VizItem("state", robot, msg.t, msg))
            elif suffix == keys.STATE_FORCE:
                assert isinstance(msg, ForceSample)
                batch = self._forces.add(robot, msg.t, list(msg.force), now)
                if batch is not None:
                    self.queue.put(VizItem("force", robot, msg.t, batch))
            elif suffix in (keys.VIDEO_CAMERA, keys.VIDEO_ULTRASOUND):
                # JPEG pictures are thinned to image_fps; an H.264 frame needs the ones before it: every one goes.
                # A failure notice (or the end of one) always goes (see _news).
                news = self._news(robot, suffix, msg)
                if news or getattr(msg, "encoding", "") == "h264" or self._image.due((robot, suffix), now):
                    self.queue.put(VizItem("image", robot, msg.t, (suffix, msg)))
            elif suffix == keys.MARKERS:
                if self._news(robot, suffix, msg) or self._markers.due(robot, now):
                    self.queue.put(VizItem("markers", robot, msg.t, msg))
            elif suffix == keys.SENSOR_VITAL:
                self.queue.put(VizItem("vital", robot, msg.t, msg))  # a patient monitor's pace: a few per second
            elif suffix in (keys.STATE_FORCE_LEVEL, keys.STATE_SERVO):
                self.queue.put(VizItem(suffix, robot, msg.t, msg))  # on change / ≤ 10 Hz already

    def event(self, ev: Event) -> None:
        self.queue.put(VizItem("event", ev.robot, 0 if ev.cloud_clock else ev.t, ev))

    def online(self, robot: str, online: bool) -> None:
        self.queue.put(VizItem("online", robot, 0, online))

    def preview(self, robot: str, detail: dict[str, Any], sent_mono: float | None = None) -> None:
        """A preview's plan to draw as a ghost until its token expires: ``detail["ttl"]`` seconds from
        ``sent_mono`` (when the twin asked the edge: the token was issued after, so the ghost never outlives it)."""
        self.queue.put(VizItem("preview", robot, 0, (detail, time.monotonic() if sent_mono is None else sent_mono)))


# ---------------------------------------------------------------------------------------------------------
# The blueprint


def blueprint(robots: list[str]) -> rrb.Blueprint:
    """3D view | force plot, images (tabs), events; time following the newest data. Panels collapsed: the viewer
    is also used on phones."""
    images: list[rrb.View] = []
    for r in robots:
        images.append(rrb.Spatial2DView(name=f"{r} camera", origin=f"/robots/{r}/tcp/camera"))
        images.append(rrb.Spatial2DView(name=f"{r} ultrasound", origin=f"/robots/{r}/ultrasound"))
    # The force and the patient's vital signs (iorthand bridge mqtt), as tabs: one plot at a time on a phone.
    right: list[Any] = [rrb.Tabs(
        rrb.TimeSeriesView(name="force (N)", origin="/robots", contents=["+ /robots/*/force_plot/**"]),
        rrb.TimeSeriesView(name="vital signs", origin="/robots", contents=["+ /robots/*/vitals/**"]),
    )]
    if images:
        right.append(rrb.Tabs(*images))
    right.append(rrb.TextLogView(name="safety events", origin="/robots"))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="robots", origin="/"),
            rrb.Vertical(*right, row_shares=[2, 2, 1] if images else [2, 1]),
            column_shares=[3, 2],
        ),
        # A browser that opens the viewer lands on now and stays there (not at the start of what the relay holds).
        rrb.TimePanel(timeline=TIMELINE, play_state="following"),
        collapse_panels=True,
    )


# ---------------------------------------------------------------------------------------------------------
# The logging thread


@dataclass
class _Drawn:
    view: RobotView
    arm: model.ArmModel
    level: int = 0
    level_stale: bool = True
    caution: float = 6.0
    danger: float = 8.0
    last_force: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    last_force_mono: float = -math.inf
    arrow_grey: bool = True
    series_named: bool = False
    vitals_named: set[str] = field(default_factory=set)  # vital signs given their series line (name, unit)
    thresholds_named: bool = False
    thresholds_logged: float = -math.inf
    arrow_colour: tuple[int, int, int, int] = (0, 0, 0, 0)
    online: bool = True
    marker_poses: dict[int, Any] = field(default_factory=dict)
    arm_pose: tuple[float, ...] | None = None  # the TCP pose the arm was last drawn at
    drawn_pose: tuple[float, ...] = ()
    clock_offset_ns: int = 0  # the edge's clock minus ours, at the newest edge-stamped item (0 until one)
    media_seen: dict[str, float] = field(default_factory=dict)  # image/markers entity shown -> monotonic of its last message
    preview_until: float = math.inf  # monotonic time the preview ghost expires


class Visualizer:
    """Owns the rerun recording stream; every rerun call happens on its ``twin-viz`` thread."""

    def __init__(self, config: TwinConfig, rec: rr.RecordingStream,
                 on_drawn: Callable[[str, list[float]], None] | None = None) -> None:
        self.config = config
        self.rec = rec
        self.queue = Inbox(config.viewer.queue, keep="newest")
        self.feeder = VizFeeder(config, self.queue)
        self.on_drawn = on_drawn
        self._arm_gate = RateGate(config.viewer.arm_hz)
        self._video_paths: set[str] = set()  # entities whose H.264 codec was logged
        self._robots: dict[str, _Drawn] = {}
        self._t = 0  # the time the recording stream is set to on TIMELINE (ns)
        self._logged_t: dict[str, int] = {}  # entity path -> newest time logged there (bounded: fixed paths per robot)
        self._stop = threading.Event()
        self._worker: Worker | None = None
        self.handled = 0
        self.errors = 0
        self.busy_s = 0.0  # time spent in rerun calls (the benchmark reports it)

    @property
    def dropped(self) -> int:
        return self.queue.dropped

    def start(self) -> None:
        self.rec.log("/", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.rec.send_blueprint(blueprint([]))
        self._worker = Worker("twin-viz", self._run, self._stop)
        self._worker.start()

    def stop(self, timeout: float = 3.0) -> None:
        self._stop.set()
        self.queue.close()
        if self._worker is not None:
            self._worker.join(timeout)
        try:
            self.rec.flush()
        except Exception as exc:  # flushing to a dead viewer must not fail shutdown
            log.debug("flush: %s", exc)

    def _run(self, stop: threading.Event) -> None:
        next_tick = time.monotonic()
        while not stop.is_set():
            item = self.queue.get(timeout=0.2)
            now = time.monotonic()
            if item is not None:
                t0 = time.perf_counter()
                try:
                    self._handle(item)
                except Exception:  # one bad item must not end the visualisation
                    self.errors += 1
                    if self.errors <= 5:
                        log.exception("could not draw %s for %s", item.kind, item.robot)
                self.busy_s += time.perf_counter() - t0
                self.handled += 1
            if now >= next_tick:
                next_tick = now + 0.25
                self._tick(now)

    # ------------------------------------------------------------------ handlers

    def _set_time(self, t_ns: int) -> None:
        self._t = int(t_ns)
        self.rec.set_time(TIMELINE, timestamp=np.datetime64(self._t, "ns"))

    def _set_twin_time(self, drawn: _Drawn, *paths: str) -> None:
        """The time of something the twin makes (see the module's docstring): our clock moved onto the edge's,
        and after anything already logged on ``paths`` (list the children a recursive clear covers)."""
        t = time.time_ns() + drawn.clock_offset_ns
        for p in paths:
            t = max(t, self._logged_t.get(p, -1) + 1)
        self._set_time(t)

    def _log(self, path: str, *archetypes: Any, static: bool = False) -> None:
        self.rec.log(path, *archetypes, static=static)
        if not static and self._logged_t.get(path, -1) < self._t:
            self._logged_t[path] = self._t

    def _handle(self, item: VizItem) -> None:
        if item.kind == "robot":
            self._add_robot(item.robot, int(item.data))
            return
        drawn = self._robots.get(item.robot)
        if drawn is None:
            drawn = self._add_robot(item.robot, len(self._robots))
        if item.t_ns:  # the source's time
            if item.kind != "vital":  # vital signs come from the MQTT bridge, whose clock is not the edge's
                drawn.clock_offset_ns = int(item.t_ns) - time.time_ns()
            self._set_time(item.t_ns)
        else:  # the twin's own: its handler places it after what it covers
            self._set_twin_time(drawn)
        handler = getattr(self, "_on_" + item.kind.replace("/", "_"))
        handler(item.robot, drawn, item.data)

    def _add_robot(self, robot: str, index: int) -> _Drawn:
        if robot in self._robots:
            return self._robots[robot]
        view = self.config.view(robot, index)
        drawn = self._robots[robot] = _Drawn(view, model.ArmModel(view))
        root = f"robots/{robot}"
        self._set_twin_time(drawn, f"{root}/tcp/camera", f"{root}/events")
        tr, quat = model.transform_parts(model.world_from_base(view))
        self._log(root, rr.Transform3D(translation=tr, quaternion=rr.Quaternion(xyzw=quat)), static=True)
        self._log(f"{root}/base_label", rr.Points3D([[0, 0, 0.02]], labels=[robot], radii=0.01), static=True)
        for obj in view.scene:
            self._log(f"{root}/scene/{obj.name}", rr.Boxes3D(centers=[obj.center], sizes=[obj.size], colors=[obj.color],
                                                             fill_mode="solid"), static=True)
        if view.workspace_min is not None and view.workspace_max is not None:
            lo, hi = np.asarray(view.workspace_min), np.asarray(view.workspace_max)
            self._log(f"{root}/workspace", rr.Boxes3D(centers=[(lo + hi) / 2], sizes=[hi - lo], colors=[(90, 140, 255, 255)],
                                                      fill_mode="majorwireframe", labels=["workspace"]), static=True)
        probe = view.probe_length
        if probe > 0:
            self._log(f"{root}/tcp/probe", rr.Capsules3D(lengths=[probe], radii=[0.012], translations=[[0, 0, -probe]],
                                                         colors=[(235, 235, 235, 255)]), static=True)
        cam = view.camera
        self._log(f"{root}/tcp/camera", rr.Pinhole(image_from_camera=model.intrinsics(cam), resolution=[cam.width, cam.height],
                                                   camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=cam.frustum_depth),
                  static=True)
        self._on_state_servo_angles(robot, 0.0, 0.0)
        self.rec.send_blueprint(blueprint(list(self._robots)))
        self._log(f"{root}/events", rr.TextLog(f"robot {robot} added to the twin", level="INFO"))
        return drawn

    def _on_state(self, robot: str, drawn: _Drawn, st: RobotState) -> None:
        root = f"robots/{robot}"
        pose = tuple(st.tcp_pose)
        if pose == drawn.drawn_pose:
            # A robot at rest: nothing to redraw, except an arm that the rate gate left behind the tool.
            if drawn.arm_pose != pose:
                self._draw_arm(robot, drawn, st)
            return
        drawn.drawn_pose = pose
        # The arm (inverse kinematics + capsules) at arm_hz; the tool frame at every drawn pose.
        if self._arm_gate.due(robot, time.monotonic()):
            self._draw_arm(robot, drawn, st)
        tr, quat = model.transform_parts(geometry.pose_to_matrix(st.tcp_pose))
        self._log(f"{root}/tcp", rr.Transform3D(translation=tr, quaternion=rr.Quaternion(xyzw=quat)), rr.TransformAxes3D(0.05))

    def _draw_arm(self, robot: str, drawn: _Drawn, st: RobotState) -> None:
        drawn.arm_pose = tuple(st.tcp_pose)
        q = drawn.arm.solve(st.tcp_pose, st.q)
        if q is None:
            return
        caps = drawn.arm.capsules(q)
        colour = model.ARM_COLOUR if drawn.online else model.COLOURS["grey"]
        self._log(f"robots/{robot}/arm", rr.Capsules3D(lengths=caps.lengths, radii=caps.radii,
                                                       translations=caps.translations, quaternions=caps.quaternions,
                                                       colors=[colour]))
        if self.on_drawn is not None:
            self.on_drawn(robot, [float(v) for v in q])

    def _draw_arrow(self, robot: str, drawn: _Drawn, stale: bool) -> None:
        colour = model.force_colour(drawn.level, stale)
        vec = np.asarray(drawn.last_force) * FORCE_SCALE
        self._log(f"robots/{robot}/tcp/force", rr.Arrows3D(vectors=[vec], origins=[[0, 0, 0]], colors=[colour], radii=0.004,
                                                           labels=[f"{np.linalg.norm(drawn.last_force):.1f} N"]))
        drawn.arrow_grey = stale
        drawn.arrow_colour = colour

    def _on_force(self, robot: str, drawn: _Drawn, batch: ForceBatch) -> None:
        f = np.asarray(batch.force, dtype=float)
        times = rr.TimeColumn(TIMELINE, timestamp=np.asarray(batch.t_ns, dtype="datetime64[ns]"))
        base = f"robots/{robot}/force_plot"
        if not drawn.series_named:
            self._log(f"{base}/force", rr.SeriesLines(names=["fx", "fy", "fz", "|F|"]), static=True)
            drawn.series_named = True
        # One entity, four series, one call per batch: every rerun call costs the twin CPU.
        values = np.column_stack([f, np.linalg.norm(f, axis=1)])
        self.rec.send_columns(f"{base}/force", indexes=[times],
                              columns=rr.Scalars.columns(scalars=values.reshape(-1)).partition([4] * len(values)))
        # Threshold lines: a point per second is enough for a horizontal line.
        now = time.monotonic()
        if now - drawn.thresholds_logged >= 1.0:
            drawn.thresholds_logged = now
            self._log(f"{base}/thresholds", rr.Scalars([drawn.caution, drawn.danger]))
        drawn.last_force = list(f[-1])
        drawn.last_force_mono = time.monotonic()
        self._draw_arrow(robot, drawn, drawn.level_stale)

    def _on_vital(self, robot: str, drawn: _Drawn, msg: SensorReading) -> None:
        entity = f"robots/{robot}/vitals/{rr.escape_entity_path_part(msg.name)}"
        if msg.name not in drawn.vitals_named:
            if len(drawn.vitals_named) >= MAX_VITALS:
                return  # a flood of names must not grow the recording without bound
            drawn.vitals_named.add(msg.name)
            self._log(entity, rr.SeriesLines(names=[f"{msg.name} ({msg.unit})" if msg.unit else msg.name]),
                      static=True)
        self._log(entity, rr.Scalars([msg.value]))

    def _on_state_force_level(self, robot: str, drawn: _Drawn, msg: ForceLevelState) -> None:
        first = drawn.caution != msg.caution or drawn.danger != msg.danger
        drawn.level, drawn.level_stale, drawn.caution, drawn.danger = msg.level, msg.stale, msg.caution, msg.danger
        base = f"robots/{robot}/force_plot"
        if first or not drawn.thresholds_named:
            drawn.thresholds_named = True
            drawn.thresholds_logged = -math.inf
            self._log(f"{base}/thresholds", rr.SeriesLines(colors=[model.COLOURS["yellow"], model.COLOURS["red"]],
                                                           names=["caution", "danger"]), static=True)
        if model.force_colour(msg.level, msg.stale) != drawn.arrow_colour:
            self._draw_arrow(robot, drawn, msg.stale)  # otherwise the next force batch redraws it

    def _on_state_servo(self, robot: str, drawn: _Drawn, msg: ServoState) -> None:
        self._on_state_servo_angles(robot, msg.pan, msg.tilt)

    def _on_state_servo_angles(self, robot: str, pan: float, tilt: float) -> None:
        view = self._robots[robot].view
        tr, quat = model.transform_parts(model.tcp_camera(view.camera, pan, tilt))
        self._log(f"robots/{robot}/tcp/camera", rr.Transform3D(translation=tr, quaternion=rr.Quaternion(xyzw=quat)))

    def _on_markers(self, robot: str, drawn: _Drawn, msg: Markers) -> None:
        """All markers of a frame as one batch of labelled axes (two log calls whatever their number), and
        only when something moved by more than 0.5 mm / 0.5° or the set changed: markers on a lying patient
        are still most of the time, and every rerun call costs the twin CPU. Every message renews the markers
        shown (see :meth:`_tick`); a failure notice clears them."""
        poses = {} if msg.failure else {m.id: geometry.unflatten(m.pose) for m in msg.markers}
        path = f"robots/{robot}/markers"
        if poses:
            drawn.media_seen[path] = time.monotonic()
        else:
            drawn.media_seen.pop(path, None)
        prev = drawn.marker_poses
        if set(poses) == set(prev) and all(
            geometry.translation_distance(poses[k], prev[k]) < 5e-4 and geometry.rotation_angle(poses[k], prev[k]) < 0.01
            for k in poses
        ):
            return
        drawn.marker_poses = poses
        if not poses:
            self._log(path, rr.Clear(recursive=True))
            return
        ids = sorted(poses)
        origins = np.array([poses[k][:3, 3] for k in ids])
        axes = np.array([poses[k][:3, :3].T for k in ids]) * 0.03  # rows: x, y, z axes of each marker
        self._log(path, rr.Points3D(origins, labels=[f"marker {k}" for k in ids], radii=0.004,
                                    colors=[(255, 120, 0, 255)]))
        self._log(f"{path}/axes", rr.Arrows3D(vectors=axes.reshape(-1, 3), origins=np.repeat(origins, 3, axis=0),
                                              colors=[(230, 40, 40, 255), (40, 190, 60, 255), (40, 80, 230, 255)] * len(ids),
                                              radii=0.0015))

    def _on_image(self, robot: str, drawn: _Drawn, data: tuple[str, VideoFrame]) -> None:
        suffix, frame = data
        path = f"robots/{robot}/tcp/camera/image" if suffix == keys.VIDEO_CAMERA else f"robots/{robot}/ultrasound"
        if frame.failure:  # no picture rather than a frozen one that reads as live; the event log says why
            self._clear_media(drawn, path)
            return
        drawn.media_seen[path] = time.monotonic()
        if frame.encoding == "h264":
            # A video stream: its codec once, then each access unit as a sample (rerun decodes in the viewer).
            if path not in self._video_paths:
                self._log(path, rr.VideoStream(codec=rr.VideoCodec.H264), static=True)
                self._video_paths.add(path)
            self._log(path, rr.VideoStream.from_fields(sample=frame.data, is_keyframe=frame.keyframe))
            return
        media = "image/jpeg" if frame.encoding.lower() in ("jpeg", "jpg") else "image/png"
        self._log(path, rr.EncodedImage(contents=frame.data, media_type=media))

    def _on_event(self, robot: str, drawn: _Drawn, ev: Event) -> None:
        path = f"robots/{robot}/events"
        if ev.cloud_clock:
            self._set_twin_time(drawn, path)
        self._log(path, rr.TextLog(ev.text, level=ev.level))

    @staticmethod
    def _media_paths(robot: str) -> dict[str, str]:
        """What the edge's media streams draw, by entity (cleared with its children where it has some)."""
        return {f"robots/{robot}/tcp/camera/image": "camera picture", f"robots/{robot}/ultrasound": "ultrasound picture",
                f"robots/{robot}/markers": "markers"}

    def _clear_media(self, drawn: _Drawn, path: str) -> None:
        """No picture/markers rather than frozen ones that read as live (the time is set by the caller)."""
        recursive = path.endswith("/markers")
        self._log(path, rr.Clear(recursive=recursive))
        if recursive:
            drawn.marker_poses = {}  # the next markers are drawn even if they did not move
        drawn.media_seen.pop(path, None)

    @staticmethod
    def _preview_paths(robot: str) -> list[str]:
        root = f"robots/{robot}/preview"
        return [root, f"{root}/path", f"{root}/goal", f"{root}/arm"]

    def _on_online(self, robot: str, drawn: _Drawn, online: bool) -> None:
        """Online: the arm in its colour again. Offline: the arm greyed at its last pose, the force arrow grey, and
        the pictures, markers and preview ghost cleared: nothing of a dead edge passes for live."""
        drawn.online = online
        drawn.drawn_pose = ()  # redraw in the new colour at the next state
        arm = f"robots/{robot}/arm"
        media = self._media_paths(robot)
        if online:
            self._set_twin_time(drawn, arm)
        else:
            self._set_twin_time(drawn, arm, f"robots/{robot}/tcp/force", f"robots/{robot}/markers/axes",
                                *media, *self._preview_paths(robot))
        if drawn.arm.q is not None:
            caps = drawn.arm.capsules(drawn.arm.q)
            colour = model.ARM_COLOUR if online else model.COLOURS["grey"]
            self._log(arm, rr.Capsules3D(lengths=caps.lengths, radii=caps.radii, translations=caps.translations,
                                         quaternions=caps.quaternions, colors=[colour]))
        if online:
            return
        for path in media:
            self._clear_media(drawn, path)
        self._log(f"robots/{robot}/preview", rr.Clear(recursive=True))
        drawn.preview_until = math.inf
        if not drawn.arrow_grey:
            self._draw_arrow(robot, drawn, True)

    def _on_preview(self, robot: str, drawn: _Drawn, data: tuple[dict[str, Any], float]) -> None:
        """The ghost of a previewed plan, until its token expires (``ttl`` s after the twin asked; a refused plan,
        which has no token, for :data:`REFUSED_GHOST_S`): an expired plan is not what a go would do."""
        detail, since = data
        root = f"robots/{robot}/preview"
        self._set_twin_time(drawn, *self._preview_paths(robot))
        ok = bool(detail.get("ok"))
        colour = model.GHOST_OK if ok else model.GHOST_REFUSED
        path = np.asarray(detail.get("path") or [], dtype=float).reshape(-1, 3)
        self._log(root, rr.Clear(recursive=True))
        try:
            ttl = float(detail.get("ttl") or 0.0)
        except (TypeError, ValueError):
            ttl = 0.0
        drawn.preview_until = since + (ttl if math.isfinite(ttl) and ttl > 0 else REFUSED_GHOST_S)
        if len(path) >= 2:
            label = f"{detail.get('name')}: {'ok' if ok else 'refused'} {detail.get('duration', 0):.1f} s"
            self._log(f"{root}/path", rr.LineStrips3D([path], colors=[colour], radii=0.003, labels=[label]))
        goal = detail.get("goal")
        if goal and len(goal) == 6:
            tr, quat = model.transform_parts(geometry.pose_to_matrix(goal))
            self._log(f"{root}/goal", rr.Transform3D(translation=tr, quaternion=rr.Quaternion(xyzw=quat)),
                      rr.TransformAxes3D(0.04))
            q = kinematics.solve_near(drawn.arm.model, goal, drawn.arm.q, drawn.arm.tcp_offset)
            if q is not None:
                caps = drawn.arm.capsules(q)
                self._log(f"{root}/arm", rr.Capsules3D(lengths=caps.lengths, radii=caps.radii * 0.9,
                                                       translations=caps.translations, quaternions=caps.quaternions,
                                                       colors=[colour]))

    def _tick(self, now: float) -> None:
        """Grey force arrows whose sensor went silent (no force sample for ``stale_after``); clear pictures and
        markers not renewed for ``media_stale_after`` (the edge, the link or the gates may be why: a frozen picture
        must not read as live) and preview ghosts whose token expired, each with a line in the events."""
        stale_after = self.config.viewer.stale_after
        media_after = self.config.viewer.media_stale_after
        for robot, drawn in self._robots.items():
            events = f"robots/{robot}/events"
            names = self._media_paths(robot)
            for path, seen in list(drawn.media_seen.items()):
                if now - seen > media_after:
                    self._set_twin_time(drawn, path, f"{path}/axes", events)
                    self._clear_media(drawn, path)
                    self._log(events, rr.TextLog(f"{names.get(path, path)} cleared: nothing new for {now - seen:.1f} s",
                                                 level="WARN"))
            if now >= drawn.preview_until:
                drawn.preview_until = math.inf
                self._set_twin_time(drawn, *self._preview_paths(robot), events)
                self._log(f"robots/{robot}/preview", rr.Clear(recursive=True))
                self._log(events, rr.TextLog("preview ghost removed: its plan expired (preview again)", level="INFO"))
            if not drawn.arrow_grey and now - drawn.last_force_mono > stale_after:
                self._set_twin_time(drawn, f"robots/{robot}/tcp/force")
                self._draw_arrow(robot, drawn, True)


__all__ = ["ForceBatcher", "RateGate", "Visualizer", "VizFeeder", "VizItem", "blueprint"]
