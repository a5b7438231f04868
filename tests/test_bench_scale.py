"""The scale benchmark's machinery on a small N: real router and role processes on 127.0.0.1, every command
matched to its echo by sequence number. The scale figures themselves are a benchmark (``iorthand bench
scale``), not a test."""

from __future__ import annotations

from pathlib import Path

import pytest

from iorthand_operator.bench.scale import run_scale_point


@pytest.mark.serial  # two operators at 60 Hz: no sequence number may be lost
def test_two_robots_two_operators_through_one_router(tmp_path: Path) -> None:
    point = run_scale_point(tmp_path, n=2, duration=2.0, topology="router")
    assert point["operators"] == "light" and point["edges"] == "light"
    assert set(point["per_robot"]) == {"r000", "r001"}
    # 60 Hz for 2 s per operator, plus the final deadman release; the sleeping sender may slip a few ticks.
    assert point["sent"] >= 2 * 60 * 2 * 0.9
    for robot, r in point["per_robot"].items():
        assert r["sequence"]["lost"] == 0, robot
        assert r["refused"] == 0, robot  # each operator acquired its own robot
        assert r["rtt_ms"]["count"] == r["sequence"]["sent"], robot
    assert point["lost"] == 0 and point["rtt_ms"]["p50"] > 0
    assert point["router_cpu_percent_total"] > 0


def test_unknown_operator_kind_is_named() -> None:
    with pytest.raises(ValueError, match="unknown scale operators 'fast'"):
        run_scale_point(Path("/nonexistent"), n=1, duration=1.0, operators="fast")
