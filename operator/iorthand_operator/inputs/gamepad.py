"""Gamepads and joysticks through SDL (pygame-ce), headless.

SDL needs a video subsystem for its event queue; ``SDL_VIDEODRIVER=dummy`` gives one without a display, and
``SDL_JOYSTICK_ALLOW_BACKGROUND_EVENTS=1`` keeps joystick events flowing when no window has focus (there is no
window at all). Both are set here before pygame is imported, unless the environment already chose.

The device's state is built from SDL *events* (axis motion, button up/down, hat motion, device added/removed),
not by reading the joystick object, so a test can inject an event stream with ``pygame.event.post`` and exercise
exactly the code path a real pad does. All pygame calls happen on the thread that calls ``poll`` (SDL's event
queue is not meant to be pumped from several threads).

Unplugging the pad mid-session drops every axis and button: the sample becomes idle (no motion, no deadman)
and says so; the sender then sends its short release tail and goes quiet. Plugging it back in resumes once the
enable button is pressed again — a held button is not trusted across a reconnect.
"""

from __future__ import annotations

import logging
import os
import threading
from typing import Any

from iorthand_operator.inputs.base import InputDevice, InputSample
from iorthand_operator.inputs.mapping import GamepadConfig, map_gamepad

log = logging.getLogger("iorthand.operator.gamepad")

_HAT_ACTIONS = {(-1, 0): "pan_left", (1, 0): "pan_right", (0, 1): "tilt_up", (0, -1): "tilt_down"}


def _pygame() -> Any:
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
    os.environ.setdefault("SDL_JOYSTICK_ALLOW_BACKGROUND_EVENTS", "1")
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    import pygame

    return pygame


class GamepadInput(InputDevice):
    def __init__(self, config: GamepadConfig) -> None:
        self.config = config
        self.name = config.name
        self._pg = _pygame()
        self._lock = threading.Lock()
        self._initialised = False
        self._joystick: Any = None
        self._instance: int | None = None
        self.connected = False
        self.status = "no gamepad found"
        self._axes: dict[int, float] = {}
        self._buttons: set[int] = set()
        self._actions: list[str] = []
        self.events = 0

    def _init(self) -> None:
        pg = self._pg
        pg.display.init()
        pg.joystick.init()
        self._initialised = True
        if pg.joystick.get_count() > self.config.device:
            self._open(self.config.device)

    def _open(self, device_index: int) -> None:
        try:
            js = self._pg.joystick.Joystick(device_index)
            self._joystick, self._instance = js, js.get_instance_id()
            label = js.get_name()
        except self._pg.error:
            # An injected "device added" without a real device behind it (tests): accept any instance.
            self._joystick, self._instance, label = None, None, "injected device"
        self.connected = True
        self.status = f"{label} connected: hold button {self.config.enable_button} to move"
        log.info("gamepad %s connected (device %d)", label, device_index)

    def _mine(self, event: Any) -> bool:
        inst = getattr(event, "instance_id", None)
        return self._instance is None or inst is None or inst == self._instance

    def _handle(self, event: Any) -> None:
        pg = self._pg
        self.events += 1
        if event.type == pg.JOYDEVICEADDED:
            if not self.connected and event.device_index == self.config.device:
                self._open(event.device_index)
            return
        if event.type == pg.JOYDEVICEREMOVED:
            if self.connected and self._mine(event):
                self.connected = False
                self._joystick = self._instance = None
                self._axes.clear()
                self._buttons.clear()
                self.status = "GAMEPAD UNPLUGGED: motion stopped; plug it back in and press enable"
                log.warning("gamepad unplugged: motion stopped")
            return
        if not self.connected or not self._mine(event):
            return
        if event.type == pg.JOYAXISMOTION:
            self._axes[event.axis] = float(event.value)
        elif event.type == pg.JOYBUTTONDOWN:
            self._buttons.add(event.button)
            for action, button in self.config.buttons.items():
                if button == event.button:
                    self._actions.append(action)
        elif event.type == pg.JOYBUTTONUP:
            self._buttons.discard(event.button)
        elif event.type == pg.JOYHATMOTION and self.config.hat is not None and event.hat == self.config.hat:
            action = _HAT_ACTIONS.get(tuple(event.value))
            if action:
                self._actions.append(action)

    def control_name(self, binding: str) -> str:
        if binding == "deadman":
            return f"button {self.config.enable_button}"
        button = self.config.buttons.get(binding)
        return f"button {button}" if button is not None else binding

    def poll(self, now: float) -> InputSample:
        with self._lock:
            if not self._initialised:
                self._init()
            for event in self._pg.event.get():
                self._handle(event)
            actions, self._actions = self._actions, []
            if not self.connected:
                return self.idle(self.status, connected=False, actions=actions)
            twist, deadman = map_gamepad(self._axes, self._buttons, self.config)
            status = "enable held" if deadman else f"hold button {self.config.enable_button} to move"
            return InputSample(twist, deadman, True, status, actions)

    def close(self) -> None:
        with self._lock:
            if self._initialised:
                self._pg.joystick.quit()
                self._pg.display.quit()
                self._initialised = False
