"""The twin's pure parts: rate gates, force batches, colours, the drawing geometry, the drop-oldest queue,
and every visualiser handler run against an in-memory rerun recording (no viewer)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import rerun as rr

from iorthand import geometry, keys, kinematics
from iorthand.config import from_dict
from iorthand.protocol import (
    ForceLevelState,
    ForceSample,
    MarkerPose,
    Markers,
    RobotState,
    SafetyStatus,
    ServoState,
    VideoFrame,
)
from iorthand.transport import Inbox
from iorthand_cloud.twin import model
from iorthand_cloud.twin.config import RobotView, TwinConfig
from iorthand_cloud.twin.state import Event, TwinStore
from iorthand_cloud.twin.viz import ForceBatcher, RateGate, Visualizer, VizFeeder, blueprint


def config(**viewer: object) -> TwinConfig:
    return from_dict({"zenoh": {"mode": "peer"}, "viewer": {"serve": False, **viewer}}, TwinConfig, source="<test>")


def test_rate_gate_keeps_the_mean_rate():
    gate = RateGate(30.0)
    passed = sum(gate.due("r", t) for t in np.arange(0, 10, 1 / 125))
    assert passed == pytest.approx(300, abs=2)
    assert gate.due("other", 0.0)  # per key


def test_force_batcher_hands_over_every_period():
    b = ForceBatcher(0.1)
    out = [b.add("r", i, [0, 0, float(i)], i / 100) for i in range(31)]
    batches = [x for x in out if x is not None]
    assert len(batches) >= 2 and all(10 <= len(x.t_ns) <= 12 for x in batches)


def test_force_colours():
    assert model.force_colour(0, False) == model.COLOURS["green"]
    assert model.force_colour(1, False) == model.COLOURS["yellow"]
    assert model.force_colour(2, False) == model.COLOURS["red"]
    assert model.force_colour(2, True) == model.COLOURS["grey"]


def test_capsules_follow_the_links():
    arm = model.ArmModel(RobotView())
    q = arm.solve([0.30, 0.0, 0.20, math.pi, 0.0, 0.0])
    assert q is not None and arm.reachable
    caps = arm.capsules(q)
    pts = kinematics.link_points(arm.model, q)
    assert len(caps.lengths) >= 6 and np.all(caps.lengths > 0)
    # each capsule: start + R(quaternion)·[0,0,length] is the next point
    for t, qn, length in zip(caps.translations, caps.quaternions, caps.lengths, strict=True):
        x, y, z, w = qn
        r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        end = t + r @ [0, 0, length]
        assert np.min(np.linalg.norm(pts - end, axis=1)) < 1e-9
    # unreachable pose: keeps the last drawing, says so
    assert arm.solve([2.0, 0.0, 0.2, math.pi, 0, 0]) is None and not arm.reachable and arm.q is not None


def test_quaternions():
    for rv in ([0, 0, 0], [0.3, -0.2, 0.1], [math.pi, 0, 0], [0, 0, 3.0]):
        r = geometry.rotvec_to_matrix(rv)
        x, y, z, w = geometry.matrix_to_quaternion(r)
        assert np.allclose(geometry.rotvec_to_matrix(
            2 * math.acos(max(-1.0, min(1.0, w))) * np.array([x, y, z]) / max(np.linalg.norm([x, y, z]), 1e-12)), r,
            atol=1e-9)


def test_queue_drops_the_oldest_and_counts():
    q = Inbox(4, keep="newest")
    feeder = VizFeeder(config(pose_hz=500.0), q)
    for i in range(10):
        feeder.offer("r", keys.STATE_ROBOT, RobotState().stamp(i + 1, i + 1), now=i * 0.01)
    items = q.drain()
    assert [it.data.seq for it in items] == [7, 8, 9, 10] and q.dropped == 6


def test_store_events_on_changes_only():
    store = TwinStore()
    k = keys.RobotKeys("r1")
    for i, (level, stale) in enumerate([(0, True), (0, False), (0, False), (2, False), (2, False), (0, True)]):
        store.ingest(k.key(keys.STATE_FORCE_LEVEL), ForceLevelState(level=level, stale=stale).stamp(i + 1).encode(), 0)
    texts = [e.text for e in store.robots["r1"].events]
    assert texts[0] == "force sensor stale" and "safe" in texts[1] and "danger" in texts[2] and texts[3] == "force sensor stale"
    assert len(texts) == 4
    _, _, msg, _, _ = store.ingest(k.key(keys.STATE_ROBOT), b"\x00junk", 0)
    assert msg is None and store.robots["r1"].streams[keys.STATE_ROBOT].rejected == 1


def test_the_store_follows_at_most_max_robots_besides_the_configured_ones():
    store = TwinStore(max_robots=3, configured=["ward1"])
    safety = SafetyStatus().stamp(1).encode()
    for i in range(1000):  # a flood of new robot ids
        store.ingest(keys.RobotKeys(f"z{i}").key(keys.STATE_SAFETY), safety, 0)
    assert sorted(store.robots) == ["z0", "z1", "z2"]
    assert store.refused_robots == 997 and store.last_refused == "z999"
    robot, _, msg, _, new = store.ingest(keys.RobotKeys("ward1").key(keys.STATE_SAFETY), safety, 0)
    assert (robot, new) == ("ward1", True) and msg is not None  # a configured robot is never crowded out
    assert store.add_event("z5", "WARN", "preview refused") is None and store.set_online("z6", True) == (None, False)
    assert store.set_online("Not A Robot", True) == (None, False) and "Not A Robot" not in store.robots
    assert store.add_event("z1", "INFO", "kept") is not None  # robots it follows go on as before


def test_every_handler_logs_without_error_to_a_memory_recording():
    cfg = config(pose_hz=500.0, image_fps=60.0, markers_hz=100.0, force_batch_s=0.01)
    rec = rr.RecordingStream("iorthand-twin-test")
    mem = rec.memory_recording()
    drawn: list[tuple[str, list[float]]] = []
    viz = Visualizer(cfg, rec, on_drawn=lambda r, q: drawn.append((r, q)))
    viz.start()
    try:
        f = viz.feeder
        now = time.monotonic()
        f.robot_added("a", 0)
        f.robot_added("b", 1)
        f.offer("a", keys.STATE_ROBOT, RobotState(tcp_pose=[0.3, 0, 0.2, math.pi, 0, 0]).stamp(1), now)
        f.offer("a", keys.STATE_FORCE, ForceSample(force=[0, 0, 5.0]).stamp(1), now)
        f.offer("a", keys.STATE_FORCE_LEVEL, ForceLevelState(level=1, stale=False, value=6.5).stamp(1), now)
        f.offer("a", keys.STATE_SERVO, ServoState(pan=0.3, tilt=0.1).stamp(1), now)
        m = geometry.flatten(np.eye(4))
        f.offer("a", keys.MARKERS, Markers(markers=[MarkerPose(id=3, pose=m, raw=m)]).stamp(1), now)
        f.offer("a", keys.MARKERS, Markers(markers=[]).stamp(2), now + 1)  # marker 3 lost: cleared
        f.offer("a", keys.VIDEO_CAMERA, VideoFrame(width=2, height=2, data=b"\xff\xd8\xff\xd9").stamp(1), now)
        f.offer("b", keys.VIDEO_ULTRASOUND, VideoFrame(width=2, height=2, data=b"\xff\xd8\xff\xd9").stamp(1), now)
        f.offer("b", keys.VIDEO_ULTRASOUND, VideoFrame(width=2, height=2, failure="no frame").stamp(2), now + 1)
        f.event(Event("a", time.time_ns(), "WARN", "stopped: test"))
        f.online("a", False)
        f.preview("a", {"name": "home", "ok": True, "duration": 2.0, "path": [[0.3, 0, 0.2], [0.32, 0.05, 0.25]],
                        "goal": [0.32, 0.05, 0.25, math.pi, 0, 0]})
        f.preview("a", {"name": "far", "ok": False, "path": [], "goal": []})
        deadline = time.monotonic() + 5
        while (viz.handled < 14 or len(viz.queue)) and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        viz.stop()
    assert viz.errors == 0 and viz.handled >= 14
    assert drawn and drawn[0][0] == "a"
    assert len(mem.drain_as_bytes()) > 1000


def test_blueprint_lists_each_robots_images():
    bp = blueprint(["a", "b"])
    assert bp is not None
    assert blueprint([]) is not None


def test_store_says_when_the_edge_drops_commands_unread():
    """The edge's count of twists dropped unread is news only when it grows, and the line says by how much."""
    store = TwinStore()
    key = keys.RobotKeys("r1").key(keys.STATE_SAFETY)
    for i, count in enumerate([5, 5, 12, 12]):  # 5 before the twin joined: not news
        store.ingest(key, SafetyStatus(armed=True, superseded=count).stamp(i + 1).encode(), 0)
    news = [e for e in store.robots["r1"].events if "unread" in e.text]
    assert [(e.level, e.text.split(" commands")[0]) for e in news] == [("WARN", "the edge dropped 7")]


def test_store_says_when_perception_loses_and_regains_its_camera():
    """A Markers message with ``failure`` set is news when the failure starts or changes, and so is its end."""
    store = TwinStore()
    key = keys.RobotKeys("r1").key(keys.MARKERS)
    failures = ["", "camera 0 stopped delivering frames", "camera 0 stopped delivering frames", ""]
    for i, failure in enumerate(failures):
        store.ingest(key, Markers(failure=failure).stamp(i + 1).encode(), 0)
    news = [(e.level, e.text) for e in store.robots["r1"].events if "perception" in e.text]
    assert news == [
        ("WARN", "perception has no frames: camera 0 stopped delivering frames (the edge retries)"),
        ("INFO", "perception back: frames flow again"),
    ]


def test_store_says_when_a_video_source_fails_and_shows_no_picture_meanwhile():
    """A VideoFrame with ``failure`` is news when the failure starts or changes and when pictures return; the
    snapshot carries the reason and no image, so a client never shows the last picture as if it were live."""
    store = TwinStore()
    key = keys.RobotKeys("r1").key(keys.VIDEO_CAMERA)
    jpeg = b"\xff\xd8\xff\xd9"
    frames = [jpeg, b"", b"", jpeg]
    reasons = ["", "cannot open video device '/dev/video0'", "cannot open video device '/dev/video0'", ""]
    for i, (data, failure) in enumerate(zip(frames, reasons, strict=True)):
        store.ingest(key, VideoFrame(source="camera", width=640, height=480, data=data, failure=failure).stamp(i + 1).encode(), 0)
        if i == 1:
            (image,) = store.snapshot("r1", include_images=True).images
            assert (image.failure, image.data) == (reasons[1], b"")
    news = [(e.level, e.text) for e in store.robots["r1"].events if "video" in e.text]
    assert news == [
        ("WARN", "camera video has no frames: cannot open video device '/dev/video0' (the edge retries)"),
        ("INFO", "camera video back: frames flow again"),
    ]
    (image,) = store.snapshot("r1", include_images=True).images
    assert (image.failure, image.data) == ("", jpeg)


def test_vital_signs_are_plotted_per_name_with_their_unit(tmp_path) -> None:
    from rerun.chunk import RrdReader

    from iorthand.protocol import SensorReading

    cfg = config()
    rec = rr.RecordingStream("iorthand-twin-test")
    mem = rec.memory_recording()
    viz = Visualizer(cfg, rec)
    viz.start()
    try:
        now = time.monotonic()
        viz.feeder.robot_added("a", 0)
        for i, bpm in enumerate((72.0, 75.0, 80.0)):
            viz.feeder.offer("a", keys.SENSOR_VITAL, SensorReading(name="heart_rate", value=bpm, unit="bpm").stamp(i + 1),
                             now)
        viz.feeder.offer("a", keys.SENSOR_VITAL, SensorReading(name="sp o2", value=98.0, unit="%").stamp(9), now)
        deadline = time.monotonic() + 5
        while (viz.handled < 5 or len(viz.queue)) and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        viz.stop()
    assert viz.errors == 0
    path = tmp_path / "vitals.rrd"
    path.write_bytes(mem.drain_as_bytes())
    values: dict[str, list[float]] = {}
    names: dict[str, list[str]] = {}
    for chunk in RrdReader(str(path)).stream():
        batch = chunk.to_record_batch().to_pydict()
        if "/vitals/" not in chunk.entity_path:
            continue
        if "Scalars:scalars" in batch:
            values.setdefault(chunk.entity_path, []).extend(v[0] for v in batch["Scalars:scalars"])
        if "SeriesLines:names" in batch:
            names[chunk.entity_path] = [str(n) for n in batch["SeriesLines:names"][0]]
    assert values["/robots/a/vitals/heart_rate"] == [72.0, 75.0, 80.0]
    assert names["/robots/a/vitals/heart_rate"] == ["heart_rate (bpm)"]
    assert values[r"/robots/a/vitals/sp\ o2"] == [98.0]  # a name with a space stays one entity part


def test_the_default_phantom_is_drawn_where_the_demo_edge_has_it() -> None:
    """The twin draws the phantom the demo's simulated edge presses on (configs/edge-sim.yaml), so the probe is
    drawn touching it when the force sensor says it does, and its markers lie on it."""
    from pathlib import Path

    import yaml

    edge = yaml.safe_load((Path(__file__).resolve().parent.parent / "configs" / "edge-sim.yaml").read_text())
    phantom = next(o for o in RobotView().scene if o.name == "phantom")
    lo = np.subtract(phantom.center, np.divide(phantom.size, 2))
    hi = np.add(phantom.center, np.divide(phantom.size, 2))
    ph = edge["phantom"]
    assert hi[2] == pytest.approx(ph["surface_z"])
    assert [lo[0], hi[0]] == pytest.approx(ph["x_range"]) and [lo[1], hi[1]] == pytest.approx(ph["y_range"])
    for marker in edge["perception"]["scene"]["markers"]:
        x, y, z = marker["pose"][:3]
        assert lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and z == pytest.approx(hi[2]), marker
