"""``iorthand operator move``: one constant-velocity motion and a JSON-able summary of it; the motion of the
headless clients goes on through lost leases, dead links and halts (:func:`drive_for`)."""

from __future__ import annotations

import time

import numpy as np

from iorthand import stats
from iorthand_operator import recovery
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


# A headless client recovers when the edge has not driven the robot for this long (shorter: a command on its way).
STALL_S = 0.25


def drive_for(client: OperatorClient, seconds: float, patience: float,
              since: float | None = None) -> tuple[float, list[str]]:
    """Hold the deadman with the client's twist until the edge has driven the robot for ``seconds`` in all
    (accepted the commands: its limits may clip them, a force or workspace limit even to zero).

    The intent is clear (the caller asked for this motion), so whatever halts it on the way — a lost lease, a
    dead link — the client takes the step itself (:meth:`recover`) and the motion goes on. A stop command that
    halts it on the way ends it instead: somebody (the nurse at the patient, another operator) stopped the
    robot after this motion was asked for (``since``, monotonic: by default now; a script's start), and nothing
    resumes motion without a fresh intent. (A stop from before, and the client's own, such as a script's
    ``stop`` step, are recovered from: the motion asked after it is that intent.) Gives up ``patience`` s after
    it would have finished. Returns (s moved, what it did)."""
    moved, actions = 0.0, []
    last = started = time.monotonic()
    since = started if since is None else since
    still_since = last
    give_up = last + seconds + patience
    while moved < seconds and time.monotonic() < give_up:
        time.sleep(0.01)
        now = time.monotonic()
        if client.stopped_by_other_at > since:
            actions.append(f"stopped: {client.stopped_by_other}")
            break
        if client.driving():
            moved += now - last
            still_since = now
        elif now - still_since > STALL_S:
            step = client.recover()
            if step.step is not recovery.Step.NONE and (not actions or actions[-1] != f"{step.step.value}: {step.why}"):
                actions.append(f"{step.step.value}: {step.why}")
            still_since = now  # give what it did time to take effect
        last = now
    return moved, actions


def move(client: OperatorClient, linear: np.ndarray, angular: np.ndarray, seconds: float,
         patience: float = 30.0) -> dict:
    """Hold the deadman and command a constant twist until the robot has moved for ``seconds`` (recovering from
    halts on the way, :func:`drive_for`), release, wait for rest."""
    start = _position(client)
    first_echo = client.echo_count
    client.set_twist(linear, angular, deadman=True)
    moved_s, recoveries = drive_for(client, seconds, patience)
    client.set_twist(np.zeros(3), np.zeros(3), deadman=False)
    _wait_still(client)
    end = _position(client)
    echoes = client.echoes_since(first_echo)
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
        "moved_s": round(moved_s, 3),
        "completed": moved_s >= seconds,
        "recoveries": recoveries,
    }
