"""A clinic day in small: the demo's full load for hours (issue 24). Not a CI test.

Starts, as `iorthand demo` does, a router, the recorder, the twin (serving its web viewer, saving its .rrd), the
simulated edge of configs/edge-sim.yaml (robot, force, servos, torch, camera + ultrasound video in H.264,
perception) and one scripted operator that plays configs/demo-script.yaml over and over for ``--minutes``
(one process, one recording: a session, not a series of starts). Every ``--sample-s`` it samples the resident
memory of each service (with its children: the edge's media process, the twin's rerun relay) and how much of it
is Zenoh's shared memory (pools mapped by every receiver, bounded by iorthand.transport.SHM_POOL_SIZE). At the end
it stops the operator, opens the twin's viewer in Debian's Chromium (Playwright) and reads how far its time cursor is
behind live (:mod:`iorthand_cloud.twin.viewer_state`), stops the recording and reads what it holds.

Targets: every service's RSS flat after the first 10 minutes (growth ≤ 50 MB), the viewer ≤ 1 s behind live,
0 messages missing in the recording. Writes benchmarks/results/soak.json and soak.png (RSS over time).

    .venv/bin/python benchmarks/bench_soak.py [--minutes 120] [--sample-s 10]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import psutil
import yaml

from iorthand.transport import free_port
from iorthand_cloud.recorder import manifest as mf
from iorthand_cloud.recorder.reader import iter_records
from iorthand_cloud.twin import viewer_state
from iorthand_operator.bench import report
from iorthand_operator.bench.procs import Group, iorthand_argv

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
SERVICES = ("router", "recorder", "twin", "edge", "operator")
TARGET_GROWTH_MB = 50.0
TARGET_LAG_S = 1.0
SETTLE_MIN = 10.0


def memory_mb(pid: int, children: bool = True) -> tuple[float, float]:
    """Resident memory of a process and (``children``) its children, and how much of it is shared memory (MB):
    Zenoh's pools, which every receiver maps and counts (iorthand.transport.SHM_POOL_SIZE)."""
    try:
        p = psutil.Process(pid)
        procs = [p, *(p.children(recursive=True) if children else [])]
    except psutil.NoSuchProcess:
        return float("nan"), float("nan")
    rss = shm = 0
    for q in procs:
        with contextlib.suppress(psutil.NoSuchProcess, FileNotFoundError, ProcessLookupError):
            rss += q.memory_info().rss
            with open(f"/proc/{q.pid}/status") as f:
                shm += next((int(line.split()[1]) * 1024 for line in f if line.startswith("RssShmem:")), 0)
    return rss / 1e6, shm / 1e6


def settled_growth(samples: list[dict[str, Any]], column: str) -> dict[str, Any]:
    """A column's start, its value at SETTLE_MIN, its end, and its growth after SETTLE_MIN (to its highest)."""
    series = [(s["t_s"], s[column]) for s in samples if s.get(column) == s.get(column)]  # NaN-free
    after = [v for t, v in series if t >= 60 * SETTLE_MIN]
    at_settle = after[0] if after else None
    return {"start_mb": series[0][1] if series else None, "at_10_min_mb": at_settle,
            "end_mb": series[-1][1] if series else None,
            "growth_after_10_min_mb": round(max(after) - at_settle, 1) if after else None}


def long_script(path: Path, minutes: float) -> None:
    """configs/demo-script.yaml's steps, repeated for about ``minutes`` (one session)."""
    demo = yaml.safe_load((ROOT / "configs" / "demo-script.yaml").read_text())
    steps = demo["steps"]
    one = sum(s.get("duration", 0.0) or s.get("wait", 0.0) or 0.0 for s in steps) + 1.0
    # A fifth more than the estimate: a repeat can take less than its steps' durations (a 2-hour run played
    # this script out at 114 min), and the soak stops the operator at its end anyway.
    repeats = max(1, int(minutes * 60 * 1.2 / one) + 1)
    script = {**demo, "name": "soak", "steps": steps * repeats, "patience": 30.0}
    path.write_text(yaml.safe_dump(script, sort_keys=False))


def viewer_lag(url: str, seconds: float = 60.0) -> dict[str, Any]:
    """Open the twin's viewer in Chromium; once it follows live data, how far its cursor is behind now (s)."""
    from playwright.sync_api import sync_playwright

    lags: list[float] = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=[
            "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader"])
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        page.route("**/*", lambda r: r.continue_() if "127.0.0.1" in r.request.url else r.abort())
        opened = time.monotonic()
        page.goto(url, wait_until="domcontentloaded", timeout=60_000)
        deadline = opened + seconds
        while time.monotonic() < deadline:
            page.wait_for_timeout(1000)
            try:
                state = bytes(page.evaluate("window._handle ? Array.from(window._handle.viewer_state()) : []"))
                lag = viewer_state.lag_seconds(state, "time", time.time_ns()) if state else None
            except Exception:  # the viewer is still starting
                lag = None
            if lag is not None:
                lags.append(lag)
        browser.close()
    last = lags[-10:]
    return {"samples": [round(x, 3) for x in lags],
            "lag_s_end_median": round(sorted(last)[len(last) // 2], 3) if last else None}


def gaps_in(folder: Path, keys: set[str], started_ns: int) -> list[dict[str, Any]]:
    """Where each sequence gap of ``keys`` fell: after which message, how many missing, how far into the run (s),
    so that a gap can be matched against what else the machine was doing then."""
    stats = {key: mf.KeyStats() for key in keys}
    found: list[dict[str, Any]] = []
    for rec in iter_records(folder, topics=keys):
        if rec.malformed:
            continue
        st = stats[rec.key]
        after, missing = st.last_seq, st.missing
        st.observe(len(rec.data), rec.log_time, rec.sequence)
        if st.missing > missing:
            found.append({"key": rec.key, "after_seq": after, "missing": st.missing - missing,
                          "at_s": round((rec.log_time - started_ns) / 1e9, 1)})
    return found


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", type=float, default=120.0)
    p.add_argument("--sample-s", type=float, default=10.0)
    p.add_argument("--out", default=str(RESULTS / "soak.json"))
    p.add_argument("--twin-config", default=str(ROOT / "configs" / "twin.yaml"), help="e.g. another memory_limit")
    args = p.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="iorthand-soak-"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    edge = yaml.safe_load((ROOT / "configs" / "edge-sim.yaml").read_text())
    edge["zenoh"]["connect"] = [endpoint]
    (work / "edge.yaml").write_text(yaml.safe_dump(edge))
    (work / "recorder.yaml").write_text(yaml.safe_dump({"zenoh": {"mode": "client", "connect": [endpoint]},
                                                        "output_dir": str(work / "recordings")}))
    long_script(work / "script.yaml", args.minutes)
    web_port, grpc_port = free_port(), free_port()
    samples: list[dict[str, Any]] = []
    stop = threading.Event()
    operator_ended_s: float | None = None  # when the scripted operator finished before the soak did (None: it did not)
    cpu0 = report.cpu_times()
    started = time.time()
    with Group(work) as g:
        procs = {
            "router": g.start("router", iorthand_argv("router", "--listen", endpoint), ready="router ready"),
            "recorder": g.start("recorder", iorthand_argv("recorder", "--config", str(work / "recorder.yaml")),
                                ready="recorder ready"),
            "twin": g.start("twin", iorthand_argv("twin", "--config", args.twin_config, "--connect",
                                                  endpoint, "--save", str(work / "twin.rrd"), "--log-dir", str(work),
                                                  "--web-port", str(web_port), "--grpc-port", str(grpc_port)),
                            ready="twin ready", timeout=60.0),
            "edge": g.start("edge", iorthand_argv("edge", "--config", str(work / "edge.yaml")), ready="edge agent",
                            timeout=60.0),
        }
        subprocess.run(iorthand_argv("recorder", "start", "--connect", endpoint, "--session", "soak", "--robot",
                                     "sim1", "--operator", "soak-operator", "--note", "soak benchmark"),
                       check=True, capture_output=True, timeout=60)
        procs["operator"] = g.start("operator", iorthand_argv("operator", "script", str(work / "script.yaml"),
                                                              "--robot", "sim1", "--operator-id", "soak-operator",
                                                              "--connect", endpoint))

        def sample() -> None:
            t0 = time.monotonic()
            while not stop.wait(0 if not samples else args.sample_s):
                row: dict[str, float] = {"t_s": round(time.monotonic() - t0, 1)}
                for name, c in procs.items():
                    rss, shm = memory_mb(c.proc.pid)
                    row[name], row[f"{name}_shm"] = round(rss, 1), round(shm, 1)
                # The parts: the twin's Python process (its rerun relay is a child), the edge's control process
                # (its media process is a child).
                row["twin_own"] = round(memory_mb(procs["twin"].proc.pid, children=False)[0], 1)
                row["edge_own"] = round(memory_mb(procs["edge"].proc.pid, children=False)[0], 1)
                samples.append(row)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        t_load = time.monotonic()
        end = t_load + 60 * args.minutes
        while time.monotonic() < end:
            time.sleep(5)
            print(f"  soak: {samples[-1] if samples else '…'}", flush=True)
            if operator_ended_s is None and procs["operator"].proc.poll() is not None:
                operator_ended_s = round(time.monotonic() - t_load, 1)
                print(f"  soak: the scripted operator ended at {operator_ended_s} s, before the soak", flush=True)
        # The load ends here; the viewer is measured after it. Chromium starting on this 2-core machine starves
        # the other processes for a moment, and an operator still streaming drops commands at its own sender
        # (command QoS: DROP): a 30-s run lost 8 of 2 777 that way, and the edge got none of the 8 either.
        procs["operator"].stop()
        twin_log = (work / "twin.log").read_text() if (work / "twin.log").exists() else ""
        url = next((line.split(": ", 1)[1] for line in twin_log.splitlines() if line.startswith("twin viewer: ")), "")
        if not url:
            url = f"http://127.0.0.1:{web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc_port}%2Fproxy"
        lag = viewer_lag(url)
        stop.set()
        sampler.join(5)
        subprocess.run(iorthand_argv("recorder", "stop", "--connect", endpoint), capture_output=True, timeout=60)
    manifest = mf.Manifest.read(work / "recordings" / "soak")
    totals = mf.totals(manifest.keys)
    gapped = {key for key, st in manifest.keys.items() if st.missing}
    gaps = gaps_in(work / "recordings" / "soak", gapped, int(started * 1e9)) if gapped else []
    growth = {name: {**settled_growth(samples, name),
                     "of_which_shared_memory": settled_growth(samples, f"{name}_shm")} for name in SERVICES}
    data = {
        "benchmark": "soak", "machine": report.machine(),
        "config": {"minutes": args.minutes, "sample_s": args.sample_s, "workdir": str(work), "started": started,
                   "operator_ended_s": operator_ended_s,
                   "twin_memory_limit": yaml.safe_load(Path(args.twin_config).read_text())["viewer"]["memory_limit"]},
        "host_cpu": report.cpu_share_since(cpu0),
        "rss_mb": samples, "growth": growth, "viewer": lag,
        "recording": {"messages": totals.get("messages"), "missing": totals.get("missing"),
                      "malformed": totals.get("malformed"), "dropped": manifest.dropped, "gaps": gaps},
        "targets": {
            "rss_growth_mb": {"limit": TARGET_GROWTH_MB, "pass": all(
                g["growth_after_10_min_mb"] is not None and g["growth_after_10_min_mb"] <= TARGET_GROWTH_MB
                for g in growth.values())},
            "viewer_lag_s": {"limit": TARGET_LAG_S, "value": lag["lag_s_end_median"],
                             "pass": lag["lag_s_end_median"] is not None and lag["lag_s_end_median"] <= TARGET_LAG_S},
            "missing": {"value": totals.get("missing"), "pass": totals.get("missing") == 0},
        },
    }
    report.write_json(Path(args.out), data)
    _plot(samples, Path(args.out).with_suffix(".png"))
    print(json.dumps({k: data[k] for k in ("growth", "recording", "targets")}, indent=1))
    print(f"wrote {args.out}")
    return 0


def _plot(samples: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.5))
    for name in SERVICES:
        ax.plot([s["t_s"] / 60 for s in samples], [s[name] for s in samples], label=name)
    ax.axvline(SETTLE_MIN, color="grey", linestyle=":", label="10 min")
    ax.set_xlabel("minutes")
    ax.set_ylabel("RSS with children (MB)")
    ax.set_title("soak: resident memory of each service")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    sys.exit(main())
