"""What ``bench_flood_memory.py`` and ``bench_cpu_hogs.py`` share: the real programs of a teleoperation
(``iorthand router``, ``iorthand edge``, an :class:`OperatorClient`) on 127.0.0.1, and a watcher that records
what the edge publishes about the robot and its safety state. Every process is started in a
:class:`~iorthand_operator.bench.procs.Group`, which stops it on the way out (also on SIGTERM or a failure)."""

from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
import zenoh

from iorthand import keys
from iorthand.protocol import DecodeError, RobotState, SafetyStatus, Status
from iorthand.transport import client_config, open_session
from iorthand_operator.bench.procs import Child, Group, iorthand_argv
from iorthand_operator.client import OperatorClient

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
CONFIGS = ROOT / "configs"


def start_router(group: Group, endpoint: str) -> Child:
    # --no-shared-memory: the operator and an attacker sit on other hosts, where no shared memory exists.
    return group.start("router", iorthand_argv("router", "--listen", endpoint, "--no-shared-memory"),
                       ready="router ready", timeout=30.0)


def edge_config(base: Path, out: Path, endpoint: str, overrides: dict[str, Any]) -> Path:
    """``base`` (a YAML of configs/) with the router endpoint and ``overrides`` merged per top-level key."""
    cfg = yaml.safe_load(base.read_text())
    cfg["zenoh"] = {**cfg.get("zenoh", {}), "connect": [endpoint], "connect_retry_s": 30.0}
    for name, value in overrides.items():
        cfg[name] = {**cfg.get(name, {}), **value} if isinstance(value, dict) else value
    out.write_text(yaml.safe_dump(cfg))
    return out


def start_edge(group: Group, config: Path) -> Child:
    return group.start("edge", iorthand_argv("--log-level", "warning", "edge", "--config", str(config)))


@dataclass
class Seen:
    """state/robot and state/safety as received (wall-clock receive time, ns, first)."""

    robot: list[tuple[int, RobotState]] = field(default_factory=list)
    safety: list[tuple[int, SafetyStatus]] = field(default_factory=list)


class Watcher:
    """A session of its own that records the edge's state/robot and state/safety (a console would show them)."""

    def __init__(self, endpoint: str, robot_id: str) -> None:
        self.session = open_session(client_config(endpoint))
        self.seen = Seen()
        self._lock = threading.Lock()
        k = keys.RobotKeys(robot_id)
        self._subs = [
            self.session.declare_subscriber(k.key(keys.STATE_ROBOT), lambda s: self._on(s, RobotState, self.seen.robot)),
            self.session.declare_subscriber(k.key(keys.STATE_SAFETY), lambda s: self._on(s, SafetyStatus, self.seen.safety)),
        ]

    def _on(self, sample: zenoh.Sample, cls: type[Any], into: list[tuple[int, Any]]) -> None:
        now = time.time_ns()
        try:
            msg = cls.decode(sample.payload.to_bytes())
        except DecodeError:
            return  # the edge's own messages always decode; nothing else publishes here in a benchmark
        with self._lock:
            into.append((now, msg))

    def snapshot(self) -> Seen:
        with self._lock:
            return Seen(list(self.seen.robot), list(self.seen.safety))

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self.session.close()


def lease_lost(status: SafetyStatus) -> bool:
    """The edge says the owner lost control: its lease expired or its session was lost."""
    return status.status == Status.OWNER_LOST or re.search(r"\blease\b", status.reason) is not None


def driver_fault(state: RobotState | None, status: SafetyStatus | None) -> str:
    """The fault the edge reports, from state/robot or state/safety; empty if none."""
    if state is not None and state.fault:
        return state.fault
    if status is not None and status.status == Status.FAULT:
        return status.reason or "fault"
    return ""


def operator(endpoint: str, robot_id: str, name: str, profile: str = "", bind_keys: bool = False) -> OperatorClient:
    """An operator that holds control: connected, state seen, control acquired, sender running (deadman up).
    ``bind_keys``: commands on keys that carry its name (an edge with ``bind_operator_keys``)."""
    session = open_session(client_config(endpoint))
    op = OperatorClient(session, robot_id, name, bind_keys=bind_keys)
    op.wait_for_state(timeout=60.0)
    op.acquire(profile)
    op.start()
    return op


def close_operator(op: OperatorClient) -> None:
    op.close()
    op.session.close()


def wait(pred: Any, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.02)
