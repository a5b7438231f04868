"""Motion primitives: approach(marker, standoff), a zig-zag sweep in contact mode, the retreat to the safe pose.

Each is previewed (the single-use token), runs through the same safety core, reports its progress, and is
preempted by a deadman release, a stop or a new goal. The sweeps run on the curved phantoms in simulated time
(tests/sim_loop.py: the real supervisor, goto, robot model and phantom on a fake clock); the live edge runs them
in tests/test_primitives_live.py."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from iorthand import geometry, motion
from iorthand.protocol import ControlReply, ForceLevel, Status
from iorthand_edge.force.contact import PhantomConfig
from iorthand_edge.goto import GotoConfig, GotoController
from tests.sim_loop import CONTROL_PERIOD, CYLINDER, START_ABOVE, SimEdge, within

TARGET = 4.0
# 5 lanes of 60 mm at 5 mm/s, 8 mm apart: 66.6 s of sweeping.
SWEEP = {"width": 0.06, "pitch": 0.008, "lanes": 5, "speed": 0.005}
LIMITS = motion.Limits(0.03, 0.2, 0.25, (0.1, -0.3, 0.02), (0.45, 0.3, 0.45))
HERE = np.array([0.30, 0.0, 0.20, math.pi, 0.0, 0.0])


# ------------------------------------------------------------------------------------------------ planning

def test_a_sweep_is_a_zig_zag_of_lanes_at_its_speed() -> None:
    route = motion.plan_route(motion.SWEEP, HERE, LIMITS, {}, params={"width": 0.04, "pitch": 0.01, "lanes": 3,
                                                                      "speed": 0.004})
    assert route.ok and route.planar
    assert [leg.goal[0] - leg.start[0] for leg in route.legs] == pytest.approx([0.04, 0, -0.04, 0, 0.04])
    assert [leg.goal[1] - leg.start[1] for leg in route.legs] == pytest.approx([0, 0.01, 0, 0.01, 0])
    assert route.labels[0] == "lane 1 of 3" and route.labels[1] == "step to lane 2 of 3"
    assert route.duration > 0.14 / 0.004  # 140 mm at no more than 4 mm/s
    summary = route.summary()
    assert summary["legs"] == 5 and summary["planar"] and len(summary["path"]) >= 10
    # Never faster than the profile: asking 0.25 m/s on the remote profile's 8 mm/s.
    slow = motion.Limits(0.008, 0.1, 0.25, LIMITS.workspace_min, LIMITS.workspace_max)
    fast = motion.plan_route(motion.SWEEP, HERE, slow, {}, params={"speed": 0.25, "lanes": 1})
    assert fast.duration >= 0.06 / 0.008


@pytest.mark.parametrize(("params", "named"), [
    ({"width": -0.01}, "width"),
    ({"lanes": 500}, "lanes"),
    ({"pitch": "wide"}, "pitch"),
    ({"speed": float("nan")}, "speed"),
    ({"depth": 0.01}, "unknown parameter(s) depth"),
])
def test_bad_sweep_parameters_are_refused_by_name(params, named) -> None:
    route = motion.plan_route(motion.SWEEP, HERE, LIMITS, {}, params=params)
    assert not route.ok and named in route.reason


def test_a_sweep_leaving_the_workspace_is_refused_with_its_lane() -> None:
    route = motion.plan_route(motion.SWEEP, HERE, LIMITS, {}, params={"width": 0.2, "lanes": 2})
    assert not route.ok and "lane 1 of 2" in route.reason and "workspace" in route.reason


def test_the_summary_of_the_longest_sweep_fits_a_reply_with_its_corners() -> None:
    """99 legs: two points each would be ~5 KB, over ControlReply.detail's 4 KB (the preview reached the operator
    as a malformed reply). The corners, thinned to the summary's 60 points, start and end where the sweep does."""
    route = motion.plan_route("sweep", HERE, LIMITS, {}, params={"lanes": 50, "width": 0.15, "pitch": 0.001})
    assert route.ok and len(route.legs) == 99
    out = route.summary()
    assert len(json.dumps(out)) <= ControlReply.max_len("detail")
    assert len(out["path"]) == 60
    assert out["path"][0] == [round(float(v), 4) for v in HERE[:3]]
    assert out["path"][-1] == [round(float(v), 4) for v in route.goal[:3]]
    assert len(motion.plan_route("sweep", HERE, LIMITS, {}, params=SWEEP).summary()["path"]) <= 60


def test_approach_and_retreat() -> None:
    marker = geometry.translation(0.32, 0.02, 0.10)  # T_base_marker: lying face up on the table
    route = motion.plan_route(f"{motion.APPROACH}7", HERE, LIMITS, {}, {7: marker}, params={"standoff": 0.05})
    assert route.ok and route.goal[2] == pytest.approx(0.15, abs=1e-6) and route.goal[:2] == pytest.approx([0.32, 0.02])
    missing = motion.plan_route(f"{motion.APPROACH}8", HERE, LIMITS, {}, {7: marker})
    assert not missing.ok and "8" in missing.reason
    home = [0.25, 0.0, 0.30, math.pi, 0.0, 0.0]
    retreat = motion.plan_route(motion.RETREAT, HERE, LIMITS, {"home": home}, retract_distance=0.05)
    assert retreat.ok and len(retreat.legs) == 2 and retreat.labels == ["up, away from the patient", "to the safe pose"]
    assert retreat.legs[0].goal[2] == pytest.approx(0.25) and retreat.goal[:3] == pytest.approx(home[:3])
    assert motion.plan_route(motion.RETREAT, HERE, LIMITS, {}, params={"x": 1}).reason.startswith("retreat: unknown")


@pytest.mark.parametrize("name", [motion.SWEEP, motion.RETREAT])
def test_every_leg_of_a_route_is_solved_from_the_joints_the_leg_before_left(name: str) -> None:
    """A route of several legs is one motion of the arm: its first leg starts from the arm's joints now (here an
    elbow-down arm, not the home posture's branch) and each next leg from where the one before left them. Solved
    each on its own, the sweep's legs were checked on the home posture's branch, not the arm's: a flip between
    the arm and the plan, or between two legs, was never seen."""
    from iorthand import kinematics

    arm = kinematics.model(LIMITS.model)
    usual = kinematics.solve_near(arm, HERE)
    q_now = next(q for q in kinematics.inverse(arm, HERE) if not np.allclose(q, usual) and q[1] < -1.5)
    route = motion.plan_route(name, HERE, LIMITS, {"home": [0.25, 0.0, 0.30, math.pi, 0.0, 0.0]}, reference_q=q_now,
                              params={"lanes": 3} if name == motion.SWEEP else None)
    assert route.ok and len(route.legs) > 1, route.reason
    assert np.allclose(route.legs[0].joints[0], q_now, atol=1e-6)
    for before, leg in zip(route.legs, route.legs[1:], strict=False):
        assert np.allclose(leg.joints[0], before.joints[-1], atol=1e-6)


def test_a_move_to_a_marker_runs_only_while_the_marker_is_where_the_preview_saw_it() -> None:
    """The preview planned on the marker then in view; a start up to the token's 10 s later, or the move itself,
    must not aim at where the patient was. A marker out of view during the move goes on (the probe hides it)."""
    ctl = GotoController(GotoConfig(), LIMITS.workspace_min, LIMITS.workspace_max)
    marker = geometry.translation(0.32, 0.02, 0.10)
    moved = geometry.translation(0.32, 0.03, 0.10)  # 10 mm: the patient moved
    name = f"{motion.APPROACH}7"

    def previewed() -> str:
        pv = ctl.preview(name, "op1", HERE, 0.0, LIMITS, markers={7: marker})
        assert pv.ok, pv.plan.reason
        return pv.token

    assert ctl.start(name, previewed(), "op1", HERE, 9.9, LIMITS, markers={}) == (
        False, "marker 7 is not in view now: preview again once it is")
    ok, why = ctl.start(name, previewed(), "op1", HERE, 1.0, LIMITS, markers={7: moved})
    assert not ok and why == "marker 7 moved 10.0 mm / 0.0° since the preview: preview again"
    turned = marker @ geometry.make_transform(geometry.rotvec_to_matrix([0.0, 0.2, 0.0]), [0.0, 0.0, 0.0])
    assert not ctl.start(name, previewed(), "op1", HERE, 1.0, LIMITS, markers={7: turned})[0]
    assert ctl.start(name, previewed(), "op1", HERE, 1.0, LIMITS, markers={7: marker})[0]
    assert np.any(ctl.twist(HERE, 1.1, contact_off="", markers={}))  # out of view: on
    assert not np.any(ctl.twist(HERE, 1.2, contact_off="", markers={7: moved}))
    assert not ctl.active and ctl.reason == "marker 7 moved 10.0 mm / 0.0° since the preview: move cancelled, preview again"


def test_the_edge_lists_its_primitives_with_their_defaults() -> None:
    listed = {p["name"]: p for p in motion.primitives([3], 0.12)}
    assert listed[motion.SWEEP]["params"] == motion.SWEEP_DEFAULTS and "contact mode" in listed[motion.SWEEP]["description"]
    assert listed["approach:3"]["params"] == {"standoff": 0.12} and motion.RETREAT in listed


# ------------------------------------------------------------------------------------------------ in contact

def _in_contact(stiffness: float, shape: dict | None = None) -> SimEdge:
    edge = SimEdge(PhantomConfig(**(shape or CYLINDER), stiffness=stiffness), START_ABOVE)
    edge.contact(True, TARGET)
    edge.run(10.0, until=lambda: edge.trace.force[-1] > TARGET - 0.5)  # deadman held: contact mode comes down
    assert edge.trace.force[-1] > TARGET - 0.5, "no contact"
    edge.run(1.0)
    return edge


@pytest.mark.parametrize("stiffness_n_per_mm", [2.0, 4.0, 8.0])
def test_a_minute_of_sweeping_the_curved_phantom_holds_the_force(stiffness_n_per_mm: float) -> None:
    edge = _in_contact(1000 * stiffness_n_per_mm)
    edge.start(motion.SWEEP, SWEEP)
    t0 = edge.clock.t
    edge.run(120.0, until=lambda: not edge.goto.active)
    assert edge.goto.status == "done", edge.goto.reason
    assert edge.clock.t - t0 >= 60.0
    share, rms, worst = within(edge.trace, TARGET, t0)
    assert share >= 0.95, f"{100 * share:.1f} % within ±1 N (RMS {rms:.2f} N, max {worst:.2f} N)"
    assert edge.trace.peak_level < ForceLevel.DANGER
    # Progress, lane by lane, on the console's status line.
    lanes = [p for p in edge.trace.progress if "lane 3 of 5" in p]
    assert lanes and any(p.startswith("sweep: 5") for p in edge.trace.progress)
    end = edge.robot.read_state().tcp_pose
    assert end[0] == pytest.approx(START_ABOVE[0] + SWEEP["width"], abs=0.001)
    assert end[1] == pytest.approx(START_ABOVE[1] + 4 * SWEEP["pitch"], abs=0.001)


def test_sweeping_the_abdomen_like_ellipsoid_holds_the_force() -> None:
    ellipsoid = dict(shape="ellipsoid", semi_axes=[0.10, 0.08, 0.06], base_z=0.09, x_range=[0.20, 0.40],
                     y_range=[-0.10, 0.10], damping=20.0)
    edge = _in_contact(4000.0, ellipsoid)
    edge.start(motion.SWEEP, {"width": 0.04, "pitch": 0.01, "lanes": 3, "speed": 0.005})
    t0 = edge.clock.t
    edge.run(60.0, until=lambda: not edge.goto.active)
    assert edge.goto.status == "done", edge.goto.reason
    share, rms, worst = within(edge.trace, TARGET, t0)
    assert share >= 0.95, f"{100 * share:.1f} % within ±1 N (RMS {rms:.2f} N, max {worst:.2f} N)"
    assert edge.trace.peak_level < ForceLevel.DANGER


def test_a_sweep_needs_contact_mode() -> None:
    edge = SimEdge(PhantomConfig(**CYLINDER), START_ABOVE)
    here = edge.robot.read_state().tcp_pose
    pv = edge.goto.preview(motion.SWEEP, "op1", here, edge.clock.t, edge.limits())
    assert pv.ok
    ok, reason = edge.goto.start(motion.SWEEP, pv.token, "op1", here, edge.clock.t, edge.limits(), contact=False)
    assert not ok and "contact mode" in reason


# ------------------------------------------------------------------------------------------------ preemption

def _sweeping() -> SimEdge:
    edge = _in_contact(4000.0)
    edge.start(motion.SWEEP, SWEEP)
    edge.run(5.0)
    assert edge.goto.active
    return edge


def _stopped_within(edge: SimEdge, seconds: float) -> bool:
    edge.run(seconds, deadman=False)
    return bool(np.allclose(edge.robot.read_state().tcp_speed, 0.0, atol=1e-9))


def test_releasing_the_deadman_ends_the_sweep_at_once() -> None:
    edge = _sweeping()
    edge.command(deadman=False)  # the operator lets go
    stop_s = edge.safety.command_timeout + CONTROL_PERIOD
    assert not edge.goto.active and "deadman released" in edge.goto.reason
    assert _stopped_within(edge, stop_s)
    edge.run(3.0)  # the deadman pressed again: nothing resumes
    assert not edge.goto.active and np.allclose(edge.robot.read_state().tcp_speed[:2], 0.0, atol=1e-9)


def test_a_silent_operator_ends_the_sweep_at_the_command_timeout() -> None:
    edge = _sweeping()
    # No command at all (the console froze): the supervisor times out; its halt ends the move.
    end = edge.clock.t + edge.safety.command_timeout + 2 * CONTROL_PERIOD
    while edge.clock.t < end:
        edge.sample()
        decision = edge.sv.step(edge.clock.t, edge.robot.read_state().tcp_pose)
        if edge.goto.active and decision.status.halts:
            edge.goto.cancel(decision.reason)
        edge._drive(decision)
        edge.clock.t += CONTROL_PERIOD
    assert edge.sv.status == Status.COMMAND_TIMEOUT and not edge.goto.active
    assert "no command" in edge.goto.reason


def test_a_stop_and_a_new_goal_preempt_the_sweep() -> None:
    edge = _sweeping()
    edge.sv.stop("stop pressed on the console")
    edge.run(CONTROL_PERIOD * 2)
    assert not edge.goto.active and "stop" in edge.goto.reason
    edge = _sweeping()
    edge.start(motion.RETREAT)  # a new goal, while the sweep runs
    assert edge.goto.active and "preempted" not in edge.goto.reason
    assert edge.goto.reason.startswith("retreat: started")


def test_leaving_contact_mode_ends_the_sweep() -> None:
    """A sweep's height is the held force's: without contact mode nothing would follow the surface."""
    edge = _sweeping()
    edge.contact(False)
    edge.run(0.05)
    assert not edge.goto.active and "contact mode ended" in edge.goto.reason
    assert np.allclose(edge.robot.read_state().tcp_speed[:2], 0.0, atol=1e-9)


def test_goto_progress_names_each_leg() -> None:
    edge = SimEdge(PhantomConfig(**CYLINDER), START_ABOVE, goto=GotoConfig(poses={"home": [0.25, 0.0, 0.30, math.pi, 0, 0]}))
    edge.start(motion.RETREAT)
    edge.run(30.0, until=lambda: not edge.goto.active)
    assert edge.goto.status == "done", edge.goto.reason
    assert any("(up, away from the patient)" in p for p in edge.trace.progress)
    assert any("(to the safe pose)" in p for p in edge.trace.progress)
