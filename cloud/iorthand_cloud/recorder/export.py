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
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
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
from iorthand_cloud.recorder.export_ros2 import H264Sync
from iorthand_cloud.recorder.reader import iter_records, read_manifest, session_dir

LEVEL_COLOURS = {0: (0, 170, 0, 255), 1: (230, 190, 0, 255), 2: (220, 0, 0, 255)}


def export_rrd(session: str | Path, out: str | Path | None = None, start: float | None = None,
               end: float | None = None, video_fps: float = 5.0) -> tuple[Path, int]:
    """Write the .rrd; ``start``/``end`` are seconds from the session's first message. Returns (path, logged)."""
    folder = session_dir(session)
    manifest = read_manifest(folder)
    path = Path(out) if out else folder / f"{manifest.session_id}.rrd"
    first = next(iter_records(folder), None)
    t0 = first.log_time if first else 0
    lo = t0 + int(start * 1e9) if start is not None else None
    hi = t0 + int(end * 1e9) if end is not None else None
    rec = rr.RecordingStream("iorthand_session", recording_id=manifest.session_id)
    rec.save(str(path))
    ann_key = keys.service_key(keys.RECORDER, keys.RECORDER_ANNOTATIONS)
    paths: dict[str, list[list[float]]] = {}
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
        cls = message_type_for(r.key)
        if cls is None:
            continue
        try:
            msg = cls.decode(r.data)
        except DecodeError:
            continue
        robot, suffix = keys.split_key(r.key)
        rec.set_time("time", timestamp=np.datetime64(msg.t or r.publish_time, "ns"))  # exact: ns
        base = f"{robot}"
        if isinstance(msg, RobotState):
            p = msg.tcp_pose
            rec.log(f"{base}/world/tcp", rr.Transform3D(translation=p[:3], rotation=rr.RotationAxisAngle(
                axis=p[3:6] if np.linalg.norm(p[3:6]) > 0 else [0, 0, 1], radians=float(np.linalg.norm(p[3:6])))))
            trail = paths.setdefault(robot, [])
            trail.append(list(p[:3]))
            if len(trail) % 25 == 0:  # the path, at 5 Hz: enough to see it, cheap to store
                rec.log(f"{base}/world/path", rr.LineStrips3D([trail[-2000:]]))
            for i, axis in enumerate("xyz"):
                rec.log(f"{base}/tcp/{axis}", rr.Scalars(p[i]))
        elif isinstance(msg, ForceSample):
            for i, axis in enumerate("xyz"):
                rec.log(f"{base}/force/f{axis}", rr.Scalars(msg.force[i]))
            rec.log(f"{base}/force/norm", rr.Scalars(float(np.linalg.norm(msg.force))))
        elif isinstance(msg, ForceLevelState):
            rec.log(f"{base}/force/level", rr.Scalars(-1.0 if msg.stale else float(msg.level)))
        elif isinstance(msg, Markers):
            if msg.markers:
                pts = [[m.pose[3], m.pose[7], m.pose[11]] for m in msg.markers]
                rec.log(f"{base}/world/markers", rr.Points3D(pts, labels=[str(m.id) for m in msg.markers],
                                                             radii=0.005))
        elif isinstance(msg, SafetyStatus):
            if last_status.get(robot) != msg.status:
                last_status[robot] = msg.status
                rec.log(f"{base}/safety", rr.TextLog(f"{msg.status}: {msg.reason}", level="WARN"
                                                     if msg.status not in ("ok", "idle") else "INFO"))
        elif isinstance(msg, VideoFrame):
            period = int(1e9 / video_fps) if video_fps > 0 else 0
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
