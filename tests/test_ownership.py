"""Ownership bound to the session that acquired it, and motion that resumes only on purpose. Pure safety core:
explicit times, no Zenoh, milliseconds per test (the attacks through real routers: test_forged_owner.py)."""

from __future__ import annotations

import numpy as np

from iorthand import keys
from iorthand.protocol import ServoCommand, Status, TwistCommand
from iorthand.security import auth
from iorthand_edge.supervisor import Action, SafetyConfig, Supervisor
from tests.grants import Grants

POSE = np.array([0.30, 0.0, 0.20, 3.14159, 0.0, 0.0])
WALL0 = 1_700_000_000.0


class Operator(Grants):
    """One operator's session against one supervisor, with the time of the test."""

    def __init__(self, sv: Supervisor, name: str, clock: list[float]) -> None:
        super().__init__()
        self.sv, self.name, self.clock, self.seq = sv, name, clock, 0

    def take(self) -> tuple[bool, str]:
        return self.acquire(self.sv, self.name, self.clock[0])

    def twist(self, vx: float = 0.005, deadman: bool = True, view_age: float = 0.02, seq: int | None = None,
              name: str | None = None, skew: float = 0.0, view_t: int = 0) -> TwistCommand:
        """A command of this operator's session; ``skew``: how far (s) its clock is ahead of the edge's (it stamps
        the command, and its view's age is its clock minus the state's stamp); ``view_t``: the state it names."""
        self.seq += 1
        cmd = TwistCommand(operator=name or self.name, linear=[vx, 0.0, 0.0], deadman=deadman, state_age=view_age,
                           view_t=view_t)
        cmd.stamp(self.seq if seq is None else seq, int((WALL0 + self.clock[0] + skew) * 1e9))
        return self.sign(self.sv, self.name, cmd)

    def send(self, cmd: TwistCommand):
        return self.sv.on_command(cmd, WALL0 + self.clock[0], self.clock[0], POSE)


def setup(**cfg: object) -> tuple[Supervisor, Operator, Operator, list[float]]:
    sv = Supervisor(SafetyConfig(auto_arm=True, **cfg), robot="sim1")
    clock = [100.0]
    alice, mallory = Operator(sv, "alice", clock), Operator(sv, "mallory", clock)
    assert alice.take()[0]
    return sv, alice, mallory, clock


def test_a_command_in_the_owners_name_without_its_key_is_refused_unanswered() -> None:
    sv, alice, mallory, _clock = setup()
    assert alice.send(alice.twist()).accepted
    # Mallory writes alice's name, a huge sequence, and signs with nothing, or with a key of her own.
    for forged in (mallory.twist(name="alice", seq=2**62),
                   auth.sign(b"k" * 32, auth.context("sim1", keys.CMD_TWIST), mallory.twist(name="alice", seq=2**62 + 1))):
        d = mallory.send(forged)
        assert not d.accepted and d.status == Status.NOT_OWNER and not d.answer
    assert sv.counters.forged == 2 and sv.owner == "alice"
    # Alice's own next command still goes: the forgeries moved her sequence nowhere.
    assert alice.send(alice.twist()).accepted


def test_a_replayed_command_is_refused() -> None:
    _sv, alice, _, _ = setup()
    cmd = alice.twist()
    assert alice.send(cmd).accepted
    d = alice.send(cmd)
    assert not d.accepted and d.status == Status.OUT_OF_ORDER


def test_an_absurd_sequence_jump_is_refused_even_when_signed() -> None:
    _sv, alice, _, _ = setup(max_sequence_jump=100)
    assert alice.send(alice.twist()).accepted
    d = alice.send(alice.twist(seq=5000))
    assert not d.accepted and d.status == Status.OUT_OF_ORDER and "jumps" in d.reason


def test_another_session_cannot_renew_or_release_the_owners_grant() -> None:
    sv, alice, mallory, _ = setup()
    ok, reason = mallory.acquire(sv, "alice", 100.5)  # alice's name, mallory's session: no key
    assert not ok and "does not hold its key" in reason
    ok, reason = sv.release(mallory.request(sv, "alice", keys.CONTROL_RELEASE))
    assert not ok and sv.owner == "alice"
    servo = ServoCommand(operator="alice", pan=0.3).stamp(1)
    assert "not signed" in sv.owner_refusal(servo, keys.CMD_SERVO)
    signed = alice.sign(sv, "alice", ServoCommand(operator="alice", pan=0.3).stamp(1), keys.CMD_SERVO)
    assert sv.owner_refusal(signed, keys.CMD_SERVO) == ""
    assert "not after" in sv.owner_refusal(signed, keys.CMD_SERVO)  # the same message again: a replay
    # Alice renews (signed) and keeps her key; releasing (signed) ends the grant and the key with it.
    key = alice.keys["alice"]
    assert alice.take()[0] and alice.keys["alice"] == key
    ok, _ = sv.release(alice.request(sv, "alice", keys.CONTROL_RELEASE))
    assert ok and sv.owner == ""
    d = alice.send(alice.twist())
    assert not d.accepted and d.status == Status.NOT_OWNER


def test_every_grant_has_a_new_key_and_a_new_sequence() -> None:
    sv, alice, _, _clock = setup()
    for _ in range(5):
        assert alice.send(alice.twist()).accepted
    old = alice.twist()  # signed with the first grant's key, never sent
    assert sv.owner_lost("alice", "liveliness lost")
    assert alice.take()[0]  # a new grant
    assert not alice.send(old).accepted  # the old key is worthless now
    assert alice.seq == 1  # the client restarted its sequence with the new key: its release came first
    assert alice.send(alice.twist()).accepted


def test_a_long_gap_with_the_deadman_held_needs_a_fresh_press_and_a_short_one_does_not() -> None:
    sv, alice, _, clock = setup()
    assert alice.send(alice.twist()).accepted
    clock[0] += 0.2  # a 0.2 s gap: the deadman timed out, then motion resumes by itself
    assert not np.any(sv.step(clock[0] - 0.01, POSE).twist) and sv.status == Status.COMMAND_TIMEOUT
    d = alice.send(alice.twist())
    assert d.accepted and np.any(d.twist)
    clock[0] += 1.0  # a 1 s blackout with the deadman held all along
    sv.step(clock[0] - 0.5, POSE)
    for _ in range(3):
        d = alice.send(alice.twist())
        assert not d.accepted and not np.any(d.twist) and d.status == Status.LINK_GAP and "press it again" in d.reason
        assert not np.any(sv.step(clock[0], POSE).twist)
        clock[0] += 1 / 60
    assert alice.send(alice.twist(deadman=False)).accepted
    d = alice.send(alice.twist())
    assert d.accepted and np.any(d.twist)


def test_the_safety_status_names_the_latch_that_holds_the_robot_after_a_stale_view_clears() -> None:
    """Found by the WAN bench's blackout trials: the first commands after a blackout carry an old picture of the
    robot (stale_view, a halt that clears with a fresh picture) and resume after a long gap (link_gap, latched).
    Once the picture was fresh again, the latched refusals kept the published status at stale_view: a console
    (recovery.next_step) saw nothing to do, and no press came. The status names the latch that holds the robot."""
    sv, alice, _, clock = setup()
    assert alice.send(alice.twist()).accepted
    clock[0] += 1.5  # a blackout with the deadman held; the first command back shows a 1 s old picture
    sv.step(clock[0] - 0.5, POSE)
    d = alice.send(alice.twist(view_age=1.0))
    assert not d.accepted and sv.status == Status.STALE_VIEW
    for _ in range(3):  # the picture is live again: the gap's latch is what holds the robot now
        clock[0] += 1 / 60
        d = alice.send(alice.twist())
        assert not d.accepted and d.status == Status.LINK_GAP
        assert sv.status == Status.LINK_GAP and "press it again" in sv.reason
    assert alice.send(alice.twist(deadman=False)).accepted
    assert alice.send(alice.twist()).accepted


def test_a_fresh_press_after_a_long_release_moves_at_once() -> None:
    _sv, alice, _, clock = setup()
    assert alice.send(alice.twist(deadman=False)).accepted
    clock[0] += 5.0
    assert alice.send(alice.twist()).accepted


def test_motion_from_an_old_picture_is_refused_and_stops_the_robot() -> None:
    _sv, alice, _, _clock = setup(max_view_age=0.5)
    d = alice.send(alice.twist(view_age=0.1))
    assert d.accepted and d.action == Action.MOVE
    d = alice.send(alice.twist(view_age=0.8))
    assert not d.accepted and d.status == Status.STALE_VIEW and "800 ms" in d.reason and d.action == Action.STOP
    d = alice.send(alice.twist(view_age=-1.0))
    assert not d.accepted and "no robot state" in d.reason and d.action == Action.HOLD
    d = alice.send(alice.twist(view_age=0.05))  # the picture is live again (no gap: commands kept coming)
    assert d.accepted and d.action == Action.MOVE


def test_an_operator_clock_behind_the_robots_cannot_make_an_old_picture_look_fresh() -> None:
    """The operator's clock is 0.4 s behind the edge's and its screen froze on a state 0.8 s old: it computes an
    age of 0.4 s. The command names that state (its stamp on the edge's clock), and the edge measures 0.8 s.
    (The sequence goes on: a stale picture halts, it does not latch.)"""
    _sv, alice, _, clock = setup(max_view_age=0.5)
    now_ns = int((WALL0 + clock[0]) * 1e9)
    d = alice.send(alice.twist(view_age=0.1, view_t=now_ns - 100_000_000))
    assert d.accepted and d.action == Action.MOVE
    d = alice.send(alice.twist(view_age=0.4, view_t=now_ns - 800_000_000, skew=-0.4))
    assert not d.accepted and d.status == Status.STALE_VIEW and "800 ms" in d.reason and d.action == Action.STOP
    # Nor can a clock 0.3 s ahead make a fresh picture (0.25 s here) look old (0.55 s by the operator's clock).
    d = alice.send(alice.twist(view_age=0.55, view_t=now_ns - 250_000_000, skew=0.3))
    assert d.accepted and d.action == Action.MOVE, d
    # A state stamped later than the command arrived is none of this edge's: what the operator says stands.
    d = alice.send(alice.twist(view_age=0.8, view_t=now_ns + 10**12))
    assert not d.accepted and d.status == Status.STALE_VIEW and "800 ms" in d.reason


def test_a_command_refused_for_its_time_says_when_the_clocks_differ() -> None:
    """An operator whose clock is 2 s off gets every command refused (the edge cannot tell a late command from a
    wrong clock by the command's time alone), but the state it names was stamped a moment ago on the edge's
    clock: the refusal says which clock is off, not that the command is old."""
    _sv, alice, _, clock = setup()
    now_ns = int((WALL0 + clock[0]) * 1e9)
    for skew, side in ((-2.0, "behind"), (2.0, "ahead of")):
        d = alice.send(alice.twist(view_t=now_ns - 30_000_000, skew=skew))
        assert not d.accepted and d.status == Status.STALE_COMMAND, d
        assert f"clock is 2000 ms {side} this robot's" in d.reason and "NTP" in d.reason, d.reason
    # Without a fresh state to go by, an old command is just old.
    d = alice.send(alice.twist(view_t=now_ns - 3_000_000_000, skew=-2.0))
    assert not d.accepted and d.reason.startswith("command is 2000 ms old"), d.reason
    d = alice.send(alice.twist(skew=-2.0))
    assert not d.accepted and d.reason.startswith("command is 2000 ms old"), d.reason


def test_the_driver_is_told_to_stop_once_after_motion_then_nothing() -> None:
    sv, alice, _, clock = setup()
    assert alice.send(alice.twist()).action == Action.MOVE
    sv.stop("e-stop from bob")
    assert sv.step(clock[0], POSE).action == Action.STOP
    assert sv.step(clock[0] + 0.01, POSE).action == Action.HOLD


def test_a_stop_from_anyone_stops_the_owners_motion() -> None:
    sv, alice, _, _clock = setup()
    assert alice.send(alice.twist()).accepted
    sv.stop("stop from 'mallory': e-stop")
    d = alice.send(alice.twist())
    assert not d.accepted and d.status == Status.STOPPED
    assert sv.owner == "alice"  # a stop is obeyed but takes nobody's control


def test_every_status_has_a_message() -> None:
    for status in Status:
        assert status.message and status == status.value


def test_the_operators_stream_is_signed_as_the_edge_decodes_it() -> None:
    """The operator's send loop signs its commands without a validation round trip: what it builds must be what
    the edge decodes (ints given as velocities included), or every command would read as a forgery."""
    import time

    from iorthand.protocol import ControlRequest
    from iorthand_operator.sender import CommandStream

    sv = Supervisor(SafetyConfig(auto_arm=True), robot="sim1")
    grant = sv.acquire(ControlRequest(operator="alice").stamp(1), 100.0)
    stream = CommandStream("sim1", "alice", release_tail=0.3, ui_timeout=0.5)
    for i in range(4):  # the grant's first command is a release (sent by the stream itself), then the press
        now, state_t = time.monotonic(), time.time_ns() - 20_000_000
        out = stream.next(now, [0, 0.004, 0, 0, 0, 0], True, 0.0, False, now, state_t, 1.0, grant.key,
                          pressed_at=now, press_from=now - 0.01)
        assert out is not None
        cmd, payload = out
        assert cmd.seq == i + 1 and cmd.deadman == (i > 0)
        assert cmd.view_t == state_t and 0.02 <= cmd.state_age < 0.5  # the state it names, and its age here
        d = sv.on_command(TwistCommand.decode(payload), time.time(), 100.0 + i / 60, POSE)
        assert d.accepted and (d.twist[1] > 0) == (i > 0), d
    # A new grant (a new key) restarts the sequence at 1, as the edge expects.
    sv.owner_lost("alice", "test")
    regrant = sv.acquire(ControlRequest(operator="alice").stamp(1), 101.0)
    now = time.monotonic()
    out = stream.next(now, [0.0] * 6, False, now, False, now, time.time_ns(), 2.0, regrant.key)
    assert out is not None and out[0].seq == 1
    assert sv.on_command(TwistCommand.decode(out[1]), time.time(), 101.0, POSE).accepted


def test_a_new_grant_moves_nothing_before_a_release_and_a_press_under_it() -> None:
    """A client that re-acquired by itself (its edge restarted, its lease was lost) while the operator kept the
    deadman held: the edge refuses motion until it sees a release under the new grant, and the client keeps the
    old press released until the operator presses again."""
    import time

    from iorthand.protocol import ControlRequest
    from iorthand_operator.sender import CommandStream

    sv = Supervisor(SafetyConfig(auto_arm=True), robot="sim1")
    grant = sv.acquire(ControlRequest(operator="alice").stamp(1), 100.0)
    raw = TwistCommand(operator="alice", linear=[0.004, 0.0, 0.0], deadman=True, state_age=0.01).stamp(1)
    d = sv.on_command(auth.sign(grant.key, auth.context("sim1", keys.CMD_TWIST), raw), time.time(), 100.0, POSE)
    assert not d.accepted and d.status == Status.NO_DEADMAN and "release the deadman" in d.reason
    # The client side: the press began before the key arrived.
    stream = CommandStream("sim1", "alice", release_tail=0.3, ui_timeout=0.5)
    pressed, press_from = time.monotonic() - 2.0, time.monotonic() - 1.0
    sent = []
    for _ in range(30):
        now = time.monotonic()
        out = stream.next(now, [0.004, 0, 0, 0, 0, 0], True, 0.0, False, now, time.time_ns(), 1.0, grant.key,
                          pressed_at=pressed, press_from=press_from)
        if out is not None:
            sent.append(out[0])
    assert sent and not any(c.deadman for c in sent)  # held from before: released, then quiet
    now = time.monotonic()  # the operator releases and presses again
    out = stream.next(now, [0.004, 0, 0, 0, 0, 0], True, now - 0.05, False, now, time.time_ns(), 1.0, grant.key,
                      pressed_at=now, press_from=press_from)
    assert out is not None and out[0].deadman


def test_a_resumed_stream_goes_on_with_the_grants_sequence_that_the_edge_still_accepts() -> None:
    """A sender process that died is replaced by one whose stream resumes after the last command sent: no release
    first (the grant's went out), a sequence the edge accepts (one that started again at 1 would read as a replay),
    and a press held from before the restart still moves nothing."""
    import time

    from iorthand.protocol import ControlRequest
    from iorthand_operator.sender import CommandStream

    sv = Supervisor(SafetyConfig(auto_arm=True), robot="sim1")
    grant = sv.acquire(ControlRequest(operator="alice").stamp(1), 100.0)
    first = CommandStream("sim1", "alice", release_tail=0.3, ui_timeout=0.5)
    pressed = time.monotonic()
    for i in range(5):
        now = time.monotonic()
        cmd, payload = first.next(now, [0.004, 0, 0, 0, 0, 0], True, 0.0, False, now, time.time_ns(), 1.0, grant.key,
                                  pressed_at=pressed, press_from=pressed - 0.01)
        assert sv.on_command(TwistCommand.decode(payload), time.time(), 100.0 + i / 60, POSE).accepted
    restarted = time.monotonic()
    second = CommandStream("sim1", "alice", release_tail=0.3, ui_timeout=0.5)
    second.resume(first.key_gen, first.seq)
    now = time.monotonic()
    cmd, payload = second.next(now, [0.004, 0, 0, 0, 0, 0], True, 0.0, False, now, time.time_ns(), 1.0, grant.key,
                               pressed_at=pressed, press_from=restarted)
    assert cmd.seq == 6 and not cmd.deadman  # the press from before the restart: released
    assert sv.on_command(TwistCommand.decode(payload), time.time(), 100.2, POSE).accepted
    now = time.monotonic()  # a fresh press moves
    cmd, payload = second.next(now, [0.004, 0, 0, 0, 0, 0], True, now - 0.05, False, now, time.time_ns(), 1.0,
                               grant.key, pressed_at=now, press_from=restarted)
    d = sv.on_command(TwistCommand.decode(payload), time.time(), 100.22, POSE)
    assert cmd.seq == 7 and cmd.deadman and d.accepted and d.twist[0] > 0, d
    # Without resume, the replacement's sequence starts again at 1 under the same grant: refused as a replay.
    third = CommandStream("sim1", "alice", release_tail=0.3, ui_timeout=0.5)
    now = time.monotonic()
    cmd, payload = third.next(now, [0.0] * 6, False, now, False, now, time.time_ns(), 1.0, grant.key)
    assert cmd.seq == 1 and not sv.on_command(TwistCommand.decode(payload), time.time(), 100.24, POSE).accepted


def test_a_request_anyone_may_make_is_refused_in_the_owners_name_without_its_signature() -> None:
    """The plain plan/preview is open to every granted operator (the twin asks it for them), so a name there is a
    claim: previews claiming the owner's name would each get a token kept as the owner's, and push its own token
    out. They must carry the owner's signature."""
    sv, alice, mallory, _ = setup()
    claimed = mallory.request(sv, "alice", keys.PLAN_PREVIEW, name="home")  # mallory's session holds no key
    assert "not signed by the session that holds control for 'alice'" in sv.impersonation(claimed, keys.PLAN_PREVIEW)
    assert sv.impersonation(alice.request(sv, "alice", keys.PLAN_PREVIEW, name="home"), keys.PLAN_PREVIEW) == ""
    assert sv.impersonation(mallory.request(sv, "mallory", keys.PLAN_PREVIEW, name="home"), keys.PLAN_PREVIEW) == ""
