"""Transports under test and the two kinds of measurement run over them.

Topologies (all on 127.0.0.1, free ports, Zenoh shared memory off — it does not exist between sites):

- ``zenoh-peer``: the two sides connect directly, peer to peer;
- ``zenoh-router``: both are clients of one router;
- ``zenoh-chain2``: edge-site router ← cloud router (the edge side's router connects out, as behind NAT);
- ``zenoh-chain3``: edge-site router → cloud router ← operator-site router;
- ``mqtt``: Debian's mosquitto broker, paho-mqtt clients, QoS 0 (the reference system's transport).

Measurements: :func:`run_ping` (the same Python ping/echo on every transport, for the comparison) and
:func:`run_command_path` (the real edge agent, ``iorthand edge --config``, driven by ``OperatorClient``; the
edge echoes every command on ``state/applied``).
"""

from __future__ import annotations

import json
import shutil
import socket
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from iorthand.transport import free_port
from iorthand_operator.bench import report, stats
from iorthand_operator.bench.procs import Group, Unavailable, iorthand_argv, python_argv

ROLES = "iorthand_operator.bench.roles"
ZENOH_TRANSPORTS = ("zenoh-peer", "zenoh-router", "zenoh-chain2", "zenoh-chain3")
TRANSPORTS = (*ZENOH_TRANSPORTS, "mqtt")


def ep(port: int, host: str = "127.0.0.1") -> str:
    return f"tcp/{host}:{port}"


@dataclass
class Sites:
    """Where each side attaches: Zenoh args for the edge side and the operator side, and the routers."""

    edge_args: list[str]
    operator_args: list[str]
    routers: dict[str, Any] = field(default_factory=dict)  # name → Child
    describe: str = ""

    @property
    def edge_connect(self) -> list[str]:
        return [a for i, a in enumerate(self.edge_args) if i and self.edge_args[i - 1] == "--connect"]


def start_router(group: Group, name: str, port: int, connect: list[str] | None = None, netns: str | None = None,
                 host: str = "127.0.0.1", datagrams: bool = False) -> Any:
    # Every bench router stands for a site on its own host: no shared memory between them (nor with clients).
    argv = iorthand_argv("router", "--listen", ep(port, host), "--no-shared-memory", *(["--datagrams"] if datagrams else []))
    for c in connect or []:
        argv += ["--connect", c]
    return group.start(name, argv, netns=netns, ready="router ready", timeout=30.0)


def zenoh_sites(group: Group, transport: str) -> Sites:
    """Start the routers of ``transport`` and say how each side connects."""
    if transport == "zenoh-peer":
        port = free_port()
        return Sites(["--mode", "peer", "--listen", ep(port)], ["--mode", "peer", "--connect", ep(port)],
                     describe="peer to peer, direct TCP")
    if transport == "zenoh-router":
        port = free_port()
        r = start_router(group, "router", port)
        return Sites(["--connect", ep(port)], ["--connect", ep(port)], {"router": r}, "one router")
    if transport in ("zenoh-chain2", "zenoh-chain3"):
        cloud, edge_site = free_port(), free_port()
        routers = {"cloud": start_router(group, "router-cloud", cloud)}
        routers["edge-site"] = start_router(group, "router-edge", edge_site, [ep(cloud)])
        op_port = cloud
        if transport == "zenoh-chain3":
            op_port = free_port()
            routers["operator-site"] = start_router(group, "router-operator", op_port, [ep(cloud)])
        time.sleep(0.5)  # router-to-router links come up after their sessions open
        return Sites(["--connect", ep(edge_site)], ["--connect", ep(op_port)], routers,
                     f"chain of {len(routers)} routers: edge site → cloud" + (" ← operator site" if len(routers) == 3 else ""))
    raise ValueError(f"unknown Zenoh transport {transport!r} (known: {', '.join(ZENOH_TRANSPORTS)})")


def mosquitto_binary() -> str | None:
    return shutil.which("mosquitto") or (str(Path("/usr/sbin/mosquitto")) if Path("/usr/sbin/mosquitto").exists() else None)


def start_mosquitto(group: Group) -> tuple[int, Any]:
    binary = mosquitto_binary()
    if binary is None:
        raise Unavailable("mosquitto is not installed: apt-get install -y mosquitto (the MQTT baseline needs it)")
    port = free_port()
    conf = group.workdir / "mosquitto.conf"
    conf.write_text(
        f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\nset_tcp_nodelay true\n"
        "log_dest stderr\nlog_type error\nlog_type warning\nlog_type notice\n"
    )
    child = group.start("mosquitto", [binary, "-c", str(conf)])
    wait_port(port, 15.0)  # mosquitto buffers its log when writing to a file: poll the port instead
    return port, child


def wait_port(port: int, timeout: float, host: str = "127.0.0.1") -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with socket.create_connection((host, port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.05)
    raise RuntimeError(f"nothing listens on {host}:{port} after {timeout:.0f} s")


# ------------------------------------------------------------------------------------------------ ping


def _ping_raw(workdir: Path, transport: str, size: int, rate: float, duration: float, qos: str = "command",
              load: Any = None, tag: str = "") -> tuple[dict[str, Any], str]:
    """One ping/echo run: the pinger's raw output and the topology it crossed."""
    name = f"{transport}-{size}B-{qos}" + ("-load" if load else "") + tag
    out = workdir / f"{name}.json"
    with Group(workdir / name) as g:
        if transport == "mqtt":
            port, _ = start_mosquitto(g)
            echo_args = ["--port", str(port)]
            ping_args = ["--port", str(port)]
            role = "mqtt"
            sites = Sites([], [], describe="mosquitto broker, paho-mqtt, QoS 0")
        else:
            sites = zenoh_sites(g, transport)
            echo_args, ping_args, role = sites.edge_args, sites.operator_args, "zenoh"
        if load is not None:
            load(g, sites)
        g.start("echo", python_argv(ROLES, f"{role}-echo", *echo_args, "--qos", qos), ready="echo ready")
        ping = g.start("ping", python_argv(ROLES, f"{role}-ping", *ping_args, "--qos", qos, "--size", str(size),
                                           "--rate", str(rate), "--duration", str(duration), "--out", str(out)))
        ping.wait(duration + 60.0)
        if not out.exists():
            raise RuntimeError(f"{name}: the pinger wrote nothing; log {ping.log_path}: {ping.output()[-1000:]}")
        return json.loads(out.read_text()), sites.describe


def run_ping(workdir: Path, transport: str, size: int, rate: float, duration: float, qos: str = "command",
             load: Any = None) -> dict[str, Any]:
    """One ping/echo case. ``load(group, sites)`` may start background streams through the same routers."""
    cpu_before = report.cpu_times()
    data, topology = _ping_raw(workdir, transport, size, rate, duration, qos, load)
    result = analyse_ping(data)
    result.update(transport=transport, size=size, rate=rate, qos=qos, topology=topology, duration_s=duration,
                  host_cpu=report.cpu_share_since(cpu_before))
    return result


def run_pings_interleaved(workdir: Path, transports: list[str], size: int, rate: float, duration: float,
                          qos: str, rounds: int) -> dict[str, dict[str, Any]]:
    """Ping every transport for ``duration`` s in all, in ``rounds`` alternating slices (A B C A B C …) rather
    than one after the other: on a shared machine, a burst of someone else's load then falls on every
    transport alike instead of deciding a comparison."""
    raws: dict[str, list[dict[str, Any]]] = {t: [] for t in transports}
    topology: dict[str, str] = {}
    cpu: dict[str, Counter[str]] = {t: Counter() for t in transports}  # CPU seconds by kind over each one's slices
    for r in range(rounds):
        for t in transports:
            before = report.cpu_times()
            data, topology[t] = _ping_raw(workdir, t, size, rate, duration / rounds, qos, tag=f"-round{r}")
            cpu[t].update(report.cpu_spent(before, report.cpu_times()))
            raws[t].append(data)
    out = {}
    for t in transports:
        result = analyse_ping(merge_ping_rounds(raws[t]))
        result.update(transport=t, size=size, rate=rate, qos=qos, topology=topology[t], duration_s=duration,
                      rounds=rounds, host_cpu=report.cpu_share(cpu[t]))
        out[t] = result
    return out


def merge_ping_rounds(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """Several pinger outputs as one: each round's sequence numbers are moved into a range of their own (every
    round starts from the same first number), so loss and reordering stay per round."""
    stride = 1 + max((max(d["sent"], default=0) for d in rounds), default=0)
    failed = [d.get("status") for d in rounds if d.get("status") != "ok"]
    merged: dict[str, Any] = {"status": failed[0] if failed else "ok", "sent": [], "records": []}
    for i, d in enumerate(rounds):
        merged["sent"] += [seq + i * stride for seq in d["sent"]]
        merged["records"] += [[rec[0] + i * stride, *rec[1:]] for rec in d["records"]]
    return merged


def analyse_ping(data: dict[str, Any]) -> dict[str, Any]:
    """Statistics of a ping run: round trip (t4 − t1), one-way estimates, loss and reordering."""
    if data.get("status") != "ok":
        return {"error": data.get("status", "no data"), "rtt_ms": stats.latency_summary([])}
    recs = data["records"]
    ex = [stats.Timestamps(r[1], r[2], r[3], r[4]) for r in recs]
    return _exchange_stats(ex, data["sent"], [r[0] for r in recs])


def _exchange_stats(ex: list[stats.Timestamps], sent: list[int], received: list[int]) -> dict[str, Any]:
    rtt = [(e.t4 - e.t1) / 1e6 for e in ex]
    clock = stats.clock_offset(ex)
    up, down = stats.one_way_ms(ex, clock.offset_ns) if ex else ([], [])
    return {
        "rtt_ms": stats.latency_summary(rtt),
        "one_way_up_ms": stats.latency_summary(up),
        "one_way_down_ms": stats.latency_summary(down),
        "clock": clock.as_dict(),
        "sequence": stats.sequence_report(sent, received).as_dict(),
        "samples_ms": [round(v, 4) for v in rtt],
        "arrival_s": [round((e.t4 - ex[0].t4) / 1e9, 4) for e in ex] if ex else [],
    }


# ------------------------------------------------------------------------------------------------ command path


def edge_config(robot: str, connect: list[str], **safety: Any) -> dict[str, Any]:
    return {
        "robot_id": robot,
        "zenoh": {"mode": "client", "connect": connect, "shared_memory": False, "connect_retry_s": 60.0},
        "robot": {"kind": "sim", "initial_pose": [0.30, 0.0, 0.20, 3.14159, 0.0, 0.0]},
        "safety": {"auto_arm": True, **safety},
    }


def start_edge(group: Group, robot: str, connect: list[str], netns: str | None = None, name: str = "edge",
               video: dict[str, Any] | None = None) -> Any:
    cfg = group.workdir / f"{name}.yaml"
    cfg.parent.mkdir(parents=True, exist_ok=True)
    config = edge_config(robot, connect)
    if video is not None:
        config["video"] = video
    cfg.write_text(yaml.safe_dump(config, sort_keys=False))
    return group.start(name, iorthand_argv("edge", "--config", str(cfg)), netns=netns, ready="edge agent", timeout=60.0)


def analyse_probe(robot_data: dict[str, Any]) -> dict[str, Any]:
    """Command → applied echo statistics of one robot from an operator-probe output."""
    sent = [s for s, _ in robot_data["sent"]]
    recs = robot_data["records"]
    ex = [stats.Timestamps(r[1], r[2], r[3], r[4]) for r in recs]
    out = _exchange_stats(ex, sent, [r[0] for r in recs])
    out["refused"] = sum(1 for r in recs if not r[5])
    out["refusals"] = sorted({r[6] for r in recs if not r[5]})
    out["edge_counters"] = robot_data.get("edge", {})
    return out


def run_command_path(workdir: Path, transport: str, duration: float, rate: float = 60.0, robot: str = "bench",
                     load: Any = None, name: str = "") -> dict[str, Any]:
    """The real command path: operator (OperatorClient) → routers → edge agent (simulated robot) → echo."""
    name = name or f"command-{transport}" + ("-load" if load else "")
    out = workdir / f"{name}.json"
    cpu_before = report.cpu_times()
    with Group(workdir / name) as g:
        sites = zenoh_sites(g, transport)
        start_edge(g, robot, sites.edge_connect or _peer_listen(sites))
        if load is not None:
            load(g, sites)
        probe = g.start("operator", python_argv(ROLES, "operator-probe", *sites.operator_args, "--robots", robot,
                                                "--duration", str(duration), "--rate", str(rate), "--out", str(out)))
        probe.wait(duration + 120.0)
        if not out.exists():
            raise RuntimeError(f"{name}: the operator probe wrote nothing; log {probe.log_path}: {probe.output()[-1500:]}")
        data = json.loads(out.read_text())
    result = analyse_probe(data["robots"][robot])
    result.update(transport=transport, topology=sites.describe, duration_s=duration, rate=rate,
                  host_cpu=report.cpu_share_since(cpu_before))
    return result


def _peer_listen(sites: Sites) -> list[str]:
    raise ValueError("the edge agent runs in client mode: use a router transport for the command path")
