"""Who may log in to the web console, and what each user may do there. Pure: no sockets, files read by the caller.

Users are the deployment's (``deploy/deployment.example.yaml``): an ``operators`` entry may command the robots it
is granted, a ``viewers`` entry may watch every robot and move none, exactly as the router's ACL grants their
certificates (:mod:`iorthand.security.acl`). Their web passwords are kept apart from the router's machine
credentials, in a file of scrypt hashes (``iorthand web password NAME`` writes one): the server never holds a
password in clear, and a stolen file does not open the router.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import hmac
import ipaddress
import secrets
from collections.abc import Collection, Mapping
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
    """Refuses log-ins from an address after ``max_failures`` failures within ``window`` s; and to a user name
    after ``max_user_failures`` (from any address) within ``window`` s, from every address with failures of its
    own in that window.

    An attempt counts as a failure from the moment it is let through (:meth:`attempt`), before its password is
    checked, so that attempts sent at once cannot all slip in before the first one fails; a success takes back
    only its own attempt (:meth:`succeeded`), never other failures: a valid log-in of one account does not
    clear the guesses at another from the same address.

    An account under attack (its failures at the limit) stays open to an address with no recent failure: the
    lock refused every address, and anyone could lock the physician out with 20 wrong passwords a minute (red team,
    e7). A clean address gets one try (its failure makes it unclean for ``window`` s), and such tries are
    themselves limited to ``max_user_failures`` a window: guessing one account stays bounded (2 × the limit a
    window), and locking its user out now takes that many fresh addresses a minute, not 20 requests."""

    def __init__(self, max_failures: int = 5, window: float = 60.0, max_user_failures: int = 20) -> None:
        self.max_failures = max_failures
        self.max_user_failures = max_user_failures
        self.window = window
        # "addr:<address>" / "user:<name>" → failure times; "clean:<name>" → tries let through from a clean
        # address while that account was locked
        self._failures: dict[str, list[float]] = {}

    def _recent(self, key: str, now: float) -> list[float]:
        recent = [t for t in self._failures.get(key, []) if now - t < self.window]
        if recent:
            self._failures[key] = recent
        else:
            self._failures.pop(key, None)
        return recent

    def _check(self, address: str, now: float, user: str) -> tuple[float, bool]:
        """(seconds until ``address`` may try ``user`` again, 0: now; whether a try now is a clean address's try
        at a locked account)."""
        own = self._recent(f"addr:{address}", now)
        waits = [0.0]
        if len(own) >= self.max_failures:
            waits.append(self.window - (now - own[-self.max_failures]))
        clean_try = False
        if user:
            failures = self._recent(f"user:{user}", now)
            if len(failures) >= self.max_user_failures:
                unlocked = self.window - (now - failures[-self.max_user_failures])
                clean = self._recent(f"clean:{user}", now)
                if own:  # this address failed lately: it waits for the account's lock or its own failures to pass
                    waits.append(min(unlocked, self.window - (now - own[-1])))
                elif len(clean) >= self.max_user_failures:  # clean addresses' tries used up too
                    waits.append(min(unlocked, self.window - (now - clean[-self.max_user_failures])))
                else:
                    clean_try = True
        return max(waits), clean_try

    def blocked(self, address: str, now: float, user: str = "") -> float:
        """Seconds until ``address`` (and ``user``) may try again (0: now)."""
        return self._check(address, now, user)[0]

    def attempt(self, address: str, user: str, now: float) -> float:
        """Let an attempt through (0.0, counted as a failure until it succeeds) or say how long to wait."""
        wait, clean_try = self._check(address, now, user)
        if not wait:
            self.failed(address, now, user)
            if clean_try:
                self._failures.setdefault(f"clean:{user}", []).append(now)
        return wait

    def failed(self, address: str, now: float, user: str = "") -> None:
        for key in (f"addr:{address}", *((f"user:{user}",) if user else ())):
            self._failures.setdefault(key, []).append(now)
        while len(self._failures) > 20_000:  # a flood from many addresses and names costs bounded memory
            self._failures.pop(next(iter(self._failures)))

    def succeeded(self, address: str, user: str, at: float) -> None:
        """The attempt let through at ``at`` was right: it is not a failure after all."""
        for key in (f"addr:{address}", f"user:{user}", f"clean:{user}"):
            with contextlib.suppress(KeyError, ValueError):
                self._failures[key].remove(at)


__all__ = ["Grant", "LoginGuard", "Role", "check_password", "format_users", "grants", "hash_password", "parse_users"]


@dataclass(frozen=True)
class Peer:
    """Who is on the other end of a request: the browser's address, and whether it came over HTTPS."""

    address: str
    https: bool


def peer_of(remote: str | None, https: bool, headers: Mapping[str, str], trusted_proxies: Collection[str]) -> Peer:
    """The browser behind a request. From a trusted reverse proxy (its address in ``trusted_proxies``) that is what
    the proxy says: the last address of X-Forwarded-For (the one the proxy appended: the ones before it are the
    client's own claims) and X-Forwarded-Proto. Behind a proxy every request comes from the proxy's address, so
    without this one user's failed log-ins locked every user out, and cookies lost their Secure flag.
    Anyone else's forwarding headers are ignored."""
    remote = remote or "?"
    if remote not in trusted_proxies:
        return Peer(remote, https)
    forwarded = headers.get("X-Forwarded-For", "").rsplit(",", 1)[-1].strip()
    try:
        address = str(ipaddress.ip_address(forwarded)) if forwarded else remote
    except ValueError:
        address = remote  # not an address: the proxy's own stands (the stricter, shared limit)
    proto = headers.get("X-Forwarded-Proto", "").rsplit(",", 1)[-1].strip().lower()
    return Peer(address, https or proto == "https")
