"""Plug-and-play over TLS: the edge starts before its router and connects when it appears; a router restart
leaves the robot stopped during the gap, and control can be re-acquired afterwards."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from iorthand.security.lab import Lab, make_lab
from iorthand.transport import free_port, open_session
from tests.conftest import RouterProcess, edge_config, wait_until
from tests.test_tls_integration import edge_zenoh


@pytest.fixture
def lab(tmp_path: Path) -> Lab:
    return make_lab(tmp_path, free_port(), robots=["sim1"], operators={"alice": ["sim1"]})


def test_edge_started_before_the_router_connects_within_2s(lab: Lab) -> None:
    from iorthand_edge.agent import EdgeAgent

    agent = EdgeAgent(edge_config(lab.endpoint, "sim1", zenoh=edge_zenoh(lab, retry_s=60.0)))
    connected_at: list[float] = []

    def start() -> None:
        agent.start()
        connected_at.append(time.monotonic())

    t = threading.Thread(target=start, daemon=True)
    t.start()
    time.sleep(1.5)  # the edge is retrying (and diagnosing) while no router exists
    assert not connected_at
    router = RouterProcess(lab.endpoint, lab.router_config)
    router.start()
    try:
        wait_until(lambda: connected_at, 5.0, message="the edge connecting")
        delay = connected_at[0] - router.ready_at
        print(f"edge connected {delay:.3f} s after the router came up")
        assert delay <= 2.0
    finally:
        agent.shutdown()
        router.stop()


def test_router_restart_stops_the_robot_and_control_is_reacquired(lab: Lab) -> None:
    from iorthand_edge.agent import EdgeAgent
    from iorthand_operator.client import ControlRefused, OperatorClient

    router = RouterProcess(lab.endpoint, lab.router_config)
    router.start()
    agent = EdgeAgent(edge_config(lab.endpoint, "sim1", zenoh=edge_zenoh(lab)))
    agent.start()
    session = open_session(lab.client("operator-alice", retry_s=10.0))
    alice = OperatorClient(session, "sim1", "alice")
    try:
        alice.wait_for_state()
        alice.acquire()
        alice.start()
        alice.set_twist([0.004, 0, 0], [0, 0, 0], deadman=True)
        wait_until(lambda: np.any(agent._commanded), 5.0, message="motion before the restart")

        router.stop()
        # Commands no longer arrive: the deadman timeout stops the robot within command_timeout.
        wait_until(lambda: not np.any(agent._commanded), 2.0, message="the robot stopping during the gap")
        time.sleep(0.5)
        assert not np.any(agent._commanded)

        router.start()
        # Both sessions reconnect on their own; the operator asks for control again.
        def reacquired() -> bool:
            try:
                alice.acquire()
                return True
            except (ControlRefused, RuntimeError):
                return False

        wait_until(reacquired, 10.0, interval=0.2, message="control re-acquired after the restart")
        applied = agent.supervisor.counters.applied
        alice.set_twist([0, 0, 0], [0, 0, 0], deadman=False)
        time.sleep(0.2)
        alice.set_twist([0.004, 0, 0], [0, 0, 0], deadman=True)
        wait_until(lambda: agent.supervisor.counters.applied > applied + 5 and np.any(agent._commanded), 5.0,
                   message="motion after the restart")
    finally:
        alice.close()
        session.close()
        agent.shutdown()
        router.stop()
