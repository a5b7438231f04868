"""Real-time priority for the control and command threads only, and without root on the Pi.

The edge's systemd unit grants it through LimitRTPRIO; it must not make the whole process real-time, or the
perception and video threads (milliseconds of CPU per frame) would run at or above the control loop.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest

from iorthand.process import REALTIME_PRIORITY
from tests.conftest import ROOT

EDGE_UNIT = ROOT / "deploy" / "systemd" / "iorthand-edge.service"

# raise_priority in one thread; then what a thread it starts gets, and a process it starts (the UR driver,
# restarted from the control loop): both normal, not real time.
PROBE = """
import os, subprocess, sys, threading
from iorthand.process import raise_priority
got = raise_priority(True)
other = {}
t = threading.Thread(target=lambda: other.update(policy=os.sched_getscheduler(0)))
t.start(); t.join()
child = subprocess.run([sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"], capture_output=True,
                       text=True).stdout.strip()
print(got, os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO, os.sched_getparam(0).sched_priority,
      other["policy"] == os.SCHED_OTHER and child == str(os.SCHED_OTHER), sep="|")
"""


def unit_settings(path: Path) -> dict[str, str]:
    settings = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        if "=" in line and not line.lstrip().startswith(("#", "[")):
            name, value = line.split("=", 1)
            settings[name.strip()] = value.strip()
    return settings


def test_the_edge_unit_grants_the_threads_priority_and_no_process_wide_policy() -> None:
    settings = unit_settings(EDGE_UNIT)
    assert settings.get("LimitRTPRIO") == str(REALTIME_PRIORITY)
    assert "CPUSchedulingPolicy" not in settings and "CPUSchedulingPriority" not in settings
    assert settings.get("User") not in (None, "root")


def run_as_service_user(rtprio_limit: int) -> list[str]:
    def drop_privileges() -> None:
        resource.setrlimit(resource.RLIMIT_RTPRIO, (rtprio_limit, rtprio_limit))  # what LimitRTPRIO sets
        os.setgroups([])
        os.setgid(65534)
        os.setuid(65534)  # nobody: no CAP_SYS_NICE, only the rlimit below

    env = {"PYTHONPATH": os.pathsep.join(str(ROOT / p) for p in ("", "edge", "operator", "cloud")),
           "PYTHONDONTWRITEBYTECODE": "1", "PATH": os.environ.get("PATH", "")}
    done = subprocess.run(
        [sys.executable, "-c", PROBE],
        env=env, cwd="/", capture_output=True, text=True, timeout=30, preexec_fn=drop_privileges, check=False,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip().split("|")


def can_grant_rtprio() -> bool:
    """Setting LimitRTPRIO as systemd does needs root with CAP_SYS_RESOURCE (some containers lack it)."""
    if os.geteuid() != 0:
        return False
    soft, hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
    try:
        resource.setrlimit(resource.RLIMIT_RTPRIO, (soft, max(hard, REALTIME_PRIORITY)))
    except (ValueError, OSError):
        return False
    resource.setrlimit(resource.RLIMIT_RTPRIO, (soft, hard))  # lowering back is always allowed
    return True


@pytest.mark.skipif(not can_grant_rtprio(), reason="needs root with CAP_SYS_RESOURCE to set RLIMIT_RTPRIO")
def test_a_service_user_gets_real_time_threads_from_the_limit_alone() -> None:
    got, fifo, priority, other_normal = run_as_service_user(REALTIME_PRIORITY)
    assert (got, fifo, priority, other_normal) == ("SCHED_FIFO", "True", str(REALTIME_PRIORITY), "True")
    got, fifo, _priority, _other = run_as_service_user(0)  # the unit without LimitRTPRIO
    assert got.startswith("normal (") and "not permitted" in got and fifo == "False"


def test_root_gets_real_time_threads_and_what_they_start_stays_normal() -> None:
    # What the edge gets when it runs as root (the demo, this machine): the same PROBE in a child of its own.
    if os.geteuid() != 0:
        pytest.skip("needs root")
    r = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().split("|") == ["SCHED_FIFO", "True", str(REALTIME_PRIORITY), "True"]
