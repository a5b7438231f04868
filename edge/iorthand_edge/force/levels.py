"""Force warning levels: thresholds with hysteresis, and staleness. Pure logic, no I/O, explicit times.

Levels are :class:`iorthand.protocol.ForceLevel` (0 safe, 1 caution, 2 danger), defined once in the protocol.
A level is *entered* when the quantity reaches its threshold and *left* only when the quantity falls below
the threshold minus the hysteresis, so a force hovering around a threshold does not make the level flicker.
A sensor with no sample for ``stale_after`` seconds is stale: its level means nothing any more.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from iorthand.config import setting
from iorthand.protocol import ForceLevel

QUANTITIES = ("fz", "norm")


@dataclass
class LevelConfig:
    quantity: str = setting("fz", choices=QUANTITIES, help="fz: |Fz| in the sensor frame; norm: |F|")
    caution: float = setting(6.0, lo=0.0, hi=1000.0, help="N: level 1 (yellow) from here")
    danger: float = setting(8.0, lo=0.0, hi=1000.0, help="N: level 2 (red) from here")
    hysteresis: float = setting(0.5, lo=0.0, hi=100.0, help="N below a threshold before its level is left")
    stale_after: float = setting(0.1, lo=0.005, hi=5.0, help="s without a sample → stale")

    def check(self) -> None:
        if not 0.0 < self.caution < self.danger:
            raise ValueError(f"expected 0 < caution < danger, got caution {self.caution} and danger {self.danger}")
        if self.hysteresis >= self.danger - self.caution or self.hysteresis >= self.caution:
            # Otherwise leaving danger could skip caution, or caution could never be left.
            raise ValueError(
                f"hysteresis {self.hysteresis} N must be smaller than caution ({self.caution} N) "
                f"and than danger − caution ({self.danger - self.caution:g} N)"
            )

    @property
    def thresholds(self) -> tuple[float, float]:
        return (self.caution, self.danger)


def quantity_value(wrench: ArrayLike, quantity: str) -> float:
    """The number compared with the thresholds: |Fz| or the norm of the force, N. Given several wrenches
    (one per row), the largest of them: a peak between two ticks counts. NaN anywhere gives NaN."""
    w = np.asarray(wrench, dtype=float)
    if quantity == "fz" and w.shape == (6,):  # one sample, the usual case (np.max on one value costs ~10 µs)
        return abs(float(w[2]))
    w = np.atleast_2d(w)
    if quantity == "fz":
        return float(np.max(np.abs(w[:, 2])))
    if quantity == "norm":
        return float(np.max(np.linalg.norm(w[:, :3], axis=1)))
    raise ValueError(f"unknown force quantity {quantity!r} (expected one of {QUANTITIES})")


def next_level(current: ForceLevel, value: float, config: LevelConfig) -> ForceLevel:
    """The level after observing ``value`` while at ``current``.

    Level i (1 or 2) holds if ``value ≥ threshold_i`` or, when already at or above i, if ``value ≥
    threshold_i − hysteresis``. The result is the highest level that holds.
    """
    if not math.isfinite(value):
        return ForceLevel.DANGER  # a garbage reading must never look safe
    level = ForceLevel.SAFE
    for i, threshold in enumerate(config.thresholds, start=1):
        keep = threshold - config.hysteresis if current >= i else threshold
        if value >= keep:
            level = ForceLevel(i)
    return level


@dataclass(frozen=True)
class LevelState:
    level: ForceLevel
    stale: bool
    value: float  # the last quantity value, N (0 before the first sample)
    last_sample: float  # monotonic time of the last sample (−inf: none yet)


class LevelTracker:
    """The level of one sensor over time. Feed samples with :meth:`add`; ask :meth:`state` at any time."""

    def __init__(self, config: LevelConfig) -> None:
        self.config = config
        self.level = ForceLevel.SAFE
        self.value = 0.0
        self.last_sample = -math.inf

    def add(self, wrench: ArrayLike, now: float) -> ForceLevel:
        """One tick's sample: a wrench, or every wrench since the last tick (n×6; the peak decides)."""
        self.value = quantity_value(wrench, self.config.quantity)
        self.level = next_level(self.level, self.value, self.config)
        self.last_sample = now
        return self.level

    def stale(self, now: float) -> bool:
        return now - self.last_sample > self.config.stale_after

    def state(self, now: float) -> LevelState:
        return LevelState(self.level, self.stale(now), self.value, self.last_sample)
