"""Why did a connection fail? Turn Zenoh's "Unable to connect to any of [...]" into a message that names the
endpoint, the certificate and the likely cause.

Two sources of evidence:

1. :func:`precheck` — local and instant: the files exist and parse, the certificate chains to the CA, is
   valid now, and matches its private key; the endpoint scheme fits the TLS settings; the password file is
   readable.
2. :func:`probe` — Zenoh's own reason, which Python never sees (the exception only says "Unable to connect").
   A child process opens one session with the same configuration and Zenoh's Rust log at ``warn`` on its
   stderr, which we read and map to a cause with :func:`explain`. A child, not this process: the Rust
   logger is global and can be initialised once, it would write warnings to our stderr forever after, and
   the child's log cannot be mixed up with other sessions of this process. The settings (including the
   password) go through the child's stdin, never its command line.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import os
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.hazmat.primitives import serialization

from iorthand.security.certs import common_name
from iorthand.security.hosts import is_loopback

_ANSI = re.compile(r"\x1b\[[0-9;]*m")

# Zenoh/rustls log fragments → the likely cause, in order of specificity. The texts are those of
# eclipse-zenoh 1.10.2 (checked by tests/test_tls_*.py against real routers).
CAUSES: list[tuple[str, str]] = [
    (r"Connection refused", "nothing listens at the endpoint: the router is not running, or the address/port is wrong"),
    (r"(timed out|Timeout|No route to host|Network is unreachable)", "the router's host does not answer: network, firewall or address"),
    (r"invalid peer certificate: (UnknownIssuer|BadSignature)", "the router's certificate is not signed by our root CA (root_ca points to another CA, or the router uses another CA)"),
    (r"invalid peer certificate: Expired", "the router's certificate has expired"),
    (r"invalid peer certificate: NotValidForName", "the router's certificate does not name the host we dialled (add it with `iorthand certs issue router --host ...`, or dial the name it has)"),
    (r"invalid peer certificate: InvalidPurpose", "the certificate presented as the router's is not a server certificate (only the router's certificate is valid for that)"),
    (r"invalid peer certificate", "the router's certificate was refused"),
    (r"fatal alert: CertificateRequired", "the router requires a client certificate (mTLS) and we sent none: set tls.certificate, tls.private_key and tls.mtls: true"),
    (r"fatal alert: CertificateExpired", "the router refused our certificate: it has expired (issue a new one)"),
    (r"fatal alert: (DecryptError|BadCertificate|UnknownCA|UnsupportedCertificate)", "the router refused our certificate: it is not signed by the router's CA"),
    (r"fatal alert", "the router aborted the TLS handshake"),
    (r"(Cannot create a new TLS listener|No such file|Invalid private key|Invalid certificate|Permission denied)", "our certificate/key files cannot be used (missing, unreadable, or the key does not match the certificate)"),
    (r"close message \(reason GENERIC\) in response to an OpenSyn", "the router refused our credentials: wrong username or password (or the user is missing from the router's dictionary file)"),
    (r"early eof", "the router closed the connection at once: it probably expects TLS (use tls/ in the endpoint) or refused the link"),
    (r"(InvalidMessage|CorruptMessage|received corrupt message)", "protocol mismatch: TLS spoken to a plain TCP port, or the other way round"),
]


@dataclass
class Finding:
    level: str  # "error" or "warning"
    subject: str  # a file or a setting
    message: str
    # False for an error that must be fixed but cannot make a connection fail (a key every user can read): a
    # failed connection's diagnosis does not give it as the cause.
    blocks_connection: bool = True

    def __str__(self) -> str:
        return f"{self.level}: {self.subject}: {self.message}"


@dataclass
class Diagnosis:
    endpoints: list[str]
    certificate: str
    cause: str
    findings: list[Finding] = field(default_factory=list)
    log: str = ""

    def message(self) -> str:
        parts = [f"cannot connect to {', '.join(self.endpoints) or '(no endpoint)'}", f"certificate {self.certificate}"]
        parts.append(f"cause: {self.cause}")
        errors = [str(f) for f in self.findings if f.level == "error"]
        if errors:
            parts.append("; ".join(errors))
        return " — ".join(parts)


def is_encrypted(endpoint: str) -> bool:
    """A Zenoh endpoint whose link is TLS (``tls/``, ``quic/``)."""
    return endpoint.startswith(("tls/", "quic/"))


def clear_beyond_loopback(endpoints: list[str]) -> list[str]:
    """The endpoints that leave this machine unencrypted."""
    return [ep for ep in endpoints if not is_encrypted(ep) and not endpoint_is_local(ep)]


def endpoint_is_local(endpoint: str) -> bool:
    """Whether a Zenoh endpoint (``tcp/127.0.0.1:7447``, ``tls/[::1]:7447``, ``unixsock-stream/...``) stays on this
    machine. ``0.0.0.0``, ``[::]`` and any host name other than ``localhost`` do not."""
    protocol, _, rest = endpoint.partition("/")
    if protocol.startswith("unixsock"):
        return True
    address = re.split(r"[?#]", rest, maxsplit=1)[0]
    host = address.rpartition(":")[0] if ":" in address else address
    return is_loopback(host.strip("[]"))


MODE_ADVICE = "chmod 640 (group iorthand, the services' user) or 600"


def _open_to_all(path: Path, what: str) -> Finding | None:
    """An error when every user of the machine may read or write a secret (a key, a password)."""
    mode = Path(path).stat().st_mode & 0o777
    if not mode & 0o007:  # group-readable is fine: the service group
        return None
    how = " and ".join(w for w, bit in (("read", 0o004), ("write", 0o002), ("execute", 0o001)) if mode & bit)
    return Finding("error", str(path), f"{what} may be {how or 'used'} by every user of this machine (mode {oct(mode)}): "
                                       f"{MODE_ADVICE}", blocks_connection=False)


def file_problem(path: Path | None, what: str) -> Finding | None:
    """A finding when ``path`` does not exist or this user cannot read it, else None."""
    if path is None:
        return None
    p = Path(path)
    if not p.exists():
        return Finding("error", str(p), f"{what} does not exist")
    if not os.access(p, os.R_OK):
        return Finding("error", str(p), f"{what} is not readable by this user (uid {os.getuid()})")
    return None


def _load_cert(path: Path, what: str, out: list[Finding]) -> x509.Certificate | None:
    problem = file_problem(path, what)
    if problem:
        out.append(problem)
        return None
    try:
        return x509.load_pem_x509_certificate(Path(path).read_bytes())
    except ValueError as exc:
        out.append(Finding("error", str(path), f"{what} is not a PEM certificate ({exc})"))
        return None


def check_certificate_files(
    root_ca: Path | None, certificate: Path | None, private_key: Path | None, now: dt.datetime | None = None
) -> list[Finding]:
    """Pre-checks of one TLS identity. Returns findings; an empty list means all is well."""
    out: list[Finding] = []
    now = now or dt.datetime.now(dt.UTC)
    ca = _load_cert(root_ca, "root CA certificate", out) if root_ca else None
    cert = _load_cert(certificate, "certificate", out) if certificate else None
    if certificate and not private_key:
        out.append(Finding("error", str(certificate), "a certificate without its private_key"))
    if private_key and not certificate:
        out.append(Finding("error", str(private_key), "a private_key without its certificate"))
    key = None
    if private_key:
        problem = file_problem(private_key, "private key")
        if problem:
            out.append(problem)
        else:
            open_problem = _open_to_all(Path(private_key), "the private key")
            if open_problem:
                out.append(open_problem)
            try:
                key = serialization.load_pem_private_key(Path(private_key).read_bytes(), password=None)
            except (ValueError, TypeError) as exc:
                out.append(Finding("error", str(private_key), f"not an unencrypted PEM private key ({exc})"))
    for c, path, what in ((ca, root_ca, "root CA"), (cert, certificate, "certificate")):
        if c is None:
            continue
        if now < c.not_valid_before_utc:
            out.append(Finding("error", str(path), f"{what} is not valid before {c.not_valid_before_utc:%Y-%m-%d %H:%M} UTC (is this machine's clock right?)"))
        elif now > c.not_valid_after_utc:
            out.append(Finding("error", str(path), f"{what} expired on {c.not_valid_after_utc:%Y-%m-%d %H:%M} UTC"))
        elif (c.not_valid_after_utc - now).days < 30:
            out.append(Finding("warning", str(path), f"{what} expires in {(c.not_valid_after_utc - now).days} days"))
    if ca is not None and cert is not None:
        try:
            cert.verify_directly_issued_by(ca)
        except (ValueError, TypeError, Exception) as exc:  # InvalidSignature has no common base with ValueError
            out.append(Finding(
                "error", str(certificate),
                f"certificate {common_name(cert)!r} (issuer {cert.issuer.rfc4514_string()}) is not signed by the CA in "
                f"{root_ca} ({ca.subject.rfc4514_string()}): {type(exc).__name__}",
            ))
    if cert is not None and key is not None:
        pub = cert.public_key().public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)
        kpub = key.public_key().public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)
        if pub != kpub:
            out.append(Finding("error", str(private_key), f"private key does not belong to certificate {certificate}"))
    return out


def precheck(cfg: Any) -> list[Finding]:
    """Pre-checks of a :class:`iorthand.transport.ZenohConfig` (typed loosely: no import cycle)."""
    out: list[Finding] = []
    tls = cfg.tls
    endpoints = [*cfg.connect, *cfg.listen]
    uses_tls = any(is_encrypted(ep) for ep in endpoints)
    if tls is None and uses_tls:
        out.append(Finding("error", "zenoh.tls", "a tls/ endpoint needs zenoh.tls (root_ca, certificate, private_key)"))
    if tls is not None:
        clear_remote = clear_beyond_loopback(endpoints)
        if clear_remote:
            out.append(Finding("error", "zenoh.connect", (
                f"TLS is configured but {', '.join(clear_remote)} is not a tls/ endpoint and leaves this machine: "
                "commands, the password and the control key would cross the network in clear. Use tls/HOST:PORT")))
        elif not uses_tls and endpoints:
            out.append(Finding("warning", "zenoh.connect", f"TLS is configured but no endpoint uses it ({', '.join(endpoints)}): traffic is NOT encrypted"))
        if tls.root_ca is None:
            out.append(Finding("error", "zenoh.tls.root_ca", "missing: without it the router's certificate cannot be verified"))
        if cfg.mode == "client" and tls.mtls and not tls.certificate:
            out.append(Finding("error", "zenoh.tls.certificate", "mtls is on but no client certificate is set"))
        if cfg.mode == "client" and tls.certificate and not tls.mtls:
            out.append(Finding("warning", "zenoh.tls.mtls", "a certificate is set but mtls is off: Zenoh will not send it and an mTLS router refuses the link"))
        out += check_certificate_files(tls.root_ca, tls.certificate, tls.private_key)
    if cfg.username and cfg.password_file is None:
        out.append(Finding("error", "zenoh.password_file", f"username {cfg.username!r} needs a password_file"))
    if cfg.password_file is not None:
        problem = file_problem(cfg.password_file, "password file")
        if problem:
            out.append(problem)
        else:
            open_problem = _open_to_all(Path(cfg.password_file), "the password file")
            if open_problem:
                out.append(open_problem)
    return out


def explain(log_text: str) -> str | None:
    """The likely cause found in Zenoh's log, with the log line's own words, or None."""
    text = _ANSI.sub("", log_text)
    for pattern, cause in CAUSES:
        m = re.search(pattern, text)
        if m:
            line = next((ln for ln in text.splitlines() if m.group(0) in ln), m.group(0))
            detail = re.sub(r"\s+at /\S+:\d+\.?", "", line.split("Unable to connect to", 1)[-1]).strip()
            return f"{cause} [zenoh: {detail[:240]}]"
    return None


def probe(entries: dict[str, Any], timeout: float = 15.0) -> str:
    """Open one session in a child with Zenoh's log at warn; return its log (ANSI stripped)."""
    env = {k: v for k, v in os.environ.items() if k != "RUST_LOG"}
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "iorthand.security.diagnose"],
            input=json.dumps(entries), capture_output=True, text=True, timeout=timeout, env=env,
        )
    except subprocess.TimeoutExpired as exc:
        return f"probe timed out after {timeout} s\n{exc.stderr or ''}"
    return _ANSI.sub("", proc.stderr + proc.stdout)


def identity_of(cfg: Any) -> str:
    """The certificate a config presents, for messages: path and common name (or why there is none)."""
    tls = cfg.tls
    if tls is None:
        return "none (plain TCP, no TLS settings)"
    if not tls.certificate:
        return "none (TLS without a client certificate)"
    try:
        cn = common_name(x509.load_pem_x509_certificate(Path(tls.certificate).read_bytes()))
        return f"{tls.certificate} (CN={cn})"
    except (OSError, ValueError):
        return f"{tls.certificate} (unreadable)"


def diagnose(cfg: Any, entries: dict[str, Any] | None = None, run_probe: bool = True) -> Diagnosis:
    """Pre-checks, then (unless a pre-check already explains it) the child probe."""
    findings = precheck(cfg)
    errors = [f for f in findings if f.level == "error" and f.blocks_connection]
    log_text = ""
    cause = None
    if errors:
        cause = "configuration: " + str(errors[0])
    elif run_probe and entries is not None:
        log_text = probe(entries)
        if "CONNECTED" in log_text:
            cause = "the router answers now (it was probably not up yet, or the network was down)"
        else:
            cause = explain(log_text)
    if cause is None:
        cause = "unknown (no cause in Zenoh's log; run with RUST_LOG=debug)" if run_probe else "not probed"
    return Diagnosis(list(cfg.connect), identity_of(cfg), cause, findings, log_text)


def _child() -> int:
    """The probe's child side: one zenoh.open with the log at warn, its outcome on stdout."""
    import zenoh

    entries = json.loads(sys.stdin.read())
    zenoh.init_log_from_env_or("warn")
    cfg = zenoh.Config()
    for path, value in entries.items():
        cfg.insert_json5(path, json.dumps(value))
    try:
        session = zenoh.open(cfg)
    except zenoh.ZError as exc:
        print(f"FAILED {exc}")
        return 1
    print("CONNECTED")
    session.close()
    return 0


def as_dict(d: Diagnosis) -> dict[str, Any]:
    return dataclasses.asdict(d)


if __name__ == "__main__":
    sys.exit(_child())
