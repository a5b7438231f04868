"""The ``iorthand`` command. Core subcommands live here; each role package adds its own through the
``iorthand.commands`` entry-point group (a function ``register(subparsers)``), so the core imports no role."""

from __future__ import annotations

import argparse
import logging
import sys
from importlib.metadata import entry_points

import zenoh

from iorthand.config import ConfigError
from iorthand.process import name_thread
from iorthand.security.certs import CertError
from iorthand.transport import ConnectError

# What a user's mistake or an absent peer raises, when the message says it all: one line, no traceback
# (--log-level debug logs the traceback too).
USER_ERRORS = (ConnectError, CertError, FileNotFoundError, FileExistsError, IsADirectoryError, NotADirectoryError,
               PermissionError, zenoh.ZError)


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
    # ps and top show each service by its command (iorthand-router, iorthand-edge, iorthand-twin, ...), not as
    # "python" like every other Python program; threads started from here on inherit the name unless they name
    # themselves (those that the imports started stay "python").
    name_thread(f"iorthand-{args.command}")
    try:
        return int(args.func(args) or 0)
    except ConfigError as exc:
        print(f"iorthand: configuration error: {exc}", file=sys.stderr)
        return 2
    except USER_ERRORS as exc:
        logging.getLogger("iorthand").debug("%s failed", args.command, exc_info=True)
        print(f"iorthand {args.command}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
