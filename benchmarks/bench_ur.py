"""Command-path latency with the UR backend: operator → router → edge (URRobot, ur_rtde) → UR emulator.

Processes: a Zenoh router (here), the UR emulator (``python -m iorthand_edge.ur_emulator``, 500 Hz like an
e-Series), the edge agent (``iorthand edge``, armed through its local socket) and an OperatorClient (here)
streaming 60 Hz twists that reverse along x every ``--step`` seconds. Two figures:

- ``applied_echo_ms``: command sent → the edge's AppliedCommand echo received. The echo is published after
  the supervisor accepted the command and the backend handed the speedL to its driver child.
- ``motion_visible_ms``: the first command of a reversal sent → the first ``state/robot`` whose TCP speed
  shows the reversal (by > 0.5 mm/s). This crosses ur_rtde both ways: speedL into the controller, the
  controller's next cycle, RTDE output back, the driver's state relay, the agent's next control cycle.

Both are measured on the operator's clock. Writes benchmarks/results/ur.json.

    .venv/bin/python benchmarks/bench_ur.py --duration 20
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml
import zenoh

from iorthand import keys
from iorthand.protocol import RobotState
from iorthand.stats import summary
from iorthand.transport import client_config, free_port, open_session, router_json5
from iorthand_edge.ur_emulator.process import EmulatorProcess
from iorthand_operator.client import OperatorClient

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"


def _stop(proc: subprocess.Popen[Any]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def _wait(pred: Any, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        time.sleep(0.01)


def run(duration: float, step: float, speed: float, frequency: float) -> dict[str, Any]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(zenoh.Config.from_json5(router_json5(endpoint)))
    emu = EmulatorProcess(frequency=frequency).wait_ready()
    host = emu.host
    procs: list[subprocess.Popen[Any]] = []
    tmp = tempfile.TemporaryDirectory()
    op: OperatorClient | None = None
    session: zenoh.Session | None = None
    try:
        sock = Path(tmp.name) / "edge.sock"
        cfg = {
            "robot_id": "ur1",
            "zenoh": {"mode": "client", "connect": [endpoint]},
            "robot": {"kind": "ur", "host": host},
            "safety": {"auto_arm": False, "profile": "local", "lease": 30.0},
            "local_socket": str(sock),
        }
        path = Path(tmp.name) / "edge-ur.yaml"
        path.write_text(yaml.safe_dump(cfg))
        procs.append(subprocess.Popen([sys.executable, "-m", "iorthand.cli", "--log-level", "warning", "edge",
                                       "--config", str(path)]))
        session = open_session(client_config(endpoint))
        states: list[tuple[int, float]] = []  # (receive wall ns, tcp speed x)

        def on_state(sample: zenoh.Sample) -> None:
            with contextlib.suppress(Exception):
                states.append((time.time_ns(), float(RobotState.decode(sample.payload.to_bytes()).tcp_speed[0])))

        sub = session.declare_subscriber(keys.RobotKeys("ur1").key(keys.STATE_ROBOT), on_state)
        op = OperatorClient(session, "ur1", "bench")
        op.wait_for_state(timeout=30)
        _wait(sock.exists, 10, "the edge's local socket")
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
            conn.connect(str(sock))
            conn.sendall(b"arm\n")
            conn.recv(256)
        reply = op.acquire("local")
        if not reply.ok:
            raise RuntimeError(f"acquire refused: {reply.reason}")
        op.start()
        direction = 1.0
        op.set_twist([speed, 0, 0], [0, 0, 0], deadman=True)
        time.sleep(1.0)
        op.echoes.clear()
        steps: list[int] = []  # send time (wall ns) of each reversal's first command
        t_end = time.monotonic() + duration
        while time.monotonic() < t_end:
            time.sleep(step)
            direction = -direction
            before = op.sent_count
            op.set_twist([direction * speed, 0, 0], [0, 0, 0], deadman=True)
            _wait(lambda before=before: op.sent_count > before, 1.0, "the next command")
            steps.append(op.last_sent_ns)
        op.set_twist([0, 0, 0], [0, 0, 0], deadman=False)
        time.sleep(0.5)
        sub.undeclare()
        echo = [e.rtt_ms for e in op.echoes if e.accepted]
        motion: list[float] = []
        samples = list(states)
        for i, t_send in enumerate(steps):
            new_dir = -1.0 if i % 2 == 0 else 1.0
            old_speed = -new_dir * speed
            for t_recv, vx in samples:
                if t_recv > t_send and (vx - old_speed) * new_dir > 0.0005:
                    motion.append((t_recv - t_send) / 1e6)
                    break
        return {
            "benchmark": "ur_command_path",
            "path": "OperatorClient → Zenoh router → iorthand edge (URRobot, ur_rtde 1.6.5 driver child) → UR emulator",
            "rate_hz": op.rate_hz,
            "duration_s": duration,
            "reversal_every_s": step,
            "speed_m_s": speed,
            "emulator_frequency_hz": frequency,
            "commands_sent": op.sent_count,
            "applied_echo_ms": summary(echo),
            "motion_visible_ms": summary(motion),
            "reversals": len(steps),
            "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
        }
    finally:
        if op is not None:
            with contextlib.suppress(Exception):
                op.close()
        if session is not None:
            with contextlib.suppress(Exception):
                session.close()
        for proc in reversed(procs):
            _stop(proc)
        emu.stop()
        router.close()
        tmp.cleanup()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0, help="s of 60 Hz commands measured")
    ap.add_argument("--step", type=float, default=0.5, help="s between reversals of the commanded x speed")
    ap.add_argument("--speed", type=float, default=0.01, help="m/s commanded (±)")
    ap.add_argument("--frequency", type=float, default=500.0, help="emulator controller rate, Hz")
    ap.add_argument("--out", type=Path, default=RESULTS / "ur.json")
    args = ap.parse_args()
    result = run(args.duration, args.step, args.speed, args.frequency)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    e, m = result["applied_echo_ms"], result["motion_visible_ms"]
    print(f"applied echo: p50 {e['p50']:.2f} ms, p99 {e['p99']:.2f} ms (n={e['count']}); "
          f"motion visible: p50 {m['p50']:.1f} ms, p99 {m['p99']:.1f} ms (n={m['count']}) → {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
