"""Input devices behind one interface (:class:`InputDevice`): keyboard and SDL gamepads."""

from iorthand_operator.inputs.base import ACTIONS, TWIST_AXES, InputDevice, InputSample
from iorthand_operator.inputs.keyboard import KeyboardInput, KeymapConfig, load_keymap
from iorthand_operator.inputs.mapping import AxisMap, GamepadConfig, map_gamepad, shape_axis

__all__ = [
    "ACTIONS",
    "TWIST_AXES",
    "AxisMap",
    "GamepadConfig",
    "InputDevice",
    "InputSample",
    "KeyboardInput",
    "KeymapConfig",
    "load_keymap",
    "map_gamepad",
    "shape_axis",
]
