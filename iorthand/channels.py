"""The table of a robot's channels: one row per key under ``iorthand/<robot>/``, the one place its facts live.

A row says how the key is used (a stream of puts, a queryable, a liveliness token), its message class, its QoS
profile, and the roles the router's access control lets write it (publish, serve, declare) and query it. All
else is derived from the table: the suffix constants of :mod:`iorthand.keys` (aliases of the rows here), the
decoders (:data:`iorthand.protocol.MESSAGES_BY_KEY`), the QoS (:data:`iorthand.transport.QOS_BY_KEY`) and the
ACL rules (:func:`iorthand.security.acl.acl_rules`). A new channel is one new row.

The table is plain data and imports nothing of iorthand's: message classes and QoS profiles are *named*, and
the modules that hold them resolve the names when they derive their dicts, at import, failing loudly on a
typo. That is what lets keys, protocol and transport all derive from it without an import cycle (protocol
reads the suffixes of keys while its classes are being defined).

Reading is not per channel: every role may subscribe to every channel of the robots it is granted (the twin,
the recorder and viewers: of all robots; see :mod:`iorthand.security.acl`), so the table has no reader column.

The ACL grants by *family*, a suffix's first chunk: an edge may publish ``state/**``, not each state key, so a
recording of an older version with a key since renamed still replays. That is sound only while all rows of a
family agree on what the ACL grants by: :func:`check` (run at import) refuses a table where they do not.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from enum import Enum, StrEnum


class Kind(Enum):
    PUT = "put"  # a stream of samples: the writers publish it
    QUERY = "query"  # a queryable: the writers serve it, the callers query it
    TOKEN = "token"  # a liveliness token: the writers declare it


class Role(StrEnum):
    """Who may write or query a channel; each is a kind of certificate (see :mod:`iorthand.security.acl`)."""

    EDGE = "edge"  # edge-<robot>: the robot's own agent, on its robot only
    OPERATOR = "operator"  # operator-<name>: on the robots the deployment grants it
    REPLAY = "replay"  # `iorthand replay`: only under the ids reserved for replays (<robot>-replay)
    # `iorthand bridge mqtt`: readings of sensors outside the robot (a patient's vital signs) brought in from an
    # MQTT broker. Its own role so that the ACL and the bridge's own checks confine it to the rows naming it.
    BRIDGE = "bridge"
    # The twin service: it has the edge plan the operators' previews (and draws them), nothing else of a robot's.
    TWIN = "twin"


class Qos(StrEnum):
    """A named QoS profile; :data:`iorthand.transport.QOS_PROFILES` says what each is on the wire."""

    COMMAND = "command"
    CONTROL = "control"
    STATE = "state"
    SAFETY = "safety"
    DATA = "data"
    VIDEO = "video"


class OperatorKey(Enum):
    """Whether the operator's id ends the key (``.../cmd/twist/<id>``), which the ACL grants to its certificate only."""

    NONE = "none"  # the plain key iorthand/<robot>/<suffix>
    BOUND = "bound"  # with bind_operator_keys: .../<suffix>/<operator> (the edge then knows who sent it)
    ALWAYS = "always"  # always .../<suffix>/<operator>


@dataclass(frozen=True)
class Channel:
    suffix: str  # the key under iorthand/<robot>/
    kind: Kind
    message: str = ""  # class name in iorthand.protocol: what is put, or a query's payload
    qos: Qos | None = None  # puts only: queries and tokens go with Zenoh's defaults
    writers: frozenset[Role] = frozenset()  # publish a put, serve a query, declare a token
    callers: frozenset[Role] = frozenset()  # may query (queries only)
    reply: str = ""  # class name in iorthand.protocol of a query's reply
    operator_key: OperatorKey = OperatorKey.NONE
    shared: bool = False  # with bound keys the plain key stays open to every granted writer too
    # Puts a second one session may send, at most: the router drops the rest (iorthand.transport.rate_limits).
    # 0: no cap. For set-points and reports, whose newest is all that counts: a granted operator's flood of them
    # held the edge's CPU (~95 %) and delayed the owner's twists. Never a stop (every one counts) or a twist (a
    # burst after a stall is what the edge orders and applies).
    max_rate: float = 0.0

    @property
    def family(self) -> str:
        return family(self.suffix)


def family(suffix: str) -> str:
    """The first chunk of a key suffix (``state/robot`` → ``state``): what the ACL grants by."""
    return suffix.split("/", 1)[0]


_OPERATOR = frozenset({Role.OPERATOR})
_EDGE = frozenset({Role.EDGE})
# What a robot publishes, a replay publishes again as <robot>-replay.
_ROBOT = frozenset({Role.EDGE, Role.REPLAY})


def _command(suffix: str, message: str, qos: Qos, *, shared: bool = False, max_rate: float = 0.0) -> Channel:
    return Channel(suffix, Kind.PUT, message, qos, _OPERATOR, operator_key=OperatorKey.BOUND, shared=shared,
                   max_rate=max_rate)


def _robot(suffix: str, message: str, qos: Qos) -> Channel:
    return Channel(suffix, Kind.PUT, message, qos, _ROBOT)


def _control(suffix: str) -> Channel:
    return Channel(suffix, Kind.QUERY, "ControlRequest", None, _EDGE, _OPERATOR, "ControlReply", OperatorKey.BOUND)


# Operator → robot. A stop is everyone's: with bound keys every granted operator may still put the plain
# cmd/stop (its own cmd/stop/<id> also passes, and then tells the edge who sent it).
CMD_TWIST = _command("cmd/twist", "TwistCommand", Qos.COMMAND)
# Set-points: the servos step at 50 Hz, and a torch command is a switch.
CMD_SERVO = _command("cmd/servo", "ServoCommand", Qos.CONTROL, max_rate=50.0)
CMD_TORCH = _command("cmd/torch", "TorchCommand", Qos.CONTROL, max_rate=50.0)
CMD_STOP = _command("cmd/stop", "StopCommand", Qos.CONTROL, shared=True)
# A viewer's report on a video stream (keyframe requests, loss, delay): operator → edge like a command, so a replay
# never republishes it; it moves nothing. About 1 a second per stream and page (the web console's session carries
# every page's).
CMD_VIDEO_FEEDBACK = _command("cmd/video_feedback", "VideoFeedback", Qos.DATA, max_rate=50.0)
# Robot → everyone.
STATE_ROBOT = _robot("state/robot", "RobotState", Qos.STATE)
STATE_SAFETY = _robot("state/safety", "SafetyStatus", Qos.SAFETY)
# The command's echo: its own leg of the command path, at the command's priority.
STATE_APPLIED = _robot("state/applied", "AppliedCommand", Qos.COMMAND)
STATE_FORCE = _robot("state/force", "ForceSample", Qos.STATE)
STATE_FORCE_LEVEL = _robot("state/force_level", "ForceLevelState", Qos.SAFETY)
STATE_SERVO = _robot("state/servo", "ServoState", Qos.DATA)
STATE_TORCH = _robot("state/torch", "TorchState", Qos.DATA)
MARKERS = _robot("markers", "Markers", Qos.DATA)
VIDEO_CAMERA = _robot("video/camera", "VideoFrame", Qos.VIDEO)
VIDEO_ULTRASOUND = _robot("video/ultrasound", "VideoFrame", Qos.VIDEO)
# External sensors (MQTT → Zenoh through `iorthand bridge mqtt`): a family of its own, so that granting the bridge
# sensor/** grants nothing of the robot's own state/**; a replay republishes it as it does the robot's streams.
SENSOR_VITAL = Channel("sensor/vital", Kind.PUT, "SensorReading", Qos.DATA, frozenset({Role.BRIDGE, Role.REPLAY}))
# The edge's queryables.
CONTROL_ACQUIRE = _control("control/acquire")
CONTROL_RELEASE = _control("control/release")
CONTROL_ARM = _control("control/arm")
CONTROL_POSES = _control("control/poses")
CONTROL_GOTO = _control("control/goto")
CONTROL_FORCE_ZERO = _control("control/force_zero")
CONTROL_CONTACT = _control("control/contact")  # contact mode on (name "on", the force in params) or off
# Plan a named pose or a primitive; answer the verdict, the path and a single-use token for control/goto. A family
# of its own: the twin asks it for the operators (it draws the plan), and an ACL grants a family whole, so the
# twin gets this and nothing of control/**. Moving nothing, it is open to every granted operator; with bound keys
# the plain key stays open too (shared), as the twin's query carries the operator's name as a claim only (the
# token it yields is good for a goto signed by that operator's grant alone).
PLAN_PREVIEW = Channel("plan/preview", Kind.QUERY, "ControlRequest", None, _EDGE, frozenset({Role.OPERATOR, Role.TWIN}),
                       "ControlReply", OperatorKey.BOUND, shared=True)
# Liveliness: an operator's token carries its id always, so nobody can look like another operator to the edge.
ALIVE_EDGE = Channel("alive/edge", Kind.TOKEN, writers=_EDGE)
ALIVE_OPERATOR = Channel("alive/operator", Kind.TOKEN, writers=_OPERATOR, operator_key=OperatorKey.ALWAYS)

TABLE: tuple[Channel, ...] = (
    CMD_TWIST, CMD_SERVO, CMD_TORCH, CMD_STOP, CMD_VIDEO_FEEDBACK,
    STATE_ROBOT, STATE_SAFETY, STATE_APPLIED, STATE_FORCE, STATE_FORCE_LEVEL, STATE_SERVO, STATE_TORCH,
    MARKERS, VIDEO_CAMERA, VIDEO_ULTRASOUND, SENSOR_VITAL,
    CONTROL_ACQUIRE, CONTROL_RELEASE, CONTROL_ARM, CONTROL_POSES, CONTROL_GOTO, CONTROL_FORCE_ZERO, CONTROL_CONTACT,
    PLAN_PREVIEW,
    ALIVE_EDGE, ALIVE_OPERATOR,
)

_SUFFIX = re.compile(r"^[a-z_]+(/[a-z_]+)*$")


def families(table: Iterable[Channel], kind: Kind) -> dict[str, list[Channel]]:
    """The rows of ``kind`` by family, in table order."""
    out: dict[str, list[Channel]] = {}
    for c in table:
        if c.kind is kind:
            out.setdefault(c.family, []).append(c)
    return out


def check(table: Iterable[Channel]) -> None:
    """Refuse a table the derived dicts or the ACL would get wrong."""
    rows = list(table)
    suffixes = [c.suffix for c in rows]
    if len(set(suffixes)) != len(suffixes):
        raise ValueError(f"a key suffix has two rows: {sorted(s for s in suffixes if suffixes.count(s) > 1)}")
    for c in rows:
        if not _SUFFIX.match(c.suffix):
            raise ValueError(f"{c.suffix!r}: a suffix is chunks of [a-z_] without wildcards")
        if not c.writers:
            raise ValueError(f"{c.suffix}: nobody may write it")
        if (c.kind is Kind.PUT) != (c.qos is not None) or (c.kind is Kind.TOKEN) == bool(c.message):
            raise ValueError(f"{c.suffix}: a put has a message and a QoS, a query a message, a token neither")
        if (c.kind is Kind.QUERY) != bool(c.callers) or (c.kind is Kind.QUERY) != bool(c.reply):
            raise ValueError(f"{c.suffix}: callers and a reply belong to queries, and every query has both")
        if c.max_rate and (c.kind is not Kind.PUT or c.max_rate < 0):
            raise ValueError(f"{c.suffix}: a rate cap is for puts, and positive")
        if c.shared and c.operator_key is not OperatorKey.BOUND:
            raise ValueError(f"{c.suffix}: only a bound key has a shared plain key")
        if c.operator_key is OperatorKey.BOUND and Role.OPERATOR not in c.writers | c.callers:
            raise ValueError(f"{c.suffix}: only a key operators write or query can be bound to them")
        if (c.operator_key is OperatorKey.ALWAYS) != (c.kind is Kind.TOKEN and Role.OPERATOR in c.writers):
            raise ValueError(f"{c.suffix}: an operator's token, and only it, always carries the operator's id")
    kinds: dict[str, set[Kind]] = {}
    for c in rows:
        kinds.setdefault(c.family, set()).add(c.kind)
    if mixed := sorted(f for f, k in kinds.items() if len(k) > 1):
        raise ValueError(f"a family mixes puts, queries and tokens: {mixed}")
    if len({c.family for c in rows if c.kind is Kind.PUT and Role.OPERATOR in c.writers}) != 1:
        raise ValueError("operator commands are one family (the recorder and the replay tell commands by it)")
    for kind in (Kind.PUT, Kind.QUERY):  # tokens are granted by their exact keys
        for fam, members in families(rows, kind).items():
            if len({(c.writers, c.callers, c.operator_key) for c in members}) > 1:
                raise ValueError(f"the {fam} rows differ in who may write or query them, or in operator keys: "
                                 "the ACL grants a family at once")


check(TABLE)
BY_SUFFIX: dict[str, Channel] = {c.suffix: c for c in TABLE}
COMMANDS = CMD_TWIST.family  # the family of every operator → robot command (one: see check)

__all__ = ["COMMANDS", "TABLE", "Channel", "Kind", "OperatorKey", "Qos", "Role", "check", "families", "family"]
