"""What the full security stack (TLS + mTLS + user/password + ACL) costs on the command path, versus plain TCP.

One process holds two routers on loopback — plain TCP and the generated secure configuration — and, for each,
an "operator" session (operator-alice) and an "edge" session (edge-sim1). The operator puts a TwistCommand on
``iorthand/sim1/cmd/twist``; the edge's callback echoes it at once on ``state/applied``; the round trip crosses
the router twice. Blocks of pings alternate between the two stacks so that load from other processes on the
machine hits both alike. The one-way command-path overhead is half the difference of the round-trip medians.

    .venv/bin/python benchmarks/bench_security.py [--n 3000] [--out benchmarks/results/security.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import threading
import time
from pathlib import Path

import zenoh

from iorthand import keys
from iorthand.protocol import TwistCommand
from iorthand.security.lab import make_lab
from iorthand.transport import ZenohConfig, client_config, free_port, open_session, publisher, router_json5


class Pair:
    def __init__(self, op_cfg: ZenohConfig, edge_cfg: ZenohConfig) -> None:
        k = keys.RobotKeys("sim1")
        self.op = open_session(op_cfg)
        self.edge = open_session(edge_cfg)
        self.echo_pub = publisher(self.edge, k.key(keys.STATE_APPLIED))
        self.cmd_pub = publisher(self.op, k.key(keys.CMD_TWIST))
        self.got = threading.Event()
        self.edge.declare_subscriber(k.key(keys.CMD_TWIST), lambda s: self.echo_pub.put(s.payload.to_bytes()))
        self.op.declare_subscriber(k.key(keys.STATE_APPLIED), lambda s: self.got.set())
        self.payload = TwistCommand(operator="alice", linear=[0.001, 0, 0], deadman=True).stamp(1).encode()
        time.sleep(0.5)

    def ping(self) -> float:
        self.got.clear()
        t0 = time.perf_counter_ns()
        self.cmd_pub.put(self.payload)
        if not self.got.wait(1.0):
            return float("nan")
        return (time.perf_counter_ns() - t0) / 1e6

    def close(self) -> None:
        self.op.close()
        self.edge.close()


def pct(xs: list[float], p: float) -> float:
    xs = sorted(x for x in xs if x == x)
    return xs[min(len(xs) - 1, int(p / 100 * len(xs)))]


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=3000, help="round trips per stack")
    ap.add_argument("--block", type=int, default=100)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "security.json"))
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        lab = make_lab(Path(tmp), free_port(), robots=["sim1"], operators={"alice": ["sim1"]})
        tcp_ep = f"tcp/127.0.0.1:{free_port()}"
        routers = [zenoh.open(zenoh.Config.from_json5(router_json5(tcp_ep))),
                   zenoh.open(zenoh.Config.from_file(str(lab.router_config)))]
        # Shared memory off: it would bypass the link layer on one host, and it does not exist between sites.
        plain = Pair(client_config(tcp_ep, shared_memory=False), client_config(tcp_ep, shared_memory=False))
        op, edge = lab.client("operator-alice"), lab.client("edge-sim1")
        op.shared_memory = edge.shared_memory = False
        secure = Pair(op, edge)
        rtt: dict[str, list[float]] = {"tcp": [], "secure": []}
        for _ in range(50):  # warm-up
            plain.ping()
            secure.ping()
        done = 0
        while done < args.n:
            for name, pair in (("tcp", plain), ("secure", secure)):
                for _ in range(args.block):
                    rtt[name].append(pair.ping())
                    time.sleep(0.001)
            done += args.block
        plain.close()
        secure.close()
        for r in routers:
            r.close()
    res: dict[str, object] = {"n": args.n, "payload_bytes": len(TwistCommand(operator="alice").stamp(1).encode())}
    for name, xs in rtt.items():
        res[name] = {"rtt_p50_ms": round(statistics.median(x for x in xs if x == x), 4), "rtt_p99_ms": round(pct(xs, 99), 4),
                     "lost": sum(1 for x in xs if x != x)}
    t, s = res["tcp"], res["secure"]  # type: ignore[assignment]
    res["one_way_overhead_p50_ms"] = round((s["rtt_p50_ms"] - t["rtt_p50_ms"]) / 2, 4)
    res["one_way_overhead_p99_ms"] = round((s["rtt_p99_ms"] - t["rtt_p99_ms"]) / 2, 4)
    res["stack"] = "TLS 1.3 (rustls, ECDSA P-256) + mTLS + user/password + ACL (default deny, generated)"
    res["load_average"] = list(__import__("os").getloadavg())
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=2) + "\n")
    print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
