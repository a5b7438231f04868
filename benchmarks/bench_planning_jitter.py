"""The control loop's rhythm while the edge plans, for two source trees taken in turns in one run (before/after).

Each run starts a router and ``iorthand edge`` with its tree's ``configs/edge-sim.yaml`` (simulated robot, the
media process with video and perception), records the arrival times of ``state/robot`` (published by the
control loop at every cycle, 125 Hz) and measures the gaps between them in two phases of ``--seconds`` each:

- ``quiet``: nothing asked of the edge;
- ``planning``: previews of the longest sweep the edge accepts (50 lanes of 15 cm, 1 mm apart: ~1.7 s of
  planning each), back to back, one at a time, as an operator previewing again and again would.

A gap longer than the 8 ms period is a cycle the control loop ran late; a deadman stop waits for the loop. Trees
alternate (before, after, after, before, ...) so that other load on a shared machine hits both alike.

    .venv/bin/python benchmarks/bench_planning_jitter.py --before /tmp/iorthand-before [--rounds 2] [--seconds 8]
        [--out benchmarks/results/planning_jitter.json]
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from iorthand.transport import client_config, free_port, open_session

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_edge_demo_cpu import describe, stop, tree_env, wait_for  # noqa: E402

ROBOT = "jitter1"
SWEEP = {"lanes": 50, "width": 0.15, "pitch": 0.001}
PERIOD_MS = 8.0


def gaps_ms(arrivals: list[float]) -> dict[str, float]:
    gaps = sorted(1000.0 * (b - a) for a, b in itertools.pairwise(arrivals))
    if not gaps:
        return {"count": 0}
    return {
        "count": len(gaps),
        "p50": round(statistics.median(gaps), 2),
        "p99": round(gaps[min(len(gaps) - 1, int(0.99 * len(gaps)))], 2),
        "max": round(gaps[-1], 2),
        "late_cycles": sum(int(g // PERIOD_MS) - 1 for g in gaps if g >= 2 * PERIOD_MS),
    }


def run_tree(tree: Path, seconds: float, workdir: Path) -> dict[str, Any]:
    from iorthand import keys
    from iorthand.protocol import ControlRequest

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    config = yaml.safe_load((tree / "configs" / "edge-sim.yaml").read_text())
    config["robot_id"] = ROBOT
    config["zenoh"]["connect"] = [endpoint]
    config_path = workdir / f"edge-{port}.yaml"
    config_path.write_text(yaml.safe_dump(config))
    env = tree_env(tree)
    router_log, edge_log = workdir / f"router-{port}.log", workdir / f"edge-{port}.log"
    router = subprocess.Popen([sys.executable, "-m", "iorthand.cli", "router", "--listen", endpoint],
                              env=env, stdout=router_log.open("wb"), stderr=subprocess.STDOUT)
    edge = None
    session = None
    try:
        wait_for(router_log, "router ready", router, 20.0)
        edge = subprocess.Popen([sys.executable, "-m", "iorthand.cli", "edge", "--config", str(config_path)],
                                env=env, stdout=edge_log.open("wb"), stderr=subprocess.STDOUT)
        wait_for(edge_log, f"edge agent '{ROBOT}' up", edge, 60.0)
        session = open_session(client_config(endpoint))
        k = keys.RobotKeys(ROBOT)
        arrivals: list[float] = []
        session.declare_subscriber(k.key(keys.STATE_ROBOT), lambda _s: arrivals.append(time.monotonic()))
        time.sleep(3.0)  # warm-up: the media process up, its first frames out
        t0 = time.monotonic()
        time.sleep(seconds)
        quiet = gaps_ms([t for t in arrivals if t >= t0])
        t1 = time.monotonic()
        previews: list[float] = []
        seq = 0
        while time.monotonic() - t1 < seconds:
            seq += 1
            req = ControlRequest(operator="bench", name="sweep", params=json.dumps(SWEEP)).stamp(seq)
            asked = time.monotonic()
            replies = list(session.get(k.key(keys.PLAN_PREVIEW), payload=req.encode(), timeout=30.0))
            if not any(r.ok is not None for r in replies):
                raise RuntimeError(f"preview {seq} not answered: {edge_log.read_text(errors='replace')[-1000:]}")
            previews.append(round(time.monotonic() - asked, 3))
        planning = gaps_ms([t for t in arrivals if t >= t1])
        return {"tree": describe(tree), "quiet": quiet, "planning": planning, "preview_s": previews}
    finally:
        if session is not None:
            session.close()
        for proc in (edge, router):
            if proc is not None:
                stop(proc)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", type=Path, required=True, help="a checkout of the code to compare with")
    parser.add_argument("--after", type=Path, default=ROOT)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "planning_jitter.json")
    args = parser.parse_args()
    runs: dict[str, list[dict[str, Any]]] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory(prefix="iorthand-jitter-") as tmp:
        for i in range(args.rounds):
            order = ("before", "after") if i % 2 == 0 else ("after", "before")
            for label in order:
                result = run_tree(getattr(args, label), args.seconds, Path(tmp))
                runs[label].append(result)
                print(label, json.dumps(result), flush=True)
    out = {
        "benchmark": "planning_jitter",
        "what": "gaps between state/robot samples (the control loop, 125 Hz), quiet and during back-to-back "
                f"previews of a sweep {SWEEP}, one edge from configs/edge-sim.yaml",
        "config": {"rounds": args.rounds, "seconds": args.seconds, "period_ms": PERIOD_MS,
                   "trees": {label: describe(getattr(args, label)) for label in ("before", "after")}},
        "runs": runs,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
