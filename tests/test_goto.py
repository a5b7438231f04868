"""The edge's preview/goto logic, as pure code: tokens, refusals, and a previewed goto driving the simulated
robot through the real supervisor (limits, deadman) on a simulated clock until it reaches the pose.

The agent's queryables (plan/preview, control/goto) are wired by the lead; this tests everything else.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from iorthand import geometry
from iorthand.config import from_dict
from iorthand.protocol import TwistCommand
from iorthand_edge.goto import GotoConfig, GotoController
from iorthand_edge.robots.config import SimRobotConfig
from iorthand_edge.robots.sim import SimRobot
from iorthand_edge.supervisor import SafetyConfig, Supervisor
from tests.grants import Grants

START = [0.30, 0.0, 0.20, math.pi, 0.0, 0.0]
HOME = [0.32, 0.05, 0.25, math.pi, 0.0, 0.0]


class FakeClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def make(**goto: object) -> tuple[GotoController, SafetyConfig]:
    safety = from_dict({"auto_arm": True, "profile": "local"}, SafetyConfig)
    cfg = from_dict({"poses": {"home": HOME, "outside": [0.30, 0.0, 0.60, math.pi, 0.0, 0.0]}, **goto}, GotoConfig)
    ctl = GotoController(cfg, safety.workspace.min, safety.workspace.max)
    return ctl, safety


def limits_of(ctl: GotoController, safety: SafetyConfig):
    p = safety.profiles[safety.profile]
    return ctl.limits(p.linear, p.angular, safety.max_linear_acceleration)


def test_preview_inside_gives_a_token_and_the_path():
    ctl, safety = make()
    pv = ctl.preview("home", "op1", START, 0.0, limits_of(ctl, safety))
    assert pv.ok and pv.token
    d = pv.detail()
    assert d["inside_workspace"] and d["reachable"] and d["token"] == pv.token
    assert d["path"][0] == pytest.approx(START[:3], abs=1e-4) and d["path"][-1] == pytest.approx(HOME[:3], abs=1e-4)
    dist = math.dist(START[:3], HOME[:3])
    assert d["duration"] == pytest.approx(dist / 0.030 + 0.030 / 0.25, rel=0.02)


def test_preview_outside_the_workspace_is_refused_with_the_reason():
    ctl, safety = make()
    pv = ctl.preview("outside", "op1", START, 0.0, limits_of(ctl, safety))
    assert not pv.ok and pv.token == ""
    assert not pv.plan.inside_workspace
    assert "workspace" in pv.plan.reason and "z=" in pv.plan.reason


def test_preview_out_of_reach_and_unknown_pose_are_refused():
    ctl, safety = make(poses={"far": [0.44, 0.29, 0.44, math.pi, 0.0, 0.0]})
    pv = ctl.preview("far", "op1", START, 0.0, limits_of(ctl, safety))
    assert not pv.ok and not pv.plan.reachable and "reach" in pv.plan.reason
    pv = ctl.preview("nowhere", "op1", START, 0.0, limits_of(ctl, safety))
    assert not pv.ok and "unknown pose" in pv.plan.reason


def test_goto_without_a_valid_token_is_refused():
    ctl, safety = make(token_ttl=5.0)
    lim = limits_of(ctl, safety)
    ok, reason = ctl.start("home", "", "op1", START, 0.0, lim)
    assert not ok and "preview" in reason
    ok, reason = ctl.start("home", "deadbeef", "op1", START, 0.0, lim)
    assert not ok and "unknown" in reason
    # expired
    pv = ctl.preview("home", "op1", START, 0.0, lim)
    ok, reason = ctl.start("home", pv.token, "op1", START, 6.0, lim)
    assert not ok and "expired" in reason
    # another pose than previewed
    pv = ctl.preview("home", "op1", START, 10.0, lim)
    ok, reason = ctl.start("retract", pv.token, "op1", START, 10.5, lim)
    assert not ok and "issued for 'home'" in reason
    # single use: the token of a refused goto is consumed too
    ok, reason = ctl.start("home", pv.token, "op1", START, 10.6, lim)
    assert not ok and "already used" in reason
    # another operator
    pv = ctl.preview("home", "op1", START, 20.0, lim)
    ok, reason = ctl.start("home", pv.token, "op2", START, 20.1, lim)
    assert not ok and "op1" in reason
    # the robot moved since the preview
    pv = ctl.preview("home", "op1", START, 30.0, lim)
    moved = [START[0] + 0.02, *START[1:]]
    ok, reason = ctl.start("home", pv.token, "op1", moved, 30.1, lim)
    assert not ok and "moved" in reason
    # slower profile than at the preview
    pv = ctl.preview("home", "op1", START, 40.0, lim)
    slow = ctl.limits(0.008, 0.1, 0.25)
    ok, reason = ctl.start("home", pv.token, "op1", START, 40.1, slow)
    assert not ok and "speed limits" in reason
    assert not ctl.active


def test_previews_from_others_never_void_the_owners_tokens():
    """Found by a red-team run: 16 previews from a session holding nothing evicted the owner's token, and his
    goto was refused as "unknown or already used"."""
    ctl, safety = make(token_ttl=30.0)
    lim = limits_of(ctl, safety)
    mine = ctl.preview("home", "alice", START, 0.0, lim, owner="alice")
    for i in range(3 * ctl.max_tokens):
        assert ctl.preview("home", "mallory", START, 0.1 + i * 0.01, lim, owner="alice").token
    ok, reason = ctl.start("home", mine.token, "alice", START, 2.0, lim)
    assert ok, reason
    # The owner's own previews still bound his tokens: the oldest of them goes.
    first = ctl.preview("home", "alice", START, 3.0, lim, owner="alice")
    for i in range(ctl.max_tokens):
        ctl.preview("home", "alice", START, 3.1 + i * 0.01, lim, owner="alice")
    ok, reason = ctl.start("home", first.token, "alice", START, 4.0, lim)
    assert not ok and "unknown" in reason


def _drive(ctl: GotoController, safety: SafetyConfig, robot: SimRobot, clock: FakeClock, max_s: float,
           deadman_until: float = math.inf) -> None:
    """The agent's loop in miniature: the operator holds the deadman (a zero twist at 60 Hz), the goto
    replaces the velocity, the supervisor applies its rules, the robot moves."""
    period = robot.control_period
    sup = Supervisor(safety, period=period)
    grants = Grants()
    ok, _ = grants.acquire(sup, "op1", clock.t)
    assert ok
    seq = grants.seq  # after the grant's release
    next_cmd = clock.t
    end = clock.t + max_s
    t0 = clock.t
    while clock.t < end and ctl.active:
        pose = robot.read_state().tcp_pose
        if clock.t >= next_cmd:
            seq += 1
            held = clock.t - t0 < deadman_until
            cmd = TwistCommand(operator="op1", deadman=held, state_age=0.02).stamp(seq, int(clock.t * 1e9))
            goto = ctl.twist(pose, clock.t, contact_off=sup.contact_off_reason).tolist() if ctl.active else None
            decision = sup.on_command(grants.sign(sup, "op1", cmd), clock.t, clock.t, pose, goto)
            if decision.cancel_goto:
                ctl.cancel(decision.cancel_goto)
            next_cmd += 1 / 60
        decision = sup.step(clock.t, pose)
        if np.any(decision.twist):
            robot.send_twist(decision.twist, safety.max_linear_acceleration)
        else:
            robot.stop(safety.stop_deceleration)
        clock.t += period
    # let the robot come to rest
    for _ in range(100):
        robot.stop(safety.stop_deceleration)
        clock.t += period
        robot.read_state()


def test_previewed_goto_reaches_the_pose_within_1mm_through_the_supervisor():
    ctl, safety = make()
    clock = FakeClock()
    robot = SimRobot(SimRobotConfig(initial_pose=list(START)), clock=clock)
    robot.connect()
    lim = limits_of(ctl, safety)
    pv = ctl.preview("home", "op1", robot.read_state().tcp_pose, clock.t, lim)
    assert pv.ok
    ok, reason = ctl.start("home", pv.token, "op1", robot.read_state().tcp_pose, clock.t + 0.5, lim)
    assert ok, reason
    _drive(ctl, safety, robot, clock, max_s=pv.plan.duration + 5.0)
    assert ctl.status == "done", ctl.reason
    final = geometry.pose_to_matrix(robot.read_state().tcp_pose)
    goal = geometry.pose_to_matrix(HOME)
    assert geometry.translation_distance(final, goal) < 0.001
    assert geometry.rotation_angle(final, goal) < 0.01


def test_goto_with_rotation_and_retract_reach_the_pose():
    ctl, safety = make(poses={"tilted": [0.33, -0.03, 0.22, 3.0, 0.3, 0.1]})
    clock = FakeClock()
    robot = SimRobot(SimRobotConfig(initial_pose=list(START)), clock=clock)
    robot.connect()
    lim = limits_of(ctl, safety)
    for name in ("tilted", "retract"):
        here = robot.read_state().tcp_pose
        pv = ctl.preview(name, "op1", here, clock.t, lim)
        assert pv.ok, pv.plan.reason
        ok, reason = ctl.start(name, pv.token, "op1", here, clock.t, lim)
        assert ok, reason
        _drive(ctl, safety, robot, clock, max_s=pv.plan.duration + 5.0)
        assert ctl.status == "done", ctl.reason
        assert geometry.translation_distance(geometry.pose_to_matrix(robot.read_state().tcp_pose),
                                             geometry.pose_to_matrix(pv.plan.goal)) < 0.001


def test_releasing_the_deadman_cancels_the_goto_and_it_does_not_resume():
    ctl, safety = make()
    clock = FakeClock()
    robot = SimRobot(SimRobotConfig(initial_pose=list(START)), clock=clock)
    robot.connect()
    lim = limits_of(ctl, safety)
    pv = ctl.preview("home", "op1", START, clock.t, lim)
    ok, _ = ctl.start("home", pv.token, "op1", START, clock.t, lim)
    assert ok
    _drive(ctl, safety, robot, clock, max_s=pv.plan.duration + 5.0, deadman_until=0.5)
    assert ctl.status == "cancelled" and "deadman" in ctl.reason
    here = robot.read_state().tcp_pose
    assert geometry.translation_distance(geometry.pose_to_matrix(here), geometry.pose_to_matrix(HOME)) > 0.01
    assert np.allclose(ctl.twist(here, clock.t, contact_off=""), 0.0)


def test_a_blocked_goto_cancels_when_off_the_path():
    ctl, safety = make(max_tracking_error=0.002)
    lim = limits_of(ctl, safety)
    pv = ctl.preview("home", "op1", START, 0.0, lim)
    ctl.start("home", pv.token, "op1", START, 0.0, lim)
    # the robot did not move at all (blocked by a limit or a force reaction) while the path went on
    ctl.twist(START, 0.1, contact_off="")
    assert ctl.active
    ctl.twist(START, 1.0, contact_off="")
    assert not ctl.active and ctl.status == "cancelled" and "off the planned path" in ctl.reason
