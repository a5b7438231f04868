"""Foxglove channels in recordings: the pure conversions (iorthand message → Foxglove message), and sessions
recorded through a real router and read back with the real ``mcap`` reader and Foxglove's protobuf schemas:
every Foxglove channel decodes, its messages line up one for one with their raw source, H.264 frames become
CompressedVideo that a decoder plays, and the raw recording (manifest, report, readers) is as before."""

from __future__ import annotations

import io
import itertools
import json
import math
import time
from collections import Counter, defaultdict
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf import descriptor_pool, message_factory
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from mcap.reader import make_reader
from PIL import Image

from iorthand import geometry, keys
from iorthand.protocol import (
    AppliedCommand,
    ForceLevelState,
    ForceSample,
    MarkerPose,
    Markers,
    RobotState,
    SafetyStatus,
    Status,
    VideoFrame,
    message_type_for,
)
from iorthand_cloud import foxglove_channels as fx
from iorthand_cloud.recorder import client
from iorthand_cloud.recorder import manifest as mf
from iorthand_cloud.recorder.config import ReportConfig
from iorthand_cloud.recorder.reader import iter_records, segment_files
from iorthand_cloud.recorder.repair import has_footer
from iorthand_cloud.recorder.report import build_report
from iorthand_cloud.recorder.service import FOXGLOVE, RecorderService
from iorthand_cloud.recorder.simulate import SyntheticSession
from tests.conftest import wait_until
from tests.test_recorder import recorder_config

PROTO = {c.DESCRIPTOR.full_name: c for c in (FrameTransforms, SceneUpdate, CompressedImage, CompressedVideo, Log)}

# ---------------------------------------------------------------------------------------------------------
# Pure conversions


def _rotate(q: tuple[float, float, float, float], v: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    u = np.array([x, y, z])
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


ROTVECS = [[0.0, 0.0, 0.0], [1e-14, 0.0, 0.0], [math.pi, 0.0, 0.0], [0.0, math.pi, 0.0], [0.0, 0.0, math.pi],
           [0.3, -1.2, 2.0], [2.2, 2.0, 0.1], [-1.0, 0.5, -2.9]]


@pytest.mark.parametrize("rv", ROTVECS)
def test_quaternions_rotate_as_the_ur_pose_and_the_matrix_do(rv: list[float]) -> None:
    r = geometry.rotvec_to_matrix(rv)
    for q in (geometry.rotvec_to_quaternion(rv), geometry.matrix_to_quaternion(geometry.flatten(geometry.make_transform(r)))):
        assert math.isclose(sum(c * c for c in q), 1.0, rel_tol=1e-9)
        for v in np.eye(3):
            assert np.allclose(_rotate(q, v), r @ v, atol=1e-9)
    assert geometry.matrix_to_quaternion(r.flatten().tolist())[3] >= 0.0  # 3×3 too, and w ≥ 0


@pytest.mark.parametrize("d", [(1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.6, -0.48, 0.64)])
def test_arrows_point_along_the_force(d: tuple[float, float, float]) -> None:
    assert np.allclose(_rotate(fx.x_axis_to(*d), np.array([1.0, 0.0, 0.0])), d, atol=1e-9)


def test_robot_state_is_base_to_tcp_in_the_robots_frames() -> None:
    msg = RobotState(tcp_pose=[0.3, -0.1, 0.2, 0.0, 0.0, math.pi / 2]).stamp(5, t=1_700_000_000_123_456_789)
    out = FrameTransforms.FromString(fx.robot_transforms("sim1", msg).SerializeToString())
    (tf,) = out.transforms
    assert (tf.parent_frame_id, tf.child_frame_id) == ("sim1/base", "sim1/tcp")
    assert (tf.timestamp.seconds, tf.timestamp.nanos) == (1_700_000_000, 123_456_789)
    assert (tf.translation.x, tf.translation.y, tf.translation.z) == (0.3, -0.1, 0.2)
    s = math.sqrt(0.5)
    assert np.allclose([tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w], [0, 0, s, s])


def _marker(mid: int, pose: list[float]) -> MarkerPose:
    return MarkerPose(id=mid, pose=pose, raw=pose)


def test_markers_replace_the_previous_ones_in_the_base_frame() -> None:
    t = geometry.make_transform(geometry.rot_z(math.pi / 2)[:3, :3], [0.4, 0.1, 0.0])
    msg = Markers(markers=[_marker(7, geometry.flatten(t)), _marker(9, geometry.flatten(np.eye(4)))]).stamp(3)
    scene = SceneUpdate.FromString(fx.marker_scene("sim1", msg).SerializeToString())
    assert [d.type for d in scene.deletions] == [SceneEntityDeletion.Type.ALL]
    assert [(e.id, e.frame_id) for e in scene.entities] == [("marker_7", "sim1/base"), ("marker_9", "sim1/base")]
    cube = scene.entities[0].cubes[0]
    assert (cube.pose.position.x, cube.pose.position.y) == (0.4, 0.1)
    assert scene.entities[0].texts[0].text == "marker 7"
    tfs = fx.marker_transforms("sim1", msg)
    assert tfs is not None
    assert [(tf.parent_frame_id, tf.child_frame_id) for tf in tfs.transforms] == [
        ("sim1/base", "sim1/marker_7"), ("sim1/base", "sim1/marker_9")]
    assert np.allclose([tfs.transforms[0].rotation.z, tfs.transforms[0].rotation.w], [math.sqrt(0.5)] * 2)
    empty = Markers(markers=[], failure="camera unplugged").stamp(4)
    assert fx.marker_transforms("sim1", empty) is None
    assert len(fx.marker_scene("sim1", empty).entities) == 0  # all deleted: nothing in view is drawn as such


def test_probe_and_force_arrow_at_the_tcp_coloured_by_level() -> None:
    msg = ForceSample(force=[0.0, 0.0, -5.0]).stamp(1)
    scene = fx.probe_scene("sim1", msg, 2)
    (e,) = scene.entities
    assert (e.frame_id, e.frame_locked) == ("sim1/tcp", True)
    assert e.cylinders[0].pose.position.z == pytest.approx(-fx.PROBE_LENGTH / 2)
    arrow = e.arrows[0]
    assert arrow.shaft_length + arrow.head_length == pytest.approx(5.0 * fx.FORCE_SCALE)
    q = arrow.pose.orientation
    assert np.allclose(_rotate((q.x, q.y, q.z, q.w), np.array([1.0, 0, 0])), [0, 0, -1])
    assert (arrow.color.r, arrow.color.g) == pytest.approx(fx.LEVEL_COLOURS[2][:2])
    stale = fx.probe_scene("sim1", msg, None).entities[0].arrows[0].color
    assert (stale.r, stale.g, stale.b) == fx.STALE_COLOUR[:3]
    assert not fx.probe_scene("sim1", ForceSample().stamp(2), 0).entities[0].arrows  # no force, no arrow


def test_video_frames_by_encoding() -> None:
    jpeg = VideoFrame(width=4, height=2, data=b"\xff\xd8jpeg\xff\xd9").stamp(1)
    img = fx.video_message("sim1", "camera", jpeg)
    assert isinstance(img, CompressedImage) and (img.format, img.data, img.frame_id) == ("jpeg", jpeg.data, "sim1/camera")
    h264 = VideoFrame(width=4, height=2, encoding="h264", data=b"\x00\x00\x00\x01\x67").stamp(2)
    vid = fx.video_message("sim1", "ultrasound", h264)
    assert isinstance(vid, CompressedVideo) and (vid.format, vid.data) == ("h264", h264.data)
    assert fx.video_message("sim1", "camera", VideoFrame(width=4, height=2, failure="unplugged").stamp(3)) is None
    assert fx.video_message("sim1", "camera", VideoFrame(width=4, height=2, encoding="y4m", data=b"x").stamp(4)) is None


def test_logs_for_safety_changes_refusals_and_sources() -> None:
    stopped = SafetyStatus(status=Status.COMMAND_TIMEOUT, reason="no fresh command").stamp(1)
    log = fx.safety_log("sim1", stopped, "ok")
    assert log is not None and log.level == Log.Level.WARNING and log.message == "command_timeout: no fresh command"
    assert log.name == "sim1/safety"
    assert fx.safety_log("sim1", stopped, "command_timeout") is None  # no change, no line
    ok = fx.safety_log("sim1", SafetyStatus(status=Status.OK).stamp(2), None)
    assert ok is not None and ok.level == Log.Level.INFO and ok.message == f"ok: {Status.OK.message}"
    assert fx.safety_log("sim1", SafetyStatus(status=Status.FAULT, reason="rtde lost").stamp(3), "ok").level == Log.Level.ERROR
    refused = AppliedCommand(operator="op1", cmd_seq=42, accepted=False, status=Status.NO_DEADMAN,
                             reason="deadman released").stamp(4)
    rlog = fx.refusal_log("sim1", refused)
    assert rlog is not None and rlog.message == "command 42 from op1 refused: deadman_released: deadman released"
    assert fx.refusal_log("sim1", AppliedCommand(accepted=True).stamp(5)) is None
    down = fx.source_log("sim1", "camera video", 6, "", "device gone")
    back = fx.source_log("sim1", "camera video", 7, "device gone", "")
    assert down is not None and down.level == Log.Level.WARNING and "device gone" in down.message
    assert back is not None and back.level == Log.Level.INFO
    assert fx.source_log("sim1", "camera video", 8, "", "") is None


def test_force_samples_for_the_plot_panel() -> None:
    f = fx.force_sample(ForceSample(force=[3.0, 0.0, -4.0], torque=[0.1, 0.2, 0.3]).stamp(1, t=2_500_000_000))
    assert f == {"timestamp": {"sec": 2, "nsec": 500_000_000}, "fx": 3.0, "fy": 0.0, "fz": -4.0, "tx": 0.1,
                 "ty": 0.2, "tz": 0.3, "norm": 5.0}
    lv = fx.force_level_sample(ForceLevelState(level=1, stale=False, value=6.5).stamp(2))
    assert (lv["level"], lv["stale"], lv["value"]) == (1, False, 6.5)


def test_converter_keeps_state_per_robot_and_leaves_video_out_on_request() -> None:
    conv = fx.FoxgloveConverter()
    key = keys.RobotKeys("sim1").key
    level = ForceLevelState(level=2, stale=False).stamp(1)
    assert [m.channel.topic for m in conv.convert(key(keys.STATE_FORCE_LEVEL), level)] == ["/sim1/force_level"]
    t0 = 1_000_000_000
    force = conv.convert(key(keys.STATE_FORCE), ForceSample(force=[0, 0, -9.0]).stamp(2, t=t0))
    assert [m.channel.topic for m in force] == ["/sim1/force", "/sim1/probe"]
    arrow = SceneUpdate.FromString(force[1].data).entities[0].arrows[0]
    assert arrow.color.r == pytest.approx(fx.LEVEL_COLOURS[2][0])  # the latest level of this robot
    # The probe at most every PROBE_PERIOD_NS of receive time, at once on a level change; the source's clock
    # (here: stepping back a second a sample) does not time it.
    conv = fx.FoxgloveConverter()
    conv.convert(key(keys.STATE_FORCE_LEVEL), level)
    assert len(conv.convert(key(keys.STATE_FORCE), ForceSample().stamp(2, t=t0), recv_ns=t0)) == 2
    topics = [[m.channel.topic for m in conv.convert(key(keys.STATE_FORCE), ForceSample().stamp(3 + i, t=t0 - i * 10**9),
                                                     recv_ns=r)]
              for i, r in enumerate((t0 + 10_000_000, t0 + fx.PROBE_PERIOD_NS, t0 + fx.PROBE_PERIOD_NS + 1))]
    assert topics == [["/sim1/force"], ["/sim1/force", "/sim1/probe"], ["/sim1/force"]]
    conv.convert(key(keys.STATE_FORCE_LEVEL), ForceLevelState(level=1, stale=False).stamp(9))
    assert len(conv.convert(key(keys.STATE_FORCE), ForceSample().stamp(10), recv_ns=t0 + fx.PROBE_PERIOD_NS + 2)) == 2
    other = conv.convert(keys.RobotKeys("sim2").key(keys.STATE_FORCE), ForceSample(force=[0, 0, -9.0]).stamp(2))
    assert SceneUpdate.FromString(other[1].data).entities[0].arrows[0].color.r == fx.STALE_COLOUR[0]
    safety = SafetyStatus(status="ok").stamp(3)
    assert len(conv.convert(key(keys.STATE_SAFETY), safety)) == 1
    assert conv.convert(key(keys.STATE_SAFETY), safety) == []
    assert conv.convert(key(keys.CMD_TWIST), message_type_for(key(keys.CMD_TWIST))().stamp(1)) == []
    assert not conv.handles("iorthand/_twin/sim1/snapshot") and not conv.handles("not/a/robot")
    ch = conv.convert(key(keys.STATE_ROBOT), RobotState().stamp(1))[0].channel
    assert ch.metadata == {fx.SOURCE_META: key(keys.STATE_ROBOT)} and ch.message_encoding == "protobuf"
    frame = VideoFrame(width=4, height=2, data=b"\xff\xd8\xff\xd9").stamp(1)
    assert [m.channel.topic for m in conv.convert(key(keys.VIDEO_CAMERA), frame)] == ["/sim1/camera"]
    no_video = fx.FoxgloveConverter(video=False)
    assert not no_video.handles(key(keys.VIDEO_CAMERA)) and no_video.convert(key(keys.VIDEO_CAMERA), frame) == []


def _shown(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(CompressedImage.FromString(data).data)).convert("RGB"))


def test_a_video_failure_notice_replaces_the_last_picture_in_a_recording() -> None:
    """An image panel keeps the last image it was given: without a picture of its own, a failure notice left a
    recording showing the last frame as if live."""
    conv = fx.FoxgloveConverter()
    key = keys.RobotKeys("sim1").key(keys.VIDEO_CAMERA)
    t0 = 1_000_000_000_000
    r0 = 5_000_000_000_000  # the recording's log time (the recorder's receive time): not the edge's clock

    def camera(msg: VideoFrame, received: int) -> list[str]:
        return [m.channel.topic for m in conv.convert(key, msg, received)]

    frame = VideoFrame(width=64, height=48, data=b"\xff\xd8\xff\xd9")
    assert camera(frame.stamp(1, t=t0), r0) == ["/sim1/camera"]
    notice = VideoFrame(width=640, height=480, failure="cannot open video device '0'")
    out = conv.convert(key, notice.stamp(2, t=t0 + 1), r0 + 1)
    assert [m.channel.topic for m in out] == ["/sim1/camera", "/sim1/events"], "no picture replaced the last frame"
    picture = CompressedImage.FromString(out[0].data)
    assert out[0].channel.schema_name == "foxglove.CompressedImage" and out[0].t == t0 + 1
    assert picture.format == "jpeg" and picture.frame_id == "sim1/camera"
    assert (picture.timestamp.seconds, picture.timestamp.nanos) == divmod(t0 + 1, 1_000_000_000)
    image = _shown(out[0].data)
    assert image.shape == (480, 640, 3) and image.mean() < 60  # the stream's size, dark: not the last frame
    # The source retrying: one picture per NOTICE_INTERVAL_NS of receive time (an edge's clock that went back
    # draws none sooner), at once for another failure, and afresh when the receive times go back.
    assert camera(notice.stamp(3, t=t0 - 10 * fx.NOTICE_INTERVAL_NS), r0 + 2) == []
    assert camera(notice.stamp(4, t=t0 + 1 + fx.NOTICE_INTERVAL_NS), r0 + fx.NOTICE_INTERVAL_NS) == []
    assert camera(notice.stamp(5, t=t0), r0 + 1 + fx.NOTICE_INTERVAL_NS) == ["/sim1/camera"]
    other = VideoFrame(width=640, height=480, failure="media process down")
    assert camera(other.stamp(6, t=t0 + 2), r0 + 2 + fx.NOTICE_INTERVAL_NS) == ["/sim1/camera", "/sim1/events"]
    assert camera(other.stamp(7, t=t0 + 3), r0) == ["/sim1/camera"]
    # Back to pictures, then failing again: a picture at once.
    assert camera(frame.stamp(8, t=t0 + 10), r0 + 10) == ["/sim1/camera", "/sim1/events"]
    assert camera(notice.stamp(9, t=t0 + 11), r0 + 11) == ["/sim1/camera", "/sim1/events"]
    # An H.264 stream gets a keyframe of its size; a caller that draws its own notices turns them off.
    h264 = conv.convert(keys.RobotKeys("sim1").key(keys.VIDEO_ULTRASOUND),
                        VideoFrame(width=320, height=240, encoding="h264", failure="frame not sent").stamp(10, t=t0))
    assert h264[0].channel.schema_name == "foxglove.CompressedVideo"
    assert CompressedVideo.FromString(h264[0].data).data.startswith((b"\x00\x00\x00\x01", b"\x00\x00\x01"))
    quiet = fx.FoxgloveConverter(failure_pictures=False)
    assert [m.channel.topic for m in quiet.convert(key, notice.stamp(11, t=t0))] == ["/sim1/events"]


def test_failure_pictures_follow_the_log_time_whatever_the_edges_clock_does() -> None:
    """Found by a review: the pictures were timed by the notices' source time, the edge's to set: a clock that
    stepped back drew one for every notice, one that stood still (or had jumped ahead) drew no more. A recording is
    converted with its log times (the recorder's receive times): one picture per NOTICE_INTERVAL_NS of them, and
    the same pictures every time the same recording is converted."""
    key = keys.RobotKeys("sim1").key(keys.VIDEO_CAMERA)
    r0, step = 5_000_000_000_000, fx.NOTICE_INTERVAL_NS // 5  # a notice every 100 ms of log time, for 2 s
    edge_clocks = {
        "stepping back": lambda i: 10**15 - i * 10**9,
        "standing still": lambda i: 10**15,
        "jumped ahead, then back": lambda i: 2**61 if i == 3 else 10**15 + i * step,
    }
    for name, edge_t in edge_clocks.items():
        recorded = [(VideoFrame(width=64, height=48, failure="cannot open video device '0'").stamp(1 + i, t=edge_t(i)),
                     r0 + i * step) for i in range(21)]
        runs = []
        for _ in range(2):  # the same recording, converted twice
            conv = fx.FoxgloveConverter()
            runs.append([[(m.channel.topic, m.t, m.data) for m in conv.convert(key, msg, received)]
                         for msg, received in recorded])
        assert runs[0] == runs[1], name
        drawn = [i for i, out in enumerate(runs[0]) if any(topic == "/sim1/camera" for topic, _, _ in out)]
        assert drawn == [0, 5, 10, 15, 20], (name, drawn)


# ---------------------------------------------------------------------------------------------------------
# Reading a session's Foxglove files back


@dataclass
class FoxRecord:
    topic: str
    schema: str
    log_time: int
    publish_time: int
    sequence: int
    msg: Any
    source: str


def _schema_class(name: str, data: bytes) -> type:
    """The message class built from the schema stored in the file alone, as the Foxglove app does."""
    pool = descriptor_pool.DescriptorPool()
    for f in FileDescriptorSet.FromString(data).file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def read_foxglove(folder: Path) -> list[FoxRecord]:
    out: list[FoxRecord] = []
    checked: set[str] = set()
    for path in sorted((folder / FOXGLOVE).glob("*.mcap")):
        with path.open("rb") as f:
            for schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
                assert schema is not None
                if channel.message_encoding == "protobuf":
                    assert schema.encoding == "protobuf"
                    msg = PROTO[schema.name].FromString(message.data)
                    if schema.name not in checked:  # the stored schema decodes it the same, on its own
                        assert _schema_class(schema.name, schema.data).FromString(message.data).SerializeToString(
                            deterministic=True) == msg.SerializeToString(deterministic=True)
                        checked.add(schema.name)
                else:
                    assert (channel.message_encoding, schema.encoding) == ("json", "jsonschema")
                    properties = json.loads(schema.data)["properties"]
                    msg = json.loads(message.data)
                    assert set(msg) <= set(properties)
                out.append(FoxRecord(channel.topic, schema.name, message.log_time, message.publish_time,
                                     message.sequence, msg, channel.metadata[fx.SOURCE_META]))
    return out


def _by_topic(records: list[FoxRecord]) -> dict[str, list[FoxRecord]]:
    out: dict[str, list[FoxRecord]] = defaultdict(list)
    for r in records:
        out[r.topic].append(r)
    return out


@pytest.fixture
def recorder(router_endpoint: str, tmp_path: Path):
    services: list[RecorderService] = []

    def make(**extra: object) -> RecorderService:
        svc = RecorderService(recorder_config(router_endpoint, tmp_path / "rec", **extra))
        svc.start()
        services.append(svc)
        return svc

    yield make
    for svc in services:
        svc.shutdown()


def _publish_sim2(s: Any) -> dict[str, int]:
    """A second robot with what the synthetic one lacks in a few seconds: safety changes, refusals, a camera
    that fails and comes back, a perception failure."""
    k = keys.RobotKeys("sim2")
    pubs = {suffix: s.declare_publisher(k.key(suffix)) for suffix in
            (keys.STATE_SAFETY, keys.STATE_APPLIED, keys.VIDEO_CAMERA, keys.MARKERS, keys.STATE_ROBOT)}
    time.sleep(0.3)
    statuses = ["idle", "idle", "ok", "ok", "ok", "command_timeout", "command_timeout", "ok", "fault"]
    for seq, st in enumerate(statuses, 1):
        pubs[keys.STATE_SAFETY].put(SafetyStatus(status=st, reason=f"reason {seq}").stamp(seq).encode())
    for seq in range(1, 11):
        refused = seq % 3 == 0
        pubs[keys.STATE_APPLIED].put(AppliedCommand(
            cmd_seq=seq, accepted=not refused, status=Status.NO_DEADMAN if refused else Status.OK,
            reason="deadman released" if refused else "").stamp(seq).encode())
    frames = ["", "", "camera unplugged", "camera unplugged", "", ""]
    for seq, failure in enumerate(frames, 1):
        data = b"" if failure else b"\xff\xd8frame%d\xff\xd9" % seq
        pubs[keys.VIDEO_CAMERA].put(VideoFrame(width=4, height=2, data=data, failure=failure).stamp(seq).encode())
    pubs[keys.MARKERS].put(Markers(markers=[], failure="no camera").stamp(1).encode())
    pubs[keys.STATE_ROBOT].put(b"\xc1 not msgpack")  # malformed: stored raw, never converted
    # 4 frames and one notice picture (the second notice follows within NOTICE_INTERVAL_NS)
    return {"messages": 27, "safety_changes": 5, "refusals": 3, "pictures": 5, "events": 3}


def test_a_recorded_session_opens_in_foxglove_one_message_per_source(recorder, session_factory, tmp_path) -> None:
    svc = recorder()
    s, video = session_factory(), session_factory()
    sim = SyntheticSession(s, "sim1", 3.0, video_session=video)
    time.sleep(0.3)
    assert client.start(s, session_id="fox", operator="alice").ok
    sim.run()
    expected_sim2 = _publish_sim2(s)
    assert client.annotate(s, "probe slipped", author="alice", tags=["slip"], score=2.0).ok
    total = sum(sim.stats.published.values()) + expected_sim2["messages"]
    wait_until(lambda: svc.status.messages >= total, message="all recorded")
    assert client.stop(s).ok
    folder = tmp_path / "rec" / "fox"

    # The raw recording is what it was: its files, its manifest, its report.
    assert sorted(p.name for p in segment_files(folder)) == ["telemetry-0001.mcap", "video-0001.mcap"]
    raw = list(iter_records(folder))
    m = mf.Manifest.read(folder)
    assert all(k.startswith("iorthand/") for k in m.keys)
    assert mf.totals(m.keys)["messages"] + m.annotations == len(raw)
    assert [seg.file for seg in m.segments] == ["telemetry-0001.mcap", "video-0001.mcap"]
    report = build_report(folder, ReportConfig(plots=False), tmp_path / "report")
    assert report["recording"]["messages"] == mf.totals(m.keys)["messages"]
    assert m.config["foxglove"] == {"enabled": True, "video": True}

    fox = read_foxglove(folder)
    topics = _by_topic(fox)
    assert all(has_footer(p) for p in (folder / FOXGLOVE).glob("*.mcap"))
    decoded: dict[str, list[tuple[Any, Any]]] = defaultdict(list)  # raw key → (record, message)
    for r in raw:
        cls = message_type_for(r.key)
        if cls is not None and not r.malformed:
            decoded[r.key].append((r, cls.decode(r.data)))
    k1, k2 = keys.RobotKeys("sim1").key, keys.RobotKeys("sim2").key

    # One Foxglove message per raw message, at the same receive time and sequence.
    for topic_name, key in (("/sim1/tf", k1(keys.STATE_ROBOT)), ("/sim1/force", k1(keys.STATE_FORCE)),
                            ("/sim1/force_level", k1(keys.STATE_FORCE_LEVEL)),
                            ("/sim1/markers", k1(keys.MARKERS)), ("/sim1/markers/tf", k1(keys.MARKERS)),
                            ("/sim1/camera", k1(keys.VIDEO_CAMERA))):
        got = [(r.log_time, r.sequence) for r in topics[topic_name]]
        want = [(r.log_time, r.sequence) for r, _ in decoded[key]]
        assert len(want) > 10 and got == want, topic_name
        assert {r.source for r in topics[topic_name]} == {key}
    assert len(decoded[k1(keys.STATE_ROBOT)]) >= 300  # 125 Hz for 3 s: the real rate went through
    # The contents are the raw messages'.
    for fr, (_, rs) in zip(topics["/sim1/tf"], decoded[k1(keys.STATE_ROBOT)], strict=True):
        tf = fr.msg.transforms[0]
        assert [tf.translation.x, tf.translation.y, tf.translation.z] == rs.tcp_pose[:3] and fr.publish_time == rs.t
    for fr, (_, vf) in zip(topics["/sim1/camera"], decoded[k1(keys.VIDEO_CAMERA)], strict=True):
        assert fr.schema == "foxglove.CompressedImage" and fr.msg.format == "jpeg" and fr.msg.data == vf.data
    for fr, (_, fs) in zip(topics["/sim1/force"], decoded[k1(keys.STATE_FORCE)], strict=True):
        assert fr.msg["fz"] == fs.force[2]
    # The probe: the force samples 40 ms of receive (log) time apart, and those at a new level (in receive order).
    want_probes, last, level = [], None, None
    for r in raw:
        if r.key == k1(keys.STATE_FORCE_LEVEL):
            lv = ForceLevelState.decode(r.data)
            level = None if lv.stale else lv.level
        elif r.key == k1(keys.STATE_FORCE) and (
                last is None or last[1] != level or not 0 <= r.log_time - last[0] < fx.PROBE_PERIOD_NS):
            last = (r.log_time, level)
            want_probes.append((r.log_time, r.sequence))
    probes = topics["/sim1/probe"]
    assert [(p.log_time, p.sequence) for p in probes] == want_probes and len(probes) > 50
    assert [len(fr.msg.transforms) for fr in topics["/sim1/markers/tf"]] == [3] * len(topics["/sim1/markers/tf"])
    # Logs: the first safety status and each change; each refusal; sources failing and recovering.
    sim1_status = [sf.status for _, sf in decoded[k1(keys.STATE_SAFETY)]]
    changes = 1 + sum(a != b for a, b in itertools.pairwise(sim1_status))
    assert len(topics["/sim1/safety"]) == changes
    sim2_safety = [r.msg for r in topics["/sim2/safety"]]
    assert len(sim2_safety) == expected_sim2["safety_changes"]
    assert [lg.message for lg in sim2_safety[:2]] == ["idle: reason 1", "ok: reason 3"]
    assert sim2_safety[-1].level == Log.Level.ERROR
    refused = [ap for _, ap in decoded[k2(keys.STATE_APPLIED)] if not ap.accepted]
    assert len(topics["/sim2/refusals"]) == len(refused) == expected_sim2["refusals"]
    assert all("deadman released" in r.msg.message for r in topics["/sim2/refusals"])
    assert len(topics["/sim2/camera"]) == expected_sim2["pictures"]
    # The failure shows where it happened: after the last frame before it, a picture that says so.
    assert [r.msg.data.startswith(b"\xff\xd8frame") for r in topics["/sim2/camera"]] == [True] * 2 + [False] + [True] * 2
    assert _shown(topics["/sim2/camera"][2].msg.SerializeToString()).mean() < 60
    events = [r.msg.message for r in topics["/sim2/events"]]
    assert len(events) == expected_sim2["events"] and "camera unplugged" in events[0] and "no camera" in events[2]
    assert "/sim2/tf" not in topics  # its only robot state was malformed
    (ann,) = topics["/annotations"]
    assert ann.msg.message == "probe slipped [slip] (score 2)" and ann.msg.name == "alice"
    # Nothing else was made, and nothing from keys without a conversion (commands).
    made_from = Counter(r.source for r in fox)
    assert k1(keys.CMD_TWIST) not in made_from
    assert set(topics) == {
        "/sim1/tf", "/sim1/force", "/sim1/probe", "/sim1/force_level", "/sim1/markers", "/sim1/markers/tf",
        "/sim1/camera", "/sim1/safety", "/sim2/safety", "/sim2/refusals", "/sim2/camera", "/sim2/events",
        "/sim2/markers", "/annotations"}
    assert svc.foxglove_errors == 0


def _h264_frames(n: int, width: int = 160, height: int = 120) -> list[bytes]:
    """``n`` H.264 access units (Annex B, SPS/PPS in-band) of a moving gradient, made with PyAV's libx264."""
    ctx = av.CodecContext.create("libx264", "w")
    ctx.width, ctx.height, ctx.pix_fmt = width, height, "yuv420p"
    ctx.time_base, ctx.framerate = Fraction(1, 30), Fraction(30, 1)
    ctx.options = {"preset": "ultrafast", "tune": "zerolatency", "g": "10"}
    y, x = np.mgrid[0:height, 0:width]
    units: list[bytes] = []
    for i in range(n):
        img = np.stack([(x + 4 * i) % 256, (y * 2) % 256, np.full_like(x, 128)], -1).astype("uint8")
        frame = av.VideoFrame.from_ndarray(img, format="rgb24").reformat(format="yuv420p")
        frame.pts = i
        units.extend(bytes(p) for p in ctx.encode(frame))
    units.extend(bytes(p) for p in ctx.encode(None))
    return units


def test_h264_video_frames_become_compressed_video_a_decoder_plays(recorder, session_factory, tmp_path) -> None:
    units = _h264_frames(24)
    assert len(units) == 24 and units[0].startswith((b"\x00\x00\x00\x01", b"\x00\x00\x01"))
    svc = recorder()
    s = session_factory()
    pub = s.declare_publisher(keys.RobotKeys("sim1").key(keys.VIDEO_ULTRASOUND))
    time.sleep(0.3)
    assert client.start(s, session_id="h264").ok
    for seq, unit in enumerate(units, 1):
        pub.put(VideoFrame(source="ultrasound", width=160, height=120, encoding="h264", data=unit).stamp(seq).encode())
    wait_until(lambda: svc.status.messages >= len(units), message="all frames recorded")
    assert client.stop(s).ok
    topics = _by_topic(read_foxglove(tmp_path / "rec" / "h264"))
    video = topics["/sim1/ultrasound"]
    assert [r.schema for r in video] == ["foxglove.CompressedVideo"] * len(units)
    assert [r.msg.format for r in video] == ["h264"] * len(units)
    assert [r.msg.data for r in video] == units and [r.sequence for r in video] == list(range(1, len(units) + 1))
    assert video[0].msg.frame_id == "sim1/ultrasound"
    decoder = av.CodecContext.create("h264", "r")
    pictures = []
    for r in video:  # what the Foxglove app does: each message is one access unit, decoded in order
        pictures.extend(decoder.decode(av.Packet(r.msg.data)))
    pictures.extend(decoder.decode(None))
    assert len(pictures) == len(units) and {(p.width, p.height) for p in pictures} == {(160, 120)}


def test_a_failing_conversion_never_costs_the_raw_recording(recorder, session_factory, tmp_path, monkeypatch) -> None:
    def broken(self: fx.FoxgloveConverter, key: str, msg: Any) -> list[fx.FoxgloveMessage]:
        raise ZeroDivisionError("a bug in a conversion")

    monkeypatch.setattr(fx.FoxgloveConverter, "convert", broken)
    svc = recorder()
    s = session_factory()
    pub = s.declare_publisher(keys.RobotKeys("sim1").key(keys.STATE_FORCE))
    time.sleep(0.3)
    assert client.start(s, session_id="broken").ok
    for seq in range(1, 51):
        pub.put(ForceSample(force=[0.0, 0.0, 1.0]).stamp(seq).encode())
    wait_until(lambda: svc.status.messages >= 50, message="50 raw messages")
    stopped = client.stop(s)
    assert stopped.ok and svc.foxglove_errors == 50
    assert [r.sequence for r in iter_records(tmp_path / "rec" / "broken")] == list(range(1, 51))


def test_a_writer_behind_records_raw_first(recorder, session_factory, tmp_path, monkeypatch) -> None:
    svc = recorder()
    s = session_factory()
    pub = s.declare_publisher(keys.RobotKeys("sim1").key(keys.STATE_ROBOT))
    time.sleep(0.3)
    assert client.start(s, session_id="behind").ok
    pub.put(RobotState().stamp(1).encode())
    wait_until(lambda: svc.status.messages >= 1, message="the first message")
    # From here the writer sees a backlog of a tenth of its inbox: the Foxglove channels yield.
    monkeypatch.setattr(type(svc._inbox), "__len__", lambda self: svc.config.inbox_max // 10)
    for seq in range(2, 31):
        pub.put(RobotState().stamp(seq).encode())
    wait_until(lambda: svc.status.messages >= 30, message="30 raw messages")
    monkeypatch.undo()
    assert client.stop(s).ok and svc.foxglove_skipped == 29
    assert [r.sequence for r in iter_records(tmp_path / "rec" / "behind")] == list(range(1, 31))
    assert [r.sequence for r in read_foxglove(tmp_path / "rec" / "behind")] == [1]


def test_foxglove_channels_can_be_turned_off_or_left_without_video(recorder, session_factory, tmp_path) -> None:
    k = keys.RobotKeys("sim1")
    for session_id, options in (("off", {"enabled": False}), ("novideo", {"video": False})):
        svc = recorder(foxglove=options)
        s = session_factory()
        robot, cam = s.declare_publisher(k.key(keys.STATE_ROBOT)), s.declare_publisher(k.key(keys.VIDEO_CAMERA))
        time.sleep(0.3)
        assert client.start(s, session_id=session_id).ok
        for seq in range(1, 6):
            robot.put(RobotState().stamp(seq).encode())
            cam.put(VideoFrame(width=4, height=2, data=b"\xff\xd8\xff\xd9").stamp(seq).encode())
        wait_until(lambda svc=svc: svc.status.messages >= 10, message="10 messages")
        assert client.stop(s).ok
        svc.shutdown()
    assert not (tmp_path / "rec" / "off" / FOXGLOVE).exists()
    topics = _by_topic(read_foxglove(tmp_path / "rec" / "novideo"))
    assert set(topics) == {"/sim1/tf"} and len(topics["/sim1/tf"]) == 5


def test_a_torn_foxglove_segment_is_repaired_at_the_next_start(recorder, session_factory, tmp_path) -> None:
    svc = recorder(flush_interval=0.05)
    s = session_factory()
    pub = s.declare_publisher(keys.RobotKeys("sim1").key(keys.STATE_FORCE))
    time.sleep(0.3)
    assert client.start(s, session_id="torn").ok
    for seq in range(1, 201):
        pub.put(ForceSample(force=[0.0, 0.0, 1.0]).stamp(seq).encode())
        if seq % 50 == 0:
            time.sleep(0.15)  # flushes: the file is a few chunks, as a recorder writes it over time
    wait_until(lambda: svc.status.messages >= 200, message="200 messages")
    assert client.stop(s).ok
    svc.shutdown()
    folder = tmp_path / "rec" / "torn"
    (seg,) = (folder / FOXGLOVE).glob("*.mcap")
    whole = len(read_foxglove(folder))
    data = seg.read_bytes()
    seg.write_bytes(data[: len(data) * 3 // 4])  # a killed recorder: no footer, the tail lost
    # As a killed recorder leaves it: "recording", and no live writer holds the session's lock.
    manifest = json.loads((folder / mf.MANIFEST).read_text())
    (folder / mf.MANIFEST).write_text(json.dumps({**manifest, "status": mf.RECORDING}))
    assert not has_footer(seg)
    recorder()  # start-up repairs
    assert has_footer(seg)
    assert 0 < len(read_foxglove(folder)) <= whole
    assert mf.Manifest.read(folder).status == mf.RECOVERED
