"""The console's settings (the ``console:`` section of configs/operator.yaml). No UI imports here."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from iorthand.config import setting
from iorthand_operator.link import STATE_STALE_S, LinkThresholds


@dataclass
class ConsoleSettings:
    input: str = setting("keyboard", choices=("keyboard", "gamepad"))
    keymap: str = setting("", help="keymap name (configs/keymap-<name>.yaml) or file; empty: built-in default")
    gamepad: Path | None = setting(None, help="gamepad mapping YAML (configs/gamepad-*.yaml)")
    profiles: list[str] = field(default_factory=lambda: ["remote", "local"])  # cycled by profile_next
    force_stale_after: float = setting(0.5, lo=0.05, hi=10.0, help="s without a force_level message → stale")
    state_stale_after: float = setting(STATE_STALE_S, lo=0.05, hi=10.0,
                                       help="s without robot state → no data (and a dead downlink in the link figures)")
    link: LinkThresholds = field(default_factory=LinkThresholds)
    link_window: float = setting(5.0, lo=0.5, hi=120.0, help="s of history behind the link figures")
    input_hz: float = setting(50.0, lo=5.0, hi=500.0, help="how often the input device is polled")
    refresh_hz: float = setting(10.0, lo=1.0, hi=60.0, help="screen refresh rate")
    pan_tilt_step_deg: float = setting(5.0, lo=0.1, hi=45.0)

    def check(self) -> None:
        if self.input == "gamepad" and self.gamepad is None:
            raise ValueError("gamepad: input is 'gamepad' but no gamepad mapping file is given")
        if not self.profiles:
            raise ValueError("profiles: list at least one speed profile")
