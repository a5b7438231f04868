"""Recorder benchmarks → JSON (default benchmarks/results/recorder.json).

Processes: a router (``iorthand router``), the recorder (``iorthand recorder``), and a synthetic full-rate robot
(``python -m iorthand_cloud.recorder.simulate``: state 125 Hz, force 100 Hz, markers 30 Hz, commands 60 Hz +
echoes, safety 20 Hz, force level 10 Hz, camera JPEG 640×480 30 fps), all on 127.0.0.1. This process only sends
queries and reads the results.

- ``startstop``: N start/stop cycles while the robot publishes. Start latency = start query sent → the first
  message of the session flushed into its file (the recorder stamps that instant; same host clock); stop
  latency = stop query sent → files closed (footer written, fsync'd). Reply round trips are reported too.
- ``session``: one recording of ``--duration`` s (300 for the issue's 5 minutes): messages/s, MB/s, recorder
  CPU % (psutil, one core = 100 %), sequence gaps, malformed, dropped.
- ``kill9``: SIGKILL the recorder mid-session, restart it (repair), measure what was lost at the end.

Usage: ``python benchmarks/bench_recorder.py [--duration 300] [--cycles 50] [--only startstop,session,kill9]``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil
import yaml

from iorthand import stats
from iorthand.transport import client_config, free_port, open_session
from iorthand_cloud.recorder import client
from iorthand_cloud.recorder import manifest as mf
from iorthand_cloud.recorder.reader import iter_records, segment_files

ROOT = Path(__file__).resolve().parent.parent


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "iorthand.cli", *args]


def _wait_line(proc: subprocess.Popen[bytes], text: str, timeout: float = 30.0) -> None:
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout
    for line in proc.stdout:
        if text.encode() in line:
            return
        if time.monotonic() > deadline:
            break
    raise RuntimeError(f"{proc.args} did not print {text!r}")


def _stop(proc: subprocess.Popen[bytes] | None, sig: int = signal.SIGTERM) -> None:
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(sig)
    try:
        proc.wait(15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)


class Rig:
    def __init__(self, workdir: Path) -> None:
        self.workdir = workdir
        workdir.mkdir(parents=True, exist_ok=True)
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.out = workdir / "sessions"
        self.cfg = workdir / "recorder.yaml"
        self.cfg.write_text(yaml.safe_dump({
            "zenoh": {"mode": "client", "connect": [self.endpoint]}, "output_dir": str(self.out),
            "flush_interval": 0.5, "fsync": True,
        }))
        self.router: subprocess.Popen[bytes] | None = None
        self.recorder: subprocess.Popen[bytes] | None = None
        self.sim: subprocess.Popen[bytes] | None = None

    def start_router(self) -> None:
        self.router = subprocess.Popen(_cli("router", "--listen", self.endpoint), stdout=subprocess.PIPE,
                                       stderr=subprocess.STDOUT)
        _wait_line(self.router, "router ready")

    def start_recorder(self, *extra: str) -> None:
        log = (self.workdir / "recorder.log").open("ab")
        self.recorder = subprocess.Popen(_cli("recorder", "--config", str(self.cfg), *extra), stdout=subprocess.PIPE,
                                         stderr=log)
        _wait_line(self.recorder, "recorder ready")

    def start_sim(self, duration: float, name: str = "sim") -> Path:
        out = self.workdir / f"{name}.json"
        self.sim = subprocess.Popen(
            [sys.executable, "-m", "iorthand_cloud.recorder.simulate", "--connect", self.endpoint,
             "--duration", str(duration), "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        _wait_line(self.sim, "synthetic session ready")
        time.sleep(0.6)  # the simulator waits 0.5 s for subscriptions before publishing
        return out

    def close(self) -> None:
        for p in (self.sim, self.recorder, self.router):
            _stop(p)


def bench_startstop(rig: Rig, cycles: int) -> dict[str, Any]:
    rig.start_recorder()
    rig.start_sim(cycles * 0.6 + 20)
    s = open_session(client_config(rig.endpoint))
    start_ms, stop_ms, start_rtt, stop_rtt = [], [], [], []
    try:
        # Warm-up (not measured): wait until the robot's messages reach the recorder.
        assert client.start(s, session_id="warm-up").ok
        deadline = time.monotonic() + 20
        while client.status(s).messages == 0 and time.monotonic() < deadline:
            time.sleep(0.1)
        client.stop(s)
        for i in range(cycles):
            t0 = time.time_ns()
            st = client.start(s, session_id=f"cycle-{i:03d}")
            start_rtt.append((time.time_ns() - t0) / 1e6)
            assert st.ok, st.reason
            time.sleep(0.2)
            t1 = time.time_ns()
            sp = client.stop(s)
            stop_rtt.append((time.time_ns() - t1) / 1e6)
            assert sp.ok and sp.first_message_t, sp.reason
            start_ms.append((sp.first_message_t - t0) / 1e6)
            stop_ms.append((sp.closed_t - t1) / 1e6)
            time.sleep(0.1)
    finally:
        s.close()
        _stop(rig.sim)
        _stop(rig.recorder)
    r = lambda v: {k: round(x, 3) for k, x in stats.summary(v).items()}  # noqa: E731
    return {"cycles": cycles, "start_to_first_message_in_file_ms": r(start_ms), "stop_to_file_closed_ms": r(stop_ms),
            "start_reply_rtt_ms": r(start_rtt), "stop_reply_rtt_ms": r(stop_rtt),
            "publishing_during_cycles": "full-rate synthetic robot incl. 30 fps video"}


def bench_session(rig: Rig, duration: float) -> dict[str, Any]:
    rig.start_recorder()
    proc = psutil.Process(rig.recorder.pid)  # type: ignore[union-attr]
    s = open_session(client_config(rig.endpoint))
    try:
        assert client.start(s, session_id="full-rate").ok
        sim_out = rig.start_sim(duration, "session-sim")
        proc.cpu_percent(None)
        cpu0 = proc.cpu_times()
        t0 = time.monotonic()
        samples: list[float] = []
        rss: list[int] = []
        while rig.sim.poll() is None:  # type: ignore[union-attr]
            time.sleep(1.0)
            samples.append(proc.cpu_percent(None))
            rss.append(proc.memory_info().rss)
        elapsed = time.monotonic() - t0
        cpu1 = proc.cpu_times()
        time.sleep(0.5)
        sp = client.stop(s)
    finally:
        s.close()
        _stop(rig.recorder)
    sim = json.loads(sim_out.read_text())
    m = mf.Manifest.read(rig.out / "full-rate")
    t = mf.totals(m.keys)
    span = (max(k.last_t or 0 for k in m.keys.values()) - min(k.first_t or 0 for k in m.keys.values())) / 1e9
    disk = sum(p.stat().st_size for p in segment_files(rig.out / "full-rate"))
    published = sum(sim["published"].values())
    cpu_s = (cpu1.user + cpu1.system) - (cpu0.user + cpu0.system)
    return {
        "duration_s": round(span, 2), "published": published, "recorded": t["messages"],
        "missing_by_sequence": t["missing"], "gaps": t["gaps"], "malformed": t["malformed"], "dropped": m.dropped,
        "messages_per_s": round(t["messages"] / span, 1), "payload_MB_per_s": round(t["bytes"] / span / 1e6, 3),
        "disk_MB_per_s": round(disk / span / 1e6, 3), "disk_MB": round(disk / 1e6, 1),
        "recorder_cpu_percent_mean": round(100 * cpu_s / elapsed, 1),
        "recorder_cpu_percent_p95_1s": round(stats.percentile(samples, 95), 1) if samples else None,
        "recorder_rss_MB_max": round(max(rss) / 1e6, 1) if rss else None,
        "per_key": {k: {"messages": v.messages, "missing": v.missing, "MB": round(v.bytes / 1e6, 2)}
                    for k, v in sorted(m.keys.items())},
        "segments": [s.file for s in m.segments], "status": m.status, "stop_reply_ok": sp.ok,
        "simulator_max_late_ms": round(sim["late_ms_max"], 1),
    }


def bench_kill9(rig: Rig, before_kill: float = 8.0) -> dict[str, Any]:
    rig.start_recorder("--start-now", "--session", "killed")
    rig.start_sim(before_kill + 5)
    time.sleep(before_kill)
    kill_ns = time.time_ns()
    os.kill(rig.recorder.pid, signal.SIGKILL)  # type: ignore[union-attr]
    rig.recorder.wait(5)  # type: ignore[union-attr]
    _stop(rig.sim)
    t0 = time.monotonic()
    rig.start_recorder()  # start-up repairs the killed session
    repair_s = time.monotonic() - t0
    _stop(rig.recorder)
    folder = rig.out / "killed"
    m = mf.Manifest.read(folder)
    last = max((r.log_time for r in iter_records(folder)), default=0)
    return {
        "killed_after_s": before_kill, "status_after_restart": m.status, "repaired": m.repaired,
        "segments": [{"file": s.file, "status": s.status, "recovered_messages": s.recovered_messages,
                      "lost_tail_bytes": s.lost_bytes} for s in m.segments],
        "recovered_messages": mf.totals(m.keys)["messages"],
        "lost_at_end_s": round((kill_ns - last) / 1e9, 3),
        "restart_with_repair_s": round(repair_s, 2),
        "missing_by_sequence_in_recovered_part": mf.totals(m.keys)["missing"],
    }


def main() -> int:
    p = argparse.ArgumentParser(description="recorder benchmarks")
    p.add_argument("--duration", type=float, default=300.0, help="s of the full-rate session")
    p.add_argument("--cycles", type=int, default=50)
    p.add_argument("--only", default="startstop,session,kill9")
    p.add_argument("--keep", action="store_true", help="keep the sessions and logs")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "recorder.json"))
    args = p.parse_args()
    which = set(args.only.split(","))
    results: dict[str, Any] = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "load_avg_at_start": os.getloadavg()},
        "mutual_reference_start_ms": {"scripted_recorder": 639, "ros2_local": 142, "ros2_networked": 1211},
    }
    tmp = tempfile.mkdtemp(prefix="bench-recorder-")
    try:
        for name, fn in (("startstop", lambda r: bench_startstop(r, args.cycles)),
                         ("session", lambda r: bench_session(r, args.duration)),
                         ("kill9", bench_kill9)):
            if name not in which:
                continue
            rig = Rig(Path(tmp) / name)
            try:
                rig.start_router()
                results[name] = fn(rig)
                # Other work on this shared machine inflates tails: keep the load next to each figure.
                results[name]["load_avg_after"] = [round(x, 2) for x in os.getloadavg()]
            finally:
                rig.close()
            print(json.dumps({name: results[name]}, indent=1), flush=True)
    finally:
        if args.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.exists() and which != {"startstop", "session", "kill9"}:  # a partial re-run updates its sections
        results = {**json.loads(out.read_text()), **results}
    out.write_text(json.dumps(results, indent=1))
    print(f"results: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
