"""PNG plots of benchmark results (matplotlib, no display needed)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt


def latency_plots(cases: dict[str, dict[str, Any]], path: Path, title: str) -> Path:
    """Histogram (log-spaced bins) and time series of round trips, one colour per case."""
    import numpy as np

    fig, (ax_h, ax_t) = plt.subplots(1, 2, figsize=(14, 5))
    all_values = [v for c in cases.values() for v in c.get("samples_ms", []) if v > 0]
    if all_values:
        bins = np.logspace(np.log10(min(all_values)), np.log10(max(all_values)), 60)
        for name, c in cases.items():
            s = c.get("samples_ms", [])
            if s:
                ax_h.hist(s, bins=bins, histtype="step", linewidth=1.5, label=f"{name} (p99 {c['rtt_ms']['p99']:.2f} ms)")
                ax_t.plot(c.get("arrival_s", range(len(s))), s, ".", markersize=2, label=name)
    ax_h.set_xscale("log")
    ax_h.set_xlabel("round trip, ms (log)")
    ax_h.set_ylabel("count")
    ax_h.legend(fontsize=7)
    ax_h.set_title("distribution")
    ax_t.set_yscale("log")
    ax_t.set_xlabel("time in run, s")
    ax_t.set_ylabel("round trip, ms (log)")
    ax_t.set_title("time series")
    ax_t.legend(fontsize=7, markerscale=4)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def cdf_plot(cases: dict[str, dict[str, Any]], path: Path, title: str) -> Path:
    """Cumulative distribution of round trips per case (WAN profiles)."""
    fig, ax = plt.subplots(figsize=(8, 5))
    for name, c in cases.items():
        s = sorted(c.get("samples_ms", []))
        if s:
            ax.plot(s, [(i + 1) / len(s) for i in range(len(s))], label=name)
    ax.set_xscale("log")
    ax.set_xlabel("command → applied → echo round trip, ms (log)")
    ax.set_ylabel("fraction of commands")
    ax.grid(True, alpha=0.3)
    ax.legend()
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def blackout_plot(trials: list[dict[str, Any]], limit_ms: float, path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(8, 4))
    xs = [t["trial"] for t in trials if "stop_after_last_command_ms" in t]
    ys = [t["stop_after_last_command_ms"] for t in trials if "stop_after_last_command_ms" in t]
    ax.bar(xs, ys, color=["tab:green" if y <= limit_ms else "tab:red" for y in ys])
    ax.axhline(limit_ms, color="k", linestyle="--", label=f"command_timeout + control period = {limit_ms:.0f} ms")
    ax.set_xlabel("trial")
    ax.set_ylabel("edge stop after last command received, ms")
    ax.legend(loc="lower right")
    ax.set_title("blackout: deadman stop per trial")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def scale_plot(points: list[dict[str, Any]], path: Path) -> Path:
    fig, (ax_l, ax_c) = plt.subplots(1, 2, figsize=(13, 4.5))
    for topo in sorted({p["topology"] for p in points}):
        pts = sorted((p for p in points if p["topology"] == topo), key=lambda p: p["n"])
        n = [p["n"] for p in pts]
        ax_l.plot(n, [p["rtt_ms"]["p50"] for p in pts], "o-", label=f"{topo} p50")
        ax_l.plot(n, [p["rtt_ms"]["p99"] for p in pts], "s--", label=f"{topo} p99 (all robots)")
        ax_l.plot(n, [p["worst_robot_p99_ms"] for p in pts], "^:", label=f"{topo} worst robot p99")
        ax_c.plot(n, [p["router_cpu_percent_total"] for p in pts], "o-", label=f"{topo} routers' CPU")
    ax_l.set_xlabel("robots (and operators)")
    ax_l.set_ylabel("command → echo round trip, ms")
    ax_l.set_yscale("log")
    ax_l.legend(fontsize=7)
    ax_l.grid(True, alpha=0.3)
    ax_c.set_xlabel("robots (and operators)")
    ax_c.set_ylabel("CPU, % of one core")
    ax_c.legend(fontsize=7)
    ax_c.grid(True, alpha=0.3)
    fig.suptitle("scale: command latency and router CPU")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
