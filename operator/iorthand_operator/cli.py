"""``iorthand operator ...``: teleoperation from the command line.

``iorthand operator --robot R --config configs/operator.yaml`` (no action) opens the console; actions:
``script FILE.yaml`` (headless, JSON summary; what the demo runs), ``move``, ``stop``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from iorthand.config import ConfigError, cli_number, from_dict, load
from iorthand.transport import open_session
from iorthand_operator.client import ControlRefused, OperatorClient
from iorthand_operator.config import OperatorConfig
from iorthand_operator.scripted import move

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
    if getattr(args, "input", None):
        config.console.input = args.input
    if getattr(args, "keymap", None):
        config.console.keymap = args.keymap
    if getattr(args, "gamepad", None):
        config.console.gamepad = Path(args.gamepad)
    return config


def connect(config: OperatorConfig) -> OperatorClient:
    session = open_session(config.zenoh)
    return OperatorClient(
        session, config.robot, config.operator_id, rate_hz=config.rate_hz, release_tail=config.release_tail,
        link_window=config.console.link_window, bind_keys=config.bind_operator_keys,
        sender_config=config.zenoh,  # the sender in its own process, out of reach of the UI's GIL
    )


def json_safe(value: Any) -> Any:
    """NaN/inf → null, so the printed summary is strict JSON."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def _configs_dir(args: argparse.Namespace) -> Path:
    return Path(args.config).resolve().parent if getattr(args, "config", None) else Path.cwd() / "configs"


def make_device(config: OperatorConfig, configs_dir: Path):
    """The input device the console settings ask for (a bad keymap or gamepad file fails here, at start)."""
    from iorthand_operator.inputs.keyboard import KeyboardInput, load_keymap

    settings = config.console
    if settings.input == "gamepad":
        from iorthand_operator.inputs.gamepad import GamepadInput
        from iorthand_operator.inputs.mapping import GamepadConfig

        assert settings.gamepad is not None  # ConsoleSettings.check
        return GamepadInput(load(settings.gamepad, GamepadConfig))
    return KeyboardInput(load_keymap(settings.keymap, configs_dir))


def _console(args: argparse.Namespace) -> int:
    config = operator_config(args)
    try:
        device = make_device(config, _configs_dir(args))
    except FileNotFoundError as exc:
        raise ConfigError("console", "keymap", str(exc)) from None
    from iorthand_operator.console.app import OperatorConsole
    from iorthand_operator.console.controller import ConsoleController

    client = connect(config)
    controller = ConsoleController(client, device, config.console, router=", ".join(config.zenoh.connect))
    try:
        client.start()  # the sender before control: the lease starts when the first command can go
        try:
            client.acquire(config.profile)
        except ControlRefused as exc:
            # Stay up and show why (the log line is in the console); "e" asks again.
            log.warning("control refused: %s", exc)
        controller.start()
        return OperatorConsole(controller).run() or 0
    finally:
        controller.stop()
        client.close()
        client.session.close()


def _script(args: argparse.Namespace) -> int:
    from iorthand_operator.script import Script, run_script

    script = load(args.file, Script)
    if script.profile and not getattr(args, "profile", None):
        args.profile = script.profile
    return _run_with_control(args, lambda c: run_script(c, script))


def _run_with_control(args: argparse.Namespace, action) -> int:
    config = operator_config(args)
    client = connect(config)
    try:
        try:
            client.wait_for_state(timeout=10.0)
        except TimeoutError as exc:
            # Connected to the router, but no robot answers: say where to look rather than a traceback.
            print(f"iorthand operator: {exc}: check that the edge agent of {config.robot!r} runs and is connected to "
                  f"the router ({', '.join(config.zenoh.connect) or 'no endpoint'}), that robot is the edge's robot_id, "
                  f"and that the router grants operator-{config.operator_id} that robot", file=sys.stderr)
            return 4
        # The sender first (its process can take seconds to start on a loaded machine), then control: the lease
        # starts when the first command is ready to go, never before.
        client.start()
        try:
            client.acquire(config.profile)
        except ControlRefused as exc:
            print(f"iorthand operator: control refused: {exc}", file=sys.stderr)
            return 3
        result = action(client)
        print(json.dumps(json_safe(result), indent=2))
        return 0
    finally:
        client.close()
        client.session.close()


def move_velocity(vx: float, vy: float, vz: float) -> np.ndarray:
    """The linear velocity of ``operator move``; all zero is a mistake (it would take control, hold it for
    --seconds and move nothing), refused before anything connects."""
    if not (vx or vy or vz):
        raise ConfigError("command line", "--vx/--vy/--vz", "all zero: the move would move nothing; "
                          "give at least one velocity in m/s (e.g. --vx 0.02)")
    return np.array([vx, vy, vz])


def _move(args: argparse.Namespace) -> int:
    linear = move_velocity(args.vx, args.vy, args.vz)
    return _run_with_control(args, lambda c: move(c, linear, np.zeros(3), args.seconds, args.patience))


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


def _common(p: argparse.ArgumentParser, suppress: bool = True) -> None:
    # Actions take the same options as ``iorthand operator`` itself; SUPPRESS keeps an action's unset option
    # from overwriting one given before the action name.
    d: dict[str, Any] = {"default": argparse.SUPPRESS} if suppress else {}
    p.add_argument("--config", help="operator YAML (configs/operator.yaml)", **d)
    p.add_argument("--robot", help="robot id", **d)
    p.add_argument("--operator-id", help="this operator's id", **d)
    p.add_argument("--connect", action="append", help="router endpoint, e.g. tcp/127.0.0.1:7447", **d)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "operator", help="teleoperate a robot (no action: the console)",
        description="Without an action: the operator console (terminal UI, keyboard or gamepad).",
    )
    _common(p, suppress=False)
    p.add_argument("--profile", help="speed profile to ask for (local, remote)")
    p.add_argument("--input", choices=["keyboard", "gamepad"], help="input device (default: from the config)")
    p.add_argument("--keymap", help="keymap name (configs/keymap-<name>.yaml) or file")
    p.add_argument("--gamepad", help="gamepad mapping YAML (configs/gamepad-*.yaml)")
    p.set_defaults(func=_console)
    osub = p.add_subparsers(dest="action", metavar="ACTION", required=False)

    sc = osub.add_parser("script", help="play a YAML script of timed twists and actions; prints a JSON summary")
    _common(sc)
    sc.add_argument("file", help="script YAML")
    sc.add_argument("--profile", help="speed profile to ask for (overrides the script's)", default=argparse.SUPPRESS)
    sc.set_defaults(func=_script)

    m = osub.add_parser("move", help="move the tool at a constant velocity, then print where it went")
    _common(m)
    m.add_argument("--vx", type=cli_number(float, lo=-1.0, hi=1.0), default=0.0, help="m/s")
    m.add_argument("--vy", type=cli_number(float, lo=-1.0, hi=1.0), default=0.0, help="m/s")
    m.add_argument("--vz", type=cli_number(float, lo=-1.0, hi=1.0), default=0.0, help="m/s")
    m.add_argument("--seconds", type=cli_number(float, lo=0.1, hi=600.0), default=1.0,
                   help="s of motion (a halt on the way is recovered from and does not count)")
    m.add_argument("--patience", type=cli_number(float, lo=0.0, hi=3600.0), default=30.0,
                   help="s the move may take beyond --seconds to recover from halts (a lost lease, a dead link)")
    m.add_argument("--profile", help="speed profile to ask for (local, remote)", default=argparse.SUPPRESS)
    m.set_defaults(func=_move)

    s = osub.add_parser("stop", help="send an emergency stop")
    _common(s)
    s.add_argument("--reason", default="operator e-stop from the command line")
    s.set_defaults(func=_stop)
