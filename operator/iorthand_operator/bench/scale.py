"""Scale: N simulated robots (full streams: state/robot 125 Hz, safety 20 Hz, a command echo per twist) and N
operators (60 Hz commands each) through one router or a mesh of three routers; no video. Reports per-robot
command latency and loss as N grows, and the routers' CPU.

On real sites every robot and every operator is its own computer; here all 2N of them share two cores with
the routers, so both sides are light stand-ins by default, several per process, each with its own Zenoh
session, link, keys, messages and QoS (``LightRobot``, ``LightOperator`` in ``roles.py``). That keeps the
router the thing measured. The heavier variants measure this machine instead, and are kept to show it:
``edges="full"`` runs one ``iorthand edge`` process per robot (~8 % of a core each, idle);
``operators="client"`` runs the real ``OperatorClient`` (own sender and lease threads, every state decoded;
~5 % of a core each).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import yaml

from iorthand.transport import free_port
from iorthand_operator.bench import stats
from iorthand_operator.bench.procs import CpuMeter, Group, iorthand_argv, python_argv
from iorthand_operator.bench.transports import ROLES, analyse_probe, edge_config, ep, start_router


def _routers(g: Group, topology: str) -> list[tuple[str, Any]]:
    if topology == "router":
        port = free_port()
        return [(ep(port), start_router(g, "router", port))]
    if topology == "mesh":
        out: list[tuple[str, Any]] = []
        for i in range(3):
            port = free_port()
            out.append((ep(port), start_router(g, f"router{i}", port, [e for e, _ in out])))
        time.sleep(0.5)
        return out
    raise ValueError(f"unknown scale topology {topology!r} (router, mesh)")


def _operator_role(operators: str) -> list[str]:
    if operators == "light":
        return ["operator-farm"]
    if operators == "client":
        return ["operator-probe", "--shared-cpu"]
    raise ValueError(f"unknown scale operators {operators!r} (light, client)")


def run_scale_point(workdir: Path, n: int, duration: float, topology: str = "router", per_process: int = 10,
                    edges: str = "light", operators: str = "light") -> dict[str, Any]:
    role = _operator_role(operators)
    name = f"scale-{topology}-{edges}-{operators}-{n}"
    with Group(workdir / name) as g:
        routers = _routers(g, topology)
        robots = [f"r{i:03d}" for i in range(n)]
        children = []
        if edges == "full":
            for i, robot in enumerate(robots):
                cfg = g.workdir / f"edge-{robot}.yaml"
                cfg.write_text(yaml.safe_dump(edge_config(robot, [routers[i % len(routers)][0]]), sort_keys=False))
                children.append((g.start(f"edge-{robot}", iorthand_argv("edge", "--config", str(cfg))), "edge agent"))
        else:
            for k in range(math.ceil(n / per_process)):
                group_robots = robots[k * per_process:(k + 1) * per_process]
                children.append((g.start(f"farm{k}", python_argv(ROLES, "robot-farm", "--connect", routers[k % len(routers)][0],
                                                                 "--robots", ",".join(group_robots))), "farm ready"))
        for child, ready in children:
            child.wait_for(ready, 120.0)
        probes, outs = [], []
        for k in range(math.ceil(n / per_process)):
            group_robots = robots[k * per_process:(k + 1) * per_process]
            router = routers[(k + 1) % len(routers)][0]  # operators attach away from their robots' router
            out = g.workdir / f"probe{k}.json"
            outs.append(out)
            probes.append(g.start(f"probe{k}", python_argv(ROLES, *role, "--connect", router, "--robots", ",".join(group_robots),
                                                            "--operator-id", f"op{k}", "--duration", str(duration),
                                                            "--out", str(out))))
        for p in probes:
            p.wait_for("probe ready", 180.0)
        meters = [CpuMeter(child.pid) for _, child in routers]
        t0 = time.monotonic()
        for p in probes:
            p.wait(duration + 120.0)
        window = time.monotonic() - t0
        cpu = [m.percent() for m in meters]
        per_robot: dict[str, Any] = {}
        for out in outs:
            data = json.loads(out.read_text())
            for robot, rd in data["robots"].items():
                a = analyse_probe(rd)
                per_robot[robot] = {"rtt_ms": a["rtt_ms"], "sequence": a["sequence"], "refused": a["refused"],
                                    "samples_ms": a["samples_ms"]}
    all_rtt = [v for r in per_robot.values() for v in r["samples_ms"]]
    sent = sum(r["sequence"]["sent"] for r in per_robot.values())
    lost = sum(r["sequence"]["lost"] for r in per_robot.values())
    return {
        "n": n, "topology": topology, "edges": edges, "operators": operators, "duration_s": duration, "cpu_window_s": window,
        "router_cpu_percent": cpu, "router_cpu_percent_total": sum(cpu),
        "rtt_ms": stats.latency_summary(all_rtt), "sent": sent, "lost": lost,
        "refused": sum(r["refused"] for r in per_robot.values()),
        "worst_robot_p99_ms": max((r["rtt_ms"]["p99"] for r in per_robot.values()), default=math.nan),
        "per_robot": {k: {kk: vv for kk, vv in v.items() if kk != "samples_ms"} for k, v in per_robot.items()},
        "samples_ms": all_rtt,
    }


def run_scale(workdir: Path, counts: list[int], duration: float, topologies: list[str], per_process: int = 10,
              edges: str = "light", operators: str = "light") -> dict[str, Any]:
    return {
        "counts": counts,
        "edges": edges,
        "operators": operators,
        "per_process": per_process,
        "points": [run_scale_point(workdir, n, duration, topo, per_process, edges, operators)
                   for topo in topologies for n in counts],
    }
