"""Axis shaping for joysticks, as in ROS's teleop_twist_joy: deadband, expo curve, scale, invert. Pure.

``shape_axis`` maps a raw axis value (−1…1) to a command: inverted if asked, zero inside the deadband, then
rescaled so the output starts at 0 at the deadband's edge (no jump), bent by the expo curve
(``(1−e)·x + e·x³``: fine control near the centre, full speed at the end), then multiplied by ``scale``
(m/s or rad/s at full deflection).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from iorthand.config import setting
from iorthand_operator.inputs.base import ACTIONS, TWIST_AXES


@dataclass
class AxisMap:
    axis: int = setting(0, lo=0, hi=63, help="SDL axis index")
    scale: float = setting(0.005, lo=0.0, hi=10.0, help="m/s or rad/s at full deflection")
    deadband: float = setting(0.1, lo=0.0, hi=0.95)
    expo: float = setting(0.0, lo=0.0, hi=1.0, help="0 linear, 1 cubic")
    invert: bool = False


@dataclass
class GamepadConfig:
    """A gamepad mapping (configs/gamepad-*.yaml). Buttons and axes are SDL indices."""

    name: str = "gamepad"
    device: int = setting(0, lo=0, hi=15, help="SDL device index")
    enable_button: int = setting(4, lo=0, hi=63, help="deadman: motion only while held")
    turbo_button: int | None = setting(None, lo=0, hi=63)
    turbo_factor: float = setting(2.0, lo=1.0, hi=10.0, help="scale multiplier while turbo is held")
    axes: dict[str, AxisMap] = field(default_factory=dict)  # twist component → axis mapping
    buttons: dict[str, int] = field(default_factory=dict)  # action → button index
    hat: int | None = setting(0, lo=0, hi=7, help="hat for camera pan (x) and tilt (y); null: none")

    def check(self) -> None:
        # One control, one meaning: a stick on two twist components moves the tool diagonally when it is pushed
        # straight, a turbo on the enable button doubles every motion the deadman allows, and a button with two
        # meanings does both (an e-stop on the torch button stops the robot whenever the torch is switched).
        by_axis: dict[int, str] = {}
        for name, m in self.axes.items():
            if name not in TWIST_AXES:
                raise ValueError(f"axes.{name}: unknown twist component (expected one of {list(TWIST_AXES)})")
            if m.axis in by_axis:
                raise ValueError(f"axes.{name}: axis {m.axis} already drives {by_axis[m.axis]}: one axis, one twist "
                                 "component")
            by_axis[m.axis] = name
        by_button: dict[int, str] = {self.enable_button: "the enable (deadman) button"}
        if self.turbo_button is not None:
            if self.turbo_button == self.enable_button:
                raise ValueError(f"turbo_button: button {self.turbo_button} is the enable (deadman) button: every "
                                 "motion would be at turbo speed")
            by_button[self.turbo_button] = "the turbo button"
        for action, button in self.buttons.items():
            if action not in ACTIONS:
                raise ValueError(f"buttons.{action}: unknown action (expected one of {list(ACTIONS)})")
            if not isinstance(button, int) or not 0 <= button < 64:
                raise ValueError(f"buttons.{action}: expected a button index 0–63, got {button!r}")
            if button in by_button:
                raise ValueError(f"buttons.{action}: button {button} is {by_button[button]}")
            by_button[button] = f"already {action!r}"
        if not self.axes:
            raise ValueError("axes: map at least one twist component to an axis")


def shape_axis(raw: float, m: AxisMap) -> float:
    if not math.isfinite(raw):
        return 0.0
    x = max(-1.0, min(1.0, float(raw)))
    if m.invert:
        x = -x
    mag = abs(x)
    if mag <= m.deadband:
        return 0.0
    y = (mag - m.deadband) / (1.0 - m.deadband)
    y = (1.0 - m.expo) * y + m.expo * y**3
    return math.copysign(y * m.scale, x)


def map_gamepad(axes: dict[int, float], buttons: set[int], cfg: GamepadConfig) -> tuple[np.ndarray, bool]:
    """Raw axis values and held buttons → (twist, deadman). Without the enable button: zero, no deadman."""
    if cfg.enable_button not in buttons:
        return np.zeros(6), False
    factor = cfg.turbo_factor if cfg.turbo_button is not None and cfg.turbo_button in buttons else 1.0
    twist = np.zeros(6)
    for i, name in enumerate(TWIST_AXES):
        m = cfg.axes.get(name)
        if m is not None:
            twist[i] = shape_axis(axes.get(m.axis, 0.0), m) * factor
    return twist, True
