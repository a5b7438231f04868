"""The one interface every input device implements, and the names it speaks in.

A device is polled (``poll(now)``) by the console's input thread; it returns an :class:`InputSample`: the
twist it asks for (SI units: m/s, rad/s, base frame), whether its deadman is held, whether the device is
connected at all, and the actions triggered since the last poll. The sender thread never waits for a device:
it sends whatever the last poll set, at its own fixed rate.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

# The six twist components, in the order of the wire's [linear, angular].
TWIST_AXES = ("linear_x", "linear_y", "linear_z", "angular_x", "angular_y", "angular_z")

# Everything an input may trigger besides motion. The console maps each to a client call.
ACTIONS = (
    "estop",  # cmd/stop
    "acquire",  # ask for control again (after a refusal or a lost lease)
    "profile_next",  # cycle the speed profile (within the edge's profiles)
    "pan_left",
    "pan_right",
    "tilt_up",
    "tilt_down",
    "camera_center",
    "torch",  # toggle
    "frame_toggle",  # twists in the base frame ⇄ in the probe's frame about its tip
    "contact_toggle",  # contact mode on (the edge holds the force along the probe) ⇄ off
    "poses",  # open the safety-pose list
    "quit",
)


@dataclass
class InputSample:
    twist: np.ndarray = field(default_factory=lambda: np.zeros(6))  # m/s, rad/s
    deadman: bool = False
    connected: bool = True
    status: str = ""  # shown next to the device: "gamepad unplugged", "deadman expires in 3 s", ...
    actions: list[str] = field(default_factory=list)


class InputDevice(ABC):
    """A source of twists, a deadman and actions. Implementations are thread-safe for ``poll``."""

    name: str = "input"

    @abstractmethod
    def poll(self, now: float) -> InputSample:
        """The current command at monotonic time ``now`` and the actions since the last poll."""

    def close(self) -> None:  # noqa: B027 (optional hook)
        """Release the device."""

    # Whether the deadman stays on by itself once pressed (a toggle key) rather than only while held.
    deadman_toggles: bool = False

    def release_deadman(self) -> None:  # noqa: B027 (a held control has nothing to forget)
        """Forget a deadman the device keeps on by itself (a toggle): after an e-stop or a halt, only a new
        press may count as the operator's intent. A held button or key needs no forgetting: it is let go."""

    def warnings(self) -> list[str]:
        """What in the device's configuration does nothing (the console shows each in its log at start)."""
        return []

    def control_name(self, binding: str) -> str:
        """What the operator presses for ``binding`` ("deadman", "acquire", ...), as the screen names it."""
        return binding

    @staticmethod
    def idle(status: str, connected: bool = True, actions: list[str] | None = None) -> InputSample:
        """No motion, no deadman: what a device returns whenever it cannot vouch for the operator."""
        return InputSample(np.zeros(6), False, connected, status, actions or [])
