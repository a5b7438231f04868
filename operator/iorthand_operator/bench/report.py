"""Benchmark reports: the machine and versions, JSON files, summary tables and the issue's targets."""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import sys
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import psutil

from iorthand_operator.bench.stats import ratio


def _pkg(name: str) -> str:
    try:
        return version(name)
    except PackageNotFoundError:
        return ""


def _cmd_version(argv: list[str]) -> str:
    try:
        r = subprocess.run(argv, capture_output=True, text=True, timeout=5)
        return (r.stdout or r.stderr).strip().splitlines()[0]
    except (OSError, IndexError, subprocess.TimeoutExpired):
        return ""


def source_tree() -> str:
    """The commit of the iorthand code that runs (``+changes`` when its files differ from it), or "" outside a
    git checkout: a result names the code that produced it."""
    root = Path(__file__).resolve().parents[3]
    commit = _cmd_version(["git", "-C", str(root), "rev-parse", "--short", "HEAD"])
    if not commit or " " in commit:  # not a checkout: git's error message
        return ""
    dirty = subprocess.run(["git", "-C", str(root), "diff", "--quiet", "HEAD", "--"], capture_output=True, timeout=10)
    return commit + ("+changes" if dirty.returncode else "")


def _read(path: str) -> str:
    try:
        return Path(path).read_text().strip()
    except OSError:
        return ""


def idle_penalty(samples: int = 40, gap_s: float = 0.016) -> dict[str, Any]:
    """How much slower Python runs right after the CPU idled, as each thread of a 60 Hz command path does:
    CPU time to decode one twist command back to back, and after ``gap_s`` asleep. On a VM whose idle vCPUs
    halt (cpuidle ``haltpoll`` with polling off), the second was 10–20× the first here."""
    import statistics

    from iorthand.protocol import TwistCommand

    # As an operator sends it: the age of its robot state and a 16-byte signature (iorthand.security.auth).
    payload = TwistCommand(operator="bench", linear=[0.0, 0.02, 0.0], angular=[0.0, 0.0, 0.0], deadman=True,
                           state_age=0.01, mac=bytes(16)).stamp(1).encode()

    def decode_us(gap: float) -> float:
        costs = []
        for _ in range(samples):
            if gap:
                time.sleep(gap)
            t0 = time.thread_time_ns()
            TwistCommand.decode(payload)
            costs.append((time.thread_time_ns() - t0) / 1e3)
        return statistics.median(costs)

    hot, after_idle = decode_us(0.0), decode_us(gap_s)
    return {
        "decode_hot_us": round(hot, 1), "decode_after_idle_us": round(after_idle, 1),
        "factor": round(after_idle / hot, 1) if hot else None, "idle_gap_ms": gap_s * 1000,
        "cpuidle_driver": _read("/sys/devices/system/cpu/cpuidle/current_driver"),
        "guest_halt_poll_ns": _read("/sys/module/haltpoll/parameters/guest_halt_poll_ns"),
    }


def cpu_times() -> dict[str, float]:
    """The machine's cumulative CPU seconds by kind (user, system, idle, iowait, steal, ...), all CPUs together.
    Guest times are left out: the kernel already counts them in user and nice."""
    return {k: v for k, v in psutil.cpu_times()._asdict().items() if k not in ("guest", "guest_nice")}


def cpu_spent(before: dict[str, float], after: dict[str, float]) -> dict[str, float]:
    """CPU seconds by kind between two :func:`cpu_times` (spans add up: several slices of one case)."""
    return {k: max(0.0, after[k] - before.get(k, 0.0)) for k in after}


def cpu_share(delta: dict[str, float]) -> dict[str, float]:
    """Where the CPU time of a :func:`cpu_spent` went: busy, and stolen (time the hypervisor gave this VM's CPUs
    to other guests; round trips measured while it is high are the host's figures, not the software's)."""
    total = sum(delta.values())
    if total <= 0:
        return {"cpu_seconds": 0.0, "busy_percent": math.nan, "steal_percent": math.nan}
    idle = delta.get("idle", 0.0) + delta.get("iowait", 0.0)
    steal = delta.get("steal", 0.0)
    return {"cpu_seconds": round(total, 2), "busy_percent": round(100 * (total - idle - steal) / total, 1),
            "steal_percent": round(100 * steal / total, 2)}


def cpu_share_since(before: dict[str, float]) -> dict[str, float]:
    """:func:`cpu_share` from ``before`` (a :func:`cpu_times`) until now."""
    return cpu_share(cpu_spent(before, cpu_times()))


def machine() -> dict[str, Any]:
    """What a reader needs to judge the figures: hardware, load at the start, versions."""
    return {
        "hostname": platform.node(),
        "platform": platform.platform(),
        "kernel": platform.release(),
        "cpu": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "memory_gb": round(psutil.virtual_memory().total / 2**30, 1),
        "load_average_at_start": list(os.getloadavg()),
        "cpu_percent_at_start": psutil.cpu_percent(interval=0.5),
        "python": sys.version.split()[0],
        "idle_penalty": idle_penalty(),
        "versions": {
            "eclipse-zenoh": _pkg("eclipse-zenoh"),
            "paho-mqtt": _pkg("paho-mqtt"),
            "msgpack": _pkg("msgpack"),
            "iorthand": _pkg("iorthand"),
            "iorthand_tree": source_tree(),
            "mosquitto": _cmd_version(["dpkg-query", "-W", "-f=${Version}", "mosquitto"]),
            "nftables": _cmd_version(["dpkg-query", "-W", "-f=${Version}", "nftables"]),
        },
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def write_json(path: Path, data: dict[str, Any]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1, default=_jsonable, allow_nan=True))
    return path


def _jsonable(o: Any) -> Any:
    if hasattr(o, "tolist"):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")


def fmt(v: Any, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "—"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def table(headers: list[str], rows: list[list[Any]]) -> str:
    cells = [[fmt(c) for c in r] for r in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(headers)]
    line = "  ".join(h.ljust(w) for h, w in zip(headers, widths, strict=True))
    out = [line, "  ".join("-" * w for w in widths)]
    out += ["  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True))) for r in cells]
    return "\n".join(out)


def latency_rows(cases: dict[str, dict[str, Any]]) -> list[list[Any]]:
    rows = []
    for name, c in cases.items():
        r, s = c["rtt_ms"], c.get("sequence", {})
        rows.append([name, r["count"], r["p50"], r["p90"], r["p99"], r["p99.9"], r["max"], r["jitter"],
                     s.get("lost", "—"), s.get("reordered", "—"), c.get("host_cpu", {}).get("steal_percent", "—")])
    return rows


LATENCY_HEADERS = ["case", "n", "p50 ms", "p90 ms", "p99 ms", "p99.9 ms", "max ms", "jitter ms", "lost", "reord",
                   "stolen %"]


def transport_ratios(cases: dict[str, dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Each Zenoh transport's p50 and p99 divided by MQTT's, per payload (below 1: Zenoh is faster)."""
    out: dict[str, dict[str, float]] = {}
    for name, c in cases.items():
        if c["transport"] == "mqtt":
            continue
        base = next((m for m in cases.values() if m["transport"] == "mqtt" and m["size"] == c["size"]), None)
        if base is None:
            continue
        out[name] = {q: ratio(c["rtt_ms"][q], base["rtt_ms"][q]) for q in ("p50", "p99")}
    return out


def targets(results: dict[str, Any]) -> list[dict[str, Any]]:
    """The issue's "must show" checks, for whichever parts were run."""
    out: list[dict[str, Any]] = []
    load = results.get("load")
    if load:
        p99 = load["cases"]["command_path_video"]["rtt_ms"]["p99"]
        out.append({"target": "command path through one router with video, p99 ≤ 3 ms", "value_ms": p99, "ok": p99 <= 3.0})
    tr = results.get("transports")
    if tr:
        for name, rr in tr["ratios"].items():
            if tr["cases"][name]["transport"] == "zenoh-router":
                out.append({"target": f"{name}: Zenoh via one router faster than MQTT (p50 and p99)",
                            "ratio_p50": rr["p50"], "ratio_p99": rr["p99"], "ok": rr["p50"] < 1 and rr["p99"] < 1})
    wan = results.get("wan")
    if wan and "blackout" in wan["profiles"]:
        b = wan["profiles"]["blackout"]["blackout_summary"]
        out.append({"target": f"blackout: robot stops within {b['limit_ms']:.0f} ms of the last command, every trial",
                    "passed": b["passed"], "trials": b["trials"], "max_ms": b["stop_ms"]["max"],
                    "ok": b["trials"] > 0 and b["passed"] == b["trials"]})
    sc = results.get("scale")
    if sc:
        for p in sc["points"]:
            if p["n"] == 20:
                out.append({"target": f"scale ({p['topology']}): 20 robots, no command lost, p99 ≤ 10 ms",
                            "operators": p["operators"], "lost": p["lost"], "p99_ms": p["rtt_ms"]["p99"], "ok": p["lost"] == 0 and p["rtt_ms"]["p99"] <= 10})
    return out


def print_targets(checks: list[dict[str, Any]]) -> None:
    if not checks:
        return
    print("\nTargets (issue 9):")
    for c in checks:
        detail = ", ".join(f"{k}={fmt(v)}" for k, v in c.items() if k not in ("target", "ok"))
        print(f"  [{'PASS' if c['ok'] else 'MISS'}] {c['target']}: {detail}")
