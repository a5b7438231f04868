"""Command latency with and without a 30 fps 640×480 JPEG camera stream through the same router.

Starts a router and an edge agent (simulated robot, force sensor, servos, torch) as separate processes on
127.0.0.1, with shared memory off (as between sites: every byte goes through the router's TCP links). The
benchmark process is the operator: it holds the deadman and streams 60 Hz twists, and measures each command's
round trip to the edge's ``state/applied`` echo. Phases alternate: the edge without video, then with the
camera stream (plus a subscriber in this process on its own session, so the frames really cross the router).
Writes benchmarks/results/video_load.json.

    .venv/bin/python benchmarks/bench_video_load.py [--seconds 15] [--rounds 2]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import yaml

from iorthand import keys, stats
from iorthand.protocol import VideoFrame
from iorthand.transport import client_config, free_port, open_session
from iorthand_operator.client import OperatorClient

ROOT = Path(__file__).resolve().parent.parent
RESULT = ROOT / "benchmarks" / "results" / "video_load.json"
ROBOT = "bench"


def edge_config(endpoint: str, video: bool) -> dict:
    cfg: dict = {
        "robot_id": ROBOT,
        "zenoh": {"mode": "client", "connect": [endpoint], "shared_memory": False},
        "robot": {"kind": "sim", "initial_pose": [0.30, 0.0, 0.20, 3.14159, 0.0, 0.0]},
        "safety": {"auto_arm": True, "profile": "local"},
        "phantom": {"surface_z": 0.15},
        "force": {"sensor": {"kind": "sim"}},
        "servos": {},
        "torch": {},
    }
    if video:
        cfg["video"] = {"camera": {"source": "pattern", "width": 640, "height": 480, "fps": 30, "quality": 80}}
    return cfg


def start(argv: list[str], log: Path, ready: str, timeout: float = 30.0) -> subprocess.Popen[bytes]:
    out = log.open("wb")
    proc = subprocess.Popen(argv, stdout=out, stderr=out, start_new_session=True)
    deadline = time.monotonic() + timeout
    while ready not in log.read_text(errors="replace"):
        if proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"{argv[3]} did not start; see {log}")
        time.sleep(0.05)
    return proc


def stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def phase(endpoint: str, workdir: Path, video: bool, seconds: float, index: int) -> dict:
    cfg_path = workdir / f"edge-{index}.yaml"
    cfg_path.write_text(yaml.safe_dump(edge_config(endpoint, video)))
    edge = start([sys.executable, "-m", "iorthand.cli", "edge", "--config", str(cfg_path)], workdir / f"edge-{index}.log", "edge agent")
    op_session = open_session(client_config(endpoint, shared_memory=False))
    video_session = open_session(client_config(endpoint, shared_memory=False))
    frames: list[tuple[int, int, int]] = []  # (seq, bytes, latency ns)
    lock = threading.Lock()

    def on_frame(sample) -> None:
        payload = sample.payload.to_bytes()
        f = VideoFrame.decode(payload)
        with lock:
            frames.append((f.seq, len(payload), time.time_ns() - f.t))

    sub = video_session.declare_subscriber(keys.RobotKeys(ROBOT).key(keys.VIDEO_CAMERA), on_frame)
    client = OperatorClient(op_session, ROBOT, "bench-op")
    try:
        client.wait_for_state(10.0)
        client.acquire()
        client.start()
        edge_ps = psutil.Process(edge.pid)
        time.sleep(1.0)  # warm-up: subscriptions propagated, video flowing
        with lock:
            frames.clear()
        first = client.echo_count
        cpu0 = edge_ps.cpu_times()
        t0 = time.monotonic()
        direction = 1.0
        while time.monotonic() - t0 < seconds:
            client.set_twist([0.01 * direction, 0, 0], [0, 0, 0], deadman=True)  # back and forth in x
            time.sleep(2.0)
            direction = -direction
        elapsed = time.monotonic() - t0
        cpu1 = edge_ps.cpu_times()
        client.set_twist(np.zeros(3), np.zeros(3), deadman=False)
        echoes = client.echoes_since(first)
        with lock:
            got = list(frames)
    finally:
        client.close()
        sub.undeclare()
        video_session.close()
        op_session.close()
        stop(edge)
    rtts = [e.rtt_ms for e in echoes]
    seqs = [s for s, _, _ in got]
    return {
        "video": video,
        "seconds": round(elapsed, 1),
        "commands_echoed": len(rtts),
        "commands_refused": sum(not e.accepted for e in echoes),
        "command_rtt_ms": {k: round(v, 3) for k, v in stats.summary(rtts).items()},
        "edge_cpu_percent": round(100 * ((cpu1.user + cpu1.system) - (cpu0.user + cpu0.system)) / elapsed, 1),
        "video_frames_received": len(got),
        "video_fps_received": round(len(got) / elapsed, 1),
        "video_frames_missing": (seqs[-1] - seqs[0] + 1 - len(seqs)) if seqs else 0,
        "video_mean_frame_kb": round(sum(b for _, b, _ in got) / len(got) / 1024, 1) if got else 0.0,
        "video_latency_ms": {k: round(v, 2) for k, v in stats.summary([lat / 1e6 for _, _, lat in got]).items()},
    }


def _finite(x: Any) -> Any:  # JSON has no NaN: an empty sample's statistics become null
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_finite(v) for v in x]
    return None if isinstance(x, float) and x != x else x


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=15.0, help="per phase")
    ap.add_argument("--rounds", type=int, default=2, help="pairs of phases (without, with video)")
    args = ap.parse_args()
    workdir = Path(tempfile.mkdtemp(prefix="bench-video-"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    load_before = os.getloadavg()
    router = start([sys.executable, "-m", "iorthand.cli", "router", "--listen", endpoint], workdir / "router.log", "router ready")
    phases = []
    try:
        for r in range(args.rounds):
            for video in (False, True):
                result = phase(endpoint, workdir, video, args.seconds, len(phases))
                phases.append(result)
                print(json.dumps(_finite({"round": r, **result})), flush=True)
    finally:
        stop(router)
    without = [p["command_rtt_ms"]["p99"] for p in phases if not p["video"]]
    with_video = [p["command_rtt_ms"]["p99"] for p in phases if p["video"]]
    summary = {
        "p99_without_video_ms": round(float(np.median(without)), 3),
        "p99_with_video_ms": round(float(np.median(with_video)), 3),
    }
    summary["ratio"] = round(summary["p99_with_video_ms"] / summary["p99_without_video_ms"], 2)
    summary["within_2x"] = summary["ratio"] <= 2.0
    out = {
        "benchmark": "command latency (60 Hz twist → state/applied echo) with and without a 30 fps 640x480 JPEG stream",
        "setup": "router, edge (sim robot + force + servos + torch [+ camera video on its own session]) and operator "
                 "as separate processes on 127.0.0.1, shared memory off; medians over rounds of each phase's p99",
        "cpus": os.cpu_count(),
        "load_average_before": [round(x, 2) for x in load_before],
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
        "summary": summary,
        "phases": phases,
    }
    RESULT.parent.mkdir(parents=True, exist_ok=True)
    RESULT.write_text(json.dumps(_finite(out), indent=2) + "\n")
    print(json.dumps(summary))
    print(f"written {RESULT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
