"""Who may log in to the web console, and what each user may do there. Pure: no sockets, files read by the caller.

Users are the deployment's (``deploy/deployment.example.yaml``): an ``operators`` entry may command the robots it
is granted, a ``viewers`` entry may watch every robot and move none, exactly as the router's ACL grants their
certificates (:mod:`iorthand.security.acl`). Their web passwords are kept apart from the router's machine
credentials, in a file of scrypt hashes (``iorthand web password NAME`` writes one): the server never holds a
password in clear, and a stolen file does not open the router.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import secrets
from dataclasses import dataclass
from enum import StrEnum

from iorthand import keys
from iorthand.security.acl import Deployment

# scrypt's cost: ~50 ms and 16 MiB per check on a Pi-class core, which bounds guessing (with the rate limit).
SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**14, 8, 1
_SCHEME = "scrypt"


class Role(StrEnum):
    OPERATOR = "operator"  # commands its granted robots (one page at a time holds control of a robot)
    VIEWER = "viewer"  # sees every robot, moves none


@dataclass(frozen=True)
class Grant:
    user: str
    role: Role
    robots: tuple[str, ...]

    def may_watch(self, robot: str) -> bool:
        return robot in self.robots

    def may_command(self, robot: str) -> bool:
        return self.role is Role.OPERATOR and robot in self.robots


def grants(dep: Deployment) -> dict[str, Grant]:
    """Every user of the deployment with its role and robots. A name both operator and viewer is an operator."""
    out = {name: Grant(name, Role.VIEWER, tuple(dep.robots)) for name in dep.viewers}
    out.update({name: Grant(name, Role.OPERATOR, tuple(robots)) for name, robots in dep.operators.items()})
    return out


def hash_password(password: str, salt: bytes | None = None) -> str:
    """``scrypt$N$r$p$salt$hash`` (base64), one line of the users file."""
    if not password:
        raise ValueError("an empty password is no password")
    salt = salt if salt is not None else secrets.token_bytes(16)
    digest = hashlib.scrypt(password.encode(), salt=salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P, dklen=32)
    b64 = base64.b64encode
    return f"{_SCHEME}${SCRYPT_N}${SCRYPT_R}${SCRYPT_P}${b64(salt).decode()}${b64(digest).decode()}"


def check_password(password: str, stored: str) -> bool:
    """Whether ``password`` matches the stored hash; a malformed entry matches nothing. Constant time in the hash."""
    try:
        scheme, n, r, p, salt, digest = stored.split("$")
        if scheme != _SCHEME:
            return False
        expected = base64.b64decode(digest, validate=True)
        got = hashlib.scrypt(password.encode(), salt=base64.b64decode(salt, validate=True), n=int(n), r=int(r),
                             p=int(p), dklen=len(expected))
    except (ValueError, TypeError):
        return False
    return hmac.compare_digest(got, expected)


def parse_users(text: str, where: str = "users file") -> dict[str, str]:
    """``name:hash`` lines (``#`` comments, blank lines) → {name: hash}; ValueError naming the line if malformed."""
    out: dict[str, str] = {}
    for i, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        name, sep, stored = line.partition(":")
        if not sep or not stored.startswith(_SCHEME + "$"):
            raise ValueError(f"{where} line {i}: expected NAME:{_SCHEME}$..., got {line[:40]!r}")
        keys.check_operator_id(name)
        out[name] = stored
    return out


def format_users(users: dict[str, str]) -> str:
    return "# iorthand web console users: NAME:scrypt hash (written by `iorthand web password NAME`)\n" + "".join(
        f"{name}:{stored}\n" for name, stored in sorted(users.items()))


class LoginGuard:
    """Refuses log-ins from an address after ``max_failures`` failures within ``window`` s, for ``window`` s."""

    def __init__(self, max_failures: int = 5, window: float = 60.0) -> None:
        self.max_failures = max_failures
        self.window = window
        self._failures: dict[str, list[float]] = {}

    def blocked(self, address: str, now: float) -> float:
        """Seconds until ``address`` may try again (0: now)."""
        recent = [t for t in self._failures.get(address, []) if now - t < self.window]
        if recent:
            self._failures[address] = recent
        else:
            self._failures.pop(address, None)
        return self.window - (now - recent[0]) if len(recent) >= self.max_failures else 0.0

    def failed(self, address: str, now: float) -> None:
        self._failures.setdefault(address, []).append(now)
        if len(self._failures) > 10_000:  # a flood from many addresses costs bounded memory
            self._failures.pop(next(iter(self._failures)))

    def succeeded(self, address: str) -> None:
        self._failures.pop(address, None)


__all__ = ["Grant", "LoginGuard", "Role", "check_password", "format_users", "grants", "hash_password", "parse_users"]
