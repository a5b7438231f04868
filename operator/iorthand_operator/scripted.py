"""``iorthand operator move``: one constant-velocity motion and a JSON-able summary of it."""

from __future__ import annotations

import time

import numpy as np

from iorthand import stats
from iorthand_operator.client import OperatorClient


def _position(client: OperatorClient) -> np.ndarray:
    return np.array(client.wait_for_state().tcp_pose[:3])


def _wait_still(client: OperatorClient, timeout: float = 2.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        state = client.robot_state
        if state is not None and np.linalg.norm(state.tcp_speed[:3]) < 1e-5:
            return
        time.sleep(0.01)


def move(client: OperatorClient, linear: np.ndarray, angular: np.ndarray, seconds: float) -> dict:
    """Hold the deadman and command a constant twist for ``seconds``, release, wait for rest."""
    start = _position(client)
    first_echo = len(client.echoes)
    client.set_twist(linear, angular, deadman=True)
    time.sleep(seconds)
    client.set_twist(np.zeros(3), np.zeros(3), deadman=False)
    _wait_still(client)
    end = _position(client)
    echoes = client.echoes[first_echo:]
    limit = client.safety.linear_limit if client.safety else float("nan")
    return {
        "start_mm": (1000 * start).round(2).tolist(),
        "end_mm": (1000 * end).round(2).tolist(),
        "distance_mm": round(1000 * float(np.linalg.norm(end - start)), 2),
        "requested_mm": round(1000 * float(np.linalg.norm(linear)) * seconds, 2),
        "speed_limit_mm_s": round(1000 * limit, 2),
        "commands_echoed": len(echoes),
        "accepted": sum(e.accepted for e in echoes),
        "refused": sum(not e.accepted for e in echoes),
        "last_refusal": client.last_refusal.reason if client.last_refusal else "",
        "rtt_ms": {k: round(v, 3) for k, v in stats.summary([e.rtt_ms for e in echoes]).items()},
    }
