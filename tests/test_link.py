"""Link statistics (pure): RTT percentiles, jitter, loss from sequence numbers, grading."""

from __future__ import annotations

import math

import pytest

from iorthand_operator.link import BAD, GOOD, NONE, WARN, LinkThresholds, LinkWindow, gap_loss, grade, jitter

MS = 1_000_000


def test_empty_window_is_no_data_never_good() -> None:
    q = LinkWindow().snapshot(10**12)
    assert math.isnan(q.rtt_p50_ms) and math.isnan(q.jitter_ms) and math.isnan(q.uplink_loss)
    assert q.overall(LinkThresholds()) == NONE


def test_rtt_percentiles_and_jitter_over_window() -> None:
    w = LinkWindow(window_s=1.0, echo_grace_s=0.1)
    t0 = 10**12
    for i in range(100):  # RTT 10 ms, every tenth 30 ms
        sent = t0 + i * 10 * MS
        rtt = 30 if i % 10 == 9 else 10
        w.sent(i + 1, sent)
        w.echoed(i + 1, sent, sent + rtt * MS)
    q = w.snapshot(t0 + 999 * MS)
    assert q.rtt_p50_ms == pytest.approx(10.0)
    assert q.rtt_p95_ms == pytest.approx(30.0)
    assert q.jitter_ms == pytest.approx(jitter([30.0 if i % 10 == 9 else 10.0 for i in range(100)]))
    assert q.uplink_loss == 0.0
    # The window slides: 0.5 s later only the newer half counts.
    assert w.snapshot(t0 + 1500 * MS).echoes < 60


def test_uplink_loss_counts_only_commands_past_the_grace() -> None:
    w = LinkWindow(window_s=5.0, echo_grace_s=0.5)
    t0 = 10**12
    for i in range(1, 101):
        w.sent(i, t0 + i * MS)
        if i % 4:  # every fourth is lost
            w.echoed(i, t0 + i * MS, t0 + i * MS + 5 * MS)
    w.sent(101, t0 + 900 * MS)  # just sent, echo not due yet
    q = w.snapshot(t0 + 1000 * MS)
    assert q.uplink_loss == pytest.approx(0.25)


def test_gap_loss_from_sequence_numbers() -> None:
    assert gap_loss([1, 2, 3, 4]) == 0.0
    assert gap_loss([1, 2, 4, 5]) == pytest.approx(0.2)  # 3 missing of 5
    assert gap_loss([1, 1, 2]) == 0.0  # duplicates are not loss
    assert gap_loss([10, 11, 1, 2]) == 0.0  # the publisher restarted
    assert math.isnan(gap_loss([5]))


def test_downlink_loss_from_state_sequences() -> None:
    w = LinkWindow(window_s=5.0)
    t0 = 10**12
    for i, seq in enumerate([1, 2, 3, 5, 6, 7, 8, 9, 10, 11]):
        w.state(seq, t0 + i * MS)
    assert w.snapshot(t0 + 20 * MS).downlink_loss == pytest.approx(1 / 11)


def test_grades_against_thresholds() -> None:
    t = LinkThresholds(rtt_warn_ms=50, rtt_bad_ms=100)
    assert grade(10, 50, 100) == GOOD
    assert grade(60, 50, 100) == WARN
    assert grade(150, 50, 100) == BAD
    assert grade(math.nan, 50, 100) == NONE
    with pytest.raises(ValueError):
        LinkThresholds(loss_warn=0.5, loss_bad=0.1).check()
    w = LinkWindow()
    w.sent(1, 0)
    w.echoed(1, 0, 120 * MS)
    assert w.snapshot(200 * MS).grades(t)["rtt"] == BAD


def test_a_window_nobody_reads_stays_bounded() -> None:
    """A scripted operator runs for hours without asking for a snapshot: what is two windows old is dropped."""
    w = LinkWindow(window_s=1.0)
    t0 = 10**12
    for i in range(60 * 600):  # ten minutes of 60 Hz sends, echoes and states
        t = t0 + i * 16 * MS
        w.sent(i, t)
        w.echoed(i, t, t + 5 * MS)
        w.state(i, t)
    kept = len(w._sent) + len(w._echoes) + len(w._states) + len(w._echoed)
    assert kept <= 4 * 2 * 64, kept  # ~2 s of each at 60 Hz
