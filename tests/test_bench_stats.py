"""Statistics of the benchmarks, with known inputs."""

from __future__ import annotations

import math

import pytest

from iorthand_operator.bench import stats


def test_percentiles_of_known_sample() -> None:
    values = list(range(1, 101))  # 1..100
    s = stats.latency_summary([float(v) for v in values])
    assert s["count"] == 100
    assert s["p50"] == pytest.approx(50.5)
    assert s["p90"] == pytest.approx(90.1)
    assert s["p99"] == pytest.approx(99.01)
    assert s["p99.9"] == pytest.approx(99.901)
    assert s["max"] == 100 and s["min"] == 1
    assert s["mean"] == pytest.approx(50.5)


def test_empty_summary_is_nan_not_an_error() -> None:
    s = stats.latency_summary([])
    assert s["count"] == 0 and math.isnan(s["p99"]) and math.isnan(s["jitter"])


def test_rfc3550_jitter() -> None:
    assert stats.rfc3550_jitter([5.0] * 10) == 0.0
    # One step of 16 ms: J = 16/16 = 1 after the first difference, then decays by 15/16 per constant step.
    j = stats.rfc3550_jitter([0.0, 16.0, 16.0])
    assert j == pytest.approx(1.0 * 15 / 16)


def test_interarrival_jitter() -> None:
    r = stats.interarrival_jitter([0.0, 10.0, 20.0, 35.0], period=10.0)
    assert r["max_gap"] == 15.0
    assert r["mean_abs_dev"] == pytest.approx(5.0 / 3)


def test_loss_from_sequence_numbers() -> None:
    r = stats.sequence_report(range(1, 11), [1, 2, 3, 5, 6, 8, 9, 10])
    assert r.sent == 10 and r.lost == 2 and r.lost_seqs == (4, 7)
    assert r.loss_ratio == pytest.approx(0.2)
    assert r.reordered == 0 and r.duplicates == 0


def test_reordering_duplicates_and_unexpected() -> None:
    r = stats.sequence_report([1, 2, 3, 4, 5], [1, 3, 2, 5, 4, 4, 99])
    assert r.reordered == 2  # 2 after 3, 4 after 5
    assert r.max_reorder_distance == 1
    assert r.duplicates == 1
    assert r.unexpected == 1
    assert r.lost == 0
    far = stats.sequence_report(range(1, 11), [10, 1, 2, 3, 4, 5, 6, 7, 8, 9])
    assert far.reordered == 9 and far.max_reorder_distance == 9


def test_clock_offset_symmetric_paths() -> None:
    # Server clock 5 ms ahead; one-way delay 1 ms each way; server holds 0.2 ms.
    off, d, hold = 5_000_000, 1_000_000, 200_000
    ex = []
    for i in range(20):
        t1 = i * 10_000_000
        t2 = t1 + d + off
        t3 = t2 + hold
        t4 = t3 - off + d
        ex.append(stats.Timestamps(t1, t2, t3, t4))
    assert ex[0].rtt == 2 * d
    assert ex[0].offset == pytest.approx(off)
    est = stats.clock_offset(ex)
    assert est.offset_ns == pytest.approx(off)
    assert est.error_ns == pytest.approx(d)
    up, down = stats.one_way_ms(ex, est.offset_ns)
    assert up == pytest.approx([1.0] * 20) and down == pytest.approx([1.0] * 20)


def test_clock_offset_prefers_least_queued_exchanges() -> None:
    # True offset −3 ms. Most exchanges see 8 ms extra queueing on the way out only (asymmetric), which biases
    # θ by +4 ms; the fastest 10 % do not, and they decide.
    off = -3_000_000
    ex = []
    for i in range(100):
        up = 500_000 + (8_000_000 if i % 10 else 0)
        t1 = i * 20_000_000
        t2 = t1 + up + off
        t3 = t2 + 100_000
        t4 = t3 - off + 500_000
        ex.append(stats.Timestamps(t1, t2, t3, t4))
    est = stats.clock_offset(ex, best_fraction=0.1)
    assert est.offset_ns == pytest.approx(off)
    assert est.samples_used == 10
    naive = sum(e.offset for e in ex) / len(ex)
    assert abs(naive - off) > 3_000_000


def test_clock_offset_empty_and_bad_fraction() -> None:
    assert math.isnan(stats.clock_offset([]).offset_ns)
    with pytest.raises(ValueError):
        stats.clock_offset([stats.Timestamps(0, 1, 2, 3)], best_fraction=0)


def test_histogram_counts_everything() -> None:
    h = stats.histogram([0.0, 0.5, 1.0, 1.5, 2.0, 10.0], bins=4, lo=0.0, hi=2.0)
    assert h["counts"] == [1.0, 1.0, 1.0, 3.0]  # half-open bins; 2.0 (the top edge) and 10.0 go to the last
    assert len(h["edges"]) == 5 and sum(h["counts"]) == 6


def test_ratio() -> None:
    assert stats.ratio(1.0, 2.0) == 0.5
    assert math.isnan(stats.ratio(1.0, 0.0)) and math.isnan(stats.ratio(math.nan, 1.0))


def test_median_is_numpys_to_the_last_bit_and_refuses_no_values() -> None:
    """iorthand.stats.median stands in for np.median in the perception pipeline: the same value, odd and even
    counts, ties and negative numbers included."""
    import numpy as np

    from iorthand.stats import median

    rng = np.random.default_rng(7)
    for n in range(1, 40):
        values = rng.normal(0.0, 3.0, n)
        values[: n // 3] = values[-1]  # ties
        assert median(values) == float(np.median(values)), n
    assert median([2.0, 1.0]) == 1.5 and median([[3.0], [1.0], [2.0]]) == 2.0
    with pytest.raises(ValueError, match="no values"):
        median([])
