"""Zenoh key expressions: the one place that builds them.

Every key starts with ``iorthand/<robot>/``. Cloud services live under ``iorthand/_twin`` and
``iorthand/_recorder``. Code never writes a key literal: it asks :class:`RobotKeys` or the helpers here.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from iorthand import channels

ROOT = "iorthand"
ROBOT_ID_PATTERN = re.compile(r"^[a-z0-9_-]{1,64}$")
OPERATOR_ID_PATTERN = re.compile(r"^[A-Za-z0-9_.@-]{1,64}$")

# Suffixes under iorthand/<robot>/: each is a row of the table of channels, aliased here so that callers name
# keys by keys.X.
CMD_TWIST = channels.CMD_TWIST.suffix
CMD_SERVO = channels.CMD_SERVO.suffix
CMD_TORCH = channels.CMD_TORCH.suffix
CMD_STOP = channels.CMD_STOP.suffix
CMD_VIDEO_FEEDBACK = channels.CMD_VIDEO_FEEDBACK.suffix
STATE_ROBOT = channels.STATE_ROBOT.suffix
STATE_SAFETY = channels.STATE_SAFETY.suffix
STATE_APPLIED = channels.STATE_APPLIED.suffix
STATE_FORCE = channels.STATE_FORCE.suffix
STATE_FORCE_LEVEL = channels.STATE_FORCE_LEVEL.suffix
STATE_SERVO = channels.STATE_SERVO.suffix
STATE_TORCH = channels.STATE_TORCH.suffix
MARKERS = channels.MARKERS.suffix
VIDEO_CAMERA = channels.VIDEO_CAMERA.suffix
VIDEO_ULTRASOUND = channels.VIDEO_ULTRASOUND.suffix
SENSOR_VITAL = channels.SENSOR_VITAL.suffix
CONTROL_ACQUIRE = channels.CONTROL_ACQUIRE.suffix
CONTROL_RELEASE = channels.CONTROL_RELEASE.suffix
CONTROL_ARM = channels.CONTROL_ARM.suffix
CONTROL_POSES = channels.CONTROL_POSES.suffix
CONTROL_GOTO = channels.CONTROL_GOTO.suffix
CONTROL_FORCE_ZERO = channels.CONTROL_FORCE_ZERO.suffix
CONTROL_CONTACT = channels.CONTROL_CONTACT.suffix
PLAN_PREVIEW = channels.PLAN_PREVIEW.suffix
ALIVE_EDGE = channels.ALIVE_EDGE.suffix
ALIVE_OPERATOR = channels.ALIVE_OPERATOR.suffix

TWIN = "_twin"
RECORDER = "_recorder"
TWIN_SNAPSHOT = "snapshot"  # iorthand/_twin/<robot>/snapshot: latest state of one robot, with ages
TWIN_PREVIEW = "preview"  # iorthand/_twin/<robot>/preview: forwarded to the edge's plan/preview, drawn

# Recorder service keys, under iorthand/_recorder/ (see service_key): queryables, and the status stream that
# also carries errors (a full disk must be visible to every client, not only in the recorder's log).
RECORDER_START = "start"
RECORDER_STOP = "stop"
RECORDER_ANNOTATE = "annotate"  # annotate/<author> carries its author: the router binds it to the certificate
RECORDER_STATUS = "status"
RECORDER_ANNOTATIONS = "annotations"  # the channel annotations are stored on, inside recordings


class KeyExprError(ValueError):
    """A robot or operator id that cannot be part of a key expression."""


def is_robot_id(robot: str) -> bool:
    return isinstance(robot, str) and ROBOT_ID_PATTERN.match(robot) is not None


def check_robot_id(robot: str) -> str:
    if not is_robot_id(robot):
        raise KeyExprError(f"robot id {robot!r} is invalid: expected 1-64 characters of [a-z0-9_-]")
    return robot


# A replay publishes a recorded robot as "<robot>-replay", and no edge may take such an id: a replayed stream
# can never be taken for a robot, on a console, in the twin, or by the router's access control.
REPLAY_SUFFIX = "-replay"


def replay_id(robot: str) -> str:
    """The id a replay publishes recorded robot ``robot`` as (a replay of a replay keeps its id)."""
    check_robot_id(robot)
    return robot if robot.endswith(REPLAY_SUFFIX) else check_robot_id(robot + REPLAY_SUFFIX)


def check_edge_robot_id(robot: str) -> str:
    """A robot id an edge (a real or simulated robot) may have: valid, and not one reserved for replays."""
    check_robot_id(robot)
    if robot.endswith(REPLAY_SUFFIX):
        raise KeyExprError(f"robot id {robot!r} ends in {REPLAY_SUFFIX!r}, which is reserved for replayed recordings")
    return robot


def check_operator_id(operator: str) -> str:
    if not isinstance(operator, str) or not OPERATOR_ID_PATTERN.match(operator):
        raise KeyExprError(f"operator id {operator!r} is invalid: expected 1-64 characters of [A-Za-z0-9_.@-]")
    return operator


@dataclass(frozen=True)
class RobotKeys:
    """All key expressions of one robot."""

    robot: str

    def __post_init__(self) -> None:
        check_robot_id(self.robot)

    def key(self, suffix: str) -> str:
        return f"{ROOT}/{self.robot}/{suffix}"

    @property
    def prefix(self) -> str:
        return f"{ROOT}/{self.robot}"

    @property
    def all(self) -> str:
        return f"{ROOT}/{self.robot}/**"

    def alive_operator(self, operator: str) -> str:
        return self.key(f"{ALIVE_OPERATOR}/{check_operator_id(operator)}")

    @property
    def alive_operators(self) -> str:
        return self.key(f"{ALIVE_OPERATOR}/*")


def all_robots(suffix: str) -> str:
    """A key expression matching ``suffix`` on every robot, e.g. ``iorthand/*/state/robot``."""
    return f"{ROOT}/*/{suffix}"


def all_replays(suffix: str) -> str:
    """A key expression matching ``suffix`` on every id reserved for replays, e.g. ``iorthand/$*-replay/markers``."""
    return f"{ROOT}/$*{REPLAY_SUFFIX}/{suffix}"


# Every operator → robot command is a put under iorthand/<robot>/cmd/ (bound keys add /<operator>).
ALL_COMMANDS = f"{ROOT}/*/{channels.COMMANDS}/**"


def channel_suffix(suffix: str) -> str:
    """The row of the table of channels a key suffix is on: an operator's own key (``cmd/twist/<operator>``, with
    bind_operator_keys) is on its channel's row (``cmd/twist``); any other suffix is its own."""
    parent, sep, operator = suffix.rpartition("/")
    channel = channels.BY_SUFFIX.get(parent) if sep and suffix not in channels.BY_SUFFIX else None
    if channel is not None and channel.operator_key is not channels.OperatorKey.NONE \
            and OPERATOR_ID_PATTERN.match(operator):
        return parent
    return suffix


def is_command_key(key: str) -> bool:
    """True for an operator → robot command key (``iorthand/<robot>/cmd/...``)."""
    try:
        return split_key(key)[1].startswith(f"{channels.COMMANDS}/")
    except KeyExprError:
        return False


def service_key(service: str, *parts: str) -> str:
    """A cloud service key, e.g. ``service_key(TWIN, robot, "snapshot")``."""
    return "/".join((ROOT, service, *parts))


def split_key(key: str) -> tuple[str, str]:
    """``iorthand/<robot>/<suffix>`` → ``(robot, suffix)``; raises if the key is not a robot key."""
    parts = str(key).split("/", 2)
    if len(parts) != 3 or parts[0] != ROOT or parts[1].startswith("_"):
        raise KeyExprError(f"{key!r} is not a robot key (iorthand/<robot>/<suffix>)")
    return parts[1], parts[2]


def robot_of(key: str) -> str:
    """The robot id segment of a key under ``iorthand/<robot>/...``, "" where there is none."""
    try:
        return split_key(key)[0]
    except KeyExprError:
        return ""


def operator_from_alive_key(key: str) -> str:
    """The operator id at the end of an ``alive/operator/<id>`` liveliness key."""
    return str(key).rsplit("/", 1)[-1]
