"""Session report maths (pure): the performance index against the reference's published rows, contact time,
warning edges, hysteresis."""

from __future__ import annotations

import math

import pytest

from iorthand_cloud.recorder import metrics
from iorthand_cloud.recorder.simulate import expected_events


@pytest.mark.parametrize(
    ("t_t", "tau", "red", "yellow", "phi"),
    [(180.67, 55.88, 6, 15, 57.02), (130.46, 51.22, 0, 4, 88.66)],
)
def test_performance_index_matches_the_published_rows(t_t, tau, red, yellow, phi) -> None:
    ix = metrics.PerformanceIndex(t_t, tau, red, yellow)
    assert ix.phi == pytest.approx(phi, abs=0.01)
    assert ix.omega == 4 * red + yellow
    assert 0 < ix.psi < 1  # ψ is a fraction: in percent neither row comes out


def test_performance_index_edges() -> None:
    assert math.isnan(metrics.PerformanceIndex(0.0, 0.0, 0, 0).phi)
    assert metrics.PerformanceIndex(10.0, 10.0, 1, 0).phi == -math.inf
    assert metrics.PerformanceIndex(10.0, 5.0, 0, 0, alpha=100.0).phi == pytest.approx(50.0)


def test_contact_time_counts_samples_above_threshold_and_caps_gaps() -> None:
    samples = [(i * 0.01, 5.0 if 100 <= i < 300 else 0.0) for i in range(500)]
    assert metrics.contact_time(samples, 1.0, 0.1) == pytest.approx(2.0)
    gap = [(0.0, 5.0), (0.01, 5.0), (3.0, 5.0)]  # a silent sensor for 3 s is not 3 s of contact
    assert metrics.contact_time(gap, 1.0, 0.1) == pytest.approx(0.01 + 0.1 + 0.01)
    assert metrics.contact_time([], 1.0, 0.1) == 0.0


def test_warning_edges_count_rising_edges_only() -> None:
    levels = [0, 1, 1, 2, 1, 2, 0, 2, 2, 1, 0, 1]
    samples = [(float(i), lv, False) for i, lv in enumerate(levels)]
    red, yellow, edges = metrics.warning_edges(samples)
    # 0→1 (t=1), 1→2 (3), 1→2 (5), 0→2 (7), 0→1 (11); 2→1 at 4 and 9 are falling edges.
    assert (red, yellow) == (3, 2)
    assert [t for t, _ in edges] == [1.0, 3.0, 5.0, 7.0, 11.0]


def test_stale_levels_are_skipped() -> None:
    red, yellow, _ = metrics.warning_edges([(0, 2, False), (1, 0, True), (2, 2, False)])
    assert (red, yellow) == (1, 0)  # the stale sample is no evidence the level fell


def test_levels_from_force_with_hysteresis() -> None:
    values = [0.0, 6.5, 5.8, 6.2, 5.4, 8.5, 7.8, 7.4, 0.0]
    levels = [lv for _, lv in metrics.levels_from_force(enumerate(values), 6.0, 8.0, 0.5)]
    assert levels == [0, 1, 1, 1, 0, 2, 2, 1, 0]


def test_rising_edges_and_teleoperation_time() -> None:
    states = [(0.0, "ok"), (1.0, "command_timeout"), (1.1, "command_timeout"), (2.0, "ok"), (3.0, "deadman_released")]
    assert metrics.rising_edges(states, {"command_timeout", "deadman_released"}) == [1.0, 3.0]
    assert metrics.teleoperation_time([(1.0, False), (2.0, True), (5.0, True), (6.0, False)]) == 3.0


def test_simulation_script_expectations() -> None:
    ev = expected_events(10.0)
    assert ev == {"contact_time": 6.0, "omega_R": 2, "omega_Y": 1, "deadman_stops": 1}
    assert expected_events(20.0)["omega_R"] == 4
