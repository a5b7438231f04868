"""Scripted motions: what ``iorthand operator move`` and the demo run. Each returns a JSON-able summary."""

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


def measure_deadman_stop(client: OperatorClient, linear: np.ndarray, hold: float = 0.5) -> float:
    """Move, then go silent with the deadman still held (a dead link). Returns the seconds from the last
    command sent to the edge's first state with a zero commanded twist (edge time stamp; same host clock)."""
    client.set_twist(linear, np.zeros(3), deadman=True)
    time.sleep(hold)
    client.muted = True
    time.sleep(2.0 / client.rate_hz)  # a send may be under way
    last_sent_ns = client.last_sent_ns
    deadline = time.monotonic() + 2.0
    stop_ns = None
    while time.monotonic() < deadline and stop_ns is None:
        state = client.robot_state
        if state is not None and state.t > last_sent_ns and not np.any(state.commanded):
            stop_ns = state.t
        time.sleep(0.001)
    client.set_twist(np.zeros(3), np.zeros(3), deadman=False)
    client.muted = False
    _wait_still(client)
    return float("nan") if stop_ns is None else (stop_ns - last_sent_ns) / 1e9


def demo_motion(client: OperatorClient) -> dict:
    """The demo: a square-ish path, then a dead-link stop measured end to end."""
    start = _position(client)
    sent0 = client.sent_count
    legs = []
    for linear in ([0.02, 0.0, 0.0], [0.0, 0.02, 0.0], [-0.02, 0.0, 0.0], [0.0, 0.0, 0.05]):
        legs.append(move(client, np.array(linear), np.zeros(3), 1.0))
    deadman_stop = measure_deadman_stop(client, np.array([0.0, -0.02, 0.0]))
    end = _position(client)
    rtts = [e.rtt_ms for e in client.echoes]
    safety = client.safety
    return {
        "robot": client.keys.robot,
        "operator": client.operator_id,
        "profile": safety.profile if safety else "",
        "path_mm": round(sum(leg["distance_mm"] for leg in legs), 1),
        "net_displacement_mm": round(1000 * float(np.linalg.norm(end - start)), 1),
        "legs": legs,
        "commands_sent": client.sent_count - sent0,
        "commands_applied": sum(e.accepted for e in client.echoes),
        "commands_rejected": sum(not e.accepted for e in client.echoes),
        "command_to_applied_ms": {k: round(v, 3) for k, v in stats.summary(rtts).items()},
        "deadman_stop_ms": round(1000 * deadman_stop, 1),
        "edge_counters": {
            "received": safety.received, "applied": safety.applied, "rejected": safety.rejected,
            "malformed": safety.malformed, "stops": safety.stops,
        } if safety else {},
    }
