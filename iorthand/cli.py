"""The ``iorthand`` command. Core subcommands live here; each role package adds its own through the
``iorthand.commands`` entry-point group (a function ``register(subparsers)``), so the core imports no role."""

from __future__ import annotations

import argparse
import difflib
import logging
import sys
from collections.abc import Sequence
from importlib.metadata import entry_points
from typing import NoReturn

import zenoh

from iorthand import logs
from iorthand.config import ConfigError
from iorthand.process import name_thread
from iorthand.security.certs import CertError
from iorthand.transport import ConnectError

# What a user's mistake or an absent peer raises, when the message says it all: one line, no traceback
# (--log-level debug logs the traceback too).
USER_ERRORS = (ConnectError, CertError, FileNotFoundError, FileExistsError, IsADirectoryError, NotADirectoryError,
               PermissionError, zenoh.ZError)


class CommandParser(argparse.ArgumentParser):
    """A parser that answers an argument it does not know itself, naming the (sub)command and the nearest option.

    argparse hands what a subcommand does not know up to the top parser, which printed the top-level usage and
    "unrecognized arguments" without saying of which subcommand: ``iorthand demo --veiw`` showed how to call
    ``iorthand``. Subcommands' parsers are of their parent's class (``add_subparsers`` makes them so), so every
    level of ``iorthand ... `` answers for its own arguments."""

    def parse_known_args(self, args: Sequence[str] | None = None,
                         namespace: argparse.Namespace | None = None) -> tuple[argparse.Namespace, list[str]]:
        parsed, extras = super().parse_known_args(args, namespace)
        if extras:
            self.unrecognized(extras)
        return parsed, extras

    def unrecognized(self, extras: list[str]) -> NoReturn:
        """Exit 2 with this command's usage and, for each unknown argument, what it is and the nearest option."""
        said = []
        for arg in extras:
            if len(arg) > 1 and arg[0] in self.prefix_chars:
                nearest = difflib.get_close_matches(arg.split("=", 1)[0], list(self._option_string_actions), n=1)
                said.append(f"option {arg}" + (f" (did you mean {nearest[0]}?)" if nearest else ""))
            else:
                said.append(f"argument {arg!r}")
        self.print_usage(sys.stderr)
        self.exit(2, f"{self.prog}: unrecognized {', '.join(said)}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = CommandParser(prog="iorthand", description="Safe robot teleoperation over Zenoh.")
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
    logs.setup(args.log_level)
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
