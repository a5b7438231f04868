"""Perception throughput on one thread: fps, per-stage ms, frame-to-publish latency.

    PYTHONPATH=edge:. python benchmarks/bench_perception.py [--frames 300]

Frames are rendered beforehand by the synthetic camera (rendering is not timed), converted to BGR as a real
camera delivers them, stamped just before processing, and "published" by encoding the Markers message.
Writes benchmarks/results/perception.json and prints a summary. Not part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from pathlib import Path

import cv2
import numpy as np

from iorthand.config import from_dict
from iorthand.geometry import compose, invert
from iorthand_edge.perception.camera import Frame
from iorthand_edge.perception.chain import CameraChain
from iorthand_edge.perception.config import PerceptionConfig
from iorthand_edge.perception.pipeline import PerceptionPipeline
from iorthand_edge.perception.synthetic import SyntheticCamera, look_at

RESULTS = Path(__file__).resolve().parent / "results" / "perception.json"
SERVO = (0.2, -0.1)
MARKER_POSES = [
    [0.40, 0.05, 0.02, 0.0, 0.0, 0.4],
    [0.465, 0.045, 0.03, 0.2, -0.1, 0.6],
    [0.335, 0.055, 0.015, -0.15, 0.2, 0.2],
    [0.40, -0.01, 0.02, 0.0, 0.1, -0.3],
]


def make_config(width: int, height: int, markers: int) -> PerceptionConfig:
    focal = 600.0 * width / 640
    return from_dict(
        {
            "camera": {
                "kind": "synthetic",
                "width": width,
                "height": height,
                "fx": focal,
                "fy": focal,
                "cx": (width - 1) / 2,
                "cy": (height - 1) / 2,
                "noise_sigma": 2.0,
                "blur_sigma": 0.6,
            },
            "geometry": {"tcp_mount": [0.0, 0.045, 0.03, 0, 0, 0], "tilt_camera": [0.0, 0.015, 0.035, 0, 0, 0]},
            "scene": {"markers": [{"id": i + 1, "size": 0.045, "pose": MARKER_POSES[i]} for i in range(markers)]},
        },
        PerceptionConfig,
    )


def run_case(width: int, height: int, markers: int, frames: int) -> dict[str, object]:
    config = make_config(width, height, markers)
    chain = CameraChain(config.geometry)
    poses = []
    for i in range(16):  # a few viewpoints 0.3 m above the markers, cycled
        angle = 2 * math.pi * i / 16
        eye = np.array([0.40 + 0.08 * math.cos(angle), 0.03 + 0.08 * math.sin(angle), 0.32])
        poses.append(
            compose(look_at(eye, np.array([0.40, 0.03, 0.02]), 0.2 * math.sin(angle)), invert(chain.tcp_camera(*SERVO)))
        )
    images = []
    for pose in poses:
        camera = SyntheticCamera.from_config(config, lambda _t, p=pose: p, lambda _t: SERVO)
        images.append(cv2.cvtColor(camera.capture(0).image, cv2.COLOR_GRAY2BGR))
    current = {"pose": poses[0]}
    pipeline = PerceptionPipeline(config, lambda _t: current["pose"], lambda _t: SERVO, lambda _m: None)
    stages: dict[str, list[float]] = {k: [] for k in ("convert", "detect", "refine", "pose", "chain", "filter", "total")}
    latencies, seen = [], []
    for i in range(frames):
        current["pose"] = poses[i % len(poses)]
        frame = Frame(images[i % len(images)], time.time_ns(), i)
        message = pipeline.process(frame)
        message.encode()
        latencies.append((time.time_ns() - frame.t_ns) / 1e6)
        seen.append(len(message.markers))
        for name in stages:
            stages[name].append(getattr(pipeline.stats.stages, name))
    mean_total = float(np.mean(stages["total"]))
    return {
        "width": width,
        "height": height,
        "markers": markers,
        "frames": frames,
        "markers_found_mean": float(np.mean(seen)),
        "fps": 1000.0 / float(np.mean(latencies)),
        "processing_fps": 1000.0 / mean_total,
        "stage_ms_mean": {k: round(float(np.mean(v)), 4) for k, v in stages.items()},
        "latency_ms": {
            p: round(float(np.percentile(latencies, q)), 4) for p, q in (("p50", 50), ("p99", 99), ("max", 100))
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=300)
    args = parser.parse_args()
    cv2.setNumThreads(1)  # the single-thread figures the issue asks for
    cases = [run_case(w, h, n, args.frames) for w, h in ((640, 480), (1280, 720)) for n in (1, 4)]
    result = {
        "benchmark": "perception",
        "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "opencv": cv2.__version__,
        "machine": platform.machine(),
        "threads": 1,
        "note": "fps and latency are frame stamp → Markers encoded (detection, edge refinement, PnP, chain, filter, encode)",
        "cases": cases,
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2), encoding="utf-8")
    for c in cases:
        s = c["stage_ms_mean"]
        print(
            f"{c['width']}×{c['height']} {c['markers']} marker(s): {c['fps']:.0f} fps, p99 {c['latency_ms']['p99']:.2f} ms "
            f"(found {c['markers_found_mean']:.1f}; ms: convert {s['convert']:.2f} detect {s['detect']:.2f} "
            f"refine {s['refine']:.2f} pose {s['pose']:.2f} chain {s['chain']:.3f} filter {s['filter']:.3f})"
        )
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
