"""``iorthand export SESSION --format ros2``: a session (or a time range of it) as a ROS 2 bag.

Written with ``rosbags`` (pure Python: no ROS installation), ROS 2 Jazzy message definitions, MCAP storage by
default (ROS 2's default since Iron; ``sqlite3`` for Humble without the MCAP plugin). The bag is a folder
(``metadata.yaml`` + the storage file) that ``ros2 bag play``, Foxglove and rosbags read.

Topics, each robot under its namespace ``/<ns>`` (the robot id with ``-`` turned into ``_``, a valid ROS name):

==============================================  ===============================  ==================================
topic                                           type                             from
==============================================  ===============================  ==================================
``/<ns>/joint_states``                          sensor_msgs/msg/JointState       ``state/robot`` ``q`` (UR joint
                                                                                 names; no velocity nor effort)
``/tf``                                         tf2_msgs/msg/TFMessage           ``state/robot`` ``tcp_pose``: base
                                                                                 → tcp; ``markers``: base →
                                                                                 marker_<id> (filtered poses)
``/tf_static``                                  tf2_msgs/msg/TFMessage           base_link → base, once per robot
``/<ns>/wrench``                                geometry_msgs/msg/WrenchStamped  ``state/force`` (frame tcp)
``/<ns>/applied_twist``                         geometry_msgs/msg/TwistStamped   ``state/applied`` ``applied``
                                                                                 (every echo, refused ones too)
``/<ns>/camera/image/compressed``,              sensor_msgs/msg/CompressedImage  ``video/camera``,
``/<ns>/ultrasound/image/compressed``                                            ``video/ultrasound`` (JPEG frames;
                                                                                 failure notices are not images)
``/<ns>/camera/video/compressed``,              foxglove_msgs/msg/               ``video/camera``,
``/<ns>/ultrasound/video/compressed``           CompressedVideo                  ``video/ultrasound`` (H.264 frames,
                                                                                 one Annex B access unit each,
                                                                                 format ``h264``: see below)
``/rosout``                                     rcl_interfaces/msg/Log           safety status changes, refusals,
                                                                                 video failures, annotations
==============================================  ===============================  ==================================

Frames (REP-103: metres, radians, right-handed, quaternions x-y-z-w; REP-105/ur_description names):

- ``base``: the UR controller's base frame, the one ``getActualTCPPose`` reports in and the edge publishes every
  pose in (z up). ROS's ``base_link`` is this frame turned by 180° about z (:mod:`iorthand.kinematics`); the
  bag carries that static transform on ``/tf_static``, so a URDF of the arm hangs off ``base_link`` as usual.
- ``tcp``: the controller's tool centre point (the probe tip when the TCP offset is set), not ``tool0`` (the
  flange). The force sensor's frame is the tool frame (see ``iorthand_edge.force``): wrenches are in ``tcp``.
- ``marker_<id>``: a patient marker's filtered pose, in ``base``.
- ``camera_optical`` and ``ultrasound``: the images' frames; no transform is exported for them (the camera sits
  on pan/tilt servos whose chain is not part of the recording).

With more than one robot in the session, every frame and joint name is prefixed with the robot's namespace
(``sim1/base``, ``sim1/tcp``…) so that the trees do not merge; with one robot they are plain.

H.264 frames go into the bag as Foxglove reads them natively (``foxglove_msgs/msg/CompressedVideo``; its
definition is in the bag, for readers without foxglove_msgs). A P-frame needs the frames before it back to a
keyframe, so a topic starts at a keyframe: the frames before the first keyframe of the exported range (a
recording or a ``--start`` that begins inside a group of pictures) are left out, and so are those after a
failure notice or a frame missing from the recording (a gap in ``seq``) until the next keyframe (a missing frame
is said on ``/rosout``; the frames left out are counted in :attr:`Ros2Export.skipped`). :class:`H264Sync` is
that rule, shared with the other exports.

Times: each header stamp (a CompressedVideo's ``timestamp``) is the message's source time ``t`` (ns, the edge's
clock); the bag's own timestamp is
when the recorder received it (as ``ros2 bag record`` stores reception times). A refusal goes to ``/rosout``
once when it starts (the first refused command of a run with the same status), not once per refused command:
a released deadman refuses 60 commands a second, which ``applied_twist`` carries anyway.

The conversion (:class:`Ros2Converter`) is pure: decoded messages in, ROS messages out; :func:`export_ros2`
does the reading and writing.
"""

from __future__ import annotations

import contextlib
import logging
import re
import shutil
from collections.abc import Collection, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from iorthand import geometry, keys
from iorthand.protocol import (
    Annotation,
    AppliedCommand,
    DecodeError,
    ForceSample,
    Markers,
    Message,
    RobotState,
    SafetyStatus,
    Status,
    VideoFrame,
    message_type_for,
    source_news,
)
from iorthand_cloud.recorder.manifest import Manifest
from iorthand_cloud.recorder.reader import iter_records, read_manifest, segment_topics, session_dir
from iorthand_cloud.recorder.repair import repair_if_crashed

log = logging.getLogger("iorthand.recorder")

# UR's joint names, as ur_description and the ROS driver name them (base to wrist).
JOINT_NAMES = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
               "wrist_3_joint")
BASE, BASE_LINK, TCP = "base", "base_link", "tcp"
MARKER_FRAME = "marker_{id}"
# Frame of each video key's images; a key not listed uses the last part of its suffix.
VIDEO_FRAMES = {keys.VIDEO_CAMERA: "camera_optical", keys.VIDEO_ULTRASOUND: "ultrasound"}
TF, TF_STATIC, ROSOUT = "/tf", "/tf_static", "/rosout"
STORAGES = ("mcap", "sqlite3")
INSTALL = "pip install rosbags==0.11.9"  # what this export needs beyond iorthand-cloud

JOINT_STATE = "sensor_msgs/msg/JointState"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
WRENCH = "geometry_msgs/msg/WrenchStamped"
TWIST = "geometry_msgs/msg/TwistStamped"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
COMPRESSED_VIDEO = "foxglove_msgs/msg/CompressedVideo"
# foxglove_msgs/msg/CompressedVideo as foxglove/schemas publishes it: not in the ROS distributions' typestores.
COMPRESSED_VIDEO_MSG = """\
# A single frame of a compressed video bitstream
builtin_interfaces/Time timestamp
string frame_id
uint8[] data
string format
"""
LOG = "rcl_interfaces/msg/Log"

ANNOTATIONS_KEY = keys.service_key(keys.RECORDER, keys.RECORDER_ANNOTATIONS)
_ROS_NAME = re.compile(r"[^A-Za-z0-9_]")


class ExportError(ValueError):
    """A session that cannot be exported as asked; the message says what and why."""


def add_foxglove_types(typestore: Any) -> None:
    """Teach ``typestore`` :data:`COMPRESSED_VIDEO` (once)."""
    if COMPRESSED_VIDEO not in typestore.types:
        from rosbags.typesys import get_types_from_msg

        typestore.register(get_types_from_msg(COMPRESSED_VIDEO_MSG, COMPRESSED_VIDEO))


class H264Sync:
    """Which frames of one H.264 stream can be decoded, taken in recorded order (one per video key).

    A P-frame needs every frame back to the last keyframe. So the stream is decodable from a keyframe on, until
    a failure notice (no picture; the edge's next frame is a keyframe) or a gap in ``seq`` (a frame lost on the
    way or by the recorder; ``seq`` going back is an edge that restarted, a new stream) breaks it until the next
    keyframe. Frames before the first keyframe (a recording or an exported range that starts inside a group of
    pictures) cannot be decoded either."""

    def __init__(self) -> None:
        self.synced = False
        self.missing = 0  # frames missing just before the latest message (its seq gap)
        self.left_out = 0  # H.264 frames :meth:`admit` refused
        self._seq: int | None = None

    def admit(self, msg: VideoFrame) -> bool:
        """Whether ``msg`` (a frame or a failure notice of the stream) is a picture to pass on to a decoder."""
        prev, self._seq = self._seq, msg.seq
        self.missing = msg.seq - prev - 1 if prev is not None and msg.seq > prev + 1 else 0
        if msg.failure or self.missing or (prev is not None and msg.seq <= prev):
            self.synced = False
        if msg.failure:
            return False
        if not self.synced and not msg.keyframe:
            self.left_out += 1
            return False
        self.synced = True
        return True

    def lose(self) -> None:
        """A frame did not decode: the ones after it cannot either, until the next keyframe."""
        self.synced = False


# --------------------------------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class Decoded:
    """One recorded message, decoded with its protocol class. ``robot`` is "" for the recorder's annotations."""

    key: str
    robot: str
    suffix: str
    log_time: int  # the recorder's receive time, ns
    msg: Message
    stream: str = ""  # the recorder's stream it was read from (segments.VIDEO, TELEMETRY)


def export_target(session: str | Path, out: str | Path | None, fmt: str, *,
                  default: str = "{session_id}-{fmt}") -> tuple[Path, Manifest, Path]:
    """The session's folder, its manifest and where an export goes (``out``, else ``default`` in the session's
    folder): never over something that exists."""
    folder = session_dir(session)
    # A session whose recorder died: repaired first (as the report does), so that its manifest is up to date.
    repaired = repair_if_crashed(folder)
    if repaired:
        log.warning("%s: %s", folder, repaired)
    manifest = read_manifest(folder)
    path = Path(out) if out else folder / default.format(session_id=manifest.session_id, fmt=fmt)
    if path.exists():
        raise FileExistsError(f"{path} exists already: remove it or choose another --out")
    return folder, manifest, path


def time_window(folder: Path, start: float | None, end: float | None) -> tuple[int | None, int | None]:
    """``start``/``end`` (s from the session's first message, as export_rrd takes them) → receive times, ns."""
    if start is not None and end is not None and end <= start:
        raise ExportError(f"--end {end:g} s is not after --start {start:g} s")
    if start is None and end is None:
        return None, None
    first = next(iter_records(folder), None)
    t0 = first.log_time if first else 0
    return (t0 + int(start * 1e9) if start is not None else None, t0 + int(end * 1e9) if end is not None else None)


def iter_decoded(folder: Path, lo: int | None = None, hi: int | None = None,
                 suffixes: set[str] | None = None, skipped: dict[str, int] | None = None,
                 streams: Collection[str] | None = None, topics: Collection[str] | None = None) -> Iterator[Decoded]:
    """The session's messages in receive order, decoded; ``suffixes`` keeps only those robot keys (annotations
    are always kept); ``streams`` and ``topics`` read only those streams and keys (:func:`iter_records`).
    Malformed payloads (stored raw by the recorder) and keys without a message type are left out and counted in
    ``skipped``."""
    for r in iter_records(folder, lo, hi, streams, topics):
        if r.key == ANNOTATIONS_KEY:
            cls: type[Message] | None = Annotation
            robot, suffix = "", keys.RECORDER_ANNOTATIONS
        else:
            try:
                robot, suffix = keys.split_key(r.key)
            except keys.KeyExprError:
                continue  # another service's traffic: not part of a robot's recording
            if suffixes is not None and suffix not in suffixes:
                continue
            cls = message_type_for(r.key)
        if r.malformed or cls is None:
            if skipped is not None:
                why = "malformed" if r.malformed else "no message type"
                skipped[why] = skipped.get(why, 0) + 1
            continue
        try:
            msg = cls.decode(r.data)
        except DecodeError:
            if skipped is not None:
                skipped["undecodable"] = skipped.get("undecodable", 0) + 1
            continue
        yield Decoded(r.key, robot, suffix, r.log_time, msg, r.stream)


def session_robots(folder: Path) -> list[str]:
    """The robots of a session: the manifest's list and those of the keys in its manifest and its segments (a
    session still being recorded has a manifest up to one manifest_interval old)."""
    m = read_manifest(folder)
    robots = set(m.robots)
    for key in {*m.keys, *segment_topics(folder)}:
        with contextlib.suppress(keys.KeyExprError):  # a service key (annotations): no robot
            robots.add(keys.split_key(key)[0])
    return sorted(robots)


# --------------------------------------------------------------------------------------------------- maths


def ros_namespaces(robots: Iterable[str]) -> dict[str, str]:
    """Robot id → ROS namespace token: ``-`` (valid in our ids, not in ROS names) becomes ``_``, and a leading
    digit (invalid in ROS) gets an ``r`` before it. Two ids that would share a namespace are refused."""
    out: dict[str, str] = {}
    for robot in robots:
        ns = _ROS_NAME.sub("_", robot)
        if ns[:1].isdigit():
            ns = "r" + ns
        clash = [r for r, n in out.items() if n == ns]
        if clash:
            raise ExportError(f"robots {clash[0]!r} and {robot!r} would share the ROS namespace /{ns}")
        out[robot] = ns
    return out


# --------------------------------------------------------------------------------------------------- conversion


@dataclass(frozen=True)
class BagMessage:
    topic: str
    msgtype: str
    timestamp: int  # the bag's timestamp: the recorder's receive time, ns
    msg: Any  # an instance of the typestore's class for msgtype


@dataclass
class Ros2Converter:
    """Decoded session messages → ROS 2 messages (instances of ``typestore``'s classes). Pure apart from its
    own memory of what changed (safety status, refusal runs, video failures) and which robots had their static
    transform."""

    robots: Sequence[str]
    typestore: Any
    namespaces: dict[str, str] = field(init=False)
    _prefix: dict[str, str] = field(init=False)
    _static_done: set[str] = field(default_factory=set, init=False)
    _status: dict[str, str] = field(default_factory=dict, init=False)
    _refusing: dict[str, str | None] = field(default_factory=dict, init=False)
    _video_failure: dict[str, str] = field(default_factory=dict, init=False)
    _h264: dict[str, H264Sync] = field(default_factory=dict, init=False)
    skipped: dict[str, int] = field(default_factory=dict, init=False)  # recorded messages left out, by why

    def __post_init__(self) -> None:
        self.namespaces = ros_namespaces(self.robots)
        several = len(self.namespaces) > 1
        self._prefix = {r: f"{ns}/" if several else "" for r, ns in self.namespaces.items()}
        add_foxglove_types(self.typestore)
        t = self.typestore.types
        self._Time, self._Header = t["builtin_interfaces/msg/Time"], t["std_msgs/msg/Header"]
        self._Vector3, self._Quaternion = t["geometry_msgs/msg/Vector3"], t["geometry_msgs/msg/Quaternion"]
        self._Transform = t["geometry_msgs/msg/Transform"]
        self._TransformStamped = t["geometry_msgs/msg/TransformStamped"]
        self._Wrench, self._Twist = t["geometry_msgs/msg/Wrench"], t["geometry_msgs/msg/Twist"]
        self._types = {name: t[name] for name in (JOINT_STATE, TF_MESSAGE, WRENCH, TWIST, COMPRESSED_IMAGE,
                                                  COMPRESSED_VIDEO, LOG)}
        self._empty = np.zeros(0, dtype=np.float64)

    # ---------------------------------------------------------------- names

    def frame(self, robot: str, name: str) -> str:
        return self._prefix[robot] + name

    def topic(self, robot: str, name: str) -> str:
        return f"/{self.namespaces[robot]}/{name}"

    def video_topic(self, robot: str, suffix: str, encoding: str = "jpeg") -> str:
        kind = "video" if encoding == "h264" else "image"
        return self.topic(robot, f"{suffix.rsplit('/', 1)[-1]}/{kind}/compressed")

    # ---------------------------------------------------------------- building blocks

    def _stamp(self, t: int) -> Any:
        return self._Time(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000)

    def _header(self, t: int, frame_id: str) -> Any:
        return self._Header(stamp=self._stamp(t), frame_id=frame_id)

    def _transform(self, t: int, parent: str, child: str, xyz: Sequence[float],
                   quat: tuple[float, float, float, float]) -> Any:
        return self._TransformStamped(
            header=self._header(t, parent), child_frame_id=child,
            transform=self._Transform(translation=self._Vector3(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])),
                                      rotation=self._Quaternion(x=quat[0], y=quat[1], z=quat[2], w=quat[3])))

    def _tf(self, transforms: list[Any]) -> Any:
        return self._types[TF_MESSAGE](transforms=transforms)

    def _log(self, t: int, level: int, name: str, text: str) -> Any:
        return self._types[LOG](stamp=self._stamp(t), level=level, name=name, msg=text, file="", function="", line=0)

    def static_transforms(self, robot: str, t: int, log_time: int) -> BagMessage:
        """base_link → base: UR's base is ROS's base_link turned by π about z (quaternion (0, 0, 1, 0))."""
        tf = self._transform(t, self.frame(robot, BASE_LINK), self.frame(robot, BASE), (0.0, 0.0, 0.0),
                             (0.0, 0.0, 1.0, 0.0))
        return BagMessage(TF_STATIC, TF_MESSAGE, log_time, self._tf([tf]))

    # ---------------------------------------------------------------- per message

    def convert(self, d: Decoded) -> list[BagMessage]:
        """The ROS messages of one decoded session message (none for what the bag does not carry)."""
        msg = d.msg
        if isinstance(msg, Annotation):
            tags = f" [{', '.join(msg.tags)}]" if msg.tags else ""
            score = f" score {msg.score:g}" if msg.score is not None else ""
            text = f"{msg.author or 'annotation'}: {msg.text}{tags}{score}"
            return [BagMessage(ROSOUT, LOG, d.log_time,
                               self._log(msg.t or d.log_time, self._types[LOG].INFO, "iorthand.annotations", text))]
        robot = d.robot
        if robot not in self._prefix:  # not one of the robots this converter was made for
            why = "robot not exported"
            self.skipped[why] = self.skipped.get(why, 0) + 1
            return []
        out: list[BagMessage] = []
        if robot not in self._static_done:
            self._static_done.add(robot)
            out.append(self.static_transforms(robot, msg.t or d.log_time, d.log_time))
        t = msg.t
        if isinstance(msg, RobotState):
            js = self._types[JOINT_STATE](
                header=self._header(t, ""), name=[self._prefix[robot] + n for n in JOINT_NAMES],
                position=np.asarray(msg.q, dtype=np.float64), velocity=self._empty, effort=self._empty)
            out.append(BagMessage(self.topic(robot, "joint_states"), JOINT_STATE, d.log_time, js))
            p = msg.tcp_pose
            tf = self._transform(t, self.frame(robot, BASE), self.frame(robot, TCP), p[:3], geometry.rotvec_to_quaternion(p[3:6]))
            out.append(BagMessage(TF, TF_MESSAGE, d.log_time, self._tf([tf])))
        elif isinstance(msg, Markers):
            base = self.frame(robot, BASE)
            tfs = [self._transform(t, base, self.frame(robot, MARKER_FRAME.format(id=m.id)),
                                   (m.pose[3], m.pose[7], m.pose[11]), geometry.matrix_to_quaternion(m.pose))
                   for m in msg.markers]
            if tfs:
                out.append(BagMessage(TF, TF_MESSAGE, d.log_time, self._tf(tfs)))
        elif isinstance(msg, ForceSample):
            f, tq = msg.force, msg.torque
            w = self._types[WRENCH](header=self._header(t, self.frame(robot, TCP)), wrench=self._Wrench(
                force=self._Vector3(x=f[0], y=f[1], z=f[2]), torque=self._Vector3(x=tq[0], y=tq[1], z=tq[2])))
            out.append(BagMessage(self.topic(robot, "wrench"), WRENCH, d.log_time, w))
        elif isinstance(msg, AppliedCommand):
            a = msg.applied
            tw = self._types[TWIST](header=self._header(t, self.frame(robot, BASE)), twist=self._Twist(
                linear=self._Vector3(x=a[0], y=a[1], z=a[2]), angular=self._Vector3(x=a[3], y=a[4], z=a[5])))
            out.append(BagMessage(self.topic(robot, "applied_twist"), TWIST, d.log_time, tw))
            out.extend(self._refusal(robot, msg, d.log_time))
        elif isinstance(msg, SafetyStatus):
            if self._status.get(robot) != msg.status:
                self._status[robot] = msg.status
                level = self._types[LOG].INFO if msg.status in (Status.OK, Status.IDLE) else self._types[LOG].WARN
                out.append(BagMessage(ROSOUT, LOG, d.log_time, self._log(
                    t, level, f"iorthand.{self.namespaces[robot]}.safety", f"{msg.status}: {_meaning(msg)}")))
        elif isinstance(msg, VideoFrame):
            news = source_news(f"{msg.source} video", self._video_failure.get(d.key, ""), msg.failure)
            self._video_failure[d.key] = msg.failure
            if news:
                level = self._types[LOG].WARN if msg.failure else self._types[LOG].INFO
                out.append(BagMessage(ROSOUT, LOG, d.log_time, self._log(
                    t, level, f"iorthand.{self.namespaces[robot]}.video", news)))
            frame_id = self.frame(robot, VIDEO_FRAMES.get(d.suffix, d.suffix.rsplit("/", 1)[-1]))
            if msg.encoding == "h264":
                out.extend(self._h264_frame(robot, d, msg, frame_id))
            elif not msg.failure and msg.encoding == "jpeg":  # a failure notice carries no picture
                img = self._types[COMPRESSED_IMAGE](header=self._header(t, frame_id), format="jpeg",
                                                    data=np.frombuffer(msg.data, dtype=np.uint8))
                out.append(BagMessage(self.video_topic(robot, d.suffix), COMPRESSED_IMAGE, d.log_time, img))
            elif not msg.failure:
                why = f"{msg.encoding} video frames (not a ROS format)"
                self.skipped[why] = self.skipped.get(why, 0) + 1
        return out

    def _h264_frame(self, robot: str, d: Decoded, msg: VideoFrame, frame_id: str) -> list[BagMessage]:
        """A CompressedVideo message for a frame a decoder can take (see :class:`H264Sync`); a /rosout warning
        when frames are missing from a stream that was being decoded."""
        sync = self._h264.setdefault(d.key, H264Sync())
        was_synced = sync.synced
        ok = sync.admit(msg)
        out: list[BagMessage] = []
        if sync.missing and was_synced:
            text = (f"{msg.source} video: {sync.missing} H.264 frame(s) missing before frame {msg.seq}: "
                    "frames left out until the next keyframe")
            out.append(BagMessage(ROSOUT, LOG, d.log_time, self._log(
                msg.t, self._types[LOG].WARN, f"iorthand.{self.namespaces[robot]}.video", text)))
        if ok:
            video = self._types[COMPRESSED_VIDEO](timestamp=self._stamp(msg.t), frame_id=frame_id, format="h264",
                                                  data=np.frombuffer(msg.data, dtype=np.uint8))
            out.append(BagMessage(self.video_topic(robot, d.suffix, "h264"), COMPRESSED_VIDEO, d.log_time, video))
        elif not msg.failure:
            why = "h264 frames before a keyframe"
            self.skipped[why] = self.skipped.get(why, 0) + 1
        return out

    def _refusal(self, robot: str, msg: AppliedCommand, log_time: int) -> list[BagMessage]:
        if msg.accepted:
            self._refusing[robot] = None
            return []
        if self._refusing.get(robot) == msg.status:
            return []  # the same refusal goes on: said once, when it started
        self._refusing[robot] = msg.status
        text = f"command {msg.cmd_seq} from {msg.operator or '?'} refused: {msg.status}: {_meaning(msg)}"
        return [BagMessage(ROSOUT, LOG, log_time, self._log(
            msg.t, self._types[LOG].WARN, f"iorthand.{self.namespaces[robot]}.supervisor", text))]


def _meaning(msg: SafetyStatus | AppliedCommand) -> str:
    """The message's reason, or what its status code means when it gives none."""
    if msg.reason:
        return msg.reason
    try:
        return Status(msg.status).message
    except ValueError:
        return "(no reason given)"


# --------------------------------------------------------------------------------------------------- writing


@dataclass
class Ros2Export:
    path: Path
    counts: dict[str, int]  # messages per topic
    skipped: dict[str, int]  # recorded messages left out, by why

    @property
    def messages(self) -> int:
        return sum(self.counts.values())


def _static_qos() -> list[Any]:
    """/tf_static is latched in ROS 2 (transient local, keep last 1): played back, late subscribers get it."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    unset = QosTime(0, 0)
    return [Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, unset, unset,
                QosLiveliness.AUTOMATIC, unset, False)]


def export_ros2(session: str | Path, out: str | Path | None = None, start: float | None = None,
                end: float | None = None, storage: str = "mcap") -> Ros2Export:
    """Write the bag folder (refusing one that exists); ``start``/``end`` are seconds from the session's first
    message."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    if storage not in STORAGES:
        raise ExportError(f"storage {storage!r} is not one of {', '.join(STORAGES)}")
    folder, manifest, path = export_target(session, out, "ros2")
    lo, hi = time_window(folder, start, end)
    typestore = get_typestore(Stores.ROS2_JAZZY)
    conv = Ros2Converter(session_robots(folder), typestore)  # adds foxglove_msgs/msg/CompressedVideo to it
    counts: dict[str, int] = {}
    skipped: dict[str, int] = {}
    serialize = typestore.serialize_cdr
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    try:
        with Writer(path, version=Writer.VERSION_LATEST, storage_plugin=plugin) as writer:
            writer.set_custom_data("iorthand.session", manifest.session_id)
            connections: dict[str, Any] = {}
            for d in iter_decoded(folder, lo, hi, skipped=skipped):
                for m in conv.convert(d):
                    conn = connections.get(m.topic)
                    if conn is None:
                        qos = _static_qos() if m.topic == TF_STATIC else ()
                        conn = connections[m.topic] = writer.add_connection(
                            m.topic, m.msgtype, typestore=typestore, offered_qos_profiles=qos)
                    writer.write(conn, m.timestamp, serialize(m.msg, m.msgtype))
                    counts[m.topic] = counts.get(m.topic, 0) + 1
        for why, n in conv.skipped.items():
            skipped[why] = skipped.get(why, 0) + n
        if not counts:
            raise ExportError("the session has nothing a ROS 2 bag carries in the exported range")
    except BaseException:
        shutil.rmtree(path, ignore_errors=True)  # ours (it did not exist): an empty or half bag would mislead
        raise
    return Ros2Export(path, counts, skipped)
