"""The UR backend (``URRobot``) with the REAL ur_rtde library against the UR controller emulator (issue 5).

The emulator runs in this process (its own threads, on a loopback address of its own: ur_rtde hard-codes the
ports); the backend runs ur_rtde in its spawned driver child, as in production. Faults are injected through
the emulator's methods. The tests assert behaviour; the few times they print are measurements, and the only
time bound asserted is the issue's link-loss detection (100 ms, against ~10 ms measured).
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rtde_control", reason="ur-rtde is not installed on this platform (pip install ur-rtde==1.6.5)")

from iorthand_edge.robots.base import RobotFault, RobotReading
from iorthand_edge.robots.config import URRobotConfig
from iorthand_edge.robots.ur import DRIVER_PRIORITY, URRobot
from iorthand_edge.supervisor import SafetyConfig
from iorthand_edge.ur_emulator import HOME_POSE, HOME_Q
from iorthand_edge.ur_emulator.process import UR_PORTS, free_loopback_host
from tests.conftest import Emulator
from tests.ur_rt_kernel_probe import policies

# serial: the test's own loop is the agent's, and the controller's watchdog stops the program if it misses 100 ms;
# a lost link must be reported within the driver's 100 ms link timeout.
pytestmark = pytest.mark.serial


def cycle(robot: URRobot, seconds: float, twist: list[float] | None = None, acceleration: float = 0.5) -> RobotReading:
    """Run the agent's side for ``seconds`` at the control rate: read, and send ``twist`` if given."""
    end = time.monotonic() + seconds
    reading = robot.read_state()
    while time.monotonic() < end:
        if twist is not None:
            robot.send_twist(np.array(twist), acceleration)
        time.sleep(robot.control_period)
        reading = robot.read_state()
    return reading


def until(robot: URRobot, pred: Callable[[RobotReading], bool], timeout: float, what: str) -> tuple[RobotReading, float]:
    """Read at the control rate until ``pred``; returns the reading and the time it took."""
    t0 = time.monotonic()
    while True:
        reading = robot.read_state()
        if pred(reading):
            return reading, time.monotonic() - t0
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}; last fault {reading.fault!r}")
        time.sleep(robot.control_period)


def wait_emu(pred: Callable[[], bool], timeout: float, what: str) -> float:
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.005)
    return time.monotonic() - t0


def healthy(r: RobotReading) -> bool:
    return r.connected and not r.fault


def test_state_speedl_and_stop(emu: Emulator, make_robot: Callable[..., URRobot]) -> None:
    robot = make_robot()
    robot.connect()
    emu.set_force(wrench=[1.0, -2.0, 10.0, 0.1, 0.0, 0.0])
    # Right after connecting the state stream may show the script as not yet running for a period: wait for both.
    reading, _ = until(robot, lambda r: healthy(r) and r.tcp_force[2] == pytest.approx(10.0), 2.0, "the force")
    assert reading.mode == "running"
    assert list(reading.tcp_pose) == pytest.approx(list(HOME_POSE), abs=1e-9)
    assert list(reading.q) == pytest.approx(list(HOME_Q))
    assert list(reading.tcp_force) == pytest.approx([1.0, -2.0, 10.0, 0.1, 0.0, 0.0])
    status = emu.status()
    assert status["watchdog"] == ["input_int_register_0", 10.0]  # set by the driver after connecting
    robot_time = reading.robot_time

    reading = cycle(robot, 0.5, [0.02, 0, 0, 0, 0, 0], acceleration=0.5)
    assert reading.robot_time > robot_time
    assert emu.status()["twist"][0] == pytest.approx(0.02)
    assert reading.tcp_speed[0] == pytest.approx(0.02)
    assert reading.tcp_pose[0] > HOME_POSE[0] + 0.005  # ~10 mm in 0.5 s
    robot.stop(0.5)
    reading, _ = until(robot, lambda r: not np.any(r.tcp_speed), 2.0, "the tool at rest")
    assert healthy(reading)  # a blocking speedStop in the driver must not look like a hung driver
    assert emu.status()["motion"] == "idle"
    # The watchdog kept being kicked while idle: the program still runs after many watchdog periods.
    cycle(robot, 0.5)
    assert emu.status()["runtime_state"] == "PLAYING"


def test_link_drop_detected_at_once_and_reconnect_does_not_resume(emu: Emulator,
                                                                  make_robot: Callable[..., URRobot]) -> None:
    robot = make_robot()
    robot.connect()
    cycle(robot, 0.3, [0.02, 0, 0, 0, 0, 0])
    t0 = time.monotonic()
    emu.drop_link()
    reading, dt = until(robot, lambda r: bool(r.fault), 2.0, "the link fault")
    print(f"link drop detected by URRobot after {1000 * dt:.1f} ms: {reading.fault}")
    assert "link" in reading.fault and not reading.connected
    assert time.monotonic() - t0 < robot.config.link_timeout  # the 100 ms (measured ~10 ms)
    with pytest.raises(RobotFault):
        robot.send_twist(np.array([0.02, 0, 0, 0, 0, 0]), 0.5)
    # Nobody kicks the watchdog any more: the controller stops the program and the arm (second layer).
    wait_emu(lambda: emu.status()["motion"] == "idle", 2.0, "the controller's watchdog to stop the arm")
    assert any("watchdog" in e for e in emu.status()["events"])
    emu.restore_link()
    reading, dt = until(robot, healthy, 10.0, "the reconnect")
    print(f"reconnected {1000 * dt:.0f} ms after the link came back")
    status = emu.status()
    assert status["runtime_state"] == "PLAYING" and status["watchdog"] == ["input_int_register_0", 10.0]
    cycle(robot, 0.3)  # the stale speedL must not come back with the new script
    assert emu.status()["twist"] == [0.0] * 6 and emu.status()["motion"] == "idle"
    cycle(robot, 0.3, [0.0, 0.01, 0, 0, 0, 0])  # and commands work again
    assert emu.status()["twist"][1] == pytest.approx(0.01)


def test_frozen_stream_detected_by_timestamp(emu: Emulator, make_robot: Callable[..., URRobot]) -> None:
    """ur_rtde stays "connected" while a frozen controller streams stale data: only the timestamp shows it."""
    robot = make_robot()
    robot.connect()
    cycle(robot, 0.2)
    emu.freeze(mode="stale")
    reading, dt = until(robot, lambda r: bool(r.fault), 2.0, "the frozen-stream fault")
    print(f"frozen stream detected after {1000 * dt:.0f} ms: {reading.fault}")
    assert "timestamp frozen" in reading.fault
    emu.unfreeze()
    until(robot, healthy, 10.0, "the reconnect")


def test_hung_controller_connect_times_out(emu: Emulator, make_robot: Callable[..., URRobot]) -> None:
    emu.hang()
    robot = make_robot(connect_timeout=1.0)
    t0 = time.monotonic()
    with pytest.raises(RobotFault, match="did not answer within 1 s"):
        robot.connect()
    dt = time.monotonic() - t0
    print(f"hung controller: connect() raised after {dt:.2f} s (connect_timeout 1 s)")
    assert dt < 1.0 + 1.0  # the timeout plus the child's start; never the forever of ur_rtde's constructor
    emu.unhang()


def test_hang_while_up_is_reported_without_blocking(emu: Emulator, make_robot: Callable[..., URRobot]) -> None:
    robot = make_robot(connect_timeout=1.0, reconnect_max_s=0.5)
    robot.connect()
    cycle(robot, 0.2)
    emu.hang()
    slowest, faults, t0 = 0.0, [], time.monotonic()
    while time.monotonic() - t0 < 2.5:  # covers a detection and at least one timed-out reconnect
        c0 = time.monotonic()
        reading = robot.read_state()
        slowest = max(slowest, time.monotonic() - c0)
        if reading.fault and (not faults or faults[-1][1] != reading.fault):
            faults.append((time.monotonic() - t0, reading.fault))
        time.sleep(robot.control_period)
    print(f"hung controller while up: {[(round(t, 3), f) for t, f in faults]}; slowest read_state {1000 * slowest:.1f} ms")
    assert faults and faults[0][0] < 1.0 and ("frozen" in faults[0][1] or "no state" in faults[0][1])
    assert any("did not answer within 1 s" in f for _, f in faults)  # the reconnect attempt timed out
    assert slowest < 0.5  # the agent's loop never waits for the controller
    emu.unhang()
    until(robot, healthy, 10.0, "the reconnect after the hang")


def test_protective_stop_reported_and_never_resumed(emu: Emulator, make_robot: Callable[..., URRobot]) -> None:
    robot = make_robot()
    robot.connect()
    cycle(robot, 0.3, [0.02, 0, 0, 0, 0, 0])
    emu.protective_stop(reason="test")
    # The fault comes from the control stream; the mode from the receive stream, up to a period later.
    until(robot, lambda r: "protective stop" in r.fault and "protective stop" in r.mode, 2.0, "the protective stop")
    with pytest.raises(RobotFault, match="protective stop"):
        robot.send_twist(np.array([0.02, 0, 0, 0, 0, 0]), 0.5)
    wait_emu(lambda: emu.status()["motion"] == "idle", 2.0, "the arm at rest")
    cycle(robot, 0.5)  # still protective-stopped: the fault stays
    assert "protective stop" in robot.read_state().fault
    emu.clear_protective_stop()
    # Cleared: the stopped program takes the driver through a reconnect (new script, watchdog set again)...
    until(robot, healthy, 10.0, "the reconnect after clearing")
    assert emu.status()["watchdog"] == ["input_int_register_0", 10.0]
    cycle(robot, 0.3)
    # ...and nothing moves by itself (the supervisor additionally waits for an operator to re-acquire).
    assert emu.status()["twist"] == [0.0] * 6


def test_program_stop_reconnects_without_replaying_speedl(emu: Emulator,
                                                         make_robot: Callable[..., URRobot]) -> None:
    robot = make_robot()
    robot.connect()
    cycle(robot, 0.3, [0.02, 0, 0, 0, 0, 0])
    emu.stop_program()  # stopped from outside the edge: it holds back until armed again (tests/test_ur_pendant.py)
    until(robot, lambda r: "not running" in r.fault or bool(r.takeover), 2.0, "the program-stop fault")
    until(robot, lambda r: bool(r.takeover), 2.0, "the takeover")
    robot.allow_restart()  # armed again at the edge
    until(robot, healthy, 10.0, "the reconnect")
    for _ in range(30):  # the last speedL is still in the command register: it must never run again
        cycle(robot, 0.01)
        assert emu.status()["twist"] == [0.0] * 6


def test_silent_agent_stops_the_tool(emu: Emulator, make_robot: Callable[..., URRobot]) -> None:
    """The agent's loop stops (hung, not dead): the driver stops the tool and stops kicking the watchdog."""
    robot = make_robot()
    robot.connect()
    cycle(robot, 0.3, [0.02, 0, 0, 0, 0, 0])
    t0 = time.monotonic()
    dt = wait_emu(lambda: emu.status()["motion"] == "idle", 2.0, "the tool at rest without heartbeats")
    print(f"silent agent: tool at rest {1000 * (time.monotonic() - t0):.0f} ms after the last heartbeat")
    assert dt < 2.0


def test_disconnect_stops_motion_and_program(emu: Emulator, make_robot: Callable[..., URRobot]) -> None:
    robot = make_robot()
    robot.connect()
    cycle(robot, 0.3, [0.02, 0, 0, 0, 0, 0])
    robot.disconnect()
    status = emu.status()
    assert status["motion"] == "idle" and status["runtime_state"] == "STOPPED"
    assert "disconnected" in robot.read_state().fault


def test_unreachable_controller_raises_at_once() -> None:
    robot = URRobot(URRobotConfig(host=free_loopback_host(UR_PORTS), connect_timeout=5.0), SafetyConfig().stop_deceleration)
    t0 = time.monotonic()
    with pytest.raises(RobotFault, match="cannot connect"):
        robot.connect()
    assert time.monotonic() - t0 < 5.0
    robot.disconnect()


def test_connect_during_protective_stop_says_why(emu: Emulator, make_robot: Callable[..., URRobot]) -> None:
    emu.protective_stop(reason="test")
    robot = make_robot()
    with pytest.raises(RobotFault, match="protective stop"):
        robot.connect()


def test_the_drivers_command_thread_alone_runs_real_time(emu: Emulator) -> None:
    """The driver's main thread writes the commands and kicks the controller's watchdog: real time, under the
    edge's control loop (at normal priority, two CPU hogs delayed a kick past the 100 ms watchdog in 2 of 3
    minutes of bench_cpu_hogs.py). Its other threads, the reader and ur_rtde's own, stay normal: with them real
    time too the command path's p99 under the hogs rose from 9-25 to 29-67 ms. ``realtime: false`` leaves it all
    normal."""
    safety = SafetyConfig()
    robot = URRobot(URRobotConfig(host=emu.host), safety.stop_deceleration)
    robot.connect()
    cycle(robot, 0.2)  # the driver's loop has run: what it set after saying ready counts too
    try:
        if not robot.driver_priority.startswith("SCHED_FIFO"):
            pytest.skip(f"real time not allowed here: {robot.driver_priority}")
        assert robot._proc is not None
        got = policies(robot._proc.pid)
        assert got.pop(str(robot._proc.pid)) == (os.SCHED_FIFO, DRIVER_PRIORITY)
        assert len(got) >= 2 and set(got.values()) == {(os.SCHED_OTHER, 0)}, got  # the reader and ur_rtde's threads
    finally:
        robot.disconnect()
    plain = URRobot(URRobotConfig(host=emu.host), safety.stop_deceleration, realtime=False)
    plain.connect()
    cycle(plain, 0.2)
    try:
        assert plain.driver_priority == "normal"
        assert plain._proc is not None
        assert set(policies(plain._proc.pid).values()) == {(os.SCHED_OTHER, 0)}
    finally:
        plain.disconnect()



def test_ur_rtdes_threads_stay_normal_on_a_real_time_kernel() -> None:
    """On a PREEMPT_RT kernel (a Pi's, say) ur_rtde by default puts its receive threads, and the thread that calls
    its constructors, at SCHED_FIFO 90: above the edge's control loop and the driver's command thread. The driver
    asks it not to, so the order measured here (the command thread alone at real time) holds on any kernel. This
    kernel is not real time: the probe runs in a mount namespace whose /sys/kernel/realtime reads 1, which is what
    ur_rtde 1.6.5 checks. It shows first that a bare ur_rtde is fooled, so the check on the driver is not vacuous.
    (Without the driver's request, two of its threads ran at SCHED_FIFO 90.)"""
    if os.geteuid() != 0 or shutil.which("unshare") is None:
        pytest.skip("needs root and unshare (a mount namespace)")
    repo = Path(__file__).resolve().parents[1]
    script = ("mount -t tmpfs iorthand-fake-rt /sys/kernel && echo 1 > /sys/kernel/realtime && "
              f"exec {shlex.quote(sys.executable)} -m tests.ur_rt_kernel_probe")
    r = subprocess.run(["unshare", "--mount", "--propagation", "private", "sh", "-c", script], cwd=repo,
                       capture_output=True, text=True, timeout=90)
    if r.returncode != 0 and r.stderr.startswith(("unshare:", "mount:")):
        pytest.skip(f"no mount namespace here: {r.stderr.strip()[:200]}")
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    got = json.loads(r.stdout.strip().splitlines()[-1])
    # ur_rtde's default: its receive thread and the thread that called its constructor at real time, high.
    fooled = [v for v in got["bare_ur_rtde"].values() if v[0] == os.SCHED_FIFO and v[1] > DRIVER_PRIORITY]
    assert len(fooled) >= 2, got
    driver = {int(tid): tuple(v) for tid, v in got["driver"].items()}
    assert got["driver_priority"].startswith("SCHED_FIFO"), got
    assert driver.pop(got["driver_pid"]) == (os.SCHED_FIFO, DRIVER_PRIORITY)
    assert len(driver) >= 3 and set(driver.values()) == {(os.SCHED_OTHER, 0)}, driver  # reader + ur_rtde's two


def test_a_driver_that_stopped_reading_never_blocks_the_agent() -> None:
    """A driver child whose main thread hangs inside ur_rtde (a speedStop waiting for a "done" that a program played
    over the edge's script never writes) stops reading its pipe; at the control rate the pipe filled and the
    agent's next send blocked, freezing its control loop. Here the child's end is a real pipe that nobody reads."""
    from iorthand_edge.robots.ur import send_without_blocking

    agent_end, child_end = mp.Pipe()
    try:
        sent, started = 0, time.monotonic()
        while not (problem := send_without_blocking(agent_end, ("twist", [0.01] * 6, 0.5))):
            sent += 1
            assert time.monotonic() - started < 10.0, "the pipe never filled"
        assert problem == "the UR driver stopped reading its commands (hung inside ur_rtde)"
        assert sent > 10 and time.monotonic() - started < 10.0
        started = time.monotonic()
        assert send_without_blocking(agent_end, ("heartbeat",)) == problem  # at once, not blocked
        assert time.monotonic() - started < 0.5
        while child_end.poll(0):  # the driver reads again: the agent's sends go through
            child_end.recv()
        assert send_without_blocking(agent_end, ("heartbeat",)) == ""
        child_end.close()
        assert send_without_blocking(agent_end, ("heartbeat",)) == "UR driver pipe broken"
    finally:
        agent_end.close()
