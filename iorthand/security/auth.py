"""Commands bound to the session that acquired control: a secret only the owner holds, and a MAC on each command.

Zenoh does not tell a subscriber who sent a sample (``source_info`` is the sender's own claim), and a name in a
payload is a claim too. So when the edge grants control it draws a fresh random key and returns it in the
acquire reply, which Zenoh routes to the querier alone. The owner signs every command with that key; the edge
acts only on commands whose MAC verifies. Another session — on an open router, or another certificate granted
the same robot behind mTLS — can copy the owner's name and any sequence number, but not the key: its commands
are refused. A replayed command fails the sequence check (the sequence and time are inside the MAC), and
every acquire draws a new key, so nothing signed for an earlier owner is valid afterwards.

On a router without TLS the acquire reply itself crosses the network in clear: anyone who can read that
traffic can read the key. TLS to the router (docs/DEPLOY.md) is what keeps it secret on the wire.

The MAC is BLAKE2s keyed (a standard keyed hash, 16 bytes) over the message in its canonical form (what the
receiver decodes, without the ``mac`` field) and a context: the robot and the key suffix, so a signature for
one robot or one kind of message is worthless for another.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from typing import TypeVar

import msgpack

from iorthand.protocol import Message

KEY_BYTES = 32
MAC_BYTES = 16

M = TypeVar("M", bound=Message)


def new_key() -> bytes:
    """A fresh secret for one grant of control."""
    return secrets.token_bytes(KEY_BYTES)


def context(robot: str, suffix: str) -> bytes:
    """What a signature is bound to besides the message: the robot id and the key suffix (``cmd/twist``)."""
    return f"iorthand/{robot}/{suffix}".encode()


def _digest(key: bytes, ctx: bytes, msg: Message) -> bytes:
    # The fields as they are: a decoded (or validated, or canonical) message holds plain Python values only, and
    # the per-value conversion of _to_map() costs a third of a check on the edge. A message built in-process with
    # numpy arrays (never one off the wire) is converted first.
    fields = {name: getattr(msg, name) for name, _, _ in msg._fields() if name != "mac"}
    try:
        packed = msgpack.packb([ctx, fields], use_bin_type=True)
    except TypeError:
        fields = {name: value for name, value in msg._to_map().items() if name != "mac"}
        packed = msgpack.packb([ctx, fields], use_bin_type=True)
    return hashlib.blake2s(packed, key=key, digest_size=MAC_BYTES).digest()


def sign(key: bytes, ctx: bytes, msg: M, canonical: bool = False) -> M:
    """Set ``msg.mac`` (the message must be stamped). The MAC covers the message as the receiver will decode
    it (an int 0 sent in a float field arrives as 0.0), so it is computed on the validated copy — unless the
    caller says the message is already ``canonical`` (every field of the type decode returns: the operator's
    60 Hz sender, where the round trip is most of the signing cost on a cold CPU)."""
    msg.mac = b""  # type: ignore[attr-defined]
    msg.mac = _digest(key, ctx, msg if canonical else msg.validate())  # type: ignore[attr-defined]
    return msg


def verify(key: bytes, ctx: bytes, msg: Message) -> bool:
    """Whether ``msg`` (as decoded) carries a valid MAC under ``key``. Constant time."""
    mac = getattr(msg, "mac", b"")
    if not key or len(mac) != MAC_BYTES:
        return False
    return hmac.compare_digest(mac, _digest(key, ctx, msg))


__all__ = ["KEY_BYTES", "MAC_BYTES", "context", "new_key", "sign", "verify"]
