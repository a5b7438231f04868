"""What a page may send to the web console's server: parsed and checked here, pure.

A page message is one JSON object with a ``type``. Every problem raises :class:`PageError` with a reason the page
shows (the field that was wrong and what was expected); nothing that fails here reaches Zenoh.

The twist is what the page sends ``twist_hz`` times a second (the server's setting, in its hello) from its timer
while it is open, deadman held or not: one message, one command (the server never repeats, stores or invents one).
:class:`TwistBudget` bounds how fast a page may send them. Velocities are SI (m/s, rad/s) in the
robot's base frame; the edge clips them to its limits. ``seen`` is the source time (ns) of the newest robot state
the page has drawn, so the edge can refuse motion from a screen that shows an old picture.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

from iorthand.protocol import TWIST_FRAMES

# A twist is ~150 bytes; the largest legitimate message is a goto with its token.
MAX_MESSAGE_BYTES = 2048
MAX_SPEED = 1.0  # m/s or rad/s: anything faster is not a joystick (the edge's limits are far below)
NAME_MAX = 64


class PageError(ValueError):
    """A page message that is not valid; the text says what was wrong."""


@dataclass(frozen=True)
class Twist:
    id: int
    linear: tuple[float, float, float]
    angular: tuple[float, float, float]
    deadman: bool
    seen: int  # ns: the newest robot state drawn (0: none)
    frame: str = "base"  # or "tool": the probe's frame about its tip


@dataclass(frozen=True)
class Control:
    """acquire (``profile``: "" or a speed profile), release, stop, poses."""

    verb: str
    profile: str = ""


@dataclass(frozen=True)
class Pose:
    """preview a named pose, or goto it with the preview's token."""

    verb: str
    name: str
    token: str = ""


@dataclass(frozen=True)
class Camera:
    """servo steps (rad) and the torch."""

    pan: float = 0.0
    tilt: float = 0.0
    torch: bool | None = None


@dataclass(frozen=True)
class View:
    """What the page wants pushed: video or not (a slow link, a phone saving its battery)."""

    video: bool


PageMessage = Twist | Control | Pose | Camera | View
CONTROL_VERBS = ("acquire", "release", "stop", "poses", "contact_on", "contact_off")


def parse(data: str | bytes) -> PageMessage:
    if len(data) > MAX_MESSAGE_BYTES:
        raise PageError(f"message of {len(data)} bytes exceeds {MAX_MESSAGE_BYTES}")
    try:
        obj = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise PageError(f"not JSON ({type(exc).__name__})") from None
    except RecursionError:  # ~1 000 nested brackets fit in MAX_MESSAGE_BYTES
        raise PageError("JSON nested too deeply") from None
    if not isinstance(obj, dict):
        raise PageError(f"expected a JSON object, got {type(obj).__name__}")
    kind = obj.get("type")
    if kind == "twist":
        _only(obj, {"type", "id", "linear", "angular", "deadman", "seen", "frame"})
        frame = obj.get("frame", "base")
        if frame not in TWIST_FRAMES:
            raise PageError(f"frame: expected one of {', '.join(TWIST_FRAMES)}, got {str(frame)[:20]!r}")
        return Twist(_int(obj, "id"), _vec3(obj, "linear"), _vec3(obj, "angular"), _bool(obj, "deadman"),
                     _int(obj, "seen"), frame)
    if kind in CONTROL_VERBS:
        _only(obj, {"type", "profile"})
        return Control(kind, _name(obj, "profile", required=False))
    if kind in ("preview", "goto"):
        _only(obj, {"type", "name", "token"})
        token = _text(obj, "token", 128) if kind == "goto" else ""
        return Pose(kind, _name(obj, "name"), token)
    if kind == "view":
        _only(obj, {"type", "video"})
        return View(_bool(obj, "video"))
    if kind == "camera":
        _only(obj, {"type", "pan", "tilt", "torch"})
        torch = obj.get("torch")
        if torch is not None and not isinstance(torch, bool):
            raise PageError("torch: expected true, false or nothing")
        pan, tilt = (_number(obj, k, math.pi / 2) if k in obj else 0.0 for k in ("pan", "tilt"))
        return Camera(pan, tilt, torch)
    raise PageError(f"type: unknown message type {str(kind)[:30]!r}")


class RateBudget:
    """A token bucket: ``rate`` a second on average, ``burst`` at once. Pure: the caller gives the time."""

    def __init__(self, rate: float, burst: float) -> None:
        self.rate, self.burst = rate, burst
        self._tokens = burst
        self._at = -math.inf

    def _refill(self, now: float) -> None:
        self._tokens = min(self.burst, self._tokens + (now - self._at) * self.rate)
        self._at = now

    def allow(self, now: float) -> bool:
        """Whether one more passes now (if not, it is not counted)."""
        self._refill(now)
        if self._tokens < 1.0:
            return False
        self._tokens -= 1.0
        return True

    def delay(self, now: float) -> float:
        """Take one, and say how long to wait before it conforms (0: at once): a pace, nothing refused."""
        self._refill(now)
        self._tokens -= 1.0
        return max(0.0, -self._tokens / self.rate)


class TwistBudget:
    """How many twists a page may have forwarded: ``twist_hz`` a second on average with a quarter second's worth
    at once, both twice what a well-behaved page sends (a busy browser runs late timer ticks close together). A
    page that sends faster, a hostile script or a broken one, has the excess dropped, which bounds what it can
    push through the server to the edge. The first release after a held twist always passes: letting go must
    reach the robot."""

    def __init__(self, twist_hz: float) -> None:
        self.rate = 2.0 * twist_hz
        self._bucket = RateBudget(self.rate, 0.25 * self.rate)
        self._held = False  # the deadman of the last twist forwarded

    def allow(self, twist: Twist, now: float) -> bool:
        """Whether ``twist``, arriving at ``now`` (s, monotonic), is forwarded."""
        if not self._bucket.allow(now) and (twist.deadman or not self._held):
            return False
        self._held = twist.deadman
        return True


class Notices:
    """Which refusals to say to a page: each text at most once a second, and at most ``remember`` texts
    remembered (a refusal's text may quote the page's own message: a page sending a million different ones grew
    the table by 155 MiB)."""

    def __init__(self, remember: int = 256) -> None:
        self.remember = remember
        self._said: dict[str, float] = {}

    def due(self, text: str, now: float) -> bool:
        if now - self._said.get(text, -math.inf) < 1.0:
            return False
        if len(self._said) >= self.remember and text not in self._said:
            self._said = {t: at for t, at in self._said.items() if now - at < 1.0}  # the others are due anyway
            if len(self._said) >= self.remember:
                return False  # hundreds of different refusals within a second: the page is told of them later
        self._said[text] = now
        return True


class PageBudgets:
    """What one page may push through the server, beyond the twists' own :class:`TwistBudget`:

    - ``reading``: the server reads at most 500 messages a second from a page (8 times what the console sends)
      and waits before reading more: a page that floods (a script, a broken one) is slowed to that pace, at no
      cost to the other pages (a viewer's flood of 50 000 a second held up the driving page's twists by 0.6 s);
    - ``camera``: servo steps and torch switches, 20 a second (a held button repeats at 10);
    - ``stops``: a stop is forwarded at once, and then at most 5 a second (the edge holds a stop until the
      deadman is released; repeating it a thousand times adds nothing but load).
    """

    READ_HZ = 500.0
    CAMERA_HZ = 20.0
    STOP_HZ = 5.0

    def __init__(self) -> None:
        self.reading = RateBudget(self.READ_HZ, 0.5 * self.READ_HZ)
        self.camera = RateBudget(self.CAMERA_HZ, self.CAMERA_HZ)
        self.stops = RateBudget(self.STOP_HZ, 1.0)


def _only(obj: dict[str, Any], allowed: set[str]) -> None:
    extra = set(obj) - allowed
    if extra:
        raise PageError(f"{sorted(extra)[0][:30]}: unknown field of a {obj['type']} message")


def _int(obj: dict[str, Any], name: str) -> int:
    v = obj.get(name)
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < 2**63:
        raise PageError(f"{name}: expected a whole number ≥ 0, got {v!r:.30}")
    return v


def _bool(obj: dict[str, Any], name: str) -> bool:
    v = obj.get(name)
    if not isinstance(v, bool):
        raise PageError(f"{name}: expected true or false, got {v!r:.30}")
    return v


def _number(obj: dict[str, Any], name: str, limit: float) -> float:
    v = obj.get(name)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or abs(v) > limit:
        raise PageError(f"{name}: expected a finite number within ±{limit:g}, got {v!r:.30}")
    return float(v)


def _vec3(obj: dict[str, Any], name: str) -> tuple[float, float, float]:
    v = obj.get(name)
    if not isinstance(v, list) or len(v) != 3:
        raise PageError(f"{name}: expected 3 numbers")
    x, y, z = (_number({name: e}, name, MAX_SPEED) for e in v)
    return x, y, z


def _text(obj: dict[str, Any], name: str, max_len: int, required: bool = True) -> str:
    v = obj.get(name, None if required else "")
    if not isinstance(v, str) or len(v) > max_len:
        raise PageError(f"{name}: expected text of at most {max_len} characters")
    return v


def _name(obj: dict[str, Any], name: str, required: bool = True) -> str:
    v = _text(obj, name, NAME_MAX, required)
    if required and not v:
        raise PageError(f"{name}: must not be empty")
    return v


__all__ = ["MAX_MESSAGE_BYTES", "Camera", "Control", "PageError", "PageMessage", "Pose", "Twist", "TwistBudget", "View", "parse"]
