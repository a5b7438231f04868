"""``iorthand export SESSION``: a session (or a time range of it) as a rerun ``.rrd`` file for viewing.

Decoded with the protocol classes and logged on a ``time`` timeline (the messages' source times): the tool
pose and path, forces and warning levels as time series, markers as points, camera frames as JPEG images or
an H.264 video stream, annotations and safety-state changes as text logs. JPEG video is thinned to
``video_fps`` (rerun holds every frame in memory). H.264 cannot be thinned (a P-frame needs every frame back to
its keyframe): each stream is logged as a ``VideoStream`` (its codec once, static; then every access unit as a
sample, which the viewer decodes), from its first keyframe in the exported range on; after a failure notice or
a frame missing from the recording, from the next keyframe (:class:`~iorthand_cloud.recorder.export_ros2.H264Sync`).
A failure notice clears the picture (no frozen picture that reads as live), and so does a missing frame. Nothing
is logged from a Zenoh callback: this is an offline conversion.

The time series, poses, path and markers (nearly every row of a session) are sent with rerun's columnar API:
one ``send_columns`` per entity and batch of rows (:class:`_Columns`), where a ``log`` per row costs ~0.2 ms
of Python. Text logs, pictures and video samples are logged one by one, as they come.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import rerun as rr

from iorthand import keys
from iorthand.protocol import (
    Annotation,
    DecodeError,
    ForceLevelState,
    ForceSample,
    Markers,
    RobotState,
    SafetyStatus,
    VideoFrame,
    message_type_for,
    source_news,
)
from iorthand_cloud.recorder.export_ros2 import H264Sync, export_target
from iorthand_cloud.recorder.reader import iter_records

LEVEL_COLOURS = {0: (0, 170, 0, 255), 1: (230, 190, 0, 255), 2: (220, 0, 0, 255)}
BATCH_ROWS = 4096  # rows of one entity per send_columns
PATH_EVERY, PATH_POINTS, PATH_BATCH = 25, 2000, 100  # the path: each 25th pose (5 Hz), its last 2000 points
MARKER_RADIUS = 0.005

# What the export logs of each message type (the others are not decoded at all).
_HANDLED = (RobotState, ForceSample, ForceLevelState, Markers, SafetyStatus, VideoFrame)


class _Columns:
    """The rows of one entity (source time, row), sent with ``send_columns`` when ``batch`` are pending and at
    the end (:meth:`flush`). ``build`` turns the pending rows into the archetype's component columns. Each row
    gets the ``time`` of its message and, as ``log`` would stamp it, the ``log_time`` of its sending."""

    def __init__(self, rec: rr.RecordingStream, path: str, build: Callable[[list[Any]], Any],
                 batch: int | None = None) -> None:
        self.rec, self.path, self.build, self.batch = rec, path, build, batch or BATCH_ROWS
        self.times: list[int] = []
        self.rows: list[Any] = []

    def add(self, t: int, row: Any) -> None:
        self.times.append(t)
        self.rows.append(row)
        if len(self.rows) >= self.batch:
            self.flush()

    def flush(self) -> None:
        if not self.rows:
            return
        indexes = [rr.TimeColumn("time", timestamp=np.array(self.times, dtype="datetime64[ns]")),
                   rr.TimeColumn("log_time", timestamp=np.full(len(self.rows), time.time_ns(), "datetime64[ns]"))]
        self.rec.send_columns(self.path, indexes=indexes, columns=self.build(self.rows))
        self.times, self.rows = [], []


def _scalars(rows: list[float]) -> Any:
    return rr.Scalars.columns(scalars=np.array(rows, dtype=np.float64))


_AXIS_ANGLE = rr.components.RotationAxisAngleBatch._ARROW_DATATYPE


def _transforms(rows: list[tuple[Any, Any, float]]) -> Any:
    """Rows of (translation, rotation axis, radians): as ``Transform3D(translation, RotationAxisAngle(...))``."""
    n = len(rows)
    translation = np.array([r[0] for r in rows], dtype=np.float32).reshape(n, 3)
    axis = np.array([r[1] for r in rows], dtype=np.float32).reshape(-1)
    radians = np.array([r[2] for r in rows], dtype=np.float32)
    axes = pa.FixedSizeListArray.from_arrays(pa.array(axis), type=_AXIS_ANGLE.field(0).type)
    rotation = pa.StructArray.from_arrays([axes, pa.array(radians)], fields=list(_AXIS_ANGLE))
    return rr.Transform3D.columns(translation=translation, rotation_axis_angle=rotation)


def _paths(rows: list[np.ndarray]) -> Any:
    """Rows of one strip each: as ``LineStrips3D([strip])``."""
    return rr.LineStrips3D.columns(strips=rows)


def _points(rows: list[tuple[list[list[float]], list[str]]]) -> Any:
    """Rows of (positions, labels): as ``Points3D(positions, labels=labels, radii=MARKER_RADIUS)``."""
    positions = np.array([xyz for pts, _ in rows for xyz in pts], dtype=np.float32).reshape(-1, 3)
    labels = [label for _, ls in rows for label in ls]
    cols = rr.Points3D.columns(positions=positions, labels=labels).partition([len(pts) for pts, _ in rows])
    radii = rr.Points3D.columns(radii=np.full(len(rows), MARKER_RADIUS, dtype=np.float32))  # one per row
    return [*cols, *radii]


class _Trail:
    """The latest ``PATH_POINTS`` tool positions of one robot, and how many it had in all."""

    def __init__(self) -> None:
        self.count = 0
        self._buf = np.empty((2 * PATH_POINTS, 3))
        self._end = 0

    def add(self, xyz: list[float]) -> None:
        if self._end == len(self._buf):
            self._buf[:PATH_POINTS] = self._buf[-PATH_POINTS:]
            self._end = PATH_POINTS
        self._buf[self._end] = xyz
        self._end += 1
        self.count += 1

    def points(self) -> np.ndarray:
        return self._buf[max(0, self._end - PATH_POINTS):self._end].astype(np.float32)


class _Robot:
    """The columnar entities of one robot."""

    def __init__(self, rec: rr.RecordingStream, robot: str) -> None:
        def col(path: str, build: Callable[[list[Any]], Any] = _scalars, batch: int | None = None) -> _Columns:
            return _Columns(rec, f"{robot}/{path}", build, batch)

        self.tcp = col("world/tcp", _transforms)
        self.path = col("world/path", _paths, PATH_BATCH)
        self.trail = _Trail()
        self.tcp_xyz = [col(f"tcp/{axis}") for axis in "xyz"]
        self.force = [col(f"force/f{axis}") for axis in "xyz"]
        self.force_norm = col("force/norm")
        self.level = col("force/level")
        self.markers = col("world/markers", _points)

    def all(self) -> list[_Columns]:
        return [self.tcp, self.path, *self.tcp_xyz, *self.force, self.force_norm, self.level, self.markers]


def export_rrd(session: str | Path, out: str | Path | None = None, start: float | None = None,
               end: float | None = None, video_fps: float = 5.0) -> tuple[Path, int]:
    """Write the .rrd; ``start``/``end`` are seconds from the session's first message. Returns (path, logged)."""
    # As the other exports: a killed recorder's session repaired first, never over a file that exists.
    folder, manifest, path = export_target(session, out, "rrd", default="{session_id}.rrd")
    first = next(iter_records(folder), None)
    t0 = first.log_time if first else 0
    lo = t0 + int(start * 1e9) if start is not None else None
    hi = t0 + int(end * 1e9) if end is not None else None
    rec = rr.RecordingStream("iorthand_session", recording_id=manifest.session_id)
    rec.save(str(path))
    ann_key = keys.service_key(keys.RECORDER, keys.RECORDER_ANNOTATIONS)
    period = int(1e9 / video_fps) if video_fps > 0 else 0
    types: dict[str, type | None] = {}  # per key: its message class, if the export logs it
    robots: dict[str, _Robot] = {}
    last_frame: dict[str, int] = {}
    last_status: dict[str, str] = {}
    video_failure: dict[str, str] = {}  # per key: the failure of its latest frame ("" = pictures)
    h264: dict[str, H264Sync] = {}  # per key of an H.264 stream: which of its frames a decoder can take
    video_streams: set[str] = set()  # entity paths whose VideoStream codec is logged
    logged = 0
    for r in iter_records(folder, lo, hi):
        if r.malformed:
            continue
        if r.key == ann_key:
            try:
                a = Annotation.decode(r.data)
            except DecodeError:
                continue
            rec.set_time("time", timestamp=np.datetime64(a.t or r.log_time, "ns"))
            tags = f" [{', '.join(a.tags)}]" if a.tags else ""
            score = f" score {a.score}" if a.score is not None else ""
            rec.log("annotations", rr.TextLog(f"{a.author}: {a.text}{tags}{score}", level="INFO"))
            logged += 1
            continue
        if r.key in types:
            cls = types[r.key]
        else:
            cls = message_type_for(r.key)
            cls = types[r.key] = cls if cls is not None and issubclass(cls, _HANDLED) else None
        if cls is None:
            continue
        try:
            msg = cls.decode(r.data)
        except DecodeError:
            continue
        robot, suffix = keys.split_key(r.key)
        when = msg.t or r.publish_time  # exact: ns
        base = f"{robot}"
        cols = robots.get(robot)
        if cols is None:
            cols = robots[robot] = _Robot(rec, robot)
        if isinstance(msg, RobotState):
            p = msg.tcp_pose
            norm = np.linalg.norm(p[3:6])
            cols.tcp.add(when, (p[:3], p[3:6] if norm > 0 else [0, 0, 1], float(norm)))
            cols.trail.add(p[:3])
            if cols.trail.count % PATH_EVERY == 0:  # the path, at 5 Hz: enough to see it, cheap to store
                cols.path.add(when, cols.trail.points())
            for i in range(3):
                cols.tcp_xyz[i].add(when, p[i])
        elif isinstance(msg, ForceSample):
            for i in range(3):
                cols.force[i].add(when, msg.force[i])
            cols.force_norm.add(when, float(np.linalg.norm(msg.force)))
        elif isinstance(msg, ForceLevelState):
            cols.level.add(when, -1.0 if msg.stale else float(msg.level))
        elif isinstance(msg, Markers):
            if msg.markers:
                cols.markers.add(when, ([[m.pose[3], m.pose[7], m.pose[11]] for m in msg.markers],
                                        [str(m.id) for m in msg.markers]))
        elif isinstance(msg, SafetyStatus):
            if last_status.get(robot) != msg.status:
                last_status[robot] = msg.status
                rec.set_time("time", timestamp=np.datetime64(when, "ns"))
                rec.log(f"{base}/safety", rr.TextLog(f"{msg.status}: {msg.reason}", level="WARN"
                                                     if msg.status not in ("ok", "idle") else "INFO"))
        elif isinstance(msg, VideoFrame):
            rec.set_time("time", timestamp=np.datetime64(when, "ns"))
            news = source_news(f"{msg.source} video", video_failure.get(r.key, ""), msg.failure)
            video_failure[r.key] = msg.failure
            if news:
                rec.log(f"{base}/events", rr.TextLog(news, level="WARN" if msg.failure else "INFO"))
            if msg.encoding == "h264":
                if not _log_h264(rec, f"{base}/{suffix}", f"{base}/events", h264.setdefault(r.key, H264Sync()),
                                 msg, video_streams):
                    continue
            elif msg.failure:  # no picture rather than a frozen one
                rec.log(f"{base}/{suffix}", rr.Clear(recursive=False))
            elif msg.t - last_frame.get(r.key, -period) >= period and msg.encoding == "jpeg":
                last_frame[r.key] = msg.t
                rec.log(f"{base}/{suffix}", rr.EncodedImage(contents=msg.data, media_type="image/jpeg"))
            else:
                continue
        else:
            continue
        logged += 1
    for cols in robots.values():
        for c in cols.all():
            c.flush()
    rec.flush()
    rec.disconnect()  # closes the file sink: the .rrd is complete when we return
    return path, logged


def _log_h264(rec: rr.RecordingStream, path: str, events: str, sync: H264Sync, msg: VideoFrame,
              streams: set[str]) -> bool:
    """One frame (or failure notice) of an H.264 stream at ``path``; whether anything was logged (``streams``:
    the paths whose codec is logged already)."""
    was_synced = sync.synced
    ok = sync.admit(msg)
    lost = bool(sync.missing) and was_synced
    if lost:
        rec.log(events, rr.TextLog(f"{msg.source} video: {sync.missing} frame(s) missing before frame {msg.seq}: "
                                   "no picture until the next keyframe", level="WARN"))
    if msg.failure or lost:  # no picture rather than a frozen one
        rec.log(path, rr.Clear(recursive=False))
    if ok:
        if path not in streams:  # the codec once (static), then each access unit as a sample
            rec.log(path, rr.VideoStream(codec=rr.VideoCodec.H264), static=True)
            streams.add(path)
        rec.log(path, rr.VideoStream.from_fields(sample=msg.data, is_keyframe=msg.keyframe))
    return ok or msg.failure != "" or lost
