"""``iorthand bench ...``: latency benchmarks. Each sub-command prints a summary table and writes JSON and
PNG files into ``--out`` (default ``benchmarks/results``). ``iorthand bench all`` runs transports, load, wan
and scale (load measures the command path with and without video, so command-latency is left to runs alone).

    iorthand bench transports   # Zenoh peer / router / chain of 2 and 3 routers vs MQTT, 64 B and 300 KB
    iorthand bench load         # commands with and without 30 fps video through the same router
    iorthand bench command-latency [--video]   # the edge command path through one router
    iorthand bench wan          # lan / 5g / 4g / poor / blackout profiles between three namespaces
    iorthand bench scale        # N robots and N operators through one router and a mesh
    iorthand bench linkemu ...  # run the link emulator alone (a delaying TCP relay)
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from pathlib import Path
from typing import Any

from iorthand.config import cli_number
from iorthand.cpu_latency import CpuLatencyHold
from iorthand_operator.bench import linkemu, report
from iorthand_operator.bench.procs import Unavailable, run_cleanups, set_nice
from iorthand_operator.bench.wan import EMULATORS, FRAME_DELAY_OVER_LINK_TARGET_MS, PROFILES, VIDEOS

log = logging.getLogger("iorthand.bench")

DEFAULT_OUT = Path("benchmarks/results")
SIZES = {"small": 64, "frame": 300_000}
RATES = {"small": 60.0, "frame": 30.0}


def _strip(d: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in d.items() if k not in ("samples_ms", "arrival_s")}


def _workdir(args: argparse.Namespace) -> Path:
    if args.workdir:
        Path(args.workdir).mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix="iorthand-bench-", dir=args.workdir))


def _finish(args: argparse.Namespace, name: str, data: dict[str, Any], cpu_before: dict[str, float]) -> dict[str, float]:
    """Write the part's JSON with the machine, the configuration and where the CPU time went while it ran."""
    host_cpu = report.cpu_share_since(cpu_before)
    data = {"benchmark": name, "machine": report.machine(), "config": _config(args), "host_cpu": host_cpu, **data}
    path = report.write_json(args.out / f"{name}.json", data)
    print(f"\nhost CPU while it ran: {host_cpu['busy_percent']} % busy, {host_cpu['steal_percent']} % stolen by "
          f"the hypervisor\nwrote {path}")
    return host_cpu


def _config(args: argparse.Namespace) -> dict[str, Any]:
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k != "func"}


# ------------------------------------------------------------------------------------------------ parts


def run_transports(args: argparse.Namespace) -> dict[str, Any]:
    from iorthand_operator.bench import plots  # matplotlib: loaded only when a part draws
    from iorthand_operator.bench.transports import run_pings_interleaved

    work = _workdir(args)
    cases: dict[str, Any] = {}
    for size_name in args.sizes:
        print(f"  {size_name}: {', '.join(args.transports)} in {args.rounds} alternating rounds ...", flush=True)
        by_transport = run_pings_interleaved(work, args.transports, SIZES[size_name], RATES[size_name], args.duration,
                                             "command" if size_name == "small" else "frame", args.rounds)
        cases.update({f"{t}/{size_name}": r for t, r in by_transport.items()})
    ratios = report.transport_ratios(cases)
    print("\nTransports: ping/echo round trip (same Python code on each), Zenoh shared memory off")
    print(report.table(report.LATENCY_HEADERS, report.latency_rows(cases)))
    print("\nRatio Zenoh / MQTT (below 1 = Zenoh faster):")
    print(report.table(["case", "p50", "p99"], [[k, v["p50"], v["p99"]] for k, v in ratios.items()]))
    pngs = []
    for size_name in args.sizes:
        sub = {k: v for k, v in cases.items() if k.endswith("/" + size_name)}
        pngs.append(plots.latency_plots(sub, args.out / f"transports-{size_name}.png",
                                        f"transports, {SIZES[size_name]} B payload, round trip"))
    return {"cases": cases, "ratios": ratios, "pngs": [str(p) for p in pngs]}


def run_load_part(args: argparse.Namespace) -> dict[str, Any]:
    from iorthand_operator.bench import plots  # matplotlib: loaded only when a part draws
    from iorthand_operator.bench.load import run_load

    res = run_load(_workdir(args), args.duration, fps=args.fps)
    print("\nLoad: commands while 30 fps 640×480 JPEG video and state streams cross the same router")
    print(report.table(report.LATENCY_HEADERS, report.latency_rows(res["cases"])))
    v = res["cases"]["command_path_video"].get("video", {})
    print(f"video: {v.get('frame_bytes', 0) / 1000:.0f} KB frames, received {v.get('fps', 0):.1f} fps at the operator")
    png = plots.latency_plots(res["cases"], args.out / "load.png", "commands under video load (one router)")
    res["pngs"] = [str(png)]
    return res


def run_command_latency(args: argparse.Namespace) -> dict[str, Any]:
    from iorthand_operator.bench import plots  # matplotlib: loaded only when a part draws
    from iorthand_operator.bench.load import video_load
    from iorthand_operator.bench.transports import run_command_path

    res = run_command_path(_workdir(args), args.transport, args.duration, load=video_load() if args.video else None)
    cases = {f"command-path {args.transport}" + (" + video" if args.video else ""): res}
    print("\nCommand → applied latency (operator → router → edge → echo), simulated robot")
    print(report.table(report.LATENCY_HEADERS, report.latency_rows(cases)))
    print(f"one-way up p50 {res['one_way_up_ms']['p50']:.3f} ms, down p50 {res['one_way_down_ms']['p50']:.3f} ms, "
          f"clock offset {res['clock']['offset_ms']:.3f} ± {res['clock']['error_bound_ms']:.3f} ms")
    png = plots.latency_plots(cases, args.out / "command_latency.png", "command → applied round trip")
    return {"result": res, "pngs": [str(png)]}


def run_wan_part(args: argparse.Namespace) -> dict[str, Any]:
    from iorthand_operator.bench import plots  # matplotlib: loaded only when a part draws
    from iorthand_operator.bench.wan import run_wan

    res = run_wan(_workdir(args), args.profiles, args.duration, args.trials, args.blackout_s, args.links, args.loopback,
                  tuple(args.long_blackout_s), args.emulator, tuple(getattr(args, "video", None) or ["none"]))
    profs = res["profiles"]
    print(f"\nWAN profiles ({res['isolation']}, {res['emulator']}: {res['why']}; profile on the {res['links']} link(s))")
    rows = report.latency_rows(profs)
    for row, p in zip(rows, profs.values(), strict=True):
        row.append(p["deadman_stops_while_driving"])
    print(report.table([*report.LATENCY_HEADERS, "deadman stops"], rows))
    vids = {n: p for n, p in profs.items() if "video" in p}
    if vids:
        print("\nVideo across the link (640×480, 30 fps captured)")
        print(report.table(["profile+codec", "fps delivered", "delay p50 ms", "delay p99 ms", "p99 over link ms",
                            f"% over link +{FRAME_DELAY_OVER_LINK_TARGET_MS:g} ms", "kbit/s", "command p99 ÷ no video"],
                           [[n, p["video"]["fps_delivered"], p["video"].get("delay_ms", {}).get("p50"),
                             p["video"].get("delay_ms", {}).get("p99"), p["video"].get("delay_over_link_p99_ms"),
                             None if p["video"].get("share_over_target") is None
                             else round(100 * p["video"]["share_over_target"], 2), p["video"].get("bitrate_kbit_s"),
                             p.get("command_p99_ratio_to_no_video")]
                            for n, p in vids.items()]))
    pngs = [plots.cdf_plot(profs, args.out / "wan-cdf.png", "what the operator experiences, per WAN profile")]
    if "blackout" in profs:
        b = profs["blackout"]["blackout_summary"]
        print(f"\nBlackout ({args.blackout_s:g} s, {b['trials']} trials): stop after the last command received "
              f"max {report.fmt(b['stop_ms']['max'])} ms, p50 {report.fmt(b['stop_ms']['p50'])} ms "
              f"(limit {b['limit_ms']:.0f} ms), {b['passed']}/{b['trials']} within the limit; operator echoes back "
              f"after the link returns: p50 {report.fmt(b['operator_recovery_ms']['p50'])} ms, "
              f"max {report.fmt(b['operator_recovery_ms']['max'])} ms")
        for t in b["long_blackouts"]:
            print(f"  long blackout {t['blackout_ms'] / 1000:.1f} s: stop after {report.fmt(t.get('stop_after_last_command_ms'))} ms, "
                  f"operator echoes back after {report.fmt(t.get('operator_echo_after_ms'))} ms, motion after "
                  f"{report.fmt(t.get('motion_resumed_after_ms'))} ms")
        pngs.append(plots.blackout_plot(profs["blackout"]["trials"], b["limit_ms"], args.out / "wan-blackout.png"))
    res["pngs"] = [str(p) for p in pngs]
    return res


def run_scale_part(args: argparse.Namespace) -> dict[str, Any]:
    from iorthand_operator.bench import plots  # matplotlib: loaded only when a part draws
    from iorthand_operator.bench.scale import run_scale

    res = run_scale(_workdir(args), args.counts, args.duration, args.topologies, args.per_process, args.edges,
                    args.operators)
    rows = [[f"{p['topology']} N={p['n']}", p["sent"], p["lost"], p["refused"], p["rtt_ms"]["p50"], p["rtt_ms"]["p99"],
             p["worst_robot_p99_ms"], p["router_cpu_percent_total"]] for p in res["points"]]
    print(f"\nScale: N robots ({args.edges} edges) + N operators ({args.operators}), full streams without video")
    print(report.table(["case", "sent", "lost", "refused", "p50 ms", "p99 ms", "worst robot p99", "router CPU %"], rows))
    res["pngs"] = [str(plots.scale_plot(res["points"], args.out / "scale.png"))]
    for p in res["points"]:
        p.pop("samples_ms", None)
    return res


PARTS = {
    "transports": run_transports,
    "load": run_load_part,
    "command-latency": run_command_latency,
    "wan": run_wan_part,
    "scale": run_scale_part,
}


def _run(args: argparse.Namespace) -> int:
    args.out = Path(args.out)
    args.out.mkdir(parents=True, exist_ok=True)
    set_nice(args.nice)
    # A machine-wide PM QoS request for the run (the JSON's config says what it got); default: the host as it is.
    hold = CpuLatencyHold(args.cpu_latency_us) if args.cpu_latency_us is not None else None
    args.cpu_latency = hold.state if hold else "the host's own idle states"
    try:
        if args.bench == "all":
            return _run_all(args)
        cpu_before = report.cpu_times()
        result = PARTS[args.bench](args)
        name = args.bench.replace("-", "_")
        _finish(args, name, result, cpu_before)
        report.print_targets(report.targets({args.bench.replace("-", "_"): result}))
        return 0
    except Unavailable as exc:
        print(f"iorthand bench {args.bench}: {exc}", file=sys.stderr)
        return 2
    finally:
        run_cleanups()
        if hold:
            hold.close()


def _run_all(args: argparse.Namespace) -> int:
    results: dict[str, Any] = {}
    base = dict(vars(args))
    q = args.quick
    plan = [
        ("transports", {"duration": 6.0 if q else 30.0, "transports": list(TRANSPORTS_ALL), "sizes": ["small", "frame"],
                        "rounds": 2 if q else 3}),
        ("load", {"duration": 8.0 if q else 60.0, "fps": 30.0}),
        ("wan", {"duration": 8.0 if q else 15.0, "profiles": list(PROFILES),
                 "trials": 5 if q else 20, "blackout_s": 1.5, "links": "edge", "loopback": False, "emulator": "auto",
                 "long_blackout_s": [] if q else [5.0]}),
        ("scale", {"duration": 8.0 if q else 15.0, "counts": [1, 5, 10, 20], "topologies": ["router"] if q else ["router", "mesh"],
                   "per_process": 10, "edges": "light", "operators": "light"}),
    ]
    host_cpu: dict[str, dict[str, float]] = {}
    for part, overrides in plan:
        print(f"\n=== {part} ===", flush=True)
        sub = argparse.Namespace(**{**base, **overrides, "bench": part})
        cpu_before = report.cpu_times()
        try:
            results[part] = PARTS[part](sub)
            host_cpu[part] = _finish(sub, part, results[part], cpu_before)
        except Exception as exc:  # one part failing must not hide the others' figures
            log.exception("%s failed", part)
            results[part] = {"error": str(exc)}
    checks = report.targets({k: v for k, v in results.items() if "error" not in v})
    host = report.machine()
    report.write_json(args.out / "summary.json", {"machine": host, "targets": checks, "host_cpu": host_cpu,
                                                  "errors": {k: v["error"] for k, v in results.items() if "error" in v}})
    report.print_targets(checks)
    print("\nStolen by the hypervisor while each part ran: "
          + ", ".join(f"{part} {c['steal_percent']} %" for part, c in host_cpu.items()))
    idle = host["idle_penalty"]
    print(f"\nThis host: Python runs {idle['factor']}× slower right after {idle['idle_gap_ms']:.0f} ms idle (decoding a "
          f"command: {idle['decode_after_idle_us']} µs against {idle['decode_hot_us']} µs back to back); every thread "
          "wake-up on the command path pays it (cpuidle "
          f"{idle['cpuidle_driver'] or '?'}, guest_halt_poll_ns {idle['guest_halt_poll_ns'] or '-'}; "
          f"CPU wake-up latency: {args.cpu_latency}).")
    print(f"\nwrote {args.out / 'summary.json'}")
    return 0 if all("error" not in v for v in results.values()) else 1


TRANSPORTS_ALL = ("zenoh-peer", "zenoh-router", "zenoh-chain2", "zenoh-chain3", "mqtt")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="latency benchmarks: transports, load, WAN profiles, scale (JSON + PNG)")
    bsub = p.add_subparsers(dest="bench", metavar="BENCHMARK", required=True)

    def common(b: argparse.ArgumentParser, duration: float) -> None:
        b.add_argument("--out", default=str(DEFAULT_OUT), help="where JSON and PNG go (default benchmarks/results)")
        b.add_argument("--workdir", default=None, help="parent folder for logs of the processes (default: /tmp)")
        b.add_argument("--duration", type=cli_number(float, lo=1.0), default=duration, help="s measured per case")
        b.add_argument("--nice", type=int, default=0,
                       help="nice increment of every process started (e.g. -5 as root: shield from other load)")
        b.add_argument("--cpu-latency-us", type=cli_number(int, lo=0), default=None, metavar="US",
                       help="hold a PM QoS request for the whole run (root): no CPU enters an idle state slower than "
                            "US µs to leave; 0 keeps idle CPUs polling, as a host tuned for latency would. "
                            "Default: the host as it is")
        b.set_defaults(func=_run)

    a = bsub.add_parser("all", help="every benchmark; prints the targets of issue 9")
    common(a, 15.0)
    a.add_argument("--quick", action="store_true", help="short runs (about 8 minutes): a smoke test, not figures")

    t = bsub.add_parser("transports", help="Zenoh peer / router / chains vs MQTT (mosquitto), small and 300 KB")
    common(t, 30.0)
    t.add_argument("--transports", nargs="+", default=list(TRANSPORTS_ALL), choices=TRANSPORTS_ALL)
    t.add_argument("--sizes", nargs="+", default=["small", "frame"], choices=sorted(SIZES))
    t.add_argument("--rounds", type=cli_number(int, lo=1), default=3,
                   help="the measured time is split into this many slices, transports alternating (fair under load)")

    lo = bsub.add_parser("load", help="commands with and without video + state load through one router")
    # 60 s per case: a p99 from 20 s (1,200 commands) rests on its 12 slowest and flips with one burst of load.
    common(lo, 60.0)
    lo.add_argument("--fps", type=cli_number(float, lo=1.0, hi=120.0), default=30.0)

    c = bsub.add_parser("command-latency", help="command → applied latency through one router, simulated edge")
    common(c, 20.0)
    c.add_argument("--transport", default="zenoh-router", choices=["zenoh-router", "zenoh-chain2", "zenoh-chain3"])
    c.add_argument("--video", action="store_true", help="with 30 fps video and state streams through the router")

    w = bsub.add_parser("wan", help="WAN profiles between operator, cloud and edge namespaces; blackout trials")
    common(w, 15.0)
    w.add_argument("--profiles", nargs="+", default=list(PROFILES), choices=list(PROFILES))
    w.add_argument("--trials", type=cli_number(int, lo=1), default=20, help="blackout trials")
    w.add_argument("--blackout-s", type=cli_number(float, lo=0.2), default=1.5, help="s each blackout lasts")
    w.add_argument("--links", default="edge", choices=["edge", "both"],
                   help="the profile applies to the edge's link only (operator on LAN) or to both links")
    w.add_argument("--loopback", action="store_true", help="do not use namespaces (relays on 127.0.0.1)")
    w.add_argument("--emulator", default="auto", choices=EMULATORS,
                   help="what adds delay, jitter and loss: the kernel's netem, the project's TCP relay, or auto "
                        "(netem where the kernel has it)")
    w.add_argument("--long-blackout-s", type=cli_number(float, lo=0.2), nargs="*", default=[5.0],
                   help="extra blackouts longer than the Zenoh lease (sessions drop and must recover)")
    w.add_argument("--video", nargs="+", default=["none"], choices=list(VIDEOS),
                   help="each profile once per choice: the edge streaming nothing, or its camera (640×480 30 fps) "
                        "as JPEG or H.264, watched from the operator's side")

    s = bsub.add_parser("scale", help="N robots and N operators through one router / a mesh of three")
    common(s, 15.0)
    s.add_argument("--counts", type=cli_number(int, lo=1), nargs="+", default=[1, 5, 10, 20])
    s.add_argument("--topologies", nargs="+", default=["router", "mesh"], choices=["router", "mesh"])
    s.add_argument("--per-process", type=cli_number(int, lo=1), default=10, help="operators (and light robots) per process")
    s.add_argument("--edges", default="light", choices=["light", "full"],
                   help="light: LightRobot stand-ins, several per process; full: one iorthand edge process each")
    s.add_argument("--operators", default="light", choices=["light", "client"],
                   help="light: LightOperator stand-ins; client: the real OperatorClient (measures this machine)")

    le = bsub.add_parser("linkemu", help="run the link emulator (TCP relay with delay/jitter) in the foreground")
    linkemu.add_arguments(le)
    le.set_defaults(func=linkemu.run)
