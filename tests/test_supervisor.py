"""The safety supervisor as pure logic: explicit times, no Zenoh, milliseconds per test."""

from __future__ import annotations

import time

import numpy as np
import pytest

from iorthand.protocol import ForceLevel, Status, TwistCommand
from iorthand_edge.supervisor import Action, SafetyConfig, Supervisor, WorkspaceBox
from tests.grants import Grants

POSE = np.array([0.30, 0.0, 0.20, 3.14159, 0.0, 0.0])  # tool pointing down, inside the default box
T0 = 1_700_000_000.0  # wall clock of the tests, s


class Clock(Grants):
    """Time, and the operators' grants: commands are signed with the key of the operator's grant."""

    def __init__(self, sv: Supervisor | None = None) -> None:
        super().__init__()
        self.sv = sv
        self.mono = 100.0
        self.seq = 0

    def cmd(self, vx: float = 0.005, deadman: bool = True, operator: str = "op1", age: float = 0.0,
            view_age: float = 0.02, **kw: object) -> TwistCommand:
        self.seq += 1
        c = TwistCommand(operator=operator, linear=[vx, kw.get("vy", 0.0), kw.get("vz", 0.0)],
                         angular=[0.0, 0.0, kw.get("wz", 0.0)], deadman=deadman, state_age=view_age)
        c.stamp(kw.get("seq", self.seq), int((self.wall - age) * 1e9))
        assert self.sv is not None
        return self.sign(self.sv, operator, c)

    @property
    def wall(self) -> float:
        return T0 + self.mono


def armed(**cfg: object) -> tuple[Supervisor, Clock]:
    sv = Supervisor(SafetyConfig(auto_arm=True, **cfg))
    clock = Clock(sv)
    ok, _ = clock.acquire(sv, "op1", clock.mono)
    assert ok
    return sv, clock


def test_starts_disarmed_and_remote_can_only_request() -> None:
    sv = Supervisor(SafetyConfig())
    c = Clock(sv)
    c.acquire(sv, "op1", c.mono)
    d = sv.on_command(c.cmd(), c.wall, c.mono, POSE)
    assert not d.accepted and d.status == Status.DISARMED and not np.any(d.twist)
    ok, reason = sv.request_arm("op1")
    assert not ok and "confirmation" in reason and sv.arm_requested and not sv.armed
    sv.arm()
    assert sv.on_command(c.cmd(), c.wall, c.mono, POSE).accepted


def test_ownership_is_exclusive_with_reason_and_lease() -> None:
    sv, c = armed()
    ok, reason = c.acquire(sv, "op2", c.mono + 1.0)
    assert not ok and "op1" in reason
    d = sv.on_command(c.cmd(operator="op2"), c.wall, c.mono, POSE)
    assert not d.accepted and d.status == Status.NOT_OWNER and "op1" in d.reason
    # The lease runs out without renewal: another operator may take over.
    ok, _ = c.acquire(sv, "op2", c.mono + sv.config.lease + 0.1)
    assert ok and sv.owner == "op2"


def test_owner_lost_stops_and_latches_until_reacquired() -> None:
    sv, c = armed()
    assert np.any(sv.on_command(c.cmd(), c.wall, c.mono, POSE).twist)
    assert sv.owner_lost("op1", "liveliness lost")
    assert sv.owner == "" and sv.status == Status.OWNER_LOST
    assert not np.any(sv.step(c.mono, POSE).twist)
    c.acquire(sv, "op1", c.mono, release=False)
    d = sv.on_command(c.cmd(), c.wall, c.mono, POSE)
    assert not d.accepted and "press it again" in d.reason  # acquiring only acknowledges
    sv.on_command(c.cmd(deadman=False), c.wall, c.mono, POSE)
    assert sv.on_command(c.cmd(), c.wall, c.mono, POSE).accepted


def test_lease_renewal_never_resumes_after_a_fault_or_a_stop() -> None:
    """The client renews its lease with acquire every second while the operator may hold the deadman."""
    sv, c = armed()
    assert sv.on_command(c.cmd(), c.wall, c.mono, POSE).accepted
    sv.set_fault("protective stop")
    sv.set_fault("")  # cleared on the robot side
    for _ in range(3):  # renewals, deadman held all along
        assert c.acquire(sv, "op1", c.mono)[0]
        d = sv.on_command(c.cmd(), c.wall, c.mono, POSE)
        assert not d.accepted and not np.any(d.twist) and not np.any(sv.step(c.mono, POSE).twist)
    sv.on_command(c.cmd(deadman=False), c.wall, c.mono, POSE)
    assert sv.on_command(c.cmd(), c.wall, c.mono, POSE).accepted
    sv.stop("e-stop")
    c.acquire(sv, "op1", c.mono)
    assert not sv.on_command(c.cmd(), c.wall, c.mono, POSE).accepted


def test_allow_list() -> None:
    sv = Supervisor(SafetyConfig(auto_arm=True, allowed_operators=["alice"]))
    c = Clock(sv)
    ok, reason = c.acquire(sv, "mallory", 0.0)
    assert not ok and "allow-list" in reason
    assert c.acquire(sv, "alice", 0.0)[0]


def test_deadman_flag_required() -> None:
    sv, c = armed()
    d = sv.on_command(c.cmd(deadman=False), c.wall, c.mono, POSE)
    assert d.status == Status.NO_DEADMAN and not np.any(d.twist)


def test_command_timeout_zeroes_the_twist() -> None:
    sv, c = armed()
    sv.on_command(c.cmd(), c.wall, c.mono, POSE)
    assert np.any(sv.step(c.mono + 0.149, POSE).twist)
    d = sv.step(c.mono + 0.151, POSE)
    assert not np.any(d.twist) and sv.status == Status.COMMAND_TIMEOUT and "150 ms" in sv.reason


def test_the_stops_the_supervisor_decides_alone_are_handed_to_the_log() -> None:
    """A command timeout and an expired lease stop the robot with no request behind them: each is an
    intervention the agent logs (a red-team run found them only on state/safety, not in the edge's log)."""
    sv, c = armed()
    sv.on_command(c.cmd(), c.wall, c.mono, POSE)
    sv.interventions.clear()
    sv.step(c.mono + 0.151, POSE)
    assert [s for s, _ in sv.interventions] == [Status.COMMAND_TIMEOUT]
    sv.step(c.mono + 0.2, POSE)
    assert len(sv.interventions) == 1  # once, not at every cycle after it
    sv.step(c.mono + sv.config.lease + 1.0, POSE)
    assert sv.interventions[-1][0] == Status.OWNER_LOST and "lease of 'op1' expired" in sv.interventions[-1][1]
    assert not sv.owner


def test_stale_and_out_of_order_commands_dropped() -> None:
    sv, c = armed()
    d = sv.on_command(c.cmd(age=0.6), c.wall, c.mono, POSE)
    assert d.status == Status.STALE_COMMAND and "old" in d.reason
    d = sv.on_command(c.cmd(age=-5.0), c.wall, c.mono, POSE)
    assert d.status == Status.STALE_COMMAND and "future" in d.reason
    assert sv.on_command(c.cmd(seq=10), c.wall, c.mono, POSE).accepted
    d = sv.on_command(c.cmd(seq=9), c.wall, c.mono, POSE)
    assert d.status == Status.OUT_OF_ORDER and not d.accepted
    d = sv.on_command(c.cmd(seq=10), c.wall, c.mono, POSE)
    assert d.status == Status.OUT_OF_ORDER  # a replay of the same sequence number
    assert sv.counters.rejected == 4 and sv.counters.applied == 2  # the grant's release, and seq 10


@pytest.mark.parametrize(("profile", "limit"), [("remote", 0.008), ("local", 0.030)])
def test_speed_clipped_to_profile(profile: str, limit: float) -> None:
    sv, c = armed(profile=profile)
    d = sv.on_command(c.cmd(vx=0.1, vy=0.1), c.wall, c.mono, POSE)
    assert d.accepted and d.status == Status.SPEED_LIMITED and "linear_speed" in d.limits_hit
    assert np.linalg.norm(d.twist[:3]) == pytest.approx(limit)
    assert d.twist[0] == pytest.approx(d.twist[1])  # direction kept
    d = sv.on_command(c.cmd(vx=0.0, wz=5.0), c.wall, c.mono, POSE)
    assert abs(d.twist[5]) == pytest.approx(sv.limits.angular)


def test_workspace_removes_outward_velocity_only() -> None:
    sv, c = armed(workspace=WorkspaceBox(min=[0.1, -0.3, 0.02], max=[0.3, 0.3, 0.45]))
    at_face = POSE.copy()
    at_face[0] = 0.3
    d = sv.on_command(c.cmd(vx=0.006, vy=0.004), c.wall, c.mono, at_face)  # under the 8 mm/s limit
    assert d.twist[0] == 0.0 and d.twist[1] == pytest.approx(0.004) and d.status == Status.WORKSPACE
    d = sv.on_command(c.cmd(vx=-0.008), c.wall, c.mono, at_face)
    assert d.twist[0] == pytest.approx(-0.008)  # inward is free
    near = POSE.copy()
    near[0] = 0.3 - 0.00002  # 20 µm from the face: only what still stops in time
    d = sv.on_command(c.cmd(vx=0.008), c.wall, c.mono, near)
    assert 0 < d.twist[0] < 0.008


def test_stop_latches_until_deadman_released() -> None:
    sv, c = armed()
    sv.on_command(c.cmd(), c.wall, c.mono, POSE)
    sv.stop("e-stop")
    d = sv.on_command(c.cmd(), c.wall, c.mono, POSE)
    assert not d.accepted and d.status == Status.STOPPED and not np.any(d.twist)
    sv.on_command(c.cmd(deadman=False), c.wall, c.mono, POSE)
    assert sv.on_command(c.cmd(), c.wall, c.mono, POSE).accepted


def test_a_stop_is_in_force_until_the_deadman_is_released_after_it() -> None:
    """What lets the edge take a repeated stop as nothing new: only while the first one holds the robot still."""
    sv, c = armed()
    assert not sv.stop_in_force
    sv.on_command(c.cmd(), c.wall, c.mono, POSE)
    sv.stop("e-stop")
    assert sv.stop_in_force
    sv.on_command(c.cmd(), c.wall, c.mono, POSE)  # the deadman still held: refused, the stop holds
    assert sv.stop_in_force
    sv.on_command(c.cmd(deadman=False), c.wall, c.mono, POSE)  # released: the next press may move
    assert not sv.stop_in_force
    assert sv.on_command(c.cmd(), c.wall, c.mono, POSE).accepted and not sv.stop_in_force


def test_a_deadman_held_under_a_latch_times_out_and_the_loop_is_not_woken_for_it_again() -> None:
    """Found by a red-team run of the edge: the owner held the deadman under a stop (or after a link gap), then
    its twists ceased while its lease was renewed. timeout_at() stayed in the past, and the control loop, which
    wakes at it, spun: state/robot at ~20 000 Hz and a core busy, on the Pi at real-time priority."""
    sv, c = armed()
    sv.on_command(c.cmd(), c.wall, c.mono, POSE)
    sv.stop("e-stop")
    sv.on_command(c.cmd(), c.wall, c.mono, POSE)  # held under the stop: refused
    assert sv.timeout_at() == pytest.approx(c.mono + sv.config.command_timeout)
    c.mono += sv.config.command_timeout + 0.01  # the twists cease
    d = sv.step(c.mono, POSE)
    assert not np.any(d.twist) and sv.timeout_at() == float("inf")
    assert sv.status == Status.STOPPED and sv.stop_in_force  # the stop, its reason and its latch stand
    sv.on_command(c.cmd(deadman=False), c.wall, c.mono, POSE)  # and clear as before: release, then press
    assert sv.on_command(c.cmd(), c.wall, c.mono, POSE).accepted


def test_fault_refuses_and_needs_reacquire() -> None:
    sv, c = armed()
    sv.set_fault("robot link lost")
    d = sv.on_command(c.cmd(), c.wall, c.mono, POSE)
    assert not d.accepted and d.reason == "robot link lost"
    sv.set_fault("")
    d = sv.on_command(c.cmd(), c.wall, c.mono, POSE)
    assert not d.accepted and d.status == Status.FAULT  # cleared fault: still latched
    c.acquire(sv, "op1", c.mono)
    assert not sv.on_command(c.cmd(), c.wall, c.mono, POSE).accepted  # acknowledged, deadman still held
    sv.on_command(c.cmd(deadman=False), c.wall, c.mono, POSE)
    assert sv.on_command(c.cmd(), c.wall, c.mono, POSE).accepted


def test_force_danger_removes_pressing_component() -> None:
    sv = Supervisor(SafetyConfig(auto_arm=True), force_required=True)
    c = Clock(sv)
    c.acquire(sv, "op1", c.mono)
    sv.update_force(ForceLevel.SAFE, stale=False)
    # Tool points down (rotation π about x): pressing is −z in the base frame.
    assert sv.on_command(c.cmd(vx=0.0, vz=-0.005), c.wall, c.mono, POSE).twist[2] < 0
    sv.update_force(ForceLevel.DANGER, stale=False)
    d = sv.on_command(c.cmd(vx=0.004, vz=-0.005), c.wall, c.mono, POSE)
    assert d.status == Status.FORCE_DANGER and d.twist[2] == pytest.approx(0.0, abs=1e-6)
    assert d.twist[0] == pytest.approx(0.004)
    d = sv.on_command(c.cmd(vx=0.0, vz=0.005), c.wall, c.mono, POSE)
    assert d.twist[2] == pytest.approx(0.005)  # retreat allowed


def test_red_during_a_previewed_move_stops_it_unless_it_lifts_off() -> None:
    """Red during a move: it met what its preview did not show. A move that does not lift off stops (its status
    halts, so the move ends); one that lifts off goes on. The operator's own sideways twist keeps the rule it had:
    only motion pressing harder is removed."""
    sv = Supervisor(SafetyConfig(auto_arm=True), force_required=True)
    c = Clock(sv)
    c.acquire(sv, "op1", c.mono)
    sv.update_force(ForceLevel.DANGER, stale=False)
    c.mono += 0.02
    d = sv.on_command(c.cmd(vx=0.0), c.wall, c.mono, POSE, [0.005, 0.0, 0.0, 0.0, 0.0, 0.02])
    assert d.status == Status.FORCE_DANGER and d.status.halts and not np.any(d.twist)
    assert "previewed move stopped" in d.cancel_goto
    c.mono += 0.02
    lifting = [0.002, 0.0, 0.004, 0.0, 0.0, 0.0]  # the tool points down: +z lifts off
    d = sv.on_command(c.cmd(vx=0.0), c.wall, c.mono, POSE, lifting)
    assert d.accepted and not d.cancel_goto and d.twist == pytest.approx(lifting)
    c.mono += 0.02
    d = sv.on_command(c.cmd(vx=0.004), c.wall, c.mono, POSE)
    assert d.accepted and d.twist[0] == pytest.approx(0.004)


def test_a_pose_that_is_not_a_number_is_a_fault() -> None:
    """Every limit compares with the pose, and no comparison with NaN holds: the workspace box would let
    anything through."""
    sv, c = armed()
    nan_pose = [0.30, float("nan"), 0.20, 3.14159, 0.0, 0.0]
    assert sv.on_reading("", True, nan_pose) == "the robot reported a pose that is not a number: no limit can hold"
    d = sv.on_command(c.cmd(vx=-0.008), c.wall, c.mono, nan_pose)
    assert not d.accepted and d.status == Status.FAULT and not np.any(d.twist)
    assert sv.on_reading("", True, POSE) == ""


def test_a_takeover_at_the_robot_disarms_with_its_reason_until_armed_on_site() -> None:
    """Somebody at the robot took it over (a program stopped on its pendant, local control): the edge disarms with
    that reason, and neither a fresh acquire nor a fresh press moves the arm until it is armed again."""
    sv, c = armed()
    takeover = "the program was stopped on the teach pendant"
    assert sv.on_reading("", True, POSE, takeover) == ""
    assert not sv.armed and sv.status == Status.DISARMED and sv.reason == takeover
    # A driver that is down for it reports the takeover as its fault too: the operator reads the takeover.
    sv.arm()
    assert sv.on_reading(takeover, True, POSE, takeover) == takeover
    assert not sv.armed and sv.status == Status.DISARMED and sv.reason == takeover
    sv.arm()
    sv.on_reading("", True, POSE)
    c.acquire(sv, "op1", c.mono)
    sv.on_reading("", True, POSE, takeover)
    d = sv.on_command(c.cmd(), c.wall, c.mono, POSE)
    assert not d.accepted and d.status == Status.DISARMED and d.reason.startswith(takeover)
    assert "confirm arming" in d.reason
    c.acquire(sv, "op1", c.mono)
    sv.on_command(c.cmd(deadman=False), c.wall, c.mono, POSE)
    assert not sv.on_command(c.cmd(), c.wall, c.mono, POSE).accepted
    sv.arm()
    sv.on_reading("", True, POSE)
    c.acquire(sv, "op1", c.mono)
    sv.on_command(c.cmd(deadman=False), c.wall, c.mono, POSE)
    assert sv.on_command(c.cmd(), c.wall, c.mono, POSE).accepted


def test_stale_force_stops_then_refuses_contact_motion() -> None:
    sv = Supervisor(SafetyConfig(auto_arm=True), force_required=True)
    c = Clock(sv)
    c.acquire(sv, "op1", c.mono)
    sv.update_force(ForceLevel.SAFE, stale=False)
    sv.on_command(c.cmd(vx=0.0, vz=-0.005), c.wall, c.mono, POSE)
    sv.update_force(ForceLevel.SAFE, stale=True)
    assert not np.any(sv.step(c.mono, POSE).twist)
    d = sv.on_command(c.cmd(vx=0.0, vz=-0.005), c.wall, c.mono, POSE)
    assert d.twist[2] == pytest.approx(0.0, abs=1e-6) and d.status == Status.FORCE_STALE


def test_a_twist_in_the_probe_frame_moves_about_the_probe_tip() -> None:
    """frame "tool": the probe's own axes (the tool frame about its tip) — along the probe is, with the tool
    pointing down, down in the base frame; a turn about the probe axis is a turn about -z of the base. The
    limits apply to the converted twist, and an unknown frame is refused with its reason."""
    sv, c = armed()
    c.mono += 0.02
    along = c.cmd(vx=0.0, vz=0.004)
    along.frame = "tool"
    d = sv.on_command(c.sign(sv, "op1", along), c.wall, c.mono, POSE)
    assert d.accepted and d.twist[2] == pytest.approx(-0.004, abs=1e-5) and abs(d.twist[0]) < 1e-5, d.twist
    c.mono += 0.02
    turn = c.cmd(vx=0.0, wz=0.05)
    turn.frame = "tool"
    d = sv.on_command(c.sign(sv, "op1", turn), c.wall, c.mono, POSE)
    assert d.accepted and d.twist[5] == pytest.approx(-0.05, abs=1e-4)
    c.mono += 0.02
    fast = c.cmd(vx=0.5)  # 500 mm/s along the probe's x: clipped to the profile like any twist
    fast.frame = "tool"
    d = sv.on_command(c.sign(sv, "op1", fast), c.wall, c.mono, POSE)
    assert np.linalg.norm(d.twist[:3]) == pytest.approx(sv.limits.linear, rel=1e-3)
    c.mono += 0.02
    odd = c.cmd()
    odd.frame = "world"
    d = sv.on_command(c.sign(sv, "op1", odd), c.wall, c.mono, POSE)
    assert not d.accepted and d.status == Status.BAD_COMMAND and "unknown twist frame 'world'" in d.reason


def test_a_stale_view_spell_longer_than_the_resume_gap_needs_a_fresh_press() -> None:
    """Commands keep coming (no gap) but each shows an old picture of the robot (a downlink that stalled, a clock
    that makes fresh states look old): each is refused and the robot stops. Once the picture is fresh again after
    more than ``resume_gap``, the operator has not driven for that long: motion resumes on a fresh press only, as
    after a gap in the commands (it resumed by itself before)."""
    sv, c = armed(max_view_age=0.5, resume_gap=0.5)
    assert sv.on_command(c.cmd(), c.wall, c.mono, POSE).action == Action.MOVE
    for _ in range(60):  # one second of commands at 60 Hz, the deadman held, the picture 0.8 s old
        c.mono += 1 / 60
        d = sv.on_command(c.cmd(view_age=0.8), c.wall, c.mono, POSE)
        assert not d.accepted and d.status == Status.STALE_VIEW and not np.any(d.twist)
    c.mono += 1 / 60
    d = sv.on_command(c.cmd(), c.wall, c.mono, POSE)
    assert not d.accepted and d.status == Status.LINK_GAP and not np.any(d.twist), d
    assert "motion was refused for" in d.reason and "press it again" in d.reason
    c.mono += 1 / 60
    assert sv.on_command(c.cmd(deadman=False), c.wall, c.mono, POSE).accepted
    c.mono += 1 / 60
    assert sv.on_command(c.cmd(), c.wall, c.mono, POSE).action == Action.MOVE
    # A short spell (shorter than the bound) still resumes by itself: the picture was old for a moment only.
    c.mono += 1 / 60
    assert not sv.on_command(c.cmd(view_age=0.8), c.wall, c.mono, POSE).accepted
    c.mono += 1 / 60
    assert sv.on_command(c.cmd(), c.wall, c.mono, POSE).action == Action.MOVE


def _naming_view(c: Clock, sv: Supervisor, view_t: float, age: float = 0.0, deadman: bool = True) -> TwistCommand:
    """A command of op1 stamped by the operator's clock (``c.wall - age``) naming the robot state stamped
    ``view_t`` (s, the edge's clock)."""
    c.seq += 1
    cmd = TwistCommand(operator="op1", linear=[0.005, 0.0, 0.0], deadman=deadman, state_age=0.02,
                       view_t=int(view_t * 1e9))
    cmd.stamp(c.seq, int((c.wall - age) * 1e9))
    return c.sign(sv, "op1", cmd)


def test_an_edge_clock_step_stops_the_robot_with_one_reason_that_names_the_step() -> None:
    """This edge's wall clock steps 5 s forward (NTP) while the operator drives: every command is now 5 s old on
    it. The refusals give one reason (rounded: a reason that changed with each command's jitter was a new line
    in the operator's log 60 times a second), it says this robot's clock stepped, and once the robot has stopped
    the safety status says the same (it said "no command for 150 ms" while commands kept arriving)."""
    sv, c = armed()
    assert sv.on_command(_naming_view(c, sv, c.wall - 0.01), c.wall, c.mono, POSE).action == Action.MOVE
    reasons = set()
    for i in range(30):
        c.mono += 1 / 60
        edge_wall = c.wall + 5.0
        jitter = 0.003 * (i % 5)  # the link's delay varies by a few ms
        d = sv.on_command(_naming_view(c, sv, edge_wall - 0.01, age=jitter), edge_wall, c.mono, POSE)
        assert not d.accepted and d.status == Status.STALE_COMMAND
        reasons.add(d.reason)
        sv.step(c.mono + 0.001, POSE)
    assert len(reasons) == 1, reasons
    (reason,) = reasons
    assert "the operator's clock is 5000 ms behind this robot's" in reason
    assert "this robot's clock stepped 5000 ms forward" in reason and len(reason) <= 200
    assert not sv.deadman and not sv.moving and sv.status == Status.STALE_COMMAND and sv.reason == reason
    assert Status.STALE_COMMAND in [s for s, _ in sv.interventions]
    # The clock is put right: the spell was longer than the resume gap, so a fresh press is needed.
    c.mono += 1 / 60
    d = sv.on_command(_naming_view(c, sv, c.wall - 0.01), c.wall, c.mono, POSE)
    assert not d.accepted and d.status == Status.LINK_GAP
    c.mono += 1 / 60
    assert sv.on_command(_naming_view(c, sv, c.wall - 0.01, deadman=False), c.wall, c.mono, POSE).accepted
    c.mono += 1 / 60
    assert sv.on_command(_naming_view(c, sv, c.wall - 0.01), c.wall, c.mono, POSE).action == Action.MOVE


def test_a_new_grant_is_refused_with_both_clocks_readings_when_they_disagree() -> None:
    """An edge that booted without a real-time clock reads 1970: every command of any operator would be refused.
    Control is refused at once, with both readings, so that the operator sees which clock to set; a renewal of
    a grant is not (a step during a session refuses commands, not control)."""
    wall = [3600.0]
    sv = Supervisor(SafetyConfig(auto_arm=True), wall_clock=lambda: wall[0])
    c = Clock(sv)
    grant = c.grant(sv, "op1", c.mono)
    assert not grant.ok and not grant.key and not sv.owner
    assert grant.reason.startswith("clocks disagree: this robot's reads 1970-01-01 01:00 UTC, the operator's ")
    assert "years apart" in grant.reason and "NTP" in grant.reason and len(grant.reason) <= 200
    wall[0] = time.time()
    ok, _ = c.acquire(sv, "op1", c.mono)
    assert ok and sv.owner == "op1"
    wall[0] = 3600.0  # the edge's clock steps back to 1970 during the session: the lease is renewed all the same
    ok, reason = c.acquire(sv, "op1", c.mono + 1.0)
    assert ok and "renewed" in reason
