"""What ``iorthand bridge mqtt`` mirrors, and how: topic and key templates, what may cross, JSON both ways. Pure.

A mapping pairs one key of the table of channels (:mod:`iorthand.channels`), ``iorthand/{robot}/<suffix>`` or one
robot's ``iorthand/<robot>/<suffix>``, with an MQTT topic template (``site/{robot}/robot_state``). ``{robot}`` is a
whole level of both or of neither: the robot id travels in the topic, never in a payload an MQTT client chose.

- **out** (Zenoh → MQTT): a robot stream, decoded with its message class and written as a JSON object (its fields,
  ``v``, ``seq`` and ``t``), at most ``max_hz`` per robot and always the newest sample (:class:`LatestThrottle`).
  Messages with binary fields (video frames) are refused at configuration time: JSON carries no bytes. A
  signature (``mac``, :mod:`iorthand.security.auth`) is left out: it signs the bytes as they travel on Zenoh and
  means nothing in a JSON copy.
- **in** (MQTT → Zenoh): a JSON object checked field by field by the key's message class (types, finite numbers,
  bounds), then by the mapping (fixed fields, a plausible range, age), stamped by the bridge and published. Only
  keys whose writers in the table include :attr:`Role.BRIDGE` may be written, and never a command, a control
  query or a liveliness token: :func:`bridge_channel` says so at configuration time and again before every put.

Nothing here opens a socket: :mod:`iorthand_cloud.bridge.mqtt` is the adapter that does.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import types
import typing
from collections import Counter, OrderedDict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from iorthand import channels, keys
from iorthand.channels import Channel, Kind, Role
from iorthand.protocol import DecodeError, Message, message_class

ROBOT = "{robot}"  # the one placeholder of a template
MAX_TOPIC_BYTES = 65535  # MQTT's limit of a topic name
NAME_PATTERN = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_MAX_INT = 2**63 - 1
STAMPED = ("seq", "t")  # numbered and timed by the bridge (``t`` may come from the sensor: see InRoute.reading)
MAX_KEYS = 256  # robots one bridge serves, and per-key state (throttles, rate limits) it keeps: bounded memory
MAX_ROBOT_ID = 64  # bytes of a robot id (keys.ROBOT_ID_PATTERN)
# What an MQTT v5 PUBLISH adds to its payload: the fixed header (1 byte and a length of up to 4), the topic's length
# (2), a packet id (2), the properties' length (up to 4) and the properties the sender attached, which the broker
# passes on (content type, expiry, user properties...): 256 bytes are left for them. A reading sent with more is
# dropped by the broker like one too large.
PUBLISH_OVERHEAD = 1 + 4 + 2 + 2 + 4 + 256
NO_INPUT_PACKET = 1024  # bytes: with no 'in' mapping the broker sends the bridge only its acknowledgements


class Direction(StrEnum):
    OUT = "out"  # Zenoh → MQTT
    IN = "in"  # MQTT → Zenoh


class MappingError(ValueError):
    """A mapping the bridge refuses to run (at configuration time, or a key refused at run time)."""


class Refused(ValueError):
    """One MQTT message refused; the text says why (counted and logged, never published)."""


# ------------------------------------------------------------------------------------------------ what may cross


def _forbidden_families() -> dict[str, str]:
    """Families no mapping may touch, derived from the table, each with why."""
    out = {channels.COMMANDS: "operator commands (cmd/) come only from an operator holding control of the robot: "
                              "the bridge never writes or mirrors them"}
    for c in channels.TABLE:
        if c.kind is Kind.QUERY:
            out.setdefault(c.family, f"{c.family}/ holds the edge's control queries (acquire, arm, goto...): "
                                     "never reachable through the bridge")
        elif c.kind is Kind.TOKEN:
            out.setdefault(c.family, f"{c.family}/ is the liveliness space (presence tokens of edges and "
                                     "operators): never bridged")
    return out


FORBIDDEN_FAMILIES = _forbidden_families()
_ROWS = {c.suffix: c for c in channels.TABLE}


def channel_of(suffix: str) -> Channel:
    """The row of the table of channels for ``suffix``; MappingError (with why) for a family no mapping may touch
    or an unknown suffix."""
    fam = channels.family(suffix)
    if fam in FORBIDDEN_FAMILIES:
        raise MappingError(f"{suffix!r}: {FORBIDDEN_FAMILIES[fam]}")
    row = _ROWS.get(suffix)
    if row is None:
        known = ", ".join(c.suffix for c in channels.TABLE if c.kind is Kind.PUT and c.family not in FORBIDDEN_FAMILIES)
        raise MappingError(f"{suffix!r} is not a stream of the table of channels (known: {known})")
    if row.kind is not Kind.PUT:  # every query and token family is forbidden above; kept for a table that grows
        raise MappingError(f"{suffix!r} is a {row.kind.value}, not a stream of messages")
    return row


def bridge_channel(suffix: str) -> Channel:
    """The row of ``suffix`` if the bridge may publish on it: a stream whose writers include Role.BRIDGE."""
    row = channel_of(suffix)
    if Role.BRIDGE not in row.writers:
        writable = ", ".join(c.suffix for c in channels.TABLE if Role.BRIDGE in c.writers and c.kind is Kind.PUT)
        raise MappingError(f"{suffix!r} is written only by {', '.join(sorted(r.value for r in row.writers))} "
                           f"(the table of channels): MQTT input goes to the bridge's keys only ({writable})")
    return row


def check_bridge_key(key: str) -> Channel:
    """Run-time defence in depth, before every put: ``key`` is ``iorthand/<robot>/<suffix>`` of a robot an edge
    may be, and the bridge may write ``suffix``. MappingError otherwise."""
    try:
        robot, suffix = keys.split_key(key)
        keys.check_edge_robot_id(robot)
    except keys.KeyExprError as exc:
        raise MappingError(str(exc)) from None
    return bridge_channel(suffix)


def _element(hint: Any) -> Any:
    """The type a field holds once ``X | None`` and ``list[X]`` are unwrapped."""
    while True:
        origin = typing.get_origin(hint)
        if origin in (typing.Union, types.UnionType):
            hint = next(a for a in typing.get_args(hint) if a is not type(None))
        elif origin is list:
            hint = typing.get_args(hint)[0]
        else:
            return hint


SIGNATURE = "mac"  # a signed message's MAC (iorthand.security.auth): not part of what a JSON copy carries


def binary_fields(cls: type[Any], prefix: str = "") -> list[str]:
    """The fields of a message (and of its nested maps) that hold bytes, which JSON cannot carry."""
    out: list[str] = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        inner = _element(hints[f.name])
        if f.name == SIGNATURE:
            continue
        if inner is bytes:
            out.append(f"{prefix}{f.name}")
        elif dataclasses.is_dataclass(inner):
            out += binary_fields(inner, f"{prefix}{f.name}[].")
    return out


# ------------------------------------------------------------------------------------------------ templates


@dataclass(frozen=True)
class TopicTemplate:
    """An MQTT topic with at most one ``{robot}`` level (no wildcards: a template names topics, it is no filter)."""

    text: str
    levels: tuple[str, ...]
    robot_level: int | None

    @classmethod
    def parse(cls, text: str) -> TopicTemplate:
        if not text:
            raise MappingError("topic is empty")
        if len(text.encode()) > MAX_TOPIC_BYTES or "\x00" in text:
            raise MappingError(f"topic {text!r} is not a valid MQTT topic (NUL, or over {MAX_TOPIC_BYTES} bytes)")
        if "+" in text or "#" in text:
            raise MappingError(f"topic {text!r} has an MQTT wildcard (+ or #): a mapping names topics, with "
                               f"{ROBOT} for the robot's level")
        if text.startswith("$"):
            raise MappingError(f"topic {text!r} starts with '$', the broker's own space ($SYS)")
        levels = tuple(text.split("/"))
        if "" in levels:
            raise MappingError(f"topic {text!r} has an empty level (a leading, trailing or double '/')")
        robot_levels = [i for i, lv in enumerate(levels) if lv == ROBOT]
        if len(robot_levels) > 1:
            raise MappingError(f"topic {text!r} has {ROBOT} more than once")
        if any(("{" in lv or "}" in lv) and lv != ROBOT for lv in levels):
            raise MappingError(f"topic {text!r}: the only placeholder is {ROBOT}, as a whole level")
        return cls(text, levels, robot_levels[0] if robot_levels else None)

    def topic(self, robot: str) -> str:
        return self.text.replace(ROBOT, robot)

    @property
    def subscription(self) -> str:
        """The MQTT filter of every topic of this template (``{robot}`` → ``+``)."""
        return self.text.replace(ROBOT, "+")

    def robot_of(self, topic: str) -> str | None:
        """The robot level of ``topic`` ('' without one), or None if ``topic`` is not one of this template's."""
        levels = topic.split("/")
        if len(levels) != len(self.levels):
            return None
        if any(t != lv for i, (t, lv) in enumerate(zip(levels, self.levels, strict=True)) if i != self.robot_level):
            return None
        return "" if self.robot_level is None else levels[self.robot_level]

    def overlaps(self, other: TopicTemplate) -> bool:
        """Whether one MQTT topic can be of both templates (``{robot}`` matches any level)."""
        if len(self.levels) != len(other.levels):
            return False
        return all(a == b or ROBOT in (a, b) for a, b in zip(self.levels, other.levels, strict=True))


@dataclass(frozen=True)
class KeyTemplate:
    """``iorthand/{robot}/<suffix>`` or ``iorthand/<robot>/<suffix>``: one row of the table of channels."""

    text: str
    robot: str | None  # the one robot named, or None for {robot}
    channel: Channel

    @classmethod
    def parse(cls, text: str) -> KeyTemplate:
        parts = text.split("/", 2)
        if len(parts) != 3 or parts[0] != keys.ROOT:
            raise MappingError(f"key {text!r} is not {keys.ROOT}/{ROBOT}/<suffix> (e.g. {keys.ROOT}/{ROBOT}/"
                               f"{channels.STATE_ROBOT.suffix})")
        robot_part, suffix = parts[1], parts[2]
        if any(ch in text.replace(ROBOT, "") for ch in "*$?#{}"):
            raise MappingError(f"key {text!r} has a wildcard or placeholder other than {ROBOT}: a mapping is one key "
                               "of the table of channels")
        channel = channel_of(suffix)
        if robot_part == ROBOT:
            return cls(text, None, channel)
        try:
            keys.check_edge_robot_id(robot_part)
        except keys.KeyExprError as exc:
            raise MappingError(f"key {text!r}: {exc}") from None
        return cls(text, robot_part, channel)

    @property
    def expr(self) -> str:
        """The Zenoh key expression of every key of this template (``{robot}`` → ``*``)."""
        return keys.RobotKeys(self.robot).key(self.channel.suffix) if self.robot else keys.all_robots(self.channel.suffix)

    def key(self, robot: str) -> str:
        return keys.RobotKeys(self.robot or robot).key(self.channel.suffix)

    @property
    def message(self) -> type[Message]:
        return message_class(self.channel.message)


def _pair(key: KeyTemplate, topic: TopicTemplate) -> None:
    if key.robot is None and topic.robot_level is None:
        raise MappingError(f"the key has {ROBOT} but topic {topic.text!r} has not: every robot would share one topic "
                           f"(put {ROBOT} in the topic, or name one robot in the key)")
    if key.robot is not None and topic.robot_level is not None:
        raise MappingError(f"topic {topic.text!r} has {ROBOT} but the key names robot {key.robot!r}: use "
                           f"{keys.ROOT}/{ROBOT}/{key.channel.suffix}, or no {ROBOT} in the topic")


# ------------------------------------------------------------------------------------------------ routes


def _robot_allowed(robot: str, robots: frozenset[str], *, replays: bool = False) -> None:
    """Refused unless ``robot`` is a valid id in ``robots`` (empty: any); a replay's id only with ``replays``."""
    try:
        (keys.check_robot_id if replays else keys.check_edge_robot_id)(robot)
    except keys.KeyExprError as exc:
        raise Refused(str(exc)) from None
    if robots and robot not in robots:
        raise Refused(f"robot {robot!r} is not one of the bridge's robots {sorted(robots)}")


@dataclass(frozen=True)
class OutRoute:
    """Zenoh → MQTT: one robot stream to a topic, as JSON, at most ``max_hz`` per robot."""

    name: str
    key: KeyTemplate
    topic: TopicTemplate
    qos: int
    retain: bool
    max_hz: float
    robots: frozenset[str] = frozenset()  # empty: every robot

    @property
    def message(self) -> type[Message]:
        return self.key.message

    @property
    def exprs(self) -> list[str]:
        """The Zenoh key expressions to subscribe: the one robot named, each robot bridged, or every robot (a
        replay's ``<robot>-replay`` too: its id in the topic says what it is)."""
        if self.key.robot is None and self.robots:
            return [self.key.key(r) for r in sorted(self.robots)]
        return [self.key.expr]

    def topic_for(self, key: str) -> str:
        """The MQTT topic of a sample received on ``key``; Refused for a key of a robot not bridged."""
        try:
            robot, _ = keys.split_key(key)
        except keys.KeyExprError as exc:
            raise Refused(str(exc)) from None
        _robot_allowed(robot, self.robots, replays=True)
        return self.topic.topic(robot)


def to_json(msg: Message) -> bytes:
    """A decoded message as a JSON object: ``v``, then its fields (``seq`` and ``t`` included), nested maps as
    objects. Numbers are finite (the decoder checked them); a bytes field raises TypeError (refused at start)."""
    fields = {k: v for k, v in dataclasses.asdict(msg).items() if k != SIGNATURE}
    return json.dumps({"v": msg.VERSION, **fields}, separators=(",", ":"), allow_nan=False).encode()


def _refuse_constant(name: str) -> float:
    raise Refused(f"{name} is not a number JSON allows (finite numbers only)")


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """An object whose every name is one field: with ``{"value": 400, "value": 72}`` Python keeps the last, other
    readers of the same broker the first, and the bridge would publish what a dashboard shows differently."""
    data = dict(pairs)
    if len(data) != len(pairs):
        twice = next(k for k, n in Counter(k for k, _ in pairs).items() if n > 1)
        raise Refused(f"field {twice[:40]!r} appears twice in one object (which one counts differs between readers)")
    return data


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):  # 1e400 parses to inf
        raise Refused(f"{text} is not a finite number")
    return value


@dataclass(frozen=True)
class InRoute:
    """MQTT → Zenoh: JSON objects on a topic, checked, to one of the bridge's keys."""

    name: str
    key: KeyTemplate
    topic: TopicTemplate
    qos: int
    max_hz: float
    fixed: Mapping[str, Any]  # fields the mapping sets; a payload may repeat them, not contradict them
    bounds: Mapping[str, tuple[float, float]]  # plausible range per numeric field
    max_age_s: float  # a reading timed by its sensor (``t``) older than this is refused
    max_future_s: float  # and one from further in the future
    accept_retained: bool
    max_payload: int
    robots: frozenset[str] = frozenset()

    @property
    def message(self) -> type[Message]:
        return self.key.message

    @property
    def payload_fields(self) -> list[str]:
        """The fields a payload may carry: the message's, but its sequence (the bridge numbers what it sends)."""
        return [f.name for f in dataclasses.fields(self.message) if f.name != "seq"]

    @property
    def max_packet(self) -> int:
        """Bytes of the largest MQTT packet a message this route takes can be: ``max_payload``, the longest topic
        (the robot level one of the robots named) and the headers (:data:`PUBLISH_OVERHEAD`)."""
        robot = max((len(r) for r in self.robots), default=MAX_ROBOT_ID) if self.topic.robot_level is not None else 0
        topic = len(self.topic.text.replace(ROBOT, "").encode()) + robot
        return self.max_payload + topic + PUBLISH_OVERHEAD

    @property
    def required(self) -> list[str]:
        """The fields a payload must carry: all the mapping does not fix (``t`` is optional)."""
        return [n for n in self.payload_fields if n not in STAMPED and n not in self.fixed]

    def key_for(self, topic: str) -> str:
        """The Zenoh key a message on ``topic`` goes to; Refused if the topic names no robot the bridge serves."""
        robot = self.topic.robot_of(topic)
        if robot is None:
            raise Refused(f"topic {topic!r} is not one of {self.topic.text!r}")
        if self.key.robot is None:
            _robot_allowed(robot, self.robots)
        key = self.key.key(robot)
        try:  # '_twin' matches the id pattern but names a service's space: left to the check before every put,
            keys.split_key(key)  # it was counted as a bug and logged at every message, at the sender's rate
        except keys.KeyExprError as exc:
            raise Refused(str(exc)) from None
        return key

    def reading(self, payload: bytes, now_ns: int, retained: bool = False) -> Message:
        """The message a payload makes, checked (sequence 0: the adapter numbers it); Refused with why."""
        if retained and not self.accept_retained:
            raise Refused("a retained message: the broker's stored copy of an earlier reading, not a live one "
                          "(accept_retained: true takes it)")
        if len(payload) > self.max_payload:
            raise Refused(f"payload of {len(payload)} bytes exceeds the mapping's limit of {self.max_payload}")
        try:
            data = json.loads(bytes(payload).decode("utf-8"), parse_constant=_refuse_constant,
                              parse_float=_finite_float, object_pairs_hook=_no_duplicates)
        except UnicodeDecodeError:
            raise Refused("not UTF-8 text: a JSON object is expected") from None
        except RecursionError:
            raise Refused("not a flat JSON object: nested too deeply") from None
        except ValueError as exc:  # JSONDecodeError, an integer of too many digits, or Refused from a hook
            raise Refused(str(exc) if isinstance(exc, Refused) else f"not JSON ({exc})") from None
        if not isinstance(data, dict):
            raise Refused(f"expected a JSON object with {', '.join(self.required)}, got {type(data).__name__}")
        if unknown := [k for k in data if k not in self.payload_fields]:
            raise Refused(f"unknown field {str(unknown[0])[:40]!r} (known: {', '.join(self.payload_fields)})")
        if missing := [k for k in self.required if k not in data]:
            raise Refused(f"missing field {missing[0]!r} (required: {', '.join(self.required)})")
        for name, value in self.fixed.items():
            if name in data and data[name] != value:
                raise Refused(f"{name} {str(data[name])[:40]!r} differs from the mapping's {value!r}")
        if retained and "t" not in data:  # else it would be stamped now: a reading of any age passed for a live one
            raise Refused("a retained message without t: its age is unknown (the sensor's time t is required to "
                          "take a retained copy)")
        t = data.pop("t", now_ns)
        if isinstance(t, bool) or not isinstance(t, int):
            raise Refused(f"t must be an integer (ns since the epoch), got {type(t).__name__}")
        if t < now_ns - self.max_age_s * 1e9:
            raise Refused(f"t is {(now_ns - t) / 1e9:.1f} s old (max_age_s {self.max_age_s:g}): not a current reading")
        if t > now_ns + self.max_future_s * 1e9:
            raise Refused(f"t is {(t - now_ns) / 1e9:.1f} s in the future (max_future_s {self.max_future_s:g}): "
                          "check the sensor's clock")
        for name, value in data.items():  # msgpack (under validate) would only say "Integer value out of range"
            if isinstance(value, int) and not isinstance(value, bool) and abs(value) > _MAX_INT:
                raise Refused(f"{self.message.__name__}.{name}: integer out of the 64-bit range")
        try:
            msg = self.message(**{**self.fixed, **data}, seq=0, t=t).validate()  # the protocol's own checks
        except DecodeError as exc:
            raise Refused(str(exc)) from None
        except (OverflowError, ValueError, TypeError) as exc:  # msgpack refuses integers beyond 64 bits
            raise Refused(f"{type(exc).__name__}: {exc}") from None
        for name, (lo, hi) in self.bounds.items():
            value = getattr(msg, name)
            if not lo <= value <= hi:
                raise Refused(f"{name} {value:g} is outside the plausible range [{lo:g}, {hi:g}] of mapping "
                              f"{self.name!r}")
        return msg


Route = OutRoute | InRoute


def _numeric_fields(cls: type[Message]) -> set[str]:
    hints = typing.get_type_hints(cls)
    return {f.name for f in dataclasses.fields(cls) if hints[f.name] in (int, float) and f.name not in STAMPED}


def compile_route(
    name: str, direction: str, key: str, topic: str, *, qos: int = 0, max_hz: float = 10.0, retain: bool = False,
    fixed: Mapping[str, Any] | None = None, bounds: Mapping[str, Iterable[float]] | None = None,
    max_age_s: float = 60.0, max_future_s: float = 5.0, accept_retained: bool = False, max_payload: int = 4096,
    robots: Iterable[str] = (),
) -> Route:
    """A mapping checked and compiled; MappingError naming the mapping and what is wrong."""
    try:
        way = Direction(direction)
    except ValueError:
        raise MappingError(f"mapping {name!r}: direction {direction!r} is not one of "
                           f"{[d.value for d in Direction]}") from None
    try:
        return _compile(name, way, key, topic, qos, max_hz, retain, dict(fixed or {}),
                        {k: tuple(v) for k, v in (bounds or {}).items()}, max_age_s, max_future_s,
                        accept_retained, max_payload, frozenset(robots))
    except MappingError as exc:
        raise MappingError(f"mapping {name!r}: {exc}") from None


def _compile(name: str, direction: Direction, key_text: str, topic_text: str, qos: int, max_hz: float, retain: bool,
             fixed: dict[str, Any], bounds: dict[str, tuple[float, ...]], max_age_s: float, max_future_s: float,
             accept_retained: bool, max_payload: int, robots: frozenset[str]) -> Route:
    if not NAME_PATTERN.match(name):
        raise MappingError("a mapping's name is 1-64 characters of [A-Za-z0-9_.-]")
    if qos not in (0, 1):
        raise MappingError(f"qos {qos!r}: the bridge uses MQTT QoS 0 or 1")
    if not 0 < max_hz <= 1000 or not math.isfinite(max_hz):
        raise MappingError(f"max_hz {max_hz!r} is not within (0, 1000]")
    key = KeyTemplate.parse(key_text)
    topic = TopicTemplate.parse(topic_text)
    _pair(key, topic)
    for r in robots:
        try:
            keys.check_edge_robot_id(r)
        except keys.KeyExprError as exc:
            raise MappingError(f"robots: {exc}") from None
    if direction is Direction.OUT:
        if binary := binary_fields(key.message):
            raise MappingError(f"{key.channel.suffix} is {key.message.__name__}, whose "
                               f"{', '.join(binary)} is binary: JSON carries no bytes, so video frames and "
                               "signed commands are not mirrored")
        if fixed or bounds:
            raise MappingError("fields and bounds belong to 'in' mappings (what MQTT input must be)")
        return OutRoute(name, key, topic, qos, retain, max_hz, robots)
    bridge_channel(key.channel.suffix)
    if retain:
        raise MappingError("retain belongs to 'out' mappings (what the bridge publishes on MQTT)")
    cls = key.message
    if binary := binary_fields(cls):  # no such row today; a JSON payload cannot fill a bytes field
        raise MappingError(f"{cls.__name__}.{binary[0]} is binary: MQTT input is JSON")
    allowed = [f.name for f in dataclasses.fields(cls) if f.name not in STAMPED]
    for f in fixed:
        if f not in allowed:
            raise MappingError(f"fields: {f!r} is not a field the mapping can fix (one of {', '.join(allowed)})")
    numeric = _numeric_fields(cls)
    for f, b in bounds.items():
        if f not in numeric:
            raise MappingError(f"bounds: {f!r} is not a numeric field of {cls.__name__} ({', '.join(sorted(numeric))})")
        if len(b) != 2 or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in b) or not b[0] <= b[1]:
            raise MappingError(f"bounds: {f} is {list(b)}; expected [low, high] with low <= high")
    if max_age_s <= 0 or max_future_s < 0:
        raise MappingError("max_age_s must be > 0 and max_future_s >= 0")
    if not 2 <= max_payload <= 65536:
        raise MappingError(f"max_payload {max_payload} is not within 2..65536 bytes")
    route = InRoute(name, key, topic, qos, max_hz, fixed, {k: (float(v[0]), float(v[1])) for k, v in bounds.items()},
                    max_age_s, max_future_s, accept_retained, max_payload, robots)
    try:  # the fixed values themselves must be a valid message (a unit of 40 characters is not)
        cls(**fixed, seq=0, t=0).validate()
    except (DecodeError, OverflowError, ValueError, TypeError) as exc:
        raise MappingError(f"fields: {exc}") from None
    return route


def check_routes(routes: list[Route]) -> None:
    """Refuse a set of mappings that would collide: two names alike, or two mappings whose topics one MQTT topic
    can match: two 'in' would publish a reading twice, two 'out' mix two streams on one topic, and an 'out' with an
    'in' would read back what the bridge itself publishes. And an 'in' mapping whose topic chooses the robot
    without the robots it may choose named: any client of the broker could invent robots."""
    seen: set[str] = set()
    for r in routes:
        if r.name in seen:
            raise MappingError(f"mapping {r.name!r}: two mappings have this name")
        seen.add(r.name)
    for i, a in enumerate(routes):
        for b in routes[i + 1:]:
            if a.topic.overlaps(b.topic):
                raise MappingError(f"mappings {a.name!r} and {b.name!r}: topics {a.topic.text!r} and "
                                   f"{b.topic.text!r} can be one MQTT topic")
    for r in routes:
        if isinstance(r, InRoute) and r.key.robot is None and not r.robots:
            raise MappingError(
                f"mapping {r.name!r} takes the robot from the MQTT topic ({r.topic.text}): name the robots this "
                f"bridge serves (robots: [...], at most {MAX_KEYS}). With none named any client of the broker could "
                "publish readings for robots it invents, and take from the real devices the slots the bridge keeps")


def max_packet_size(routes: Iterable[Route]) -> int:
    """Bytes of the largest MQTT packet the bridge takes: what it announces to an MQTT v5 broker, which then drops
    a larger message for the bridge instead of sending it (paho reads a message whole before any check)."""
    return max((r.max_packet for r in routes if isinstance(r, InRoute)), default=NO_INPUT_PACKET)


# ------------------------------------------------------------------------------------------------ rates


class LatestThrottle:
    """At most one item per ``1/max_hz``, and always the newest: an item offered too soon waits (replacing any
    waiting one) until :meth:`poll` finds its time has come. A 125 Hz stream reaches MQTT at ``max_hz`` and the
    last state before a pause still goes out, which a plain drop-if-too-soon limiter would lose."""

    def __init__(self, max_hz: float) -> None:
        self.period = 1.0 / max_hz
        self.next_ok = -math.inf
        self.pending: Any = None
        self.superseded = 0  # items replaced while waiting: never sent

    def offer(self, item: Any, now: float) -> Any:
        """``item`` if it may go now, else None (it waits)."""
        if now >= self.next_ok:
            self.next_ok = now + self.period
            if self.pending is not None:
                self.superseded += 1
                self.pending = None
            return item
        if self.pending is not None:
            self.superseded += 1
        self.pending = item
        return None

    def poll(self, now: float) -> Any:
        """The waiting item if its time has come, else None."""
        if self.pending is None or now < self.next_ok:
            return None
        item, self.pending = self.pending, None
        self.next_ok = now + self.period
        return item

    def due(self) -> float | None:
        """When the waiting item may go (None: nothing waits)."""
        return None if self.pending is None else self.next_ok

    def idle(self, now: float) -> bool:
        """Nothing waits and the next item may go at once: a new throttle would do the same, so this one can be
        forgotten without letting anything through sooner or losing anything."""
        return self.pending is None and now >= self.next_ok


class RateLimits:
    """At most one item per ``1/max_hz`` per key (MQTT input: a flooding sensor), for at most ``max_keys`` keys at
    a time. A key's limit is forgotten only once its window has passed: forgetting it sooner (least recently used)
    let a flood over more robots than the table holds reset every robot's limit, and every message passed. While
    ``max_keys`` keys are within their window a new key is refused like an excess item, so a mapping puts at most
    ``max_keys * max_hz`` a second whatever the number of topics.

    :meth:`ready` only asks (the adapter asks before it parses, so an excess message costs no parsing), and
    :meth:`take` spends the key's turn (only a valid item does: garbage does not use up a sensor's turn)."""

    def __init__(self, max_hz: float, max_keys: int) -> None:
        self.period = 1.0 / max_hz
        self.max_keys = max_keys
        self._next_ok: OrderedDict[str, float] = OrderedDict()  # in the order turns were taken: soonest free first

    def __len__(self) -> int:
        return len(self._next_ok)

    def ready(self, key: str, now: float) -> bool:
        """Whether an item of ``key`` may go now (nothing is spent)."""
        if key in self._next_ok:
            return now >= self._next_ok[key]
        self._forget_past(now)
        return len(self._next_ok) < self.max_keys

    def take(self, key: str, now: float) -> bool:
        """Spend ``key``'s turn if it may go now; False (nothing spent) otherwise."""
        if not self.ready(key, now):
            return False
        self._next_ok[key] = now + self.period
        self._next_ok.move_to_end(key)
        return True

    def _forget_past(self, now: float) -> None:
        while self._next_ok and next(iter(self._next_ok.values())) <= now:
            self._next_ok.popitem(last=False)


__all__ = [
    "MAX_KEYS", "Direction", "InRoute", "KeyTemplate", "LatestThrottle", "MappingError", "OutRoute", "RateLimits",
    "Refused", "Route", "TopicTemplate", "binary_fields", "bridge_channel", "channel_of", "check_bridge_key",
    "check_routes", "compile_route", "max_packet_size", "to_json",
]
