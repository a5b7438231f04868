"""Commands bound to the session that acquired control: a secret only the owner holds, and a MAC on each command.

Zenoh does not tell a subscriber who sent a sample (``source_info`` is the sender's own claim), and a name in a
payload is a claim too. So when the edge grants control it draws a fresh random key and returns it in the
acquire reply, which Zenoh routes to the querier alone. The owner signs every command with that key; the edge
acts only on commands whose MAC verifies. Another session — on an open router, or another certificate granted
the same robot behind mTLS — can copy the owner's name and any sequence number, but not the key: its commands
are refused. A replayed command fails the sequence check (the sequence and time are inside the MAC), and
every acquire draws a new key, so nothing signed for an earlier owner is valid afterwards.

On a router without TLS the acquire reply itself crosses the network in clear: anyone who can read that
traffic can read the key. TLS to the router (docs/DEPLOY.md) is what keeps it secret on the wire. Nor does an
open router say who answers a query: another session can declare a queryable on ``control/acquire`` and answer
with a grant of its own, a key it also holds. The operator's client believes no answer when more than one
session answered (the edge always answers too), but while the edge is silent a lone impostor would be believed:
the deployment's ACL, which lets only the edge's certificate answer under ``control/**``, closes that.

The other way, the edge signs its robot state, its command echoes, its safety state and its force levels with
the same key while someone holds control (``Supervisor.for_owner``), and the owner's client believes only those
that verify: a third session cannot feed the owner a fresh-looking robot state (which the owner's commands would
report to the edge as the age of its picture), fake echoes (the link's latency), a false safety state or a green
force level. Watchers hold no key and check nothing.

The edge's answers to the owner's control queries are signed too (``reply_context``), each carrying the sequence
of the request it answers: the owner takes the answer that verifies and ignores any other session's, so another
session answering on ``control/acquire`` (an open router), or holding the query open, no longer costs the owner
its lease renewal; and an old answer replayed does not pass for the answer to a new request.

The MAC is BLAKE2s keyed (a standard keyed hash, 16 bytes) over a context (the robot and the key suffix, so a
signature for one robot or one kind of message is worthless for another) and the message's bytes as they travel,
up to the MAC itself: a signed message's ``mac`` is its last field, so its payload ends with the MAC's 16 bytes.
The receiver checks the very bytes it decoded (``Message.decode`` keeps them), with no re-encoding and no
question of a canonical form.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from typing import TypeVar

from iorthand.protocol import Message

KEY_BYTES = 32
MAC_BYTES = 16
# How a signed payload ends: the key "mac" and a 16-byte bin header (msgpack), then the MAC.
_TRAILER = b"\xa3mac\xc4" + bytes([MAC_BYTES])

M = TypeVar("M", bound=Message)


def new_key() -> bytes:
    """A fresh secret for one grant of control."""
    return secrets.token_bytes(KEY_BYTES)


def context(robot: str, suffix: str) -> bytes:
    """What a signature is bound to besides the message: the robot id and the key suffix (``cmd/twist``)."""
    return f"iorthand/{robot}/{suffix}".encode()


def reply_context(robot: str, suffix: str) -> bytes:
    """The context of the edge's answer to a ``control/<verb>`` query: apart from the request's, which the same key
    signs ('#' is in no key expression)."""
    return context(robot, suffix) + b"#reply"


def _digest(key: bytes, ctx: bytes, signed: bytes) -> bytes:
    # The context's length first: no context and message can pass for another pair.
    return hashlib.blake2s(len(ctx).to_bytes(2, "big") + ctx + signed, key=key, digest_size=MAC_BYTES).digest()


def seal(key: bytes, ctx: bytes, msg: Message) -> bytes:
    """Sign ``msg`` (stamped, of a signed type) and return its payload: the encoding with the MAC as its end."""
    msg.mac = bytes(MAC_BYTES)  # type: ignore[attr-defined]  # the placeholder: the MAC's place in the encoding
    unsigned = msg.encode()
    if not unsigned.endswith(_TRAILER + bytes(MAC_BYTES)):
        raise TypeError(f"{type(msg).__name__} has no mac as its last field: it cannot be signed")
    signed = unsigned[:-MAC_BYTES]
    msg.mac = _digest(key, ctx, signed)  # type: ignore[attr-defined]
    return signed + msg.mac  # type: ignore[attr-defined]


def sign(key: bytes, ctx: bytes, msg: M) -> M:
    """Set ``msg.mac`` (the message must be stamped); its ``encode()`` then carries the signature."""
    seal(key, ctx, msg)
    return msg


def verify(key: bytes, ctx: bytes, msg: Message) -> bool:
    """Whether ``msg`` carries a valid MAC under ``key``: the payload it was decoded from, or (a message built in
    this process) its encoding. Constant time in the MAC."""
    payload = getattr(msg, "_wire", None)
    if payload is None:
        payload = msg.encode()
    if not key or len(payload) <= len(_TRAILER) + MAC_BYTES or \
            payload[-MAC_BYTES - len(_TRAILER):-MAC_BYTES] != _TRAILER:
        return False
    return hmac.compare_digest(payload[-MAC_BYTES:], _digest(key, ctx, payload[:-MAC_BYTES]))


__all__ = ["KEY_BYTES", "MAC_BYTES", "context", "new_key", "reply_context", "seal", "sign", "verify"]
