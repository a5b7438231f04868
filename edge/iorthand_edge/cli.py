"""``iorthand edge``: run the edge agent from a YAML configuration."""

from __future__ import annotations

import argparse
import socket
import sys
from pathlib import Path

from iorthand.memory import Trimmer
from iorthand_edge.agent import AgentAlreadyOnline, run
from iorthand_edge.config import load_edge_config


def _running_agent(path: Path) -> str:
    """What an edge agent already answering on the local socket ``path`` says of itself (its status line), or ""
    when none does: no file, or one left by an agent that was killed (nothing listens on it)."""
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
            conn.settimeout(5.0)
            conn.connect(str(path))
            # A whole exchange, as `iorthand edge-status` does: the agent's local thread answers every line it reads.
            conn.sendall(b"status\n")
            return conn.recv(4096).decode(errors="replace").strip() or "(no answer)"
    except (FileNotFoundError, ConnectionRefusedError):
        return ""
    except TimeoutError:
        return "it takes connections but did not answer within 5 s"


def _edge(args: argparse.Namespace) -> int:
    config = load_edge_config(args.config)
    if args.connect:
        config.zenoh.connect = list(args.connect)
    if config.local_socket is not None:
        # A second agent for the same robot (a manual run beside the service) took the first one's local socket
        # without a word (it unlinks the file), so that arming and disarming reached the newcomer, and both answered
        # the operators' control queries (each granted control, each refused the other's commands as forged).
        running = _running_agent(config.local_socket)
        if running:
            print(f"{args.config}: an edge agent is already running for robot {config.robot_id!r}: it answers on "
                  f"{config.local_socket} ({running}); stop it first (systemctl stop iorthand-edge)", file=sys.stderr)
            return 1
    # What a flood of input made the agent allocate goes back to the system once it is freed (iorthand.memory).
    trimmer = Trimmer()
    trimmer.start()
    try:
        run(config)
    except AgentAlreadyOnline as exc:
        print(f"{args.config}: {exc}", file=sys.stderr)
        return 1
    finally:
        trimmer.stop()
    return 0


def _local(args: argparse.Namespace) -> int:
    """Send one local command to a running agent through its Unix socket (needs the rights on that file)."""
    config = load_edge_config(args.config)
    if config.local_socket is None:
        print(f"{args.config}: local_socket is not set: this agent takes no local commands", file=sys.stderr)
        return 2
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
            conn.settimeout(5.0)
            conn.connect(str(config.local_socket))
            conn.sendall(args.local_command.encode() + b"\n")
            answer = conn.recv(4096).decode(errors="replace").strip()
    except OSError as exc:
        print(f"cannot reach the edge agent at {config.local_socket}: {exc} (is it running, are you allowed?)", file=sys.stderr)
        return 1
    print(answer)
    return 0 if not answer.startswith("error") else 1


def register(sub: argparse._SubParsersAction) -> None:
    for name, text in (("arm", "confirm arming on the robot side (local to the edge computer)"),
                       ("disarm", "disarm the robot (local)"), ("edge-status", "the agent's safety state (local)")):
        p = sub.add_parser(name, help=text)
        p.add_argument("--config", required=True, help="the edge YAML of the running agent (its local_socket)")
        p.set_defaults(func=_local, local_command={"edge-status": "status"}.get(name, name))

    p = sub.add_parser("edge", help="run the edge agent (robot driver and safety supervisor)")
    p.add_argument("--config", required=True, help="edge YAML, e.g. configs/edge-sim.yaml")
    p.add_argument("--connect", action="append", help="router endpoint, overrides the config (repeatable)")
    p.set_defaults(func=_edge)
