"""Edge memory under a flood of hostile input, and the legitimate operator's control during it (issue 20).

Processes: a Zenoh router (``iorthand router``), the edge agent (``iorthand edge`` with configs/edge-sim.yaml:
simulated robot, video and perception, auto-armed, operator keys bound so that per-operator sub-keys reach
it), an :class:`OperatorClient` ``alice`` that holds control and drives back and forth with the deadman
pressed (released for 0.1 s at each reversal, as a hand does), and an attacker session that sends
``--messages`` malformed payloads round-robin over every input of the edge: puts on cmd/twist, cmd/stop,
cmd/servo, cmd/torch and on fresh sub-keys cmd/twist/<random> (each one new: a table keyed by the key grows
with every one), queries on control/* and control/acquire/<random>; plus ``--big`` payloads of ``--big-mb`` MB
spread through the flood on the same inputs. Nothing the attacker sends is a valid command.

The edge's RSS (its main process, and with its child processes) is sampled every 0.1 s: at the start (mean of
the last second before the flood), its peak, and ``--settle`` s after the flood's last message. The operator's
figures: echoes by status during the flood and the settling time, the longest gap between accepted echoes,
``not_owner`` refusals, lease expiries and owner losses in state/safety, and whether it still owns the robot.
A malformed cmd/stop is still a stop (stopping is the safe side), so ``stopped`` refusals are expected until
the next deadman press; losing control is not.

Writes benchmarks/results/flood_memory.json.

    .venv/bin/python benchmarks/bench_flood_memory.py [--messages 100000] [--big 20] [--big-mb 10] [--settle 10]
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import random
import statistics
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import msgpack
import psutil
import zenoh
from teleop_stack import (
    CONFIGS,
    RESULTS,
    Watcher,
    close_operator,
    edge_config,
    lease_lost,
    operator,
    start_edge,
    start_router,
)

from iorthand import keys
from iorthand.protocol import Status, TwistCommand
from iorthand.transport import client_config, free_port, open_session
from iorthand_operator.bench.procs import Group
from iorthand_operator.bench.report import machine, write_json
from iorthand_operator.client import OperatorClient

ROBOT = "sim1"
SPEED = 0.005  # m/s, within the remote profile's 8 mm/s: the robot moves, nothing is clipped


def garbage(rng: random.Random, i: int) -> bytes:
    """One malformed payload of many kinds: random bytes, truncated or wrong-typed msgpack, NaN, nesting,
    a huge array header, a map of junk just under the 64 KB limit of a command."""
    valid = TwistCommand(operator="alice", linear=[SPEED, 0, 0], deadman=True).stamp(i).encode()
    kind = i % 7
    if kind == 0:
        return rng.randbytes(rng.randint(0, 256))
    if kind == 1:
        return valid[: rng.randint(0, len(valid) - 1)]
    if kind == 2:
        return msgpack.packb({"v": 1, "seq": i, "t": time.time_ns(), "operator": "alice",
                              "linear": [float("nan"), 0, 0], "angular": [0, 0, 0], "deadman": True})
    if kind == 3:
        return msgpack.packb({"v": 1, "seq": 2**64 - 1, "t": -1, "operator": 5, "linear": "fast", "deadman": 1})
    if kind == 4:
        return b"\x91" * 2000 + b"\xc0"
    if kind == 5:
        return b"\xdd\xff\xff\xff\xff" + b"\x00" * 16
    return msgpack.packb({"v": 1, "x": rng.randbytes(60_000)})


class Attacker:
    """A session that sends malformed input to every key the edge listens on."""

    def __init__(self, endpoint: str, seed: int = 20) -> None:
        self.session = open_session(client_config(endpoint, shared_memory=False))
        self.rng = random.Random(seed)
        self.k = keys.RobotKeys(ROBOT)
        self.payloads = [garbage(self.rng, i) for i in range(210)]
        # BLOCK: every message is delivered to the router rather than dropped in the attacker's own queue.
        self.pubs = {suffix: self.session.declare_publisher(self.k.key(suffix),
                                                           congestion_control=zenoh.CongestionControl.BLOCK)
                     for suffix in (keys.CMD_TWIST, keys.CMD_STOP, keys.CMD_SERVO, keys.CMD_TORCH)}
        self.queries = [keys.CONTROL_ACQUIRE, keys.CONTROL_RELEASE, keys.CONTROL_ARM, keys.CONTROL_FORCE_ZERO,
                        keys.CONTROL_GOTO, keys.CONTROL_POSES]
        self.sent: Counter[str] = Counter()

    def _query(self, key: str, payload: bytes) -> None:
        # Replies are ignored (a callback that drops them); the short timeout bounds the attacker's own state.
        self.session.get(key, lambda _reply: None, payload=payload, timeout=1.0)

    def send(self, i: int, payload: bytes) -> None:
        """Message ``i`` of the flood: inputs in turn, a fresh random sub-key every third message."""
        slot = i % 12
        if slot < 4:
            suffix = list(self.pubs)[slot]
            self.pubs[suffix].put(payload)
            self.sent[suffix] += 1
        elif slot < 8:
            self.session.put(f"{self.k.key(keys.CMD_TWIST)}/{self.rng.getrandbits(64):016x}", payload,
                             congestion_control=zenoh.CongestionControl.BLOCK)
            self.sent[keys.CMD_TWIST + "/<random>"] += 1
        elif slot < 10:
            suffix = self.queries[(i // 12) % len(self.queries)]
            self._query(self.k.key(suffix), payload)
            self.sent[suffix] += 1
        else:
            self._query(f"{self.k.key(keys.CONTROL_ACQUIRE)}/{self.rng.getrandbits(64):016x}", payload)
            self.sent[keys.CONTROL_ACQUIRE + "/<random>"] += 1

    def flood(self, n: int, big: int, big_bytes: int) -> None:
        big_every = max(1, n // big) if big else 0
        big_payload = msgpack.packb({"v": 1, "operator": "alice", "x": b"\x00" * big_bytes})
        for i in range(n):
            self.send(i, self.payloads[i % len(self.payloads)])
            if big_every and i % big_every == big_every // 2 and self.sent["big"] < big:
                # The big ones go to the same inputs in turn (i varies, so does the slot).
                self.send(i // big_every, big_payload)
                self.sent["big"] += 1

    def close(self) -> None:
        self.session.close()


class RssSampler(threading.Thread):
    """The RSS of a process (alone, and with its children) every ``period`` s: (monotonic, rss, rss_tree)."""

    def __init__(self, pid: int, period: float = 0.1) -> None:
        super().__init__(name="rss-sampler", daemon=True)
        self.proc = psutil.Process(pid)
        self.period = period
        self.samples: list[tuple[float, int, int]] = []
        self.stop_event = threading.Event()

    def run(self) -> None:
        while not self.stop_event.wait(self.period):
            try:
                rss = self.proc.memory_info().rss
                tree = rss + sum(c.memory_info().rss for c in self.proc.children(recursive=True))
            except psutil.Error:
                return
            self.samples.append((time.monotonic(), rss, tree))

    def between(self, t0: float, t1: float, column: int = 1) -> list[int]:
        return [s[column] for s in self.samples if t0 <= s[0] <= t1]


def drive(op: OperatorClient, stop: threading.Event, period: float = 0.5, release: float = 0.1) -> None:
    """Back and forth along x, the deadman released for ``release`` s at each reversal (a fresh press also
    clears the stop that a garbled cmd/stop causes, as it would for a person). The input is given at 20 Hz,
    as a UI does: the client releases the deadman itself when its input goes silent."""
    t0 = time.monotonic()
    while not stop.wait(0.05):
        phase, cycle = math.modf((time.monotonic() - t0) / period)
        pressed = phase * period < period - release
        direction = 1.0 if int(cycle) % 2 == 0 else -1.0
        op.set_twist([direction * SPEED if pressed else 0.0, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=pressed)


def mb(nbytes: float) -> float:
    return round(nbytes / 2**20, 1)


def longest_gap_s(times_ns: list[int]) -> float:
    return max((b - a for a, b in itertools.pairwise(times_ns)), default=0) / 1e9


def run(args: argparse.Namespace) -> dict[str, Any]:
    workdir = Path(tempfile.mkdtemp(prefix="iorthand-flood-"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Group(workdir) as group:
        start_router(group, endpoint)
        cfg = edge_config(CONFIGS / "edge-sim.yaml", workdir / "edge.yaml", endpoint,
                          {"safety": {"auto_arm": True}, "bind_operator_keys": args.bind_keys})
        edge = start_edge(group, cfg)
        watcher = Watcher(endpoint, ROBOT)
        op = operator(endpoint, ROBOT, "alice", bind_keys=args.bind_keys)
        stop = threading.Event()
        driver = threading.Thread(target=drive, args=(op, stop), name="operator-drive", daemon=True)
        driver.start()
        rss = RssSampler(edge.pid)
        rss.start()
        attacker: Attacker | None = None
        try:
            time.sleep(args.warmup)  # the edge's start-up allocations (video, perception) settle
            attacker = Attacker(endpoint)
            time.sleep(0.5)  # the attacker's declarations reach the router
            t0 = time.monotonic()
            t0_ns = time.time_ns()
            attacker.flood(args.messages, args.big, args.big_mb * 2**20)
            t1 = time.monotonic()
            time.sleep(args.settle)
            t2 = time.monotonic()
            t2_ns = time.time_ns()
            owner_at_end = op.owner
        finally:
            stop.set()
            driver.join(2.0)
            rss.stop_event.set()
            if attacker is not None:
                attacker.close()
            close_operator(op)
            watcher.close()
            alive = edge.proc is not None and edge.proc.poll() is None
        seen = watcher.snapshot()
    start = rss.between(t0 - 1.0, t0)
    start_tree = rss.between(t0 - 1.0, t0, column=2)
    after = rss.between(t2 - 0.5, t2)
    after_tree = rss.between(t2 - 0.5, t2, column=2)
    peak = max(rss.between(t0, t2))
    window = [e for e in op.echoes if t0_ns <= e.sent_ns <= t2_ns]
    safety = [s for t, s in seen.safety if t0_ns <= t <= t2_ns]
    return {
        "benchmark": "flood_memory",
        "config": {"messages": args.messages, "big": args.big, "big_mb": args.big_mb, "settle_s": args.settle,
                   "warmup_s": args.warmup, "bind_operator_keys": args.bind_keys, "edge_config": "configs/edge-sim.yaml",
                   "workdir": str(workdir), "malloc_env": {k: v for k, v in os.environ.items() if k.startswith("MALLOC_")}},
        "attacker": {"sent": dict(attacker.sent) if attacker else {}, "seconds": round(t1 - t0, 2),
                     "rate_per_s": round(args.messages / (t1 - t0))},
        "edge_rss_mb": {
            "start": mb(statistics.fmean(start)), "peak": mb(peak), "after": mb(statistics.fmean(after)),
            "after_minus_start": mb(statistics.fmean(after) - statistics.fmean(start)),
            "with_children_start": mb(statistics.fmean(start_tree)), "with_children_after": mb(statistics.fmean(after_tree)),
            "series": [(round(t - t0, 2), mb(r)) for t, r, _ in rss.samples[::5]],
        },
        "edge_alive": alive,
        "edge_malformed_counted": max((s.malformed for s in safety), default=0),
        "operator": {
            "echoes": len(window),
            "echo_status": dict(Counter(str(e.status) for e in window)),
            "not_owner": sum(e.status == Status.NOT_OWNER for e in window),
            "longest_gap_between_accepted_s": round(longest_gap_s([e.echoed_ns for e in window if e.accepted]), 3),
            "lease_lost_reports": sum(lease_lost(s) for s in safety),
            "safety_status": dict(Counter(f"{s.status}: {s.reason[:60]}" for s in safety)),
            "owner_at_end": owner_at_end,
            "owner_in_safety_at_end": safety[-1].owner if safety else "",
        },
        "machine": machine(),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=100_000)
    ap.add_argument("--big", type=int, default=20, help="payloads of --big-mb MB among them")
    ap.add_argument("--big-mb", type=int, default=10)
    ap.add_argument("--settle", type=float, default=10.0, help="s after the flood when RSS is read again")
    ap.add_argument("--warmup", type=float, default=10.0, help="s of driving before the flood")
    ap.add_argument("--no-bind-keys", dest="bind_keys", action="store_false",
                    help="the edge's default keys: per-operator sub-keys then reach nothing")
    ap.add_argument("--out", type=Path, default=RESULTS / "flood_memory.json")
    args = ap.parse_args()
    result = run(args)
    write_json(args.out, result)
    r, o = result["edge_rss_mb"], result["operator"]
    print(f"flood: {args.messages} malformed + {args.big} × {args.big_mb} MB in {result['attacker']['seconds']} s; "
          f"edge RSS start {r['start']} MB, peak {r['peak']} MB, {args.settle:.0f} s after {r['after']} MB "
          f"(Δ {r['after_minus_start']:+.1f} MB); operator: {o['echoes']} echoes {o['echo_status']}, "
          f"not_owner {o['not_owner']}, lease lost {o['lease_lost_reports']}, owner at end {o['owner_at_end']} → {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
