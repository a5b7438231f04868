"""What a person at the UR's teach pendant can do while the edge drives, against the REAL ur_rtde library and the
UR controller emulator (in a process of its own, as in tests/test_ur_backend.py): the speed slider, the
installation's TCP and payload, and the modes that stop the arm (safeguard stop, e-stop, power off, local control,
a stopped program, reduced mode). The pendant itself is the emulator's control socket and its dashboard port.
A program stopped from outside the edge and local control take the robot over: the driver holds back until the
edge is armed again (``allow_restart``, what ``iorthand arm`` leads to; the agent's side in tests/test_ur_stack.py).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import re
import signal
import time
from collections.abc import Callable

import numpy as np
import pytest

pytest.importorskip("rtde_control", reason="ur-rtde is not installed on this platform (pip install ur-rtde==1.6.5)")

from iorthand_edge.robots.base import RobotFault, RobotReading
from iorthand_edge.robots.ur import (
    LOCAL_TAKEOVER,
    PROGRAM_STOPPED_OUTSIDE,
    URRobot,
    WriteTimeline,
    foreign_program,
    installation_mismatch,
    program_running,
)
from iorthand_edge.ur_emulator.arm import ArmModel
from tests.conftest import Emulator, ur_dashboard
from tests.test_ur_backend import cycle, healthy, until, wait_emu

pytestmark = pytest.mark.serial  # the controller's watchdog and the link timeout are real-time bounds (see test_ur_backend)

PROBE_TCP = [0.0, 0.0, 0.2, 0.0, 0.0, 0.0]  # a probe tip 200 mm along the flange's z


@pytest.fixture
def make_robot(make_robot: Callable[..., URRobot]) -> Callable[..., URRobot]:
    """conftest's, quick to give up and to reconnect (the pendant's modes come and go within a test)."""
    return functools.partial(make_robot, connect_timeout=3.0, reconnect_max_s=0.5)




# ------------------------------------------------------------------------------------------------ speed slider


def test_emulated_arm_runs_speedl_at_the_speed_sliders_fraction() -> None:
    """A controller scales every motion by the pendant's slider: speedl 20 mm/s at 30 % moves at 6 mm/s."""
    arm = ArmModel("ur5e")
    arm.speed_fraction = 0.3
    x0 = arm.pose[0]
    arm.speedl([0.02, 0, 0, 0, 0, 0], 10.0)
    for _ in range(500):  # 1 s at 500 Hz
        arm.step(0.002)
    assert arm.twist[0] == pytest.approx(0.006)
    assert arm.pose[0] - x0 == pytest.approx(0.006, abs=2e-4)  # minus the 0.6 ms ramp
    arm.speed_fraction = 1.0  # back at 100 %: the commanded speed, no jump in between
    arm.step(0.002)
    assert arm.twist[0] == pytest.approx(0.02)


def test_speed_slider_below_100_is_reported_and_applied_twist_is_what_the_arm_does(
        emu: Emulator, make_robot: Callable[..., URRobot], caplog: pytest.LogCaptureFixture) -> None:
    emu.set_speed_slider(fraction=0.3)
    robot = make_robot()
    with caplog.at_level(logging.WARNING, logger="iorthand.edge.ur"):
        robot.connect()
        reading, _ = until(robot, healthy, 2.0, "a healthy state")
    # At start: a warning that names the slider, and the mode on every state/robot while it stays there.
    assert any("speed slider at 30 %" in r.getMessage() for r in caplog.records), caplog.text
    assert "speed 30%" in reading.mode
    reading = cycle(robot, 0.5, [0.02, 0, 0, 0, 0, 0], acceleration=0.5)
    applied = robot.send_twist(np.array([0.02, 0, 0, 0, 0, 0]), 0.5)
    assert applied[0] == pytest.approx(0.006)  # the applied echo carries what the arm does, not 20 mm/s
    assert emu.status()["twist"][0] == pytest.approx(0.006)
    assert reading.tcp_speed[0] == pytest.approx(0.006, abs=1e-4)
    # Set back to 100 % on the pendant: the mode says nothing more, commands apply in full.
    emu.set_speed_slider(fraction=1.0)
    reading, _ = until(robot, lambda r: "speed" not in r.mode, 2.0, "the mode without the slider")
    cycle(robot, 0.3, [0.02, 0, 0, 0, 0, 0], acceleration=0.5)
    assert robot.send_twist(np.array([0.02, 0, 0, 0, 0, 0]), 0.5)[0] == pytest.approx(0.02)
    # Lowered while driving: warned again.
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="iorthand.edge.ur"):
        emu.set_speed_slider(fraction=0.5)
        until(robot, lambda r: "speed 50%" in r.mode, 2.0, "the slider at 50 % in the mode")
    assert any("speed slider at 50 %" in r.getMessage() for r in caplog.records), caplog.text
    robot.stop(0.5)


# ------------------------------------------------------------------------------------------------ TCP and payload


def installation_config(**overrides: object) -> dict[str, object]:
    return {"tcp_offset": PROBE_TCP, "tcp_tolerance_m": 0.001, "tcp_tolerance_rad": 0.01, "payload_kg": 1.2,
            "payload_tolerance_kg": 0.05, **overrides}


def test_installation_mismatch_names_both_values() -> None:
    assert installation_mismatch(installation_config(), PROBE_TCP, 1.2) == ""
    assert installation_mismatch(installation_config(tcp_offset=None, payload_kg=None), [0.0] * 6, 0.0) == ""
    why = installation_mismatch(installation_config(), [0.0, 0.0, 0.15, 0.0, 0.0, 0.0], 1.2)
    assert "[0.0000, 0.0000, 0.1500" in why and "[0.0000, 0.0000, 0.2000" in why and "50.0 mm" in why
    assert "differs from robot.payload_kg" not in why
    why = installation_mismatch(installation_config(), [0.0, 0.0, 0.2, 0.0, 0.0, 0.1], 0.0)
    assert "5.7°" in why and "payload 0.000 kg differs from robot.payload_kg 1.200 kg" in why


def test_controller_with_another_tcp_or_payload_is_refused_at_connect(emu: Emulator,
                                                                      make_robot: Callable[..., URRobot]) -> None:
    emu.set_tcp(offset=[0.0, 0.0, 0.15, 0.0, 0.0, 0.0])  # the installation still has last week's gripper
    emu.set_payload(mass=1.2)
    robot = make_robot(tcp_offset=PROBE_TCP, payload_kg=1.2)
    with pytest.raises(RobotFault, match=r"TCP offset \[0\.0000, 0\.0000, 0\.1500.*goto\.tcp_offset \[0\.0000, 0\.0000, "
                                         r"0\.2000"):
        robot.connect()
    # No control script is left running on the controller after the refusal.
    wait_emu(lambda: emu.status()["runtime_state"] == "STOPPED", 2.0, "the script stopped")
    emu.set_tcp(offset=PROBE_TCP)
    emu.set_payload(mass=0.4)
    with pytest.raises(RobotFault, match=r"payload 0\.400 kg differs from robot\.payload_kg 1\.200 kg"):
        make_robot(tcp_offset=PROBE_TCP, payload_kg=1.2).connect()
    emu.set_payload(mass=1.2)
    robot = make_robot(tcp_offset=PROBE_TCP, payload_kg=1.2)
    robot.connect()
    assert robot.installation == (pytest.approx(PROBE_TCP), pytest.approx(1.2))


def counting_spawns(robot: URRobot, monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """How many driver children ``robot`` starts from now on (each one connection attempt, or one re-check)."""
    spawns = [0]
    spawn = robot._spawn

    def counted() -> None:
        spawns[0] += 1
        spawn()

    monkeypatch.setattr(robot, "_spawn", counted)
    return spawns


def scripts_uploaded(emu: Emulator) -> int:
    return emu.status()["counters"].get("scripts_received_30003", 0)


def theirs_plays_untouched(emu: Emulator, scripts: int) -> None:
    """The person's program still plays, and the edge uploaded nothing over it since ``scripts`` were counted."""
    status = emu.status()
    assert status["program"] == "/programs/palletizing.urp" and status["runtime_state"] == "PLAYING"
    assert scripts_uploaded(emu) == scripts


def test_a_mismatched_installation_gets_no_script_and_connects_once_it_is_set_right(
        emu: Emulator, make_robot: Callable[..., URRobot], caplog: pytest.LogCaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The controller still has last week's gripper. RTDE tells its TCP offset and payload before any upload: the
    driver uploads nothing onto it (each upload starts and stops a program on the pendant), says the mismatch once
    with both values, re-checks at every reconnect, and connects once the installation is set right, with no
    restart of the edge."""
    emu.set_tcp(offset=[0.0, 0.0, 0.15, 0.0, 0.0, 0.0])
    emu.set_payload(mass=0.4)
    robot = make_robot(tcp_offset=PROBE_TCP, payload_kg=1.2)  # reconnects within 0.5 s
    with caplog.at_level(logging.ERROR, logger="iorthand.edge.ur"):
        with pytest.raises(RobotFault) as refusal:
            robot.connect()
        why = str(refusal.value)
        assert "TCP offset [0.0000, 0.0000, 0.1500" in why and "goto.tcp_offset [0.0000, 0.0000, 0.2000" in why
        assert "payload 0.400 kg differs from robot.payload_kg 1.200 kg" in why
        spawns = counting_spawns(robot, monkeypatch)
        end = time.monotonic() + 4.0
        while time.monotonic() < end:  # several reconnect periods: the same reason, and no upload
            reading = robot.read_state()
            assert reading.fault == why[:200] and not reading.connected and not reading.takeover
            assert scripts_uploaded(emu) == 0
            time.sleep(robot.control_period)
    assert spawns[0] >= 2  # re-checked, not given up
    said = [r.getMessage() for r in caplog.records if "differs from" in r.getMessage()]
    assert len(said) == 1 and "payload 0.400 kg" in said[0] and "0.1500" in said[0], said
    assert not any("rtde_control" in e for e in emu.status()["events"])  # the pendant saw no program come and go
    emu.set_tcp(offset=PROBE_TCP)  # set right on the pendant
    emu.set_payload(mass=1.2)
    until(robot, healthy, 10.0, "the connection once the installation matches")
    assert emu.status()["program"] == "rtde_control"
    assert robot.installation == (pytest.approx(PROBE_TCP), pytest.approx(1.2))


def test_unchecked_installation_is_warned_with_the_controllers_values(emu: Emulator,
                                                                      make_robot: Callable[..., URRobot],
                                                                      caplog: pytest.LogCaptureFixture) -> None:
    emu.set_tcp(offset=[0.0, 0.0, 0.15, 0.0, 0.0, 0.0])
    with caplog.at_level(logging.WARNING, logger="iorthand.edge.ur"):
        make_robot().connect()
    assert "goto.tcp_offset is not set" in caplog.text and "[0.0000, 0.0000, 0.1500" in caplog.text
    assert "robot.payload_kg is not set" in caplog.text


# ------------------------------------------------------------------------------------------------ pendant modes


def stays_still(robot: URRobot, emu: Emulator, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        robot.read_state()
        assert emu.status()["twist"] == [0.0] * 6
        time.sleep(0.02)


def refuses(robot: URRobot, words: str) -> RobotReading:
    reading, _ = until(robot, lambda r: words in r.fault, 3.0, f"a fault saying {words!r}")
    with pytest.raises(RobotFault, match=re.escape(words)):
        robot.send_twist(np.array([0.02, 0, 0, 0, 0, 0]), 0.5)
    return reading


@pytest.mark.parametrize(("enter", "fault", "leave"), [
    ("safeguard", "safeguard stop: a safeguard input", "safeguard"),
    ("estop", "robot emergency stop: release the emergency stop button", "estop"),
    ("power_off", "robot not running (power off): power it on", "power_on"),
    ("program_stop_local", "the person at the robot has it; arm again at the edge", "remote"),
])
def test_pendant_mode_stops_says_what_to_do_and_nothing_moves_after_it_is_undone(
        emu: Emulator, make_robot: Callable[..., URRobot], enter: str, fault: str, leave: str) -> None:
    robot = make_robot()
    robot.connect()
    cycle(robot, 0.3, [0.02, 0, 0, 0, 0, 0])
    assert emu.status()["twist"][0] == pytest.approx(0.02)
    if enter == "safeguard":
        emu.set_safety_mode(mode="SAFEGUARD_STOP", reason="light curtain")
    elif enter == "estop":
        emu.emergency_stop(reason="pendant button")
    elif enter == "power_off":
        assert ur_dashboard(emu.host, "power off") == "Powering off"
    else:  # the person stops the program and takes local control, to jog by hand
        emu.set_remote_control(on=False)
        emu.stop_program()
    refuses(robot, fault)
    wait_emu(lambda: emu.status()["motion"] == "idle", 2.0, "the arm at rest")
    stays_still(robot, emu, 0.5)
    assert fault in robot.read_state().fault  # still refused: nothing was undone yet
    if leave == "safeguard":
        emu.set_safety_mode(mode="NORMAL", reason="reset")
    elif leave == "estop":
        emu.release_emergency_stop()
        refuses(robot, "robot not running (idle)")  # released, but the brakes are on
        assert ur_dashboard(emu.host, "power on") == "Powering on"
        assert ur_dashboard(emu.host, "brake release") == "Brake releasing"
    elif leave == "power_on":
        assert ur_dashboard(emu.host, "power on") == "Powering on"
        assert ur_dashboard(emu.host, "brake release") == "Brake releasing"
    else:
        emu.set_remote_control(on=True)
        assert robot.read_state().takeover  # held: no script of the edge's until it is armed again on site
        robot.allow_restart()
    # Undone: the driver reconnects (a new script) and the arm stays still; moving needs a new command, which the
    # supervisor allows only after a re-acquire and a fresh press (tests/test_ur_stack.py).
    until(robot, healthy, 10.0, "the reconnect")
    stays_still(robot, emu, 0.3)


def test_reduced_mode_is_shown_and_motion_goes_on(emu: Emulator, make_robot: Callable[..., URRobot]) -> None:
    robot = make_robot()
    robot.connect()
    emu.set_safety_mode(mode="REDUCED", reason="safety plane")
    reading, _ = until(robot, lambda r: "reduced" in r.mode, 2.0, "reduced in the mode")
    assert not reading.fault
    cycle(robot, 0.3, [0.02, 0, 0, 0, 0, 0])
    assert emu.status()["twist"][0] == pytest.approx(0.02)
    robot.stop(0.5)


# ------------------------------------------------------------------------------------------------ taken over at the robot


def held_without_a_script(robot: URRobot, emu: Emulator, words: str, seconds: float) -> None:
    """For ``seconds``: the takeover is the reason, and no script of the edge's runs on the controller (the driver
    re-uploaded one within ~1 s before it held back)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        reading = robot.read_state()
        assert words in reading.takeover and words in reading.fault
        assert emu.status()["program"] is None
        time.sleep(0.02)


def test_program_stopped_on_the_pendant_holds_the_driver_until_the_edge_is_armed_again(
        emu: Emulator, make_robot: Callable[..., URRobot]) -> None:
    robot = make_robot()
    robot.connect()
    cycle(robot, 0.3, [0.02, 0, 0, 0, 0, 0])
    assert ur_dashboard(emu.host, "stop") == "Stopped"  # the Stop button of the pendant (or a dashboard client)
    reading, _ = until(robot, lambda r: bool(r.takeover), 3.0, "the takeover")
    assert reading.takeover == PROGRAM_STOPPED_OUTSIDE and reading.fault == PROGRAM_STOPPED_OUTSIDE
    refuses(robot, "the person at the robot has it")
    wait_emu(lambda: emu.status()["motion"] == "idle", 2.0, "the arm at rest")
    held_without_a_script(robot, emu, "stopped on the teach pendant", 2.5)
    robot.allow_restart()  # armed again at the edge: the person is done
    until(robot, healthy, 10.0, "the reconnect")
    assert not robot.read_state().takeover
    stays_still(robot, emu, 0.3)


def stall_until_the_watchdog_stops_the_program(robot: URRobot, emu: Emulator) -> None:
    """The driver child stopped (SIGSTOP) until the controller's watchdog stops the edge's program, as a vCPU taken
    away does; then let go."""
    assert robot._proc is not None
    os.kill(robot._proc.pid, signal.SIGSTOP)
    try:
        wait_emu(lambda: emu.status()["program"] is None, 2.0, "the watchdog stopping the program")
    finally:
        os.kill(robot._proc.pid, signal.SIGCONT)


def test_watchdog_expiry_on_the_edges_own_stall_reconnects_without_a_takeover(
        emu: Emulator, make_robot: Callable[..., URRobot]) -> None:
    """The driver (and the agent's side: this test does not read meanwhile) stalls for 0.3 s, as a vCPU taken away
    does: the controller's watchdog stops the program on the edge's account. Today's recovery, no disarm."""
    robot = make_robot()
    robot.connect()
    cycle(robot, 0.3)
    stall_until_the_watchdog_stops_the_program(robot, emu)
    assert any("RTDE watchdog" in e for e in emu.status()["events"])
    takeovers: list[str] = []

    def back(r: RobotReading) -> bool:
        takeovers.append(r.takeover)
        return healthy(r)

    until(robot, back, 10.0, "the reconnect")
    assert not any(takeovers)


def test_write_timeline_tells_a_late_silence_around_a_stop() -> None:
    """The driver's own measure, on a simulated clock: the watchdog's period is 100 ms, a silence of 80 ms or more
    may have expired it."""
    writes = WriteTimeline(0.08, now=0.0)
    for t in range(1, 50):  # kicks every 8 ms, each call taking 1 ms
        writes.wrote(t * 0.008, t * 0.008 + 0.001)
    assert not writes.late_between(0.2, 0.4)
    writes.wrote(0.5, 0.5 + 0.001)  # 0.5 - 0.392: a 109 ms silence, ended at 0.501
    writes.wrote(0.508, 0.509)
    assert writes.late_between(0.45, 0.55) and not writes.late_between(0.52, 0.55)
    assert writes.late_between(0.52, 0.6)  # nothing written since 0.508: a silence of 92 ms going on


def drive_until_takeover(robot: URRobot, seconds: float) -> RobotReading:
    """Command motion every control period, as the agent does, until the driver reports a takeover (or ``seconds``
    pass); the last reading."""
    end = time.monotonic() + seconds
    reading = robot.read_state()
    while not reading.takeover and time.monotonic() < end:
        with contextlib.suppress(RobotFault):
            robot.send_twist(np.array([0.02, 0, 0, 0, 0, 0]), 0.5)
        time.sleep(robot.control_period)
        reading = robot.read_state()
    return reading


def test_local_control_while_driving_stops_the_arm_and_holds_the_driver(
        emu: Emulator, make_robot: Callable[..., URRobot]) -> None:
    robot = make_robot()
    robot.connect()
    cycle(robot, 0.3, [0.02, 0, 0, 0, 0, 0])
    emu.set_remote_control(on=False)  # the pendant's switch; the program goes on running, RTDE has no bit for it
    # Seen within the dashboard's poll (1 s) while the edge still commands motion; then refused.
    reading = drive_until_takeover(robot, 3.0)
    assert reading.takeover == LOCAL_TAKEOVER and reading.fault == LOCAL_TAKEOVER
    refuses(robot, "switched to local control")
    wait_emu(lambda: emu.status()["motion"] == "idle", 2.0, "the arm at rest")
    wait_emu(lambda: emu.status()["program"] is None, 2.0, "the edge's script stopped by the driver")
    assert any("stopScript" in e or "stopped" in e for e in emu.status()["events"][-5:])
    held_without_a_script(robot, emu, "switched to local control", 1.5)
    emu.set_remote_control(on=True)
    held_without_a_script(robot, emu, "switched to local control", 1.0)  # back in remote: still the edge's arming
    robot.allow_restart()
    until(robot, healthy, 10.0, "the reconnect")
    stays_still(robot, emu, 0.3)


def test_a_program_played_on_the_pendant_takes_over_and_the_edge_leaves_it_running(
        emu: Emulator, make_robot: Callable[..., URRobot]) -> None:
    """Somebody at the robot loads and plays a program of their own while the edge's script runs: the controller runs
    theirs instead, and RTDE still says "program running". The edge sees another program named on the dashboard,
    disarms with that name, and neither stops their program nor uploads its script over it until armed again."""
    robot = make_robot()
    robot.connect()
    cycle(robot, 0.3, [0.02, 0, 0, 0, 0, 0])
    scripts = scripts_uploaded(emu)
    assert ur_dashboard(emu.host, "load /programs/palletizing.urp") == "Loading program: /programs/palletizing.urp"
    assert ur_dashboard(emu.host, "play") == "Starting program"
    assert emu.status()["program"] == "/programs/palletizing.urp"
    # Seen within the dashboard's poll (1 s) while the edge still commands (speedL into registers nobody reads) and
    # stops (a speedStop that their program never answers).
    reading = drive_until_takeover(robot, 3.0)
    robot.stop(0.5)
    reading, _ = until(robot, lambda r: bool(r.takeover), 2.0, "the takeover")
    assert reading.takeover == foreign_program("/programs/palletizing.urp") == reading.fault
    refuses(robot, "another program (/programs/palletizing.urp) was started on the teach pendant")
    end = time.monotonic() + 2.5
    while time.monotonic() < end:  # theirs runs on: the edge stopped nothing and uploaded nothing over it
        reading = robot.read_state()
        assert reading.takeover == foreign_program("/programs/palletizing.urp")
        theirs_plays_untouched(emu, scripts)
        time.sleep(0.02)
    assert ur_dashboard(emu.host, "stop") == "Stopped"  # the person is done
    held_without_a_script(robot, emu, "another program", 1.0)
    robot.allow_restart()  # armed again at the edge
    until(robot, healthy, 10.0, "the reconnect")
    assert not robot.read_state().takeover
    stays_still(robot, emu, 0.3)


def test_a_reconnect_after_a_fault_does_not_upload_over_a_program_played_meanwhile(
        emu: Emulator, make_robot: Callable[..., URRobot]) -> None:
    """The driver stalls (a vCPU taken away: the controller's watchdog stops the script, the agent kills the driver)
    and, before the reconnect, somebody plays a program of their own: the new driver must not stop it by uploading
    the edge's script. It holds with the program's name instead."""
    robot = make_robot()
    robot.connect()
    cycle(robot, 0.3)
    until(robot, lambda r: robot._script_name is not None, 3.0, "the dashboard's name for the script")
    stall_until_the_watchdog_stops_the_program(robot, emu)
    until(robot, lambda r: robot._phase == "down", 3.0, "the agent ending the stalled driver")
    scripts = scripts_uploaded(emu)
    assert ur_dashboard(emu.host, "load /programs/palletizing.urp") == "Loading program: /programs/palletizing.urp"
    assert ur_dashboard(emu.host, "play") == "Starting program"
    reading, _ = until(robot, lambda r: bool(r.takeover), 5.0, "the takeover")
    assert reading.takeover == foreign_program("/programs/palletizing.urp")
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        assert robot.read_state().takeover
        theirs_plays_untouched(emu, scripts)
        time.sleep(0.02)
    assert ur_dashboard(emu.host, "stop") == "Stopped"  # the person is done
    held_without_a_script(robot, emu, "another program", 0.5)
    robot.allow_restart()  # and arms again at the edge
    until(robot, healthy, 10.0, "the reconnect")
    assert emu.status()["program"] == "rtde_control"
    stays_still(robot, emu, 0.3)


def test_arming_while_their_program_still_plays_waits_for_it_to_stop_without_a_retry_storm(
        emu: Emulator, make_robot: Callable[..., URRobot], caplog: pytest.LogCaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Somebody at the robot played a program of their own (a takeover), and the edge is armed again (``iorthand
    arm``) while it still plays. Uploading the edge's script would stop it (ur_rtde writes a stop that their program
    never answers, waits 3 s, then stops it on the dashboard): before, each attempt ended as "did not answer within
    3 s (hung or half-open connection?)", again and again. Now one reason, said once, tells what to do; nothing is
    uploaded and their program plays on; once it is stopped on the pendant the edge connects, with no second arm."""
    robot = make_robot()
    robot.connect()
    cycle(robot, 0.3)
    assert ur_dashboard(emu.host, "load /programs/palletizing.urp") == "Loading program: /programs/palletizing.urp"
    assert ur_dashboard(emu.host, "play") == "Starting program"
    assert drive_until_takeover(robot, 3.0).takeover == foreign_program("/programs/palletizing.urp")
    until(robot, lambda r: robot._phase == "down", 3.0, "the held driver gone")
    scripts = scripts_uploaded(emu)
    spawns = counting_spawns(robot, monkeypatch)
    caplog.clear()
    with caplog.at_level(logging.ERROR, logger="iorthand.edge.ur"):
        robot.allow_restart()  # armed at the edge while their program still plays
        faults = set()
        end = time.monotonic() + 4.0
        while time.monotonic() < end:
            reading = robot.read_state()
            assert not reading.connected and not reading.takeover  # armed: no takeover; not connected: a fault
            faults.add(reading.fault)
            theirs_plays_untouched(emu, scripts)
            time.sleep(robot.control_period)
    why = program_running("/programs/palletizing.urp")
    assert why == ("another program (/programs/palletizing.urp) is running on the controller: stop it on the teach "
                   "pendant first; the edge connects once it has stopped")
    # The takeover's reason until the first check answered, then this one only.
    assert why in faults and faults <= {why, foreign_program("/programs/palletizing.urp")}, faults
    assert spawns[0] >= 2
    said = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert said == [f"UR driver fault: {why}"], said
    assert ur_dashboard(emu.host, "stop") == "Stopped"  # the person at the robot stops theirs
    until(robot, healthy, 10.0, "the connection once their program stopped")
    assert emu.status()["program"] == "rtde_control"
    stays_still(robot, emu, 0.3)


def test_a_silent_dashboard_is_no_fault_and_the_mode_says_so(
        emu: Emulator, make_robot: Callable[..., URRobot], caplog: pytest.LogCaptureFixture) -> None:
    robot = make_robot()
    robot.connect()
    with caplog.at_level(logging.WARNING, logger="iorthand.edge.ur"):
        emu.set_dashboard_silent(on=True)
        reading, _ = until(robot, lambda r: "no dashboard" in r.mode, 5.0, "the mode saying so")
        assert not reading.fault and reading.connected
        cycle(robot, 1.5, [0.02, 0, 0, 0, 0, 0])  # motion goes on; asked again meanwhile, logged once
        assert emu.status()["twist"][0] == pytest.approx(0.02)
    warnings = [r.getMessage() for r in caplog.records if "does not answer" in r.getMessage()]
    assert len(warnings) == 1 and "local control on the teach pendant cannot be seen" in warnings[0], caplog.text
    emu.set_dashboard_silent(on=False)
    until(robot, lambda r: "no dashboard" not in r.mode, 5.0, "the mode without it")
    robot.stop(0.5)


def test_safeguard_stop_pauses_the_program_and_nothing_moves_when_it_resumes(
        emu: Emulator, make_robot: Callable[..., URRobot]) -> None:
    """A UR pauses its program on a safeguard stop and resumes it by itself at the reset, with its registers as
    they were: the edge must not have left a speedL there, and reconnects with a fresh script."""
    robot = make_robot()
    robot.connect()
    cycle(robot, 0.3, [0.02, 0, 0, 0, 0, 0])
    emu.set_safety_mode(mode="SAFEGUARD_STOP", reason="light curtain")
    reading = refuses(robot, "safeguard stop: a safeguard input")
    assert reading.mode.startswith("safeguard stop")
    wait_emu(lambda: emu.status()["motion"] == "idle", 2.0, "the arm at rest")
    assert emu.status()["runtime_state"] == "PAUSED" and emu.status()["program"] is not None
    stays_still(robot, emu, 0.3)
    emu.set_safety_mode(mode="NORMAL", reason="reset")
    end = time.monotonic() + 1.0
    while time.monotonic() < end:  # the paused script resumed (or was replaced): still nothing moves
        robot.read_state()
        assert emu.status()["twist"] == [0.0] * 6
        time.sleep(0.01)
    assert any("resumed: safeguard reset" in e for e in emu.status()["events"])
    until(robot, healthy, 10.0, "the reconnect")
    assert not robot.read_state().takeover
    stays_still(robot, emu, 0.3)
