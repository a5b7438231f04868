"""Command line: run the emulator (``main(argv)``), or inject a fault into a running one (``--inject``)."""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import sys
import threading
from typing import Any

from iorthand.config import ConfigError, cli_number, from_dict, read_yaml, to_dict
from iorthand_edge.force.contact import PhantomConfig

from .arm import MAX_JOINT_SPEED
from .controller import ControllerConfig
from .emulator import DEFAULT_CONTROL_PORT, EmulatorConfig, UREmulator
from .faults import OPS, ControlClient


def _version(text: str) -> tuple[int, int, int, int]:
    parts = [int(x) for x in text.split(".")]
    if len(parts) < 2 or len(parts) > 4:
        raise argparse.ArgumentTypeError("expected MAJOR.MINOR[.BUGFIX[.BUILD]]")
    parts += [0] * (4 - len(parts))
    return parts[0], parts[1], parts[2], parts[3]


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="ur-emulator",
        description="UR e-Series controller emulator for ur_rtde (RTDE, dashboard, script ports) with fault "
                    "injection. ur_rtde 1.6.5 hard-codes its ports: run several emulators on different "
                    "loopback addresses (127.0.0.2, 127.0.0.3, ...).",
    )
    ap.add_argument("--host", default="127.0.0.1", help="address to bind (default %(default)s)")
    ap.add_argument("--rtde-port", type=cli_number(int, lo=1, hi=65535), default=30004)
    ap.add_argument("--dashboard-port", type=cli_number(int, lo=1, hi=65535), default=29999)
    ap.add_argument("--script-ports", type=int, nargs="*", default=[30002, 30003],
                    help="ports accepting URScript (ur_rtde uses 30003)")
    ap.add_argument("--control-port", type=int, default=DEFAULT_CONTROL_PORT,
                    help="fault-injection JSON-lines port; negative disables (default %(default)s)")
    ap.add_argument("--frequency", type=cli_number(float, lo=1.0, hi=2000.0), default=500.0, help="controller loop rate in Hz (e-Series: 500)")
    ap.add_argument("--version", type=_version, default=(5, 15, 2, 0), dest="ur_version",
                    help="reported PolyScope/URControl version (default 5.15.2.0)")
    ap.add_argument("--unlock-delay", type=cli_number(float, lo=0.0), default=5.0,
                    help="seconds after a protective stop during which unlocking is refused (PolyScope: 5)")
    ap.add_argument("--shared-inputs", action="store_true",
                    help="let several RTDE clients claim the same input registers (a real controller refuses)")
    ap.add_argument("--arm", choices=sorted(MAX_JOINT_SPEED), default="ur3e",
                    help="the arm's kinematics, joint speeds and limits (default %(default)s)")
    ap.add_argument("--joint-limits-deg", type=float, nargs=12, metavar="DEG",
                    help="min max of each joint, base first (default: the arm's, ±360°, UR3e wrist 3 unlimited; "
                         "inf for none)")
    ap.add_argument("--phantom", metavar="FILE",
                    help="YAML phantom for the F/T sensor and force mode: a PhantomConfig, or a file with a "
                         "phantom: section (configs/edge-sim.yaml); also for --inject set_phantom")
    ap.add_argument("--inject", choices=OPS, metavar="OP",
                    help=f"send OP to a running emulator at --host/--control-port and exit; one of {', '.join(OPS)}")
    ap.add_argument("--duration", type=float, default=None, help="for --inject drop_link")
    ap.add_argument("--mode", default="stale", choices=("stale", "silent"), help="for --inject freeze")
    ap.add_argument("--wrench", type=float, nargs=6, metavar="F", help="for --inject set_force (N, N*m)")
    ap.add_argument("--pose", type=float, nargs=6, metavar="P", help="for --inject set_pose (m, rad)")
    ap.add_argument("--joints", type=float, nargs=6, metavar="Q", help="for --inject set_joints (rad)")
    ap.add_argument("-v", "--verbose", action="store_true")
    return ap


def load_phantom(path: str) -> PhantomConfig:
    """A PhantomConfig from a YAML file: the file itself, or its ``phantom:`` section."""
    data = read_yaml(path)
    if isinstance(data, dict) and "phantom" in data:
        data = data["phantom"]
    return from_dict(data, PhantomConfig, source=path)


def _inject(args: argparse.Namespace) -> int:
    extra: dict[str, object] = {}
    if args.inject == "drop_link" and args.duration is not None:
        extra["duration"] = args.duration
    elif args.inject == "freeze":
        extra["mode"] = args.mode
    elif args.inject == "set_force":
        if args.wrench is None:
            print("--inject set_force needs --wrench FX FY FZ TX TY TZ", file=sys.stderr)
            return 2
        extra["wrench"] = args.wrench
    elif args.inject == "set_pose":
        if args.pose is None:
            print("--inject set_pose needs --pose X Y Z RX RY RZ", file=sys.stderr)
            return 2
        extra["pose"] = args.pose
    elif args.inject == "set_joints":
        if args.joints is None:
            print("--inject set_joints needs --joints Q1 Q2 Q3 Q4 Q5 Q6", file=sys.stderr)
            return 2
        extra["q"] = args.joints
    elif args.inject == "set_phantom":  # without --phantom: remove it
        try:
            extra["phantom"] = to_dict(load_phantom(args.phantom)) if args.phantom else None
        except ConfigError as exc:
            print(f"ur-emulator: {exc}", file=sys.stderr)
            return 2
    try:
        with ControlClient(args.host, args.control_port) as client:
            result = client.call(args.inject, **extra)
    except (OSError, RuntimeError) as exc:
        print(f"ur-emulator: {args.inject} failed: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(result, indent=2) if result is not None else "ok")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.inject:
        return _inject(args)
    limits: Any = None
    if args.joint_limits_deg is not None:
        d = [math.radians(v) for v in args.joint_limits_deg]
        limits = tuple((d[2 * i], d[2 * i + 1]) for i in range(6))
    try:
        phantom = load_phantom(args.phantom) if args.phantom else None
    except ConfigError as exc:
        print(f"ur-emulator: {exc}", file=sys.stderr)
        return 2
    config = EmulatorConfig(
        host=args.host,
        rtde_port=args.rtde_port,
        dashboard_port=args.dashboard_port,
        script_ports=tuple(args.script_ports),
        control_port=None if args.control_port < 0 else args.control_port,
        controller=ControllerConfig(frequency=args.frequency, version=args.ur_version,
                                    unlock_delay=args.unlock_delay, exclusive_inputs=not args.shared_inputs,
                                    robot_model=args.arm[:3].upper(), arm=args.arm, joint_limits=limits,
                                    phantom=phantom),
    )
    try:
        emu = UREmulator(config)
    except ValueError as exc:  # joint limits that exclude the arm's starting posture
        print(f"ur-emulator: {exc}", file=sys.stderr)
        return 2
    try:
        emu.start()
    except OSError as exc:
        print(f"ur-emulator: cannot bind {args.host}: {exc}", file=sys.stderr)
        return 1
    done = threading.Event()

    def _on_signal(signum: int, _frame: object) -> None:
        done.set()

    old = {s: signal.signal(s, _on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        for name, ep in emu.endpoints().items():
            print(f"{name:>10}: {ep}")
        # One machine-readable line last, for whoever started us as a subprocess.
        print("READY " + json.dumps(emu.endpoints()), flush=True)
        while not done.wait(0.5):
            pass
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        emu.stop()
        print("ur-emulator stopped", flush=True)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """``iorthand ur-emulator ...``: every argument goes to :func:`main` unparsed, so the subcommand and
    ``python -m iorthand_edge.ur_emulator`` accept exactly the same options (``--help`` included)."""
    p = sub.add_parser("ur-emulator", add_help=False, prefix_chars="\0",
                       help="UR controller emulator for ur_rtde, with fault injection (--help for options)")
    p.add_argument("args", nargs=argparse.REMAINDER)
    p.set_defaults(func=lambda args: main(args.args))
