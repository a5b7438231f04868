"""Twin load benchmark: 4 simulated robots publishing every stream at full rate; the twin's CPU and lag.

Processes (so each one's CPU is measured alone): a Zenoh router (this process), one publisher process for the
4 robots (state/robot 125 Hz, state/safety 20 Hz, state/force 100 Hz, state/force_level 10 Hz, markers 30 Hz,
state/servo 2 Hz, video/camera and video/ultrasound 15 fps of ~30 KB each, and each robot's liveliness token
``alive/edge``), the twin (``iorthand twin``, serving the web viewer through the rerun relay as deployed) and
the relay. No browser is connected (software rendering would take both cores).

Reports the twin's CPU (% of one core), the relay's, the received/published ratio per stream (does the twin
keep up?), and the snapshot lag (answer in hand − the edge's source time of the pose in it).

    .venv/bin/python benchmarks/bench_twin.py [--seconds 15] [--out benchmarks/results/twin.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil
import yaml
import zenoh

from iorthand import geometry, keys, stats
from iorthand.protocol import (
    ForceLevelState,
    ForceSample,
    MarkerPose,
    Markers,
    RobotState,
    SafetyStatus,
    ServoState,
    TwinSnapshot,
    VideoFrame,
)
from iorthand.transport import client_config, free_port, open_session, publisher, query, router_json5

ROBOTS = ["r1", "r2", "r3", "r4"]
RATES = {  # Hz per robot
    keys.STATE_ROBOT: 125.0,
    keys.STATE_FORCE: 100.0,
    keys.MARKERS: 30.0,
    keys.STATE_SAFETY: 20.0,
    keys.VIDEO_CAMERA: 15.0,
    keys.VIDEO_ULTRASOUND: 15.0,
    keys.STATE_FORCE_LEVEL: 10.0,
    keys.STATE_SERVO: 2.0,
}


def publish(endpoint: str, seconds: float, counts_path: str) -> None:
    """The publisher process: all robots, all streams, one scheduler thread (like 4 edges' outputs)."""
    s = open_session(client_config(endpoint))
    pubs = {(r, k): publisher(s, keys.RobotKeys(r).key(k)) for r in ROBOTS for k in RATES}
    tokens = [s.liveliness().declare_token(keys.RobotKeys(r).key(keys.ALIVE_EDGE)) for r in ROBOTS]
    rng = np.random.default_rng(0)
    jpeg = b"\xff\xd8" + rng.integers(0, 255, 30_000, dtype=np.uint8).tobytes() + b"\xff\xd9"
    marker = geometry.flatten(geometry.make_transform(None, [0.35, 0.02, 0.05]))
    counts = {f"{r}/{k}": 0 for r in ROBOTS for k in RATES}
    seq = dict.fromkeys(counts, 0)
    nxt = dict.fromkeys(counts, time.monotonic() + 1.0)
    end = time.monotonic() + 1.0 + seconds
    t0 = time.monotonic()
    while True:
        now = time.monotonic()
        if now >= end:
            break
        due = min(nxt.values())
        if due > now:
            time.sleep(due - now)
            continue
        for name, t_next in list(nxt.items()):
            if t_next > now:
                continue
            r, k = name.split("/", 1)
            seq[name] += 1
            n, tt = seq[name], now - t0
            if k == keys.STATE_ROBOT:
                pose = [0.3 + 0.05 * math.sin(tt), 0.05 * math.cos(tt), 0.2, math.pi, 0.0, 0.0]
                msg = RobotState(tcp_pose=pose, q=[0.0, -1.57, 1.57, -1.57, -1.57, 0.0], mode="running")
            elif k == keys.STATE_FORCE:
                msg = ForceSample(force=[0.1, 0.0, 5.0 + 2 * math.sin(3 * tt)])
            elif k == keys.MARKERS:
                msg = Markers(markers=[MarkerPose(id=i, pose=marker, raw=marker) for i in range(3)], fps=30.0)
            elif k == keys.STATE_SAFETY:
                msg = SafetyStatus(armed=True, owner="op1", status="ok", profile="remote", force_stale=False)
            elif k in (keys.VIDEO_CAMERA, keys.VIDEO_ULTRASOUND):
                msg = VideoFrame(source=k.rsplit("/", 1)[1], width=640, height=480, data=jpeg)
            elif k == keys.STATE_FORCE_LEVEL:
                v = 5.0 + 2 * math.sin(3 * tt)
                msg = ForceLevelState(level=0 if v < 6 else 1, stale=False, value=v)
            else:
                msg = ServoState(pan=0.1 * math.sin(tt), tilt=0.0)
            pubs[(r, k)].put(msg.stamp(n).encode())
            counts[name] += 1
            period = 1.0 / RATES[k]
            nxt[name] = t_next + period if now - t_next < period else now + period
    Path(counts_path).write_text(json.dumps(counts))
    del tokens
    s.close()


def cpu_percent(proc: psutil.Process, seconds: float) -> float:
    a = proc.cpu_times()
    t = time.monotonic()
    time.sleep(seconds)
    b = proc.cpu_times()
    return 100.0 * ((b.user - a.user) + (b.system - a.system)) / (time.monotonic() - t)


def children_named(proc: psutil.Process, name: str) -> list[psutil.Process]:
    return [c for c in proc.children(recursive=True) if name in " ".join(c.cmdline())]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "twin.json"))
    ap.add_argument("--no-serve", action="store_true", help="twin without the web viewer relay (no rerun sink)")
    args = ap.parse_args()

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(zenoh.Config.from_json5(router_json5(endpoint)))
    tmp = Path(tempfile.mkdtemp(prefix="bench_twin_"))
    cfg = {
        "zenoh": {"mode": "client", "connect": [endpoint]},
        "viewer": {"serve": not args.no_serve, "enabled": not args.no_serve, "bind": "127.0.0.1",
                   "grpc_port": free_port(), "web_port": free_port()},
    }
    (tmp / "twin.yaml").write_text(yaml.safe_dump(cfg))
    twin = subprocess.Popen([sys.executable, "-m", "iorthand.cli", "--log-level", "warning", "twin", "--config",
                             str(tmp / "twin.yaml"), "--log-dir", str(tmp)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    assert twin.stdout is not None
    deadline = time.monotonic() + 60
    for line in twin.stdout:
        if b"twin ready" in line or time.monotonic() > deadline:
            break
    threading.Thread(target=lambda: [None for _ in twin.stdout], daemon=True).start()  # type: ignore[union-attr]
    counts_path = tmp / "counts.json"
    pub = subprocess.Popen([sys.executable, __file__, "--publish", endpoint, str(args.seconds + 6), str(counts_path)])
    tp = psutil.Process(twin.pid)
    relay = children_named(tp, "--serve-web")
    time.sleep(4.0)  # warm-up: routes, first frames, relay connection
    pp = psutil.Process(pub.pid)
    results: dict[str, float] = {}
    meas = [("twin", tp), ("publisher", pp)] + [("relay", r) for r in relay]
    cpu_threads = {name: threading.Thread(target=lambda n=name, p=p: results.__setitem__(n, cpu_percent(p, args.seconds)))
                   for name, p in meas}
    for t in cpu_threads.values():
        t.start()
    s = open_session(client_config(endpoint))
    lags: list[float] = []
    snaps_t0 = time.monotonic()
    while time.monotonic() - snaps_t0 < args.seconds - 0.5:
        for r in ROBOTS:
            (payload,) = query(s, keys.service_key(keys.TWIN, r, keys.TWIN_SNAPSHOT), b"")
            snap = TwinSnapshot.decode(payload)
            lags.append((time.time_ns() - snap.robot_t) / 1e6)
        time.sleep(0.1)
    for t in cpu_threads.values():
        t.join()
    pub.wait(30)
    time.sleep(0.5)
    published = json.loads(counts_path.read_text())
    received: dict[str, int] = {}
    online = 0
    for r in ROBOTS:
        (payload,) = query(s, keys.service_key(keys.TWIN, r, keys.TWIN_SNAPSHOT), b"")
        snap = TwinSnapshot.decode(payload)
        online += snap.online
        for st in snap.streams:
            received[f"{r}/{st.key}"] = st.count
    ratio = {k: round(received.get(f"r1/{k}", 0) / max(published[f"r1/{k}"], 1), 4) for k in RATES}
    total_rate = sum(RATES.values()) * len(ROBOTS)
    s.close()
    twin.terminate()
    twin.wait(10)
    router.close()
    out = {
        "benchmark": "twin: 4 simulated robots at full rate",
        "robots": len(ROBOTS),
        "rates_hz_per_robot": RATES,
        "messages_per_s": total_rate,
        "video_frame_bytes": 30_004,
        "seconds": args.seconds,
        "viewer": "served via rerun relay, no browser connected" if not args.no_serve else "off",
        "cpu_percent_one_core": {k: round(v, 1) for k, v in results.items()},
        "received_over_published_r1": ratio,
        "received_total": sum(received.values()),
        "published_total": sum(published.values()),
        "robots_online_at_end": online,
        "snapshot_lag_ms": {k: round(v, 2) for k, v in stats.summary(lags).items()},
        "machine": {"cpus": psutil.cpu_count(), "python": platform.python_version(),
                    "load_average_1min_at_end": round(os.getloadavg()[0], 2)},
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2))
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--publish":
        publish(sys.argv[2], float(sys.argv[3]), sys.argv[4])
        sys.exit(0)
    sys.exit(main())
