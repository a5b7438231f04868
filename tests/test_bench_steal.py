"""The vCPU steal bursts that bench_cpu_hogs.py reports beside its false faults, from known samples, and the
sampler on this machine's real /proc/stat."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from iorthand_operator.bench.steal import Burst, Sample, bursts, explained, parse_steal

MS = 1_000_000  # ns

STAT = """cpu  2336231 196929 420627 5888395 19753 0 22853 3715 0 0
cpu0 1168115 98464 210313 2944197 9876 0 11426 1850 0 0
cpu1 1168116 98465 210314 2944198 9877 0 11427 1865 0 0
intr 1 2 3
"""


def samples(per_cpu: list[list[float]], step_ms: float = 10.0) -> list[Sample]:
    """Samples every ``step_ms`` from cumulative steal columns, one list per CPU."""
    return [Sample(int(i * step_ms * MS), tuple(col[i] for col in per_cpu)) for i in range(len(per_cpu[0]))]


def test_parse_steal_reads_each_cpu_in_ms() -> None:
    assert parse_steal(STAT, 100) == (18_500.0, 18_650.0)  # the 8th number, 10 ms ticks
    assert parse_steal(STAT, 250) == (7_400.0, 7_460.0)


def test_a_100_ms_burst_on_one_cpu_is_found_with_its_cpu_and_end() -> None:
    quiet = [0.0] * 10
    cpu1 = [0, 0, 0, 0, 100, 100, 100, 100, 100, 100]  # the counter jumps once the CPU is back
    assert bursts(samples([quiet, cpu1])) == [Burst(40 * MS, 1, 100.0)]


def test_steal_seen_in_close_samples_adds_up_to_one_burst() -> None:
    cpu0 = [0, 0, 30, 60, 90, 90, 90, 90]
    assert bursts(samples([cpu0])) == [Burst(40 * MS, 0, 90.0)]


def test_scattered_ticks_are_not_a_burst() -> None:
    # 10 ms of steal every 200 ms: 50 ms in all, never 50 ms at once.
    cpu0 = [10.0 * (i // 20) for i in range(120)]
    assert bursts(samples([cpu0])) == []
    assert bursts(samples([cpu0]), min_ms=10.0)  # each tick on its own is found at a lower bound


def test_two_bursts_apart_stay_two() -> None:
    cpu0 = [0, 100, 100, 100, 100, 100, 100, 100, 100, 200]
    assert bursts(samples([cpu0])) == [Burst(10 * MS, 0, 100.0), Burst(90 * MS, 0, 100.0)]


def test_a_fault_is_explained_only_by_a_burst_just_before_it() -> None:
    found = [Burst(1_000 * MS, 0, 100.0)]
    assert explained(1_050 * MS, found)  # seen 50 ms after the CPU came back
    assert explained(960 * MS, found)  # the sampler itself read late
    assert not explained(1_600 * MS, found)  # too long after
    assert not explained(800 * MS, found)  # before the burst
    assert not explained(1_050 * MS, [])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/stat is Linux's")
def test_the_sampler_reads_this_machine() -> None:
    r = subprocess.run([sys.executable, "-m", "iorthand_operator.bench.steal", "--seconds", "0.3"],
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["samples"] >= 5
    cpu_lines = [line for line in Path("/proc/stat").read_text().splitlines() if line.startswith("cpu")]
    assert len(out["steal_ms_per_cpu"]) == len(cpu_lines) - 1  # one per CPU, without the total
    assert all(v >= 0 for v in out["steal_ms_per_cpu"])
