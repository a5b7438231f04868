"""The ``iorthand`` command. Core subcommands live here; each role package adds its own through the
``iorthand.commands`` entry-point group (a function ``register(subparsers)``), so the core imports no role."""

from __future__ import annotations

import argparse
import logging
import sys
from importlib.metadata import entry_points

from iorthand.config import ConfigError


def _setup_logging(level: str) -> None:
    logging.basicConfig(level=getattr(logging, level.upper()), format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="iorthand", description="Safe robot teleoperation over Zenoh.")
    parser.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    from iorthand import check, demo, router
    from iorthand.security import cli as security_cli

    router.register(sub)
    demo.register(sub)
    security_cli.register(sub)
    check.register(sub)
    for ep in sorted(entry_points(group="iorthand.commands"), key=lambda e: e.name):
        try:
            ep.load()(sub)
        except (ImportError, AttributeError) as exc:
            # A role installed without its optional dependencies (or broken) must not take the others down.
            print(f"iorthand: the {ep.name!r} commands are unavailable: {exc}", file=sys.stderr)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.log_level)
    try:
        return int(args.func(args) or 0)
    except ConfigError as exc:
        print(f"iorthand: configuration error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
