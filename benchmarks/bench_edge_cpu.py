"""CPU time the edge spends on one twist command, hot (back to back) and cold (after the CPU idled).

No Zenoh and no threads: one edge agent with the simulated robot (the benchmark's edge configuration), armed
and owned, handles signed commands with its control loop's own code (``EdgeAgent.handle_twist``: decode, gate,
signature, supervisor, robot call, echo; then the echo is encoded), and the control loop's state message (robot read +
encode) is timed alongside. Each step is measured
in thread CPU time (``time.thread_time_ns``), so waiting does not count. "Cold" sleeps ``--gap-ms`` before each
command, as the 60 Hz command stream does between commands: on a VM the first Python after an idle gap runs
many times slower (``machine.idle_penalty`` in every ``iorthand bench`` result).

    .venv/bin/python benchmarks/bench_edge_cpu.py [--commands 400] [--gap-ms 16] [--out benchmarks/results/edge_cpu.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

from iorthand import config, keys
from iorthand.protocol import ControlRequest, RobotState, TwistCommand
from iorthand.security import auth
from iorthand_edge.agent import EdgeAgent
from iorthand_edge.config import EdgeConfig
from iorthand_operator.bench.transports import edge_config

STEPS = ("handle_twist", "echo_encode", "state_read_encode")


def make_agent() -> tuple[EdgeAgent, bytes]:
    """The agent, armed and owned by "op", and the key of op's grant (it signs the commands)."""
    agent = EdgeAgent(config.from_dict(edge_config("bench", ["tcp/127.0.0.1:7447"]), EdgeConfig))
    agent.robot.connect()
    agent.reading = agent.robot.read_state()
    agent.supervisor.arm()
    grant = agent.supervisor.acquire(ControlRequest(operator="op").stamp(1), time.monotonic())
    if not grant.ok:
        raise RuntimeError(grant.reason)
    # The grant's first command releases the deadman, as the operator's client sends it: only then may a press move.
    release = TwistCommand(operator="op", deadman=False, state_age=0.01).stamp(1)
    payload = auth.sign(grant.key, auth.context(agent.keys.robot, keys.CMD_TWIST), release).encode()
    agent.handle_twist(agent.keys.key(keys.CMD_TWIST), payload, time.time_ns())
    return agent, grant.key


def one_command(agent: EdgeAgent, key: bytes, seq: int, speed: float) -> dict[str, float]:
    """One command through the control loop's own code (EdgeAgent.handle_twist: decode, gate, signature,
    supervisor, robot call, echo), its echo encoded, and the control loop's state message; each step's thread CPU
    time (µs). The operator's signing is not timed."""
    cmd = TwistCommand(operator="op", linear=[speed, 0.0, 0.0], deadman=True, state_age=0.01).stamp(seq)
    payload = auth.sign(key, auth.context(agent.keys.robot, keys.CMD_TWIST), cmd).encode()
    key = agent.keys.key(keys.CMD_TWIST)
    clock = time.thread_time_ns
    marks = [clock()]
    recv_ns = time.time_ns()
    echo = agent.handle_twist(key, payload, recv_ns)
    marks.append(clock())
    if echo is None or not echo.accepted:
        raise RuntimeError(f"command refused: {echo}")
    echo.encode()
    marks.append(clock())
    with agent.lock:
        reading = agent.robot.read_state()
        RobotState(tcp_pose=reading.tcp_pose, tcp_speed=reading.tcp_speed, q=reading.q, commanded=agent._commanded,
                   mode=reading.mode, cmd_seq=seq, cmd_recv_t=recv_ns).stamp(seq).encode()
    marks.append(clock())
    return {step: (b - a) / 1e3 for step, a, b in zip(STEPS, marks[:-1], marks[1:], strict=True)}


def run(agent: EdgeAgent, key: bytes, first_seq: int, n: int, gap_s: float) -> dict[str, dict[str, float]]:
    samples: dict[str, list[float]] = {step: [] for step in (*STEPS, "command_total")}
    for i in range(n):
        if gap_s:
            time.sleep(gap_s)
        # Alternate a speed under and over the profile's limit: both the plain and the clipping path run.
        steps = one_command(agent, key, first_seq + i, 0.004 if i % 2 else 0.012)
        for step, us in steps.items():
            samples[step].append(us)
        samples["command_total"].append(steps["handle_twist"] + steps["echo_encode"])
    return {
        step: {"p50_us": round(statistics.median(v), 1), "p90_us": round(statistics.quantiles(v, n=10)[-1], 1)}
        for step, v in samples.items()
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--commands", type=int, default=400, help="commands per mode (hot, cold)")
    ap.add_argument("--gap-ms", type=float, default=16.0, help="idle gap before each cold command (60 Hz ≈ 16 ms)")
    ap.add_argument("--out", default="benchmarks/results/edge_cpu.json")
    args = ap.parse_args()
    agent, key = make_agent()
    run(agent, key, 2, 199, 0.0)  # warm-up: imports, caches, first allocations (after the grant's release)
    # One sequence, as one operator's stream: the edge refuses a jump over max_sequence_jump.
    hot = run(agent, key, 201, args.commands, 0.0)
    cold = run(agent, key, 201 + args.commands, args.commands, args.gap_ms / 1000.0)
    result = {
        "benchmark": "edge_cpu",
        "machine": {"hostname": platform.node(), "python": platform.python_version(), "kernel": platform.release()},
        "config": {"commands": args.commands, "gap_ms": args.gap_ms, "robot": "sim"},
        "hot": hot,
        "cold": cold,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(f"{'step':20s} {'hot p50 µs':>11s} {'cold p50 µs':>12s} {'cold p90 µs':>12s}")
    for step in (*STEPS, "command_total"):
        print(f"{step:20s} {hot[step]['p50_us']:11.1f} {cold[step]['p50_us']:12.1f} {cold[step]['p90_us']:12.1f}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
