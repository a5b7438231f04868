"""iorthand's command path against a bare Zenoh echo, interleaved, through one router (issue 20).

One run starts one router (``iorthand router``, 127.0.0.1, free port, no shared memory), a bare Zenoh echo (a
process that subscribes to a key and republishes each payload at once from its callback, with the command QoS
of ``QOS_BY_KEY``) and, in turn, a real edge agent (``iorthand edge``, the simulated robot from
``configs/edge-sim.yaml`` with auto-arm and the bench router) in two variants:

- ``plain``: no video, no perception (force, servos and torch simulated as in edge-sim.yaml);
- ``video``: 30 fps camera video from the perception camera + perception, as in edge-sim.yaml, with a video
  subscriber on the operator side so the frames really cross the router;
- ``video-apart`` (not by default): the same video + perception load from a second edge process (robot
  ``bench-media``) while the commands go through a plain edge: what moving media out of the control process gives.

In each phase one client process runs the real ``OperatorClient`` (acquire, deadman held, 60 Hz twists, the
edge's ``state/applied`` echo timed by the client itself) and, on the same Zenoh session, a bare ping of the
same payload size and QoS half a period after each twist: bare and iorthand round trips alternate over the
same link, router and CPUs. Phases alternate (plain, video, plain, video, ...) over ``--rounds``.

Writes ``benchmarks/results/command_path.json``: p50/p99/max of bare and iorthand per variant, their
difference, the video/plain p99 ratio and the targets of issue 20 (PASS/MISS).

Variants of the code: ``--edge-pythonpath LABEL=DIR ...`` runs the edge and the operator's client from other
source trees (copies of the repository: their core, edge and operator code), taking turns in every round, or with
``--side-by-side`` all at once (robot ``bench-<LABEL>`` each, a client process each, their ticks spread over the
period from one instant, their slots rotating from round to round): the fairest comparison on a noisy machine.
An edge that writes per-command stamps gets a per-hop breakdown (the JSON's ``hops``): at shutdown it writes to
``$IORTHAND_HOPS_OUT`` a JSON map ``{cmd_seq: {stamp name: wall-clock ns, ...}}`` in path order (``"router"``: the router's HLC timestamp on the
sample, ``sample.timestamp.get_time_as_ntp64().as_nanos()``); the shipped edge writes none.

    .venv/bin/python benchmarks/bench_command_path.py            # ~2.5 min: 2 rounds x 2 variants x 25 s
    .venv/bin/python benchmarks/bench_command_path.py --duration 10 --rounds 1   # smoke test
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import struct
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parent.parent
PING_KEY = "iorthand/_bench/bare/ping"
PONG_KEY = "iorthand/_bench/bare/pong"
ROBOT = "bench"
OPERATOR = "bench-op"
TARGETS = {"diff_p50_ms": 0.15, "diff_p99_ms": 0.5, "video_p99_ratio": 1.3}
# A bare echo slower than this at p99 means the host, not the middleware, set the tail (a quiet host of this
# kind: 1.45 ms with video, FACTS.md): the targets are still computed, and flagged as measured on a noisy host.
NOISY_BARE_P99_MS = 5.0


# ------------------------------------------------------------------------------------------------ children


def _session(connect: str) -> Any:
    from iorthand.transport import ZenohConfig, open_session

    return open_session(ZenohConfig(mode="client", connect=[connect], shared_memory=False, connect_retry_s=30.0))


def _stop_on_signals() -> threading.Event:
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def role_echo(args: argparse.Namespace) -> int:
    """The bare echo: every payload on PING_KEY goes back on PONG_KEY from the callback, untouched."""
    from iorthand import keys
    from iorthand.transport import QOS_BY_KEY, publisher

    stop = _stop_on_signals()
    session = _session(args.connect)
    pub = publisher(session, PONG_KEY, QOS_BY_KEY[keys.CMD_TWIST])
    sub = session.declare_subscriber(PING_KEY, lambda s: pub.put(s.payload.to_bytes()))
    print("echo ready", flush=True)
    stop.wait(args.max_seconds)
    sub.undeclare()
    session.close()
    return 0


def role_video_sub(args: argparse.Namespace) -> int:
    """The operator's video view: takes every camera frame through a ring channel and counts them."""
    import zenoh

    from iorthand import keys

    stop = _stop_on_signals()
    session = _session(args.connect)
    robots = args.robots.split(",")
    subs = [session.declare_subscriber(keys.RobotKeys(r).key(keys.VIDEO_CAMERA), zenoh.handlers.RingChannel(4))
            for r in robots]
    frames = 0
    print("video-sub ready", flush=True)
    t0 = time.monotonic()
    while not stop.is_set() and time.monotonic() - t0 < args.max_seconds:
        got = sum(sub.try_recv() is not None for sub in subs)
        frames += got
        if not got:
            stop.wait(0.005)
    Path(args.out).write_text(json.dumps({"frames": frames / len(robots), "seconds": time.monotonic() - t0}))
    session.close()
    return 0


def role_client(args: argparse.Namespace) -> int:
    """OperatorClient twists at ``--rate`` and bare pings half a period after each, on one session. Side by side
    (``--slots N``: N trees, one client process each, this one's robots from ``--first-slot``), every client's
    ticks spread evenly over the period from a common instant (the orchestrator writes it to ``--start-file`` once
    every client holds control), and the bare pings (only the process with ``--bare``) in the last slot."""
    import numpy as np

    from iorthand import keys
    from iorthand.transport import QOS_BY_KEY, publisher
    from iorthand_operator.client import OperatorClient

    stop = _stop_on_signals()
    session = _session(args.connect)
    robots = args.robots.split(",")
    # Several senders: sleeping ones (a spinning sender holds a CPU the others' echoes need, or their GIL).
    extra: dict[str, Any] = {"spin": False} if args.slots > 1 else {}
    clients = [OperatorClient(session, r, OPERATOR, rate_hz=args.rate, **extra) for r in robots]
    bare: list[tuple[int, int]] = []  # (t1, t4) ns
    pad = b"\0" * max(0, args.size - 16)

    def on_pong(sample: Any) -> None:
        t4 = time.time_ns()
        _, t1 = struct.unpack_from("<qq", sample.payload.to_bytes())
        bare.append((t1, t4))

    ping_pub = publisher(session, PING_KEY, QOS_BY_KEY[keys.CMD_TWIST])
    pong_sub = session.declare_subscriber(PONG_KEY, on_pong)
    period = 1.0 / args.rate
    slot = period / (args.slots + 1)
    speed = 0.005
    try:
        for client in clients:
            client.wait_for_state(timeout=60.0)
            deadline = time.monotonic() + 30.0
            while True:
                try:
                    client.acquire()
                    break
                except Exception:  # refused or not answered yet (the edge may still be starting)
                    if time.monotonic() > deadline or stop.is_set():
                        raise
                    stop.wait(0.3)
        t_start = time.monotonic()
        print(f"client code: {Path(sys.modules[OperatorClient.__module__].__file__).parent}", flush=True)
        if args.start_file:
            print("client acquired", flush=True)
            start_file = Path(args.start_file)
            while not start_file.exists() and not stop.is_set() and time.monotonic() - t_start < 120.0:
                time.sleep(0.005)
            t_start = float(start_file.read_text())  # CLOCK_MONOTONIC: one clock for every process of this host
        for i, client in enumerate(clients, start=args.first_slot):
            client.set_twist([0.0, speed, 0.0], np.zeros(3), deadman=True)
            delay = t_start + i * slot - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            client.start()
        send_times = getattr(clients[0], "send_times", None)
        while send_times is not None and not send_times and time.monotonic() - t_start < 2.0:
            time.sleep(0.001)
        t0 = send_times[0] - args.first_slot * slot if send_times else t_start  # slot 0's first tick
        # The bare ping: half a period after the tick with one robot, else in the slot after the last robot's.
        offset = 0.5 * period if args.slots == 1 else args.slots * slot
        measure_from = time.time_ns() + int(args.warmup * 1e9)
        end = time.monotonic() + args.warmup + args.duration
        n, flip = 0, time.monotonic() + 2.0
        print("client running", flush=True)
        while not stop.is_set() and time.monotonic() < end:
            n += 1
            # Half a period after the sender's tick n: the twist's echo is back, the next twist is far.
            target = t0 + (n - 1) * period + offset
            delay = target - time.monotonic()
            if delay < -period:  # fell behind (a stall): skip ahead, never burst
                n = int((time.monotonic() - t0) / period) + 1
                continue
            if delay > 0:
                stop.wait(delay)
            if args.bare:
                ping_pub.put(struct.pack("<qq", n, time.time_ns()) + pad)
            if time.monotonic() > flip:  # back and forth along y, as an operator would
                speed, flip = -speed, time.monotonic() + 2.0
                for client in clients:
                    client.set_twist([0.0, speed, 0.0], np.zeros(3), deadman=True)
        measure_until = time.time_ns()
        for client in clients:
            client.set_twist(np.zeros(3), np.zeros(3), deadman=False)
        time.sleep(0.5)
        out: dict[str, Any] = {"bare": [b for b in bare if measure_from <= b[0] < measure_until],
                               "twist_bytes": args.size, "robots": {}}
        for r, client in zip(robots, clients, strict=True):
            echoes = [(e.seq, e.sent_ns, e.echoed_ns, bool(e.accepted), str(e.status)) for e in list(client.echoes)
                      if measure_from <= e.sent_ns < measure_until]
            out["robots"][r] = {"iorthand": echoes, "refused": sum(1 for e in echoes if not e[3])}
        Path(args.out).write_text(json.dumps(out))
        return 0
    finally:
        pong_sub.undeclare()
        for client in clients:
            with contextlib.suppress(Exception):
                client.close()
        session.close()


def twist_size() -> int:
    """Bytes of one encoded TwistCommand as the client sends it (the bare ping carries as many)."""
    from iorthand.protocol import TwistCommand

    try:
        return len(TwistCommand(operator=OPERATOR, linear=[0.0, 0.005, 0.0], angular=[0.0, 0.0, 0.0],
                                deadman=True).stamp(1).encode())
    except Exception:  # the message gained required fields: a typical size
        return 120


# ------------------------------------------------------------------------------------------------ orchestrator


def edge_config(variant: str, endpoint: str, robot: str = ROBOT, cpu_latency_us: int | None = None) -> dict[str, Any]:
    cfg = yaml.safe_load((ROOT / "configs" / "edge-sim.yaml").read_text())
    cfg["robot_id"] = robot
    if cpu_latency_us is not None:  # the edge's PM QoS request: machine-wide, so the bare echo has it too
        cfg["cpu_latency_us"] = cpu_latency_us
    cfg["zenoh"] = {"mode": "client", "connect": [endpoint], "shared_memory": False, "connect_retry_s": 60.0}
    cfg.setdefault("safety", {})["auto_arm"] = True
    if variant in ("plain", "video-apart"):
        cfg.pop("video", None)
        cfg.pop("perception", None)
    else:  # the camera video comes from the perception camera's frames: both at 30 fps
        cfg["video"]["camera"]["fps"] = 30
        cfg["perception"]["camera"]["fps"] = 30.0
    return cfg


def summary(values: list[float]) -> dict[str, float]:
    from iorthand_operator.bench import stats

    s = stats.latency_summary(values)
    return {k: round(float(s[k]), 4) for k in ("count", "p50", "p90", "p99", "max", "mean") if k in s}


def hop_breakdown(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Per-hop latencies from an instrumented edge's stamps (ns, wall clock), joined by command seq with the
    client's send/echo times of the same phase. Every stamp name the edge wrote becomes a hop from the one
    before it ("router": the router's HLC timestamp on the sample)."""
    rows: list[list[int]] = []
    names: list[str] = []
    for d in runs:
        stamps = d.get("stamps", {})
        for seq, sent, echoed, ok, _ in d["iorthand"]:
            st = stamps.get(str(seq))
            if not st or not ok:
                continue
            if not names:
                names = list(st)
            if list(st) != names:
                continue
            rows.append([sent, *(st[n] for n in names), echoed])
    if not rows:
        return {}
    labels = ["client send", *names, "client echo"]
    out: dict[str, Any] = {"commands": len(rows), "hops_ms": {}}
    for i in range(1, len(labels)):
        vals = [(r[i] - r[i - 1]) / 1e6 for r in rows]
        out["hops_ms"][f"{labels[i - 1]} -> {labels[i]}"] = summary(vals)
    # Spans across several hops (per command, not sums of percentiles): inside the edge, and from the router's
    # timestamp to the echo leaving (the same for every variant of the edge's receive path).
    first = 2 if names[0] == "router" else 1
    out["spans_ms"] = {f"{labels[first]} -> {labels[-2]}": summary([(r[-2] - r[first]) / 1e6 for r in rows])}
    if names[0] == "router":
        out["spans_ms"][f"router -> {labels[-2]}"] = summary([(r[-2] - r[1]) / 1e6 for r in rows])
    return out


def run_phase(group_dir: Path, variant: str, endpoint: str, args: argparse.Namespace, size: int,
              trees: dict[str, str]) -> dict[str, dict[str, Any]]:
    """One phase: an edge per tree (one tree: robot ``bench``; several: side by side, robot ``bench-<tree>``)
    and the client; returns each tree's data (the bare pings are shared)."""
    from iorthand_operator.bench.procs import Group, iorthand_argv

    group_dir.mkdir(parents=True, exist_ok=True)
    robots = {tree: ROBOT if len(trees) == 1 else f"{ROBOT}-{tree}" for tree in trees}
    me = [sys.executable, str(Path(__file__).resolve())]
    robot_list = ",".join(robots.values())

    def tree_env(path: str) -> list[str]:
        """The tree's code first on the path (the whole of it: core, edge and operator)."""
        pp = [path, f"{path}/edge", f"{path}/operator"]
        return ["PYTHONPATH=" + os.pathsep.join([*pp, os.environ.get("PYTHONPATH", "")])] if path else []

    with Group(group_dir) as g:
        edges = []
        for tree, path in trees.items():
            cfg_path = group_dir / f"edge-{tree}.yaml"
            cfg_path.write_text(yaml.safe_dump(edge_config(variant, endpoint, robots[tree], args.cpu_latency_us),
                                              sort_keys=False))
            env = [f"IORTHAND_HOPS_OUT={group_dir / f'hops-{tree}.json'}", *tree_env(path)]
            edges.append(g.start(f"edge-{tree}", ["env", *env, *iorthand_argv("edge", "--config", str(cfg_path))],
                                 ready="edge agent", timeout=60.0))
        video_robots = robot_list
        if variant == "video-apart":
            # The same video + perception load in a process of its own (another edge agent, robot bench-media),
            # the commands through a plain edge: what moving media out of the control process would give.
            video_robots = f"{ROBOT}-media"
            cfg_path = group_dir / "edge-media.yaml"
            cfg_path.write_text(yaml.safe_dump(edge_config("video", endpoint, video_robots, args.cpu_latency_us),
                                              sort_keys=False))
            g.start("edge-media", iorthand_argv("edge", "--config", str(cfg_path)), ready="edge agent", timeout=60.0)
        if variant in ("video", "video-apart"):
            g.start("video-sub", [*me, "--role", "video-sub", "--connect", endpoint, "--robots", video_robots,
                                  "--out", str(group_dir / "video.json"), "--max-seconds", str(args.duration + 120)],
                    ready="video-sub ready")
        # Side by side, each tree's own client code in a process of its own (the first one also pings bare), their
        # ticks spread over the period from one instant; else one client process for every robot.
        start_file = group_dir / "start"
        client_argv = [*me, "--role", "client", "--connect", endpoint, "--duration", str(args.duration),
                       "--warmup", str(args.warmup), "--rate", str(args.rate), "--size", str(size),
                       "--slots", str(len(trees))]
        runs = ([(tree, i, robots[tree], tree_env(path)) for i, (tree, path) in enumerate(trees.items())]
                if args.side_by_side else [("all", 0, robot_list, tree_env(next(iter(trees.values()))))])
        clients = []
        for name, slot, robot, env in runs:
            extra = ["--start-file", str(start_file)] if len(runs) > 1 else []
            clients.append(g.start(f"client-{name}", ["env", *env, *client_argv, "--robots", robot, "--first-slot",
                                                      str(slot), *([] if slot else ["--bare"]), *extra,
                                                      "--out", str(group_dir / f"client-{name}.json")],
                                   ready="client acquired" if extra else None, timeout=120.0))
        if len(runs) > 1:
            start_file.with_suffix(".tmp").write_text(repr(time.monotonic() + 0.5))
            start_file.with_suffix(".tmp").rename(start_file)  # whole, never half written
        for client in clients:
            client.wait(args.duration + args.warmup + 120.0)
        for edge in edges:
            edge.stop()  # SIGTERM: an instrumented edge writes its stamps on the way out
        g.stop()
    data: dict[str, Any] = {"bare": [], "robots": {}}
    for name, _, _, _ in runs:
        out = group_dir / f"client-{name}.json"
        if not out.exists():
            raise RuntimeError(f"{variant}: a client wrote nothing; log {group_dir / f'client-{name}.log'}")
        got = json.loads(out.read_text())
        data["bare"] += got["bare"]
        data["robots"].update(got["robots"])
    data["loadavg"] = os.getloadavg()[0]
    video = None
    with contextlib.suppress(OSError, ValueError):
        video = json.loads((group_dir / "video.json").read_text())
    result: dict[str, dict[str, Any]] = {}
    for tree, robot in robots.items():
        d: dict[str, Any] = {"bare": data["bare"], "loadavg": data["loadavg"], **data["robots"][robot]}
        if video is not None:
            d["video"] = video
        with contextlib.suppress(OSError, ValueError):
            d["stamps"] = json.loads((group_dir / f"hops-{tree}.json").read_text())
        result[tree] = d
    return result


def analyse(phases: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    res: dict[str, Any] = {}
    for variant, runs in phases.items():
        bare = [(t4 - t1) / 1e6 for d in runs for t1, t4 in d["bare"]]
        ior = [(e[2] - e[1]) / 1e6 for d in runs for e in d["iorthand"] if e[3]]
        b, i = summary(bare), summary(ior)
        r: dict[str, Any] = {
            "bare_ms": b, "iorthand_ms": i,
            "diff_ms": {k: round(i[k] - b[k], 4) for k in ("p50", "p90", "p99", "max", "mean")},
            "refused": sum(d["refused"] for d in runs),
            "loadavg_1min_after_each_phase": [round(d.get("loadavg", 0.0), 2) for d in runs],
            "noisy_host": b["p99"] > NOISY_BARE_P99_MS,
        }
        if any("video" in d for d in runs):
            frames = sum(d.get("video", {}).get("frames", 0) for d in runs)
            secs = sum(d.get("video", {}).get("seconds", 0.0) for d in runs)
            r["video_fps_received"] = round(frames / secs, 1) if secs else 0.0
        if any(d.get("stamps") for d in runs):
            r["hops"] = hop_breakdown(runs)
        res[variant] = r
    if "plain" in res and "video-apart" in res:
        p, v = res["plain"], res["video-apart"]
        res["video_apart_p99_ratio"] = round(v["iorthand_ms"]["p99"] / p["iorthand_ms"]["p99"], 3)
        res["bare_video_apart_p99_ratio"] = round(v["bare_ms"]["p99"] / p["bare_ms"]["p99"], 3)
    if "plain" in res and "video" in res:
        p, v = res["plain"], res["video"]
        res["video_p99_ratio"] = round(v["iorthand_ms"]["p99"] / p["iorthand_ms"]["p99"], 3)
        res["bare_video_p99_ratio"] = round(v["bare_ms"]["p99"] / p["bare_ms"]["p99"], 3)
        noisy = p["noisy_host"] or v["noisy_host"]
        res["targets"] = {
            "diff_p50_ms": {"value": p["diff_ms"]["p50"], "limit": TARGETS["diff_p50_ms"],
                            "pass": p["diff_ms"]["p50"] <= TARGETS["diff_p50_ms"]},
            "diff_p99_ms": {"value": p["diff_ms"]["p99"], "limit": TARGETS["diff_p99_ms"],
                            "pass": p["diff_ms"]["p99"] <= TARGETS["diff_p99_ms"]},
            "video_p99_ratio": {"value": res["video_p99_ratio"], "limit": TARGETS["video_p99_ratio"],
                                "pass": res["video_p99_ratio"] <= TARGETS["video_p99_ratio"]},
        }
        for name, t in res["targets"].items():
            t["noisy_host"] = noisy if name == "video_p99_ratio" else p["noisy_host"]
    return res


def orchestrate(args: argparse.Namespace) -> int:
    from iorthand.transport import free_port
    from iorthand_operator.bench import report
    from iorthand_operator.bench.procs import Group, run_cleanups
    from iorthand_operator.bench.transports import ep, start_router

    work = Path(tempfile.mkdtemp(prefix="iorthand-cmdpath-", dir=args.workdir))
    size = twist_size()
    trees = dict(e.split("=", 1) if "=" in e else ("edge", e) for e in args.edge_pythonpath) or {"repo": ""}
    phases: dict[str, dict[str, list[dict[str, Any]]]] = {t: {v: [] for v in args.variants} for t in trees}
    cpu_before = report.cpu_times()
    started = time.time()
    try:
        with Group(work) as g:
            port = free_port()
            start_router(g, "router", port)
            endpoint = ep(port)
            g.start("echo", [sys.executable, str(Path(__file__).resolve()), "--role", "echo", "--connect", endpoint,
                             "--max-seconds", "3600"], ready="echo ready")
            # Trees side by side in each phase (--side-by-side), or taking turns.
            groups = [trees] if args.side_by_side else [{t: p} for t, p in trees.items()]
            for r in range(args.rounds):
                for variant in args.variants:
                    for group in groups:
                        # side by side: the trees' slots in the period rotate from round to round
                        items = list(group.items())
                        group = dict(items[r % len(items):] + items[:r % len(items)])
                        names = "+".join(group)
                        print(f"  round {r + 1}/{args.rounds}: {names} {variant} ({args.duration:g} s) ...", flush=True)
                        got = run_phase(work / f"r{r}-{names}-{variant}", variant, endpoint, args, size, group)
                        for tree, d in got.items():
                            phases[tree][variant].append(d)
    finally:
        run_cleanups()
    by_tree = {tree: analyse(ph) for tree, ph in phases.items()}
    # One edge (the default): its figures at the top level; several (agent.py variants): one entry each.
    res = next(iter(by_tree.values())) if len(by_tree) == 1 else {"edges": by_tree}
    data = {
        "benchmark": "command_path",
        "what": "round trip at the operator: OperatorClient twist -> router -> edge agent -> state/applied, and a "
                "bare Zenoh echo (subscribe, republish from the callback) of the same size and QoS half a period "
                "later on the same session, through the same router",
        "machine": report.machine(),
        "config": {"duration_s": args.duration, "warmup_s": args.warmup, "rounds": args.rounds, "rate_hz": args.rate,
                   "variants": args.variants, "payload_bytes": size, "edge_trees": trees,
                   "label": args.label, "side_by_side": args.side_by_side, "cpu_latency_us": args.cpu_latency_us, "workdir": str(work), "started": started},
        "host_cpu": report.cpu_share_since(cpu_before),
        **res,
    }
    out = Path(args.out)
    report.write_json(out, data)
    rows = []
    for tree in trees:
        for variant in args.variants:
            v = by_tree[tree][variant]
            b, i = v["bare_ms"], v["iorthand_ms"]
            rows.append([f"{tree} {variant}", b["count"], b["p50"], b["p99"], b["max"], i["count"], i["p50"], i["p99"],
                         i["max"], v["diff_ms"]["p50"], v["diff_ms"]["p99"]])
    print(report.table(["variant", "bare n", "bare p50", "bare p99", "bare max", "ior n", "ior p50", "ior p99",
                        "ior max", "diff p50", "diff p99"], rows))
    for tree, r in by_tree.items():
        for variant in args.variants:
            hops = r[variant].get("hops", {})
            for hop, s in [*hops.get("hops_ms", {}).items(), *hops.get("spans_ms", {}).items()]:
                print(f"  {tree} {variant}: {hop:45s} p50 {s['p50']:.3f}  p99 {s['p99']:.3f} ms")
        for name, t in r.get("targets", {}).items():
            note = f" (noisy host: bare p99 over {NOISY_BARE_P99_MS} ms, the host set the tail)" if t["noisy_host"] else ""
            print(f"  {tree} {name}: {t['value']} (limit {t['limit']}) {'PASS' if t['pass'] else 'MISS'}{note}")
    print(f"host CPU: {data['host_cpu']}\nwrote {out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--duration", type=float, default=25.0, help="s measured per phase (after the warm-up)")
    p.add_argument("--warmup", type=float, default=2.0, help="s of each phase not measured")
    p.add_argument("--rounds", type=int, default=2, help="plain/video phases alternate this many times")
    p.add_argument("--rate", type=float, default=60.0, help="twists per s (and as many bare pings)")
    p.add_argument("--variants", nargs="+", default=["plain", "video"], choices=["plain", "video", "video-apart"],
                   help="plain: no video; video: 30 fps video + perception in the edge; video-apart: the same load "
                        "from a second edge process (robot bench-media), commands through a plain edge")
    p.add_argument("--edge-pythonpath", nargs="+", default=[], metavar="[LABEL=]DIR",
                   help="run the edge and the client from these source trees (their whole code), taking turns in "
                        "every round")
    p.add_argument("--side-by-side", action="store_true",
                   help="with several --edge-pythonpath trees: run each tree's edge and client (its own code) at once, "
                        "commands interleaved")
    p.add_argument("--cpu-latency-us", type=int, default=None, metavar="US",
                   help="the edge's cpu_latency_us (a PM QoS request while the client holds control, machine-wide: "
                        "the bare echo has it too); default: the edge configuration's")
    p.add_argument("--label", default="", help="a note stored in the JSON (which edge variant)")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "command_path.json"))
    p.add_argument("--workdir", default=None, help="parent folder of the processes' logs (default /tmp)")
    # Internal: the child processes are this script in a role.
    p.add_argument("--role", choices=["echo", "client", "video-sub"], help=argparse.SUPPRESS)
    p.add_argument("--connect", help=argparse.SUPPRESS)
    p.add_argument("--size", type=int, default=120, help=argparse.SUPPRESS)
    p.add_argument("--robots", default=ROBOT, help=argparse.SUPPRESS)
    p.add_argument("--slots", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument("--first-slot", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--bare", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--start-file", default="", help=argparse.SUPPRESS)
    p.add_argument("--max-seconds", type=float, default=600.0, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.role is None:
        try:
            return orchestrate(args)
        except KeyboardInterrupt:  # every child was stopped on the way out (Group, run_cleanups)
            print("interrupted: every process this run started is stopped", file=sys.stderr)
            return 130
    roles = {"echo": role_echo, "client": role_client, "video-sub": role_video_sub}
    code = roles[args.role](args)
    sys.stdout.flush()
    os._exit(code)  # Zenoh's runtime threads can delay interpreter exit; the output is already written


if __name__ == "__main__":
    sys.exit(main())
