"""The console's engine, without any UI: polls the input device, feeds the client's sender, runs actions.

Threads:
- ``operator-input`` polls the device at ``input_hz`` and calls ``client.set_twist``. It never blocks on the
  network: if it stalled, the sender would keep repeating the last twist (the edge's timeout would not fire
  because commands keep coming).
- ``operator-actions`` runs actions that query the edge (profile switch) so a slow answer cannot stall input.
- The client's own sender thread sends at its fixed rate whatever the last ``set_twist`` said.

The UI (textual) only forwards keys to :class:`KeyboardInput` and renders :meth:`view` — or nothing at all:
tests and the headless script use this class directly.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from iorthand_operator import recovery
from iorthand_operator.client import ControlRefused, OperatorClient, actuator_stale_after
from iorthand_operator.console.model import (
    ForceView,
    LinkRow,
    force_view,
    inert,
    link_rows,
    markers_note,
    next_profile,
    sparkline,
    stale_note,
    vitals_line,
)
from iorthand_operator.console.settings import ConsoleSettings
from iorthand_operator.inputs.base import InputDevice, InputSample

log = logging.getLogger("iorthand.operator.console")


@dataclass
class ConsoleView:
    """Everything the screen shows, as plain data (tests assert on it)."""

    router: str = ""
    connected: bool = False
    robot_online: str = "unknown"  # online / offline / unknown
    state_fresh: bool = False
    armed: bool = False
    owner: str = ""
    we_own: bool = False
    edge_deadman: bool = False
    deadman: bool = False  # what the command stream sends (not the input's: OperatorClient.sending_deadman)
    edge_status: str = ""
    edge_reason: str = ""
    # "stale 3.2 s" when the safety status behind armed, owner, status, the edge's deadman and the profile is older
    # than the client's bound (OperatorClient.safety_stale): those rows are then history, not the edge's state.
    safety_stale: str = ""
    hint: str = ""  # what to do before the robot moves again, with the key that does it ("" when nothing)
    force: ForceView = field(default_factory=lambda: force_view(None, 0.0, 0.0, 1.0))
    wrench: list[float] = field(default_factory=list)
    spark: str = ""
    tcp_pose_mm_deg: list[float] = field(default_factory=list)
    tcp_speed_mm_s: float = math.nan
    profile: str = ""
    frame: str = "base"  # of our twists: base, or tool (the probe's frame about its tip)
    contact: str = ""  # contact mode: "holding 4 N" ("" when off)
    task: str = ""  # a motion primitive under way and its progress
    vitals: str = ""  # the patient's vital signs (sensor/vital), "" when none has arrived
    linear_limit_mm_s: float = math.nan
    angular_limit_deg_s: float = math.nan
    limits_hit: list[str] = field(default_factory=list)
    link: list[LinkRow] = field(default_factory=list)
    input_name: str = ""
    input_connected: bool = True
    input_status: str = ""
    command: list[float] = field(default_factory=list)  # what we send, mm/s and deg/s
    markers: list[int] = field(default_factory=list)
    markers_note: str = ""  # why there are no markers, when it is not that none are in view
    markers_failed: bool = False  # the edge reports a camera failure (the note says which)
    camera: str = ""
    camera_stale: str = ""  # "stale 3.2 s" when the servo state is older than actuator_stale_after ("" while current)
    torch: str = ""
    torch_stale: str = ""  # likewise for the torch state
    events: list[str] = field(default_factory=list)  # the latest 50, oldest first
    events_logged: int = 0  # the number of the newest of them (Event.n): what is new since the last view
    sent: int = 0
    edge_judged: int = 0  # commands the edge's supervisor judged
    edge_superseded: int = 0  # commands the edge dropped unread, newer ones having arrived while it was busy


class ConsoleController:
    def __init__(
        self,
        client: OperatorClient,
        device: InputDevice,
        settings: ConsoleSettings | None = None,
        router: str = "",
        on_ui_action: Callable[[str], None] | None = None,
    ) -> None:
        self.client = client
        self.device = device
        self.settings = settings or ConsoleSettings()
        self.router = router
        self.on_ui_action = on_ui_action  # "poses", "quit": the UI's business
        self.sample = InputSample()
        self._input_was_connected = True
        self._halted_at = client.halted_at
        self._stop = threading.Event()
        self._actions: queue.Queue[str] = queue.Queue(maxsize=64)
        self._threads: list[threading.Thread] = []
        self.polls = 0

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        # The input loop's twists are the console's sign of life, not the client's own threads: an input thread
        # that stalls with the deadman held (a device read that never returns) releases it after ui_timeout.
        self.client.beats_itself = False
        # Logged at load too, but that line is behind the console's screen: what does nothing is said here.
        for warning in self.device.warnings():
            self.client.log_event("warning", "input", warning)
        for name, fn in (("input", self._input_loop), ("actions", self._action_loop)):
            t = threading.Thread(target=fn, name=f"operator-{name}", daemon=True)
            t.start()
            self._threads.append(t)

    def stop(self) -> None:
        self._stop.set()
        self.client.set_twist(np.zeros(3), np.zeros(3), deadman=False)
        for t in self._threads:
            t.join(timeout=2.0)
        self.device.close()

    # ------------------------------------------------------------------ input → sender

    def _input_loop(self) -> None:
        period = 1.0 / self.settings.input_hz
        while not self._stop.is_set():
            try:
                self.poll_once(time.monotonic())
            except Exception as exc:  # a broken device must stop motion, not the console
                self.client.set_twist(np.zeros(3), np.zeros(3), deadman=False)
                self.client.log_event("input", "input_error", f"input device failed: {exc}")
                log.exception("input device failed")
                self._stop.wait(1.0)
            self._stop.wait(period)

    def poll_once(self, now: float) -> InputSample:
        if self.client.halted_at != self._halted_at:
            # The edge halted (a stop, a long gap, a lost grant): a toggled deadman from before is no intent to
            # move now. The operator's next press is, and the hint says which key it is.
            self._halted_at = self.client.halted_at
            self.device.release_deadman()
        sample = self.device.poll(now)
        if not sample.connected:
            sample.twist, sample.deadman = np.zeros(6), False
        if sample.connected != self._input_was_connected:
            self._input_was_connected = sample.connected
            self.client.log_event("input", "input_lost" if not sample.connected else "input_back", sample.status)
        self.client.set_twist(sample.twist[:3], sample.twist[3:], deadman=sample.deadman)
        self.sample = sample
        self.polls += 1
        for action in sample.actions:
            self.dispatch(action)
        return sample

    def dispatch(self, action: str) -> None:
        if action == "estop":
            # At once, on this thread: a stop must not wait behind a slow query. A toggled deadman is forgotten
            # first, so the next poll cannot press it again.
            self.device.release_deadman()
            self.client.emergency_stop("operator e-stop key")
        elif action in ("poses", "quit"):
            if self.on_ui_action is not None:
                self.on_ui_action(action)
        else:
            try:
                self._actions.put_nowait(action)
            except queue.Full:
                log.warning("action %s dropped: too many pending", action)

    def _action_loop(self) -> None:
        while not self._stop.is_set():
            try:
                action = self._actions.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                self.run_action(action)
            except (ControlRefused, RuntimeError) as exc:
                self.client.log_event("action", action, f"{action} failed: {exc}")

    def run_action(self, action: str) -> None:
        c, step = self.client, math.radians(self.settings.pan_tilt_step_deg)
        if action == "acquire":
            try:
                c.acquire(c.safety.profile if c.safety and c.owner else "")
                c.log_event("action", "acquire", "control granted")
            except ControlRefused:
                pass  # acquire() logged the edge's reason
        elif action == "profile_next":
            current = c.safety.profile if c.safety else ""
            target = next_profile(current, self.settings.profiles)
            try:
                c.switch_profile(target)
                c.log_event("action", "profile", f"speed profile {target}")
            except ControlRefused as exc:
                c.log_event("refused", "profile", f"profile {target!r} refused: {exc}")
        elif action == "pan_left":
            c.step_servo(dpan=step)
        elif action == "pan_right":
            c.step_servo(dpan=-step)
        elif action == "tilt_up":
            c.step_servo(dtilt=step)
        elif action == "tilt_down":
            c.step_servo(dtilt=-step)
        elif action == "camera_center":
            c.send_servo(0.0, 0.0)
        elif action == "torch":
            on = c.toggle_torch()
            c.log_event("action", "torch", f"torch {'on' if on else 'off'}")
        elif action == "contact_toggle":
            c.set_contact(not (c.safety is not None and c.safety.contact_target >= 0))
        elif action == "frame_toggle":
            c.set_frame("tool" if c.frame == "base" else "base")
            c.log_event("action", "frame", "moving in the probe's frame (about its tip)" if c.frame == "tool"
                        else "moving in the robot's base frame")

    # ------------------------------------------------------------------ what the screen shows

    def view(self, now: float | None = None) -> ConsoleView:
        now = time.monotonic() if now is None else now
        c, s = self.client, self.settings
        v = ConsoleView(router=self.router, sent=c.sent_count)
        state = c.robot_state
        v.state_fresh = state is not None and now - c.robot_state_at <= s.state_stale_after
        # Connected: something from the robot arrives through the router. Not "its liveliness was ever heard of":
        # an edge gone offline, or a link gone dead, left "connected" on the screen.
        v.connected = v.state_fresh or (c.safety is not None and not c.safety_stale(now))
        v.robot_online = {True: "online", False: "offline", None: "unknown"}[c.edge_alive]
        if c.edge_alive is None and v.state_fresh:
            v.robot_online = "online"
        safety = c.safety
        if safety is not None:
            v.armed, v.owner, v.edge_deadman = safety.armed, safety.owner, safety.deadman
            v.we_own = safety.owner == c.operator_id
            v.edge_status, v.edge_reason = safety.status, safety.reason
            v.profile = safety.profile
            v.linear_limit_mm_s = 1000 * safety.linear_limit
            v.angular_limit_deg_s = math.degrees(safety.angular_limit)
            v.limits_hit = list(safety.limits_hit)
            v.edge_judged, v.edge_superseded = safety.received, safety.superseded
            if c.safety_stale(now):
                v.safety_stale = f"stale {c.safety_age(now):.1f} s"
        v.deadman = c.sending_deadman(now)
        v.frame = c.frame
        if safety is not None:
            v.contact = f"holding {safety.contact_target:g} N" if safety.contact_target >= 0 else ""
            v.task = safety.task
        d = self.device
        v.hint = recovery.hint(c.next_step(), d.control_name("acquire"), d.control_name("deadman"), d.deadman_toggles)
        v.force = force_view(c.force_level, c.force_level_at, now, s.force_stale_after)
        if c.force is not None and now - c.force_at <= s.force_stale_after:
            v.wrench = [*c.force.force, *c.force.torque]
        top = c.force_level.danger if c.force_level is not None else None
        v.spark = sparkline(c.force_history, 30, top)
        v.vitals = vitals_line(dict(c.vitals), now)
        if state is not None:
            p = state.tcp_pose
            v.tcp_pose_mm_deg = [1000 * p[0], 1000 * p[1], 1000 * p[2], *(math.degrees(a) for a in p[3:])]
            v.tcp_speed_mm_s = 1000 * float(np.linalg.norm(state.tcp_speed[:3]))
        v.link = link_rows(c.link_quality(int(now * 1e9), s.state_stale_after), s.link)
        v.input_name = self.device.name
        v.input_connected = self.sample.connected
        v.input_status = self.sample.status
        tw = self.sample.twist if v.deadman else np.zeros(6)  # a released deadman sends a zero twist
        v.command = [*(1000 * tw[:3]), *(math.degrees(a) for a in tw[3:])]
        if c.markers is None:
            v.markers_note = "no marker data"
        else:
            v.markers_note, v.markers_failed = markers_note(c.markers.failure, now - c.markers_at)
            if not v.markers_note:
                v.markers = sorted(m.id for m in c.markers.markers)
        if c.servo is not None:
            v.camera = f"pan {math.degrees(c.servo.pan):+.0f}° tilt {math.degrees(c.servo.tilt):+.0f}°"
            v.camera_stale = stale_note(now - c.servo_at, actuator_stale_after(c.servo))
        if c.torch is not None:
            v.torch = f"{'on' if c.torch.on else 'off'} {100 * c.torch.brightness:.0f} %"
            v.torch_stale = stale_note(now - c.torch_at, actuator_stale_after(c.torch))
        recent = list(c.events)[-50:]
        v.events = [f"{time.strftime('%H:%M:%S', time.localtime(e.t))} {e.kind:<7} {e.status}: {e.reason}" for e in recent]
        v.events_logged = recent[-1].n if recent else 0
        return inert(v)  # text from the wire cannot steer the terminal

