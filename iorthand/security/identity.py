"""Defence in depth on the edge: who may command this robot, decided by the edge itself. Pure functions.

The router's ACL is the first wall; these checks hold even if the router is misconfigured or replaced by a
stock one without ACL. Zenoh 1.10's Python API does not tell a subscriber or a queryable *which
authenticated identity* (certificate CN, username) sent a sample: ``source_info`` and timestamps are set by
the sender and can be forged. So the binding of an operator id to a session identity is made through keys the
router's ACL scopes to that identity (see :mod:`iorthand.security.acl`):

- the liveliness token ``iorthand/<robot>/alive/operator/<id>`` can only be declared by the session whose
  certificate is ``operator-<id>`` → :meth:`CommandGate.check_acquire` with ``require_alive`` refuses to
  hand control to an id that no authenticated session currently holds;
- with ``bind_operator_keys`` the router lets ``operator-<id>`` publish only on ``.../cmd/<kind>/<id>`` and
  query only ``.../control/<verb>/<id>`` → :meth:`CommandGate.check_key` refuses any message whose
  ``operator`` field differs from the id in its key, so operator A cannot send commands in operator B's name.

And on every message, the configurable allow-list of operator ids (``SafetyConfig.allowed_operators``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from iorthand import channels, keys

OPERATOR_CN_PREFIX = "operator-"
EDGE_CN_PREFIX = "edge-"


def edge_common_name(robot: str) -> str:
    """The certificate (and router user) name of ``robot``'s edge, as the router's ACL knows it."""
    return f"{EDGE_CN_PREFIX}{robot}"


def operator_common_name(operator: str) -> str:
    """The certificate (and router user) name of an operator, as the router's ACL knows it."""
    return f"{OPERATOR_CN_PREFIX}{operator}"


def operator_from_common_name(cn: str) -> str | None:
    """``operator-alice`` → ``alice``; None for any other role."""
    if not cn.startswith(OPERATOR_CN_PREFIX):
        return None
    op = cn[len(OPERATOR_CN_PREFIX):]
    return op if keys.OPERATOR_ID_PATTERN.match(op) else None


def bound_key(robot_keys: keys.RobotKeys, suffix: str, operator: str) -> str:
    """The identity-scoped key of a command or control verb: ``iorthand/<robot>/cmd/twist/<operator>``."""
    return robot_keys.key(f"{suffix}/{keys.check_operator_id(operator)}")


def operator_in_key(key: str, suffix: str) -> str | None:
    """The operator id of an identity-scoped key (``.../<suffix>/<id>``), or None for the plain key."""
    try:
        _, rest = keys.split_key(key)
    except keys.KeyExprError:
        return None
    if not rest.startswith(suffix + "/"):
        return None
    op = rest[len(suffix) + 1:]
    return op if keys.OPERATOR_ID_PATTERN.match(op) else None


# The refusal of an acquire whose operator's liveliness token the edge has not seen. A client that has just
# declared its token may see it: the token and the query race through the router, so it asks again shortly
# (OperatorClient.acquire). The edge never waits for the token itself: a blocking check per refusal let a few
# acquires a second in made-up names hold up the owner's lease renewals on a WAN link.
NO_TOKEN = "holds no liveliness token"


@dataclass
class CommandGate:
    """The edge's own admission checks for control requests and commands.

    ``allowed``: operator ids allowed at all (empty: any). ``require_alive``: acquiring needs the operator's
    liveliness token (ACL-bound to its certificate). ``bind_keys``: the operator id must be the one in the key.
    """

    allowed: list[str] = field(default_factory=list)
    require_alive: bool = True
    bind_keys: bool = False
    alive: set[str] = field(default_factory=set)

    def operator_alive(self, operator: str) -> None:
        self.alive.add(operator)

    def operator_gone(self, operator: str) -> None:
        self.alive.discard(operator)

    def check_key(self, key: str, suffix: str, operator: str) -> tuple[bool, str]:
        if not self.bind_keys:
            return True, ""
        bound = operator_in_key(key, suffix)
        if bound is None and channels.BY_SUFFIX[suffix].shared and keys.split_key(key)[1] == suffix:
            return True, ""  # a plain key every granted caller may use (plan/preview): the name is a claim there
        if bound is None:
            return False, f"{key}: commands must come on the identity-scoped key .../{suffix}/<operator>"
        if bound != operator:
            return False, f"{key}: message claims operator {operator!r} but the router authenticated {bound!r}"
        return True, ""

    def check_operator(self, operator: str) -> tuple[bool, str]:
        if self.allowed and operator not in self.allowed:
            return False, f"operator {operator!r} is not in this robot's allow-list"
        return True, ""

    def check_acquire(self, key: str, suffix: str, operator: str) -> tuple[bool, str]:
        for ok, reason in (self.check_operator(operator), self.check_key(key, suffix, operator)):
            if not ok:
                return ok, reason
        if self.require_alive and operator not in self.alive:
            return False, (
                f"operator {operator!r} {NO_TOKEN}: only a session authenticated as "
                f"operator-{operator} can declare it"
            )
        return True, ""

    def check_command(self, key: str, suffix: str, operator: str) -> tuple[bool, str]:
        for ok, reason in (self.check_operator(operator), self.check_key(key, suffix, operator)):
            if not ok:
                return ok, reason
        return True, ""
