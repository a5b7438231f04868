"""The link to the UR controller drops packets for 50 ms, 300 ms and 3 s (nftables on the emulator's own loopback
address; root and the ``nft`` tool needed), with the REAL ur_rtde library in the driver child, as in production.

Unlike the emulator's ``drop_link`` (which closes the connections), this is what a flaky cable or switch does: the
TCP connections stay open and stall, and retransmission (200 ms minimum on Linux) delays everything behind the
gap. The right reaction every time: the fault is reported, the arm is at rest (the driver's stop, else the
controller's watchdog), the driver reconnects once the link is back, and nothing moves by itself afterwards.
Figures are printed, not asserted, beyond the bounds the driver promises.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from collections.abc import Iterator

import pytest

pytest.importorskip("rtde_control", reason="ur-rtde is not installed on this platform (pip install ur-rtde==1.6.5)")

from iorthand_edge.robots.config import URRobotConfig
from iorthand_edge.robots.ur import URRobot
from iorthand_edge.supervisor import SafetyConfig
from iorthand_edge.ur_emulator.emulator import DEFAULT_CONTROL_PORT
from tests.conftest import Emulator
from tests.test_ur_backend import cycle, healthy, until, wait_emu

pytestmark = [
    pytest.mark.serial,
    pytest.mark.skipif(os.geteuid() != 0 or shutil.which("nft") is None, reason="needs root and nftables (nft)"),
]


class Blackhole:
    """Drops every packet to and from ``host`` except the emulator's control socket (the test's back door), in an
    nftables table of this process's own; removed on exit whatever happened."""

    def __init__(self, host: str) -> None:
        self.host = host
        self.table = f"iorthand_test_{os.getpid()}"

    def _nft(self, script: str) -> None:
        subprocess.run(["nft", "-f", "-"], input=script, text=True, check=True, timeout=5.0)

    def drop(self) -> None:
        port = DEFAULT_CONTROL_PORT
        self._nft(f"table ip {self.table} {{\n chain out {{ type filter hook output priority 0;\n"
                  f"  ip daddr {self.host} tcp dport != {port} tcp sport != {port} drop\n"
                  f"  ip saddr {self.host} tcp dport != {port} tcp sport != {port} drop\n }}\n}}\n")

    def restore(self) -> None:
        subprocess.run(["nft", "delete", "table", "ip", self.table], capture_output=True, timeout=5.0)

    def __enter__(self) -> Blackhole:
        return self

    def __exit__(self, *_: object) -> None:
        self.restore()


@pytest.fixture
def robot(emu: Emulator) -> Iterator[URRobot]:
    r = URRobot(URRobotConfig(host=emu.host, connect_timeout=2.0, reconnect_max_s=1.0), SafetyConfig().stop_deceleration)
    yield r
    r.disconnect()


@pytest.mark.parametrize("gap", [0.05, 0.3, 3.0])
def test_packet_loss_on_the_controller_link_stops_reports_and_reconnects_without_moving(
        emu: Emulator, robot: URRobot, gap: float) -> None:
    robot.connect()
    cycle(robot, 0.3, [0.02, 0, 0, 0, 0, 0])
    assert emu.status()["twist"][0] > 0.019
    faults: list[tuple[float, str]] = []

    def note(r: object) -> bool:
        fault = getattr(r, "fault", "")
        if fault and (not faults or faults[-1][1] != fault):
            faults.append((time.monotonic() - t0, fault))
        return False

    with Blackhole(emu.host) as hole:
        t0 = time.monotonic()
        hole.drop()
        end = t0 + gap
        while time.monotonic() < end:  # the agent keeps commanding through the gap, as its loop would
            reading = robot.read_state()
            note(reading)
            if not reading.fault:
                robot.send_twist([0.02, 0, 0, 0, 0, 0], 0.5)
            time.sleep(robot.control_period)
        hole.restore()
    t_restored = time.monotonic() - t0
    # Look for a second more: the stall behind the gap outlasts it by TCP's recovery.
    for _ in range(int(1.0 / robot.control_period)):
        note(robot.read_state())
        time.sleep(robot.control_period)
    if not faults:
        # Ridden through: the stall stayed under the 100 ms link timeout and the controller's watchdog (TCP
        # re-sends a lost tail after ~10 ms on loopback, not 200 ms), as the design allows. Still healthy and driven.
        assert gap < 0.1, f"a {gap} s gap was not reported"
        reading = cycle(robot, 0.2, [0.02, 0, 0, 0, 0, 0])
        assert healthy(reading) and emu.status()["twist"][0] > 0.019
        print(f"gap {1000 * gap:.0f} ms: ridden through, no fault; controller events: {emu.status()['events'][-2:]}")
        robot.stop(0.5)
        return
    # Reported within a second, whatever the gap: the timestamp freezes behind TCP's retransmission.
    assert faults[0][0] < 1.0 and ("link" in faults[0][1] or "frozen" in faults[0][1] or "no state" in faults[0][1])
    # The arm comes to rest: the driver's own stop or the controller's watchdog.
    wait_emu(lambda: emu.status()["motion"] == "idle", 3.0, "the arm at rest")
    reading, t_up = until(robot, lambda r: note(r) or healthy(r), 15.0, "the reconnect")
    print(f"gap {1000 * gap:.0f} ms: faults {[(round(t, 3), f[:70]) for t, f in faults]}; link back at "
          f"{t_restored:.3f} s, healthy {t_up:.2f} s after a 1 s look; controller events: {emu.status()['events'][-4:]}")
    for _ in range(25):  # nothing moves by itself after the reconnect
        cycle(robot, 0.02)
        assert emu.status()["twist"] == [0.0] * 6
