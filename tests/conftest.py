"""Shared fixtures: real Zenoh routers on 127.0.0.1 with free ports, edge agents with a simulated robot,
operator clients. Everything a fixture starts, it stops."""

from __future__ import annotations

import contextlib
import functools
import gc
import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest
import zenoh

from iorthand import keys
from iorthand.config import from_dict
from iorthand.process import terminate
from iorthand.transport import client_config, free_port, open_session, query, router_json5

if TYPE_CHECKING:
    from iorthand_edge.ur_emulator.process import EmulatorProcess

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """A real Zenoh router in this process, listening on a free loopback port."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = zenoh.open(zenoh.Config.from_json5(router_json5(endpoint)))
    yield endpoint
    session.close()


class RouterProcess:
    """A router in its own process (``iorthand router``), so tests can kill and restart it; with ``config``, that
    router configuration file (which names the endpoint) instead of the built-in one; ``options``: more of the
    command's options (``--connect``, ``--datagrams``, ...)."""

    def __init__(self, endpoint: str, config: Path | None = None, options: tuple[str, ...] = ()) -> None:
        self.endpoint = endpoint
        self.config = config
        self.options = options
        self.proc: subprocess.Popen[bytes] | None = None
        self.ready_at = 0.0  # monotonic time it said "router ready"

    def start(self) -> None:
        settings = ["--config", str(self.config)] if self.config else ["--listen", self.endpoint]
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "iorthand.cli", "router", *settings, *self.options],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        )
        assert self.proc.stdout is not None
        deadline = time.monotonic() + 15
        seen: list[bytes] = []
        for line in self.proc.stdout:
            seen.append(line)
            if b"router ready" in line or time.monotonic() > deadline:
                break
        if not seen or b"router ready" not in seen[-1]:
            # Say so here (a port taken meanwhile, say), not as a test that waits in vain for its messages.
            output = b"".join(seen).decode(errors="replace")[-2000:]
            self.stop()
            raise RuntimeError(f"router on {self.endpoint} not ready (exit code {self.proc.poll()}): {output}")
        self.ready_at = time.monotonic()
        # Keep draining its output, or a router that logs enough blocks on a full pipe.
        threading.Thread(target=self.proc.stdout.read, daemon=True).start()

    def stop(self) -> None:
        if self.proc is not None:
            stop_process(self.proc)


# SIGTERM, then SIGKILL: a process a test started is always gone afterwards.
stop_process = terminate


@pytest.fixture
def router_process() -> Iterator[RouterProcess]:
    router = RouterProcess(f"tcp/127.0.0.1:{free_port()}")
    router.start()
    yield router
    router.stop()


def edge_config(endpoint: str, robot_id: str = "sim1", **overrides: object):
    """An edge config for tests: simulated robot, auto-armed. ``overrides`` are merged per top-level key."""
    from iorthand_edge.config import EdgeConfig

    data: dict = {
        "robot_id": robot_id,
        "zenoh": {"mode": "client", "connect": [endpoint], "connect_retry_s": 10.0},
        "robot": {"kind": "sim", "initial_pose": [0.30, 0.0, 0.20, 3.14159, 0.0, 0.0]},
        "safety": {"auto_arm": True},
    }
    for key, value in overrides.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    return from_dict(data, EdgeConfig, source="<test>")


@pytest.fixture
def edge_factory(router_endpoint: str):
    """Start edge agents in this process; all are shut down after the test."""
    from iorthand_edge.agent import EdgeAgent

    agents: list[EdgeAgent] = []

    def make(robot_id: str = "sim1", **overrides: object) -> EdgeAgent:
        agent = EdgeAgent(edge_config(router_endpoint, robot_id, **overrides))
        agent.start()
        agents.append(agent)
        return agent

    yield make
    for agent in agents:
        agent.shutdown()


@pytest.fixture
def session_factory(router_endpoint: str):
    """Client sessions to the test router, closed after the test."""
    from iorthand.transport import client_config

    sessions: list[zenoh.Session] = []

    def make() -> zenoh.Session:
        s = open_session(client_config(router_endpoint))
        sessions.append(s)
        return s

    yield make
    for s in sessions:
        s.close()


@pytest.fixture
def operator_factory(session_factory):
    """Operator clients (library) on their own sessions, closed after the test."""
    from iorthand_operator.client import OperatorClient

    clients: list[OperatorClient] = []

    def make(robot_id: str = "sim1", operator_id: str = "op1", **kwargs: object) -> OperatorClient:
        client = OperatorClient(session_factory(), robot_id, operator_id, **kwargs)
        clients.append(client)
        return client

    yield make
    for c in clients:
        with contextlib.suppress(zenoh.ZError):
            c.close()


def twin_config(endpoint: str, tmp_path: Path, **viewer: object):
    """A twin that saves to a file instead of serving a viewer (tests)."""
    from iorthand_cloud.twin.config import TwinConfig

    v = {"serve": False, "save": str(tmp_path / "twin.rrd"), **viewer}
    return from_dict({"zenoh": {"mode": "client", "connect": [endpoint]}, "viewer": v}, TwinConfig, source="<test>")


@pytest.fixture
def twin_factory(router_endpoint, tmp_path):
    from iorthand_cloud.twin.service import TwinService

    twins: list[TwinService] = []

    def make(**viewer: object) -> TwinService:
        t = TwinService(twin_config(router_endpoint, tmp_path, **viewer))
        t.start()
        twins.append(t)
        # Its queryables reach the router a moment after start(): a query sent before has no answerer and gets
        # no reply at all (seen in a loaded CI run). The snapshot's is declared first, the preview's right after.
        probe = open_session(client_config(router_endpoint))
        try:
            key = keys.service_key(keys.TWIN, "probe1", keys.TWIN_SNAPSHOT)
            wait_until(lambda: bool(query(probe, key, b"", timeout=1.0)), 15, interval=0.05,
                       message="the twin's queryables at the router")
        finally:
            probe.close()
        return t

    yield make
    for t in twins:
        t.shutdown()


@contextlib.contextmanager
def ur_controller() -> Iterator[EmulatorProcess]:
    """The UR emulator as the controller it stands for: a computer of its own. It runs in a process at real-time
    priority (``EmulatorProcess.raise_priority``), so that neither this run's load nor the edge driver's real-time
    command thread starves it into stopping the program for want of kicks that were sent. At 250 Hz (the
    emulator's default), not the e-Series' 500: the same protocol at half the CPU on a 2-core runner. At exit it
    prints its event log (watchdog, program stops), which pytest shows only for a failed test."""
    from iorthand_edge.ur_emulator.process import EmulatorProcess

    with EmulatorProcess() as emulator:
        emulator.raise_priority()
        yield emulator
        with contextlib.suppress(OSError, RuntimeError):
            print("emulator events:", *emulator.status()["events"], sep="\n  ")

def ur_dashboard(host: str, command: str) -> str:
    """One command on the controller's dashboard port, as the teach pendant's buttons do; its answer."""
    from iorthand_edge.robots.ur import DashboardLink

    with DashboardLink(host, timeout=3.0) as dashboard:
        return dashboard.ask(command)


class Emulator:
    """The UR emulator in a process of its own at real-time priority: a controller is a computer of its own, and
    in the test's process (as it was) it shared the interpreter with the agent's side, so that a loaded test run
    starved both (false "driver hung" and "control script not running" faults, 5 runs in 12 beside stress-ng).
    Its fault methods (``UREmulator``'s) go over its control socket, with keyword arguments."""

    def __init__(self, process: EmulatorProcess) -> None:
        self.process = process
        self.host = process.host

    def __getattr__(self, op: str) -> Any:
        return functools.partial(self.process.call, op)


@pytest.fixture
def emu() -> Iterator[Emulator]:
    with ur_controller() as process:
        yield Emulator(process)


@pytest.fixture
def make_robot(emu: Emulator) -> Iterator[Any]:
    """URRobot(config overrides, tcp_offset=None) on ``emu``; each disconnected after the test."""
    from iorthand_edge.robots.config import URRobotConfig
    from iorthand_edge.robots.ur import URRobot
    from iorthand_edge.supervisor import SafetyConfig

    robots: list[URRobot] = []

    def make(tcp_offset: list[float] | None = None, **overrides: object) -> URRobot:
        config = URRobotConfig(host=emu.host, **overrides)  # type: ignore[arg-type]
        robot = URRobot(config, SafetyConfig().stop_deceleration, tcp_offset=tcp_offset)
        robots.append(robot)
        return robot

    yield make
    for robot in robots:
        robot.disconnect()



@contextlib.contextmanager
def small_disk(tmp_path: Path, size: str) -> Iterator[Path]:
    """A tmpfs of ``size`` (mount's syntax: "64k", "1m") under ``tmp_path``: a disk that really fills up (root
    only; the test is skipped elsewhere)."""
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a tmpfs needs root")
    mnt = tmp_path / "small"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)]).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=True)


def wait_until(predicate, timeout: float = 5.0, interval: float = 0.01, message: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {message}")


def drive_slowly(agent, client, vx: float = 0.004) -> None:
    """``client`` takes control of ``agent``'s robot and holds the deadman with a slow twist along x, until the
    edge drives the robot with it."""
    client.wait_for_state()
    client.acquire()
    client.start()
    client.set_twist([vx, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)
    wait_until(lambda: any(agent._commanded), 5.0, message="the owner moving the robot")


def iorthand_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "iorthand.cli", *args]


os.environ.setdefault("PYTHONUNBUFFERED", "1")


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    """Everything alive when a test starts leaves the garbage collector's scans (gc.freeze). Late in a full run
    this process holds ~720 000 objects, and a full collection of them took 0.35-0.6 s on the project's 2-core
    VM: a pause of every Python thread here, the operator clients, relays and watchers that tests run in this
    process included (a page's stream stalled 0.9 s behind such a pause, and the edge latched its deadman). The
    system's own processes hold a small fraction of that. Garbage in cycles among frozen objects stays until
    the run ends: a bounded cost for a test process."""
    gc.freeze()
