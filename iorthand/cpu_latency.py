"""Keep the machine's CPUs out of slow idle states while a latency-critical process runs (Linux PM QoS).

Every hop of the command path wakes a thread. When its CPU was idle, the wake-up waits for the CPU to leave its
idle state: on the project's 2-core VM (cpuidle ``haltpoll``, ``guest_halt_poll_ns`` 0) a halted vCPU costs a VM
exit, and Python runs 10–20× slower right after one. A PM QoS request of 0 µs keeps idle CPUs polling instead,
which halved the round trip of small commands through a router there (figures in benchmarks/README.md). The
price is power: idle cores spin. Whether to pay it is the host owner's choice, so nothing holds a request
unless configured to.
"""

from __future__ import annotations

import logging
import os
import struct
from pathlib import Path

log = logging.getLogger(__name__)

CPU_DMA_LATENCY = Path("/dev/cpu_dma_latency")


def _checked_us(max_us: int) -> int:
    if isinstance(max_us, bool) or not isinstance(max_us, int) or max_us < 0:
        raise ValueError(f"cpu latency: a whole number of microseconds ≥ 0, got {max_us!r}")
    return max_us


class CpuLatencyHold:
    """One PM QoS request: while it is open, no CPU of this machine enters an idle state that takes longer than
    ``max_us`` µs to leave. The request is machine-wide and ends on :meth:`close` or when the process exits.
    Best effort, like :func:`iorthand.process.raise_priority`: it needs root, and ``state`` says what it got."""

    def __init__(self, max_us: int, path: Path = CPU_DMA_LATENCY) -> None:
        self.max_us = _checked_us(max_us)
        self._fd: int | None = None
        fd = None
        try:
            fd = os.open(path, os.O_WRONLY)
            os.write(fd, struct.pack("=i", max_us))  # the device takes a native 32-bit integer
        except OSError as exc:
            if fd is not None:
                os.close(fd)
            self.state = f"not held: {path}: {exc.strerror or exc}"
            log.warning("cpu latency %d µs %s", max_us, self.state)
            return
        self._fd = fd
        self.state = f"held at {max_us} µs"
        log.info("cpu latency %s (%s)", self.state, path)

    @property
    def held(self) -> bool:
        return self._fd is not None

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
            self.state = "released"

    def __enter__(self) -> CpuLatencyHold:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class CpuLatencyWhileNeeded:
    """A request of ``max_us`` µs held only while :meth:`need` says so (the edge: while an operator holds control,
    so that the host idles normally the rest of the day). A request the device refuses (not root) is reported
    once in ``state`` and not tried again."""

    def __init__(self, max_us: int, path: Path = CPU_DMA_LATENCY) -> None:
        self.max_us = _checked_us(max_us)
        self.path = path
        self._hold: CpuLatencyHold | None = None
        self._refused = False
        self.state = f"{max_us} µs while an operator holds control"

    @property
    def held(self) -> bool:
        return self._hold is not None

    def need(self, needed: bool) -> None:
        if needed and self._hold is None and not self._refused:
            hold = CpuLatencyHold(self.max_us, self.path)
            if hold.held:
                self._hold = hold
            else:
                self._refused, self.state = True, hold.state
        elif not needed and self._hold is not None:
            self._hold.close()
            self._hold = None

    def close(self) -> None:
        self.need(False)
