"""Run inside a mount namespace whose ``/sys/kernel/realtime`` reads 1, so that ur_rtde takes this kernel for a
PREEMPT_RT one (a real-time kernel cannot exist on the test machine; this file is all ur_rtde 1.6.5 looks at).

Prints one JSON object: the scheduling of every thread of the edge's UR driver child, and of this process's
threads once a bare ur_rtde receive interface (default priority) is made. ``tests/test_ur_backend.py`` reads it.
"""

from __future__ import annotations

import json
import os
import time

import rtde_receive

from iorthand_edge.robots.config import URRobotConfig
from iorthand_edge.robots.ur import URRobot
from iorthand_edge.supervisor import SafetyConfig
from iorthand_edge.ur_emulator.process import EmulatorProcess


def policies(pid: int) -> dict[str, tuple[int, int]]:
    """Each thread of ``pid``: (policy without reset-on-fork, priority)."""
    return {t: (os.sched_getscheduler(int(t)) & ~os.SCHED_RESET_ON_FORK, os.sched_getparam(int(t)).sched_priority)
            for t in os.listdir(f"/proc/{pid}/task")}


def main() -> None:
    with EmulatorProcess() as emulator:
        robot = URRobot(URRobotConfig(host=emulator.host), SafetyConfig().stop_deceleration)
        robot.connect()
        try:
            end = time.monotonic() + 0.2  # the driver's loop runs: what it sets after saying ready counts too
            while time.monotonic() < end:
                robot.read_state()
                time.sleep(robot.control_period)
            assert robot._proc is not None
            driver_pid = robot._proc.pid
            driver = policies(driver_pid)
        finally:
            robot.disconnect()
        # Last: ur_rtde sets the thread that calls its constructor too, and a driver child spawned from this
        # process afterwards would inherit that.
        bare = rtde_receive.RTDEReceiveInterface(emulator.host, 250.0)
        bare_threads = policies(os.getpid())
        bare.disconnect()
    print(json.dumps({"bare_ur_rtde": bare_threads, "driver_pid": driver_pid, "driver": driver,
                      "driver_priority": robot.driver_priority}))


if __name__ == "__main__":
    main()
