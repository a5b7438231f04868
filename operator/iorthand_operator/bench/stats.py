"""Pure statistics for the benchmarks: latency summaries, jitter, loss and reordering from sequence numbers,
NTP-style clock offset between two hosts. No I/O, no clocks: every function takes its samples as arguments,
so each is tested with known inputs (tests/test_bench_stats.py).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from iorthand.stats import percentile, summary

__all__ = [
    "ClockEstimate",
    "SequenceReport",
    "Timestamps",
    "clock_offset",
    "histogram",
    "interarrival_jitter",
    "latency_summary",
    "percentile",
    "ratio",
    "rfc3550_jitter",
    "sequence_report",
    "summary",
]


def latency_summary(values_ms: Sequence[float]) -> dict[str, float]:
    """count, mean, p50, p90, p99, p99.9, max, min, stdev and jitter (RFC 3550, in arrival order) in ms."""
    out = dict(summary(values_ms))
    n = len(values_ms)
    out["min"] = min(values_ms) if n else math.nan
    if n > 1:
        mean = out["mean"]
        out["stdev"] = math.sqrt(sum((v - mean) ** 2 for v in values_ms) / (n - 1))
    else:
        out["stdev"] = math.nan
    out["jitter"] = rfc3550_jitter(values_ms)
    return out


def rfc3550_jitter(latencies: Sequence[float]) -> float:
    """The interarrival jitter of RFC 3550 §6.4.1: a running mean (gain 1/16) of |D(i-1, i)|, where D is the
    change of transit time between consecutive packets. It is what RTP receivers report, so it compares with
    other systems; NaN with fewer than two samples."""
    if len(latencies) < 2:
        return math.nan
    j = 0.0
    for prev, cur in itertools.pairwise(latencies):
        j += (abs(cur - prev) - j) / 16.0
    return j


def interarrival_jitter(arrivals: Sequence[float], period: float) -> dict[str, float]:
    """How regularly a fixed-rate stream arrives: the deviation of each gap between consecutive arrivals from
    the nominal ``period`` (same unit as the inputs): mean |deviation|, p99 |deviation| and the largest gap."""
    gaps = [b - a for a, b in itertools.pairwise(arrivals)]
    if not gaps:
        return {"mean_abs_dev": math.nan, "p99_abs_dev": math.nan, "max_gap": math.nan}
    dev = [abs(g - period) for g in gaps]
    return {"mean_abs_dev": sum(dev) / len(dev), "p99_abs_dev": percentile(dev, 99), "max_gap": max(gaps)}


@dataclass(frozen=True)
class SequenceReport:
    """What sequence numbers say about a stream.

    ``sent`` numbers were sent; ``received`` lists the numbers in arrival order (duplicates possible).
    ``lost`` = sent numbers never received; ``reordered`` = arrivals whose number is below the highest number
    seen before them (they came late); ``duplicates`` = repeated arrivals; ``unexpected`` = received numbers
    that were never sent (a bug or a foreign publisher: never silently counted as delivered).
    """

    sent: int
    received: int
    lost: int
    duplicates: int
    reordered: int
    unexpected: int
    max_reorder_distance: int
    lost_seqs: tuple[int, ...]

    @property
    def loss_ratio(self) -> float:
        return self.lost / self.sent if self.sent else math.nan

    def as_dict(self, max_listed: int = 50) -> dict[str, object]:
        return {
            "sent": self.sent,
            "received": self.received,
            "lost": self.lost,
            "loss_ratio": self.loss_ratio,
            "duplicates": self.duplicates,
            "reordered": self.reordered,
            "unexpected": self.unexpected,
            "max_reorder_distance": self.max_reorder_distance,
            "lost_seqs": list(self.lost_seqs[:max_listed]),
        }


def sequence_report(sent: Iterable[int], received_in_order: Iterable[int]) -> SequenceReport:
    """Loss, duplicates and reordering of a stream from its sequence numbers (see :class:`SequenceReport`)."""
    sent_set = set(sent)
    seen: set[int] = set()
    duplicates = reordered = unexpected = 0
    max_distance = 0
    highest: int | None = None
    arrivals = 0
    for seq in received_in_order:
        arrivals += 1
        if seq not in sent_set:
            unexpected += 1
            continue
        if seq in seen:
            duplicates += 1
            continue
        seen.add(seq)
        if highest is not None and seq < highest:
            reordered += 1
            max_distance = max(max_distance, highest - seq)
        highest = seq if highest is None else max(highest, seq)
    lost = tuple(sorted(sent_set - seen))
    return SequenceReport(
        sent=len(sent_set), received=arrivals, lost=len(lost), duplicates=duplicates, reordered=reordered,
        unexpected=unexpected, max_reorder_distance=max_distance, lost_seqs=lost,
    )


@dataclass(frozen=True)
class Timestamps:
    """One request/response exchange, NTP notation, in ns: ``t1`` sent (client clock), ``t2`` received
    (server clock), ``t3`` reply sent (server clock), ``t4`` reply received (client clock)."""

    t1: int
    t2: int
    t3: int
    t4: int

    @property
    def rtt(self) -> int:
        """Round trip minus the server's hold time, ns (NTP's delay δ)."""
        return (self.t4 - self.t1) - (self.t3 - self.t2)

    @property
    def offset(self) -> float:
        """Server clock minus client clock, ns, assuming symmetric paths (NTP's θ)."""
        return ((self.t2 - self.t1) + (self.t3 - self.t4)) / 2.0


@dataclass(frozen=True)
class ClockEstimate:
    offset_ns: float  # server − client
    error_ns: float  # ± bound: half the round trip of the exchanges used
    samples_used: int
    min_rtt_ns: float

    def as_dict(self) -> dict[str, float]:
        return {
            "offset_ms": self.offset_ns / 1e6,
            "error_bound_ms": self.error_ns / 1e6,
            "samples_used": self.samples_used,
            "min_rtt_ms": self.min_rtt_ns / 1e6,
        }


def clock_offset(exchanges: Sequence[Timestamps], best_fraction: float = 0.1) -> ClockEstimate:
    """NTP-style clock offset of the server relative to the client.

    Queueing makes paths asymmetric; the exchanges with the smallest round trip are the least queued, so (as
    NTP's clock filter does) the offset is the median of θ over the ``best_fraction`` fastest exchanges (at
    least one). The true offset lies within ±δ/2 of each θ, so the bound reported is half the largest δ used.
    """
    if not exchanges:
        return ClockEstimate(math.nan, math.nan, 0, math.nan)
    if not 0.0 < best_fraction <= 1.0:
        raise ValueError("best_fraction must be in (0, 1]")
    ranked = sorted(exchanges, key=lambda e: e.rtt)
    k = max(1, int(len(ranked) * best_fraction))
    best = ranked[:k]
    offsets = [e.offset for e in best]
    return ClockEstimate(
        offset_ns=percentile(offsets, 50), error_ns=max(e.rtt for e in best) / 2.0, samples_used=k,
        min_rtt_ns=float(best[0].rtt),
    )


def one_way_ms(exchanges: Sequence[Timestamps], offset_ns: float) -> tuple[list[float], list[float]]:
    """One-way delays (ms) client→server and server→client, corrected by the estimated clock offset."""
    up = [(e.t2 - e.t1 - offset_ns) / 1e6 for e in exchanges]
    down = [(e.t4 - e.t3 + offset_ns) / 1e6 for e in exchanges]
    return up, down


def histogram(values: Sequence[float], bins: int = 50, lo: float | None = None, hi: float | None = None) -> dict[str, list[float]]:
    """Equal-width bins over [lo, hi] (default: the data's range): ``edges`` (bins+1) and ``counts`` (bins).
    Values outside the range go to the first or last bin, so counts always sum to len(values)."""
    if bins < 1:
        raise ValueError("bins must be at least 1")
    if not values:
        return {"edges": [], "counts": []}
    lo = min(values) if lo is None else lo
    hi = max(values) if hi is None else hi
    if hi <= lo:
        hi = lo + 1e-9
    width = (hi - lo) / bins
    counts = [0] * bins
    for v in values:
        i = int((v - lo) / width)
        counts[min(max(i, 0), bins - 1)] += 1
    return {"edges": [lo + i * width for i in range(bins + 1)], "counts": [float(c) for c in counts]}


def ratio(a: float, b: float) -> float:
    """a / b, NaN when either is missing or b is zero (a report never divides by zero)."""
    if b == 0 or math.isnan(a) or math.isnan(b):
        return math.nan
    return a / b
