"""Kinematic awareness in live teleoperation: a twist driving the arm toward a singularity, a joint limit or the
edge of reach slows, then halts, each with its status and a reason naming it; motion away is never slowed.

Closed loops in pure code: the supervisor with its guard, and the robot a kinematic model of the TCP (the pose
integrated from the twist the supervisor sent), the operator's intent recomputed at each cycle from the arm's
current Jacobian (an operator steering into the singularity, not a fixed twist that would wander off it)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from iorthand import geometry, kinematics
from iorthand.protocol import Status, TwistCommand
from iorthand_edge.kinematic_guard import SAME_POSE, KinematicGuard, KinematicLimits
from iorthand_edge.supervisor import SafetyConfig, Supervisor
from tests.conftest import wait_until
from tests.test_supervisor import Clock

MODEL = kinematics.UR3E
PERIOD = 0.008
# A UR3e over the table, tool down (the simulator's start pose), elbow up: far from every limit.
START_Q = kinematics.solve_near(MODEL, [0.30, 0.0, 0.25, math.pi, 0.0, 0.0], kinematics.HOME_Q)


def guarded(limits: KinematicLimits | None = None) -> tuple[Supervisor, Clock, KinematicGuard]:
    sv = Supervisor(SafetyConfig(auto_arm=True), period=PERIOD)
    sv.profile = "local"  # 30 mm/s, 0.2 rad/s: the approach is quick, the margins are what slow it
    guard = KinematicGuard(limits or KinematicLimits(), MODEL.name)
    sv.kinematics = guard
    clock = Clock(sv)
    assert clock.acquire(sv, "op1", clock.mono)[0]
    return sv, clock, guard


def command(clock: Clock, twist: np.ndarray) -> TwistCommand:
    clock.seq += 1
    c = TwistCommand(operator="op1", linear=[float(v) for v in twist[:3]], angular=[float(v) for v in twist[3:]],
                     deadman=True, state_age=0.02)
    c.stamp(clock.seq, int(clock.wall * 1e9))
    return clock.sign(clock.sv, "op1", c)


def drive(q0: np.ndarray, intent, limits: KinematicLimits | None = None, seconds: float = 12.0):
    """Run the loop from joint angles ``q0``; ``intent(q)`` is the operator's twist at the arm's angles ``q``.
    Returns the per-cycle (q, applied twist, status, reason)."""
    sv, clock, guard = guarded(limits)
    pose = kinematics.forward(MODEL, q0)
    trace = []
    for i in range(int(seconds / PERIOD)):
        # The robot reports q once (which IK branch the arm is in), then only its pose: the guard tracks q.
        assessment = guard.update(geometry.matrix_to_pose(pose), q0 if i == 0 else None)
        q = np.asarray(assessment.q)
        d = sv.on_command(command(clock, intent(q)), clock.wall, clock.mono, geometry.matrix_to_pose(pose))
        twist = np.asarray(d.twist)
        trace.append((q, twist, d.status, d.reason))
        pose = pose.copy()
        pose[:3, 3] += twist[:3] * PERIOD
        pose[:3, :3] = geometry.rotvec_to_matrix(twist[3:] * PERIOD) @ pose[:3, :3]
        clock.mono += PERIOD
    return trace


def joint_motion(joint: int, speed: float):
    """The operator's twist that turns one joint alone at ``speed`` rad/s (through the arm's Jacobian)."""
    def intent(q: np.ndarray) -> np.ndarray:
        qdot = np.zeros(6)
        qdot[joint] = speed
        return kinematics.jacobian(MODEL, q)[0] @ qdot
    return intent


def speeds(trace) -> np.ndarray:
    return np.array([np.linalg.norm(t[:3]) + 0.1 * np.linalg.norm(t[3:]) for _, t, _, _ in trace])


def test_the_guard_tracks_the_joints_from_the_pose_alone() -> None:
    guard = KinematicGuard(KinematicLimits(), MODEL.name)
    q = START_Q.copy() + 0.2  # not the branch an IK from the pose alone would pick first
    assert np.allclose(guard.update(geometry.matrix_to_pose(kinematics.forward(MODEL, q)), q).q, q)  # reported
    for _ in range(200):  # then a drift of every joint seen through the TCP pose alone: a robot reporting a wrong q
        q = q + np.array([1, -2, 1.5, -1, 2, 3]) * 1e-3
        got = guard.update(geometry.matrix_to_pose(kinematics.forward(MODEL, q)), kinematics.HOME_Q)
        assert np.allclose(got.q, q, atol=1e-6)
    assert 0.0 < got.manipulability < 1.0 and got.reach_left > 0.05


def test_an_arm_at_rest_is_assessed_once_and_a_creeping_one_never_lags_further_than_same_pose() -> None:
    """The assessment is remade only once the pose has moved SAME_POSE from where it was made (not from the
    previous cycle): an arm creeping in steps smaller than that is still followed, never more than SAME_POSE
    behind, and one at rest costs one assessment."""
    guard = KinematicGuard(KinematicLimits(), MODEL.name)
    start = geometry.matrix_to_pose(kinematics.forward(MODEL, START_Q))
    first = guard.update(start, START_Q)
    assert all(guard.update(start.copy(), START_Q.copy()) is first for _ in range(50))
    made = [first]  # the assessments made (kept alive: an id could otherwise be reused)
    for i in range(1, 300):
        pose = start.copy()
        pose[0] += 4e-6 * i  # 0.5 mm/s at 125 Hz
        got = guard.update(pose)  # the pose alone (reported angles within 0.1 mm of it would be taken as they are)
        if got is not made[-1]:
            made.append(got)
        assessed = kinematics.forward(MODEL, got.q)
        assert geometry.translation_distance(assessed, geometry.pose_to_matrix(pose)) <= SAME_POSE + 1e-7
    assert 300 * 4e-6 / SAME_POSE / 2 < len(made) < 150  # remade every few cycles, not every cycle


def test_a_pose_that_is_not_a_number_halts_every_twist_until_a_real_one_comes() -> None:
    """A broken reading (NaN) is never "the same pose" as the last: the guard does not keep its old assessment
    but has no angles at all, and halts every twist with its reason, until a finite pose is assessed again."""
    guard = KinematicGuard(KinematicLimits(), MODEL.name)
    start = geometry.matrix_to_pose(kinematics.forward(MODEL, START_Q))
    assert guard.update(start, START_Q).q is not None
    broken_pose = [math.nan, *start[1:]]
    broken_angles = [*START_Q[:5], math.nan]
    for pose, q in ((broken_pose, START_Q), (start, broken_angles)):
        assert guard.update(pose, q).q is None, (pose, q)
        twist = [0.01, 0.0, 0.0, 0.0, 0.0, 0.0]
        status, reason = guard.limit(twist)
        assert status == Status.REACH_LIMIT and twist == [0.0] * 6 and "no joint solution" in reason
        assert guard.update(start, START_Q).q is not None  # a finite pose again: assessed anew


def test_a_twist_into_the_wrist_singularity_slows_then_halts() -> None:
    q0 = START_Q.copy()
    q0[4] = -math.radians(45)  # wrist 2 at 45° from straight
    trace = drive(q0, joint_motion(4, +0.1))  # wrist 2 straightening, at 0.1 rad/s
    statuses = [s for _, _, s, _ in trace]
    first_slow = statuses.index(Status.NEAR_SINGULARITY)
    first_halt = statuses.index(Status.SINGULARITY)
    assert first_slow < first_halt
    v = speeds(trace)
    assert v[first_halt] == 0.0 and v[first_slow + 5] < v[first_slow - 5]  # slowed before it halted
    assert "wrist singularity" in trace[first_halt][3] and "halted" in trace[first_halt][3]
    assert "slowed to" in trace[first_slow + 5][3]
    wrist = [abs(math.degrees(q[4])) for q, *_ in trace]
    assert min(wrist) > 2.0  # halted before the singularity itself (the halt margin ≈ 5°)
    assert all(s == Status.SINGULARITY for s in statuses[first_halt:])  # holds while the operator pushes into it


def test_the_manipulability_bound_decides_as_the_exact_value_and_spares_most_decompositions(monkeypatch) -> None:
    """Outside the slow margin the guard may take a lower bound of the manipulability from its last decomposition
    (Weyl). Along a drive into the wrist singularity, every cycle's status, reason and scaled twist must equal those
    of a guard that decomposes at every cycle, while far from the singularity it decomposes only now and then."""
    q0 = START_Q.copy()
    q0[4] = -math.radians(45)
    intent = joint_motion(4, +0.1)
    decompositions = []
    real_svd = np.linalg.svd
    monkeypatch.setattr(np.linalg, "svd", lambda *a, **k: decompositions.append(1) or real_svd(*a, **k))
    bounded = drive(q0, intent)
    with_bound = len(decompositions)
    monkeypatch.setattr(KinematicGuard, "_bounded", lambda self, scaled: None)  # decompose at every cycle
    exact = drive(q0, intent)
    assert len(bounded) == len(exact) == 1500
    for (_, twist, status, reason), (_, twist_e, status_e, reason_e) in zip(bounded, exact, strict=True):
        assert (status, reason) == (status_e, reason_e)
        assert np.array_equal(twist, twist_e)
    statuses = [s for _, _, s, _ in bounded]
    assert Status.NEAR_SINGULARITY in statuses and Status.SINGULARITY in statuses  # the drive went in
    far = statuses.index(Status.NEAR_SINGULARITY)  # cycles before the slow margin
    assert far > 100 and with_bound < len(decompositions) - far / 2


def test_motion_away_from_a_singularity_is_not_slowed() -> None:
    q0 = START_Q.copy()
    q0[4] = -math.radians(6)  # inside the slow margin
    trace = drive(q0, joint_motion(4, -0.1), seconds=0.5)  # bending wrist 2 back, away
    assert all(s in (Status.OK, Status.SPEED_LIMITED) for _, _, s, _ in trace)


def test_a_joint_limit_slows_then_halts_with_the_joint_named() -> None:
    q0 = START_Q.copy()
    limits = KinematicLimits(joint_max=[2 * math.pi] * 5 + [q0[5] + 0.6])  # wrist 3: its cables allow 0.6 rad more
    trace = drive(q0, joint_motion(5, +0.15), limits)
    statuses = [s for _, _, s, _ in trace]
    first_slow, first_halt = statuses.index(Status.NEAR_JOINT_LIMIT), statuses.index(Status.JOINT_LIMIT)
    assert first_slow < first_halt
    assert "wrist 3" in trace[first_halt][3] and "upper limit" in trace[first_halt][3]
    final = trace[-1][0][5]
    assert limits.joint_max[5] - limits.joint_slow_margin < final <= limits.joint_max[5] - 0.8 * limits.joint_halt_margin
    back = drive(trace[-1][0], joint_motion(5, -0.15), limits, seconds=0.3)  # turning back is at full speed
    assert all(s not in (Status.NEAR_JOINT_LIMIT, Status.JOINT_LIMIT) for _, _, s, _ in back)


def test_reaching_out_slows_then_halts_at_the_edge_of_reach() -> None:
    def outward(q: np.ndarray) -> np.ndarray:  # straight out from the base, level: the operator reaching far
        p = kinematics.forward(MODEL, q)[:3, 3]
        radial = np.array([p[0], p[1], 0.0]) / math.hypot(p[0], p[1])
        return np.concatenate([0.03 * radial, np.zeros(3)])

    trace = drive(START_Q, outward, seconds=6.0)
    statuses = [s for _, _, s, _ in trace]
    first_slow, first_halt = statuses.index(Status.NEAR_REACH), statuses.index(Status.REACH_LIMIT)
    assert first_slow < first_halt
    assert speeds(trace)[first_halt] == 0.0 and speeds(trace)[first_halt - 20] < 0.5 * speeds(trace)[first_slow]
    assert "edge of reach" in trace[first_halt][3] and "halted" in trace[first_halt][3]
    left = abs(MODEL.a[1]) + abs(MODEL.a[2]) - kinematics.elbow_span(MODEL, trace[-1][0][2])
    assert left > 0.8 * KinematicLimits().reach_halt_margin  # the elbow never went straight
    assert all(s == Status.REACH_LIMIT for s in statuses[first_halt:])


def test_a_pose_without_a_joint_solution_moves_nothing() -> None:
    sv, clock, guard = guarded()
    far = [1.5, 0.0, 0.2, math.pi, 0.0, 0.0]  # 1.5 m out: beyond a UR3e
    assert guard.update(far).q is None
    d = sv.on_command(command(clock, np.array([0.0, 0.0, 0.01, 0, 0, 0])), clock.wall, clock.mono, np.array(far))
    assert d.status == Status.REACH_LIMIT and not any(d.twist) and "reach" in d.reason


def test_margins_must_nest() -> None:
    with pytest.raises(ValueError, match="halt_manipulability"):
        KinematicGuard(KinematicLimits(slow_manipulability=0.01, halt_manipulability=0.02), MODEL.name)
    with pytest.raises(ValueError, match="joint_min"):
        KinematicGuard(KinematicLimits(joint_min=[1.0] * 6, joint_max=[0.5] * 6), MODEL.name)


@pytest.mark.slow
def test_the_edge_slows_and_halts_a_twist_at_the_edge_of_reach(edge_factory, operator_factory) -> None:
    """The same, live: the simulated UR3e (which reports no joint angles: the guard tracks them from its pose),
    the operator reaching out along x at the local profile's 30 mm/s; the console sees each status."""
    edge_factory(safety={"profile": "local", "workspace": {"min": [0.1, -0.3, 0.02], "max": [0.9, 0.3, 0.45]}})
    op = operator_factory()
    op.wait_for_state()
    op.start()
    op.acquire()
    op.set_twist([0.03, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)
    seen: list[str] = []
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline and (not seen or seen[-1] != Status.REACH_LIMIT):
        if op.safety is not None and (not seen or op.safety.status != seen[-1]):
            seen.append(op.safety.status)
        time.sleep(0.005)
    x_halted = op.robot_state.tcp_pose[0]
    time.sleep(0.5)  # held there while the operator keeps pushing
    assert op.safety.status == Status.REACH_LIMIT and "edge of reach" in op.safety.reason, seen
    assert Status.NEAR_REACH in seen and seen.index(Status.NEAR_REACH) < seen.index(Status.REACH_LIMIT), seen
    assert abs(op.robot_state.tcp_pose[0] - x_halted) < 0.001
    op.set_twist([-0.03, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)  # back in: at once, at full speed
    wait_until(lambda: op.robot_state.tcp_pose[0] < x_halted - 0.01, 2.0, message="moving back in")
    op.set_twist([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=False)


@pytest.mark.slow
def test_the_simulated_arm_is_published_with_the_joint_angles_of_its_pose(edge_factory, operator_factory) -> None:
    """The simulator measures no joint angles: ``state/robot`` carries the ones the guard tracks, which put the TCP
    where the pose says and move with it (the twin, the recordings and their exports draw and store them)."""
    edge_factory(safety={"profile": "local"})
    op = operator_factory()
    op.wait_for_state()
    still = op.robot_state
    start = [list(still.tcp_pose), list(still.q)]
    assert float(np.max(np.abs(kinematics.forward(MODEL, still.q)[:3, 3] - still.tcp_pose[:3]))) < 1e-5
    assert still.q != pytest.approx(list(kinematics.HOME_Q), abs=1e-3)  # not the simulator's placeholder
    op.start()
    op.acquire()
    op.set_twist([0.0, 0.03, 0.0], [0.0, 0.0, 0.0], deadman=True)
    wait_until(lambda: op.robot_state.tcp_pose[1] > start[0][1] + 0.015, 5.0, message="moving along y")
    op.set_twist([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=False)
    wait_until(lambda: not any(op.robot_state.tcp_speed), 2.0, message="at rest")
    st = op.robot_state
    fk = kinematics.forward(MODEL, st.q)
    assert float(np.max(np.abs(fk[:3, 3] - st.tcp_pose[:3]))) < 1e-5
    assert geometry.rotation_angle(fk, geometry.pose_to_matrix(st.tcp_pose)) < 1e-5
    assert st.q[0] - start[1][0] > 0.03, (st.q, start[1])  # the base turned toward +y
