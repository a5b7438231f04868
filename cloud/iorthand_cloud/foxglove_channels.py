"""iorthand messages → Foxglove's well-known schemas: the one conversion the recorder and the twin share.

The recorder writes these channels into ``<session>/foxglove/foxglove-NNNN.mcap`` beside its raw msgpack
segments (which stay the source of truth); the twin serves the same channels live over the Foxglove WebSocket
protocol. Everything here is pure: a decoded :mod:`iorthand.protocol` message in, serialized Foxglove
messages out (:class:`FoxgloveConverter` keeps the little state that "on change" needs). No I/O.

Topics, per robot id ``<robot>`` (the raw key each is made from in brackets):

==========================  ==============================================  ==========================================
topic                       schema                                          made from
==========================  ==============================================  ==========================================
``/<robot>/tf``             ``foxglove.FrameTransforms``                    every ``state/robot``: base → tcp
``/<robot>/probe``          ``foxglove.SceneUpdate``                        ``state/force`` at most every 40 ms (and
                                                                            at each level change): the probe body
                                                                            and the force arrow at the tcp, coloured
                                                                            by the latest force level (grey: stale)
``/<robot>/markers``        ``foxglove.SceneUpdate``                        every ``markers``: one tile and label per
                                                                            marker seen; the previous ones deleted
``/<robot>/markers/tf``     ``foxglove.FrameTransforms``                    every ``markers`` with at least one
                                                                            marker: base → marker_<id>
``/<robot>/camera``         ``foxglove.CompressedImage`` (jpeg, png) or     every ``video/camera`` frame with a
                            ``foxglove.CompressedVideo`` (h264, h265:       picture; for a failure notice (no
                            one Annex B access unit per message)            picture) a "VIDEO FAILED" one, at most
                                                                            every NOTICE_INTERVAL_NS per failure
``/<robot>/ultrasound``     as ``camera``                                   every ``video/ultrasound`` frame
``/<robot>/force``          JSON ``iorthand.Force`` (fx fy fz tx ty tz      every ``state/force`` (Plot panel)
                            norm, N and N·m)
``/<robot>/force_level``    JSON ``iorthand.ForceLevel`` (level 0/1/2,      every ``state/force_level`` (Plot panel)
                            stale, value, caution, danger)
``/<robot>/safety``         ``foxglove.Log``                                ``state/safety`` when its status changes
                                                                            (the first one too), with the reason
``/<robot>/refusals``       ``foxglove.Log``                                ``state/applied`` not accepted: status and
                                                                            reason of the refused command
``/<robot>/events``         ``foxglove.Log``                                a video source or the perception failing
                                                                            or coming back (``failure`` changes)
``/annotations``            ``foxglove.Log``                                every annotation (``iorthand annotate``;
                                                                            the recorder only)
==========================  ==============================================  ==========================================

Frames (ROS REP-103: x forward, y left, z up, metres; a transform's translation and rotation place the child
frame in the parent frame). Every frame id is prefixed with the robot id, like a ROS ``tf_prefix``, so that
several robots (and their ``-replay`` ids) never share a tree:

- ``<robot>/base``: the robot's base frame (UR's ``base``, as the controller reports poses in), the root;
- ``<robot>/tcp``: the tool centre point, the probe's tip, from ``RobotState.tcp_pose`` (UR pose: metres and a
  rotation vector); the probe body is drawn along −z of it, back toward the flange, as in the twin;
- ``<robot>/marker_<id>``: a patient marker, from ``Markers`` (4×4 row-major ``T_base_marker``);
- ``<robot>/camera``, ``<robot>/ultrasound``: the ``frame_id`` of the images (no transform is published for
  them: the camera's pan/tilt chain is the edge's calibration).

A video failure notice has no picture, and an image panel keeps the last one it was given: frozen, as if live
(in a recording too, where the failure then shows nowhere but in the events log). So the converter puts a
picture on the image topic for it (``failure_pictures``): a dark one that says "VIDEO FAILED" with the reason and
since when (:func:`failure_picture`), as a JPEG, or for an H.264 stream as one H.264 keyframe of the stream's
size (a viewer decodes it without the frames before it).

Message timestamps are the source times (``t``) of the iorthand messages; the MCAP ``log_time`` the recorder
writes is its receive time, as for the raw channels. A failure picture, drawn at most every NOTICE_INTERVAL_NS,
is timed by the receiver's clock (:meth:`FoxgloveConverter.convert`'s ``recv_ns``), never by the sender's ``t``: an
edge's clock that steps back would draw one for every notice, one that stands still (or jumped ahead) no more.
"""

from __future__ import annotations

import datetime as dt
import functools
import io
import json
import math
import textwrap
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any

from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.descriptor import FileDescriptor
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.message import Message as ProtoMessage
from PIL import Image, ImageDraw, ImageFont

from iorthand import geometry, keys
from iorthand.protocol import (
    Annotation,
    AppliedCommand,
    ForceLevel,
    ForceLevelState,
    ForceSample,
    Markers,
    Message,
    RobotState,
    SafetyStatus,
    Status,
    VideoFrame,
    source_news,
)

# Channel metadata that marks a Foxglove channel and names the raw key it is made from.
SOURCE_META = "iorthand.source"

# Topic names under /<robot>/.
TF = "tf"
PROBE = "probe"
MARKERS = "markers"
MARKERS_TF = "markers/tf"
FORCE = "force"
FORCE_LEVEL = "force_level"
SAFETY = "safety"
REFUSALS = "refusals"
EVENTS = "events"
ANNOTATIONS_TOPIC = "/annotations"
ANNOTATIONS_KEY = keys.service_key(keys.RECORDER, keys.RECORDER_ANNOTATIONS)
VIDEO_TOPICS = {keys.VIDEO_CAMERA: "camera", keys.VIDEO_ULTRASOUND: "ultrasound"}

# Frame names under <robot>/.
BASE_FRAME = "base"
TCP_FRAME = "tcp"

# VideoFrame.encoding → the ``format`` of a CompressedImage (pictures) or a CompressedVideo (a video stream).
# Foxglove decodes H.264/H.265 from Annex B access units; a key frame must carry its SPS/PPS in-band (the edge's
# encoder's job), and a viewer starts at a key frame.
IMAGE_FORMATS = {"jpeg": "jpeg", "png": "png", "webp": "webp"}
VIDEO_FORMATS = {"h264": "h264", "h265": "h265"}

# Drawing: the same sizes the twin's rerun view uses (twin.config.RobotView.probe_length, viz.FORCE_SCALE).
PROBE_LENGTH = 0.10  # m, along −z of the tcp
PROBE_DIAMETER = 0.024
FORCE_SCALE = 0.01  # m of arrow per N
# 25 Hz of arrow is plenty for the 3D view (the force plot keeps every sample); at the sensor's 100 Hz the probe
# would double the Foxglove messages a force stream makes, and the recorder pays per message.
PROBE_PERIOD_NS = 40_000_000
MARKER_SIZE = 0.04  # m: the tile drawn for a marker (its real size is the edge's configuration)
LEVEL_COLOURS: dict[int, tuple[float, float, float, float]] = {
    ForceLevel.SAFE: (0.0, 0.67, 0.0, 1.0), ForceLevel.CAUTION: (0.9, 0.75, 0.0, 1.0),
    ForceLevel.DANGER: (0.86, 0.0, 0.0, 1.0),
}
STALE_COLOUR = (0.5, 0.5, 0.5, 1.0)
PROBE_COLOUR = (0.85, 0.85, 0.9, 1.0)
MARKER_COLOUR = (0.1, 0.4, 0.9, 0.8)

# Failure notice pictures.
NOTICE_MAX_SIDE = 4096  # px: a notice claiming a bigger frame is drawn at most this big (it is only text)
# At most one notice picture per stream this often, of receive time: the edge's source retries every second or
# so, and a flood of notices must not keep the converter drawing (viewers that join still see one soon).
NOTICE_INTERVAL_NS = 500_000_000

Quaternion = tuple[float, float, float, float]  # x, y, z, w (Foxglove's order)


def topic(robot: str, name: str) -> str:
    return f"/{robot}/{name}"


def frame_id(robot: str, name: str) -> str:
    return f"{robot}/{name}"


def marker_frame(robot: str, marker_id: int) -> str:
    return frame_id(robot, f"marker_{marker_id}")


# ---------------------------------------------------------------------------------------------------------
# Channels and their schemas


@dataclass(frozen=True)
class FoxgloveChannel:
    """One Foxglove channel: its topic, how its messages are encoded, the schema, and the raw key it comes from."""

    topic: str
    schema_name: str
    schema_encoding: str  # "protobuf" or "jsonschema"
    schema: bytes = field(repr=False)
    message_encoding: str  # "protobuf" or "json"
    source: str  # the iorthand key its messages are made from

    @property
    def metadata(self) -> dict[str, str]:
        return {SOURCE_META: self.source}


@dataclass(frozen=True)
class FoxgloveMessage:
    channel: FoxgloveChannel
    data: bytes
    t: int  # source time, ns


def file_descriptor_set(cls: type[ProtoMessage]) -> bytes:
    """The schema of a protobuf message class as MCAP and the Foxglove protocol want it: a FileDescriptorSet
    of its file and every file it imports, dependencies first."""
    fds = FileDescriptorSet()
    seen: set[str] = set()

    def add(fd: FileDescriptor) -> None:
        for dep in fd.dependencies:
            if dep.name not in seen:
                seen.add(dep.name)
                add(dep)
        fd.CopyToProto(fds.file.add())

    add(cls.DESCRIPTOR.file)
    return fds.SerializeToString()


_NUMBER = {"type": "number"}
FORCE_SCHEMA: dict[str, Any] = {
    "title": "iorthand.Force", "description": "the wrench at the tool (sensor frame), N and N·m, and |F|",
    "type": "object",
    "properties": {"timestamp": {"type": "object", "properties": {"sec": {"type": "integer"},
                                                                   "nsec": {"type": "integer"}}},
                   **{k: _NUMBER for k in ("fx", "fy", "fz", "tx", "ty", "tz", "norm")}},
}
FORCE_LEVEL_SCHEMA: dict[str, Any] = {
    "title": "iorthand.ForceLevel",
    "description": "contact-force warning level 0 safe, 1 caution, 2 danger; stale: no fresh sample (no colour)",
    "type": "object",
    "properties": {"timestamp": FORCE_SCHEMA["properties"]["timestamp"], "level": {"type": "integer"},
                   "stale": {"type": "boolean"}, "value": _NUMBER, "caution": _NUMBER, "danger": _NUMBER,
                   "quantity": {"type": "string"}},
}


@dataclass(frozen=True)
class _Schema:
    name: str
    encoding: str
    data: bytes
    message_encoding: str


def _proto_schema(cls: type[ProtoMessage]) -> _Schema:
    return _Schema(cls.DESCRIPTOR.full_name, "protobuf", file_descriptor_set(cls), "protobuf")


def _json_schema(schema: dict[str, Any]) -> _Schema:
    return _Schema(schema["title"], "jsonschema", json.dumps(schema, sort_keys=True).encode(), "json")


SCHEMAS: dict[str, _Schema] = {
    "FrameTransforms": _proto_schema(FrameTransforms),
    "SceneUpdate": _proto_schema(SceneUpdate),
    "CompressedImage": _proto_schema(CompressedImage),
    "CompressedVideo": _proto_schema(CompressedVideo),
    "Log": _proto_schema(Log),
    "Force": _json_schema(FORCE_SCHEMA),
    "ForceLevel": _json_schema(FORCE_LEVEL_SCHEMA),
}


# ---------------------------------------------------------------------------------------------------------
# Geometry: UR poses and 4×4 matrices → Foxglove translations and quaternions (plain floats: this runs for
# every message, where numpy's per-call overhead costs more than the arithmetic)


def x_axis_to(dx: float, dy: float, dz: float) -> Quaternion:
    """The shortest rotation taking +x onto the unit vector (dx, dy, dz): Foxglove's arrows point along +x."""
    w = 1.0 + dx
    if w < 1e-9:  # pointing along −x: half a turn about z
        return (0.0, 0.0, 1.0, 0.0)
    norm = math.sqrt(w * w + dz * dz + dy * dy)
    return (0.0, -dz / norm, dy / norm, w / norm)


def _stamp(msg: Any, t_ns: int) -> None:
    msg.sec, msg.nsec = divmod(t_ns, 1_000_000_000)


def _timestamp(ts: Any, t_ns: int) -> None:
    ts.seconds, ts.nanos = divmod(t_ns, 1_000_000_000)


def _set_pose(pose: Any, position: Sequence[float], q: Quaternion) -> None:
    pose.position.x, pose.position.y, pose.position.z = position[0], position[1], position[2]
    o = pose.orientation
    o.x, o.y, o.z, o.w = q


def _set_colour(colour: Any, rgba: tuple[float, float, float, float]) -> None:
    colour.r, colour.g, colour.b, colour.a = rgba


# ---------------------------------------------------------------------------------------------------------
# Pure conversions: one iorthand message → one Foxglove message (or None when there is nothing to show)


def robot_transforms(robot: str, msg: RobotState) -> FrameTransforms:
    """base → tcp from the UR pose [x, y, z, rx, ry, rz]."""
    out = FrameTransforms()
    tf = out.transforms.add()
    _timestamp(tf.timestamp, msg.t)
    tf.parent_frame_id, tf.child_frame_id = frame_id(robot, BASE_FRAME), frame_id(robot, TCP_FRAME)
    p = msg.tcp_pose
    tf.translation.x, tf.translation.y, tf.translation.z = p[0], p[1], p[2]
    r = tf.rotation
    r.x, r.y, r.z, r.w = geometry.rotvec_to_quaternion(p[3:6])
    return out


def marker_transforms(robot: str, msg: Markers) -> FrameTransforms | None:
    """base → marker_<id> for every marker of the frame (None: no marker seen)."""
    if not msg.markers:
        return None
    out = FrameTransforms()
    base = frame_id(robot, BASE_FRAME)
    for marker in msg.markers:
        m = marker.pose
        tf = out.transforms.add()
        _timestamp(tf.timestamp, msg.t)
        tf.parent_frame_id, tf.child_frame_id = base, marker_frame(robot, marker.id)
        tf.translation.x, tf.translation.y, tf.translation.z = m[3], m[7], m[11]
        r = tf.rotation
        r.x, r.y, r.z, r.w = geometry.matrix_to_quaternion(m)
    return out


def marker_scene(robot: str, msg: Markers) -> SceneUpdate:
    """The markers seen in one camera frame, drawn in the base frame. Every update first deletes all the
    previous ones: a marker that left the view is no longer drawn (Foxglove applies deletions first)."""
    out = SceneUpdate()
    deletion = out.deletions.add()
    _timestamp(deletion.timestamp, msg.t)
    deletion.type = SceneEntityDeletion.Type.ALL
    base = frame_id(robot, BASE_FRAME)
    for marker in msg.markers:
        m = marker.pose
        q = geometry.matrix_to_quaternion(m)
        position = (m[3], m[7], m[11])
        e = out.entities.add()
        _timestamp(e.timestamp, msg.t)
        e.frame_id, e.id = base, f"marker_{marker.id}"
        meta = e.metadata.add()
        meta.key, meta.value = "reprojection_error_px", f"{marker.reprojection_error:.3f}"
        cube = e.cubes.add()
        _set_pose(cube.pose, position, q)
        cube.size.x, cube.size.y, cube.size.z = MARKER_SIZE, MARKER_SIZE, 0.002
        _set_colour(cube.color, MARKER_COLOUR)
        text = e.texts.add()
        _set_pose(text.pose, (position[0], position[1], position[2] + 0.02), (0.0, 0.0, 0.0, 1.0))
        text.billboard, text.font_size, text.scale_invariant, text.text = True, 14.0, True, f"marker {marker.id}"
        _set_colour(text.color, (1.0, 1.0, 1.0, 1.0))
    return out


def probe_scene(robot: str, msg: ForceSample, level: int | None) -> SceneUpdate:
    """The probe body along −z of the tcp and the force arrow at its tip, fixed to the tcp frame (they move
    with the arm), coloured by the latest force level (``None``: stale or unknown → grey)."""
    out = SceneUpdate()
    e = out.entities.add()
    _timestamp(e.timestamp, msg.t)
    e.frame_id, e.id, e.frame_locked = frame_id(robot, TCP_FRAME), "probe", True
    body = e.cylinders.add()
    _set_pose(body.pose, (0.0, 0.0, -PROBE_LENGTH / 2), (0.0, 0.0, 0.0, 1.0))
    body.size.x, body.size.y, body.size.z = PROBE_DIAMETER, PROBE_DIAMETER, PROBE_LENGTH
    body.bottom_scale = body.top_scale = 1.0
    _set_colour(body.color, PROBE_COLOUR)
    fx, fy, fz = msg.force
    norm = math.sqrt(fx * fx + fy * fy + fz * fz)
    if norm > 1e-6:
        arrow = e.arrows.add()
        _set_pose(arrow.pose, (0.0, 0.0, 0.0), x_axis_to(fx / norm, fy / norm, fz / norm))
        length = norm * FORCE_SCALE
        arrow.head_length = min(0.02, 0.4 * length)
        arrow.shaft_length = length - arrow.head_length
        arrow.shaft_diameter, arrow.head_diameter = 0.004, 0.01
        _set_colour(arrow.color, LEVEL_COLOURS.get(level, STALE_COLOUR) if level is not None else STALE_COLOUR)
    return out


def video_message(robot: str, source: str, msg: VideoFrame) -> CompressedImage | CompressedVideo | None:
    """A frame with a picture → CompressedImage (JPEG, PNG) or CompressedVideo (H.264/H.265 access unit);
    None for a failure notice (no picture) or an encoding Foxglove does not decode."""
    if msg.failure or not msg.data:
        return None
    out: CompressedImage | CompressedVideo
    if msg.encoding in IMAGE_FORMATS:
        out = CompressedImage(format=IMAGE_FORMATS[msg.encoding])
    elif msg.encoding in VIDEO_FORMATS:
        out = CompressedVideo(format=VIDEO_FORMATS[msg.encoding])
    else:
        return None
    _timestamp(out.timestamp, msg.t)
    out.frame_id, out.data = frame_id(robot, source), msg.data
    return out


def notice_image(text: str, width: int, height: int) -> Image.Image:
    """A dark picture of ``width``×``height`` saying ``VIDEO FAILED`` and ``text`` (wrapped to fit)."""
    width, height = max(16, min(width, NOTICE_MAX_SIDE)), max(16, min(height, NOTICE_MAX_SIDE))
    image = Image.new("RGB", (width, height), (40, 0, 0))
    draw = ImageDraw.Draw(image)
    size = max(8, min(width // 24, height // 12))
    font = ImageFont.load_default(size=size)
    lines = ["VIDEO FAILED", *textwrap.wrap(text, max(8, int(width / (0.6 * size)) - 2))]
    y = size
    for i, line in enumerate(lines):
        draw.text((size, y), line, fill=(255, 80, 80) if i == 0 else (235, 235, 235), font=font)
        y += int(1.4 * size)
    return image


@functools.lru_cache(maxsize=16)
def _notice_data(text: str, width: int, height: int, encoding: str) -> bytes:
    """The notice encoded as the stream's frames are (cached: notices repeat at every retry of the source)."""
    image = notice_image(text, width, height)
    if encoding != "h264":
        buf = io.BytesIO()
        image.save(buf, format="JPEG", quality=80)
        return buf.getvalue()
    import av  # only for H.264 streams (imported when first needed: it loads FFmpeg)

    codec = av.CodecContext.create("libx264", "w")
    codec.width, codec.height = image.width // 2 * 2, image.height // 2 * 2  # 4:2:0 wants even sides
    codec.pix_fmt, codec.time_base = "yuv420p", Fraction(1, 1000)
    codec.options = {"preset": "ultrafast", "tune": "zerolatency"}
    frame = av.VideoFrame.from_image(image.crop((0, 0, codec.width, codec.height))).reformat(format="yuv420p")
    frame.pts = 0
    return b"".join(bytes(p) for p in [*codec.encode(frame), *codec.encode(None)])


def failure_picture(robot: str, name: str, msg: VideoFrame, since_ns: int) -> CompressedImage | CompressedVideo:
    """What the image topic ``name`` shows for a failure notice: the failure (failing since ``since_ns``) as a
    picture of the stream's size (a JPEG, or for an H.264 stream a keyframe, which a decoder takes without the
    frames before it)."""
    when = dt.datetime.fromtimestamp(since_ns / 1e9, dt.UTC).strftime("%H:%M:%S UTC")
    text = f"{msg.failure} (since {when}: this is not a live picture)"
    h264 = msg.encoding == "h264"
    out = CompressedVideo(format="h264") if h264 else CompressedImage(format="jpeg")
    out.data = _notice_data(text, msg.width, msg.height, "h264" if h264 else "jpeg")
    _timestamp(out.timestamp, max(msg.t, 0))
    out.frame_id = frame_id(robot, name)
    return out


def _log(name: str, t_ns: int, level: int, text: str) -> Log:
    out = Log(level=level, message=text, name=name)  # type: ignore[arg-type]
    _timestamp(out.timestamp, t_ns)
    return out


def safety_level(status: str) -> int:
    """Log level of a supervisor status: a fault is an error, a state that holds the robot stopped a warning."""
    if status == Status.FAULT:
        return Log.Level.ERROR
    return Log.Level.WARNING if Status.halting(status) else Log.Level.INFO


def safety_log(robot: str, msg: SafetyStatus, previous: str | None) -> Log | None:
    """A log line when the supervisor's status differs from ``previous`` (None: the first one heard)."""
    if msg.status == previous:
        return None
    try:
        meaning = Status(msg.status).message
    except ValueError:  # a newer edge's code: say it as it is
        meaning = ""
    reason = msg.reason or meaning
    text = f"{msg.status}: {reason}" if reason else msg.status
    return _log(f"{robot}/safety", msg.t, safety_level(msg.status), text)


def refusal_log(robot: str, msg: AppliedCommand) -> Log | None:
    """A log line for a command the supervisor did not accept, with its status and reason."""
    if msg.accepted:
        return None
    who = f" from {msg.operator}" if msg.operator else ""
    text = f"command {msg.cmd_seq}{who} refused: {msg.status}" + (f": {msg.reason}" if msg.reason else "")
    return _log(f"{robot}/refusals", msg.t, Log.Level.WARNING, text)


def source_log(robot: str, what: str, t_ns: int, before: str, now: str) -> Log | None:
    """A log line when a source (camera, ultrasound, perception) starts failing, fails otherwise, or recovers."""
    news = source_news(what, before, now)
    if news is None:
        return None
    return _log(f"{robot}/events", t_ns, Log.Level.WARNING if now else Log.Level.INFO, news)


def annotation_log(msg: Annotation) -> Log:
    """An annotation as a log line: author, text, tags and score."""
    tags = f" [{', '.join(msg.tags)}]" if msg.tags else ""
    score = f" (score {msg.score:g})" if msg.score is not None else ""
    return _log(msg.author or "annotation", msg.t, Log.Level.INFO, f"{msg.text}{tags}{score}")


def _ts(t_ns: int) -> dict[str, int]:
    sec, nsec = divmod(t_ns, 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def force_sample(msg: ForceSample) -> dict[str, Any]:
    """One plottable force sample (Plot panel: ``/<robot>/force.fz``, ``.norm``...)."""
    fx, fy, fz = msg.force
    tx, ty, tz = msg.torque
    return {"timestamp": _ts(msg.t), "fx": fx, "fy": fy, "fz": fz, "tx": tx, "ty": ty, "tz": tz,
            "norm": math.sqrt(fx * fx + fy * fy + fz * fz)}


def force_level_sample(msg: ForceLevelState) -> dict[str, Any]:
    return {"timestamp": _ts(msg.t), "level": msg.level, "stale": msg.stale, "value": msg.value,
            "caution": msg.caution, "danger": msg.danger, "quantity": msg.quantity}


# ---------------------------------------------------------------------------------------------------------
# The converter: dispatch by key, the state "on change" needs, serialization


Handler = Callable[[str, str, Any], list[FoxgloveMessage]]


class FoxgloveConverter:
    """Turns decoded messages into serialized Foxglove messages. One instance per thread: it keeps per-robot
    state (the last safety status, the last force level, each source's last failure) and caches channels.

    ``video=False`` leaves camera and ultrasound pictures out (they double the disk a recording takes);
    ``failure_pictures=False`` leaves out the picture that replaces the last frame at a video failure notice
    (for a caller that draws its own)."""

    # The raw key suffixes that have a Foxglove channel; the twin subscribes to exactly these.
    SUFFIXES: tuple[str, ...] = (
        keys.STATE_ROBOT, keys.STATE_FORCE, keys.STATE_FORCE_LEVEL, keys.STATE_SAFETY, keys.STATE_APPLIED,
        keys.MARKERS, keys.VIDEO_CAMERA, keys.VIDEO_ULTRASOUND,
    )

    def __init__(self, video: bool = True, failure_pictures: bool = True) -> None:
        self.video = video
        self.failure_pictures = failure_pictures
        self._channels: dict[tuple[str, str], FoxgloveChannel] = {}
        self._routes: dict[str, tuple[str, Handler] | None] = {}
        self._safety: dict[str, str] = {}
        self._level: dict[str, int | None] = {}
        self._probe: dict[str, tuple[int, int | None]] = {}  # robot → (receive time, level) of its last probe
        self._failure: dict[str, str] = {}
        # video key → (its failure, source time of its first notice, receive time of the last notice drawn)
        self._notices: dict[str, tuple[str, int, int]] = {}
        self._received = 0  # receive time (ns) of the message being converted: see convert()
        self._handlers: dict[str, Handler] = {
            keys.STATE_ROBOT: self._robot, keys.STATE_FORCE: self._force, keys.STATE_FORCE_LEVEL: self._force_level,
            keys.STATE_SAFETY: self._safety_status, keys.STATE_APPLIED: self._applied, keys.MARKERS: self._markers,
            **{suffix: functools.partial(self._video, name) for suffix, name in VIDEO_TOPICS.items()},
        }

    def handles(self, key: str) -> bool:
        """Whether messages on ``key`` can make Foxglove messages (cheap: the caller may skip decoding)."""
        return self._route(key) is not None

    def convert(self, key: str, msg: Message, recv_ns: int | None = None) -> list[FoxgloveMessage]:
        """The Foxglove messages made from ``msg`` received on ``key`` (often one, sometimes none).

        ``recv_ns`` times the failure pictures: when ``msg`` was received, on a clock of the receiver's (a
        recording's log time: converting the same recording again then makes the same pictures). None: now, on this
        process's monotonic clock (a live view). The sender's ``t`` does not time them: it is the edge's to set."""
        route = self._route(key)
        if route is None:
            return []
        self._received = time.monotonic_ns() if recv_ns is None else recv_ns
        robot, handler = route
        return handler(robot, key, msg)

    def _route(self, key: str) -> tuple[str, Handler] | None:
        try:
            return self._routes[key]
        except KeyError:
            pass
        route: tuple[str, Handler] | None = None
        if key == ANNOTATIONS_KEY:
            return (ANNOTATIONS_KEY, self._annotation)
        try:
            robot, suffix = keys.split_key(key)
            handler = self._handlers.get(suffix)
            if handler is not None and (self.video or suffix not in VIDEO_TOPICS):
                route = (robot, handler)
        except keys.KeyExprError:
            pass
        if len(self._routes) < 10_000:  # keys come from the network: never an unbounded cache
            self._routes[key] = route
        return route

    def channel(self, robot: str, name: str, schema: str, source: str) -> FoxgloveChannel:
        """The channel of topic ``/<robot>/<name>`` (``robot`` empty: ``/<name>``) with ``schema``; one per pair:
        a topic made from several keys, such as ``events``, is one channel, and ``source`` names them all."""
        k = (topic(robot, name) if robot else f"/{name}", schema)
        ch = self._channels.get(k)
        if ch is None:
            s = SCHEMAS[schema]
            ch = self._channels[k] = FoxgloveChannel(k[0], s.name, s.encoding, s.data, s.message_encoding, source)
        return ch

    def _proto(self, robot: str, name: str, schema: str, key: str, msg: ProtoMessage, t: int) -> FoxgloveMessage:
        return FoxgloveMessage(self.channel(robot, name, schema, key), msg.SerializeToString(), t)

    def _json(self, robot: str, name: str, schema: str, key: str, data: dict[str, Any], t: int) -> FoxgloveMessage:
        return FoxgloveMessage(self.channel(robot, name, schema, key), json.dumps(data).encode(), t)

    def _annotation(self, _: str, key: str, msg: Annotation) -> list[FoxgloveMessage]:
        return [self._proto("", ANNOTATIONS_TOPIC[1:], "Log", key, annotation_log(msg), msg.t)]

    def _robot(self, robot: str, key: str, msg: RobotState) -> list[FoxgloveMessage]:
        return [self._proto(robot, TF, "FrameTransforms", key, robot_transforms(robot, msg), msg.t)]

    def _force(self, robot: str, key: str, msg: ForceSample) -> list[FoxgloveMessage]:
        out = [self._json(robot, FORCE, "Force", key, force_sample(msg), msg.t)]
        level, last = self._level.get(robot), self._probe.get(robot)
        # At most every PROBE_PERIOD_NS of receive time (as the failure pictures: an edge's clock that steps back
        # would draw one per sample), at once when the colour changes.
        if last is None or last[1] != level or not 0 <= self._received - last[0] < PROBE_PERIOD_NS:
            self._probe[robot] = (self._received, level)
            out.append(self._proto(robot, PROBE, "SceneUpdate", key, probe_scene(robot, msg, level), msg.t))
        return out

    def _force_level(self, robot: str, key: str, msg: ForceLevelState) -> list[FoxgloveMessage]:
        self._level[robot] = None if msg.stale else msg.level
        return [self._json(robot, FORCE_LEVEL, "ForceLevel", key, force_level_sample(msg), msg.t)]

    def _safety_status(self, robot: str, key: str, msg: SafetyStatus) -> list[FoxgloveMessage]:
        log = safety_log(robot, msg, self._safety.get(robot))
        self._safety[robot] = msg.status
        return [] if log is None else [self._proto(robot, SAFETY, "Log", key, log, msg.t)]

    def _applied(self, robot: str, key: str, msg: AppliedCommand) -> list[FoxgloveMessage]:
        log = refusal_log(robot, msg)
        return [] if log is None else [self._proto(robot, REFUSALS, "Log", key, log, msg.t)]

    def _markers(self, robot: str, key: str, msg: Markers) -> list[FoxgloveMessage]:
        out = [self._proto(robot, MARKERS, "SceneUpdate", key, marker_scene(robot, msg), msg.t)]
        tfs = marker_transforms(robot, msg)
        if tfs is not None:
            out.append(self._proto(robot, MARKERS_TF, "FrameTransforms", key, tfs, msg.t))
        out.extend(self._source_news(robot, key, "perception", msg.t, msg.failure))
        return out

    def _video(self, name: str, robot: str, key: str, msg: VideoFrame) -> list[FoxgloveMessage]:
        out = self._source_news(robot, key, f"{msg.source} video", msg.t, msg.failure)
        frame = video_message(robot, name, msg)
        if frame is None and self.failure_pictures and (since := self._notice_due(key, msg)) is not None:
            frame = failure_picture(robot, name, msg, since)
        if frame is not None:
            schema = "CompressedImage" if isinstance(frame, CompressedImage) else "CompressedVideo"
            out.insert(0, self._proto(robot, name, schema, key, frame, msg.t))
        return out

    def _notice_due(self, key: str, msg: VideoFrame) -> int | None:
        """For a failure notice whose picture is due, when the failure began (its first notice's source time, as
        the picture says); None for a frame, or for a notice received within NOTICE_INTERVAL_NS of the last picture
        drawn for the same failure. A receive clock that went back (log times out of order) draws afresh."""
        if not msg.failure:
            self._notices.pop(key, None)
            return None
        received = self._received
        reason, since, drawn = self._notices.get(key, ("", msg.t, received))
        if msg.failure != reason:
            since = msg.t
        elif 0 <= received - drawn < NOTICE_INTERVAL_NS:
            return None
        if len(self._notices) >= 1000:  # keys come from the network: never an unbounded table
            self._notices.clear()
        self._notices[key] = (msg.failure, since, received)
        return since

    def _source_news(self, robot: str, key: str, what: str, t: int, failure: str) -> list[FoxgloveMessage]:
        log = source_log(robot, what, t, self._failure.get(key, ""), failure)
        self._failure[key] = failure
        # One events channel per robot, whatever source speaks: its source is every key of the robot.
        return [] if log is None else [self._proto(robot, EVENTS, "Log", keys.RobotKeys(robot).all, log, t)]


__all__ = [
    "SCHEMAS", "SOURCE_META", "FoxgloveChannel", "FoxgloveConverter", "FoxgloveMessage", "annotation_log",
    "failure_picture", "file_descriptor_set", "force_level_sample", "force_sample", "frame_id", "marker_scene",
    "marker_transforms", "notice_image", "probe_scene", "refusal_log", "robot_transforms", "safety_log",
    "source_log", "topic",
    "video_message", "x_axis_to",
]
