"""CPU per frame of the demo's simulators: the synthetic camera and the simulated ultrasound probe.

The synthetic camera renders configs/edge-sim.yaml's markers from a camera still above them and from one that
moves every frame (so nothing can be reused); the ultrasound image is rendered in contact (5 N) and in air.
Each figure is process CPU time per frame, over ``--frames`` frames after one warm-up frame, with one OpenCV
thread as in the edge's media process. Run it with another tree first on PYTHONPATH to measure that tree's code (e.g. a
``git worktree`` of an older commit) in the same way:

    .venv/bin/python benchmarks/bench_simulators.py [--frames 200] [--out benchmarks/results/simulators.json]
    PYTHONPATH=/tmp/iorthand-before:/tmp/iorthand-before/edge .venv/bin/python benchmarks/bench_simulators.py --out /tmp/before.json
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import yaml

import iorthand_edge
from iorthand import geometry
from iorthand.config import from_dict
from iorthand_edge.config import EdgeConfig
from iorthand_edge.perception.camera import make_camera
from iorthand_edge.video.sources import UltrasoundSimSource

ROOT = Path(__file__).resolve().parent.parent
HOME = (math.pi / 2, math.pi / 2)  # the demo's servo home: the chain's zero


def per_frame_ms(frame: Callable[[], object], frames: int) -> float:
    frame()  # warm-up: caches, lazy initialisation
    start = time.process_time()
    for _ in range(frames):
        frame()
    return round((time.process_time() - start) / frames * 1e3, 3)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "simulators.json")
    args = parser.parse_args()
    cv2.setNumThreads(1)  # as in the edge's media process (iorthand_edge.media), for both trees alike
    config = from_dict(yaml.safe_load((ROOT / "configs" / "edge-sim.yaml").read_text()), EdgeConfig, source="edge-sim")
    assert config.perception is not None and config.video is not None and config.video.ultrasound is not None
    # The camera 20 cm above the markers, looking down (tool pointing down, as in the demo).
    still = geometry.pose_to_matrix([0.30, -0.05, 0.35, math.pi, 0.0, 0.0])
    step = [0]

    def moving(_t_ns: int) -> np.ndarray:
        step[0] += 1
        return geometry.pose_to_matrix([0.30 + 0.02 * math.sin(step[0] / 30), -0.05, 0.35, math.pi, 0.0, 0.0])

    camera_still = make_camera(config.perception, lambda _t: still, lambda _t: HOME)
    camera_moving = make_camera(config.perception, moving, lambda _t: HOME)
    contact = UltrasoundSimSource(config.video.ultrasound, lambda: 5.0, seed=1)
    air = UltrasoundSimSource(config.video.ultrasound, lambda: 0.0, seed=1)
    results = {
        "synthetic_camera_still_ms": per_frame_ms(lambda: camera_still.capture(time.time_ns()), args.frames),
        "synthetic_camera_moving_ms": per_frame_ms(lambda: camera_moving.capture(time.time_ns()), args.frames),
        "ultrasound_contact_ms": per_frame_ms(contact.grab, args.frames),
        "ultrasound_air_ms": per_frame_ms(air.grab, args.frames),
    }
    data = {
        "benchmark": "simulators",
        "code": str(Path(iorthand_edge.__file__).resolve().parent),
        "machine": {"platform": platform.platform(), "python": platform.python_version()},
        "frames": args.frames,
        "camera": f"{config.perception.camera.width}x{config.perception.camera.height}",  # type: ignore[attr-defined]
        "ultrasound": f"{config.video.ultrasound.width}x{config.video.ultrasound.height}",
        "results": results,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(data, indent=1))
    print(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
