"""``iorthand certs``: the deployment's CA, role certificates, passwords and the router's configuration."""

from __future__ import annotations

import argparse
import json
import os
import secrets
import sys
from pathlib import Path

from iorthand.config import cli_number, load
from iorthand.security import acl, certs


def _init(args: argparse.Namespace) -> int:
    cert, key = certs.init_ca(Path(args.dir), days=args.days, force=args.force)
    print(f"CA: {cert} (key {key}, mode 0600 — keep it offline once the certificates are issued)")
    return 0


def _issue(args: argparse.Namespace) -> int:
    out = Path(args.out) if args.out else Path(args.dir)
    for name in args.name:
        certs.check_name(name)
    existing = [str(p) for name in args.name for p in (out / f"{name}.pem", out / f"{name}.key") if p.exists()]
    if existing and not args.force:
        # A new key replaces the one a deployed service uses: it fails at its next start until it gets the new pair.
        raise certs.CertError(
            f"{', '.join(existing)} already exist(s): nothing issued. To renew, add --force and install the new "
            "certificate and key wherever the old ones are deployed, then restart that service (docs/DEPLOY.md §1)")
    for name in args.name:
        issued = certs.issue(Path(args.dir), name, hosts=args.host or None, days=args.days, out_dir=out)
        print(f"{name}: {issued.certificate} {issued.private_key}")
    return 0


def _show(args: argparse.Namespace) -> int:
    info = certs.describe(Path(args.file))
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        for k, v in info.items():
            print(f"{k:>18}: {', '.join(map(str, v)) if isinstance(v, list) else v}")
    return 1 if info["expired"] else 0


def _password(args: argparse.Namespace) -> int:
    """Create a random password for ``name``: a 0600 file for the role, a line in the router's dictionary."""
    certs.check_name(args.name)  # the router's user names are the certificates' names
    out = Path(args.out or Path(args.dir) / f"{args.name}.password")
    users = Path(args.users_file or Path(args.dir) / "users.txt")
    lines = [ln for ln in (users.read_text().splitlines(keepends=True) if users.exists() else [])
             if not ln.startswith(f"{args.name}:")]
    existing = ([str(out)] if out.exists() else []) + (
        [f"{users} (a line for {args.name})"] if users.exists() and any(
            ln.startswith(f"{args.name}:") for ln in users.read_text().splitlines()) else [])
    if existing and not args.force:
        # The service that uses the old password would be refused by the router at its next start.
        raise certs.CertError(
            f"{args.name} has a password already: {', '.join(existing)}; nothing written. To change it, add --force, "
            f"then install the new {out.name} where {args.name} runs and the new {users.name} on the router's host, "
            "and restart both")
    password = secrets.token_urlsafe(24)
    fd = os.open(out, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(password + "\n")
    fd = os.open(users, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.writelines([*lines, acl.users_line(args.name, password)])
    print(f"{args.name}: password in {out}; router dictionary {users} updated")
    return 0


def _router_config(args: argparse.Namespace) -> int:
    dep = load(args.deployment, acl.Deployment)
    text = acl.to_json5(acl.router_config(dep))
    if args.out:
        Path(args.out).write_text(text)
        print(f"router configuration written to {args.out}", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("certs", help="certificates, passwords and the router's TLS/ACL configuration")
    cs = p.add_subparsers(dest="certs_command", metavar="ACTION", required=True)
    i = cs.add_parser("init", help="create the CA (ca.pem, ca.key)")
    i.add_argument("--dir", default="certs")
    i.add_argument("--days", type=cli_number(int, lo=1), default=certs.CA_DAYS)
    i.add_argument("--force", action="store_true", help="replace an existing CA")
    i.set_defaults(func=_init)
    s = cs.add_parser("issue", help="issue role certificates: router, twin, recorder, replay, edge-<robot>, operator-<name>, viewer-<name>")
    s.add_argument("name", nargs="+")
    s.add_argument("--dir", default="certs", help="where the CA is")
    s.add_argument("--out", help="where to write (default: --dir)")
    s.add_argument("--host", action="append", help="DNS name or IP in the certificate (the router's; repeatable)")
    s.add_argument("--days", type=cli_number(int, lo=1), default=certs.LEAF_DAYS)
    s.add_argument("--force", action="store_true", help="replace an existing certificate and key (renewal)")
    s.set_defaults(func=_issue)
    w = cs.add_parser("show", help="inspect a certificate (exit 1 if expired)")
    w.add_argument("file")
    w.add_argument("--json", action="store_true")
    w.set_defaults(func=_show)
    pw = cs.add_parser("password", help="random password for a role + the router's user dictionary")
    pw.add_argument("name")
    pw.add_argument("--dir", default="certs")
    pw.add_argument("--out", help="password file (default: <dir>/<name>.password)")
    pw.add_argument("--users-file", help="router dictionary (default: <dir>/users.txt)")
    pw.add_argument("--force", action="store_true", help="replace an existing password (and its dictionary line)")
    pw.set_defaults(func=_password)
    r = cs.add_parser("router-config", help="generate the router's JSON5 (TLS + mTLS + user/password + ACL)")
    r.add_argument("--deployment", required=True, help="deployment YAML (see deploy/deployment.example.yaml)")
    r.add_argument("--out", help="output file (default: stdout)")
    r.set_defaults(func=_router_config)
