"""Teleoperation while two CPU hogs run (issue 20): false driver faults, lease expiries, deadman stops and the
command→applied round trip, for the simulated robot and for the UR emulator.

For each robot: a Zenoh router (``iorthand router``), the edge agent (``iorthand edge``: configs/edge-sim.yaml
as the demo runs it, video and perception included, auto-armed; or configs/edge-ur.yaml against the UR
emulator, ``python -m iorthand_edge.ur_emulator`` on a loopback address of its own, armed through the agent's
local socket), an :class:`OperatorClient` that holds control, and ``stress-ng --cpu 2`` (Debian package
stress-ng) for the whole ``--duration``. The operator repeats a pattern: it drives along x with the deadman
pressed, releases it (a *release* stop), presses again, drives the other way, and goes silent with the
deadman held (a *timeout* stop: a frozen UI or a cut link); then releases and presses again (motion after a
long gap resumes only on a fresh press).

Figures:

- driver faults: episodes of a fault in state/robot or a ``fault`` status in state/safety. Nothing is
  injected, so every one is false;
- lease expiries: episodes of ``owner_lost`` or a lease in state/safety's reason, and ``not_owner`` echoes;
- deadman stops, each measured on the edge's own clock: from the receive time of the last command it applied
  (state/robot ``cmd_recv_t``) to the first state/safety that says ``command_timeout`` (the decision) and to
  the first state/robot whose commanded twist is zero (the robot told to stop). The bound is the safety
  config's ``command_timeout`` plus one control period. A silence that begins while the robot is already
  stopped (by a fault) is not a stop and is left out (``silences`` counts them all). A release stop: from the
  operator's send time of its first released command to the first zero commanded twist;
- command→applied: the operator's send time to the edge's echo (``OperatorClient.echoes``), accepted ones;
- vCPU steal (``iorthand_operator.bench.steal``): the bursts of CPU time the hypervisor took from this virtual
  machine during the run, and which fault incidents followed one (an incident: fault episodes less than
  ``RECOVERY_S`` apart, a reconnect's steps; it follows a burst of ≥ 50 ms if first seen within 0.5 s after it). On
  the test VM, the host takes a whole vCPU for 100 ms at times under the hogs, and nothing in the guest runs on
  it meanwhile, not even at SCHED_FIFO 99: the UR controller's watchdog is 100 ms.

Writes benchmarks/results/cpu_hogs.json.

    .venv/bin/python benchmarks/bench_cpu_hogs.py [--duration 60] [--robots sim ur]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import socket
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

from teleop_stack import (
    CONFIGS,
    RESULTS,
    Seen,
    Watcher,
    close_operator,
    driver_fault,
    edge_config,
    lease_lost,
    operator,
    start_edge,
    start_router,
    wait,
)

from iorthand.config import load
from iorthand.protocol import RobotState, SafetyStatus, Status
from iorthand.stats import summary
from iorthand.transport import free_port
from iorthand_edge.config import EdgeConfig
from iorthand_edge.ur_emulator.process import EmulatorProcess
from iorthand_operator.bench import steal
from iorthand_operator.bench.procs import Group, Unavailable, python_argv
from iorthand_operator.bench.report import machine, write_json
from iorthand_operator.client import OperatorClient

SPEED = 0.005  # m/s: under the remote profile's 8 mm/s
ROBOTS = {"sim": ("sim1", "edge-sim.yaml"), "ur": ("ur1", "edge-ur.yaml")}
RECOVERY_S = 3.0  # s: a UR driver's reconnect after a fault (back-off 0.5 s, a new child, the script's upload)


def send_time_of_next(op: OperatorClient, before: int, timeout: float = 1.0) -> int:
    """The send time (wall ns) of the first command the sender puts out after ``before`` were sent."""
    wait(lambda: op.sent_count > before, timeout, "the next command")
    return op.last_sent_ns


def teleoperate(op: OperatorClient, duration: float, silence: float) -> tuple[list[int], list[int]]:
    """The operator's pattern for ``duration`` s; returns the send times of the first released command of each
    release and the wall times at which the operator went silent."""
    releases: list[int] = []
    silences: list[int] = []
    direction = 1.0
    t_end = time.monotonic() + duration

    def hold(linear: float, deadman: bool, seconds: float) -> None:
        # Input as a UI gives it, at 20 Hz: the client releases the deadman itself when its input goes silent.
        until = time.monotonic() + seconds
        while time.monotonic() < until:
            op.set_twist([linear, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=deadman)
            time.sleep(0.05)

    while time.monotonic() < t_end:
        hold(direction * SPEED, True, 1.0)
        before = op.sent_count
        op.set_twist([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=False)
        releases.append(send_time_of_next(op, before))
        hold(0.0, False, 0.3)
        direction = -direction
        hold(direction * SPEED, True, 1.0)
        op.muted = True  # the deadman stays held: only the edge's timeout can stop the robot
        silences.append(time.time_ns())
        time.sleep(silence)
        op.muted = False
        hold(0.0, False, 0.3)  # a fresh press is needed after a long gap
        direction = -direction
    hold(0.0, False, 0.3)
    return releases, silences


def timeout_stops(seen: Seen, silences: list[int], silence: float) -> list[dict[str, float]]:
    """For each silence: ms from the last applied command's receipt to the timeout decision and to zero twist
    (NaN where the silence ended first). A silence that began while the robot was not moving (a fault had
    stopped it already) has nothing to stop and is left out."""
    stops = []
    for t_silent in silences:
        # The last state before the silence names the last command the edge received before it.
        before = [s for t, s in seen.robot if t <= t_silent]
        if not before or not any(before[-1].commanded):
            continue
        t_end = t_silent + silence * 1e9
        robot = [s for t, s in seen.robot if t_silent < t <= t_end]
        safety = [s for t, s in seen.safety if t_silent < t <= t_end]
        zero = next((s for s in robot if not any(s.commanded)), None)
        last_recv = max((s.cmd_recv_t for s in robot if zero is None or s.t <= zero.t), default=before[-1].cmd_recv_t)
        decided = next((s for s in safety if s.status == Status.COMMAND_TIMEOUT and s.t >= last_recv), None)
        stops.append({
            "decision_ms": (decided.t - last_recv) / 1e6 if decided is not None else float("nan"),
            "zero_twist_ms": (zero.t - last_recv) / 1e6 if zero is not None else float("nan"),
        })
    return stops


def release_stops(seen: Seen, releases: list[int]) -> list[float]:
    """ms from each released command's send time to the first state/robot with a zero commanded twist."""
    out = []
    for t_sent in releases:
        zero = next((s for t, s in seen.robot if s.t >= t_sent and not any(s.commanded)), None)
        out.append((zero.t - t_sent) / 1e6 if zero is not None else float("nan"))
    return out


def episodes(flags: list[bool]) -> int:
    """How many times a condition started (False → True) in a sequence of observations."""
    return sum(1 for prev, cur in zip([False, *flags], flags, strict=False) if cur and not prev)


def faults(seen: Seen) -> tuple[list[int], list[str]]:
    """The wall times at which each fault episode was first seen, and the reasons."""
    last_robot: RobotState | None = None
    last_safety: SafetyStatus | None = None
    events = sorted([(t, "r", s) for t, s in seen.robot] + [(t, "s", s) for t, s in seen.safety], key=lambda e: e[0])
    reasons: list[str] = []
    starts: list[int] = []
    at_fault = False
    for t, kind, msg in events:
        if kind == "r":
            last_robot = msg
        else:
            last_safety = msg
        why = driver_fault(last_robot, last_safety)
        if why and not at_fault:
            starts.append(t)
        at_fault = bool(why)
        if why:
            reasons.append(why)
    return starts, sorted(set(reasons))[:10]


def incidents(starts: list[int], within_s: float = RECOVERY_S) -> list[int]:
    """The first of each run of fault episodes that began within ``within_s`` of the one before: a driver fault
    takes the UR driver through a reconnect, whose steps can show as further short episodes."""
    return [t for i, t in enumerate(starts) if i == 0 or t - starts[i - 1] > within_s * 1e9]


def arm(sock: Path) -> None:
    """The local confirmation a real arm needs (what ``iorthand arm`` does)."""
    wait(sock.exists, 30.0, "the edge's local socket")
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
        conn.settimeout(5.0)
        conn.connect(str(sock))
        conn.sendall(b"arm\n")
        answer = conn.recv(256).decode(errors="replace").strip()
    if answer.startswith("error"):
        raise RuntimeError(f"arming refused: {answer}")


def run_robot(kind: str, workdir: Path, duration: float, silence: float, hogs: int,
              emulator_hz: float) -> dict[str, Any]:
    robot_id, base = ROBOTS[kind]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    emu: EmulatorProcess | None = None
    emulator_priority = ""
    emulator_stops: list[str] = []
    with Group(workdir) as group:
        try:
            start_router(group, endpoint)
            overrides: dict[str, Any] = {"safety": {"auto_arm": True}}
            if kind == "ur":
                emu = EmulatorProcess(frequency=emulator_hz).wait_ready()
                emulator_priority = emu.raise_priority()  # a controller is a computer of its own
                overrides = {"robot": {"host": emu.host}, "safety": {"auto_arm": False},
                             "local_socket": str(workdir / "edge.sock")}
            cfg_path = edge_config(CONFIGS / base, workdir / "edge.yaml", endpoint, overrides)
            cfg = load(cfg_path, EdgeConfig)
            start_edge(group, cfg_path)
            if kind == "ur":
                arm(workdir / "edge.sock")
            watcher = Watcher(endpoint, robot_id)
            op = operator(endpoint, robot_id, "alice")
            try:
                time.sleep(2.0)  # the first commands and the sender's schedule settle before the hogs start
                group.start("stress-ng", ["stress-ng", "--cpu", str(hogs), "--timeout", f"{duration + 10:.0f}s"])
                sampler = group.start("steal", python_argv(steal.__name__, "--seconds", f"{duration + 10:.0f}"))
                time.sleep(1.0)
                t0 = time.time_ns()
                releases, silences = teleoperate(op, duration, silence)
                t1 = time.time_ns()
                owner_at_end = op.owner
                sampler.signal(signal.SIGTERM)
                sampler.wait(10.0)
                stolen = json.loads(sampler.output().strip().splitlines()[-1])
            finally:
                close_operator(op)
                watcher.close()
            seen = watcher.snapshot()
        finally:
            if emu is not None:
                # What the controller said about every program stop (the RTDE watchdog names its gap): which
                # side went silent, when a fault shows.
                with contextlib.suppress(Exception):
                    emulator_stops = [e for e in emu.status()["events"] if "watchdog" in e.lower() or "stop" in e]
                emu.stop()
    seen = Seen([(t, s) for t, s in seen.robot if t0 <= t <= t1 + 1e9],
                [(t, s) for t, s in seen.safety if t0 <= t <= t1 + 1e9])
    echoes = [e for e in op.echoes if t0 <= e.sent_ns <= t1]
    period_ms = 1000.0 / cfg.robot.control_rate_hz
    bound_ms = 1000.0 * cfg.safety.command_timeout + period_ms
    stops = timeout_stops(seen, silences, silence)
    released = release_stops(seen, releases)
    fault_starts, fault_reasons = faults(seen)
    found = [steal.Burst(**b) for b in stolen["bursts"] if t0 <= b["t_ns"] <= t1 + 1e9]
    first = incidents(fault_starts)
    after_steal = [t for t in first if steal.explained(t, found)]
    decision = [s["decision_ms"] for s in stops]
    zero = [s["zero_twist_ms"] for s in stops]
    return {
        "robot": kind,
        "edge_config": f"configs/{base}",
        "emulator_priority": emulator_priority,
        "emulator_stop_events": emulator_stops,
        "command_timeout_ms": 1000.0 * cfg.safety.command_timeout,
        "control_period_ms": period_ms,
        "stop_bound_ms": bound_ms,
        "false_driver_faults": len(fault_starts),
        "false_driver_fault_incidents": len(first),
        "incidents_after_vcpu_steal": len(after_steal),
        "fault_reasons": fault_reasons,
        "fault_times_s": [round((t - t0) / 1e9, 3) for t in fault_starts],
        "vcpu_steal_ms_per_cpu": stolen["steal_ms_per_cpu"],
        "vcpu_steal_bursts": [{"t_s": round((b.t_ns - t0) / 1e9, 3), "cpu": b.cpu, "ms": b.ms} for b in found],
        "lease_expiries": episodes([lease_lost(s) for _, s in seen.safety]),
        "not_owner_echoes": sum(e.status == Status.NOT_OWNER for e in echoes),
        "owner_at_end": owner_at_end,
        "silences": len(silences),
        "timeout_stops": len(stops),
        "timeout_stop_decision_ms": summary([v for v in decision if v == v]),
        "timeout_stop_zero_twist_ms": summary([v for v in zero if v == v]),
        "timeout_stops_over_bound": sum(not v <= bound_ms for v in zero),
        "timeout_stops_raw": stops,
        "release_stops": len(released),
        "release_stop_ms": summary([v for v in released if v == v]),
        "release_stops_over_bound": sum(not v <= bound_ms for v in released),
        "command_applied_ms": summary([e.rtt_ms for e in echoes if e.accepted]),
        "commands_sent": len(echoes),
        "echo_status": dict(Counter(str(e.status) for e in echoes)),
        "state_robot_messages": len(seen.robot),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="s of teleoperation under the hogs, per robot")
    ap.add_argument("--robots", nargs="+", choices=sorted(ROBOTS), default=["sim", "ur"])
    ap.add_argument("--hogs", type=int, default=2, help="stress-ng --cpu N")
    ap.add_argument("--silence", type=float, default=0.6, help="s the operator goes silent in each cycle")
    ap.add_argument("--emulator-hz", type=float, default=500.0, help="the UR emulator's controller rate (e-Series: 500)")
    ap.add_argument("--out", type=Path, default=RESULTS / "cpu_hogs.json")
    args = ap.parse_args()
    if shutil.which("stress-ng") is None:
        raise Unavailable("stress-ng is not installed: apt-get install -y stress-ng")
    workdir = Path(tempfile.mkdtemp(prefix="iorthand-cpu-hogs-"))
    info = machine()
    results = {}
    for kind in args.robots:
        results[kind] = run_robot(kind, workdir / kind, args.duration, args.silence, args.hogs, args.emulator_hz)
        results[kind]["load_average_after"] = list(os.getloadavg())
    write_json(args.out, {
        "benchmark": "cpu_hogs",
        "config": {"duration_s": args.duration, "hogs": f"stress-ng --cpu {args.hogs}", "silence_s": args.silence,
                   "emulator_hz": args.emulator_hz, "speed_m_s": SPEED, "workdir": str(workdir)},
        "results": results,
        "machine": info,
    })
    for kind, r in results.items():
        z, d, rel, c = (r["timeout_stop_zero_twist_ms"], r["timeout_stop_decision_ms"], r["release_stop_ms"],
                        r["command_applied_ms"])
        print(f"{kind}: false driver faults {r['false_driver_faults']} in {r['false_driver_fault_incidents']} incidents "
              f"({r['incidents_after_vcpu_steal']} after a vCPU steal; bursts "
              f"{[round(b['ms']) for b in r['vcpu_steal_bursts']]} ms), "
              f"lease expiries {r['lease_expiries']} "
              f"(not_owner {r['not_owner_echoes']}); {r['timeout_stops']} timeout stops: decision max {d['max']:.1f} ms, "
              f"zero twist max {z['max']:.1f} ms (bound {r['stop_bound_ms']:.1f}, over {r['timeout_stops_over_bound']}); "
              f"{r['release_stops']} release stops max {rel['max']:.1f} ms; command→applied p50 {c['p50']:.2f} "
              f"p99 {c['p99']:.2f} ms (n={c['count']})")
    print(f"→ {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
