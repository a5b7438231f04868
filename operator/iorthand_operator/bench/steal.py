"""CPU time the hypervisor takes from this virtual machine ("steal"), in bursts per virtual CPU.

A virtual machine's CPU can be taken away whole by its host. Nothing inside the guest runs on it meanwhile, not
even a SCHED_FIFO 99 thread. On the test machine (a Firecracker VM, 2 vCPUs) under ``stress-ng --cpu 2`` alone,
a bare SCHED_FIFO thread that sleeps 2 ms at a time overslept by 96-101 ms, 2 times in 2 minutes at priority 4
and 2 times at priority 99. Each time, the CPU it ran on gained exactly 100 ms of steal (10 ticks). That is the
UR controller's watchdog bound. So a benchmark that counts false faults must say which of them a steal explains.

``python -m iorthand_operator.bench.steal --seconds N`` samples every CPU's steal counter of /proc/stat every
10 ms and prints one JSON object: the bursts (``t_ns``: wall time the sample saw the burst end; ``cpu``; ``ms``).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import signal
import threading
import time
from collections.abc import Sequence
from typing import NamedTuple

from iorthand.process import raise_priority

SAMPLE_S = 0.010
MERGE_S = 0.050  # steal seen in samples this close together is one burst
MIN_BURST_MS = 50.0  # a burst shorter than this cannot explain a 100 ms watchdog fault


class Sample(NamedTuple):
    t_ns: int  # wall time of the read
    steal_ms: tuple[float, ...]  # cumulative steal per CPU


class Burst(NamedTuple):
    t_ns: int  # the first sample after the burst ended
    cpu: int
    ms: float


def parse_steal(stat: str, ticks_per_s: int) -> tuple[float, ...]:
    """Cumulative steal per CPU in ms from the text of /proc/stat (the 8th number of each ``cpuN`` line)."""
    per_cpu = [line.split() for line in stat.splitlines() if line.startswith("cpu") and not line.startswith("cpu ")]
    return tuple(int(fields[8]) * 1000.0 / ticks_per_s for fields in per_cpu)


def bursts(samples: Sequence[Sample], min_ms: float = MIN_BURST_MS, merge_s: float = MERGE_S) -> list[Burst]:
    """The steal bursts of at least ``min_ms`` on each CPU. The steal that consecutive samples within ``merge_s``
    of each other saw is added into one burst (a counter moves in 10 ms ticks, and a stalled sampler reads late)."""
    found: list[Burst] = []
    n_cpus = min((len(s.steal_ms) for s in samples), default=0)
    for cpu in range(n_cpus):
        total, last_t = 0.0, 0
        for before, after in itertools.pairwise(samples):
            gained = after.steal_ms[cpu] - before.steal_ms[cpu]
            if gained <= 0:
                continue
            if total and (after.t_ns - last_t) > merge_s * 1e9:
                if total >= min_ms:
                    found.append(Burst(last_t, cpu, total))
                total = 0.0
            total, last_t = total + gained, after.t_ns
        if total >= min_ms:
            found.append(Burst(last_t, cpu, total))
    return sorted(found)


def explained(fault_ns: int, found: Sequence[Burst], before_s: float = 0.5, after_s: float = 0.1) -> bool:
    """Whether a fault first seen at ``fault_ns`` follows a burst: one ended at most ``before_s`` earlier (the
    controller and the edge see a stall once the CPU is back, then report within a period or two), or at most
    ``after_s`` later (the sampler, on the stolen CPU itself, reads the counter only once it runs again)."""
    return any(-after_s * 1e9 <= fault_ns - b.t_ns <= before_s * 1e9 for b in found)


def sample(seconds: float, stop: threading.Event) -> list[Sample]:
    ticks = os.sysconf("SC_CLK_TCK")
    out: list[Sample] = []
    end = time.monotonic() + seconds
    while time.monotonic() < end and not stop.is_set():
        with open("/proc/stat") as f:
            out.append(Sample(time.time_ns(), parse_steal(f.read(), ticks)))
        stop.wait(SAMPLE_S)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, required=True, help="how long to sample (SIGTERM ends it early)")
    args = ap.parse_args(argv)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    # The lowest real-time priority: above the hogs, so that it reads on time, and under everything measured.
    raise_priority(True, 1)
    samples = sample(args.seconds, stop)
    total = [b - a for a, b in zip(samples[0].steal_ms, samples[-1].steal_ms, strict=True)] if samples else []
    print(json.dumps({"samples": len(samples), "steal_ms_per_cpu": total,
                      "bursts": [b._asdict() for b in bursts(samples)]}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
