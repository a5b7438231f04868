"""Acquiring control and signing commands the way an operator's session does, for tests of the safety core.

The supervisor grants control with a key that only the acquirer receives and acts only on commands signed
with it (iorthand.security.auth). A test that plays an operator keeps its grant here and signs with it."""

from __future__ import annotations

from iorthand import keys
from iorthand.protocol import ControlRequest, Message
from iorthand.security import auth
from iorthand_edge.supervisor import Grant, Supervisor


class Grants:
    """The keys each operator of a test holds, per supervisor."""

    def __init__(self) -> None:
        self.keys: dict[str, bytes] = {}
        self._seq = 0

    def acquire(self, sv: Supervisor, operator: str, now: float, profile: str = "") -> tuple[bool, str]:
        """``operator`` asks for control (signed with its key when it holds one: a renewal)."""
        grant = sv.acquire(self.request(sv, operator, keys.CONTROL_ACQUIRE, profile=profile), now)
        if grant.key:
            self.keys[operator] = grant.key
        return grant.ok, grant.reason

    def grant(self, sv: Supervisor, operator: str, now: float) -> Grant:
        return sv.acquire(self.request(sv, operator, keys.CONTROL_ACQUIRE), now)

    def request(self, sv: Supervisor, operator: str, suffix: str, **fields: str) -> ControlRequest:
        self._seq += 1
        req = ControlRequest(operator=operator, **fields).stamp(self._seq)
        return self.sign(sv, operator, req, suffix)

    def sign(self, sv: Supervisor, operator: str, msg: Message, suffix: str = keys.CMD_TWIST) -> Message:
        key = self.keys.get(operator, b"")
        return auth.sign(key, auth.context(sv.robot, suffix), msg) if key else msg
