"""The emulator as a child process, for tests, benchmarks and users who run several.

ur_rtde 1.6.5 hard-codes its ports (RTDE 30004, dashboard 29999, script 30003), so emulators are told apart
by address: :func:`free_loopback_host` finds a 127.x.y.z on which all of them are free, and
:class:`EmulatorProcess` runs ``python -m iorthand_edge.ur_emulator`` there, waits for its ``READY`` line and
injects faults through its control socket. Every wait is bounded; ``stop()`` always ends the process.
"""

from __future__ import annotations

import contextlib
import os
import random
import socket
import subprocess
import sys
import threading
from typing import Any

from iorthand.process import REALTIME_PRIORITY, terminate

from .emulator import DEFAULT_CONTROL_PORT
from .faults import ControlClient

UR_PORTS = (30004, 29999, 30002, 30003)
# The emulator's real-time priority when it must stand for a controller of its own (raise_priority): under the
# edge's real-time threads, so that it never delays the edge's control loop either.
EMULATOR_PRIORITY = max(1, REALTIME_PRIORITY - 5)


def free_loopback_host(ports: tuple[int, ...] = (*UR_PORTS, DEFAULT_CONTROL_PORT), tries: int = 50) -> str:
    """A 127.x.y.z address on which every one of ``ports`` is free (127.0.0.1 may be taken by another)."""
    for _ in range(tries):
        host = f"127.{random.randint(100, 250)}.{random.randint(0, 255)}.{random.randint(2, 254)}"
        try:
            for port in ports:
                with socket.socket() as s:
                    s.bind((host, port))
        except OSError:
            continue
        return host
    raise RuntimeError(f"no loopback address with ports {ports} free after {tries} tries")


class EmulatorProcess:
    """``python -m iorthand_edge.ur_emulator`` on its own loopback address, with its fault-injection client."""

    def __init__(self, frequency: float = 250.0, unlock_delay: float = 0.3, host: str | None = None,
                 extra_args: tuple[str, ...] = ()) -> None:
        self.host = host or free_loopback_host()
        self.output: list[str] = []
        self._ready = threading.Event()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "iorthand_edge.ur_emulator", "--host", self.host, "--control-port",
             str(DEFAULT_CONTROL_PORT), "--frequency", str(frequency), "--unlock-delay", str(unlock_delay),
             *extra_args],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )
        # Drain stdout for the process's whole life: a full pipe would block the emulator.
        threading.Thread(target=self._pump, name="ur-emulator-output", daemon=True).start()
        self.ctl: ControlClient | None = None

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.output.append(line.rstrip("\n"))
            del self.output[:-200]
            if line.startswith("READY"):
                self._ready.set()

    def wait_ready(self, timeout: float = 15.0) -> EmulatorProcess:
        if not self._ready.wait(timeout):
            self.stop()
            raise RuntimeError(f"the UR emulator did not start within {timeout} s; output: {self.output[-10:]}")
        self.ctl = ControlClient(self.host, DEFAULT_CONTROL_PORT)
        return self

    def call(self, op: str, **args: Any) -> Any:
        """Inject a fault or ask the status (see iorthand_edge.ur_emulator.faults.OPS)."""
        assert self.ctl is not None, "wait_ready() first"
        return self.ctl.call(op, **args)

    def status(self) -> dict[str, Any]:
        return self.call("status")

    def raise_priority(self, nice: int = -10) -> str:
        """Make the emulator a computer of its own, as the arm's controller is: load on this machine (CPU hogs, a
        busy test run) must not starve it, or its RTDE watchdog stops the program for want of kicks that were sent
        (a fault of the rig, which the edge rightly reports). All its threads, and those they start, at SCHED_FIFO
        :data:`EMULATOR_PRIORITY` (root or CAP_SYS_NICE), else at ``nice``, else as they are; returns what they
        got. Measured: benchmarks/README.md, "the UR emulator at real-time priority". Not
        :func:`iorthand.process.raise_priority`: it resets real time on fork, and the emulator's connection threads,
        started later, must inherit it."""
        got = f"SCHED_FIFO {EMULATOR_PRIORITY}"
        try:
            for tid in os.listdir(f"/proc/{self.proc.pid}/task"):
                try:
                    os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(EMULATOR_PRIORITY))
                except PermissionError:
                    os.setpriority(os.PRIO_PROCESS, int(tid), nice)
                    got = f"nice {nice}"
        except OSError as exc:
            return f"as it was ({exc.strerror})"
        return got

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, timeout: float = 5.0) -> None:
        if self.ctl is not None:
            with contextlib.suppress(OSError, RuntimeError):
                self.call("clear_faults")
            self.ctl.close()
            self.ctl = None
        terminate(self.proc, timeout)

    def __enter__(self) -> EmulatorProcess:
        return self.wait_ready()

    def __exit__(self, *_: object) -> None:
        self.stop()
