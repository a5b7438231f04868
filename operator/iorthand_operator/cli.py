"""``iorthand operator ...``: teleoperation from the command line."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time

import numpy as np

from iorthand.config import from_dict, load
from iorthand.transport import open_session
from iorthand_operator.client import ControlRefused, OperatorClient
from iorthand_operator.config import OperatorConfig
from iorthand_operator.scripted import demo_motion, move

log = logging.getLogger("iorthand.operator")


def operator_config(args: argparse.Namespace) -> OperatorConfig:
    """The operator config from ``--config`` with command-line overrides."""
    if args.config:
        config = load(args.config, OperatorConfig)
    else:
        config = from_dict(
            {"operator_id": args.operator_id or f"op-{os.getpid()}", "robot": args.robot or "sim1"},
            OperatorConfig,
            source="<command line>",
        )
    if args.robot:
        config.robot = args.robot
    if args.operator_id:
        config.operator_id = args.operator_id
    if args.connect:
        config.zenoh.connect = list(args.connect)
    if getattr(args, "profile", None):
        config.profile = args.profile
    return config


def connect(config: OperatorConfig) -> OperatorClient:
    session = open_session(config.zenoh)
    return OperatorClient(session, config.robot, config.operator_id, rate_hz=config.rate_hz, release_tail=config.release_tail)


def _run_with_control(args: argparse.Namespace, action) -> int:  # noqa: ANN001
    config = operator_config(args)
    client = connect(config)
    try:
        client.wait_for_state(timeout=10.0)
        try:
            client.acquire(config.profile)
        except ControlRefused as exc:
            print(f"iorthand operator: control refused: {exc}", file=sys.stderr)
            return 3
        client.start()
        result = action(client)
        print(json.dumps(result, indent=2))
        return 0
    finally:
        client.close()
        client.session.close()


def _move(args: argparse.Namespace) -> int:
    linear = np.array([args.vx, args.vy, args.vz])
    return _run_with_control(args, lambda c: move(c, linear, np.zeros(3), args.seconds))


def _demo_script(args: argparse.Namespace) -> int:
    return _run_with_control(args, demo_motion)


def _stop(args: argparse.Namespace) -> int:
    config = operator_config(args)
    client = connect(config)
    try:
        client.emergency_stop(args.reason)
        time.sleep(0.2)  # let the put leave before the session closes
        print(f"stop sent to {config.robot}: {args.reason}")
        return 0
    finally:
        client.close()
        client.session.close()


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", help="operator YAML (configs/operator.yaml)")
    p.add_argument("--robot", help="robot id")
    p.add_argument("--operator-id", help="this operator's id")
    p.add_argument("--connect", action="append", help="router endpoint, e.g. tcp/127.0.0.1:7447")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("operator", help="teleoperate a robot")
    osub = p.add_subparsers(dest="action", metavar="ACTION", required=True)

    m = osub.add_parser("move", help="move the tool at a constant velocity, then print where it went")
    _common(m)
    m.add_argument("--vx", type=float, default=0.0, help="m/s")
    m.add_argument("--vy", type=float, default=0.0, help="m/s")
    m.add_argument("--vz", type=float, default=0.0, help="m/s")
    m.add_argument("--seconds", type=float, default=1.0)
    m.add_argument("--profile", help="speed profile to ask for (local, remote)")
    m.set_defaults(func=_move)

    d = osub.add_parser("demo-script", help="the demo's scripted motion; prints a JSON summary")
    _common(d)
    d.add_argument("--profile", help="speed profile to ask for (local, remote)")
    d.set_defaults(func=_demo_script)

    s = osub.add_parser("stop", help="send an emergency stop")
    _common(s)
    s.add_argument("--reason", default="operator e-stop from the command line")
    s.set_defaults(func=_stop)
