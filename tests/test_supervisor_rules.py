"""Rules of the safety core that its other tests left unpinned: each was found by mutation testing of
supervisor.py (a mutant of the rule passed every test), and each test states the rule as an operator or an
integrator would. Pure logic: explicit times, no Zenoh, milliseconds per test."""

from __future__ import annotations

import math

import pytest

from iorthand import keys
from iorthand.protocol import ForceLevel, Status, TwistCommand
from iorthand_edge.supervisor import Action, ForceReaction, SafetyConfig, SpeedProfile, Supervisor, WorkspaceBox
from tests.grants import Grants

POSE = [0.30, 0.0, 0.20, math.pi, 0.0, 0.0]  # tool pointing down (pressing is −z), inside the default box
WALL0 = 1_700_000_000.0  # the edge's wall clock at monotonic 0, s


class Operator(Grants):
    """One operator's session against one supervisor, on the test's monotonic clock ``mono``; the edge's wall
    clock is ``WALL0 + mono + edge_step`` and the operator's ``WALL0 + mono + skew``."""

    def __init__(self, sv: Supervisor, name: str = "op1") -> None:
        super().__init__()
        self.sv, self.name = sv, name
        self.mono = 100.0
        self.skew = 0.0  # the operator's clock minus the edge's (s)
        self.edge_step = 0.0  # how far the edge's wall clock has stepped (s)

    @property
    def edge_wall(self) -> float:
        return WALL0 + self.mono + self.edge_step

    def take(self) -> None:
        ok, reason = self.acquire(self.sv, self.name, self.mono)
        assert ok, reason

    def twist(self, vx: float = 0.005, vz: float = 0.0, deadman: bool = True, view_age: float = 0.02,
              seq: int | None = None) -> TwistCommand:
        self.seq += 1
        cmd = TwistCommand(operator=self.name, linear=[vx, 0.0, vz], deadman=deadman, state_age=view_age)
        cmd.stamp(self.seq if seq is None else seq, int((WALL0 + self.mono + self.skew) * 1e9))
        return self.sign(self.sv, self.name, cmd)

    def send(self, cmd: TwistCommand, goto: list[float] | None = None):
        return self.sv.on_command(cmd, self.edge_wall, self.mono, POSE, goto)


def armed(force_required: bool = False, **cfg: object) -> tuple[Supervisor, Operator]:
    sv = Supervisor(SafetyConfig(auto_arm=True, **cfg), force_required=force_required, robot="sim1")
    op = Operator(sv)
    op.take()
    return sv, op


# ---------------------------------------------------------------- a supervisor at rest


def test_a_new_supervisor_holds_no_deadman_moves_nothing_and_tells_the_driver_nothing() -> None:
    """Nobody has pressed anything yet: the published state says no deadman, not moving, no arming requested,
    the control loop has no timeout to wake for, and its cycles send the driver nothing (not even a stop)."""
    sv = Supervisor(SafetyConfig(auto_arm=True))
    assert not sv.deadman and not sv.moving and not sv.arm_requested
    assert sv.timeout_at() == math.inf and sv.command_age(100.0) == -1.0
    for t in (100.0, 100.2, 101.0):
        d = sv.step(t, POSE)
        assert d.action == Action.HOLD and not any(d.twist)
    assert sv.status == Status.IDLE and sv.counters.stops == 0


def test_arming_on_site_answers_the_pending_request() -> None:
    sv = Supervisor(SafetyConfig())
    assert sv.status == Status.DISARMED and "confirm arming on the robot side" in sv.reason
    ok, _ = sv.request_arm("op1")
    assert not ok and sv.arm_requested
    sv.arm()
    assert sv.armed and not sv.arm_requested  # the request is answered: no console keeps showing it


# ---------------------------------------------------------------- ownership and sequence


def test_a_sequence_jump_of_exactly_the_bound_is_accepted_and_one_more_is_refused() -> None:
    _sv, op = armed(max_sequence_jump=100)
    assert op.send(op.twist()).accepted  # seq 2 (the grant's release was 1)
    assert op.send(op.twist(seq=102)).accepted  # a jump of 100: lost packets, still this session's stream
    d = op.send(op.twist(seq=203))  # a jump of 101
    assert not d.accepted and d.status == Status.OUT_OF_ORDER and "jumps 101" in d.reason


def test_losing_someone_elses_liveliness_leaves_the_owner_in_control() -> None:
    """Only the owner's lost token stops the robot and releases control: another operator (a viewer, one who
    was refused) may come and go while the owner drives."""
    sv, op = armed()
    assert op.send(op.twist()).action == Action.MOVE
    assert not sv.owner_lost("op2", "liveliness lost")
    assert sv.owner == "op1" and sv.status != Status.OWNER_LOST
    op.mono += 0.02
    d = op.send(op.twist())
    assert d.accepted and d.action == Action.MOVE


def test_every_command_is_counted_once_as_received_and_once_as_applied_or_rejected() -> None:
    sv, op = armed()
    before = sv.counters.received  # the grant's release
    assert op.send(op.twist()).accepted
    assert not op.send(op.twist(seq=1)).accepted  # a replay
    assert op.send(op.twist(deadman=False)).accepted
    c = sv.counters
    assert c.received - before == 3 and c.applied + c.rejected == c.received and c.rejected == 1


# ---------------------------------------------------------------- freshness of the operator's picture


def test_a_command_acting_on_a_picture_zero_seconds_old_moves() -> None:
    """``state_age`` 0 is a picture as fresh as it gets (only a negative age means: no robot state shown)."""
    _sv, op = armed()
    d = op.send(op.twist(view_age=0.0))
    assert d.accepted and d.action == Action.MOVE


# ---------------------------------------------------------------- faults


def test_a_fault_reported_at_every_reading_is_one_stop_and_its_reason_stays_until_acknowledged() -> None:
    """The driver reports the same fault at every reading (125 Hz): one stop, one reason. When it clears, the
    robot stays held (a fresh acquire and press are needed) and the safety status still says why."""
    sv, op = armed()
    assert op.send(op.twist()).action == Action.MOVE
    for _ in range(5):
        assert sv.on_reading("protective stop", True, POSE) == "protective stop"
    assert sv.counters.stops == 1 and sv.status == Status.FAULT and sv.reason == "protective stop"
    assert sv.on_reading("", True, POSE) == ""
    assert sv.status == Status.FAULT and sv.reason == "protective stop"
    op.mono += 0.02
    d = op.send(op.twist())
    assert not d.accepted and d.status == Status.FAULT and d.reason == "protective stop"
    assert sv.counters.stops == 1


# ---------------------------------------------------------------- previewed moves


def test_a_command_from_somebody_without_control_never_ends_the_owners_move() -> None:
    """A move under way (hold-to-run by the owner) is the owner's: another operator's command — deadman released,
    or a manual twist — is refused and leaves the move running."""
    sv, op = armed()
    move = [0.004, 0.0, 0.0, 0.0, 0.0, 0.0]
    d = op.send(op.twist(vx=0.0), goto=move)
    assert d.accepted and d.twist == pytest.approx(move) and not d.cancel_goto
    other = Operator(sv, "op2")
    for deadman, vx in ((False, 0.0), (True, 0.005)):
        d = other.send(other.twist(vx=vx, deadman=deadman), goto=move)
        assert not d.accepted and d.status == Status.NOT_OWNER and d.cancel_goto == "", d


# ---------------------------------------------------------------- force


def test_the_force_sensor_may_be_zeroed_only_when_fresh_and_out_of_contact() -> None:
    """Zeroing in contact would hide the contact force from every threshold afterwards."""
    assert "no force sensor" in Supervisor(SafetyConfig()).force_zero_refusal()
    sv = Supervisor(SafetyConfig(auto_arm=True), force_required=True)
    assert "stale" in sv.force_zero_refusal()  # no sample yet
    sv.update_force(ForceLevel.SAFE, stale=False, now=100.0)
    assert sv.force_zero_refusal() == ""
    for level in (ForceLevel.CAUTION, ForceLevel.DANGER):
        sv.update_force(level, stale=False, now=100.0)
        assert "lift the tool out of contact" in sv.force_zero_refusal()
    sv.update_force(ForceLevel.SAFE, stale=False, now=100.0)
    assert sv.force_zero_refusal() == ""


# ---------------------------------------------------------------- clocks


def test_a_refusal_names_a_step_of_this_robots_clock_only_when_it_stepped() -> None:
    """The operator's clock runs 0.45 s behind (its commands are 0.45 s old, within max_command_age 0.5 s). A
    command refused for its time says "this robot's clock stepped" when the edge's wall clock jumped against its
    monotonic one by more than 50 ms (plus what NTP may slew, 500 ppm of the time between), and not otherwise."""
    _sv, op = armed()
    op.skew = -0.45
    assert op.send(op.twist()).accepted
    op.mono += 0.02
    op.skew = -0.56  # the operator's clock drifted: nothing happened on this edge
    d = op.send(op.twist())
    assert d.status == Status.STALE_COMMAND and "command is 600 ms old" in d.reason and "stepped" not in d.reason
    op.skew = -0.45
    op.mono += 0.02
    assert op.send(op.twist()).accepted
    op.mono += 0.02
    op.edge_step = 0.08  # this edge's clock steps 80 ms forward: the command now reads 0.53 s old
    d = op.send(op.twist())
    assert d.status == Status.STALE_COMMAND and "this robot's clock stepped 100 ms forward" in d.reason, d.reason


def test_the_first_command_of_a_session_refused_for_its_age_names_no_clock_step() -> None:
    sv = Supervisor(SafetyConfig(auto_arm=True), robot="sim1")
    op = Operator(sv)
    op.acquire(sv, "op1", op.mono, release=False)
    op.skew = -0.7
    d = op.send(op.twist(deadman=False))
    assert d.status == Status.STALE_COMMAND and d.reason == "command is 700 ms old (max 500 ms)", d.reason


def test_a_slow_drift_of_this_robots_clock_is_no_step_and_a_jump_beyond_the_slew_is() -> None:
    """Between two commands 100 s apart NTP may slew the wall clock 50 ms: 50 + 50 ms is jitter and slewing, a
    change of 120 ms is a step."""
    _sv, op = armed()
    op.skew = -0.45
    assert op.send(op.twist(deadman=False)).accepted
    op.mono += 100.0
    op.edge_step = 0.09  # within 50 ms + 500 ppm of 100 s
    d = op.send(op.twist(deadman=False))
    assert d.status == Status.STALE_COMMAND and "stepped" not in d.reason, d.reason
    op.mono += 100.0
    op.edge_step = 0.09 + 0.12
    d = op.send(op.twist(deadman=False))
    assert d.status == Status.STALE_COMMAND and "this robot's clock stepped 100 ms forward" in d.reason, d.reason



def test_a_command_exactly_max_command_age_old_or_ahead_is_accepted_and_one_ms_more_is_refused() -> None:
    sv, op = armed(max_command_age=0.5)
    sent = WALL0 + op.mono  # whole seconds: the command's time in ns and the ages below are exact
    for offset, accepted in ((0.5, True), (-0.5, True), (0.501, False), (-0.501, False)):
        op.seq += 1
        cmd = TwistCommand(operator="op1", linear=[0.005, 0.0, 0.0], deadman=True, state_age=0.02)
        cmd = op.sign(sv, "op1", cmd.stamp(op.seq, int(sent) * 10**9))
        d = sv.on_command(cmd, sent + offset, op.mono, POSE)
        assert d.accepted == accepted and (d.status == Status.STALE_COMMAND) != accepted, (offset, d)
        op.mono += 0.01


# ---------------------------------------------------------------- what the driver and the operator are told


def test_every_refusal_but_a_forgery_is_answered() -> None:
    """The operator's client learns why its command was refused from the echo; only forgeries go unanswered
    (an echo would amplify a flood)."""
    sv, op = armed()
    other = Operator(sv, "op2")
    op.skew = -2.0
    refusals = [op.send(op.twist()), other.send(other.twist()), op.send(op.twist(seq=1))]
    op.skew = 0.0
    sv.stop("e-stop")
    refusals.append(op.send(op.twist()))
    assert [d.status for d in refusals] == [Status.STALE_COMMAND, Status.NOT_OWNER, Status.OUT_OF_ORDER,
                                            Status.STOPPED]
    assert all(not d.accepted and d.answer for d in refusals)


def test_a_failed_driver_is_told_to_stop_whatever_it_was_told_before() -> None:
    sv, op = armed()
    assert op.send(op.twist(deadman=False)).action == Action.HOLD  # nothing was moving, nothing to send
    d = sv.driver_failed("send_twist failed: controller not in remote control")
    assert d.action == Action.STOP and not d.accepted and sv.status == Status.FAULT


def test_every_stop_of_a_moving_robot_and_every_stop_command_are_counted() -> None:
    sv, op = armed()
    assert op.send(op.twist()).action == Action.MOVE
    sv.step(op.mono + 0.2, POSE)  # the deadman times out while the robot moves
    assert sv.status == Status.COMMAND_TIMEOUT and sv.counters.stops == 1
    sv.disarm("armed off on site")  # nothing was moving: no stop
    assert sv.counters.stops == 1
    sv.stop("e-stop")  # a stop command counts whatever the robot did
    assert sv.counters.stops == 2


def test_a_stop_during_a_retreat_from_danger_counts_as_a_stop() -> None:
    sv, op = armed(force_required=True, force=ForceReaction(retract_distance=0.002, retract_speed=0.005))
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono)
    d = sv.step(op.mono + 0.01, POSE)  # deadman released: the retreat alone moves the probe (+z: away)
    assert d.action == Action.MOVE and d.twist[2] > 0 and sv.moving
    stops = sv.counters.stops
    sv.disarm("armed off on site")
    assert sv.counters.stops == stops + 1


def test_a_twist_exactly_at_the_profiles_speed_is_not_reported_as_limited() -> None:
    sv, op = armed(profile="remote")
    d = op.send(op.twist(vx=sv.limits.linear))
    assert d.accepted and d.status == Status.OK and d.limits_hit == [] and d.twist[0] == sv.limits.linear
    op.mono += 0.02
    op.seq += 1
    turn = TwistCommand(operator="op1", angular=[0.0, 0.0, sv.limits.angular], deadman=True, state_age=0.02)
    d = op.send(op.sign(sv, "op1", turn.stamp(op.seq, int((WALL0 + op.mono) * 1e9))))
    assert d.accepted and d.status == Status.OK and d.limits_hit == [] and d.twist[5] == sv.limits.angular


# ---------------------------------------------------------------- force


def test_with_the_force_reaction_switched_off_the_force_state_restricts_no_motion() -> None:
    """``force.enabled: false`` (a sensor fitted but its reaction off): no sample yet, or red, moves as without
    a sensor; the operator's own limits still apply."""
    sv, op = armed(force_required=True, force=ForceReaction(enabled=False))
    d = op.send(op.twist(vx=0.0, vz=-0.005))  # toward contact with no sample yet
    assert d.accepted and d.status == Status.OK and d.twist[2] == pytest.approx(-0.005)
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono)
    op.mono += 0.02
    d = op.send(op.twist(vx=0.0, vz=-0.005))
    assert d.accepted and d.status == Status.OK and d.twist[2] == pytest.approx(-0.005)
    sv.update_force(ForceLevel.SAFE, stale=True, now=op.mono)  # a silent sensor: no stop either
    op.mono += 0.02
    d = op.send(op.twist(vx=0.0, vz=-0.005))
    assert d.accepted and d.status == Status.OK and d.twist[2] == pytest.approx(-0.005)


def test_contact_mode_drives_on_a_force_reading_exactly_max_force_age_old() -> None:
    """Only an *older* reading stops the admittance (it holds); one exactly as old as allowed still drives it."""
    sv, op = armed(force_required=True)
    sv.config.contact.max_force_age = 0.0625  # a binary fraction: the age below is exact
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.contact_ceiling = 6.0
    ok, why = sv.set_contact(op.request(sv, "op1", keys.CONTROL_CONTACT), True, 4.0)
    assert ok, why
    sv.update_contact_force(0.0, op.mono)  # no force yet: the admittance approaches, -z with the tool down
    op.mono += 0.0625
    d = op.send(op.twist(vx=0.0))
    assert d.status == Status.CONTACT and d.twist[2] == pytest.approx(-sv.config.contact.max_speed), d
    op.mono += 0.001
    d = op.send(op.twist(vx=0.0))
    assert d.twist[2] == 0.0 and "no fresh force reading" in d.reason


def test_the_retreat_from_danger_runs_from_when_danger_was_reported_and_only_once_while_it_lasts() -> None:
    """retract_distance / retract_speed = 0.4 s of retreat, timed from the level change's own time (the force
    worker's, not the control loop's last cycle); danger reported again while it lasts starts no new retreat."""
    sv, op = armed(force_required=True, force=ForceReaction(retract_distance=0.002, retract_speed=0.005),
                   lease=10.0)
    sv.step(op.mono, POSE)  # the control loop's last cycle: 100.0
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono + 5.0)
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono + 5.0)
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono + 5.2)  # the level's periodic repeat
    assert sv.step(op.mono + 5.39, POSE).twist[2] > 0  # still backing off (+z: away, the tool points down)
    d = sv.step(op.mono + 5.41, POSE)
    assert not any(d.twist) and not sv.moving


def test_contact_mode_needs_a_force_sensor_and_a_target_above_zero_and_below_the_caution_level() -> None:
    sv, op = armed()  # no force sensor
    ok, why = sv.set_contact(op.request(sv, "op1", keys.CONTROL_CONTACT), True, 4.0)
    assert not ok and "needs a force sensor" in why and sv.contact_target is None
    sv, op = armed(force_required=True)
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.contact_ceiling = 6.0
    ok, why = sv.set_contact(op.request(sv, "op1", keys.CONTROL_CONTACT), True, 6.0)
    assert not ok and "below the caution level" in why and sv.contact_target is None
    ok, why = sv.set_contact(op.request(sv, "op1", keys.CONTROL_CONTACT), True, 0.0)
    assert not ok and "above 0" in why and sv.contact_target is None
    ok, why = sv.set_contact(op.request(sv, "op1", keys.CONTROL_CONTACT), True, 5.9)
    assert ok and sv.contact_target == 5.9, why


# ---------------------------------------------------------------- control and what it says


def test_the_owner_switches_to_a_known_profile_and_an_unknown_one_is_refused() -> None:
    sv, op = armed(profile="remote")
    ok, why = op.acquire(sv, "op1", op.mono, profile="fast")
    assert not ok and "unknown speed profile 'fast'" in why and sv.profile == "remote"
    ok, why = op.acquire(sv, "op1", op.mono, profile="local")
    assert ok and sv.profile == "local" and sv.limits.linear == 0.030, why


def test_the_lease_runs_out_exactly_lease_seconds_after_the_last_renewal() -> None:
    sv, _op = armed(lease=3.0)  # granted at 100.0 (and its release command at 100.0)
    other = Operator(sv, "op2")
    ok, why = other.acquire(sv, "op2", 102.999)
    assert not ok and "controlled by 'op1'" in why
    ok, why = other.acquire(sv, "op2", 103.0)
    assert ok and sv.owner == "op2", why


def test_the_age_of_the_last_command_is_the_time_since_it_was_accepted() -> None:
    sv, op = armed()
    assert op.send(op.twist()).accepted  # at 100.0
    assert sv.command_age(100.25) == 0.25
    assert sv.command_age(99.0) == 0.0  # a time before it (a late reading) is no negative age


def test_the_edges_answers_to_the_owner_are_signed_with_the_grants_key() -> None:
    """The owner's client believes only answers signed with its grant's key (a third session may answer on the
    same key expression); with nobody in control they go unsigned."""
    from iorthand.protocol import ControlReply
    from iorthand.security import auth

    sv = Supervisor(SafetyConfig(auto_arm=True), robot="sim1")
    payload = sv.answer(keys.CONTROL_ARM, ControlReply(ok=True, reason="armed").stamp(1))
    assert ControlReply.decode(payload).mac == b""
    op = Operator(sv)
    op.take()
    payload = sv.answer(keys.CONTROL_ARM, ControlReply(ok=True, reason="armed").stamp(2))
    reply = ControlReply.decode(payload)
    assert auth.verify(op.keys["op1"], auth.reply_context("sim1", keys.CONTROL_ARM), reply)


# ---------------------------------------------------------------- gaps, pictures and moves


def test_a_gap_of_exactly_resume_gap_resumes_without_a_fresh_press() -> None:
    """Only a gap *longer* than resume_gap needs the deadman released and pressed again."""
    _sv, op = armed(resume_gap=0.5, lease=10.0)
    assert op.send(op.twist()).accepted  # at 100.0
    op.mono += 0.5  # binary fractions: the gap is exactly 0.5 s
    d = op.send(op.twist())
    assert d.accepted and d.action == Action.MOVE, d
    op.mono += 0.5 + 2**-10
    d = op.send(op.twist())
    assert not d.accepted and d.status == Status.LINK_GAP


def test_a_picture_exactly_max_view_age_old_moves() -> None:
    _sv, op = armed(max_view_age=0.5)
    d = op.send(op.twist(view_age=0.5))
    assert d.accepted and d.action == Action.MOVE, d
    op.mono += 0.02
    d = op.send(op.twist(view_age=0.501))
    assert not d.accepted and d.status == Status.STALE_VIEW


def test_a_manual_twist_during_a_move_takes_over_and_ends_the_move() -> None:
    sv, op = armed()
    move = [0.004, 0.0, 0.0, 0.0, 0.0, 0.0]
    assert op.send(op.twist(vx=0.0), goto=move).twist == pytest.approx(move)
    op.mono += 0.02
    d = op.send(op.twist(vx=-0.003), goto=move)  # the operator steers the other way: his twist, not the move's
    assert d.accepted and d.twist[0] == pytest.approx(-0.003) and "took over" in d.cancel_goto, d
    assert sv.status == Status.OK


def test_near_a_face_of_the_workspace_the_tool_still_stops_in_half_the_distance_at_the_slower_deceleration() -> None:
    """A reduced twist is reached at the command acceleration, a stop at the stop deceleration: the speed allowed
    toward a face stops the tool within half the distance left (the margin for the sampled loop's lag) at the
    slower of the two, whichever of them is the slower."""
    for accel, stop in ((0.25, 0.5), (0.5, 0.25)):
        sv, op = armed(max_linear_acceleration=accel, stop_deceleration=stop)
        box_face = sv.config.workspace.max[0]
        near = [box_face - 0.0001, *POSE[1:]]  # 0.1 mm from the face
        d = sv.on_command(op.twist(vx=0.008), op.edge_wall, op.mono, near)
        v = d.twist[0]
        assert d.status == Status.WORKSPACE and 0 < v < 0.008
        assert v * v / (2 * min(accel, stop)) <= 0.0001 / 2 + 1e-12, (accel, stop, v)


def test_at_caution_the_approach_stops_within_the_overshoot_margin_at_the_slower_deceleration() -> None:
    """v·T + v²/(2a) ≤ overshoot_margin with a the slower of the command acceleration and the stop deceleration;
    and only at caution: at the safe level the approach is the operator's."""
    for accel, stop in ((0.25, 0.5), (0.5, 0.25)):
        sv, op = armed(force_required=True, profile="local", max_linear_acceleration=accel, stop_deceleration=stop)
        sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
        d = op.send(op.twist(vx=0.0, vz=-0.03))  # 30 mm/s toward contact (the tool points down)
        assert d.status == Status.OK and d.twist[2] == pytest.approx(-0.03)
        sv.update_force(ForceLevel.CAUTION, stale=False, now=op.mono)
        op.mono += 0.02
        d = op.send(op.twist(vx=0.0, vz=-0.03))
        v, f = -d.twist[2], sv.config.force
        assert d.status == Status.FORCE_CAUTION and 0 < v < 0.03
        assert v * f.reaction_time + v * v / (2 * min(accel, stop)) <= f.overshoot_margin + 1e-12, (accel, stop, v)


def test_a_danger_retreat_with_a_distance_but_no_speed_is_refused_when_the_file_loads() -> None:
    """Found by mutation testing: retract_distance set with retract_speed 0 loaded, and at DANGER no retreat ran,
    without a word. The edge's file now says so when it loads."""
    from iorthand.config import ConfigError, from_dict
    from iorthand_edge.config import EdgeConfig

    data = {"robot_id": "sim1", "zenoh": {"mode": "client", "connect": ["tcp/127.0.0.1:7447"]},
            "safety": {"force": {"retract_distance": 0.002, "retract_speed": 0.0}}}
    with pytest.raises(ConfigError, match=r"retract_distance 0\.002 m needs a retract_speed above 0"):
        from_dict(data, EdgeConfig, source="<test>")


# ---------------------------------------------------------------- refusals for a command's time


def test_a_refusal_for_the_commands_time_shows_in_the_safety_status_only_while_the_robot_stands_unheld() -> None:
    """The safety status says why the robot stands still: a time refusal while the robot still moves on the last
    command (the deadman timeout stops it, with its own reason) does not take it, nor does it cover the reason of
    a stop that holds the robot; with the deadman released and nothing latched, it is what the operator reads."""
    sv, op = armed()
    assert op.send(op.twist()).action == Action.MOVE
    op.mono += 0.02
    op.skew = -2.0
    d = op.send(op.twist())
    assert d.status == Status.STALE_COMMAND and not d.accepted
    assert sv.status == Status.OK, (sv.status, sv.reason)  # still moving on the last command, until the timeout
    op.skew = 0.0
    op.mono += 0.02
    assert op.send(op.twist(deadman=False)).accepted
    op.skew = -2.0
    op.mono += 0.02
    d = op.send(op.twist(deadman=False))
    assert sv.status == Status.STALE_COMMAND and sv.reason == d.reason
    sv.stop("e-stop from the nurse")
    op.mono += 0.02
    d = op.send(op.twist(deadman=False))
    assert d.status == Status.STALE_COMMAND
    assert sv.status == Status.STOPPED and sv.reason == "e-stop from the nurse"


def test_the_timeout_gives_the_time_refusals_reason_only_when_they_kept_coming_until_it() -> None:
    """Commands refused for their time up to command_timeout before the timeout fires: the stop says why they
    were refused (the clocks), not "no command". A refusal followed by a longer silence: the link is what
    stopped the robot, and the reason says so."""
    sv, op = armed(command_timeout=0.125)  # binary fractions: the times below are exact
    assert op.send(op.twist()).accepted  # at 100.0
    op.mono += 0.0625
    op.skew = -2.0
    refused = op.send(op.twist())
    assert refused.status == Status.STALE_COMMAND
    d = sv.step(100.1875, POSE)  # the last refusal exactly command_timeout ago
    assert not any(d.twist) and d.action == Action.STOP
    assert sv.status == Status.STALE_COMMAND and sv.reason == refused.reason, sv.reason

    sv, op = armed(command_timeout=0.125)
    assert op.send(op.twist()).accepted  # at 100.0
    op.mono += 0.0625
    op.skew = -2.0
    assert op.send(op.twist()).status == Status.STALE_COMMAND
    d = sv.step(100.25, POSE)  # then 187.5 ms of silence: longer than the timeout
    assert not any(d.twist) and d.action == Action.STOP
    assert sv.status == Status.COMMAND_TIMEOUT and sv.reason.startswith("no command for 250 ms"), sv.reason


def test_the_age_a_time_refusal_gives_stays_through_the_jitter_of_a_link_and_follows_a_real_change() -> None:
    """The operator's client logs each distinct refusal once: 600 ms then 680 ms old (jitter, under 200 ms) is
    one reason, "600 ms old"; 900 ms old is a change it reads."""
    _sv, op = armed()
    assert op.send(op.twist(deadman=False)).accepted
    reasons = []
    for skew in (-0.6, -0.68, -0.9):
        op.mono += 0.02
        op.skew = skew
        d = op.send(op.twist(deadman=False))
        assert d.status == Status.STALE_COMMAND
        reasons.append(d.reason)
    assert [r.split(" (")[0] for r in reasons] == ["command is 600 ms old", "command is 600 ms old",
                                                   "command is 900 ms old"], reasons


# ---------------------------------------------------------------- refused commands and the owner's motion


def test_a_refused_command_leaves_the_owners_motion_as_it_was() -> None:
    """Another operator's command, a replay or a command too old changes nothing: the driver goes on with the
    owner's twist (the deadman timeout stops it if the owner's commands stop); none of them is a stop."""
    sv, op = armed()
    assert op.send(op.twist(vx=0.005)).action == Action.MOVE
    other = Operator(sv, "op2")
    refused = [other.send(other.twist(vx=0.0, deadman=False)), op.send(op.twist(vx=0.0, seq=1))]
    op.skew = -2.0
    refused.append(op.send(op.twist(vx=0.0)))
    for d in refused:
        assert not d.accepted and d.action == Action.MOVE and d.twist == pytest.approx([0.005, 0, 0, 0, 0, 0]), d
    assert sv.deadman and sv.counters.stops == 0


# ---------------------------------------------------------------- force: what is and is not an intervention


def test_without_a_retreat_configured_danger_promises_none_and_runs_none() -> None:
    """retract_distance 0 (the default): at DANGER the reason says only that pressing harder is removed."""
    sv, op = armed(force_required=True)
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono)
    assert sv.status == Status.FORCE_DANGER and sv.reason == "danger-level force: motion pressing harder removed"
    d = sv.step(op.mono + 0.01, POSE)
    assert not any(d.twist) and not sv.moving


def test_sliding_along_the_surface_is_no_force_intervention_stale_or_at_danger() -> None:
    """The tool points down (pressing is -z): a sideways twist does not press harder, so a stale sensor or a
    danger-level force lets it through unreported; only motion toward contact is refused or removed."""
    sv, op = armed(force_required=True)  # no force sample yet: stale
    d = op.send(op.twist(vx=0.005))
    assert d.accepted and d.status == Status.OK and d.limits_hit == [] and d.twist[0] == 0.005, d
    op.mono += 0.02
    d = op.send(op.twist(vx=0.005, vz=-0.002))
    assert d.status == Status.FORCE_STALE and d.twist[2] == 0.0 and d.twist[0] == 0.005
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono)
    op.mono += 0.02
    d = op.send(op.twist(vx=0.005))
    assert d.accepted and d.status == Status.OK and d.limits_hit == [] and d.twist[0] == 0.005, d
    op.mono += 0.02
    d = op.send(op.twist(vx=0.005, vz=-0.002))
    assert d.status == Status.FORCE_DANGER and d.twist[2] == 0.0 and d.twist[0] == 0.005


def test_at_caution_an_approach_exactly_at_the_capped_speed_is_not_reported_as_slowed() -> None:
    sv, op = armed(force_required=True, profile="local")
    cap = sv.config.force.approach_speed_cap(min(sv.config.max_linear_acceleration, sv.config.stop_deceleration))
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.update_force(ForceLevel.CAUTION, stale=False, now=op.mono)
    d = op.send(op.twist(vx=0.0, vz=-cap))
    assert d.accepted and d.status == Status.OK and d.limits_hit == [] and d.twist[2] == -cap, d
    op.mono += 0.02
    d = op.send(op.twist(vx=0.0, vz=-0.03))
    assert d.status == Status.FORCE_CAUTION and d.twist[2] == pytest.approx(-cap)


# ---------------------------------------------------------------- gaps and pictures


def test_a_spell_of_refused_motion_is_told_from_a_silent_link() -> None:
    """After a picture too old (commands kept coming, within resume_gap of each other) the fresh press is asked
    for because "motion was refused", not because of a gap in the commands."""
    _sv, op = armed(resume_gap=0.5, lease=10.0)
    assert op.send(op.twist()).accepted  # at 100.0: the last live command
    op.mono += 0.25
    assert op.send(op.twist(view_age=1.0)).status == Status.STALE_VIEW
    op.mono += 0.5  # exactly resume_gap after the last command, 750 ms after the last live one
    d = op.send(op.twist())
    assert d.status == Status.LINK_GAP and d.reason.startswith("motion was refused for 750 ms"), d.reason


def test_a_command_naming_the_robot_state_stamped_as_it_arrives_acts_on_a_live_picture() -> None:
    """The picture's age is measured on this edge's clock from the state the command names, 0 s here, whatever
    the operator's own estimate (its clock against this edge's) says."""
    _sv, op = armed()
    op.seq += 1
    cmd = TwistCommand(operator="op1", linear=[0.005, 0.0, 0.0], deadman=True, state_age=5.0,
                       view_t=int(op.edge_wall) * 10**9)  # whole seconds: the age is exactly 0
    d = op.send(op.sign(op.sv, "op1", cmd.stamp(op.seq, int(op.edge_wall * 1e9))))
    assert d.accepted and d.action == Action.MOVE, d


# ---------------------------------------------------------------- the workspace box


def test_a_workspace_box_is_closed_and_has_a_volume_within_an_arms_reach() -> None:
    """A tool on a face is inside; a box flat on one axis is refused, as is a face beyond 2 m (a box written in
    millimetres); faces at 2 m load."""
    box = WorkspaceBox()
    assert box.contains(box.min) and box.contains(box.max) and box.contains([0.45, 0.0, 0.02])
    assert not box.contains([0.4501, 0.0, 0.2]) and not box.contains([0.3, 0.0, 0.0199])
    with pytest.raises(ValueError, match="must be below max"):
        WorkspaceBox(min=[0.1, -0.3, 0.2], max=[0.45, 0.3, 0.2]).check()
    WorkspaceBox(min=[-2.0, -2.0, -2.0], max=[2.0, 2.0, 2.0]).check()
    with pytest.raises(ValueError, match="beyond any arm's reach"):
        WorkspaceBox(min=[0.1, -0.3, 0.02], max=[2.5, 0.3, 0.45]).check()


def test_toward_a_face_a_speed_exactly_the_one_that_still_stops_in_time_is_not_reported_as_limited() -> None:
    """1/64 m from the face at 0.125 m/s² (half the slower of acceleration 0.25 and stop 0.5): √(2·a·d) is
    exactly 62.5 mm/s, and a twist of that speed is the operator's, unreported."""
    sv, op = armed(profiles={"remote": SpeedProfile(linear=0.0625)})
    sv.config.workspace.max[0] = 0.5
    near = [0.5 - 2**-6, *POSE[1:]]
    d = sv.on_command(op.twist(vx=0.0625), op.edge_wall, op.mono, near)
    assert d.accepted and d.status == Status.OK and d.limits_hit == [] and d.twist[0] == 0.0625, d


# ---------------------------------------------------------------- arming, control and what they say


def test_a_stop_before_anyone_took_control_holds_and_is_counted() -> None:
    """The nurse presses the e-stop before any operator connected: the stop holds and is counted like any other
    (disarming a robot that never moved is no stop)."""
    sv = Supervisor(SafetyConfig(auto_arm=True))
    sv.disarm("armed off on site")
    assert sv.counters.stops == 0
    sv.arm()
    sv.stop("e-stop pressed at the bedside")
    assert sv.status == Status.STOPPED and sv.reason == "e-stop pressed at the bedside"
    assert sv.stop_in_force and sv.counters.stops == 1 and not sv.deadman


def test_an_edge_not_yet_armed_refuses_commands_until_armed_on_site_and_then_says_so() -> None:
    sv = Supervisor(SafetyConfig(), robot="sim1")
    op = Operator(sv)
    op.take()
    d = op.send(op.twist())
    assert not d.accepted and d.status == Status.DISARMED and d.reason == "not armed: confirm arming on the robot side"
    sv.arm()
    assert sv.status == Status.IDLE and sv.reason == "armed"  # no console keeps reading "not armed"
    assert sv.request_arm("op1") == (True, "already armed") and not sv.arm_requested
    op.mono += 0.02
    assert op.send(op.twist(deadman=False)).accepted
    op.mono += 0.02
    assert op.send(op.twist()).action == Action.MOVE


def test_control_is_held_for_a_lease_from_the_grant_and_every_command_renews_it() -> None:
    """Between the grant and the operator's first command nobody else takes control; commands renew the lease
    without a renewal request."""
    sv = Supervisor(SafetyConfig(auto_arm=True, lease=3.0), robot="sim1")
    op = Operator(sv)
    op.acquire(sv, "op1", 100.0, release=False)
    other = Operator(sv, "op2")
    ok, why = other.acquire(sv, "op2", 102.0)  # the grant's lease runs to 103.0
    assert not ok and "controlled by 'op1'" in why
    for t in (102.5, 104.0, 105.5):
        op.mono = t
        assert op.send(op.twist(deadman=False)).accepted
    ok, why = other.acquire(sv, "op2", 108.0)  # 2.5 s after the last command: the lease runs to 108.5
    assert not ok and "controlled by 'op1'" in why


def test_a_new_grant_after_a_lease_ran_out_starts_a_new_sequence() -> None:
    """op1 sent 50 commands and went silent; once its lease ran out op2 takes control and its commands, numbered
    from 1 by its own session, are in order."""
    sv, op = armed(lease=3.0)
    for _ in range(50):
        op.mono += 0.01
        assert op.send(op.twist(deadman=False)).accepted
    other = Operator(sv, "op2")
    other.mono = 104.0
    other.take()
    d = other.send(other.twist())
    assert d.accepted and d.action == Action.MOVE and sv.owner == "op2", d


def test_releasing_control_stops_the_robot_at_once_and_ends_the_grants_signature() -> None:
    from iorthand.protocol import ControlReply, SafetyStatus

    sv, op = armed()
    assert op.send(op.twist()).action == Action.MOVE
    ok, why = sv.release(op.request(sv, "op1", keys.CONTROL_RELEASE))
    assert ok, why
    assert sv.status == Status.IDLE and sv.reason == "released by its owner" and not sv.deadman
    d = sv.step(op.mono + 0.01, POSE)  # well within the command timeout
    assert not any(d.twist) and d.action == Action.STOP
    assert sv.grant_key == b""
    assert ControlReply.decode(sv.answer(keys.CONTROL_ARM, ControlReply(ok=True, reason="armed").stamp(5))).mac == b""
    state = SafetyStatus(status=Status.IDLE).stamp(6)
    assert sv.for_owner(keys.STATE_SAFETY, state) == state.encode()


def test_a_request_from_outside_the_grant_is_told_who_holds_control() -> None:
    sv = Supervisor(SafetyConfig(auto_arm=True), robot="sim1")
    op = Operator(sv)
    ok, why = sv.release(op.request(sv, "op1", keys.CONTROL_RELEASE))
    assert not ok and why == "'op1' does not hold control (nobody does)"
    d = op.send(op.twist())
    assert d.status == Status.NOT_OWNER and d.reason == "no operator holds control: acquire it first"
    op.take()
    other = Operator(sv, "op2")
    ok, why = sv.release(other.request(sv, "op2", keys.CONTROL_RELEASE))
    assert not ok and why == "'op2' does not hold control ('op1' does)"


def test_acquiring_after_a_lost_owner_acknowledges_it_and_the_status_asks_for_a_fresh_press() -> None:
    sv, op = armed()
    assert op.send(op.twist()).action == Action.MOVE
    assert sv.owner_lost("op1", "liveliness lost")
    assert sv.status == Status.OWNER_LOST
    op.acquire(sv, "op1", op.mono + 1.0, release=False)
    assert sv.status == Status.STOPPED
    assert sv.reason == "liveliness lost — acknowledged: release the deadman and press it again"


# ---------------------------------------------------------------- the deadman and what the edge publishes


def test_releasing_the_deadman_is_published_at_once_as_released() -> None:
    """The safety state and the loop's wake-up follow the released deadman: no timeout is pending, the status
    says so, and the robot, stopped by the release, is no moving robot to a stop that follows."""
    sv, op = armed()
    assert op.send(op.twist()).action == Action.MOVE
    op.mono += 0.02
    d = op.send(op.twist(deadman=False))
    assert d.action == Action.STOP and not any(d.twist)
    assert not sv.deadman and sv.timeout_at() == math.inf
    assert sv.status == Status.NO_DEADMAN and sv.reason == "deadman released"
    sv.step(op.mono + 0.008, POSE)
    sv.disarm("armed off on site")
    assert sv.counters.stops == 0


def test_a_stop_shows_the_deadman_released() -> None:
    sv, op = armed()
    assert op.send(op.twist()).action == Action.MOVE
    sv.stop("e-stop")
    assert not sv.deadman and sv.timeout_at() == math.inf


def test_the_limits_a_command_hit_are_published_with_the_safety_state() -> None:
    sv, op = armed(profile="remote")
    d = op.send(op.twist(vx=0.02))
    assert d.limits_hit == ["linear_speed"] and sv.limits_hit == ["linear_speed"]
    op.mono += 0.02
    op.send(op.twist(vx=0.005))
    assert sv.limits_hit == []


def test_refusals_for_an_old_picture_and_under_a_stop_are_counted_as_rejected() -> None:
    sv, op = armed()
    before = sv.counters.rejected
    assert op.send(op.twist(view_age=2.0)).status == Status.STALE_VIEW
    sv.stop("e-stop")
    op.mono += 0.02
    assert op.send(op.twist()).status == Status.STOPPED
    c = sv.counters
    assert c.rejected - before == 2 and c.applied + c.rejected == c.received


def test_during_a_fault_even_a_released_deadman_is_refused_with_the_fault() -> None:
    """The safety status keeps the fault: a release is no acknowledgement (acquiring control again is)."""
    sv, op = armed()
    sv.set_fault("protective stop")
    d = op.send(op.twist(deadman=False))
    assert not d.accepted and d.status == Status.FAULT and d.reason == "protective stop"
    assert sv.status == Status.FAULT and sv.reason == "protective stop"


def test_a_command_saying_its_screen_shows_no_robot_state_is_refused_even_if_it_names_one() -> None:
    _sv, op = armed()
    op.seq += 1
    cmd = TwistCommand(operator="op1", linear=[0.005, 0.0, 0.0], deadman=True, state_age=-1.0,
                       view_t=int((op.edge_wall - 0.02) * 1e9))
    d = op.send(op.sign(op.sv, "op1", cmd.stamp(op.seq, int(op.edge_wall * 1e9))))
    assert not d.accepted and d.status == Status.STALE_VIEW and "no robot state" in d.reason, d


def test_a_release_of_the_deadman_counts_as_the_operators_live_intent_for_the_resume_gap() -> None:
    """Pressed, released 400 ms later, a press refused for an old picture, then a live press 300 ms after the
    release: no gap of more than resume_gap since the operator last acted, and the robot moves."""
    _sv, op = armed(resume_gap=0.5, lease=10.0)
    assert op.send(op.twist()).accepted  # at 100.0
    op.mono += 0.375
    assert op.send(op.twist(deadman=False)).accepted
    op.mono += 0.125
    assert op.send(op.twist(view_age=1.0)).status == Status.STALE_VIEW
    op.mono += 0.25
    d = op.send(op.twist())
    assert d.accepted and d.action == Action.MOVE, d


# ---------------------------------------------------------------- force and contact mode


def test_a_tilted_probe_at_danger_loses_exactly_the_motion_along_its_axis() -> None:
    """The probe tilted (its axis has components on every base axis): at DANGER the part of the twist pressing
    along the axis is removed and the sliding part is kept, on all three axes."""
    from iorthand.geometry import rotate

    sv, op = armed(force_required=True)
    pose = [0.30, 0.0, 0.20, 2.0, 1.0, 0.5]
    n = rotate(pose[3:], [0.0, 0.0, 1.0])
    assert min(abs(c) for c in n) > 0.4
    side = [n[1], -n[0], 0.0]  # perpendicular to the axis
    side = [0.003 * c / math.hypot(*side) for c in side]
    push = [s + 0.005 * c for s, c in zip(side, n, strict=True)]
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono)
    op.seq += 1
    cmd = TwistCommand(operator="op1", linear=push, deadman=True, state_age=0.02)
    cmd = op.sign(sv, "op1", cmd.stamp(op.seq, int(op.edge_wall * 1e9)))
    d = sv.on_command(cmd, op.edge_wall, op.mono, pose)
    assert d.status == Status.FORCE_DANGER and d.twist[:3] == pytest.approx(side, abs=1e-12), d


def test_contact_mode_is_logged_and_holds_the_axis_until_a_force_reading_along_the_probe_arrives() -> None:
    sv, op = armed(force_required=True)
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.contact_ceiling = 6.0
    ok, why = sv.set_contact(op.request(sv, "op1", keys.CONTROL_CONTACT), True, 4.0)
    assert ok, why
    assert sv.interventions[-1] == (Status.CONTACT, "contact mode on: holding 4 N along the probe")
    d = op.send(op.twist(vx=0.005, vz=-0.005))  # no reading along the probe yet
    assert d.accepted and d.status == Status.CONTACT, d
    assert d.reason == "contact mode: no force reading along the probe yet: holding"  # (it said "for inf ms")
    assert d.twist[0] == 0.005 and d.twist[2] == 0.0
    ok, why = sv.set_contact(op.request(sv, "op1", keys.CONTROL_CONTACT), False)
    assert ok and sv.interventions[-1] == (Status.CONTACT, "contact mode off: left by the operator")


def test_a_force_sensor_going_silent_during_a_retreat_ends_it() -> None:
    """A silent sensor stops the robot, the retreat included; once the deadman is released nothing moves and
    nothing says it is retracting."""
    sv, op = armed(force_required=True, force=ForceReaction(retract_distance=0.002, retract_speed=0.005))
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono)
    assert sv.step(op.mono + 0.01, POSE).twist[2] > 0  # backing off (+z: away)
    sv.update_force(ForceLevel.DANGER, stale=True, now=op.mono + 0.02)
    d = sv.step(op.mono + 0.03, POSE)
    assert not any(d.twist) and d.action == Action.STOP and sv.status == Status.FORCE_STALE
    op.mono += 0.04
    assert op.send(op.twist(deadman=False)).accepted
    d = sv.step(op.mono + 0.01, POSE)  # within the 0.4 s the retreat would have lasted
    assert not any(d.twist) and sv.status == Status.NO_DEADMAN and "retracting" not in sv.reason, sv.reason


def test_a_force_level_given_without_a_time_is_timed_at_the_latest_event() -> None:
    """update_force without ``now`` times the retreat from the latest command or control cycle (also before
    any: a level at start)."""
    force = ForceReaction(retract_distance=0.002, retract_speed=0.005)  # 0.4 s of retreat
    sv = Supervisor(SafetyConfig(auto_arm=True, force=force, lease=10.0), force_required=True, robot="sim1")
    sv.update_force(ForceLevel.SAFE, stale=False)  # before any event
    op = Operator(sv)
    op.take()
    sv.step(100.5, POSE)
    op.mono = 101.0
    assert op.send(op.twist(deadman=False)).accepted  # the latest event: this command at 101.0
    sv.update_force(ForceLevel.DANGER, stale=False)
    assert sv.step(101.39, POSE).twist[2] > 0
    assert not any(sv.step(101.41, POSE).twist)
    sv.update_force(ForceLevel.SAFE, stale=False)
    sv.step(102.0, POSE)  # the latest event: this cycle
    sv.update_force(ForceLevel.DANGER, stale=False)
    assert sv.step(102.39, POSE).twist[2] > 0


def test_the_retreat_from_danger_backs_off_at_exactly_retract_speed_whatever_the_operator_presses() -> None:
    """Pressing at DANGER (a twist or a previewed move), or at CAUTION once the level dropped during the retreat:
    what presses is removed or capped first, and the probe backs off at retract_speed, not faster."""
    sv, op = armed(force_required=True, profile="local",
                   force=ForceReaction(retract_distance=0.002, retract_speed=0.005))  # 0.4 s of retreat
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono)
    d = op.send(op.twist(vx=0.0, vz=-0.03))  # pressing (the tool points down)
    assert d.status == Status.FORCE_DANGER and d.reason == "danger-level force: retracting along the contact normal"
    assert d.twist[2] == pytest.approx(0.005), d
    op.mono += 0.02
    d = op.send(op.twist(vx=0.0), goto=[0.0, 0.0, -0.004, 0.0, 0.0, 0.0])  # a previewed move pressing
    assert d.status == Status.FORCE_DANGER and d.twist[2] == pytest.approx(0.005), d
    sv.update_force(ForceLevel.CAUTION, stale=False, now=op.mono)
    op.mono += 0.02
    d = op.send(op.twist(vx=0.0, vz=-0.03))
    assert d.status == Status.FORCE_DANGER and d.twist[2] == pytest.approx(0.005), d


def test_while_the_probe_backs_off_by_itself_the_status_says_so_and_the_box_still_bounds_it() -> None:
    sv, op = armed(force_required=True, force=ForceReaction(retract_distance=0.002, retract_speed=0.005))
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono)
    op.mono += 0.01
    assert op.send(op.twist(deadman=False)).accepted  # the operator lets go: the retreat goes on
    d = sv.step(op.mono + 0.01, POSE)
    assert d.twist[2] > 0 and sv.status == Status.FORCE_DANGER and sv.reason == "retracting from danger-level force"
    at_top = [*POSE[:2], sv.config.workspace.max[2], *POSE[3:]]  # backing off is +z: out of the box here
    d = sv.step(op.mono + 0.02, at_top)
    assert d.twist[2] == 0.0 and math.hypot(*d.twist[:3]) < 1e-15, d  # (a rounding error's sideways 1e-18 m/s)


def test_each_force_intervention_is_logged_once_when_it_starts() -> None:
    """The agent logs the interventions: danger when it is reported (the deadman may be released), each spell of
    a slowed approach once, however many commands it lasts, and again after a spell without."""
    sv, op = armed(force_required=True, profile="local")
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono)
    assert sv.interventions[-1] == (Status.FORCE_DANGER, "danger-level force: motion pressing harder removed")
    logged = len(sv.interventions)
    for _ in range(3):
        op.mono += 0.008
        assert op.send(op.twist(vx=0.0, vz=-0.005)).status == Status.FORCE_DANGER
    assert len(sv.interventions) == logged
    sv.update_force(ForceLevel.CAUTION, stale=False, now=op.mono)
    for vz in (-0.03, -0.03, 0.0, -0.03):
        op.mono += 0.008
        op.send(op.twist(vx=0.0 if vz else 0.005, vz=vz))
    cap = sv.config.force.approach_speed_cap(min(sv.config.max_linear_acceleration, sv.config.stop_deceleration))
    assert [r for s, r in sv.interventions if s == Status.FORCE_CAUTION] == \
        [f"caution-level force: approach slowed to {1000 * cap:.1f} mm/s"] * 2


def test_a_turn_faster_than_the_profile_is_reported_as_limited() -> None:
    sv, op = armed(profile="remote")
    op.seq += 1
    turn = TwistCommand(operator="op1", angular=[0.0, 0.0, 0.5], deadman=True, state_age=0.02)
    d = op.send(op.sign(sv, "op1", turn.stamp(op.seq, int(op.edge_wall * 1e9))))
    assert d.status == Status.SPEED_LIMITED and d.limits_hit == ["angular_speed"]
    assert d.reason == "angular speed 0.50 rad/s clipped to 0.10 rad/s (remote)" and d.twist[5] == pytest.approx(0.1)


def test_a_clock_difference_of_seconds_or_hours_is_given_in_seconds_or_hours() -> None:
    _sv, op = armed()
    assert op.send(op.twist(deadman=False)).accepted
    reasons = []
    for skew in (-30.0, -7200.0 * 2):
        op.mono += 0.02
        op.skew = skew
        reasons.append(op.send(op.twist(deadman=False)).reason)
    assert reasons == ["command is 30 s old (max 500 ms)", "command is 4 h old (max 500 ms)"], reasons


def test_without_a_retreat_its_speed_may_be_zero() -> None:
    """retract_distance 0 switches the retreat off: a retract_speed of 0 beside it loads (it is only refused
    beside a distance, where the retreat would never run)."""
    ForceReaction(retract_distance=0.0, retract_speed=0.0).check()
    ForceReaction(retract_distance=0.002, retract_speed=0.005).check()
    with pytest.raises(ValueError, match="needs a retract_speed above 0"):
        ForceReaction(retract_distance=0.001, retract_speed=0.0).check()


def test_the_retreat_lasts_exactly_its_distance_at_its_speed_and_never_overrides_a_faster_lift() -> None:
    """2^-9 m at 2^-8 m/s: 0.5 s of retreat from the level change (binary fractions: the instants are exact). At
    0.5 s the deadman held sideways moves only sideways; during it an operator lifting off at the retreat's own
    speed is not overridden (nothing to add, nothing to report)."""
    sv, op = armed(force_required=True, lease=10.0, force=ForceReaction(retract_distance=2**-9, retract_speed=2**-8))
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono)  # at 100.0: the retreat runs to 100.5
    op.mono += 0.25
    d = op.send(op.twist(vx=0.0, vz=2**-8))  # lifting (+z) at exactly the retreat's speed
    assert d.status == Status.OK and d.twist[2] == 2**-8, d
    op.mono += 0.25
    d = op.send(op.twist(vx=0.005))  # at 100.5
    assert d.status == Status.OK and d.twist[:3] == [0.005, 0.0, 0.0], d


# ---------------------------------------------------------------- units, bounds, tilted probes and what the driver gets


def test_a_clock_difference_reads_in_the_unit_a_person_reads_it_in() -> None:
    """To 100 ms below 10 s, then seconds below 2 min, minutes below 2 h, hours below 2 days, days below 2 years,
    then years; each rounded to a whole unit."""
    from iorthand_edge.supervisor import _duration

    table = [(9.7, "9700 ms"), (10.0, "10 s"), (-30.0, "30 s"), (119.4, "119 s"), (120.0, "2 min"),
             (6000.0, "100 min"), (7199.4, "120 min"), (7200.0, "2 h"), (88199.0, "24 h"), (88201.0, "25 h"),
             (172799.0, "48 h"), (172801.0, "2 days"), (215999.0, "2 days"), (216001.0, "3 days"),
             (63115199.0, "730 days"), (63115201.0, "2 years")]
    assert [(s, _duration(s)) for s, _ in table] == table


def test_a_command_from_the_future_says_so() -> None:
    _sv, op = armed()
    assert op.send(op.twist(deadman=False)).accepted
    op.mono += 0.02
    op.skew = 0.6  # the operator's clock runs 600 ms ahead
    d = op.send(op.twist(deadman=False))
    assert d.status == Status.STALE_COMMAND and d.reason == "command time is 600 ms in the future: check clock sync"


def test_a_command_with_no_sequence_number_is_refused() -> None:
    """Sequence 0 is an unstamped message: the first command of a grant must be numbered from 1."""
    sv = Supervisor(SafetyConfig(auto_arm=True), robot="sim1")
    op = Operator(sv)
    op.acquire(sv, "op1", op.mono, release=False)
    d = op.send(op.twist(deadman=False, seq=0))
    assert not d.accepted and d.status == Status.OUT_OF_ORDER, d


def test_a_contact_axis_needs_a_tenth_of_a_unit_length_and_is_normalised() -> None:
    for axis in ([0.0, 0.0, 0.1], [0.0, 0.09, 0.12]):  # length 0.1 and 0.15: load
        ForceReaction(contact_axis=axis).check()
    with pytest.raises(ValueError, match="must be a direction"):
        ForceReaction(contact_axis=[0.0, 0.0, 0.05]).check()


def test_contact_mode_holds_a_light_target_force() -> None:
    sv, op = armed(force_required=True)
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.contact_ceiling = 6.0
    ok, why = sv.set_contact(op.request(sv, "op1", keys.CONTROL_CONTACT), True, 0.5)
    assert ok and sv.contact_target == 0.5, why


def test_right_at_a_face_the_tool_takes_two_control_periods_to_reach_it() -> None:
    """10 µm from the face the reaction horizon binds, not the braking distance: v·2T ≤ d, with T the control
    period (8 ms at 125 Hz by default, 4 ms when the loop runs at 250 Hz)."""
    for period in (None, 1 / 250):
        kwargs = {} if period is None else {"period": period}
        sv = Supervisor(SafetyConfig(auto_arm=True), robot="sim1", **kwargs)
        op = Operator(sv)
        op.take()
        near = [sv.config.workspace.max[0] - 1e-5, *POSE[1:]]
        d = sv.on_command(op.twist(vx=0.008), op.edge_wall, op.mono, near)
        assert d.status == Status.WORKSPACE
        assert d.twist[0] == pytest.approx(1e-5 / (2 * (period or 1 / 125)), rel=1e-6), (period, d)


TILTED = [0.30, 0.0, 0.20, 2.0, 1.0, 0.5]  # the probe's axis has a component on every base axis


def _axis_and_side(pose: list[float]) -> tuple[list[float], list[float]]:
    """The probe's pressing direction in the base frame and a unit direction perpendicular to it."""
    from iorthand.geometry import rotate

    n = list(rotate(pose[3:], [0.0, 0.0, 1.0]))
    side = [n[1], -n[0], 0.0]
    return n, [c / math.hypot(*side) for c in side]


def _signed(op: Operator, linear: list[float], angular: list[float] | None = None, **fields: object) -> TwistCommand:
    op.seq += 1
    cmd = TwistCommand(operator=op.name, linear=linear, angular=angular or [0.0, 0.0, 0.0], deadman=True,
                       state_age=0.02)
    for name, value in fields.items():
        setattr(cmd, name, value)
    return op.sign(op.sv, op.name, cmd.stamp(op.seq, int((op.edge_wall + op.skew) * 1e9)))


def test_every_decision_gives_the_driver_a_twist_of_six_components() -> None:
    """Released, refused for an old picture or another operator's, a retreat and its end, under a stop, a failed
    driver: the driver always gets [vx, vy, vz, wx, wy, wz]."""
    sv, op = armed(force_required=True, force=ForceReaction(retract_distance=0.002, retract_speed=0.005))
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    other = Operator(sv, "op2")
    decisions = [op.send(op.twist(deadman=False)), op.send(op.twist(view_age=2.0)), other.send(other.twist())]
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono)
    decisions += [sv.step(op.mono + 0.01, POSE), sv.step(op.mono + 1.0, POSE)]
    sv.stop("e-stop")
    op.mono += 1.0
    decisions += [op.send(op.twist()), sv.step(op.mono, POSE), sv.driver_failed("send_twist failed")]
    assert decisions[3].twist[2] > 0  # the retreat moved
    assert [len(d.twist) for d in decisions] == [6] * len(decisions)


def test_near_a_lower_face_of_the_workspace_the_tool_slows_too() -> None:
    sv, op = armed()
    near = [sv.config.workspace.min[0] + 0.0001, *POSE[1:]]
    d = sv.on_command(op.twist(vx=-0.008), op.edge_wall, op.mono, near)
    assert d.status == Status.WORKSPACE and -0.008 < d.twist[0] < 0, d


def test_a_tool_outside_the_workspace_may_only_move_back_in() -> None:
    sv, op = armed()
    outside = [sv.config.workspace.max[0] + 0.01, *POSE[1:]]
    d = sv.on_command(op.twist(vx=0.005), op.edge_wall, op.mono, outside)
    assert d.status == Status.WORKSPACE and d.twist[0] == 0.0, d
    op.mono += 0.02
    d = sv.on_command(op.twist(vx=-0.005), op.edge_wall, op.mono, outside)
    assert d.status == Status.OK and d.twist[0] == -0.005, d


def test_a_tilt_faster_than_the_profile_is_clipped_and_a_turn_at_it_beside_a_full_speed_slide_is_not() -> None:
    _sv, op = armed(profile="remote")
    d = op.send(_signed(op, [0.0, 0.0, 0.0], [0.5, 0.0, 0.0]))  # tilting about x
    assert d.status == Status.SPEED_LIMITED and d.twist[3] == pytest.approx(0.1), d
    op.mono += 0.02
    d = op.send(_signed(op, [0.0, 0.0, 0.008], [0.0, 0.0, 0.1]))
    assert d.status == Status.OK and d.limits_hit == [] and d.twist[2:] == [0.008, 0.0, 0.0, 0.1], d


def test_a_previewed_move_at_danger_stops_pressing_and_only_lifting_goes_on_whatever_the_tilt() -> None:
    """No retreat configured: a move that presses along the tilted probe's axis stops entirely; a move that lifts
    goes on along the axis."""
    sv, op = armed(force_required=True)
    n, side = _axis_and_side(TILTED)
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono)
    pressing = [0.004 * a + 0.002 * s for a, s in zip(n, side, strict=True)] + [0.0, 0.0, 0.0]
    d = sv.on_command(_signed(op, [0.0, 0.0, 0.0]), op.edge_wall, op.mono, TILTED, pressing)
    assert d.status == Status.FORCE_DANGER and not any(d.twist), d
    op.mono += 0.02
    lifting = [-0.003 * a for a in n] + [0.0, 0.0, 0.0]
    d = sv.on_command(_signed(op, [0.0, 0.0, 0.0]), op.edge_wall, op.mono, TILTED, lifting)
    assert d.twist == pytest.approx(lifting, abs=1e-12), d


def test_contact_mode_replaces_the_motion_along_a_tilted_probe_and_keeps_the_sliding() -> None:
    """At the target force the operator's push along the tilted axis is replaced by nothing and the sliding is kept;
    at DANGER the sliding stops too and the probe backs off along its axis."""
    sv, op = armed(force_required=True)
    n, side = _axis_and_side(TILTED)
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.contact_ceiling = 6.0
    ok, why = sv.set_contact(op.request(sv, "op1", keys.CONTROL_CONTACT), True, 4.0)
    assert ok, why
    sv.update_contact_force(4.0, op.mono)  # at the target: the admittance moves nothing along the axis
    push = [0.003 * s + 0.004 * a for a, s in zip(n, side, strict=True)]
    d = sv.on_command(_signed(op, push), op.edge_wall, op.mono, TILTED)
    assert d.status == Status.CONTACT and d.twist[:3] == pytest.approx([0.003 * s for s in side], abs=1e-12), d
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono)  # red: the steering stops, the probe backs off
    op.mono += 0.02
    sv.update_contact_force(8.0, op.mono)  # far above the target: the admittance backs off at its top speed
    d = sv.on_command(_signed(op, push), op.edge_wall, op.mono, TILTED)
    back_off = [-sv.config.contact.max_speed * a for a in n] + [0.0, 0.0, 0.0]
    assert d.status == Status.FORCE_DANGER and d.twist == pytest.approx(back_off, abs=1e-12), d


def test_the_admittances_integral_grows_by_at_most_two_control_periods_per_step_and_never_backwards() -> None:
    """Target 4 N, reading 3.5 N: the output is gain·0.5 N plus the integral of integral_gain·0.5 N over time,
    where a long pause counts as two control periods and an event timed before the last one as none."""
    sv, op = armed(force_required=True)
    c = sv.config.contact
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.contact_ceiling = 6.0
    ok, why = sv.set_contact(op.request(sv, "op1", keys.CONTROL_CONTACT), True, 4.0)
    assert ok, why
    speeds = []
    for t in (100.0, 100.1, 100.096):  # the last one timed 4 ms before the one it follows
        op.mono = t
        sv.update_contact_force(3.5, t)
        speeds.append(-op.send(op.twist(vx=0.0)).twist[2])  # pressing is -z with the tool down
    step = c.integral_gain * 0.5 * 2 * sv.period
    assert speeds == pytest.approx([c.gain * 0.5, c.gain * 0.5 + step, c.gain * 0.5 + step], rel=1e-9), speeds


def test_a_command_naming_a_state_from_this_edges_future_is_judged_by_the_operators_age() -> None:
    """No state of this edge is stamped in its future: the operator's own estimate of the picture's age is used."""
    _sv, op = armed()
    d = op.send(_signed(op, [0.005, 0.0, 0.0], view_t=int((op.edge_wall + 0.5) * 1e9)))
    assert d.accepted and d.action == Action.MOVE, d


def test_clocks_that_differ_are_told_from_an_old_command_with_which_way_the_operators_clock_is_off() -> None:
    """The command names a robot state this edge stamped 20 ms ago: it is not old, the operator's clock is off."""
    _sv, op = armed()
    assert op.send(op.twist(deadman=False)).accepted
    reasons = []
    for skew in (-0.6, 0.6):
        op.mono += 0.02
        op.skew = skew
        reasons.append(op.send(_signed(op, [0.0, 0.0, 0.0], view_t=int((op.edge_wall - 0.02) * 1e9))).reason)
    assert reasons == ["the operator's clock is 600 ms behind this robot's: synchronise the clocks (NTP)",
                       "the operator's clock is 600 ms ahead of this robot's: synchronise the clocks (NTP)"]


def test_a_large_age_given_in_a_refusal_stays_through_five_percent_of_jitter() -> None:
    _sv, op = armed()
    assert op.send(op.twist(deadman=False)).accepted
    reasons = []
    for skew in (-20.0, -20.6, -21.6):  # 0.6 s is within 5 % of 20 s, 1.6 s is not
        op.mono += 0.02
        op.skew = skew
        reasons.append(op.send(op.twist(deadman=False)).reason)
    assert reasons == [f"command is {age} s old (max 500 ms)" for age in (20, 20, 22)], reasons


def test_the_intervention_log_keeps_the_newest_64_when_nobody_drains_it() -> None:
    sv, op = armed(force_required=True)
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.contact_ceiling = 6.0
    for _ in range(40):
        for on in (True, False):
            ok, why = sv.set_contact(op.request(sv, "op1", keys.CONTROL_CONTACT), on, 4.0 if on else None)
            assert ok, why
    assert len(sv.interventions) == 64
    assert sv.interventions[0][1].startswith("contact mode on") and sv.interventions[-1][1].startswith("contact mode off")


def test_a_deadman_held_without_motion_is_not_a_moving_robot() -> None:
    sv, op = armed()
    d = op.send(op.twist(vx=0.0))
    assert d.accepted and not any(d.twist) and not sv.moving


# ---------------------------------------------------------------- exact boundaries of leases, clocks and the deadband


def test_control_is_granted_with_clocks_exactly_max_command_age_apart_and_refused_beyond() -> None:
    from iorthand.protocol import ControlRequest

    sv = Supervisor(SafetyConfig(auto_arm=True, max_command_age=0.5), robot="sim1",
                    wall_clock=lambda: 1_700_000_100.0)
    far = ControlRequest(operator="op1").stamp(1, 1_700_000_100 * 10**9 - 625_000_000)  # 0.625 s behind
    grant = sv.acquire(far, 100.0)
    assert not grant.ok and grant.reason.startswith("clocks disagree: this robot's reads 2023-11-14 22:15 UTC")
    assert "(600 ms apart; a command may be 500 ms old)" in grant.reason, grant.reason
    near = ControlRequest(operator="op1").stamp(2, 1_700_000_100 * 10**9 - 500_000_000)  # exactly 0.5 s behind
    assert sv.acquire(near, 100.0).ok


def test_the_control_loop_releases_an_owner_when_both_its_lease_and_a_lease_since_its_last_command_ran_out() -> None:
    sv, _op = armed(lease=3.0)  # granted with its release command at 100.0
    sv.step(103.0, POSE)  # the last command exactly a lease old: not yet
    assert sv.owner == "op1"
    sv, op = armed(lease=3.0)
    ok, why = op.acquire(sv, "op1", 101.0)  # a renewal: the lease runs to 104.0
    assert ok and "renewed" in why, why
    sv.step(104.0, POSE)
    assert sv.owner == "" and sv.status == Status.OWNER_LOST and "lease of 'op1' expired" in sv.reason


def test_a_command_naming_a_state_exactly_max_view_age_old_is_diagnosed_as_a_clock_difference() -> None:
    _sv, op = armed(max_view_age=0.5)
    op.mono = 100.5
    assert op.send(op.twist(deadman=False)).accepted
    op.mono, op.skew = 101.0, -0.6  # this edge's wall clock reads 1_700_000_101.0 s
    d = op.send(_signed(op, [0.0, 0.0, 0.0], view_t=(int(WALL0) + 101) * 10**9 - 500_000_000, deadman=False))
    assert d.reason == "the operator's clock is 600 ms behind this robot's: synchronise the clocks (NTP)", d.reason


def test_contact_mode_moves_nothing_along_the_axis_for_an_error_of_exactly_the_deadband() -> None:
    sv, op = armed(force_required=True)
    sv.config.contact.deadband = 0.125
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.contact_ceiling = 6.0
    ok, why = sv.set_contact(op.request(sv, "op1", keys.CONTROL_CONTACT), True, 4.0)
    assert ok, why
    sv.update_contact_force(3.875, op.mono)
    assert op.send(op.twist(vx=0.0)).twist[2] == 0.0
    op.mono += 0.008
    sv.update_contact_force(3.75, op.mono)
    assert op.send(op.twist(vx=0.0)).twist[2] < 0  # 0.25 N short: it presses on (-z)


def test_when_the_retreat_from_danger_ends_with_the_deadman_released_the_status_says_what_holds_now() -> None:
    """Found by mutation testing: with the deadman released, the status went on saying "retracting from
    danger-level force" after the retreat had ended and the force was safe again, until the next event (seconds:
    here the lease). Now the retreat's end says what holds: the deadman released, or danger if it still is."""
    sv, op = armed(force_required=True, force=ForceReaction(retract_distance=0.002, retract_speed=0.005),
                   lease=10.0)
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono)
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono)
    assert sv.step(op.mono + 0.1, POSE).twist[2] > 0 and sv.reason == "retracting from danger-level force"
    sv.update_force(ForceLevel.SAFE, stale=False, now=op.mono + 0.2)
    d = sv.step(op.mono + 1.0, POSE)  # the 0.4 s retreat is over
    assert not any(d.twist) and (sv.status, sv.reason) == (Status.NO_DEADMAN, "deadman released")
    sv.update_force(ForceLevel.DANGER, stale=False, now=op.mono + 2.0)  # danger again, and it lasts
    sv.step(op.mono + 2.1, POSE)
    d = sv.step(op.mono + 3.0, POSE)
    assert not any(d.twist) and sv.status == Status.FORCE_DANGER and "retracting" not in sv.reason


def test_a_control_cycle_at_the_deadman_timeout_itself_stops_the_robot() -> None:
    """timeout_at() is when the control loop wakes to stop a held deadman that went silent: a cycle at that very
    instant stops it (it needed a later cycle: the loop wakes 0.1 ms after, so only the rule was wrong)."""
    sv, op = armed(command_timeout=0.125)
    op.send(op.twist(deadman=False))
    op.mono += 0.05
    d = op.send(op.twist())
    assert d.accepted and any(d.twist)
    d = sv.step(sv.timeout_at(), POSE)
    assert not any(d.twist) and sv.status == Status.COMMAND_TIMEOUT and not sv.deadman
