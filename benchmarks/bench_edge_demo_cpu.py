"""The edge's CPU in the demo configuration, for two source trees taken in turns in one run (before/after).

Each run starts ``iorthand edge`` with its tree's ``configs/edge-sim.yaml`` (the demo's edge: simulated robot,
force sensor on a phantom, servos, torch, synthetic camera with ArUco markers, camera and ultrasound video)
through one router, as ``iorthand demo`` does. An operator here acquires control and lowers the probe into the
phantom (about 5 N, below the caution level), then the run measures two phases of ``--seconds`` each:

- ``still``: the operator lets go, the robot rests in contact;
- ``moving``: the operator drives a square of 1 s legs at 20 mm/s in contact, as the demo's script does, so the
  camera sees a moving scene and every frame is rendered anew.

For each phase: the CPU time (user + system) of the edge process and of all its descendants (psutil), per
second of wall time in % of one core, and the edge process's own part (the control process: robot, supervisor,
commands, force, servos, torch); and each thread's, by the names the kernel shows (``threads``: the edge names
its threads, Zenoh's are rx-*, tx-*, ...; a tree that does not name them shows "python"). A subscriber here takes
every stream, as the twin and the recorder do (so the edge has to publish everything), and counts what arrives
per key: both trees must deliver the same work for the comparison to mean anything.

The operator is each tree's own ``OperatorClient`` (the command protocol may differ between the trees), in a
driver process of this script (``--drive``) that takes its orders on stdin; its CPU is not the edge's.

``--before`` is a checkout of the code to compare with, e.g. ``git worktree add --detach /tmp/iorthand-before
<commit>``; ``--after`` defaults to this repository. Each tree runs with its own packages first on PYTHONPATH.
Trees alternate (before, after, after, before, ...) so that other load on a shared machine hits both alike.

    .venv/bin/python benchmarks/bench_edge_demo_cpu.py --before /tmp/iorthand-before [--rounds 3] [--seconds 15]
        [--out benchmarks/results/edge_demo_cpu.json]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import psutil
import yaml
import zenoh

# Only what both trees have: this file also runs as the driver with the other tree first on PYTHONPATH.
from iorthand.transport import client_config, free_port, open_session

ROOT = Path(__file__).resolve().parent.parent
ROBOT = "demo1"
PACKAGES = (".", "edge", "operator", "cloud")  # a tree's import roots
CONTACT_DEPTH = 0.0025  # m into the phantom: ~5 N with the demo's 2000 N/m, below its 6 N caution level
SQUARE = ((0.02, 0.0), (0.0, -0.02), (-0.02, 0.0), (0.0, 0.02))  # m/s, 1 s each (the demo script's square)


def tree_env(tree: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(str(tree / p) for p in PACKAGES)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def describe(tree: Path) -> str:
    done = subprocess.run(["git", "-C", str(tree), "describe", "--always", "--dirty"], capture_output=True, text=True)
    return done.stdout.strip() or "?"


def wait_for(path: Path, text: str, proc: subprocess.Popen[bytes], timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"exited with {proc.returncode}: {path.read_text(errors='replace')[-2000:]}")
        if text in path.read_text(errors="replace"):
            return
        time.sleep(0.05)
    raise RuntimeError(f"no {text!r} within {timeout} s: {path.read_text(errors='replace')[-2000:]}")


def stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(10.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5.0)


class Tally:
    """Counts samples per key suffix (as the twin and recorder subscribe: everything of the robot)."""

    def __init__(self, session: zenoh.Session) -> None:
        self.counts: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(f"iorthand/{ROBOT}/**", self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        suffix = str(sample.key_expr).split("/", 2)[2]
        with self._lock:
            self.counts[suffix] += 1

    def snapshot(self) -> Counter[str]:
        with self._lock:
            return Counter(self.counts)


def cpu_seconds(proc: psutil.Process) -> dict[int, float]:
    """user + system CPU seconds of ``proc`` and of each of its descendants, by pid."""
    out = {}
    for p in (proc, *proc.children(recursive=True)):
        with contextlib.suppress(psutil.NoSuchProcess):
            t = p.cpu_times()
            out[p.pid] = t.user + t.system
    return out


def thread_ticks(proc: psutil.Process) -> dict[tuple[str, str], int]:
    """user + system clock ticks of every thread of ``proc`` and of its descendants, by (the process's name, the
    thread's name) as the kernel shows them (the edge names its threads: ``iorthand.process.name_thread``)."""
    out: dict[tuple[str, str], int] = Counter()
    for p in (proc, *proc.children(recursive=True)):
        with contextlib.suppress(OSError, psutil.NoSuchProcess):
            process = Path(f"/proc/{p.pid}/comm").read_text().strip()
            for task in Path(f"/proc/{p.pid}/task").iterdir():
                with contextlib.suppress(OSError):
                    stat = (task / "stat").read_text()
                    fields = stat[stat.rindex(")") + 2:].split()  # after the name, which may hold spaces
                    out[(process, (task / "comm").read_text().strip())] += int(fields[11]) + int(fields[12])
    return out


def measure(edge: psutil.Process, tally: Tally, seconds: float) -> dict[str, Any]:
    """CPU of the edge and its descendants over ``seconds``, and of each of their threads."""
    counts0 = tally.snapshot()
    ticks0 = thread_ticks(edge)
    cpu0, t0 = cpu_seconds(edge), time.monotonic()
    time.sleep(seconds)
    cpu1, t1 = cpu_seconds(edge), time.monotonic()
    ticks1 = thread_ticks(edge)
    wall = t1 - t0
    spent = {pid: cpu1[pid] - cpu0.get(pid, 0.0) for pid in cpu1}  # a child started meanwhile: all of its time
    control = spent.get(edge.pid, 0.0)
    total = sum(spent.values())
    rates = {k: round((n - counts0.get(k, 0)) / wall, 1) for k, n in sorted(tally.snapshot().items())}
    return {
        "wall_s": round(wall, 2),
        "cpu_percent_total": round(100 * total / wall, 1),  # % of one core: the edge and all its children
        "cpu_percent_control": round(100 * control / wall, 1),  # the edge process itself
        "cpu_percent_children": round(100 * (total - control) / wall, 1),
        "control_share_of_total": round(control / total, 3) if total else None,
        "processes": len(cpu1),
        "children_lost": sorted(set(cpu0) - set(cpu1)),  # a child that ended meanwhile: its time is missing
        "messages_per_s": rates,
        # % of one core per thread (name as the kernel shows it), by process name; the busiest first, 0.1 % and up.
        "threads": threads_percent(ticks0, ticks1, wall),
    }


def threads_percent(ticks0: dict[tuple[str, str], int], ticks1: dict[tuple[str, str], int], wall: float
                    ) -> dict[str, dict[str, float]]:
    hz = os.sysconf("SC_CLK_TCK")
    out: dict[str, dict[str, float]] = {}
    for (process, thread), n in sorted(ticks1.items(), key=lambda kv: ticks0.get(kv[0], 0) - kv[1]):
        percent = round(100 * (n - ticks0.get((process, thread), 0)) / hz / wall, 1)
        if percent >= 0.1:
            out.setdefault(process, {})[thread] = percent
    return out


def drive(endpoint: str, surface_z: float) -> int:
    """The driver process (``--drive``): this tree's operator client. Lowers the probe into the phantom, prints
    ``ready``, then obeys stdin: ``square`` (drive the square until the next line), ``rest``, ``quit`` (print
    what happened to the commands as JSON)."""
    from iorthand_operator.client import OperatorClient

    session = open_session(client_config(endpoint))
    op = OperatorClient(session, ROBOT, "bench-op", realtime=False, spin=False)
    op.wait_for_state(10.0)
    op.acquire("local")
    op.start()
    op.set_twist([0.0, 0.0, -0.02], [0.0, 0.0, 0.0], deadman=True)
    deadline = time.monotonic() + 15.0
    while op.robot_state is None or op.robot_state.tcp_pose[2] > surface_z - CONTACT_DEPTH:
        if time.monotonic() > deadline:
            raise RuntimeError(f"the probe did not reach the phantom: {op.robot_state}; {op.last_refusal}")
        time.sleep(0.005)
    op.set_twist([0.0] * 3, [0.0] * 3, deadman=False)
    time.sleep(0.5)  # the release tail; the robot at rest
    print("ready", flush=True)
    squaring = threading.Event()

    def square() -> None:
        leg = 0
        while True:
            squaring.wait()
            vx, vy = SQUARE[leg % len(SQUARE)]
            op.set_twist([vx, vy, 0.0], [0.0, 0.0, 0.0], deadman=True)
            time.sleep(1.0)
            leg += 1
            if not squaring.is_set():
                op.set_twist([0.0] * 3, [0.0] * 3, deadman=False)

    threading.Thread(target=square, daemon=True).start()
    for line in sys.stdin:
        order = line.strip()
        if order == "square":
            squaring.set()
        elif order == "rest":
            squaring.clear()
        elif order == "quit":
            break
    squaring.clear()
    op.set_twist([0.0] * 3, [0.0] * 3, deadman=False)
    result = {"sent": op.sent_count, "echoed": len(op.echoes), "refused": sum(not e.accepted for e in op.echoes),
              "last_refusal": op.last_refusal.reason if op.last_refusal else ""}
    print(json.dumps(result), flush=True)
    op.close()
    session.close()
    return 0


class Driver:
    """The parent's side of a driver process."""

    def __init__(self, tree: Path, endpoint: str, surface_z: float, log_path: Path) -> None:
        self._log = log_path.open("wb")
        self.proc = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "--drive", endpoint, "--surface-z", str(surface_z)],
            cwd=tree, env=tree_env(tree), stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._log, text=True)

    def expect(self, what: str) -> str:
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if what not in line:
            raise RuntimeError(f"operator driver: expected {what!r}, got {line!r} (exit {self.proc.poll()})")
        return line

    def order(self, what: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(what + "\n")
        self.proc.stdin.flush()

    def finish(self) -> dict[str, Any]:
        self.order("quit")
        result = json.loads(self.expect("{"))
        stop(self.proc)
        self._log.close()
        return result

    def kill(self) -> None:
        stop(self.proc)
        self._log.close()


def one_run(tree: Path, endpoint: str, workdir: Path, name: str, seconds: float, warmup: float,
            tally: Tally) -> dict[str, Any]:
    config = yaml.safe_load((tree / "configs" / "edge-sim.yaml").read_text())
    config["robot_id"] = ROBOT
    config["zenoh"]["connect"] = [endpoint]
    config_path = workdir / f"{name}.yaml"
    config_path.write_text(yaml.safe_dump(config))
    log_path = workdir / f"{name}.log"
    with log_path.open("wb") as log_file:
        proc = subprocess.Popen([sys.executable, "-m", "iorthand.cli", "edge", "--config", str(config_path)],
                                cwd=tree, env=tree_env(tree), stdout=log_file, stderr=subprocess.STDOUT)
    driver = None
    try:
        wait_for(log_path, "edge agent", proc, 60.0)
        time.sleep(warmup)  # imports, the first frames, the marker filters filling
        driver = Driver(tree, endpoint, config["phantom"]["surface_z"], workdir / f"{name}-operator.log")
        driver.expect("ready")
        edge = psutil.Process(proc.pid)
        result = {"tree": str(tree), "still": measure(edge, tally, seconds)}
        driver.order("square")
        result["moving"] = measure(edge, tally, seconds)
        driver.order("rest")
        result["commands"] = driver.finish()
        driver = None
        return result
    finally:
        if driver is not None:
            driver.kill()
        stop(proc)


def summarise(runs: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for variant, results in runs.items():
        out[variant] = {}
        for phase in ("still", "moving"):
            phases = [r[phase] for r in results]
            out[variant][phase] = {
                field: statistics.median(p[field] for p in phases)
                for field in ("cpu_percent_total", "cpu_percent_control", "cpu_percent_children")
            }
            for key in ("video/camera", "video/ultrasound", "markers", "state/robot"):
                out[variant][phase][f"{key} per s"] = statistics.median(p["messages_per_s"].get(key, 0.0) for p in phases)
            # Where the time went: the threads of the run whose total was the median.
            ordered = sorted(phases, key=lambda p: p["cpu_percent_total"])
            out[variant][phase]["threads_of_the_median_run"] = ordered[(len(ordered) - 1) // 2]["threads"]
    if "before" in out and "after" in out:
        out["after_over_before"] = {
            phase: round(out["after"][phase]["cpu_percent_total"] / out["before"][phase]["cpu_percent_total"], 3)
            for phase in ("still", "moving")
        }
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--drive", metavar="ENDPOINT", help=argparse.SUPPRESS)  # the driver process
    parser.add_argument("--surface-z", type=float, help=argparse.SUPPRESS)
    parser.add_argument("--before", type=Path, help="the source tree to compare with (required)")
    parser.add_argument("--after", type=Path, default=ROOT, help="the source tree measured (default: this one)")
    parser.add_argument("--rounds", type=int, default=3, help="runs of each tree")
    parser.add_argument("--seconds", type=float, default=15.0, help="length of each phase")
    parser.add_argument("--warmup", type=float, default=3.0, help="s after the edge is up before measuring")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "edge_demo_cpu.json")
    args = parser.parse_args()
    if args.drive:
        return drive(args.drive, args.surface_z)
    if args.before is None:
        parser.error("--before is required: a checkout of the code to compare with")
    from iorthand_operator.bench.report import machine, write_json

    trees = {"before": args.before.resolve(), "after": args.after.resolve()}
    for tree in trees.values():
        if not (tree / "configs" / "edge-sim.yaml").is_file():
            parser.error(f"{tree} is not a source tree of this project (no configs/edge-sim.yaml)")

    host = machine()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    workdir = Path(tempfile.mkdtemp(prefix="iorthand-edgecpu-"))
    router_log = (workdir / "router.log").open("wb")
    router = subprocess.Popen([sys.executable, "-m", "iorthand.cli", "router", "--listen", endpoint],
                              stdout=router_log, stderr=subprocess.STDOUT)
    runs: dict[str, list[dict[str, Any]]] = {"before": [], "after": []}
    session = None
    try:
        wait_for(workdir / "router.log", "router ready", router, 30.0)
        session = open_session(client_config(endpoint))
        tally = Tally(session)
        for round_ in range(args.rounds):
            order = ("before", "after") if round_ % 2 == 0 else ("after", "before")
            for variant in order:
                result = one_run(trees[variant], endpoint, workdir, f"{variant}-{round_}", args.seconds, args.warmup,
                                 tally)
                runs[variant].append(result)
                print(f"round {round_ + 1} {variant:6s}: " + "; ".join(
                    f"{phase} {result[phase]['cpu_percent_total']:.1f} % of a core "
                    f"(control {result[phase]['cpu_percent_control']:.1f} %)" for phase in ("still", "moving")),
                    flush=True)
    finally:
        if session is not None:
            session.close()
        stop(router)
        router_log.close()
    summary = summarise(runs)
    data = {
        "benchmark": "edge_demo_cpu",
        "machine": host,
        "load_average_at_end": list(os.getloadavg()),
        "config": {"trees": {k: {"path": str(v), "version": describe(v)} for k, v in trees.items()},
                   "rounds": args.rounds, "seconds": args.seconds, "warmup": args.warmup,
                   "contact_depth_m": CONTACT_DEPTH, "workdir": str(workdir)},
        "summary": summary,
        "runs": runs,
    }
    path = write_json(args.out, data)
    print(json.dumps(summary, indent=1))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
