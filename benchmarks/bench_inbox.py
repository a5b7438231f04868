"""The hand-over from a Zenoh callback to a worker (``iorthand.transport.Inbox``) against a bare ``SimpleQueue``
and against a ``threading.Condition`` (how Inbox handed over before).

The edge's command path has one such hand-over (the twist's callback → the control loop), and the worker has
slept since the last command when the next one comes: a producer thread puts a ``perf_counter_ns`` stamp every
``--gap-ms`` (16 ms: a 60 Hz command stream), the worker waits in ``get(timeout=...)`` and records how long after
the put it woke with the item. The two kinds take turns, ``--rounds`` times, in one run.

    .venv/bin/python benchmarks/bench_inbox.py [--items 300] [--rounds 4] [--out benchmarks/results/inbox.json]
"""

from __future__ import annotations

import argparse
import queue
import statistics
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

from iorthand.transport import Inbox
from iorthand_operator.bench import report

ROOT = Path(__file__).resolve().parent.parent


class BareQueue:
    """What the hand-over cannot beat: a C-level queue, unbounded, no accounting."""

    def __init__(self) -> None:
        self._q: queue.SimpleQueue[Any] = queue.SimpleQueue()

    def put(self, item: Any) -> None:
        self._q.put(item)

    def get(self, timeout: float) -> Any | None:
        try:
            return self._q.get(timeout=timeout)
        except queue.Empty:
            return None


class ConditionQueue:
    """The hand-over as Inbox did it before (a deque and a ``threading.Condition``): the reference it improves on."""

    def __init__(self) -> None:
        self._items: deque[Any] = deque()
        self._cond = threading.Condition()

    def put(self, item: Any) -> None:
        with self._cond:
            self._items.append(item)
            self._cond.notify()

    def get(self, timeout: float) -> Any | None:
        with self._cond:
            if not self._items:
                self._cond.wait(timeout)
            return self._items.popleft() if self._items else None


def wake_latencies_us(box: Any, items: int, gap_s: float) -> list[float]:
    woke: list[float] = []
    done = threading.Event()

    def worker() -> None:
        while not done.is_set():
            stamp = box.get(timeout=0.05)
            if stamp is not None:
                woke.append((time.perf_counter_ns() - stamp) / 1e3)

    t = threading.Thread(target=worker)
    t.start()
    for _ in range(items):
        time.sleep(gap_s)
        box.put(time.perf_counter_ns())
    time.sleep(0.1)
    done.set()
    t.join()
    return woke


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--items", type=int, default=300, help="puts per round and kind")
    p.add_argument("--rounds", type=int, default=4)
    p.add_argument("--gap-ms", type=float, default=16.0, help="ms between puts (the worker sleeps meanwhile)")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "inbox.json"))
    args = p.parse_args()
    kinds = {"inbox": lambda: Inbox(64, keep="newest"), "simple_queue": BareQueue, "condition": ConditionQueue}
    samples: dict[str, list[float]] = {k: [] for k in kinds}
    for _ in range(args.rounds):
        for kind, make in kinds.items():
            samples[kind] += wake_latencies_us(make(), args.items, args.gap_ms / 1e3)[10:]  # the first wake-ups warm up
    summary = {k: {"count": len(v), "p50_us": round(statistics.median(v), 1),
                   "p90_us": round(statistics.quantiles(v, n=10)[-1], 1),
                   "p99_us": round(statistics.quantiles(v, n=100)[-1], 1)} for k, v in samples.items()}
    data = {"benchmark": "inbox", "what": __doc__.split("\n\n")[1].replace("\n", " "), "machine": report.machine(),
            "config": vars(args), "wake_up": summary,
            "p50_over_simple_queue_us": round(summary["inbox"]["p50_us"] - summary["simple_queue"]["p50_us"], 1),
            "p50_saved_over_condition_us": round(summary["condition"]["p50_us"] - summary["inbox"]["p50_us"], 1)}
    report.write_json(Path(args.out), data)
    for k, s in summary.items():
        print(f"{k:13s} p50 {s['p50_us']:6.1f}  p90 {s['p90_us']:6.1f}  p99 {s['p99_us']:6.1f} µs  ({s['count']} wake-ups)")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
