"""The edge's command handling without Zenoh or threads: EdgeAgent.handle_twist judges one command the way the
command thread does (decode, gate, supervisor, robot call) and returns the echo the operator sees."""

from __future__ import annotations

import time

import pytest

from iorthand import keys
from iorthand.protocol import Status, TwistCommand
from iorthand_edge.agent import EdgeAgent
from tests.conftest import edge_config


@pytest.fixture
def agent() -> EdgeAgent:
    """An edge agent with the simulated robot, armed and owned by "op"; never started, so nothing is on the wire."""
    a = EdgeAgent(edge_config("tcp/127.0.0.1:1", "sim1"))
    a.robot.connect()
    a.reading = a.robot.read_state()
    a.supervisor.arm()
    ok, why = a.supervisor.acquire("op", time.monotonic())
    assert ok, why
    return a


def twist(seq: int, operator: str = "op", vx: float = 0.004, deadman: bool = True) -> bytes:
    return TwistCommand(operator=operator, linear=[vx, 0.0, 0.0], deadman=deadman).stamp(seq).encode()


def handle(agent: EdgeAgent, payload: bytes):
    return agent.handle_twist(agent.keys.key(keys.CMD_TWIST), payload, time.time_ns())


def test_an_allowed_command_drives_the_robot_and_echoes_what_was_sent(agent: EdgeAgent) -> None:
    echo = handle(agent, twist(1))
    assert echo is not None and echo.accepted, echo
    assert echo.cmd_seq == 1 and echo.operator == "op"
    assert echo.applied[0] == pytest.approx(0.004)
    assert list(agent._commanded) == pytest.approx(list(echo.applied))


def test_a_command_over_the_speed_limit_is_clipped_and_says_so(agent: EdgeAgent) -> None:
    limit = agent.supervisor.limits.linear
    echo = handle(agent, twist(1, vx=10 * limit))
    assert echo is not None and echo.accepted
    assert echo.status == Status.SPEED_LIMITED, echo
    assert echo.applied[0] == pytest.approx(limit)


def test_a_command_from_another_operator_moves_nothing_and_names_the_owner(agent: EdgeAgent) -> None:
    echo = handle(agent, twist(1, operator="intruder"))
    assert echo is not None and not echo.accepted
    assert echo.status == Status.NOT_OWNER and "op" in echo.reason, echo
    assert not any(echo.applied) and not agent._commanded.any()


def test_a_malformed_command_is_counted_and_gets_no_echo(agent: EdgeAgent) -> None:
    before = agent.rejects.total
    assert handle(agent, b"\x00not a command") is None
    assert agent.rejects.total == before + 1
    assert not agent._commanded.any()


def test_echoes_carry_their_own_rising_sequence_numbers(agent: EdgeAgent) -> None:
    echoes = [handle(agent, twist(seq)) for seq in (1, 2, 3)]
    assert [e.cmd_seq for e in echoes] == [1, 2, 3]
    seqs = [e.seq for e in echoes]
    assert seqs == sorted(seqs) and len(set(seqs)) == 3
