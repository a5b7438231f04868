"""The session report's mathematics, free of I/O: contact time, warning edges, the performance index.

The index follows the tele-echography reference: ψ = τ / t_t (a fraction), Ω = 4·ω_R + ω_Y, and
φ = α·ψ − β·Ω / (1 − ψ), in percent with α = 230, β = 0.25. The units were pinned with the reference's
published rows: t_t = 180.67 s, τ = 55.88 s, ω_R = 6, ω_Y = 15 gives ψ = 0.3093 and φ = 71.14 − 14.12 =
57.02 %; t_t = 130.46 s, τ = 51.22 s, ω_R = 0, ω_Y = 4 gives φ = 88.65 % (88.66 published). With ψ in percent
neither row comes out.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

_Timed = TypeVar("_Timed", bound=tuple[Any, ...])  # a sample whose first item is its time, s

ALPHA = 230.0
BETA = 0.25


@dataclass(frozen=True)
class PerformanceIndex:
    t_t: float  # teleoperation time, s
    tau: float  # body-contact time, s
    omega_R: float  # danger warnings (rising edges into level 2)
    omega_Y: float  # caution warnings (rising edges into level 1)
    alpha: float = ALPHA
    beta: float = BETA

    @property
    def psi(self) -> float:
        """Contact ratio τ / t_t (a fraction; NaN without teleoperation time)."""
        return self.tau / self.t_t if self.t_t > 0 else math.nan

    @property
    def omega(self) -> float:
        return 4.0 * self.omega_R + self.omega_Y

    @property
    def phi(self) -> float:
        """φ in percent; −inf when the probe was in contact the whole time (ψ = 1), NaN without t_t."""
        psi = self.psi
        if math.isnan(psi):
            return math.nan
        if psi >= 1.0:
            return -math.inf if self.omega > 0 else self.alpha * psi
        return self.alpha * psi - self.beta * self.omega / (1.0 - psi)

    def as_dict(self) -> dict[str, float]:
        return {"t_t": self.t_t, "tau": self.tau, "psi": self.psi, "omega_R": self.omega_R,
                "omega_Y": self.omega_Y, "Omega": self.omega, "phi": self.phi, "alpha": self.alpha,
                "beta": self.beta}


def force_value(force: Sequence[float], quantity: str) -> float:
    """The scalar compared with the thresholds: the force's norm, its z component, or |z|."""
    if quantity == "norm":
        return math.sqrt(sum(f * f for f in force[:3]))
    if quantity == "fz":
        return float(force[2])
    if quantity == "abs_fz":
        return abs(float(force[2]))
    raise ValueError(f"unknown force quantity {quantity!r} (norm, fz, abs_fz)")


def contact_time(samples: Sequence[tuple[float, float]], threshold: float, max_gap: float) -> float:
    """Seconds during which the force was above ``threshold``. Each sample (t s, value) holds until the next
    one, up to ``max_gap`` (a silent sensor is not evidence of contact); the last sample holds for the median
    sample period."""
    if not samples:
        return 0.0
    total = 0.0
    dts = [b[0] - a[0] for a, b in itertools.pairwise(samples)]
    typical = sorted(dts)[(len(dts) - 1) // 2] if dts else 0.0
    for i, (_t, value) in enumerate(samples):
        if value > threshold:
            dt = dts[i] if i < len(dts) else typical
            total += min(max(dt, 0.0), max_gap)
    return total


def levels_from_force(samples: Iterable[tuple[float, float]], caution: float, danger: float,
                      hysteresis: float) -> list[tuple[float, int]]:
    """Warning levels (0/1/2) from force values with hysteresis: a level is entered above its threshold and
    left below threshold − hysteresis (used when the session has no recorded ``state/force_level``)."""
    out: list[tuple[float, int]] = []
    level = 0
    for t, v in samples:
        if v > danger or (level == 2 and v >= danger - hysteresis):
            level = 2
        elif v > caution or (level >= 1 and v >= caution - hysteresis):
            level = 1
        else:
            level = 0
        out.append((t, level))
    return out


def warning_edges(levels: Iterable[tuple[float, int, bool]]) -> tuple[int, int, list[tuple[float, int]]]:
    """(ω_R, ω_Y, edges) from (t, level, stale) samples. A rising edge into level k is a change from a level
    below k to exactly k: 0→1 counts one caution, 1→2 and 0→2 one danger each, 2→1 nothing (it is a falling
    edge). Stale samples carry no level and are skipped, so a sensor dropout does not invent warnings."""
    red = yellow = 0
    prev = 0
    edges: list[tuple[float, int]] = []
    for t, level, stale in levels:
        if stale:
            continue
        if level == 2 and prev < 2:
            red += 1
            edges.append((t, 2))
        elif level == 1 and prev < 1:
            yellow += 1
            edges.append((t, 1))
        prev = level
    return red, yellow, edges


def rising_edges(states: Iterable[tuple[float, str]], targets: set[str]) -> list[float]:
    """Times at which the state entered one of ``targets`` (from a state outside them)."""
    out: list[float] = []
    inside = False
    for t, s in states:
        now = s in targets
        if now and not inside:
            out.append(t)
        inside = now
    return out


def teleoperation_window(commands: Sequence[tuple[float, bool]]) -> tuple[float, float] | None:
    """From the first to the last command sent with the deadman held (None without two of them)."""
    held = [t for t, deadman in commands if deadman]
    return (held[0], held[-1]) if len(held) >= 2 else None


def teleoperation_time(commands: Sequence[tuple[float, bool]]) -> float:
    """t_t: from the first to the last command sent with the deadman held, s (0 if none)."""
    window = teleoperation_window(commands)
    return window[1] - window[0] if window else 0.0


def within(samples: Iterable[_Timed], window: tuple[float, float]) -> list[_Timed]:
    """The samples whose time (their first item) lies in ``window``, bounds included."""
    return [x for x in samples if window[0] <= x[0] <= window[1]]
