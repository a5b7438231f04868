"""The force levels' and the previewed moves' rules, each pinned at its edge: found by mutation testing (a rule
changed by one operator or constant that the other tests still passed). Pure code on explicit times."""

from __future__ import annotations

import logging
import math
import threading
import time

import numpy as np
import pytest

from iorthand import geometry, motion
from iorthand.config import ConfigError, from_dict
from iorthand.protocol import ForceLevel, ForceLevelState
from iorthand_edge.force.config import ForceConfig
from iorthand_edge.force.levels import LevelConfig, LevelTracker, quantity_value
from iorthand_edge.force.monitor import ForceMonitor
from iorthand_edge.force.sensors import ForceSensor, SensorError, WrenchSample
from iorthand_edge.goto import GotoConfig, GotoController

# ------------------------------------------------------------------------------------------------ force levels


def test_a_force_sensor_silent_for_exactly_its_bound_is_fresh_and_stale_past_it() -> None:
    # 0.0 and 0.1 s: the silence is exactly stale_after (0.1 s) with no rounding between them.
    tracker = LevelTracker(LevelConfig())
    tracker.add([0, 0, 1.0, 0, 0, 0], 0.0)
    assert not tracker.state(0.1).stale
    assert tracker.state(math.nextafter(0.1, 1.0)).stale


def test_before_its_first_sample_a_sensor_reads_stale_with_no_force() -> None:
    state = LevelTracker(LevelConfig()).state(5.0)
    assert state.stale and state.level == ForceLevel.SAFE and state.value == 0.0 and state.last_sample == -math.inf


@pytest.mark.parametrize(
    ("data", "says"),
    [
        ({"caution": 8.0, "danger": 6.0}, "expected 0 < caution < danger"),
        ({"caution": 6.0, "danger": 6.0}, "expected 0 < caution < danger"),  # no room for yellow
        ({"caution": 0.0, "hysteresis": 0.0}, "expected 0 < caution < danger"),  # yellow with no force at all
        ({"hysteresis": 2.0}, "hysteresis 2.0 N must be smaller"),  # = danger − caution: red would skip yellow
        ({"caution": 1.0, "danger": 5.0, "hysteresis": 1.0}, "hysteresis 1.0 N must be smaller"),  # = caution
        ({"caution": 1.0, "danger": 5.0, "hysteresis": 1.5}, "hysteresis 1.5 N must be smaller"),  # > caution only
    ],
)
def test_a_level_configuration_that_breaks_a_rule_is_refused_naming_that_rule(data: dict, says: str) -> None:
    with pytest.raises(ConfigError, match=says):
        from_dict(data, LevelConfig)


def test_any_thresholds_with_room_between_them_are_accepted() -> None:
    assert from_dict({}, LevelConfig).thresholds == (6.0, 8.0)
    assert from_dict({"caution": 1.0, "danger": 2.0, "hysteresis": 0.2}, LevelConfig).thresholds == (1.0, 2.0)


def test_the_norm_is_of_the_force_alone_not_the_torques() -> None:
    assert quantity_value([0.0, 0.0, 0.0, 5.0, 5.0, 5.0], "norm") == 0.0
    assert quantity_value([3.0, 0.0, 4.0, 9.0, 9.0, 9.0], "norm") == 5.0


def test_with_the_norm_a_peak_inside_a_batch_counts() -> None:
    calm, spike = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0], [0.0, 6.0, 8.0, 0.0, 0.0, 0.0]
    assert quantity_value([calm, spike, calm], "norm") == 10.0
    assert LevelTracker(LevelConfig(quantity="norm")).add([calm, spike, calm], 1.0) == ForceLevel.DANGER


# ------------------------------------------------------------------------------------------------ force monitor


class _Quiet(ForceSensor):
    """Stands in for the hardware: the test hands the monitor its samples (tick), and sets ``errors`` and
    ``last_error`` as a sensor that rejected a sample does."""

    def start(self) -> None: ...
    def read(self, timeout: float) -> WrenchSample | None: return None
    def zero(self) -> None: ...
    def close(self) -> None: ...


class _Recorded:
    """Stands in for a Zenoh publisher: keeps what the monitor puts."""

    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def put(self, payload: bytes) -> None:
        self.sent.append(payload)


def _fz(newtons: float) -> WrenchSample:
    return WrenchSample(np.array([0.0, 0.0, newtons, 0.0, 0.0, 0.0]), 0)


def test_the_level_is_published_at_each_change_at_once_and_otherwise_at_its_heartbeat_rate() -> None:
    # Ticks of 1/128 s and a heartbeat of 8 Hz (1/8 s): every time below is exact in binary.
    monitor = ForceMonitor(ForceConfig(level_rate_hz=8.0), _Quiet(), [].append)
    monitor._pub_level = _Recorded()
    published: list[tuple[float, int]] = []
    for k in range(64):  # half a second
        now = 100.0 + k / 128
        sent = len(monitor._pub_level.sent)
        monitor.tick(_fz(7.0 if 20 <= k < 40 else 1.0), now)  # yellow from tick 20 to tick 39
        if len(monitor._pub_level.sent) > sent:
            published.append((now - 100.0, ForceLevelState.decode(monitor._pub_level.sent[-1]).level))
    # Fresh at 0 (a change), heartbeats every 16 ticks from the last message, each change in between at once.
    assert published == [(0.0, 0), (16 / 128, 0), (20 / 128, 1), (36 / 128, 1), (40 / 128, 0), (56 / 128, 0)]


def _logged(caplog: pytest.LogCaptureFixture) -> list[str]:
    lines = [r.getMessage() for r in caplog.records if r.name == "iorthand.edge.force"]
    caplog.clear()
    return lines


def test_a_level_change_while_fresh_is_logged_as_a_level_change_not_as_a_stale_spell(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="iorthand.edge.force")
    monitor = ForceMonitor(ForceConfig(), _Quiet(), [].append)
    monitor.tick(_fz(1.0), 10.0)
    assert _logged(caplog) == ["force sensor fresh again (level 0)"]
    monitor.tick(_fz(7.0), 10.01)
    assert _logged(caplog) == ["force level 0 → 1 (7.00 N)"]
    assert monitor.stale_since is None
    monitor.tick(None, 10.2)
    assert _logged(caplog) == ["force sensor stale: no sample for 190 ms — stopping, contact motion refused"]
    assert monitor.stale_since == 10.2


def test_a_stale_spell_names_the_sensors_reason_only_when_it_failed_since_its_last_sample(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.ERROR, logger="iorthand.edge.force")
    sensor = _Quiet()
    monitor = ForceMonitor(ForceConfig(), sensor, [].append)
    sensor.errors, sensor.last_error = 1, "bad status 0x2"  # an old error, before the samples below
    monitor.tick(_fz(1.0), 10.0)
    monitor.tick(None, 10.2)
    assert _logged(caplog) == ["force sensor stale: no sample for 200 ms — stopping, contact motion refused"]
    monitor.tick(_fz(1.0), 11.0)
    sensor.errors, sensor.last_error = 2, "frozen: 40 identical samples"  # why it went silent
    monitor.tick(None, 11.25)
    assert _logged(caplog) == [
        "force sensor stale: no sample for 250 ms (frozen: 40 identical samples) — stopping, contact motion refused"]


def test_a_sensor_whose_first_sample_is_not_a_number_is_logged_as_danger(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.ERROR, logger="iorthand.edge.force")
    monitor = ForceMonitor(ForceConfig(), _Quiet(), [].append)
    assert monitor.tick(_fz(math.nan), 10.0).level == ForceLevel.DANGER
    assert any("not numbers" in line and "level danger" in line for line in _logged(caplog))


class _PacedByTheRobot(_Quiet):
    """A sensor read from the robot state (as the simulated and the arm's own are): fails to start at first, and
    records how long each read was allowed to wait."""

    paced_by_robot = True

    def __init__(self) -> None:
        self.starts, self.closed = 0, 0
        self.timeouts: list[float] = []

    def start(self) -> None:
        self.starts += 1
        if self.starts == 1:
            raise SensorError("no state from the robot driver")

    def read(self, timeout: float) -> WrenchSample | None:
        self.timeouts.append(timeout)
        return _fz(1.0)

    def close(self) -> None:
        self.closed += 1


def test_a_sensor_that_cannot_start_is_retried_one_second_later_and_the_control_loop_never_waits_on_it() -> None:
    sensor = _PacedByTheRobot()
    monitor = ForceMonitor(ForceConfig(), sensor, [].append)
    monitor.on_robot_state(10.0)
    monitor.on_robot_state(10.99)
    assert sensor.starts == 1 and monitor.samples == 0
    assert not monitor.on_robot_state(11.0).stale and sensor.starts == 2
    assert sensor.timeouts == [0.0]  # read at once: the control loop's cycle does not wait for a sample
    monitor.join()
    assert sensor.closed == 1  # stopping the monitor releases the sensor


def test_invalid_samples_are_logged_once_per_new_count_with_the_last_reason(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="iorthand.edge.force")
    sensor = _PacedByTheRobot()
    sensor.starts = 1  # started at once
    monitor = ForceMonitor(ForceConfig(), sensor, [].append)
    sensor.errors, sensor.last_error = 1, "status word 0x8000"
    monitor.on_robot_state(10.0)
    monitor.on_robot_state(10.008)
    sensor.errors, sensor.last_error = 3, "saturated gauge"
    monitor.on_robot_state(10.016)
    assert _logged(caplog) == ["force sensor: 1 invalid samples so far, last: status word 0x8000",
                               "force sensor: 3 invalid samples so far, last: saturated gauge"]


class _Streaming(_Quiet):
    """A sensor with a stream of its own (a Net F/T): answers each read with a sample, and ends the test's loop
    after ``reads`` reads."""

    def __init__(self, stop: threading.Event, reads: int) -> None:
        self.stop, self.reads = stop, reads
        self.timeouts: list[float] = []

    def read(self, timeout: float) -> WrenchSample | None:
        self.timeouts.append(timeout)
        if len(self.timeouts) >= self.reads:
            self.stop.set()
        return _fz(1.0)


def test_a_sensor_with_a_stream_of_its_own_is_ticked_at_its_rate_each_read_waiting_at_most_half_a_period() -> None:
    stop = threading.Event()
    sensor = _Streaming(stop, reads=10)
    monitor = ForceMonitor(ForceConfig(rate_hz=100.0), sensor, [].append)
    monitor._started = True
    t0 = time.monotonic()
    monitor._loop(stop)  # the worker thread's body, here in the test's thread
    elapsed = time.monotonic() - t0
    assert sensor.timeouts == [0.005] * 10 and monitor.samples == 10
    # Ten ticks at 100 Hz span nine periods at least (a loaded machine only makes it longer): not a busy loop.
    assert elapsed >= 0.09 - 1e-3, elapsed


# ------------------------------------------------------------------------------------------------ previewed moves

WORKSPACE = ((0.1, -0.3, 0.02), (0.45, 0.3, 0.45))
LIMITS = motion.Limits(0.03, 0.2, 0.25, *WORKSPACE)
HERE = [0.30, 0.0, 0.20, math.pi, 0.0, 0.0]
HOME = [0.32, 0.05, 0.25, math.pi, 0.0, 0.0]


def _controller(**config: object) -> GotoController:
    return GotoController(from_dict({"poses": {"home": HOME}, **config}, GotoConfig), *WORKSPACE)


def test_the_tolerances_of_a_previewed_move_default_to_their_documented_values() -> None:
    c = GotoConfig()
    assert (c.token_ttl, c.start_tolerance, c.start_angle_tolerance) == (10.0, 0.005, 0.05)
    assert (c.marker_tolerance, c.marker_angle_tolerance, c.marker_max_age) == (0.005, 0.1, 0.5)
    assert (c.position_tolerance, c.angle_tolerance, c.max_tracking_error, c.settle_timeout) == (
        0.0005, 0.005, 0.01, 3.0)
    assert (c.retract_distance, c.marker_standoff) == (0.05, 0.10)


def test_with_goto_disabled_a_preview_is_refused_saying_why_and_gives_no_token() -> None:
    ctl = _controller(enabled=False)
    pv = ctl.preview("home", "op1", HERE, 0.0, LIMITS)
    assert not pv.ok and not pv.plan.ok and pv.token == "" and pv.ttl == 0.0
    detail = pv.detail()
    assert detail["reason"] == "preview/goto is disabled in this edge's configuration"
    assert not detail["inside_workspace"] and not detail["reachable"] and detail["token"] == ""
    assert ctl.start("home", "any", "op1", HERE, 0.0, LIMITS) == (
        False, "preview/goto is disabled in this edge's configuration")
    retract = ctl.preview(motion.RETRACT, "op1", HERE, 0.0, LIMITS)  # a move that needs no named pose, too
    assert not retract.ok and not retract.plan.ok and retract.token == ""


def test_a_preview_the_planner_did_not_answer_in_time_is_refused_with_the_planners_reason() -> None:
    def late(*_args: object) -> motion.Route:
        raise TimeoutError("the planner did not answer within 2 s")

    ctl = _controller()
    ctl.planner = late
    pv = ctl.preview("home", "op1", HERE, 0.0, LIMITS)
    assert not pv.ok and not pv.plan.ok and pv.token == ""
    assert pv.plan.reason == "the planner did not answer within 2 s: refused"


def test_a_goto_without_a_token_is_told_to_preview_first() -> None:
    assert _controller().start("home", "", "op1", HERE, 0.0, LIMITS) == (False, "no preview token: preview 'home' first")


def test_a_moves_token_is_valid_for_exactly_its_lifetime_even_across_another_preview() -> None:
    ctl = _controller(token_ttl=5.0)
    pv = ctl.preview("home", "op1", HERE, 1.0, LIMITS)
    ctl.preview("home", "op2", HERE, 6.0, LIMITS)  # another preview at the instant the first token turns 5 s old
    ok, why = ctl.start("home", pv.token, "op1", HERE, 6.0, LIMITS)
    assert ok, why


def test_cancelling_when_no_move_is_under_way_changes_nothing() -> None:
    ctl = _controller()
    assert not ctl.cancel("deadman released") and ctl.status == "idle" and ctl.reason == ""


def test_a_robot_within_its_start_tolerance_of_the_previews_start_may_start() -> None:
    ctl = _controller()
    settled = geometry.matrix_to_pose(geometry.pose_to_matrix(HERE) @ geometry.make_transform(
        geometry.rotvec_to_matrix([0.03, 0.0, 0.0]), [0.002, 0.0, 0.0]))  # 2 mm and 0.03 rad from it
    ok, why = ctl.start("home", ctl.preview("home", "op1", HERE, 0.0, LIMITS).token, "op1", settled, 0.1, LIMITS)
    assert ok, why


def test_a_marker_seen_within_its_tolerance_of_the_preview_jitter_does_not_refuse_nor_cancel_an_approach() -> None:
    ctl = _controller()
    marker = geometry.translation(0.32, 0.02, 0.10)
    jittered = marker @ geometry.make_transform(geometry.rotvec_to_matrix([0.0, 0.05, 0.0]), [0.002, 0.0, 0.0])
    name = f"{motion.APPROACH}7"
    pv = ctl.preview(name, "op1", HERE, 0.0, LIMITS, markers={7: marker})
    assert pv.ok, pv.plan.reason
    ok, why = ctl.start(name, pv.token, "op1", HERE, 0.1, LIMITS, markers={7: jittered})
    assert ok, why
    assert np.any(ctl.twist(HERE, 0.2, contact_off="", markers={7: jittered})) and ctl.active


@pytest.mark.parametrize(
    ("poses", "says"),
    [
        ({motion.SWEEP: HOME}, "poses.sweep: the name of a primitive"),
        ({motion.RETREAT: HOME}, "poses.retreat: the name of a primitive"),
        ({f"{motion.ABOVE_MARKER}3": HOME}, "':' is reserved for above_marker:<id>"),  # it would hide the marker's
        ({"home": HOME[:5]}, "poses.home: expected 6 numbers"),
    ],
)
def test_a_named_pose_that_would_hide_a_move_or_lacks_a_number_is_refused_by_name(poses: dict, says: str) -> None:
    with pytest.raises(ConfigError, match=says):
        from_dict({"poses": poses}, GotoConfig)


def _moving_home(ctl: GotoController) -> motion.Route:
    pv = ctl.preview("home", "op1", HERE, 0.0, LIMITS)
    ok, why = ctl.start("home", pv.token, "op1", HERE, 0.0, LIMITS)
    assert ok, why
    return pv.plan


def _shifted(pose: list[float], dx: float) -> list[float]:
    return [pose[0] + dx, *pose[1:]]


def test_a_move_follows_its_paths_velocity_and_never_exceeds_the_previews_speed_limit() -> None:
    ctl = _controller()
    route = _moving_home(ctl)
    leg = route.legs[0]
    direction = np.subtract(HOME[:3], HERE[:3]) / math.dist(HOME[:3], HERE[:3])
    # Mid-path, on the path: the twist is the path's cruise velocity, 30 mm/s along it (not only a correction).
    mid = route.duration / 2
    on_path, _ = motion.reference_at(leg, mid, LIMITS)
    v = ctl.twist(list(on_path), mid, contact_off="")[:3]
    assert np.linalg.norm(v) == pytest.approx(LIMITS.linear_speed, rel=1e-3)
    assert float(np.dot(v, direction)) == pytest.approx(LIMITS.linear_speed, rel=1e-3)
    assert ctl.reason == "home: 50 %"
    # Still at the start while the path is 9 mm ahead (under the 10 mm that cancels): the catch-up is clipped to
    # the limit, not passed on above it.
    behind = next(t for t in np.arange(0.0, route.duration, 0.001)
                  if math.dist(motion.reference_at(leg, float(t), LIMITS)[0][:3], HERE[:3]) >= 0.009)
    v = ctl.twist(HERE, float(behind), contact_off="")[:3]
    assert ctl.active and np.linalg.norm(v) == pytest.approx(LIMITS.linear_speed, rel=1e-9)


def test_after_its_path_a_move_settles_on_the_goal_then_is_done_and_stops() -> None:
    ctl = _controller()
    route = _moving_home(ctl)
    # 1 mm off the goal 1 s after the path's end: a correction of gain × 1 mm (3 mm/s) toward it, at 100 %.
    v = ctl.twist(_shifted(HOME, 0.001), route.duration + 1.0, contact_off="")
    assert v[:3] == pytest.approx([-0.003, 0.0, 0.0], abs=1e-6) and ctl.reason == "home: 100 %" and ctl.active
    # Within 0.5 mm: done, the move ends and moves nothing more.
    assert ctl.twist(_shifted(HOME, 0.0003), route.duration + 1.1, contact_off="").tolist() == [0.0] * 6
    assert not ctl.active and ctl.status == "done" and ctl.reason == "home: done (0.30 mm from its end)"
    assert not np.any(ctl.twist(_shifted(HOME, 0.0003), route.duration + 1.2, contact_off=""))


def test_a_move_that_does_not_settle_within_its_timeout_is_cancelled_and_stops() -> None:
    ctl = _controller()
    route = _moving_home(ctl)
    assert ctl.twist(_shifted(HOME, 0.001), route.duration + 3.5, contact_off="").tolist() == [0.0] * 6
    assert not ctl.active and ctl.status == "cancelled"
    assert ctl.reason == "did not settle on 'home' within 3 s (1.0 mm off)"


def test_only_a_move_to_a_marker_aims_at_one_and_only_a_sweep_is_planar() -> None:
    ctl = _controller()
    assert not ctl.aims_at_marker and not ctl.planar  # nothing under way
    _moving_home(ctl)
    assert not ctl.aims_at_marker and not ctl.planar
    marker = geometry.translation(0.32, 0.02, 0.10)
    name = f"{motion.APPROACH}7"
    pv = ctl.preview(name, "op1", HERE, 1.0, LIMITS, markers={7: marker})
    assert ctl.start(name, pv.token, "op1", HERE, 1.0, LIMITS, markers={7: marker})[0]
    assert ctl.aims_at_marker and not ctl.planar
    moved = geometry.translation(0.32, 0.03, 0.10)  # the patient moved 10 mm: the move ends, a zero twist
    assert ctl.twist(HERE, 1.1, contact_off="", markers={7: moved}).tolist() == [0.0] * 6 and not ctl.active


def test_cancelling_a_move_under_way_says_so_and_why() -> None:
    ctl = _controller()
    _moving_home(ctl)
    assert ctl.cancel("deadman released")
    assert (ctl.active, ctl.status, ctl.reason) == (False, "cancelled", "deadman released")
    assert ctl.twist(HERE, 0.5, contact_off="").tolist() == [0.0] * 6  # and nothing resumes it


def test_a_move_blocked_off_its_path_is_cancelled_with_a_zero_twist() -> None:
    ctl = _controller()
    _moving_home(ctl)
    assert ctl.twist(_shifted(HERE, -0.011), 0.0, contact_off="").tolist() == [0.0] * 6
    assert not ctl.active and ctl.reason == "11.0 mm off the planned path (max 10 mm): move cancelled"


def test_a_move_to_a_marker_is_refused_while_other_markers_but_not_its_own_are_in_view() -> None:
    ctl = _controller()
    marker = geometry.translation(0.32, 0.02, 0.10)
    name = f"{motion.APPROACH}7"
    pv = ctl.preview(name, "op1", HERE, 0.0, LIMITS, markers={7: marker})
    assert ctl.start(name, pv.token, "op1", HERE, 0.1, LIMITS, markers={3: marker}) == (
        False, "marker 7 is not in view now: preview again once it is")


@pytest.mark.parametrize("lowered", ["linear", "angular"])
def test_a_move_is_refused_when_either_speed_limit_is_lower_than_at_its_preview(lowered: str) -> None:
    ctl = _controller()
    pv = ctl.preview("home", "op1", HERE, 0.0, LIMITS)
    slower = motion.Limits(0.008 if lowered == "linear" else 0.03, 0.1 if lowered == "angular" else 0.2, 0.25,
                           *WORKSPACE)
    assert ctl.start("home", pv.token, "op1", HERE, 0.1, slower) == (
        False, "the speed limits are lower than at the preview (profile changed): preview again")
