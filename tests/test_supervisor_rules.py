"""Rules of the safety core that its other tests left unpinned: each was found by mutation testing of
supervisor.py (a mutant of the rule passed every test), and each test states the rule as an operator or an
integrator would. Pure logic: explicit times, no Zenoh, milliseconds per test."""

from __future__ import annotations

import math

import pytest

from iorthand import keys
from iorthand.protocol import ForceLevel, Status, TwistCommand
from iorthand_edge.supervisor import Action, ForceReaction, SafetyConfig, Supervisor
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
