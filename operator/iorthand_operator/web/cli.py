"""``iorthand web``: serve the console; ``iorthand web password NAME``: set a user's web password."""

from __future__ import annotations

import argparse
import getpass
import logging
import os
import secrets
import stat
import sys
import tempfile
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
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        old = _replace(path, users.format_users(current))
    except OSError as exc:
        why = " (run it as root, e.g. with sudo, as docs/DEPLOY.md does)" if isinstance(exc, PermissionError) else ""
        print(f"iorthand web password: cannot write {path}: {exc.strerror or exc}{why}; nothing written, the file "
              "is as it was", file=sys.stderr)
        return 2
    print(f"{args.name}: web password set in {path}" + (f": {password}" if args.generate else ""))
    hint = permission_hint(path, old, os.getuid())
    if hint:
        print(hint)
    return 0


def _replace(path: Path, text: str) -> os.stat_result | None:
    """Write ``path`` whole or not at all (a full disk or a kill used to leave it truncated: every user locked
    out), through a temporary file that takes the owner, group and mode of the file it replaces; a new file is
    0600. Returns the replaced file's status (None: it is new)."""
    try:
        old: os.stat_result | None = path.stat()
    except FileNotFoundError:
        old = None
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")  # (0600)
    try:
        with os.fdopen(fd, "w") as f:
            if old is not None:
                os.fchown(f.fileno(), old.st_uid, old.st_gid)  # (the service reads it through its group)
                os.fchmod(f.fileno(), stat.S_IMODE(old.st_mode))
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return old


def permission_hint(path: Path, old: os.stat_result | None, uid: int) -> str:
    """What to do about the users file's permissions after writing it: a new one is 0600 and its writer's, which
    the console's service user cannot read; an existing one keeps its owner, group and mode, but one every user
    may read is refused by ``iorthand check``."""
    if old is None:
        who = "root" if uid == 0 else "you"
        return (f"{path} is new: 0600, readable by {who} only. The console reads it as its service user: "
                f"`sudo chgrp iorthand {path} && sudo chmod 0640 {path}` (later runs keep its owner, group and mode)")
    if old.st_mode & stat.S_IROTH:
        return (f"warning: {path} is readable by every user (mode {stat.S_IMODE(old.st_mode):04o}, kept): "
                f"`sudo chmod o-rwx {path}` (`iorthand check` refuses it)")
    return ""


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
