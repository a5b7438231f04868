"""``iorthand edge``: run the edge agent from a YAML configuration."""

from __future__ import annotations

import argparse

from iorthand_edge.agent import run
from iorthand_edge.config import load_edge_config


def _edge(args: argparse.Namespace) -> int:
    config = load_edge_config(args.config)
    if args.connect:
        config.zenoh.connect = list(args.connect)
    run(config)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("edge", help="run the edge agent (robot driver and safety supervisor)")
    p.add_argument("--config", required=True, help="edge YAML, e.g. configs/edge-sim.yaml")
    p.add_argument("--connect", action="append", help="router endpoint, overrides the config (repeatable)")
    p.set_defaults(func=_edge)
