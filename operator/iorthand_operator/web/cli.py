"""``iorthand web``: serve the console; ``iorthand web password NAME``: set a user's web password."""

from __future__ import annotations

import argparse
import getpass
import logging
import secrets
import sys
from pathlib import Path

from iorthand.config import ConfigError, load
from iorthand_operator.web import users
from iorthand_operator.web.config import WebConfig

log = logging.getLogger("iorthand.web")


def _serve(args: argparse.Namespace) -> int:
    from iorthand_operator.web.server import serve  # aiohttp only when serving

    config = load(args.config, WebConfig)
    if args.listen:
        config.listen = args.listen
    if args.connect:
        config.zenoh.connect = list(args.connect)
    try:
        serve(config)
    except (ConfigError, ValueError) as exc:
        print(f"iorthand web: {exc}", file=sys.stderr)
        return 2
    return 0


def _password(args: argparse.Namespace) -> int:
    """Set NAME's password in the users file: typed twice, read from a file, or generated and printed once."""
    path = Path(args.users_file)
    try:
        current = users.parse_users(path.read_text(), str(path)) if path.exists() else {}
    except ValueError as exc:
        print(f"iorthand web password: {exc}", file=sys.stderr)
        return 2
    if args.generate:
        password = secrets.token_urlsafe(12)
    elif args.password_file:
        password = Path(args.password_file).read_text().strip()
    elif not sys.stdin.isatty():
        # Piped or redirected: the first line is the password (nobody to ask twice).
        password = sys.stdin.readline().strip()
        if not password:
            print("iorthand web password: no password on stdin (not a terminal): pipe one line, or use "
                  "--password-file FILE or --generate; nothing written", file=sys.stderr)
            return 2
    else:
        try:
            password = getpass.getpass(f"new web password for {args.name}: ")
            again = getpass.getpass("again: ")
        except EOFError:
            print("iorthand web password: no password typed: use --password-file FILE or --generate; nothing written",
                  file=sys.stderr)
            return 2
        if password != again:
            print("iorthand web password: the two passwords differ; nothing written", file=sys.stderr)
            return 2
    if len(password) < 8:
        print("iorthand web password: at least 8 characters; nothing written", file=sys.stderr)
        return 2
    current[args.name] = users.hash_password(password)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.touch(mode=0o600, exist_ok=True)
    path.write_text(users.format_users(current))
    print(f"{args.name}: web password set in {path}" + (f": {password}" if args.generate else ""))
    return 0


def _name(text: str) -> str:
    from iorthand import keys

    try:
        return keys.check_operator_id(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("web", help="the operator console in a browser (a phone or a desktop), bridged to Zenoh")
    p.add_argument("--config", default="configs/web.yaml", help="web console YAML (configs/web.yaml)")
    p.add_argument("--listen", help="HOST:PORT (overrides the config)")
    p.add_argument("--connect", action="append", help="router endpoint (overrides the config; repeatable)")
    p.set_defaults(func=_serve)
    ws = p.add_subparsers(dest="web_action")
    pw = ws.add_parser("password", help="set a user's web password (scrypt hash in the users file)")
    pw.add_argument("name", type=_name, help="an operator or viewer of the deployment")
    pw.add_argument("--users-file", required=True, help="the web users file (the config's users_file)")
    src = pw.add_mutually_exclusive_group()
    src.add_argument("--password-file", help="read the password from this file instead of asking (without it and "
                     "without a terminal, the first line of stdin)")
    src.add_argument("--generate", action="store_true", help="generate a random password and print it once")
    pw.set_defaults(func=_password)
