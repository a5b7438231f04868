"""Wall clocks that step during a session (NTP after a boot without RTC, after a long disconnection, ``date -s``).

The wire carries wall times (every message's ``t``); processes time things on the monotonic clock. A real edge
(``iorthand edge``, configs/edge-sim.yaml without its camera and video) and a real operator client drive through a
real router while one side's wall clock steps, as NTP steps it: only CLOCK_REALTIME moves, the monotonic clock
runs on.

The step is injected by a 40-line LD_PRELOAD library built here with the C compiler (``WALLSTEP_C``): it adds an
offset, read from a shared 8-byte file on every call, to CLOCK_REALTIME (``time.time()``, ``gettimeofday``,
Rust's ``SystemTime``). Debian's libfaketime 0.9.10 cannot do this: with its monotonic clock left alone
(``FAKETIME_DONT_FAKE_MONOTONIC=1``), every ``time.sleep`` of Python 3.11 fails with EINVAL (its
``clock_nanosleep`` wrapper), and without that option a step moves the monotonic clock too, which NTP never does.
"""

from __future__ import annotations

import os
import shutil
import struct
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from .conftest import ROOT, iorthand_cmd, stop_process, wait_until

ROBOT_ID = "sim1"

WALLSTEP_C = r"""
#define _GNU_SOURCE
#include <dlfcn.h>
#include <fcntl.h>
#include <stdint.h>
#include <stdlib.h>
#include <sys/mman.h>
#include <sys/time.h>
#include <time.h>
#include <unistd.h>

static volatile const int64_t *offset_ns;  /* mapped from $WALLSTEP_FILE: the wall clock's step, ns */
static int (*real_clock_gettime)(clockid_t, struct timespec *);

__attribute__((constructor)) static void wallstep_init(void) {
    real_clock_gettime = (int (*)(clockid_t, struct timespec *))dlsym(RTLD_NEXT, "clock_gettime");
    const char *path = getenv("WALLSTEP_FILE");
    int fd = path ? open(path, O_RDONLY) : -1;
    if (fd < 0) return;
    void *p = mmap(NULL, sizeof(int64_t), PROT_READ, MAP_SHARED, fd, 0);
    close(fd);
    if (p != MAP_FAILED) offset_ns = p;
}

int clock_gettime(clockid_t clock, struct timespec *ts) {
    if (!real_clock_gettime) wallstep_init();
    int r = real_clock_gettime(clock, ts);
    if (r == 0 && offset_ns && (clock == CLOCK_REALTIME || clock == CLOCK_REALTIME_COARSE)) {
        int64_t ns = (int64_t)ts->tv_sec * 1000000000 + ts->tv_nsec + *offset_ns;
        ts->tv_sec = ns / 1000000000;
        ts->tv_nsec = ns % 1000000000;
    }
    return r;
}

int gettimeofday(struct timeval *tv, void *tz) {
    struct timespec ts;
    (void)tz;
    if (clock_gettime(CLOCK_REALTIME, &ts) != 0) return -1;
    if (tv) { tv->tv_sec = ts.tv_sec; tv->tv_usec = ts.tv_nsec / 1000; }
    return 0;
}

time_t time(time_t *out) {
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    if (out) *out = ts.tv_sec;
    return ts.tv_sec;
}
"""


class WallClock:
    """One process tree's wall clock: ``env`` starts a process on it, ``step(s)`` sets its offset from the real
    wall clock (a step, as NTP makes it; 0 puts it right again)."""

    def __init__(self, library: Path, path: Path) -> None:
        self.path = path
        path.write_bytes(struct.pack("<q", 0))
        self.env = {"LD_PRELOAD": str(library), "WALLSTEP_FILE": str(path)}

    def step(self, seconds: float) -> None:
        fd = os.open(self.path, os.O_WRONLY)
        try:
            os.pwrite(fd, struct.pack("<q", round(seconds * 1e9)), 0)  # 8 aligned bytes: read whole or not at all
        finally:
            os.close(fd)


@pytest.fixture(scope="module")
def wallstep_library(tmp_path_factory: pytest.TempPathFactory) -> Path:
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        pytest.skip("no C compiler to build the wall-clock step library (apt-get install gcc)")
    out = tmp_path_factory.mktemp("wallstep")
    (out / "wallstep.c").write_text(WALLSTEP_C)
    subprocess.run([compiler, "-shared", "-fPIC", "-O2", "-o", str(out / "libwallstep.so"), str(out / "wallstep.c"),
                    "-ldl"], check=True, capture_output=True)
    return out / "libwallstep.so"


def edge_sim_config(router_endpoint: str) -> dict[str, Any]:
    """configs/edge-sim.yaml on the test's router, without its camera and video (they take most of the edge's CPU
    and have no clock of their own in this story)."""
    config = yaml.safe_load((ROOT / "configs" / "edge-sim.yaml").read_text())
    config["zenoh"] = {"mode": "client", "connect": [router_endpoint], "connect_retry_s": 10.0}
    for part in ("video", "perception", "goto"):
        config.pop(part, None)
    return config


@pytest.fixture
def stepped_edge(router_endpoint: str, tmp_path: Path, wallstep_library: Path) -> Iterator[WallClock]:
    """``iorthand edge`` (the simulated robot of configs/edge-sim.yaml) on a wall clock of its own."""
    clock = WallClock(wallstep_library, tmp_path / "edge-clock")
    config = tmp_path / "edge.yaml"
    config.write_text(yaml.safe_dump(edge_sim_config(router_endpoint)))
    proc = subprocess.Popen(iorthand_cmd("--log-level", "warning", "edge", "--config", str(config)),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env={**os.environ, **clock.env})
    yield clock
    stop_process(proc)


def moving(op) -> bool:
    return op.robot_state is not None and bool(np.any(op.robot_state.commanded))


def drive(op) -> None:
    op.wait_for_state(timeout=30.0)
    assert op.acquire().ok
    op.start()
    op.set_twist([0.004, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)
    wait_until(lambda: moving(op), 10.0, message="the robot moving")


def hold_still(op, seconds: float) -> None:
    """The operator keeps the deadman held (the console's input repeats its twist): the robot must not move."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        op.set_twist([0.004, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)
        assert not moving(op), f"the robot moved: {op.safety}"
        time.sleep(0.02)


def refused_for_the_clocks(op, says: str) -> None:
    """Once the robot has stopped: with the deadman held, every command is refused, the operator's log holds a
    line or two about it (not one per command), and the safety status names the clocks."""
    events, echoes = op.event_count, op.echo_count
    hold_still(op, 1.5)
    answered = op.echoes_since(echoes)
    assert answered and not any(e.accepted for e in answered)
    # A line or two: "command is 5000 ms old" until a command names a state stamped after the step, then the
    # clocks (a line per command before: 13-81 distinct lines here).
    refusals = {e.reason for e in op.events_since(events) if e.kind == "refused"}
    assert len(refusals) <= 3, refusals
    assert op.safety.status == "stale_command" and "synchronise the clocks (NTP)" in op.safety.reason, op.safety
    assert says in op.safety.reason, op.safety.reason


def resumes_only_on_a_fresh_press(op) -> None:
    """The clocks agree again: the refusals lasted longer than the resume gap, so the deadman held through them
    moves nothing; a release and a press do."""
    hold_still(op, 1.5)
    wait_until(lambda: op.safety.status == "link_gap" and "press it again" in op.safety.reason, 5.0,
               message="the edge waiting for a fresh press")
    op.set_twist([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=False)
    time.sleep(0.2)
    op.set_twist([0.004, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)
    wait_until(lambda: moving(op), 5.0, message="motion after a fresh press")


@pytest.mark.parametrize(("step", "says"), [(5.0, "behind this robot's (this robot's clock stepped 5000 ms forward)"),
                                            (-5.0, "ahead of this robot's (this robot's clock stepped 5000 ms back)"),
                                            (3600.0, "60 min behind this robot's (this robot's clock stepped 60 min")],
                         ids=["+5s", "-5s", "+1h"])
def test_an_edge_clock_step_stops_the_robot_says_which_clock_and_needs_a_fresh_press(
        stepped_edge: WallClock, operator_factory, step: float, says: str) -> None:
    """Measured before the fix: the robot stopped at the command timeout (~150 ms) and stayed stopped, but the
    safety status said "no command for 150 ms" while commands kept arriving, the reason blamed the operator's
    clock, and it changed with every command's jitter (27-81 distinct lines in the operator's log in 2 s)."""
    op = operator_factory(ROBOT_ID)
    drive(op)
    stepped_edge.step(step)
    wait_until(lambda: not moving(op), 5.0, message="the robot stopped")
    refused_for_the_clocks(op, says)
    stepped_edge.step(0.0)
    resumes_only_on_a_fresh_press(op)


@pytest.mark.parametrize(("step", "says"), [(5.0, "the operator's clock is 5000 ms ahead of this robot's:"),
                                            (-3600.0, "the operator's clock is 60 min behind this robot's:")],
                         ids=["+5s", "-1h"])
def test_an_operator_clock_step_stops_the_robot_says_which_clock_and_needs_a_fresh_press(
        stepped_edge: WallClock, operator_factory, wallstep_library: Path, router_endpoint: str, tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch, step: float, says: str) -> None:
    """The operator's commands leave from its sender process, on a wall clock of its own here (its time stamps
    and the age of the state it shows are what that clock says)."""
    from iorthand.transport import client_config

    clock = WallClock(wallstep_library, tmp_path / "operator-clock")
    for name, value in clock.env.items():
        monkeypatch.setenv(name, value)  # for the sender process the client starts
    op = operator_factory(ROBOT_ID, sender_config=client_config(router_endpoint))
    drive(op)
    clock.step(step)
    wait_until(lambda: not moving(op), 5.0, message="the robot stopped")
    refused_for_the_clocks(op, says)
    assert "this robot's clock stepped" not in op.safety.reason
    clock.step(0.0)
    resumes_only_on_a_fresh_press(op)


def test_an_edge_that_reads_1970_is_named_at_connect(stepped_edge: WallClock, operator_factory) -> None:
    """An edge booted without a real-time clock and without NTP yet: control was granted, and every command the
    operator sent was dropped as malformed (its state age, 56 years, is beyond the protocol's bound), unanswered:
    nothing said why nothing moved. Now the grant is refused with both clocks' readings, in one line."""
    from iorthand_operator.client import ControlRefused

    stepped_edge.step(3600.0 - time.time())
    op = operator_factory(ROBOT_ID)
    op.wait_for_state(timeout=30.0)
    with pytest.raises(ControlRefused) as refused:
        op.acquire()
    said = str(refused.value)
    assert said.startswith("clocks disagree: this robot's reads 1970-01-01 0") and "set the wrong one right (NTP)" in said
    assert "\n" not in said and not said.endswith("…")
    stepped_edge.step(0.0)  # NTP sets it right: control is granted
    wait_until(lambda: op.robot_state.t > time.time_ns() - 10**9, 5.0, message="states stamped by the right clock")
    assert op.acquire().ok


def test_the_state_age_of_a_command_stays_within_the_protocol_when_the_edge_reads_1970() -> None:
    """The command names a state stamped in 1970 by the edge's clock: the age it states, 56 years, was beyond
    TwistCommand.state_age's bound, and the edge dropped such a command as malformed, unanswered. At the bound it
    decodes, and the edge answers with a refusal that names the clocks."""
    from iorthand import keys
    from iorthand.protocol import TwistCommand
    from iorthand.security import auth
    from iorthand_operator.sender import CommandStream

    key = auth.new_key()
    stream = CommandStream(ROBOT_ID, "op1", release_tail=0.3, ui_timeout=0.5)
    now = time.monotonic()
    out = stream.next(now, [0.0] * 6, False, now, False, now, 3600 * 10**9, 1.0, key)
    assert out is not None
    cmd = TwistCommand.decode(out[1])
    assert cmd.view_t == 3600 * 10**9 and cmd.state_age > 30 * 365 * 86400  # (the bound: 1e9 s)
    assert auth.verify(key, auth.context(ROBOT_ID, keys.CMD_TWIST), cmd)


def test_a_wall_clock_step_between_a_commands_receipt_and_its_handling_costs_no_control(
        edge_factory, monkeypatch: pytest.MonkeyPatch) -> None:
    """The edge's wall clock steps 1 h forward after a command arrived and before the control loop took it: the
    command counts as received an hour ago (monotonic), the lease it renews runs out at once, and the next control
    cycle releases the operator's control ("lease expired") although the operator is right there."""
    from iorthand import keys
    from iorthand.protocol import ControlRequest, TwistCommand
    from iorthand.security import auth

    agent = edge_factory(ROBOT_ID)
    with agent.lock:
        grant = agent.supervisor.acquire(ControlRequest(operator="op1").stamp(1), time.monotonic())
    recv_ns, recv_mono = time.time_ns(), time.monotonic()  # as the subscriber stamps its receipt
    cmd = TwistCommand(operator="op1", deadman=False, state_age=0.0).stamp(1, recv_ns)
    payload = auth.seal(grant.key, auth.context(ROBOT_ID, keys.CMD_TWIST), cmd)
    real_time_ns = time.time_ns
    monkeypatch.setattr(time, "time_ns", lambda: real_time_ns() + 3600 * 10**9)  # the step, after the receipt
    try:
        echo = agent.handle_twist(agent.keys.key(keys.CMD_TWIST), payload, recv_ns, recv_mono)
    finally:
        monkeypatch.undo()
    assert echo is not None and echo.accepted, echo
    time.sleep(0.2)  # control cycles
    assert agent.supervisor.owner == "op1", agent.supervisor.reason


def test_the_robots_force_sensor_ages_its_samples_on_the_monotonic_clock(monkeypatch: pytest.MonkeyPatch) -> None:
    """Found by a review: the arm's own force sensor (RobotForceSensor) judged a state's age by the wall clock, so
    a step forward dropped every fresh sample (the force levels went stale while the arm pressed) and a step back
    kept old ones. The simulated robot's state stands in for a UR's (the sensor reads only the state's fields)."""
    from iorthand_edge.force.config import RobotForceSensorConfig
    from iorthand_edge.force.sensors import RobotForceSensor
    from iorthand_edge.robots.config import SimRobotConfig
    from iorthand_edge.robots.sim import SimRobot

    robot = SimRobot(SimRobotConfig())
    robot.connect()
    config = RobotForceSensorConfig()
    reading = robot.read_state()
    sensor = RobotForceSensor(config, lambda: reading)
    real_time_ns, real_monotonic_ns = time.time_ns, time.monotonic_ns

    # A fresh state, read after NTP stepped the wall clock an hour forward: its force is a sample.
    monkeypatch.setattr(time, "time_ns", lambda: real_time_ns() + 3600 * 10**9)
    assert sensor.read(0.0) is not None, "a fresh state gave no sample after a wall clock step forward"

    # A state older than max_age, read after the wall clock stepped an hour back: no sample (stale).
    monkeypatch.undo()
    reading = robot.read_state()
    monkeypatch.setattr(time, "time_ns", lambda: real_time_ns() - 3600 * 10**9)
    monkeypatch.setattr(time, "monotonic_ns", lambda: real_monotonic_ns() + int(2 * config.max_age * 1e9))
    assert sensor.read(0.0) is None, "a state older than max_age gave a sample after a wall clock step back"
