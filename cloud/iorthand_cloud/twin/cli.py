"""``iorthand twin``: run the digital twin from a YAML configuration."""

from __future__ import annotations

import argparse
from pathlib import Path

from iorthand.config import ConfigError, cli_number


def _twin(args: argparse.Namespace) -> int:
    from .config import load_twin_config
    from .service import TwinService

    config = load_twin_config(args.config)
    if args.connect:
        config.zenoh.connect = list(args.connect)
    if args.no_serve:
        config.viewer.serve = False
    if args.bind:
        config.viewer.bind = args.bind
    if args.web_port is not None:
        config.viewer.web_port = args.web_port
    if args.grpc_port is not None:
        config.viewer.grpc_port = args.grpc_port
    try:
        config.viewer.check()  # the overrides too (a --bind 0.0.0.0)
    except ValueError as exc:
        raise ConfigError("the command line", "viewer", str(exc)) from None
    return TwinService(config, save=Path(args.save) if args.save else None,
                       log_dir=Path(args.log_dir) if args.log_dir else None).run_forever()


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("twin", help="run the digital twin (latest state, snapshots, previews, rerun web viewer)")
    p.add_argument("--config", required=True, help="twin YAML, e.g. configs/twin.yaml")
    p.add_argument("--connect", action="append", help="router endpoint, overrides the config (repeatable)")
    p.add_argument("--save", help="also write the rerun data to this .rrd file")
    p.add_argument("--no-serve", action="store_true", help="do not serve the web viewer (with --save: file only)")
    p.add_argument("--bind", help="address of the viewer's ports, overrides viewer.bind")
    p.add_argument("--web-port", type=cli_number(int, lo=1, hi=65535), help="overrides viewer.web_port")
    p.add_argument("--grpc-port", type=cli_number(int, lo=1, hi=65535), help="overrides viewer.grpc_port")
    p.add_argument("--log-dir", help="folder for the rerun relay's log")
    p.set_defaults(func=_twin)
