"""Nothing stale is shown as current in the twin's viewer: a dead edge's pictures, markers and preview ghost are
cleared, pictures and markers that stop are cleared, a preview ghost goes when its token expires, failure notices
pass the rate gates, and what the twin makes itself lands on the timeline after the edge's data whatever the edge's
clock. And the snapshot's force level is the newest one.

The visualiser tests record rerun calls in a fake recording stream (:class:`FakeRec`: path, archetypes, timeline
time, order) and answer "what does a viewer following the newest time show on this entity" with rerun's latest-at
rule (the row with the greatest (time, order); a ``Clear`` on the entity, or a recursive one on an ancestor,
hides what came before it). The real rerun recording is exercised by test_twin_viz.py and test_twin_browser.py.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
import rerun as rr

from iorthand import geometry, keys
from iorthand.config import ConfigError, from_dict
from iorthand.protocol import (
    ForceLevelState,
    ForceSample,
    MarkerPose,
    Markers,
    RobotState,
    SafetyStatus,
    VideoFrame,
)
from iorthand.transport import Inbox
from iorthand_cloud.twin import model
from iorthand_cloud.twin.config import TwinConfig
from iorthand_cloud.twin.state import TwinStore
from iorthand_cloud.twin.viz import Visualizer, VizFeeder

JPEG = b"\xff\xd8\xff\xd9"
CAMERA = "robots/a/tcp/camera/image"
ULTRASOUND = "robots/a/ultrasound"
MARKERS = "robots/a/markers"
PREVIEW = "robots/a/preview"
FORCE = "robots/a/tcp/force"
SKEW = 2_000_000_000  # ns


def config(**viewer: object) -> TwinConfig:
    return from_dict({"zenoh": {"mode": "peer"}, "viewer": {"serve": False, **viewer}}, TwinConfig, source="<test>")


@dataclass
class Row:
    path: str
    arch: list[Any]
    t: int
    order: int

    @property
    def kinds(self) -> list[str]:
        return [type(a).__name__ for a in self.arch]

    def clears(self, path: str) -> bool:
        for a in self.arch:
            if isinstance(a, rr.Clear):
                recursive = a.is_recursive.as_arrow_array().to_pylist()[0]
                return self.path == path or (recursive and path.startswith(self.path + "/"))
        return False


class FakeRec:
    """Records every rerun call of the visualiser (a stand-in for rr.RecordingStream, see the module docstring)."""

    def __init__(self) -> None:
        self.rows: list[Row] = []
        self.t = 0

    def set_time(self, timeline: str, timestamp: Any) -> None:
        self.t = int(np.datetime64(timestamp, "ns").astype(np.int64))

    def log(self, path: str, *arch: Any, static: bool = False) -> None:
        if not static:
            self.rows.append(Row(path, list(arch), self.t, len(self.rows)))

    def send_columns(self, *a: Any, **k: Any) -> None:
        pass

    def send_blueprint(self, *a: Any, **k: Any) -> None:
        pass

    def flush(self, *a: Any, **k: Any) -> None:
        pass

    def latest(self, path: str) -> Row | None:
        """The row a viewer at the newest time shows on ``path`` (None: nothing, or cleared)."""
        rows = [r for r in self.rows if r.path == path or r.clears(path)]
        if not rows:
            return None
        row = max(rows, key=lambda r: (r.t, r.order))
        return None if row.clears(path) else row

    def on(self, path: str) -> list[Row]:
        return [r for r in self.rows if r.path == path]

    def newest_t(self, path: str) -> int:
        return max(r.t for r in self.on(path))


def pump(viz: Visualizer) -> None:
    while (item := viz.queue.get(timeout=0.01)) is not None:
        viz._handle(item)


def make(**viewer: object) -> tuple[Visualizer, FakeRec]:
    rec = FakeRec()
    viz = Visualizer(config(**viewer), rec)  # type: ignore[arg-type]
    viz.feeder.robot_added("a", 0)
    return viz, rec


def show_everything(viz: Visualizer, now: float, t: int) -> None:
    """A live edge: pose, force, a camera and an ultrasound picture, a marker, an accepted preview (ttl 10 s)."""
    f = viz.feeder
    f.offer("a", keys.STATE_ROBOT, RobotState(tcp_pose=[0.3, 0, 0.2, math.pi, 0, 0]).stamp(1, t), now)
    f.offer("a", keys.STATE_FORCE_LEVEL, ForceLevelState(level=1, stale=False, value=6.5).stamp(1, t), now)
    f.offer("a", keys.STATE_FORCE, ForceSample(force=[0, 0, 6.5]).stamp(1, t), now)
    m = geometry.flatten(np.eye(4))
    f.offer("a", keys.MARKERS, Markers(markers=[MarkerPose(id=3, pose=m, raw=m)]).stamp(1, t), now)
    f.offer("a", keys.VIDEO_CAMERA, VideoFrame(source="camera", width=2, height=2, data=JPEG).stamp(1, t), now)
    f.offer("a", keys.VIDEO_ULTRASOUND, VideoFrame(source="ultrasound", width=2, height=2, data=JPEG).stamp(1, t), now)
    f.preview("a", {"name": "home", "ok": True, "duration": 2.0, "token": "tok", "ttl": 10.0,
                    "path": [[0.3, 0, 0.2], [0.32, 0.05, 0.25]], "goal": [0.32, 0.05, 0.25, math.pi, 0, 0]})
    pump(viz)


# ---------------------------------------------------------------------------------------------------------- 1


def test_an_offline_edge_leaves_no_picture_marker_or_preview_ghost_that_looks_live():
    viz, rec = make()
    show_everything(viz, time.monotonic(), time.time_ns())
    for path in (CAMERA, ULTRASOUND, MARKERS, f"{MARKERS}/axes", f"{PREVIEW}/path", f"{PREVIEW}/arm"):
        assert rec.latest(path) is not None, path
    viz.feeder.online("a", False)
    pump(viz)
    for path in (CAMERA, ULTRASOUND, MARKERS, f"{MARKERS}/axes", f"{PREVIEW}/path", f"{PREVIEW}/goal", f"{PREVIEW}/arm"):
        assert rec.latest(path) is None, f"{path} still shows {rec.latest(path)}"
    arrow = rec.latest(FORCE)
    assert arrow is not None and arrow.arch[0].colors.as_arrow_array().to_pylist() == rec_colour(model.COLOURS["grey"])
    arm = rec.latest("robots/a/arm")
    assert arm is not None and arm.arch[0].colors.as_arrow_array().to_pylist() == rec_colour(model.COLOURS["grey"])


def rec_colour(rgba: tuple[int, int, int, int]) -> list[int]:
    return rr.Arrows3D(vectors=[[0, 0, 1]], colors=[rgba]).colors.as_arrow_array().to_pylist()


def test_pictures_and_markers_that_stop_are_cleared_after_media_stale_after_and_return_with_the_next():
    viz, rec = make()
    now = time.monotonic()
    show_everything(viz, now, time.time_ns())
    viz._tick(time.monotonic() + 1.5)  # within media_stale_after: still live
    for path in (CAMERA, ULTRASOUND, MARKERS):
        assert rec.latest(path) is not None, path
    viz._tick(time.monotonic() + 2.5)  # nothing new for 2.5 s (the edge still online: e.g. its media child hangs)
    for path in (CAMERA, ULTRASOUND, MARKERS, f"{MARKERS}/axes"):
        assert rec.latest(path) is None, f"{path} still shows {rec.latest(path)}"
    lines = [r.arch[0].text.as_arrow_array().to_pylist()[0] for r in rec.on("robots/a/events")]
    warnings = [line for line in lines if "cleared" in line]
    assert len(warnings) == 3, lines  # each says why the picture went
    n = len(rec.rows)
    viz._tick(time.monotonic() + 5.0)  # cleared once, not at every tick
    assert all(r.path != CAMERA for r in rec.rows[n:])
    # The next picture and markers are shown again (the same marker pose too: it is not "unchanged" any more).
    m = geometry.flatten(np.eye(4))
    later = time.monotonic() + 1.0
    viz.feeder.offer("a", keys.VIDEO_CAMERA, VideoFrame(source="camera", width=2, height=2, data=JPEG).stamp(2), later)
    viz.feeder.offer("a", keys.MARKERS, Markers(markers=[MarkerPose(id=3, pose=m, raw=m)]).stamp(2), later)
    pump(viz)
    assert rec.latest(CAMERA) is not None and rec.latest(MARKERS) is not None


def test_the_preview_ghost_goes_when_its_token_expires():
    viz, rec = make()
    asked = time.monotonic()
    viz.feeder.preview("a", {"name": "home", "ok": True, "duration": 2.0, "token": "tok", "ttl": 0.5,
                             "path": [[0.3, 0, 0.2], [0.32, 0.05, 0.25]], "goal": [0.32, 0.05, 0.25, math.pi, 0, 0]})
    pump(viz)
    viz._tick(asked + 0.3)
    assert rec.latest(f"{PREVIEW}/path") is not None
    viz._tick(time.monotonic() + 0.6)
    assert rec.latest(f"{PREVIEW}/path") is None and rec.latest(f"{PREVIEW}/goal") is None
    # A refused plan has no token and no ttl: its red ghost goes too, after a while.
    viz.feeder.preview("a", {"name": "far", "ok": False, "path": [[0.3, 0, 0.2], [0.9, 0, 0.2]], "goal": []})
    pump(viz)
    viz._tick(time.monotonic() + 1.0)
    assert rec.latest(f"{PREVIEW}/path") is not None
    viz._tick(time.monotonic() + 60.0)
    assert rec.latest(f"{PREVIEW}/path") is None


def test_media_stale_after_must_cover_two_frames():
    assert config().viewer.media_stale_after == 2.0  # the edge's video stall_timeout
    assert config(image_fps=1.0, markers_hz=1.0).viewer.media_stale_after == 2.0  # the browser test's rates
    with pytest.raises(ConfigError, match="media_stale_after"):
        config(image_fps=0.5)


# ---------------------------------------------------------------------------------------------------------- 2


def test_failure_notices_and_their_end_pass_the_rate_gates():
    q = Inbox(64, keep="newest")
    f = VizFeeder(config(image_fps=10.0, markers_hz=10.0), q)
    now = 100.0
    m = geometry.flatten(np.eye(4))
    f.offer("a", keys.VIDEO_ULTRASOUND, VideoFrame(source="ultrasound", width=2, height=2, data=JPEG).stamp(1), now)
    f.offer("a", keys.MARKERS, Markers(markers=[MarkerPose(id=3, pose=m, raw=m)]).stamp(1), now)
    # 20 ms later (within the 100 ms slot): the probe is unplugged, the media child is killed.
    f.offer("a", keys.VIDEO_ULTRASOUND, VideoFrame(source="ultrasound", failure="probe unplugged").stamp(2), now + 0.02)
    f.offer("a", keys.MARKERS, Markers(failure="media process killed").stamp(2), now + 0.02)
    # 20 ms after that, pictures flow again: the first one ends the failure and goes too.
    f.offer("a", keys.VIDEO_ULTRASOUND, VideoFrame(source="ultrasound", width=2, height=2, data=JPEG).stamp(3), now + 0.04)
    f.offer("a", keys.MARKERS, Markers(markers=[MarkerPose(id=3, pose=m, raw=m)]).stamp(3), now + 0.04)
    # Ordinary frames are still thinned.
    f.offer("a", keys.VIDEO_ULTRASOUND, VideoFrame(source="ultrasound", width=2, height=2, data=JPEG).stamp(4), now + 0.06)
    f.offer("a", keys.MARKERS, Markers(markers=[MarkerPose(id=3, pose=m, raw=m)]).stamp(4), now + 0.06)
    passed = [(it.kind, it.t_ns and (it.data[1] if it.kind == "image" else it.data).seq) for it in q.drain()]
    assert passed == [("image", 1), ("markers", 1), ("image", 2), ("markers", 2), ("image", 3), ("markers", 3)]


def test_a_failure_notice_right_after_a_frame_clears_the_picture():
    viz, rec = make()
    now = time.monotonic()
    show_everything(viz, now, time.time_ns())
    viz.feeder.offer("a", keys.VIDEO_ULTRASOUND,
                     VideoFrame(source="ultrasound", failure="probe unplugged").stamp(2), now + 0.02)
    viz.feeder.offer("a", keys.MARKERS, Markers(failure="media process killed").stamp(2), now + 0.02)
    pump(viz)
    assert rec.latest(ULTRASOUND) is None and rec.latest(MARKERS) is None


# ---------------------------------------------------------------------------------------------------------- 3


def _colour_of(row: Row | None) -> list[int] | None:
    return None if row is None else row.arch[0].colors.as_arrow_array().to_pylist()


@pytest.mark.parametrize("skew", [SKEW, -SKEW], ids=["edge clock 2 s ahead", "edge clock 2 s behind"])
def test_a_silent_sensor_shows_stale_and_a_live_one_live_whatever_the_edges_clock(skew):
    viz, rec = make(force_batch_s=0.01, stale_after=0.5)
    f = viz.feeder
    now = time.monotonic()
    f.offer("a", keys.STATE_FORCE_LEVEL, ForceLevelState(level=2, stale=False, value=9.0).stamp(1, time.time_ns() + skew), now)
    f.offer("a", keys.STATE_FORCE, ForceSample(force=[0, 0, 9.0]).stamp(1, time.time_ns() + skew), now)
    f.offer("a", keys.STATE_FORCE, ForceSample(force=[0, 0, 9.0]).stamp(2, time.time_ns() + skew), now + 0.02)
    pump(viz)
    red, grey = rec_colour(model.COLOURS["red"]), rec_colour(model.COLOURS["grey"])
    assert _colour_of(rec.latest(FORCE)) == red
    viz._tick(time.monotonic() + 1.0)  # the sensor went silent
    assert _colour_of(rec.latest(FORCE)) == grey, "a silent sensor must show stale"
    # The sensor speaks again, stamped by the edge's clock: the arrow is live again.
    f.offer("a", keys.STATE_FORCE, ForceSample(force=[0, 0, 9.0]).stamp(3, time.time_ns() + skew), time.monotonic() + 2)
    f.offer("a", keys.STATE_FORCE, ForceSample(force=[0, 0, 9.0]).stamp(4, time.time_ns() + skew), time.monotonic() + 2.1)
    pump(viz)
    assert _colour_of(rec.latest(FORCE)) == red, "a live sensor must not show stale"


@pytest.mark.parametrize("skew", [SKEW, -SKEW], ids=["edge clock 2 s ahead", "edge clock 2 s behind"])
def test_offline_and_preview_land_after_the_edges_data_whatever_its_clock(skew):
    viz, rec = make()
    show_everything(viz, time.monotonic(), time.time_ns() + skew)
    # The ghost is on the timeline with the robot's data, not 2 s before or after them.
    assert 0 <= rec.newest_t(f"{PREVIEW}/path") - rec.newest_t("robots/a/tcp") < 1_000_000_000
    viz.feeder.online("a", False)
    pump(viz)
    for path in (CAMERA, ULTRASOUND, MARKERS, f"{PREVIEW}/path"):
        assert rec.latest(path) is None, f"{path} still shows {rec.latest(path)}"
    # Online again: the edge's next data come after the offline greying.
    viz.feeder.online("a", True)
    pump(viz)
    show_everything(viz, time.monotonic() + 3, time.time_ns() + skew)
    assert rec.latest(CAMERA) is not None and rec.latest(ULTRASOUND) is not None and rec.latest(MARKERS) is not None
    assert rec.latest(f"{PREVIEW}/path") is not None
    assert _colour_of(rec.latest(FORCE)) == rec_colour(model.COLOURS["yellow"])  # live again, not the offline grey


# ---------------------------------------------------------------------------------------------------------- 4


def test_the_snapshot_force_level_is_the_newest_of_safety_status_and_force_level():
    store = TwinStore()
    k = keys.RobotKeys("r1")
    t0 = time.time_ns()
    # A force level from 5 s ago is read after the safety status of now: the newer status wins.
    store.ingest(k.key(keys.STATE_SAFETY), SafetyStatus(armed=True, force_level=2, force_stale=True).stamp(5, t0).encode(), t0)
    store.ingest(k.key(keys.STATE_FORCE_LEVEL),
                 ForceLevelState(level=0, stale=False, value=1.0).stamp(1, t0 - 5_000_000_000).encode(), t0)
    s = store.snapshot("r1")
    assert (s.force_level, s.force_stale) == (2, True)
    assert s.force_value == pytest.approx(1.0)
    # A newer force level than the status: it wins.
    store.ingest(k.key(keys.STATE_FORCE_LEVEL), ForceLevelState(level=1, stale=False, value=6.5).stamp(2, t0 + 1).encode(), t0)
    s = store.snapshot("r1")
    assert (s.force_level, s.force_stale) == (1, False)
    # Only one of the two known: that one.
    store2 = TwinStore()
    store2.ingest(k.key(keys.STATE_SAFETY), SafetyStatus(armed=True, force_level=1, force_stale=False).stamp(1, t0).encode(), t0)
    s = store2.snapshot("r1")
    assert (s.force_level, s.force_stale) == (1, False)
