"""Contact mode under a zig-zag sweep on the curved phantom, live (issue 22): the force error per stiffness.

For each robot (``sim``: the simulated arm and sensor; ``ur``: the real ur_rtde driving the UR emulator, the edge
reading the arm's own wrist sensor over RTDE) and each phantom stiffness (2, 4, 8 N/mm): a router, the twin (the
preview goes through it), the edge as a process (configs/edge-sim.yaml or configs/edge-ur.yaml) with the
thigh-like cylinder under the probe, and an operator client that turns contact mode on (4 N), waits for contact,
previews the sweep (5 lanes of 60 mm, 8 mm apart, 5 mm/s: 66.6 s), runs it holding the deadman, and records the
force along the probe from state/force. Per run: the share of samples within ±1 N of the target, the RMS and max
error, the peak force level (never red: 2), and whether the sweep completed.

Writes benchmarks/results/contact_sweep.json.

    .venv/bin/python benchmarks/bench_contact_sweep.py [--robots sim ur] [--stiffness 2 4 8]
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml
from teleop_stack import CONFIGS, RESULTS, close_operator, edge_config, operator, start_edge, start_router, wait

from iorthand import keys, motion
from iorthand.protocol import ForceSample
from iorthand.transport import free_port
from iorthand_edge.ur_emulator.process import EmulatorProcess
from iorthand_operator.bench.procs import Group, iorthand_argv

TARGET = 4.0
SWEEP = {"width": 0.06, "pitch": 0.008, "lanes": 5, "speed": 0.005}
CYLINDER = {"shape": "cylinder", "axis": "x", "radius": 0.07, "axis_height": 0.08, "x_range": [0.20, 0.40],
            "y_range": [-0.10, 0.10], "damping": 20.0}
START = [0.27, -0.02, 0.16, math.pi, 0.0, 0.0]  # 1 cm above the cylinder, off its crest: lanes cross its curve


def run_one(robot: str, stiffness: float, tmp: Path) -> dict[str, Any]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    emu: EmulatorProcess | None = None
    with Group(tmp / "procs") as group:
        start_router(group, endpoint)
        twin = edge_config(CONFIGS / "twin.yaml", tmp / "twin.yaml", endpoint, {"viewer": {"enabled": False}})
        group.start("twin", iorthand_argv("--log-level", "warning", "twin", "--config", str(twin)))
        phantom = {**CYLINDER, "stiffness": 1000 * stiffness}
        if robot == "sim":
            cfg = edge_config(CONFIGS / "edge-sim.yaml", tmp / "edge.yaml", endpoint, {
                "robot": {"initial_pose": START}, "phantom": phantom, "safety": {"profile": "local"},
                "force": {"sensor": {"kind": "sim", "noise": 0.05}}, "perception": None, "video": None})
            robot_id = yaml.safe_load(cfg.read_text())["robot_id"]
        else:
            emu = EmulatorProcess(frequency=250.0).wait_ready()
            emu.call("set_phantom", phantom=phantom)
            emu.call("set_pose", pose=START)
            sock = tmp / "edge.sock"
            cfg = edge_config(CONFIGS / "edge-ur.yaml", tmp / "edge.yaml", endpoint, {
                "robot": {"host": emu.host}, "safety": {"profile": "local"}, "force": {"sensor": {"kind": "robot"}},
                "local_socket": str(sock)})
            robot_id = "ur1"
        try:
            start_edge(group, cfg)
            if robot == "ur":
                wait(lambda: sock.exists(), 20.0, "the edge's local socket")
                subprocess.run(iorthand_argv("arm", "--config", str(cfg)), check=True, timeout=20, capture_output=True)
            return drive(endpoint, robot_id, robot, stiffness)
        finally:
            if emu is not None:
                emu.stop()


def drive(endpoint: str, robot_id: str, robot: str, stiffness: float) -> dict[str, Any]:
    op = operator(endpoint, robot_id, "bench", profile="local")
    forces: list[tuple[float, float]] = []
    op.session.declare_subscriber(
        keys.RobotKeys(robot_id).key(keys.STATE_FORCE),
        lambda s: forces.append((time.monotonic(), -ForceSample.decode(s.payload.to_bytes()).force[2])))
    try:
        wait(lambda: op.safety is not None and not op.safety.force_stale, 20.0, "a fresh force sensor")
        reply = op.set_contact(True, TARGET)
        assert reply.ok, reply.reason
        op.set_twist([0, 0, 0], [0, 0, 0], deadman=True)
        wait(lambda: bool(forces) and forces[-1][1] > TARGET - 0.5, 15.0, "contact")
        time.sleep(1.0)
        preview = op.preview_pose(motion.SWEEP, SWEEP)
        assert preview.ok, preview.reason
        detail = json.loads(preview.detail)
        started = op.goto_pose(motion.SWEEP, detail["token"])
        assert started.ok, started.reason
        t0 = time.monotonic()
        task = ""
        while time.monotonic() < t0 + detail["duration"] + 15.0:
            task = op.safety.task if op.safety is not None else ""
            if op.safety is not None and not task and time.monotonic() > t0 + 1.0:
                break
            time.sleep(0.05)
        elapsed = time.monotonic() - t0
        op.set_twist([0, 0, 0], [0, 0, 0], deadman=False)
        held = [f for t, f in forces if t0 <= t <= t0 + elapsed]
        errors = [f - TARGET for f in held]
        return {
            "robot": robot, "stiffness_n_per_mm": stiffness, "sweep_s": round(elapsed, 2),
            "planned_s": round(detail["duration"], 2), "completed": elapsed >= detail["duration"] - 0.5,
            "samples": len(held), "within_1n_share": round(sum(abs(e) <= 1.0 for e in errors) / len(errors), 4),
            "rms_error_n": round(math.sqrt(sum(e * e for e in errors) / len(errors)), 3),
            "max_error_n": round(max(abs(e) for e in errors), 3), "peak_level": op.peak_force_level,
            "final_status": op.safety.status if op.safety else "", "final_reason": op.safety.reason if op.safety else "",
        }
    finally:
        close_operator(op)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robots", nargs="+", default=["sim", "ur"], choices=["sim", "ur"])
    ap.add_argument("--stiffness", nargs="+", type=float, default=[2.0, 4.0, 8.0], help="N/mm")
    args = ap.parse_args()
    runs = []
    for robot in args.robots:
        for k in args.stiffness:
            with tempfile.TemporaryDirectory(prefix="iorthand-sweep-") as tmp:
                result = run_one(robot, k, Path(tmp))
            print(json.dumps(result))
            runs.append(result)
    out = {
        "target_n": TARGET, "sweep": SWEEP, "phantom": CYLINDER, "runs": runs,
        "passed": all(r["completed"] and r["within_1n_share"] >= 0.95 and r["peak_level"] < 2 for r in runs),
        "criteria": "each 60 s sweep completes, ≥ 95 % of force samples within ±1 N of the target, never red",
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "contact_sweep.json").write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {RESULTS / 'contact_sweep.json'}: passed={out['passed']}")


if __name__ == "__main__":
    main()
