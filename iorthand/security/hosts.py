"""Which host a browser's request names (its Host header), against the names a server answers to.

A DNS-rebinding page (``evil.example`` made to resolve to the server's address) is the server's own origin under
its name: same-origin to everything the server serves. Checking that a request names one of the server's own names
closes that. Pure functions: the web console and the twin's viewer gateway use them.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable
from urllib.parse import urlsplit

LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")
WILDCARDS = ("0.0.0.0", "::")  # listen addresses that name no host: every address of the machine


def is_loopback(host: str) -> bool:
    """Whether a listen address (or ``localhost``) is this machine's loopback."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def own_names(listen_host: str, others: Iterable[str] = ()) -> frozenset[str]:
    """The names a server listening on ``listen_host`` answers to: that address (unless a wildcard), ``others``,
    and the loopback names when it listens on loopback (normalised for :func:`host_allowed`)."""
    names = [*others]
    if listen_host not in WILDCARDS:
        names.append(listen_host)
    if is_loopback(listen_host):
        names += LOOPBACK_NAMES
    return normalise(names)


def normalise(names: Iterable[str]) -> frozenset[str]:
    """Host names as :func:`host_allowed` compares them (lower case, IPv6 without brackets)."""
    return frozenset(n.strip("[]").lower() for n in names if n)


def host_allowed(host_header: str, names: frozenset[str]) -> bool:
    """Whether a request's Host header names one of ``names`` (any port: a relay or a NAT may change it). A
    certificate's wildcard ``*.example.org`` covers one label, as for a browser."""
    try:
        host = (urlsplit(f"//{host_header}").hostname or "").rstrip(".")
    except ValueError:  # a malformed header (an unclosed bracket, a bad port)
        return False
    if not host:
        return False
    if host in names:
        return True
    label, dot, parent = host.partition(".")
    return bool(label and dot and f"*.{parent}" in names)


__all__ = ["LOOPBACK_NAMES", "WILDCARDS", "host_allowed", "is_loopback", "normalise", "own_names"]
