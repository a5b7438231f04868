"""The edge's command handling without Zenoh or threads: EdgeAgent.handle_twist judges one command the way the
control loop does (decode, gate, supervisor, robot call) and returns the echo the operator sees. The commands
are signed with the key of the test's grant, the way the operator's session signs them."""

from __future__ import annotations

import time

import pytest

from iorthand import keys
from iorthand.protocol import Status, TwistCommand
from iorthand_edge.agent import EdgeAgent
from tests.conftest import edge_config
from tests.grants import Grants


@pytest.fixture
def grants() -> Grants:
    return Grants()


@pytest.fixture
def agent(grants: Grants) -> EdgeAgent:
    """An edge agent with the simulated robot, armed and owned by "op"; never started, so nothing is on the wire."""
    a = EdgeAgent(edge_config("tcp/127.0.0.1:1", "sim1"))
    a.robot.connect()
    a.first_reading()
    a.supervisor.arm()
    ok, why = grants.acquire(a.supervisor, "op", time.monotonic())
    assert ok, why
    return a


def twist(agent: EdgeAgent, grants: Grants, seq: int, operator: str = "op", vx: float = 0.004,
          deadman: bool = True) -> bytes:
    """A command of ``operator``'s session, signed with its key (unsigned when it holds none), from a live view;
    ``seq`` counts after the grant's own release command."""
    cmd = TwistCommand(operator=operator, linear=[vx, 0.0, 0.0], deadman=deadman, state_age=0.02)
    cmd.stamp(grants.seq + seq)
    return grants.sign(agent.supervisor, operator, cmd).encode()


def handle(agent: EdgeAgent, payload: bytes):
    return agent.handle_twist(agent.keys.key(keys.CMD_TWIST), payload, time.time_ns())


def test_an_allowed_command_drives_the_robot_and_echoes_what_was_sent(agent: EdgeAgent, grants: Grants) -> None:
    echo = handle(agent, twist(agent, grants, 1))
    assert echo is not None and echo.accepted, echo
    assert echo.cmd_seq == grants.seq + 1 and echo.operator == "op"
    assert echo.applied[0] == pytest.approx(0.004)
    assert list(agent._commanded) == pytest.approx(list(echo.applied))


def test_a_command_over_the_speed_limit_is_clipped_and_says_so(agent: EdgeAgent, grants: Grants) -> None:
    limit = agent.supervisor.limits.linear
    echo = handle(agent, twist(agent, grants, 1, vx=10 * limit))
    assert echo is not None and echo.accepted
    assert echo.status == Status.SPEED_LIMITED, echo
    assert echo.applied[0] == pytest.approx(limit)


def test_a_command_from_another_operator_moves_nothing_and_names_the_owner(agent: EdgeAgent, grants: Grants) -> None:
    echo = handle(agent, twist(agent, grants, 1, operator="intruder"))
    assert echo is not None and not echo.accepted
    assert echo.status == Status.NOT_OWNER and "op" in echo.reason, echo
    assert not any(echo.applied) and not agent._commanded.any()


def test_a_command_in_the_owners_name_without_its_signature_moves_nothing_and_gets_no_echo(
        agent: EdgeAgent, grants: Grants) -> None:
    forged = TwistCommand(operator="op", linear=[0.004, 0.0, 0.0], deadman=True, state_age=0.02).stamp(1).encode()
    assert handle(agent, forged) is None
    assert agent.supervisor.counters.forged == 1 and not agent._commanded.any()
    # The owner's own signed command still goes: the forgery did not use up its sequence.
    echo = handle(agent, twist(agent, grants, 1))
    assert echo is not None and echo.accepted, echo


def test_commands_refused_during_a_fault_do_not_lock_the_owner_out_afterwards(agent: EdgeAgent, grants: Grants) -> None:
    """The operator holds the deadman through a protective stop of ~18 s (60 Hz): once the fault is cleared and
    acknowledged, a release and a fresh press move the robot again, with the same grant."""
    agent.supervisor.set_fault("protective stop")
    for seq in range(1, 1101):
        echo = handle(agent, twist(agent, grants, seq))
        assert echo is not None and echo.status == Status.FAULT, echo
    agent.supervisor.set_fault("")
    assert grants.acquire(agent.supervisor, "op", time.monotonic())[0]  # the client's renewal acknowledges it
    handle(agent, twist(agent, grants, 1101, deadman=False))
    echo = handle(agent, twist(agent, grants, 1102))
    assert echo is not None and echo.accepted, echo


def test_a_malformed_command_is_counted_and_gets_no_echo(agent: EdgeAgent) -> None:
    before = agent.rejects.total
    assert handle(agent, b"\x00not a command") is None
    assert agent.rejects.total == before + 1
    assert not agent._commanded.any()


def test_echoes_carry_their_own_rising_sequence_numbers(agent: EdgeAgent, grants: Grants) -> None:
    echoes = [handle(agent, twist(agent, grants, seq)) for seq in (1, 2, 3)]
    assert [e.cmd_seq - grants.seq for e in echoes] == [1, 2, 3]
    seqs = [e.seq for e in echoes]
    assert seqs == sorted(seqs) and len(set(seqs)) == 3
