"""Acquiring control and signing commands the way an operator's session does, for tests of the safety core.

The supervisor grants control with a key that only the acquirer receives and acts only on commands signed
with it (iorthand.security.auth). A test that plays an operator keeps its grant here and signs with it."""

from __future__ import annotations

import time

from iorthand import keys
from iorthand.protocol import ControlRequest, Message, TwistCommand
from iorthand.security import auth
from iorthand_edge.supervisor import Grant, Supervisor


class Grants:
    """The keys each operator of a test holds, per supervisor."""

    def __init__(self) -> None:
        self.keys: dict[str, bytes] = {}
        self.seq = 0  # the sequence of the current grant's commands
        self._seq = 0

    def acquire(self, sv: Supervisor, operator: str, now: float, profile: str = "",
                release: bool = True) -> tuple[bool, str]:
        """``operator`` asks for control (signed with its key when it holds one: a renewal). A new grant is
        followed by its release command, as the operator's client sends it (the edge moves nothing under a grant
        before it has seen the deadman released), numbered by ``self.seq``, which a test's commands continue (``release=False``: a test sends it itself)."""
        grant = sv.acquire(self.request(sv, operator, keys.CONTROL_ACQUIRE, profile=profile), now)
        if grant.key:
            self.keys[operator] = grant.key
            if release:
                self.release_after_grant(sv, operator, now)
            else:
                self.seq = 0
        return grant.ok, grant.reason

    def release_after_grant(self, sv: Supervisor, operator: str, now: float) -> None:
        """The grant's first command, deadman released, sent at ``now`` (monotonic) with a source time of now on
        the wall clock (its age is zero whatever clock the test keeps)."""
        self.seq = 1  # a new grant, a new sequence
        cmd = TwistCommand(operator=operator, deadman=False, state_age=0.0).stamp(self.seq, time.time_ns())
        sv.on_command(self.sign(sv, operator, cmd), time.time(), now, [0.3, 0.0, 0.2, 3.14159, 0.0, 0.0])

    def grant(self, sv: Supervisor, operator: str, now: float) -> Grant:
        return sv.acquire(self.request(sv, operator, keys.CONTROL_ACQUIRE), now)

    def request(self, sv: Supervisor, operator: str, suffix: str, **fields: str) -> ControlRequest:
        self._seq += 1
        req = ControlRequest(operator=operator, **fields).stamp(self._seq)
        return self.sign(sv, operator, req, suffix)

    def sign(self, sv: Supervisor, operator: str, msg: Message, suffix: str = keys.CMD_TWIST) -> Message:
        key = self.keys.get(operator, b"")
        return auth.sign(key, auth.context(sv.robot, suffix), msg) if key else msg
