"""``iorthand demo``: the whole system on this machine, from one command.

Starts a Zenoh router, a simulated edge agent and a scripted operator as separate processes on 127.0.0.1 with
free ports, drives a short motion, prints a summary and exits 0. Ctrl-C (or SIGTERM) stops everything; each
child also dies with the demo (PR_SET_PDEATHSIG), so no process is left behind even if the demo is killed.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import yaml

from iorthand.transport import free_port

_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    with contextlib.suppress(OSError):  # not Linux: the Ctrl-C handling still stops the children
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


@dataclass
class Child:
    name: str
    argv: list[str]
    log_path: Path
    proc: subprocess.Popen[bytes] | None = None
    log: IO[bytes] | None = field(default=None, repr=False)

    def start(self) -> None:
        self.log = self.log_path.open("wb")
        self.proc = subprocess.Popen(
            self.argv, stdout=subprocess.PIPE if self.name == "operator" else self.log, stderr=self.log,
            preexec_fn=_die_with_parent, start_new_session=True,
        )

    def stop(self, timeout: float = 5.0) -> int | None:
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(2.0)
        if self.log:
            self.log.close()
        return self.proc.returncode


def iorthand_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "iorthand.cli", *args]


def demo_edge_config(robot: str, endpoint: str) -> dict:
    return {
        "robot_id": robot,
        "zenoh": {"mode": "client", "connect": [endpoint]},
        "robot": {"kind": "sim", "initial_pose": [0.30, 0.0, 0.20, 3.14159, 0.0, 0.0]},
        "safety": {"auto_arm": True, "profile": "local"},
        "phantom": {"surface_z": 0.15},  # below the demo's path: the sensor reads ~0 N, the supervisor is armed for contact
        "force": {"sensor": {"kind": "sim"}},
        "servos": {}, "torch": {},
        "video": {"camera": {"width": 320, "height": 240, "fps": 15}, "ultrasound": {"source": "ultrasound_sim", "width": 320, "height": 240, "fps": 10}},
    }


def wait_for_line(child: Child, text: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if child.proc is not None and child.proc.poll() is not None:
            raise RuntimeError(f"{child.name} exited with {child.proc.returncode}; see {child.log_path}")
        if text in child.log_path.read_text(errors="replace"):
            return
        time.sleep(0.05)
    raise RuntimeError(f"{child.name} did not report {text!r} within {timeout} s; see {child.log_path}")


def print_summary(result: dict, workdir: Path) -> None:
    rtt = result["command_to_applied_ms"]
    lines = [
        "",
        "iorthand demo — summary",
        f"  robot {result['robot']} (simulated), operator {result['operator']}, profile {result['profile']}",
        f"  path travelled          {result['path_mm']:.1f} mm over {len(result['legs'])} moves",
        f"  commands sent/applied/rejected  {result['commands_sent']} / {result['commands_applied']} / {result['commands_rejected']}",
        f"  command→applied latency p50 {rtt['p50']:.2f} ms, p99 {rtt['p99']:.2f} ms (through the router, echo)",
        f"  deadman stop (dead link) {result['deadman_stop_ms']:.0f} ms after the last command",
        f"  logs and configs in {workdir}",
    ]
    print("\n".join(lines), flush=True)


def run_demo(args: argparse.Namespace) -> int:
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="iorthand-demo-"))
    workdir.mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    edge_cfg = workdir / "edge.yaml"
    edge_cfg.write_text(yaml.safe_dump(demo_edge_config(args.robot, endpoint), sort_keys=False))
    children = [
        Child("router", iorthand_argv("router", "--listen", endpoint), workdir / "router.log"),
        Child("edge", iorthand_argv("edge", "--config", str(edge_cfg)), workdir / "edge.log"),
        Child(
            "operator",
            iorthand_argv("operator", "demo-script", "--robot", args.robot, "--operator-id", "demo-operator",
                          "--connect", endpoint, "--profile", "local"),
            workdir / "operator.log",
        ),
    ]
    stopping = False

    def on_signal(signum: int, _frame: object) -> None:
        nonlocal stopping
        stopping = True
        raise KeyboardInterrupt

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    print(f"iorthand demo: router on {endpoint}, logs in {workdir}", flush=True)
    code = 1
    try:
        children[0].start()
        wait_for_line(children[0], "router ready", 15.0)
        children[1].start()
        wait_for_line(children[1], "edge agent", 20.0)
        children[2].start()
        out, _ = children[2].proc.communicate(timeout=args.timeout)  # type: ignore[union-attr]
        (workdir / "summary.json").write_bytes(out)
        if children[2].proc.returncode != 0:  # type: ignore[union-attr]
            print(f"operator failed (exit {children[2].proc.returncode}); see {children[2].log_path}", file=sys.stderr)  # type: ignore[union-attr]
        else:
            print_summary(json.loads(out), workdir)
            code = 0
    except KeyboardInterrupt:
        print("\niorthand demo: interrupted, stopping every process", flush=True)
        code = 130
    except (RuntimeError, subprocess.TimeoutExpired) as exc:
        print(f"iorthand demo failed: {exc}", file=sys.stderr)
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not interrupt the clean-up
        for child in reversed(children):
            child.stop()
    return code if not stopping else 130


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run router + simulated edge + scripted operator and print a summary")
    p.add_argument("--robot", default="demo")
    p.add_argument("--workdir", help="where logs and configs go (default: a new temporary folder)")
    p.add_argument("--timeout", type=float, default=60.0, help="s the scripted operator may take")
    p.set_defaults(func=run_demo)

