"""Servo and torch decisions: validation, clamping to the configured range, rate limiting, angle history.
Pure (explicit times, no I/O); the units in :mod:`.units` drive the hardware with what this decides.

Angles here are the servo's own angle in radians (home π/2 by default): the same number the hardware is
sent (in degrees) and that ``state/servo`` and :meth:`AngleHistory.at` report, so the perception chain's
mount geometry is expressed against it. Hobby servos do not report their position: the "current" angle is
the rate-limited command, which the servo follows within its own speed.
"""

from __future__ import annotations

import bisect
import math
import threading
from dataclasses import dataclass
from typing import Any

from iorthand_edge.actuators.config import ServoAxisConfig, ServosConfig, TorchConfig

AXES = ("pan", "tilt")


def check_angle(name: str, value: Any) -> float | None:
    """A commanded angle (rad) or None (keep the target); raise TypeError/ValueError naming the axis."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"servo {name}: expected an angle in radians (a number), got {type(value).__name__}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"servo {name}: angle must be finite, got {value}")
    return value


@dataclass(frozen=True)
class AxisLimits:
    lo: float  # rad
    hi: float
    home: float

    @classmethod
    def from_config(cls, c: ServoAxisConfig) -> AxisLimits:
        return cls(math.radians(c.min_deg), math.radians(c.max_deg), math.radians(c.home_deg))


@dataclass(frozen=True)
class ServoOutcome:
    pan_target: float
    tilt_target: float
    clamped: bool
    reason: str


class ServoController:
    def __init__(self, config: ServosConfig) -> None:
        self.limits = {"pan": AxisLimits.from_config(config.pan), "tilt": AxisLimits.from_config(config.tilt)}
        self.max_rate = math.radians(config.max_rate_deg_s)
        self.target = {a: self.limits[a].home for a in AXES}
        self.current = dict(self.target)
        self._last_step: float | None = None

    def command(self, pan: Any = None, tilt: Any = None, now: float | None = None) -> ServoOutcome:
        """Set new targets (None keeps an axis). Out-of-range angles are clamped and the reason says so.

        ``now`` (monotonic s): when the command arrived. Servos at rest start moving from then, not from their
        last step, which may be long ago (the unit does not step servos at rest)."""
        values = {"pan": check_angle("pan", pan), "tilt": check_angle("tilt", tilt)}  # validate both first
        if now is not None and not self.moving:
            self._last_step = now
        notes = []
        for axis, value in values.items():
            if value is None:
                continue
            lim = self.limits[axis]
            clamped = min(lim.hi, max(lim.lo, value))
            if clamped != value:
                notes.append(
                    f"{axis} {math.degrees(value):.1f}° clamped to {math.degrees(clamped):.1f}° "
                    f"(range {math.degrees(lim.lo):.0f}–{math.degrees(lim.hi):.0f}°)"
                )
            self.target[axis] = clamped
        return ServoOutcome(self.target["pan"], self.target["tilt"], bool(notes), "; ".join(notes))

    def home(self) -> ServoOutcome:
        return self.command(self.limits["pan"].home, self.limits["tilt"].home)

    def step(self, now: float) -> bool:
        """Move the current angles toward the targets at most ``max_rate``; True if anything moved."""
        dt = 0.0 if self._last_step is None else max(0.0, now - self._last_step)
        self._last_step = now
        moved = False
        for axis in AXES:
            delta = self.target[axis] - self.current[axis]
            if delta == 0.0:
                continue
            step = self.max_rate * dt
            self.current[axis] = self.target[axis] if abs(delta) <= step else self.current[axis] + math.copysign(step, delta)
            moved = moved or step > 0
        return moved

    @property
    def moving(self) -> bool:
        """Whether an axis is still on its way to its target."""
        return any(self.current[a] != self.target[a] for a in AXES)

    @property
    def angles(self) -> tuple[float, float]:
        return self.current["pan"], self.current["tilt"]


class AngleHistory:
    """(pan, tilt) over the last ``span_s``, interpolated at any time: a camera frame is chained with the
    angles at its capture time. Thread-safe (the servo worker adds, perception reads)."""

    def __init__(self, span_s: float, initial: tuple[float, float]) -> None:
        self._span_ns = int(span_s * 1e9)
        self._times: list[int] = []
        self._values: list[tuple[float, float]] = []
        self._initial = initial
        self._lock = threading.Lock()

    def add(self, t_ns: int, angles: tuple[float, float]) -> None:
        with self._lock:
            if self._times and t_ns <= self._times[-1]:
                return  # the clock stepped back: keep the history ordered
            self._times.append(t_ns)
            self._values.append(angles)
            drop = bisect.bisect_left(self._times, t_ns - self._span_ns)
            if drop > 1:  # keep one older sample so the oldest moment in the span can be bracketed
                del self._times[: drop - 1]
                del self._values[: drop - 1]

    def at(self, t_ns: int) -> tuple[float, float]:
        """The angles at ``t_ns``: interpolated inside the history, the newest after it, the oldest before it
        (servos hold their position between commands, so both ends are the truth, not a guess)."""
        with self._lock:
            if not self._times:
                return self._initial
            if t_ns >= self._times[-1]:
                return self._values[-1]
            i = bisect.bisect_right(self._times, t_ns)
            if i == 0:
                return self._values[0]
            t0, t1 = self._times[i - 1], self._times[i]
            (p0, q0), (p1, q1) = self._values[i - 1], self._values[i]
        s = (t_ns - t0) / (t1 - t0)
        return p0 + (p1 - p0) * s, q0 + (q1 - q0) * s


@dataclass(frozen=True)
class TorchOutcome:
    on: bool
    brightness: float
    reason: str

    @property
    def output(self) -> float:
        """The PWM level to drive."""
        return self.brightness if self.on else 0.0


def torch_command(config: TorchConfig, on: Any, brightness: Any) -> TorchOutcome:
    if not isinstance(on, bool):
        raise TypeError(f"torch on: expected true or false, got {type(on).__name__}")
    if isinstance(brightness, bool) or not isinstance(brightness, (int, float)):
        raise TypeError(f"torch brightness: expected a number in [0, 1], got {type(brightness).__name__}")
    b = float(brightness)
    if not math.isfinite(b):
        raise ValueError(f"torch brightness must be finite, got {b}")
    capped = min(config.max_brightness, max(0.0, b))
    reason = "" if capped == b else f"brightness {b:.2f} clamped to {capped:.2f} (range 0–{config.max_brightness:.2f})"
    return TorchOutcome(on, capped, reason)
