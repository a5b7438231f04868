"""The forged-owner attack through real routers: a second session writes the owner's name into its commands, with a
huge sequence, and replays the owner's own commands. On an open router, and behind mTLS + ACL from the holder of
another operator certificate granted the same robot (``bind_operator_keys`` off, the weaker deployment): nothing
it sends is applied, the robot does not move, and the owner keeps control throughout.

Then link gaps with the deadman held: a 1 s blackout does not resume motion without a fresh press; a 0.2 s gap
does. The blackout is the operator's sender going silent (``muted``) while everything else keeps running.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import zenoh

from iorthand import keys
from iorthand.protocol import (
    AppliedCommand,
    ControlReply,
    ControlRequest,
    ForceLevelState,
    RobotState,
    SafetyStatus,
    Status,
    StopCommand,
    TwistCommand,
)
from iorthand.security.lab import make_lab
from iorthand.transport import ZenohConfig, free_port, open_session
from iorthand_operator.client import ControlRefused, OperatorClient
from tests.conftest import drive_slowly, edge_config, wait_until

FORGED_SEQ = 2**62


def _attack(session: zenoh.Session, robot: str, owner: str, captured: list[bytes], n: int = 180) -> dict[str, int]:
    """``n`` forged twists in ``owner``'s name at 60 Hz (huge sequence, fast motion), every captured command of
    the owner replayed, then an acquire and a release in its name. Returns what the router let through to us."""
    k = keys.RobotKeys(robot)
    pub = session.declare_publisher(k.key(keys.CMD_TWIST))
    for i in range(n):
        cmd = TwistCommand(operator=owner, linear=[0.03, 0.0, 0.0], deadman=True, state_age=0.01)
        pub.put(cmd.stamp(FORGED_SEQ + i).encode())
        if i % 3 == 0 and captured:
            pub.put(captured[-1])  # the owner's own latest command, byte for byte
        time.sleep(1 / 60)
    answers = {}
    for verb in (keys.CONTROL_ACQUIRE, keys.CONTROL_RELEASE):
        req = ControlRequest(operator=owner).stamp(FORGED_SEQ).encode()
        replies = [r.ok.payload.to_bytes() for r in session.get(k.key(verb), payload=req, timeout=2.0) if r.ok]
        answers[verb] = len(replies)
        for raw in replies:
            reply = ControlReply.decode(raw)
            assert not reply.ok and not reply.key, f"{verb} in {owner!r}'s name was granted: {reply.reason}"
    pub.undeclare()
    return answers


def _owner_holds_still(alice: OperatorClient) -> None:
    alice.wait_for_state()
    alice.acquire()
    alice.start()
    alice.set_twist([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)  # the deadman held, standing still
    wait_until(lambda: any(e.accepted for e in list(alice.echoes)[-5:]), 5.0, message="the owner's commands applied")


def _check_nothing_forged_applied(agent, alice: OperatorClient, echoes: list[AppliedCommand], x0: np.ndarray) -> None:
    sv = agent.supervisor
    assert sv.owner == "alice"
    assert sv.counters.forged >= 150, sv.counters  # the forgeries reached the edge and were counted
    assert not [e for e in echoes if e.cmd_seq >= FORGED_SEQ], "a forged command was answered"
    assert not [e for e in echoes if e.accepted and e.cmd_seq >= FORGED_SEQ]
    moved = np.linalg.norm(np.asarray(agent.reading.tcp_pose[:3]) - x0)
    assert moved < 1e-4, f"the robot moved {1000 * moved:.2f} mm"
    # The owner kept control and its stream kept being applied to the end.
    wait_until(lambda: alice.echoes and alice.echoes[-1].accepted, 3.0, message="the owner's latest command applied")
    assert not [e for e in list(alice.echoes) if not e.accepted and e.status == Status.NOT_OWNER]


def _forge_while_alice_holds(agent, alice: OperatorClient, attacker: zenoh.Session,
                             wiretap: zenoh.Session | None = None) -> None:
    """Alice holds control and the deadman, standing still; the attacker watches every answer on the robot and
    has her commands (on an open router it reads them itself; behind the ACL, which refuses an operator the
    commands, through ``wiretap``: a leaked recording, say), then forges and replays in her name. Nothing of it
    may act."""
    _owner_holds_still(alice)
    x0 = np.asarray(agent.reading.tcp_pose[:3])
    echoes: list[AppliedCommand] = []
    captured: list[bytes] = []
    k = keys.RobotKeys("sim1")
    tap = wiretap or attacker
    subs = [
        attacker.declare_subscriber(k.key(keys.STATE_APPLIED), lambda s: echoes.append(AppliedCommand.decode(s.payload.to_bytes()))),
        tap.declare_subscriber(k.key(keys.CMD_TWIST) + "/**", lambda s: captured.append(s.payload.to_bytes())),
        tap.declare_subscriber(k.key(keys.CMD_TWIST), lambda s: captured.append(s.payload.to_bytes())),
    ]
    wait_until(lambda: captured, 3.0, message="the attacker seeing the owner's commands")
    _attack(attacker, "sim1", "alice", captured)
    _check_nothing_forged_applied(agent, alice, echoes, x0)
    for sub in subs:
        sub.undeclare()


@pytest.mark.slow
def test_forged_owner_on_an_open_router(edge_factory, operator_factory, session_factory) -> None:
    _forge_while_alice_holds(edge_factory(), operator_factory(operator_id="alice"), session_factory())


def test_a_session_answering_control_queries_in_the_edges_name_is_exposed(edge_factory, operator_factory,
                                                                        session_factory) -> None:
    """Found by a red-team run, on an open router: another session acquires in alice's name (a name is only a
    claim there), then answers alice's own acquire with a forged grant carrying its key, so that both sign with
    it and it drives the robot while alice believes she does. The edge refuses alice's acquire, so two sessions
    answer: her client believes neither."""
    edge_factory()
    alice = operator_factory(operator_id="alice")
    alice.wait_for_state()
    mallory = session_factory()
    k = keys.RobotKeys("sim1")
    raw = [r.ok.payload.to_bytes() for r in mallory.get(k.key(keys.CONTROL_ACQUIRE), timeout=5.0,
                                                        payload=ControlRequest(operator="alice").stamp(1).encode())
           if r.ok is not None]
    grant = ControlReply.decode(raw[0])
    assert grant.ok and grant.key  # open router: the name is all there is to go by

    def forge(query: zenoh.Query) -> None:
        fake = ControlReply(ok=True, reason="control granted to 'alice'", owner="alice", lease=3.0, key=grant.key)
        query.reply(query.key_expr, fake.stamp(0).encode())
        query.drop()

    impostor = mallory.declare_queryable(k.key(keys.CONTROL_ACQUIRE), forge)
    time.sleep(0.3)
    with pytest.raises(ControlRefused, match=r"2 sessions answered control/acquire .* another session is answering"):
        alice.acquire()
    assert alice._key != grant.key  # she signs nothing with the impostor's key
    impostor.undeclare()


def test_the_owner_keeps_control_while_another_session_answers_or_holds_its_lease_renewals(
        edge_factory, operator_factory, session_factory) -> None:
    """Found by a red-team run of the operator side, on an open router: while alice held control, a session that
    answered her renewals with a forged grant (two answers: none believed) or held them open without answering
    (the query timed out) made her client give control up after one renewal, although the edge still held her
    as its owner; the robot stopped. Now the edge signs its answer for her grant, with her request's sequence,
    and her client takes it as soon as it arrives: she keeps control, her key unchanged."""
    agent = edge_factory(safety={"lease": 1.0})  # a renewal every ~0.33 s
    alice = operator_factory(operator_id="alice")
    alice.wait_for_state()
    alice.acquire()
    alice.start()
    key = alice._key
    mallory = session_factory()
    k = keys.RobotKeys("sim1")
    held: list[zenoh.Query] = []

    def forge(query: zenoh.Query) -> None:
        fake = ControlReply(ok=True, reason="control granted to 'alice'", owner="alice", lease=1.0, key=b"m" * 32)
        query.reply(query.key_expr, fake.stamp(0).encode())
        query.drop()

    impostors = [mallory.declare_queryable(k.key(keys.CONTROL_ACQUIRE), forge),
                 mallory.declare_queryable(k.key(keys.CONTROL_ACQUIRE), held.append)]  # never answers
    try:
        time.sleep(0.3)
        started = time.monotonic()
        reply = alice.acquire()
        took = time.monotonic() - started
        assert reply.ok and not reply.key, reply.reason
        assert took < alice.query_timeout / 2, f"the renewal waited {took:.2f} s for the query held open"
        time.sleep(2.5)  # 2.5 leases of renewals through both impostors
        assert held, "the silent impostor saw no query"
        assert alice.owner and alice._key == key
        assert agent.supervisor.owner == "alice"
        assert not [e for e in list(alice.events) if "lost control" in e.reason or "renewal failed" in e.reason]
    finally:
        for q in impostors:
            q.undeclare()
        held.clear()


def test_a_failing_renewal_is_tried_again_until_the_lease_runs_out(edge_factory, operator_factory) -> None:
    """A renewal that fails (a busy edge, a stalled link) costs control only once the edge's lease can have run
    out: before, the first failure cleared the client's key while the edge still held it as owner (a red-team
    flood of acquire queries did that while the owner drove). The failure is the client's own acquire raising for
    a while (the cause does not matter to this rule)."""
    agent = edge_factory(safety={"lease": 1.5})  # a renewal every 0.5 s
    alice = operator_factory(operator_id="alice")
    alice.wait_for_state()
    alice.acquire()
    alice.start()
    key = alice._key
    real_acquire = alice.acquire
    failing_until = [0.0]

    def flaky_acquire(profile: str = "") -> ControlReply:
        if time.monotonic() < failing_until[0]:
            raise ControlRefused("edge busy: 256 requests are waiting before this acquire; try again")
        return real_acquire(profile)

    alice.acquire = flaky_acquire  # type: ignore[method-assign]
    failing_until[0] = time.monotonic() + 0.9  # under the lease
    time.sleep(1.6)
    assert alice.owner and alice._key == key, [e.reason for e in alice.events]
    reasons = [e.reason for e in alice.events]
    assert any("renewal failed" in r for r in reasons) and any("renewed again" in r for r in reasons), reasons
    # While she drives, her commands renew the edge's lease, and their signed echoes say so: failing renewals
    # for twice the lease cost nothing.
    alice.set_twist([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)
    wait_until(lambda: any(e.accepted for e in list(alice.echoes)[-5:]), 3.0, message="her commands applied")
    failing_until[0] = time.monotonic() + 10.0
    time.sleep(3.0)
    assert alice.owner and alice._key == key and agent.supervisor.owner == "alice"
    assert alice.echoes[-1].accepted
    # Once she stops sending, nothing renews the lease: control is given up when it has run out.
    alice.set_twist([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=False)
    wait_until(lambda: not alice.owner, 4.0, message="control given up once the lease has run out")
    assert alice._key == b""
    assert any("lost control" in e.reason for e in alice.events)


@pytest.fixture(scope="module")
def shared_robot_lab(tmp_path_factory: pytest.TempPathFactory):
    """mTLS + passwords + ACL as DEPLOY.md generates it, two operators granted the same robot, and operator keys
    NOT bound to certificates (the weaker deployment the attack was first shown on)."""
    lab = make_lab(tmp_path_factory.mktemp("pki"), free_port(), robots=["sim1"],
                   operators={"alice": ["sim1"], "mallory": ["sim1"]}, bind_operator_keys=False)
    router = zenoh.open(zenoh.Config.from_file(str(lab.router_config)))
    yield lab
    router.close()


def _edge_zenoh(lab, name: str) -> dict:
    c: ZenohConfig = lab.client(name, retry_s=10.0)
    assert c.tls is not None
    return {"mode": "client", "connect": [lab.endpoint], "connect_retry_s": 10.0,
            "tls": {"root_ca": str(c.tls.root_ca), "certificate": str(c.tls.certificate),
                    "private_key": str(c.tls.private_key)},
            "username": c.username, "password_file": str(c.password_file)}


@pytest.mark.slow
def test_the_owner_believes_only_the_robot_state_and_echoes_the_edge_signed(edge_factory, operator_factory,
                                                                           session_factory) -> None:
    """Found by a red-team run of the operator side: a third session published robot states stamped "now" (a
    fake pose), command echoes in the owner's name, safety states and green force levels. The owner's client took them: its commands told the edge
    that its screen was live while the real state came 1 s late (the robot moved 18 mm past the stale-view
    check), and 60 forged echoes a command showed a 200 ms link as 2.5 ms. While someone holds control the edge
    signs its robot state and echoes with the owner's key; the owner's client ignores what does not verify."""
    agent = edge_factory()
    alice = operator_factory(operator_id="alice")
    drive_slowly(agent, alice)
    k = keys.RobotKeys("sim1")
    mallory = session_factory()
    state_pub, echo_pub = mallory.declare_publisher(k.key(keys.STATE_ROBOT)), mallory.declare_publisher(k.key(keys.STATE_APPLIED))
    safety_pub = mallory.declare_publisher(k.key(keys.STATE_SAFETY))
    level_pub = mallory.declare_publisher(k.key(keys.STATE_FORCE_LEVEL))
    fake = [0.5, 0.5, 0.5, 0.0, 0.0, 0.0]
    poses: list[list[float]] = []
    shown: list[tuple[str, str]] = []
    echoes0, sent0 = alice.echo_count, alice.sent_count
    for i in range(200):
        now = time.time_ns()
        state_pub.put(RobotState(tcp_pose=fake).stamp(10**6 + i, now).encode())
        for seq in range(max(1, alice.sent_count - 5), alice.sent_count + 5):  # echoes for the latest commands
            echo_pub.put(AppliedCommand(operator="alice", cmd_seq=seq, cmd_t=now, recv_t=now, accepted=True)
                         .stamp(10**6 + i, now).encode())
        safety_pub.put(SafetyStatus(owner="alice", armed=True, status="stopped", reason="forged")
                       .stamp(10**6 + i, now).encode())
        level_pub.put(ForceLevelState(level=0, stale=False, quantity="forged").stamp(10**6 + i, now).encode())
        time.sleep(0.005)
        if alice.robot_state is not None:
            poses.append(list(alice.robot_state.tcp_pose))
        shown.append((alice.safety.reason if alice.safety else "",
                      alice.force_level.quantity if alice.force_level else ""))
    assert poses and fake not in poses, "a forged robot state was taken for the edge's"
    assert not [x for x in shown if "forged" in x], "a forged safety state or force level was shown"
    assert alice.rejects.counts.get(k.key(keys.STATE_ROBOT), 0) >= 150
    assert alice.rejects.counts.get(k.key(keys.STATE_APPLIED), 0) >= 1000
    assert alice.echo_count - echoes0 <= alice.sent_count - sent0  # one echo a command at most
    assert agent.supervisor.owner == "alice" and alice.robot_state.seq < 10**6  # the edge's own states, live


def test_forged_owner_from_a_second_granted_certificate(shared_robot_lab) -> None:
    from iorthand_edge.agent import EdgeAgent

    lab = shared_robot_lab
    agent = EdgeAgent(edge_config(lab.endpoint, "sim1", zenoh=_edge_zenoh(lab, "edge-sim1")))
    agent.start()
    sessions = []
    try:
        a_session = open_session(lab.client("operator-alice"))
        m_session = open_session(lab.client("operator-mallory"))
        wiretap = open_session(lab.client("recorder"))
        sessions += [a_session, m_session, wiretap]
        alice = OperatorClient(a_session, "sim1", "alice")
        _forge_while_alice_holds(agent, alice, m_session, wiretap)
        # Mallory, as herself, is refused with the owner's name; her stop is obeyed and logged as hers.
        mallory = OperatorClient(m_session, "sim1", "mallory")
        with pytest.raises(ControlRefused, match="alice"):
            mallory.acquire()
        m_session.declare_publisher(keys.RobotKeys("sim1").key(keys.CMD_STOP)).put(
            StopCommand(operator="mallory", reason="e-stop").stamp(1).encode())
        wait_until(lambda: agent.supervisor.status == Status.STOPPED and "mallory" in agent.supervisor.reason, 3.0,
                   message="the second operator's stop obeyed")
        assert agent.supervisor.owner == "alice"
        alice.close()
        mallory.close()
    finally:
        agent.shutdown()
        for s in sessions:
            s.close()


def _moving(alice: OperatorClient) -> bool:
    return bool(alice.echoes) and alice.echoes[-1].accepted and alice.echoes[-1].status != Status.NO_DEADMAN


@pytest.mark.slow
@pytest.mark.parametrize(("gap", "resumes"), [(0.2, True), (1.0, False)])
def test_a_link_gap_with_the_deadman_held(edge_factory, operator_factory, gap: float, resumes: bool) -> None:
    agent = edge_factory()
    alice = operator_factory(operator_id="alice")
    drive_slowly(agent, alice)
    alice.muted = True  # the link goes dead; the operator keeps holding the deadman
    time.sleep(gap)
    n = alice.echo_count
    alice.muted = False
    wait_until(lambda: alice.echo_count > n + 20, 5.0, message="commands flowing again")
    after = alice.echoes_since(n + 10)
    if resumes:
        assert all(e.accepted for e in after), {e.status for e in after}
        assert np.any(agent._commanded), "the robot moving again"
    else:
        assert not any(e.accepted for e in after), "motion resumed by itself after a blackout"
        assert {e.status for e in after} == {Status.LINK_GAP}
        assert not np.any(agent._commanded)
        # A fresh press (release, then press) moves again.
        alice.set_twist([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=False)
        time.sleep(0.1)
        alice.set_twist([0.004, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)
        wait_until(lambda: _moving(alice), 5.0, message="moving after a fresh press")



@pytest.mark.slow
def test_bound_keys_end_to_end(tmp_path) -> None:
    """With operator keys bound to certificates (the default DEPLOY.md generates): the owner moves the robot, the
    camera and the torch on its own keys; another granted operator's stop is obeyed and logged in the name the
    router authenticated, not the one it wrote."""
    from iorthand_edge.agent import EdgeAgent

    lab = make_lab(tmp_path, free_port(), robots=["sim1"], operators={"alice": ["sim1"], "bob": ["sim1"]},
                   bind_operator_keys=True)
    router = zenoh.open(zenoh.Config.from_file(str(lab.router_config)))
    agent = EdgeAgent(edge_config(lab.endpoint, "sim1", zenoh=_edge_zenoh(lab, "edge-sim1"), bind_operator_keys=True,
                                  servos={"driver": {"kind": "sim"}, "max_rate_deg_s": 1000.0},
                                  torch={"driver": {"kind": "sim"}}))
    agent.start()
    sessions = [open_session(lab.client("operator-alice")), open_session(lab.client("operator-bob"))]
    try:
        alice = OperatorClient(sessions[0], "sim1", "alice", bind_keys=True)
        alice.wait_for_state()
        alice.acquire()
        alice.start()
        x0 = alice.robot_state.tcp_pose[0]
        alice.set_twist([0.004, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)
        wait_until(lambda: alice.robot_state.tcp_pose[0] > x0 + 0.0005, 5.0, message="the robot moving in +x")
        alice.send_servo(pan=0.5)
        alice.set_torch(True)
        assert agent.servos is not None and agent.torch is not None
        wait_until(lambda: alice.servo is not None and alice.servo.pan_target == pytest.approx(0.5), 5.0,
                   message="the servo command applied")
        wait_until(lambda: alice.torch is not None and alice.torch.on, 5.0, message="the torch on")
        bob = sessions[1].declare_publisher(keys.RobotKeys("sim1").key(keys.CMD_STOP) + "/bob")
        bob.put(StopCommand(operator="alice", reason="bob's e-stop").stamp(1).encode())
        wait_until(lambda: agent.supervisor.status == Status.STOPPED, 3.0, message="bob's stop obeyed")
        assert "'bob' (claiming 'alice')" in agent.supervisor.reason
        assert agent.supervisor.owner == "alice"
        alice.close()
    finally:
        agent.shutdown()
        for s in sessions:
            s.close()
        router.close()
