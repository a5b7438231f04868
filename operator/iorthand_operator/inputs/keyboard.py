"""The keyboard as an input device (terminal key events, as textual delivers them).

A terminal reports no key *release*: holding a key produces a press, then — after the OS's repeat delay
(typically 250–600 ms) — repeats at 25–40 Hz. So "held" is inferred:

- a key is active from its press for ``initial_hold`` s (covering the repeat delay), and after a repeat for
  ``repeat_hold`` s more; when the repeats stop (the key was released) motion stops within ``repeat_hold``.
- a terminal repeats only the *last* key pressed, so "hold the deadman key and a move key" is impossible
  there. Two deadman modes exist instead:

  * ``toggle`` (default): the deadman key toggles the deadman on/off; it expires on its own
    ``deadman_expire`` s after the last key activity, so a forgotten toggle cannot stay armed.
  * ``motion``: holding any motion key is the deadman (release the key, the robot stops).

Whatever the mode, the edge's rules still apply: no fresh command with the deadman flag for its timeout →
stop. Bindings come from a keymap (configs/keymap*.yaml): key name → ``+linear_x``/``-angular_z``/…, an action
of :data:`ACTIONS`, or ``deadman``. A keymap with an unknown key name or binding fails to load with the key.
"""

from __future__ import annotations

import logging
import re
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from iorthand.config import load, setting
from iorthand_operator.inputs.base import ACTIONS, TWIST_AXES, InputDevice, InputSample

log = logging.getLogger("iorthand.operator.keyboard")

_NAMED_KEYS = {
    "space", "escape", "enter", "tab", "backspace", "delete", "insert", "home", "end", "pageup", "pagedown",
    "up", "down", "left", "right", "plus", "minus", "comma", "full_stop", "slash", "question_mark",
    "left_square_bracket", "right_square_bracket", "semicolon", "apostrophe",
    *(f"f{i}" for i in range(1, 13)),
}
_KEY_RE = re.compile(r"^((ctrl|shift|alt)\+)*(.+)$")
MOTION_BINDINGS = {f"{sign}{axis}" for axis in TWIST_AXES for sign in "+-"}
BINDINGS = MOTION_BINDINGS | set(ACTIONS) | {"deadman"}


def read_time(stamped: float, now: float) -> float:
    """The time to give a key event: when the terminal's input was read (``stamped``: textual stamps each event
    as its input thread parses it, on the monotonic clock), not ``now``, when a UI that stalled got round to it. A
    key pressed and let go during a stall then no longer counts as held for ``initial_hold`` after it. A stamp in
    the future or over a minute old is from some other clock: ``now``."""
    return stamped if now - 60.0 <= stamped <= now else now


def valid_key_name(name: str) -> bool:
    m = _KEY_RE.match(name)
    if not m:
        return False
    base = m.group(3)
    return (len(base) == 1 and base.isprintable() and not base.isspace()) or base in _NAMED_KEYS


DEFAULT_KEYS = {
    "w": "+linear_x", "s": "-linear_x", "a": "+linear_y", "d": "-linear_y", "r": "+linear_z", "f": "-linear_z",
    "i": "+angular_x", "k": "-angular_x", "j": "+angular_y", "l": "-angular_y", "u": "+angular_z",
    "o": "-angular_z",
    "space": "deadman", "x": "estop", "escape": "estop", "e": "acquire", "p": "profile_next", "t": "torch", "b": "frame_toggle", "h": "contact_toggle", "g": "poses", "c": "camera_center",
    "left": "pan_left", "right": "pan_right", "up": "tilt_up", "down": "tilt_down", "q": "quit",
}


@dataclass
class KeymapConfig:
    name: str = "default"
    linear_speed: float = setting(0.005, lo=0.0, hi=1.0, help="m/s per held key")
    angular_speed: float = setting(0.05, lo=0.0, hi=3.0, help="rad/s per held key")
    initial_hold: float = setting(0.6, lo=0.05, hi=2.0, help="s a single press counts as held (repeat delay)")
    repeat_hold: float = setting(0.15, lo=0.03, hi=1.0, help="s a repeat keeps the key held")
    deadman_mode: str = setting("toggle", choices=("toggle", "motion"))
    deadman_expire: float = setting(5.0, lo=0.5, hi=60.0, help="toggle mode: s after the last key activity")
    keys: dict[str, str] = field(default_factory=lambda: dict(DEFAULT_KEYS))

    def check(self) -> None:
        for key, binding in self.keys.items():
            if not valid_key_name(key):
                raise ValueError(f"keys.{key}: not a key name (a character, or one of {sorted(_NAMED_KEYS)})")
            if binding not in BINDINGS:
                raise ValueError(f"keys.{key}: unknown binding {binding!r} (expected ±<axis>, deadman or one of {list(ACTIONS)})")
        if self.deadman_mode == "toggle" and "deadman" not in self.keys.values():
            raise ValueError("keys: toggle deadman mode needs a key bound to 'deadman'")
        if "estop" not in self.keys.values():
            # The console's own stop keys (x, escape) stand in only where the keymap leaves them unbound.
            raise ValueError("keys: no key is bound to 'estop': a console must always be able to stop the robot")

    def warnings(self) -> list[str]:
        """What in this keymap does nothing, said so (not refused: a keymap that sets deadman_mode: motion and
        keeps the default keys has space bound to deadman)."""
        if self.deadman_mode != "motion":
            return []
        return [f"keymap {self.name!r}: key {key!r} is bound to 'deadman', which does nothing with deadman_mode: "
                f"motion (holding a move key is the deadman there); bind it to something else or remove it"
                for key, binding in self.keys.items() if binding == "deadman"]


def load_keymap(spec: str | None, search_dir: Path | None = None) -> KeymapConfig:
    """A keymap by file path or by name (``configs/keymap-<name>.yaml``); None → the built-in default.
    An unknown name fails with the names that exist."""
    if not spec or spec == "default":
        return KeymapConfig()
    path = Path(spec)
    if not path.suffix and search_dir is not None:
        path = search_dir / f"keymap-{spec}.yaml"
    if not path.exists():
        known = sorted(p.stem.removeprefix("keymap-") for p in search_dir.glob("keymap-*.yaml")) if search_dir else []
        names = ", ".join(sorted({"default", *known}))
        raise FileNotFoundError(f"unknown key map {spec!r}: no file {path} (known: {names})")
    config = load(path, KeymapConfig)
    for warning in config.warnings():
        log.warning("%s: %s", path, warning)
    return config


class KeyboardInput(InputDevice):
    """Fed by ``key(name, now)`` from the UI thread; polled by the input thread."""

    def __init__(self, config: KeymapConfig | None = None) -> None:
        self.config = config or KeymapConfig()
        self.name = f"keyboard ({self.config.name}, deadman {self.config.deadman_mode})"
        self._lock = threading.Lock()
        self._held_until: dict[str, float] = {}  # motion binding → monotonic time it stops counting as held
        self._last_event: dict[str, float] = {}
        self._deadman_on = False
        self._deadman_until = 0.0
        self._actions: list[str] = []

    def key(self, name: str, now: float) -> bool:
        """A key event; returns whether the key is bound (unbound keys are left to the UI)."""
        binding = self.config.keys.get(name)
        if binding is None:
            return False
        c = self.config
        with self._lock:
            last = self._last_event.get(name)
            # A repeat: another event of the same key while it still counts as held.
            repeat = last is not None and now - last <= c.initial_hold
            self._last_event[name] = now
            if binding in MOTION_BINDINGS:
                self._held_until[binding] = now + (c.repeat_hold if repeat else c.initial_hold)
                self._deadman_until = now + c.deadman_expire
            elif binding == "deadman":
                # A press soon after the last may be a repeat of a held key or a second tap meant to turn it off:
                # either way it turns the deadman off, never on (a tap meant as "off" was read as a repeat and
                # left it on). Only a press after a pause turns it on; holding the key turns it off again.
                if self._deadman_on:
                    self._deadman_on = False
                elif not repeat:
                    self._deadman_on = True
                self._deadman_until = now + c.deadman_expire
            elif not repeat or binding == "estop":  # a held action key triggers once; a stop, always
                self._actions.append(binding)
        return True

    @property
    def deadman_toggles(self) -> bool:  # type: ignore[override]
        return self.config.deadman_mode == "toggle"

    def warnings(self) -> list[str]:
        return self.config.warnings()

    def release_deadman(self) -> None:
        with self._lock:
            self._deadman_on = False

    def control_name(self, binding: str) -> str:
        if binding == "deadman" and self.config.deadman_mode == "motion":
            return "a move key"
        key = next((k for k, b in self.config.keys.items() if b == binding), None)
        return key.upper() if key else binding

    def release_all(self) -> None:
        """Forget every held key and the deadman (focus lost, screen changed)."""
        with self._lock:
            self._held_until.clear()
            self._deadman_on = False

    def poll(self, now: float) -> InputSample:
        c = self.config
        with self._lock:
            actions, self._actions = self._actions, []
            held = [b for b, until in self._held_until.items() if until > now]
            for b in [b for b in self._held_until if b not in held]:
                del self._held_until[b]
            if c.deadman_mode == "toggle" and self._deadman_on and now >= self._deadman_until:
                self._deadman_on = False
            deadman = bool(held) if c.deadman_mode == "motion" else self._deadman_on
            remaining = self._deadman_until - now
        twist = np.zeros(6)
        for b in held:
            i = TWIST_AXES.index(b[1:])
            twist[i] += (1.0 if b[0] == "+" else -1.0) * (c.linear_speed if i < 3 else c.angular_speed)
        if not deadman:
            hint = "hold a move key" if c.deadman_mode == "motion" else "press the deadman key to enable"
            return InputSample(np.zeros(6), False, True, f"deadman off ({hint})", actions)
        status = "deadman on" + (f" (expires in {remaining:.0f} s)" if c.deadman_mode == "toggle" else "")
        return InputSample(twist, True, True, status, actions)
