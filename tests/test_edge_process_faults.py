"""The edge's own processes failing: a second agent started for the same robot, the agent killed and restarted
(systemd's Restart=) while the operator holds the deadman, the agent stopped with SIGTERM while the arm moves.

The agent runs as ``iorthand edge`` in a process of its own where the test kills it; the operator is the real
OperatorClient in this process, on the test's router; the robot is the simulator (no hardware here)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from iorthand.process import terminate

from .conftest import drive_slowly, iorthand_cmd, wait_until

ROBOT_ID = "sim1"


def local_status(path: Path) -> dict[str, Any] | None:
    """The agent's answer to ``status`` on its local socket; None while nothing answers there."""
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
            conn.settimeout(5.0)
            conn.connect(str(path))
            conn.sendall(b"status\n")
            return json.loads(conn.recv(4096))  # type: ignore[no-any-return]
    except (FileNotFoundError, ConnectionRefusedError, TimeoutError):  # (a timeout: it takes no more commands)
        return None


@pytest.fixture
def edge_process(router_endpoint: str, tmp_path: Path) -> Iterator[Any]:
    """``start()`` runs ``iorthand edge`` on a simulated robot with a local socket; all are stopped afterwards."""
    config = tmp_path / "edge.yaml"
    sock = tmp_path / "edge.sock"
    config.write_text(yaml.safe_dump({
        "robot_id": ROBOT_ID, "zenoh": {"mode": "client", "connect": [router_endpoint], "connect_retry_s": 10.0},
        "robot": {"kind": "sim", "initial_pose": [0.30, 0.0, 0.20, 3.14159, 0.0, 0.0]},
        "safety": {"auto_arm": True}, "local_socket": str(sock),
    }))
    procs: list[subprocess.Popen[bytes]] = []

    def start() -> subprocess.Popen[bytes]:
        proc = subprocess.Popen(iorthand_cmd("--log-level", "warning", "edge", "--config", str(config)),
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        procs.append(proc)
        return proc

    start.config, start.sock = config, sock  # type: ignore[attr-defined]
    yield start
    for proc in procs:
        terminate(proc)


def test_a_second_edge_for_the_same_robot_refuses_to_start_and_says_why(edge_process) -> None:
    """Found by a red-team run: a second ``iorthand edge`` on the same configuration (a manual run beside the
    service) started without a word. It unlinked the first agent's local socket and bound its own, so that the
    local arm and disarm reached the newcomer, and both agents answered the operators' control queries (each
    granted control; each refused the other's signed commands as forged). Now it refuses to start, and says so."""
    first = edge_process()
    wait_until(lambda: local_status(edge_process.sock) is not None, 30.0, message="the first agent's local socket")
    second = edge_process()
    try:
        code = second.wait(timeout=60.0)
    except subprocess.TimeoutExpired:
        pytest.fail("a second edge agent for the same robot kept running beside the first")
    said = second.stderr.read().decode() if second.stderr else ""
    assert code == 1
    assert f"an edge agent is already running for robot {ROBOT_ID!r}" in said and str(edge_process.sock) in said
    assert first.poll() is None
    assert local_status(edge_process.sock) is not None  # the first agent still answers on its own socket


def test_an_agent_killed_while_the_robot_moves_restarts_and_moves_only_after_a_fresh_press(
        edge_process, operator_factory) -> None:
    """SIGKILL (the OOM killer) while the operator drives; systemd starts the agent again. Its local socket file is
    left behind by the killed agent: the restart must not take it for a second agent. The operator, still holding
    the deadman, is told the edge went offline; the new agent moves nothing until a fresh press."""
    first = edge_process()
    op = operator_factory(ROBOT_ID)
    op.wait_for_state(timeout=30.0)
    assert op.acquire().ok
    op.start()
    op.set_twist([0.004, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)
    wait_until(lambda: any(op.robot_state.commanded), 5.0, message="the robot moving")
    first.kill()
    first.wait(10.0)
    killed_ns = time.time_ns()
    wait_until(lambda: any(e.status == "edge_offline" for e in op.events), 10.0,
               message="the operator told that the edge went offline")
    assert edge_process.sock.exists()  # what the killed agent left

    again = edge_process()
    wait_until(lambda: local_status(edge_process.sock) is not None, 30.0,
               message="the restarted agent's local socket (not refused for the killed one's file)")
    assert again.poll() is None
    wait_until(lambda: op.robot_state.t > killed_ns, 10.0, message="states from the restarted agent")
    # The operator takes control of the restarted agent (the client gave it up if the restart outlasted its lease).
    assert op.acquire().ok
    wait_until(lambda: op.safety.t > killed_ns and op.safety.owner == op.operator_id, 5.0,
               message="the restarted agent's grant in state/safety")
    deadline = time.monotonic() + 1.5  # the operator still holds the deadman pressed before the restart
    while time.monotonic() < deadline:
        assert not np.any(op.robot_state.commanded), "a press held through the restart moved the robot"
        time.sleep(0.01)
    op.set_twist([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=False)
    time.sleep(0.2)
    op.set_twist([0.004, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)
    wait_until(lambda: any(op.robot_state.commanded), 5.0, message="motion after a fresh press")


def test_a_killed_agents_stale_socket_file_is_not_taken_for_a_running_agent(tmp_path: Path) -> None:
    from iorthand_edge.cli import _running_agent

    path = tmp_path / "edge.sock"
    assert _running_agent(path) == ""  # no file
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as server:
        server.bind(str(path))  # bound, not listening: what a killed agent leaves behind refuses connections
    assert path.exists() and _running_agent(path) == ""


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))


def test_shutdown_stops_the_robot_before_it_tears_the_agent_down(edge_factory, operator_factory) -> None:
    """Found by a red-team run (SIGTERM to ``iorthand edge`` on the UR emulator while the tool moved at 20 mm/s):
    the agent joined its workers (the control loop among them), closed the planner and stopped the media process
    (up to 3 s for its camera) before it stopped the robot and told the operator. The tool came to rest after
    210 ms, stopped by the UR driver's own silent-agent timeout, not by the agent; the operator read "edge agent
    shutting down" 1.28 s after the signal. The robot must be stopped first, while the control loop still runs."""
    agent = edge_factory()
    op = operator_factory()
    drive_slowly(agent, op)
    control = next(w for w in agent._workers if w.name == "edge-control")
    loop_alive_at_stop: list[bool] = []
    stop = agent.robot.stop

    def recording_stop(deceleration: float) -> None:
        loop_alive_at_stop.append(control.is_alive())
        stop(deceleration)

    agent.robot.stop = recording_stop  # type: ignore[method-assign]
    agent.shutdown()
    assert loop_alive_at_stop, "the robot was never stopped"
    assert loop_alive_at_stop[0], "the robot was first stopped once the control loop had already ended"
    wait_until(lambda: op.safety is not None and "shutting down" in op.safety.reason, 2.0,
               message="the operator told that the edge shuts down")


def test_a_local_client_that_hangs_up_before_the_answer_breaks_nothing(edge_factory, tmp_path: Path) -> None:
    """Found by a red-team run: ``echo arm | nc -U`` that closes before the agent answers (the agent was busy: here
    it holds its lock) made the agent's answer fail with EPIPE outside the local loop's try. The edge-local thread
    died (no more local arm, disarm or status) and, as a crashed Worker sets its stop event, the event it shares
    with the servos and the torch stopped those too, without a word to the operator."""
    sock = tmp_path / "edge.sock"
    agent = edge_factory(local_socket=str(sock), servos={"driver": {"kind": "sim"}})
    wait_until(lambda: local_status(sock) is not None, 5.0, message="the local socket")
    with agent.lock:  # the agent busy: the client's line is read, and answered, only after it hung up
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
            conn.connect(str(sock))
            conn.sendall(b"disarm\n")
        time.sleep(0.5)
    wait_until(lambda: not agent.supervisor.armed, 5.0, message="the local disarm carried out")
    assert local_status(sock) is not None, "local commands are no longer answered"
    assert not agent._aux_stop.is_set(), "the servos and the torch were stopped"


@pytest.mark.serial  # the controller's watchdog stops the program if this test's loop (the agent's) misses 100 ms
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_or_a_service_stop_reaching_the_ur_driver_leaves_the_stop_to_the_agent(
        sig: signal.Signals, emu, make_robot) -> None:
    """Found by a red-team run (``iorthand edge`` on the UR emulator, the tool at 20 mm/s): Ctrl-C reaches the whole
    process group, and ``systemctl stop`` sends SIGTERM to every process of the service. The UR driver child died
    of it at once (a KeyboardInterrupt traceback, or no word at all), without its speedStop: the agent found its
    driver gone ("UR driver pipe broken") and only the controller's RTDE watchdog stopped the tool, 103 ms later
    (the second safety layer doing the first one's job). The driver must leave its end to the agent, which stops
    the arm and then closes the driver (or, gone, closes its pipe: the driver stops the arm itself)."""
    pytest.importorskip("rtde_control", reason="ur-rtde is not installed on this platform")
    from .test_ur_backend import cycle

    robot = make_robot()
    robot.connect()
    cycle(robot, 0.3, [0.02, 0, 0, 0, 0, 0])
    assert emu.status()["twist"][0] == pytest.approx(0.02)
    assert robot._proc is not None and robot._proc.pid is not None
    os.kill(robot._proc.pid, sig)  # what the terminal or systemd sends to the whole group or service
    reading = cycle(robot, 0.3)  # the agent's loop goes on (heartbeats) until its own handler stops it
    assert not reading.fault, f"the driver did not survive {sig.name}: {reading.fault}"
    robot.stop(0.5)
    robot.disconnect()
    status = emu.status()
    assert status["motion"] == "idle"
    assert not any("watchdog:" in e for e in status["events"]), status["events"]


def test_a_second_agent_for_a_robot_online_elsewhere_is_refused(edge_factory) -> None:
    """Two edge computers configured with one robot id (a copied configuration): both ran, both answered the
    operators' control queries and both published the robot's state under one key, without a word. The local
    socket cannot see an agent on another computer; the agent's liveliness token on the router can."""
    first = edge_factory()
    with pytest.raises(Exception, match="already online"):
        edge_factory()
    assert first.session is not None


def test_an_edge_whose_stderr_nobody_reads_keeps_driving_and_stopping(router_endpoint: str, tmp_path: Path,
                                                                       operator_factory) -> None:
    """Found by a red-team run: an edge whose log output nobody reads (a terminal paused with Ctrl-S,
    ``iorthand edge | less`` scrolled back, a log collector that stalls) froze in the first thread that logged a
    line once the pipe was full. Here the pipe is full from the start: the edge's first line ("agent up") blocked
    it, the operator's acquire timed out, nothing could drive it. Now lines wait in the process (iorthand.logs)
    and are written when the pipe is read again."""
    import fcntl

    config = tmp_path / "edge.yaml"
    config.write_text(yaml.safe_dump({
        "robot_id": ROBOT_ID, "zenoh": {"mode": "client", "connect": [router_endpoint], "connect_retry_s": 10.0},
        "robot": {"kind": "sim", "initial_pose": [0.30, 0.0, 0.20, 3.14159, 0.0, 0.0]},
        "safety": {"auto_arm": True},
    }))
    read_end, write_end = os.pipe()
    fcntl.fcntl(write_end, fcntl.F_SETPIPE_SZ, 4096)  # the smallest pipe, filled: the edge's next line blocks
    os.set_blocking(write_end, False)
    with contextlib.suppress(BlockingIOError):
        while True:
            os.write(write_end, b"earlier output nobody read\n")
    os.set_blocking(write_end, True)
    proc = subprocess.Popen(iorthand_cmd("edge", "--config", str(config)), stdout=subprocess.DEVNULL,
                            stderr=write_end)
    os.close(write_end)
    try:
        op = operator_factory(ROBOT_ID)
        op.wait_for_state(timeout=30.0)
        assert op.acquire().ok
        op.start()
        for _ in range(3):  # presses and releases, each stopped by its release
            op.set_twist([0.004, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)
            wait_until(lambda: any(op.robot_state.commanded), 5.0, message="the robot moving")
            op.set_twist([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=False)
            wait_until(lambda: not any(op.robot_state.commanded), 5.0, message="the robot stopped on release")
        assert proc.poll() is None
        said = b""
        os.set_blocking(read_end, False)  # read again: the lines kept come out
        deadline = time.monotonic() + 10.0
        while b"control granted to 'op1'" not in said and time.monotonic() < deadline:
            try:
                said += os.read(read_end, 65536)
            except BlockingIOError:
                time.sleep(0.05)
        assert b"edge agent 'sim1' up" in said and b"control granted to 'op1'" in said, said[-2000:]
    finally:
        terminate(proc)
        os.close(read_end)
