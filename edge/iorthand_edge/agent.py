"""The edge agent: the safety authority on the end-effector computer.

Threads (all named):
- ``control``: the control loop, the only caller of the robot driver. It waits for a twist or the next tick
  (or the deadman's timeout, whichever comes first): a twist is judged by the supervisor and driven at once,
  its verdict published on ``state/applied`` (low latency, no further hand-off); a tick reads the robot, runs the
  supervisor's cycle (deadman timeout, limits), drives, publishes ``state/robot`` and ``state/safety``. Other
  threads that change the supervisor's state (a stop, a fault, the owner lost, a force level) wake it, and it
  drives the consequence at once.
- ``control-plane``: ownership queries, operator liveliness and the force-zero, arm, goto and contact requests,
  in arrival order (only the owner's signed requests may zero the sensor or start a move). A stop waits in no
  queue (its Zenoh callback acts).
- ``actuators``: servo and torch commands, the newest of each key (only the owner's move the servos or switch
  the torch), apart from the control requests so that a flood of them cannot delay the owner's lease renewal.
- Optional components, each from its own config section and with its own named thread(s): ``edge-force``
  (sensor, warning levels; a change goes straight to the supervisor), ``edge-servos``, ``edge-torch``. A force
  sensor whose samples come from the robot state (the simulator's, the arm's wrist sensor) has no thread: the
  control loop samples it once per robot state, before the supervisor's cycle.
- Perception and video run in a child process (:mod:`iorthand_edge.media`: camera, ArUco, the simulators,
  JPEG, on its own Zenoh session), so they cannot take this process's CPU or GIL. ``edge-media`` watches it and
  restarts it after a crash. Its markers come back on the ``markers`` key, the newest kept by Zenoh and decoded
  only when an ``above_marker:<id>`` move asks for them.

Zenoh callbacks only queue bytes into bounded inboxes. The supervisor is shared under one lock and decides
everything; this adapter carries events in and the supervisor's actions out. Nothing outside this process can
move the robot except through it.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import math
import os
import signal
import socket
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh

from iorthand import channels, geometry, keys, motion
from iorthand.cpu_latency import CpuLatencyWhileNeeded
from iorthand.protocol import (
    MAX_PAYLOAD,
    MESSAGES_BY_KEY,
    REVISION,
    STOP_FROM,
    AppliedCommand,
    ControlReply,
    ControlRequest,
    DecodeError,
    Markers,
    Message,
    RejectCounter,
    RobotState,
    SafetyStatus,
    Sequencer,
    ServoCommand,
    ServoState,
    Status,
    StopCommand,
    TorchCommand,
    TorchState,
    TwistCommand,
    revision_json,
    said_revision,
    unreadable_by,
    update_the_console,
)
from iorthand.security import sdnotify
from iorthand.security.identity import CommandGate, operator_in_key
from iorthand.transport import Inbox, Worker, open_session, publisher, subscribe
from iorthand_edge.actuators import ServoUnit, TorchUnit
from iorthand_edge.config import EdgeConfig
from iorthand_edge.force import LevelState, SensorError, make_force_sensor
from iorthand_edge.force.monitor import ForceMonitor
from iorthand_edge.goto import GotoController
from iorthand_edge.kinematic_guard import KinematicGuard
from iorthand_edge.media import MediaProcess, needs_media
from iorthand_edge.planner import PlannerProcess
from iorthand_edge.robots import Robot, RobotFault, RobotReading, make_robot
from iorthand_edge.supervisor import Action, Decision, Supervisor

log = logging.getLogger("iorthand.edge")

# Twists waiting for the command thread: a flood keeps only the newest (each is a whole velocity command); the
# ones dropped unread are reported as SafetyStatus.superseded.
TWIST_QUEUE = 64
# Control requests, liveliness events, servo and torch commands waiting for the control-plane thread; and the
# planning queries (preview, poses) waiting for the planner, which has a thread of its own because a plan
# takes up to seconds: behind it, renewals of the owner's lease would time out. Both keep what they hold and
# answer a query that finds them full at once, with why (a flood costs its sender, not the owner). A stop waits
# in no queue (EdgeAgent._on_stop_sample).
CONTROL_QUEUE = 256
PLANNING_QUEUE = 4
# The owner's previews (signed with its grant's key) go before everyone else's, into room of their own: 8 heavy
# previews from anyone filled the planning queue, and the owner's retreat was refused "edge busy".
OWNER_PLANNING = 2
# Likewise the owner's control requests (lease renewals, arm, goto, contact, release): Zenoh caps no query, and
# three sessions sending acquires in made-up names kept the control queue full, so the owner's renewals were
# refused "edge busy" and its control hung on a retry getting through before the lease ran out.
OWNER_CONTROL = 4
# Servo and torch commands are set-points: the newest of each key is all that matters, and they wait apart from
# the control requests (a flood of them filled the control queue and refused the owner's lease renewals "edge
# busy": the owner lost control). With bound keys each operator's key has its own slot: another's flood cannot
# push out the owner's command.
ACTUATOR_KEYS = 16

# Put into the twist inbox by a thread that changed the supervisor's state: the control loop wakes and drives
# the consequence at once (a flood of twists that pushes it out wakes the loop just as well).
_WAKE = ("wake", b"", 0)


class AgentAlreadyOnline(RuntimeError):
    """Another edge agent for this robot id answers on the router (a copied configuration, a manual run on another
    computer): two would both answer the operators and both drive the robot."""


class RateLimitedLog:
    """Logs a repeated message once, then at most every ``interval`` seconds with a count (floods of garbage
    must not flood the log, but nothing is hidden). Remembers the ``max_kinds`` most recent kinds of message: a
    flood of new kinds (keys an attacker makes up) costs log lines, never memory."""

    def __init__(self, logger: logging.Logger, interval: float = 5.0, max_kinds: int = 256) -> None:
        self._log = logger
        self._interval = interval
        self._max_kinds = max_kinds
        self._last: OrderedDict[str, float] = OrderedDict()
        self._suppressed: dict[str, int] = {}

    def warning(self, kind: str, msg: str) -> None:
        now = time.monotonic()
        if now - self._last.get(kind, -math.inf) >= self._interval:
            extra = self._suppressed.pop(kind, 0)
            self._log.warning("%s%s", msg, f" (+{extra} similar)" if extra else "")
            self._last[kind] = now
            self._last.move_to_end(kind)
            while len(self._last) > self._max_kinds:
                gone, _ = self._last.popitem(last=False)
                self._suppressed.pop(gone, None)
        else:
            self._suppressed[kind] = self._suppressed.get(kind, 0) + 1


class EdgeAgent:
    def __init__(self, config: EdgeConfig, robot: Robot | None = None) -> None:
        self.config = config
        self.keys = keys.RobotKeys(config.robot_id)
        # The tool point the kinematics use is the one the controller must have (all zero: not set).
        tcp = list(config.goto.tcp_offset) if any(config.goto.tcp_offset) else None
        self.robot = robot if robot is not None else make_robot(config.robot, config.safety.stop_deceleration,
                                                                config.realtime, tcp)
        self.period = self.robot.control_period
        self.supervisor = Supervisor(config.safety, period=self.period, force_required=config.force is not None,
                                     robot=config.robot_id)
        if config.safety.kinematics.enabled:
            self.supervisor.kinematics = KinematicGuard(config.safety.kinematics, config.robot.model,
                                                        config.goto.tcp_offset)
        if config.force is not None:  # contact mode holds a force below the caution level, never at it
            self.supervisor.contact_ceiling = config.force.levels.caution
        axis = np.asarray(config.safety.force.contact_axis, dtype=float)
        self._contact_axis = (axis / max(float(np.linalg.norm(axis)), 1e-9)).tolist()  # pressing, tool frame
        self.lock = threading.RLock()
        self.stop_event = threading.Event()
        self.rejects = RejectCounter()
        self.repeated_stops = 0  # stops that found the robot held still by a stop already (logged, not acted on)
        self.reading: RobotReading | None = None
        self._seq = {name: Sequencer() for name in ("robot", "safety", "applied")}
        self._commanded = np.zeros(6)
        self._tracked_q: list[float] | None = None  # the guard's joint angles, for a robot that measures none
        self._last_cmd_seq = 0
        self._last_cmd_recv = 0
        self._last_safety: tuple[Any, ...] | None = None
        self._last_safety_pub = 0.0
        self._twists = Inbox(TWIST_QUEUE, keep="newest")
        self._control = Inbox(CONTROL_QUEUE, keep="oldest", reserve=OWNER_CONTROL)
        self._planning = Inbox(PLANNING_QUEUE, keep="oldest", reserve=OWNER_PLANNING)
        self._actuators = Inbox(ACTUATOR_KEYS, keep="newest_per_key")
        self._workers: list[Worker] = []
        self._rlog = RateLimitedLog(log)
        self.session: zenoh.Session | None = None
        # Called with every reading, after the cycle (systemd's watchdog registers here).
        self.cycle_hooks: list[Callable[[RobotReading], None]] = []
        self.force: ForceMonitor | None = None
        if config.force is not None:
            sensor = make_force_sensor(config.force.sensor, config.phantom, lambda: self.reading)
            self.force = ForceMonitor(config.force, sensor, self._on_force_change)
            self.force.seal = self.supervisor.for_owner
        self.servos = ServoUnit(config.servos) if config.servos is not None else None
        self.torch = TorchUnit(config.torch) if config.torch is not None else None
        # Perception and video run in a child process (iorthand_edge.media) so that they never take the control
        # loop's CPU or GIL. Raises PerceptionError or VideoError (a calibration for another image size, a corrupt
        # file, a video source that needs the perception camera): refuse to start.
        self.media = MediaProcess(config) if needs_media(config) else None
        self.gate = CommandGate(
            allowed=list(config.safety.allowed_operators),
            require_alive=config.require_operator_alive,
            bind_keys=config.bind_operator_keys,
        )
        self.goto = GotoController(config.goto, config.safety.workspace.min, config.safety.workspace.max,
                                   config.robot.model)
        self._planner = PlannerProcess()  # plans off the control process's GIL (its module says why)
        self.goto.planner = self._planner.plan_route
        # The media process's markers, from this robot's markers key (for above_marker:<id>): the latest filtered
        # T_base_marker per id, and the time of the camera frame they come from (ns since the epoch).
        self._markers: dict[int, np.ndarray] = {}
        self._markers_t = 0
        self._markers_sub: zenoh.Subscriber | None = None
        self.cycle_hooks.append(sdnotify.cycle_hook())  # systemd: READY once, then the watchdog from the loop
        self._local_server: socket.socket | None = None
        # Servos, torch and video stop with the agent but a crash of theirs must not stop the robot's control:
        # they get their own stop event. The force worker shares the agent's: losing it is a safety fault.
        self._aux_stop = threading.Event()
        self._cpu_latency = None if config.cpu_latency_us is None else CpuLatencyWhileNeeded(config.cpu_latency_us)

    # ------------------------------------------------------------------ lifecycle

    def first_reading(self) -> None:
        """The robot's state before the first control cycle, assessed for the kinematic guard: without it the
        guard knows no joint angles and would halt a command sent before the first cycle as beyond reach."""
        self.reading = self.robot.read_state()
        self._assess(self.reading)

    def _assess(self, reading: RobotReading) -> None:
        """The kinematic guard's assessment of a new reading, with the joint angles it tracks from the pose."""
        guard = self.supervisor.kinematics
        if guard is not None:
            reported = reading.q if self.robot.measures_joints else None
            self._tracked_q = guard.update(reading.tcp_pose, reported).q or self._tracked_q

    def _joint_angles(self, reading: RobotReading) -> np.ndarray | list[float]:
        """The arm's joint angles: as measured, or for a robot that measures none (the simulator) as the kinematic
        guard tracks them (the last it had while beyond reach; the robot's placeholder without a guard)."""
        if self.robot.measures_joints or self._tracked_q is None:
            return reading.q
        return self._tracked_q

    def start(self) -> None:
        # The session first: another agent online for this robot id is refused before this one connects to the
        # robot (a second UR driver would replace the first one's control script; both would answer operators).
        self.session = open_session(self.config.zenoh, stop=self.stop_event)
        s, k = self.session, self.keys
        if any(reply.ok is not None for reply in s.liveliness().get(k.key(keys.ALIVE_EDGE), timeout=1.0)):
            self.session.close()
            self.session = None
            raise AgentAlreadyOnline(
                f"an edge agent for robot {self.config.robot_id!r} is already online through "
                f"{', '.join(self.config.zenoh.connect) or self.config.zenoh.mode}: stop it first (one robot, one edge)")
        try:
            self.robot.connect()
        except RobotFault as exc:
            # Not fatal: an edge that exits says nothing to the consoles (and systemd's restarts fill the journal
            # with tracebacks). It comes up, publishes the robot as not connected with this reason (read_state) and
            # the backend keeps reconnecting, as after a fault in use (the UR driver backs off up to
            # reconnect_max_s); the supervisor holds the robot until it is connected and the operator acknowledges.
            log.error("robot %r not connected at start: %s — the edge runs without it and keeps reconnecting "
                      "(check that the controller is on, reachable from this computer, and in remote control)",
                      self.config.robot_id, exc)
        self.first_reading()
        self._pub_robot = publisher(s, k.key(keys.STATE_ROBOT))
        self._pub_safety = publisher(s, k.key(keys.STATE_SAFETY))
        self._pub_applied = publisher(s, k.key(keys.STATE_APPLIED))
        # With bound keys, operators command on .../cmd/twist/<id> and query .../control/<verb>/<id>, keys the
        # router's ACL grants only to that operator's certificate (iorthand.security.identity).
        bound = "/*" if self.config.bind_operator_keys else ""
        self._declared = [
            subscribe(s, k.key(keys.CMD_TWIST) + bound, self._twists, rejects=self.rejects, monotonic=True),
            # A stop is everyone's: on the shared key, or on the sender's own (which names who sent it).
            s.declare_subscriber(k.key(keys.CMD_STOP), self._on_stop_sample),
            s.declare_subscriber(k.key(keys.CMD_STOP) + "/*", self._on_stop_sample),
            subscribe(s, k.key(keys.CMD_SERVO) + bound, self._actuators, rejects=self.rejects),
            subscribe(s, k.key(keys.CMD_TORCH) + bound, self._actuators, rejects=self.rejects),
            # With bound keys a shared query (plan/preview: the twin asks it for the operators) has its plain key too.
            *(s.declare_queryable(k.key(suffix) + tail, self._queue_query(inbox, verb, suffix)) for suffix, inbox, verb in (
                (keys.CONTROL_FORCE_ZERO, self._control, "force_zero"),
                (keys.CONTROL_ACQUIRE, self._control, "acquire"),
                (keys.CONTROL_RELEASE, self._control, "release"),
                (keys.CONTROL_ARM, self._control, "arm"),
                (keys.CONTROL_GOTO, self._control, "goto"),
                (keys.CONTROL_CONTACT, self._control, "contact"),
                (keys.PLAN_PREVIEW, self._planning, "preview"),
                (keys.CONTROL_POSES, self._planning, "poses"),
            ) for tail in {bound, *([""] if channels.BY_SUFFIX[suffix].shared else [])}),
            s.liveliness().declare_subscriber(k.alive_operators, self._on_operator_liveliness, history=True),
        ]
        self._token = s.liveliness().declare_token(k.key(keys.ALIVE_EDGE))
        # The control loop (which carries the command path too) runs at real-time priority where allowed (root
        # on the Pi): it blocks between short bursts, so it cannot starve the rest.
        for name, fn, rt in (("control", self._control_loop, True), ("control-plane", self._control_plane_loop, False),
                             ("planner", self._planner_loop, False), ("actuators", self._actuator_loop, False)):
            w = Worker(f"edge-{name}", fn, self.stop_event, realtime=rt and self.config.realtime)
            w.start()
            self._workers.append(w)
        self._start_components()
        self._start_local_socket()
        log.info(
            "edge agent %r up: robot %s, %s, armed=%s, profile %s (%.0f mm/s), CPU wake-up latency %s",
            self.config.robot_id, type(self.robot).__name__, ", ".join(self.config.zenoh.connect) or self.config.zenoh.mode,
            self.supervisor.armed, self.supervisor.profile, 1000 * self.supervisor.limits.linear,
            self._cpu_latency.state if self._cpu_latency else "the host's own",
        )
        for setting_name, why in self.config.warnings():
            log.warning("%s: %s", setting_name, why)

    def _start_components(self) -> None:
        assert self.session is not None
        if self.force is not None:
            self.force.start(self.session, self.keys, self.stop_event)
        for unit in (self.servos, self.torch):
            if unit is not None:
                unit.start(self.session, self.keys, self._aux_stop)
        if self.config.perception is not None:
            # Only the newest markers matter, and only when a move asks for them (poses, preview): Zenoh keeps
            # the newest message in a ring of one, decoded on demand, with no thread of this process woken per frame.
            self._markers_sub = self.session.declare_subscriber(self.keys.key(keys.MARKERS),
                                                                zenoh.handlers.RingChannel(1))
        if self.media is not None:
            self.media.start(self.session)

    def _stop_components(self) -> None:
        self._aux_stop.set()
        if self.media is not None:
            self.media.stop()
        if self._local_server is not None:
            self._local_server.close()
        for comp in (self.force, self.servos, self.torch):
            if comp is not None:
                comp.join()

    def run_forever(self) -> None:
        self.start()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: self.stop_event.set())
        self.stop_event.wait()
        self.shutdown()

    def shutdown(self, reason: str = "edge agent shutting down") -> None:
        # The robot first, while the control loop still runs: ending the workers, the planner and the media process
        # takes seconds, and the arm kept its last speed meanwhile (a UR until its driver's own silent-agent stop).
        with self.lock:
            self._cancel_goto(reason)
            self.supervisor.disarm(reason)
            self._commanded = np.zeros(6)
            with contextlib.suppress(RobotFault):
                self.robot.stop(self.config.safety.stop_deceleration)
        if self.session is not None:
            with contextlib.suppress(zenoh.ZError):
                self._publish_safety(force=True)
        self.stop_event.set()
        self._aux_stop.set()  # the local socket's worker is among the workers joined next
        self._twists.close()
        self._control.close()
        self._planning.close()
        self._actuators.close()
        for w in self._workers:
            w.join(timeout=2.0)
        self._planner.close()
        self._stop_components()
        with self.lock:
            try:
                self.robot.stop(self.config.safety.stop_deceleration)
            finally:
                self.robot.disconnect()
        if self.session is not None:
            with contextlib.suppress(zenoh.ZError):
                self._publish_safety(force=True)
            self.session.close()
            self.session = None
        if self._cpu_latency is not None:
            self._cpu_latency.close()
        log.info("edge agent %r stopped", self.config.robot_id)

    # ------------------------------------------------------------------ local commands

    def arm(self) -> None:
        """Local arming confirmation (a button or a command on the robot side)."""
        with self.lock:
            self.supervisor.arm()
            # The confirmation that whoever took the robot over at its side is done: a driver held since may connect.
            self.robot.allow_restart()
        log.info("armed by local confirmation")
        self._publish_safety(force=True)

    def disarm(self, reason: str) -> None:
        with self.lock:
            self.supervisor.disarm(reason)
        self._wake()
        log.warning("disarmed: %s", reason)
        self._publish_safety(force=True)

    def _start_local_socket(self) -> None:
        """The local command socket (``local_socket``): only a process on this computer, with the rights on
        that file, can confirm arming — remote clients can only request it (``iorthand arm --config``)."""
        path = self.config.local_socket
        if path is None:
            return
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
        server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        server.bind(str(path))
        os.chmod(path, 0o600)
        server.listen(2)
        server.settimeout(0.2)
        self._local_server = server
        w = Worker("edge-local", self._local_loop, self._aux_stop)
        w.start()
        self._workers.append(w)

    def _local_loop(self, stop: threading.Event) -> None:
        assert self._local_server is not None
        while not stop.is_set():
            try:
                conn, _ = self._local_server.accept()
            except TimeoutError:
                continue
            except OSError:
                return  # the socket was closed at shutdown
            with conn:
                conn.settimeout(2.0)
                try:
                    line = conn.recv(256).decode(errors="replace").strip()
                except OSError:
                    continue
                answer = self.local_command(line)
                with contextlib.suppress(OSError):  # the client hung up: its command was carried out all the same
                    conn.sendall((answer + "\n").encode())

    def local_command(self, line: str) -> str:
        """One local command: ``arm``, ``disarm`` or ``status``; the answer is one line."""
        if line == "arm":
            self.arm()
            return "ok: armed"
        if line == "disarm":
            self.disarm("disarmed by local command")
            return "ok: disarmed"
        if line == "status":
            sv = self.supervisor
            return json.dumps({"armed": sv.armed, "arm_requested": sv.arm_requested, "owner": sv.owner,
                               "status": sv.status, "reason": sv.reason})
        return f"error: unknown local command {line[:40]!r} (arm, disarm, status)"

    # ------------------------------------------------------------------ the control loop

    def _control_loop(self, stop: threading.Event) -> None:
        next_tick = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            # Wake at the next tick, or earlier when the deadman times out before it, or when a twist arrives.
            wake = min(next_tick, self.supervisor.timeout_at() + 1e-4)
            item = self._twists.get(timeout=max(0.0, wake - now))
            if item is not None and item is not _WAKE:
                echo = self.handle_twist(*item)
                if echo is not None:
                    self._pub_applied.put(self.supervisor.for_owner(keys.STATE_APPLIED, echo))
            now = time.monotonic()
            if item is _WAKE or now >= wake:
                self._cycle(now)
                if now >= next_tick:  # this cycle was a tick (not an early wake)
                    next_tick += self.period
                    if next_tick <= now:
                        next_tick = now + self.period  # overran: do not try to catch up with a burst

    def _cycle(self, now: float) -> None:
        """One control cycle: read the robot, let the supervisor decide, drive, publish the state."""
        with self.lock:
            reading = self.robot.read_state()
            self.reading = reading
            if self.force is not None and self.force.paced_by_robot:  # this state's force, before the supervisor
                self.force.on_robot_state(now)
            self._feed_contact_force()
            before, was_armed = self.supervisor.fault, self.supervisor.armed
            fault = self.supervisor.on_reading(reading.fault, reading.connected, reading.tcp_pose, reading.takeover)
            if fault and fault != before:
                log.error("robot fault: %s — stopping", fault)
            if was_armed and not self.supervisor.armed:
                log.warning("disarmed: %s", reading.takeover)
            decision = self.supervisor.step(now, reading.tcp_pose)
            if self.goto.active and decision.status.halts:
                self._cancel_goto(decision.reason or decision.status.message)
            self._drive(decision)
            self._log_interventions()
        # The kinematic guard measures the new pose outside the lock, before the next commands. A robot that does
        # not measure its joint angles is published with the ones the guard tracks: the twin, the recordings and
        # their exports see the arm move.
        self._assess(reading)
        state = RobotState(
            tcp_pose=reading.tcp_pose, tcp_speed=reading.tcp_speed, q=self._joint_angles(reading),
            commanded=self._commanded, mode=reading.mode, connected=reading.connected,
            fault=fault, robot_time=reading.robot_time,
            cmd_seq=self._last_cmd_seq, cmd_recv_t=self._last_cmd_recv,
        ).stamp(self._seq["robot"].next(), reading.timestamp_ns)
        if self._cpu_latency is not None:  # fast wake-ups while somebody drives, the host's own idle otherwise
            self._cpu_latency.need(bool(self.supervisor.owner))
        for hook in self.cycle_hooks:
            hook(reading)
        self._pub_robot.put(self.supervisor.for_owner(keys.STATE_ROBOT, state))
        self._publish_safety()

    def _feed_contact_force(self) -> None:
        """Contact mode: the newest force along the probe's axis (pressing positive) to the supervisor (caller
        holds the lock)."""
        if self.force is None or self.supervisor.contact_target is None:
            return
        w, a = self.force.last_wrench, self._contact_axis
        # The sensor measures the surface's reaction on the tool: pressing along the axis reads as force against it.
        self.supervisor.update_contact_force(-(w[0] * a[0] + w[1] * a[1] + w[2] * a[2]), self.force.state.last_sample)

    def _wake(self) -> None:
        """Another thread changed the supervisor's state: the control loop drives the consequence now."""
        self._twists.put(_WAKE)

    def _drive(self, decision: Decision) -> None:
        """Carry out the supervisor's action (the control loop only, holding the lock)."""
        try:
            if decision.action == Action.MOVE:
                self._commanded = self.robot.send_twist(decision.twist, self.config.safety.max_linear_acceleration)
            elif decision.action == Action.STOP:
                self._commanded = np.zeros(6)
                self.robot.stop(self.config.safety.stop_deceleration)
        except RobotFault as exc:
            self._commanded = np.zeros(6)
            log.error("robot refused the command: %s — stopping", exc)
            if self.supervisor.driver_failed(str(exc)).action == Action.STOP:
                with contextlib.suppress(RobotFault):
                    self.robot.stop(self.config.safety.stop_deceleration)

    def _log_interventions(self) -> None:
        """Log each safety intervention of the supervisor once, with its reason (caller holds the lock)."""
        if self.supervisor.interventions:
            for status, reason in self.supervisor.interventions:
                log.warning("safety intervention [%s]: %s", status, reason)
            self.supervisor.interventions.clear()

    # ------------------------------------------------------------------ components

    def _on_force_change(self, state: LevelState) -> None:
        """A new level or staleness goes to the supervisor. From the force thread, the control loop wakes to drive
        it at once (not at its next tick); a sensor paced by the robot is sampled by the control cycle that then
        drives it."""
        with self.lock:
            self.supervisor.update_force(state.level, state.stale, time.monotonic())
        if self.force is not None and not self.force.paced_by_robot:
            self._wake()
        self._publish_safety(force=True)

    @property
    def markers(self) -> dict[int, np.ndarray]:
        """The newest markers from the media process (T_base_marker per id); malformed messages are counted."""
        sub = self._markers_sub
        while sub is not None and (sample := sub.try_recv()) is not None:
            key = str(sample.key_expr)
            try:
                msg = Markers.decode(sample.payload.to_bytes())
            except DecodeError as exc:
                self.rejects.add(key, str(exc))
                self._rlog.warning(f"malformed:{keys.MARKERS}", f"rejected malformed markers on {key}: {exc}")
                continue
            # A failure notice (the camera failed) has no markers: none to aim at until the camera sees again.
            self._markers, self._markers_t = {m.id: geometry.unflatten(m.pose) for m in msg.markers}, msg.t
        return self._markers

    def _fresh_markers(self) -> dict[int, np.ndarray]:
        """The marker poses a move may aim at: none once their camera frame is older than
        ``goto.marker_max_age`` (the camera failed or stalled, and the patient may have moved since)."""
        markers = self.markers
        if (time.time_ns() - self._markers_t) / 1e9 > self.config.goto.marker_max_age:
            return {}
        return dict(markers)

    def _publish_safety(self, force: bool = False) -> None:
        with self.lock:
            sv = self.supervisor
            c = sv.counters
            age = sv.command_age(time.monotonic())
            fields = (
                sv.armed, sv.arm_requested, sv.owner, sv.deadman, sv.profile, sv.status, sv.reason,
                tuple(sv.limits_hit), int(sv.force_level), sv.force_stale, sv.contact_target,
            )
            now = time.monotonic()
            if not force and fields == self._last_safety and now - self._last_safety_pub < 1.0 / self.config.safety_rate_hz:
                return
            self._last_safety, self._last_safety_pub = fields, now
            msg = SafetyStatus(
                armed=sv.armed, arm_requested=sv.arm_requested, owner=sv.owner, deadman=sv.deadman,
                profile=sv.profile, linear_limit=sv.limits.linear, angular_limit=sv.limits.angular,
                limits_hit=list(sv.limits_hit), command_age=age, status=sv.status, reason=sv.reason,
                force_level=int(sv.force_level), force_stale=sv.force_stale,
                received=c.received, applied=c.applied, rejected=c.rejected,
                malformed=self.rejects.total, superseded=self.twists_superseded, stops=c.stops, forged=c.forged,
                contact_target=-1.0 if sv.contact_target is None else sv.contact_target,
                task=SafetyStatus.fit("task", self.goto.reason) if self.goto.active else "",
            ).stamp(self._seq["safety"].next())
            # Put under the lock: two threads publishing at once must not reorder the sequence numbers.
            self._pub_safety.put(self.supervisor.for_owner(keys.STATE_SAFETY, msg))

    # ------------------------------------------------------------------ commands

    @property
    def twists_superseded(self) -> int:
        """Twist commands dropped unread: newer ones queued behind them while the control loop was busy."""
        return self._twists.dropped

    def handle_twist(self, key: str, payload: bytes, recv_ns: int, recv_mono: float | None = None) -> AppliedCommand | None:
        """Judge one twist command that arrived on ``key`` at ``recv_ns`` (wall clock, ns) and ``recv_mono``
        (monotonic, s; None: now) and drive the robot with what the supervisor allows (the control loop's thread).
        Returns the echo for state/applied,
        refusals included; None for a malformed command, which is counted and logged (it names no operator to
        answer), and for a forgery (a command in the owner's name that its session did not sign), counted in
        ``SafetyStatus.forged`` and logged, never answered."""
        try:
            cmd = TwistCommand.decode(payload)
        except DecodeError as exc:
            self.rejects.add(key, str(exc))
            self._rlog.warning(f"malformed:{keys.CMD_TWIST}", f"rejected malformed command on {key}: {exc}")
            return None
        ok, why = self.gate.check_command(key, keys.CMD_TWIST, cmd.operator)
        if not ok:
            # Refused at the door, before the supervisor: still answered, so the operator sees why.
            self.rejects.add(key, why)
            self._rlog.warning(f"gate:{keys.CMD_TWIST}", f"refused command from {cmd.operator!r}: {why}")
            return AppliedCommand(
                operator=cmd.operator, cmd_seq=cmd.seq, cmd_t=cmd.t, recv_t=recv_ns, accepted=False,
                status=Status.NOT_ALLOWED, reason=AppliedCommand.fit("reason", why),
            ).stamp(self._seq["applied"].next())
        with self.lock:
            pose = self.reading.tcp_pose if self.reading is not None else np.zeros(6)
            self._feed_contact_force()
            now = time.monotonic()
            # The deadman timeout runs from when the command *arrived*, not from when this thread got to it (on the
            # monotonic clock: a wall clock step in between would move the receipt, and the lease with it).
            received = now if recv_mono is None else min(now, recv_mono)
            goto = None
            if self.goto.active:
                markers = self._fresh_markers() if self.goto.aims_at_marker else None
                goto = self.goto.twist(pose, now, contact_off=self.supervisor.contact_off_reason, markers=markers).tolist()
            decision = self.supervisor.on_command(cmd, recv_ns / 1e9, received, pose, goto)
            if decision.cancel_goto:
                self._cancel_goto(decision.cancel_goto)
            self._log_interventions()
            self._drive(decision)
            if decision.accepted:
                self._last_cmd_seq, self._last_cmd_recv = cmd.seq, recv_ns
            elif not decision.answer:
                self._rlog.warning("forged", f"refused a forged command in the name of {cmd.operator!r} on {key}: "
                                   f"{decision.reason}")
                return None
            else:
                self._rlog.warning(f"refused:{decision.status}", f"refused command {cmd.seq} from {cmd.operator!r}: {decision.reason}")
            return AppliedCommand(
                operator=cmd.operator, cmd_seq=cmd.seq, cmd_t=cmd.t, recv_t=recv_ns,
                applied=self._commanded if decision.accepted else np.zeros(6),
                accepted=decision.accepted, status=decision.status, reason=decision.reason,
            ).stamp(self._seq["applied"].next())

    # ------------------------------------------------------------------ preview and goto (hold-to-run)

    def _cancel_goto(self, reason: str) -> None:
        if self.goto.cancel(reason):
            log.warning("move cancelled: %s", reason)

    def _limits(self) -> motion.Limits:
        p = self.supervisor.limits
        return self.goto.limits(p.linear, p.angular, self.config.safety.max_linear_acceleration)

    def _on_poses(self, query: zenoh.Query) -> None:
        req = self._request(query, keys.CONTROL_POSES)
        if req is None:
            return
        markers = sorted(self._fresh_markers())
        entries = [{"name": n} for n in [*self.config.goto.poses, motion.RETRACT, *(f"{motion.ABOVE_MARKER}{i}" for i in markers)]]
        entries += motion.primitives(markers, self.config.goto.marker_standoff)
        self._reply(query, True, f"{len(entries)} poses and primitives", (keys.CONTROL_POSES, req),
                    detail=json.dumps(entries))

    def _on_preview(self, query: zenoh.Query) -> None:
        req = self._request(query, keys.PLAN_PREVIEW)
        if req is None:
            return
        with self.lock:
            reading = self.reading
            limits = self._limits()
            owner = self.supervisor.owner
            impersonation = self.supervisor.impersonation(req, keys.PLAN_PREVIEW)
        if impersonation:  # (the plain plan/preview is open to every granted operator: a name there is a claim)
            self._reply(query, False, f"preview refused: {impersonation}", (keys.PLAN_PREVIEW, req))
            return
        if reading is None:
            self._reply(query, False, "no robot state yet", (keys.PLAN_PREVIEW, req))
            return
        try:
            params = json.loads(req.params) if req.params else {}
            if not isinstance(params, dict):
                raise ValueError("not a JSON object")
        except ValueError as exc:
            self._reply(query, False, f"preview {req.name!r}: params must be a JSON object ({exc})",
                        (keys.PLAN_PREVIEW, req))
            return
        # Planning (IK along the path, up to ~2 s) runs in the planner's child while this thread waits.
        pv = self.goto.preview(req.name, req.operator, reading.tcp_pose, time.monotonic(), limits,
                               self._fresh_markers(), self._joint_angles(reading), params, owner)
        (log.info if pv.ok else log.warning)("preview %r for %r: %s", req.name, req.operator, pv.plan.reason or "ok")
        self._reply(query, pv.ok, pv.plan.reason or f"preview of {req.name!r} accepted", (keys.PLAN_PREVIEW, req),
                    detail=json.dumps(pv.detail()))

    def _on_goto(self, query: zenoh.Query) -> None:
        req = self._request(query, keys.CONTROL_GOTO)
        if req is None:
            return
        markers = self._fresh_markers()
        with self.lock:
            refusal = self.supervisor.owner_refusal(req, keys.CONTROL_GOTO)
            if refusal:
                ok, reason = False, refusal
            elif self.reading is None:
                ok, reason = False, "no robot state yet"
            else:
                contact = self.supervisor.contact_target is not None
                ok, reason = self.goto.start(req.name, req.token, req.operator, self.reading.tcp_pose,
                                             time.monotonic(), self._limits(), contact=contact, markers=markers)
                if ok and contact and not self.goto.planar:
                    # Contact mode would hold the probe's axis against the move (a retreat lifts off on purpose).
                    self.supervisor.contact_off(f"{req.name!r} moves the probe along its axis")
                    reason += "; contact mode off"
        (log.info if ok else log.warning)("goto %r by %r: %s", req.name, req.operator, reason)
        self._reply(query, ok, reason, (keys.CONTROL_GOTO, req))

    # ------------------------------------------------------------------ control plane

    def _on_operator_liveliness(self, sample: zenoh.Sample) -> None:
        operator = keys.operator_from_alive_key(str(sample.key_expr))
        event = "operator_gone" if sample.kind == zenoh.SampleKind.DELETE else "operator_alive"
        if not self._control.put((event, operator)):
            # The owner's lease still ends its control (Supervisor.step), but later than this event would have.
            self._rlog.warning("control-queue", f"control queue full: {event} of {operator!r} dropped")

    def _queue_query(self, inbox: Inbox, verb: str, suffix: str) -> Callable[[zenoh.Query], None]:
        """A queryable's callback: the query waits in ``inbox`` for its thread, or, the inbox full, is answered
        at once that the edge is busy (a querier that is not answered waits out its timeout, not knowing why).
        With a reserve in the inbox, the owner's queries go ahead of everyone else's."""

        def on_query(query: zenoh.Query) -> None:
            ahead = inbox.reserve > 0 and self._signed_by_owner(query, suffix)
            if not inbox.put((verb, query), ahead=ahead):
                why = f"edge busy: {len(inbox)} requests are waiting before this {verb}; try again"
                self.rejects.add(str(query.key_expr), why)
                self._rlog.warning(f"busy:{verb}", f"refused a {verb} query: {why}")
                self._reply(query, False, why)

        return on_query

    def _signed_by_owner(self, query: zenoh.Query, suffix: str) -> bool:
        """Whether a query's request carries the signature of the grant that holds control (only checked here, in
        Zenoh's callback, to queue it; the sequence is checked where it is handled)."""
        if not self.supervisor.owner or query.payload is None:
            return False
        try:
            req = ControlRequest.decode(query.payload.to_bytes())
        except DecodeError:
            return False
        return self.supervisor.signed_by_owner(req, suffix)

    def _control_plane_loop(self, stop: threading.Event) -> None:
        handlers: dict[str, Callable[[Any], None]] = {
            "acquire": self._on_acquire,
            "release": self._on_release,
            "arm": self._on_arm,
            "operator_gone": self._on_operator_gone,
            "force_zero": self._on_force_zero,
            "operator_alive": self.gate.operator_alive,
            "goto": self._on_goto,
            "contact": self._on_contact,
        }
        while not stop.is_set():
            item = self._control.get()  # no polling: shutdown sets stop, then closes the inbox, which ends the wait
            if item is not None:
                handlers[item[0]](item[1])

    def _actuator_loop(self, stop: threading.Event) -> None:
        by_suffix = {keys.CMD_SERVO: self._on_servo, keys.CMD_TORCH: self._on_torch}
        while not stop.is_set():
            item = self._actuators.get()  # (as the control plane's)
            if item is not None:
                _, rest = keys.split_key(item[0])  # cmd/<kind>, or cmd/<kind>/<operator> with bound keys
                by_suffix["/".join(rest.split("/")[:2])](item)

    def _planner_loop(self, stop: threading.Event) -> None:
        handlers = {"preview": self._on_preview, "poses": self._on_poses}
        while not stop.is_set():
            item = self._planning.get()  # (as the control plane's)
            if item is not None:
                handlers[item[0]](item[1])

    def _request(self, query: zenoh.Query, suffix: str) -> ControlRequest | None:
        """The request of a ``control/<verb>`` query, or None once refused (malformed, or, with bound keys, in
        the name of another operator than the one the router authenticated for the key)."""
        payload = query.payload.to_bytes() if query.payload is not None else b""
        key = str(query.key_expr)
        try:
            req = ControlRequest.decode(payload)
        except DecodeError as exc:
            self.rejects.add(key, str(exc))
            self._reply(query, False, f"malformed request: {exc}")
            return None
        ok, why = self.gate.check_key(key, suffix, req.operator)
        if not ok:
            self.rejects.add(key, why)
            self._rlog.warning(f"gate:{suffix}", f"refused {suffix} from {req.operator!r}: {why}")
            self._reply(query, False, why, (suffix, req))
            return None
        return req

    def _reply(self, query: zenoh.Query, ok: bool, reason: str, to: tuple[str, ControlRequest] | None = None,
               signing_key: bytes | None = None, **extra: Any) -> None:
        """Answer a control query. The reply goes to the querier alone (Zenoh routes it back): the only way
        the acquire's key travels. ``to``: the decoded request and its key suffix: the answer carries the request's
        sequence and is signed for the owner (``signing_key``: the grant's, default the current one), see
        Supervisor.answer. Without it (a malformed request, a full queue) it is neither."""
        reply = ControlReply(ok=ok, reason=ControlReply.fit("reason", reason), owner=self.supervisor.owner, **extra)
        reply.stamp(to[1].seq if to is not None else 0)
        if to is None:
            payload = reply.encode()
        else:
            with self.lock:
                payload = self.supervisor.answer(to[0], reply, signing_key)
        try:
            query.reply(query.key_expr, payload)
        except zenoh.ZError as exc:
            log.warning("could not answer %s: %s", query.key_expr, exc)
        finally:
            query.drop()

    def _on_acquire(self, query: zenoh.Query) -> None:
        req = self._request(query, keys.CONTROL_ACQUIRE)
        if req is None:
            return
        ok, reason = self.gate.check_acquire(str(query.key_expr), keys.CONTROL_ACQUIRE, req.operator)
        key = b""
        # A console that cannot read all this edge sends would drive with part of its picture silently missing
        # (protocol's docstring): refused, saying both revisions and what to update; the answer says ours anyway.
        console = said_revision(req.params)
        if ok and (unreadable := unreadable_by(console, self._sent_to_consoles)):
            ok, reason = False, update_the_console(console, unreadable)
        if not ok:
            self.rejects.add(str(query.key_expr), reason)
        else:
            with self.lock:
                grant = self.supervisor.acquire(req, time.monotonic())
            ok, reason, key = grant.ok, grant.reason, grant.key
        if key or not ok:  # a new grant or a refusal; renewals (every lease/3) are not worth a line
            skew = f" (its console speaks protocol revision {console}, this edge {REVISION})" \
                if ok and console != REVISION else ""
            (log.info if ok else log.warning)("acquire by %r: %s%s", req.operator, reason, skew)
        self._reply(query, ok, reason, (keys.CONTROL_ACQUIRE, req), lease=self.config.safety.lease, key=key,
                    detail=revision_json())
        self._publish_safety(force=True)

    @functools.cached_property
    def _sent_to_consoles(self) -> list[type[Message]]:
        """The messages this edge sends a console: its robot's streams (but the actuators it has not) and answers."""
        absent = {ServoState: self.servos is None, TorchState: self.torch is None}
        streams = [MESSAGES_BY_KEY[c.suffix] for c in channels.TABLE
                   if c.kind is channels.Kind.PUT and channels.Role.EDGE in c.writers]
        return [cls for cls in dict.fromkeys(streams) if not absent.get(cls, False)] + [ControlReply]

    def _on_release(self, query: zenoh.Query) -> None:
        req = self._request(query, keys.CONTROL_RELEASE)
        if req is None:
            return
        with self.lock:
            grant_key = self.supervisor.grant_key  # the answer is signed with the key of the grant it ends
            ok, reason = self.supervisor.release(req)
            if ok and self.goto.active:
                self._cancel_goto("control released")
        self._wake()
        (log.info if ok else log.warning)("release by %r: %s", req.operator, reason)
        self._reply(query, ok, reason, (keys.CONTROL_RELEASE, req), grant_key)
        self._publish_safety(force=True)

    def _on_arm(self, query: zenoh.Query) -> None:
        req = self._request(query, keys.CONTROL_ARM)
        if req is None:
            return
        with self.lock:
            ok, reason = self.supervisor.request_arm(req.operator)
        log.info("arm request by %r: %s", req.operator, reason)
        self._reply(query, ok, reason, (keys.CONTROL_ARM, req))
        self._publish_safety(force=True)

    def _on_operator_gone(self, operator: str) -> None:
        self.gate.operator_gone(operator)
        with self.lock:
            if self.goto.operator == operator:
                self._cancel_goto(f"{operator!r} disappeared")
            lost = self.supervisor.owner_lost(operator, f"owner {operator!r} disappeared (liveliness lost)")
        if lost:
            self._wake()
            log.warning("owner %r lost: robot stopped, control released", operator)
            self._publish_safety(force=True)


    def _on_servo(self, item: tuple[str, bytes, int]) -> None:
        self._on_actuator(item, self.servos, ServoCommand, keys.CMD_SERVO, lambda cmd: self.servos.command(cmd.pan, cmd.tilt))  # type: ignore[union-attr]

    def _on_torch(self, item: tuple[str, bytes, int]) -> None:
        self._on_actuator(item, self.torch, TorchCommand, keys.CMD_TORCH, lambda cmd: self.torch.command(cmd.on, cmd.brightness))  # type: ignore[union-attr]

    def _on_actuator(self, item: tuple[str, bytes, int], unit: ServoUnit | TorchUnit | None,
                     cls: type[ServoCommand] | type[TorchCommand], suffix: str, apply: Callable[[Any], None]) -> None:
        """A servo or torch command: decoded, from the owner only; every refusal is published by the unit."""
        key, payload, _ = item
        name = suffix.rsplit("/", 1)[-1]
        if unit is None:
            self._rlog.warning(f"no-{name}", f"{name} command ignored: this robot has no {name} configured")
            return
        try:
            cmd = cls.decode(payload)
        except DecodeError as exc:
            self.rejects.add(key, str(exc))
            self._rlog.warning(f"malformed:{suffix}", f"rejected {name} command: {exc}")
            unit.reject(f"rejected: {exc}")
            return
        ok, why = self.gate.check_key(key, suffix, cmd.operator)
        with self.lock:
            refusal = why if not ok else self.supervisor.owner_refusal(cmd, suffix)
        if refusal:
            self._rlog.warning(f"{name}-owner", f"{name} command refused: {refusal}")
            unit.reject(f"refused: {refusal}")
            return
        apply(cmd)

    def _on_contact(self, query: zenoh.Query) -> None:
        """Contact mode on (name "on", params {"force": N}, default the configured target) or off (name "off"):
        the owner's signed request; shown in state/safety (contact_target) and logged."""
        req = self._request(query, keys.CONTROL_CONTACT)
        if req is None:
            return
        force: float | None = None
        try:
            params = json.loads(req.params) if req.params else {}
            if not isinstance(params, dict):
                raise ValueError("not a JSON object")
            if "force" in params:
                force = float(params["force"])
                if not math.isfinite(force):
                    raise ValueError("force is not a finite number")
        except (ValueError, TypeError) as exc:
            self._reply(query, False, f"contact: params must be a JSON object like {{\"force\": 4.0}} ({exc})",
                        (keys.CONTROL_CONTACT, req))
            return
        if req.name not in ("on", "off"):
            self._reply(query, False, f"contact: name must be 'on' or 'off', got {req.name[:20]!r}",
                        (keys.CONTROL_CONTACT, req))
            return
        with self.lock:
            ok, reason = self.supervisor.set_contact(req, req.name == "on", force)
            self._log_interventions()
        self._wake()
        (log.info if ok else log.warning)("contact by %r: %s", req.operator, reason)
        self._reply(query, ok, reason, (keys.CONTROL_CONTACT, req))
        self._publish_safety(force=True)

    def _on_force_zero(self, query: zenoh.Query) -> None:
        req = self._request(query, keys.CONTROL_FORCE_ZERO)
        if req is None:
            return
        with self.lock:
            refusal = self.supervisor.owner_refusal(req, keys.CONTROL_FORCE_ZERO) or self.supervisor.force_zero_refusal()
        if self.force is None:
            ok, reason = False, "this robot has no force sensor"
        elif refusal:
            ok, reason = False, refusal
        else:
            try:
                self.force.zero()
                ok, reason = True, "force sensor zeroed"
            except SensorError as exc:
                ok, reason = False, f"force sensor not zeroed: {exc}"
        (log.info if ok else log.warning)("force zero by %r: %s", req.operator, reason)
        self._reply(query, ok, reason, (keys.CONTROL_FORCE_ZERO, req))

    def _on_stop_sample(self, sample: zenoh.Sample) -> None:
        """A stop, acted on in Zenoh's callback: no queue to wait in behind other requests, none to be dropped
        from. Any payload on the key is a stop: a garbled or oversized one too (stopping is the safe side)."""
        key, size = str(sample.key_expr), len(sample.payload)
        problem = f"a stop command of {size} bytes (over the limit of {MAX_PAYLOAD})" if size > MAX_PAYLOAD else ""
        if not problem:
            try:
                cmd = StopCommand.decode(sample.payload.to_bytes())
            except DecodeError as exc:
                problem = f"malformed stop command ({exc.field}): {exc}"
        if problem:
            self.rejects.add(key, problem)
            cmd = StopCommand(operator="?", reason=StopCommand.fit("reason", problem))
        self._on_stop(key, cmd)

    def _on_stop(self, key: str, cmd: StopCommand) -> None:
        # Who sent it: the id in the key where the router binds keys to certificates, else only a claim.
        sender = operator_in_key(key, keys.CMD_STOP)
        who = (f"{sender!r}" if sender == cmd.operator else f"{sender!r} (claiming {cmd.operator!r})") if sender \
            else f"{cmd.operator!r} (unauthenticated)"
        with self.lock:
            # A stop on a robot that a stop already holds still changes nothing: it is logged (rate-limited) and
            # counted, without waking the control loop or publishing again (a page flooding stops, 50 000 a
            # second, held up the edge's state for seconds and cost the driving operator his lease).
            repeated = self.supervisor.stop_in_force
            if not repeated:
                self._cancel_goto(f"stop from {who}")
                self.supervisor.stop(f"{STOP_FROM}{who}: {cmd.reason}")
        self._rlog.warning(f"stop:{sender or cmd.operator}", f"stop from {who} on {key}: {cmd.reason}"
                           + (" (the robot was stopped already)" if repeated else ""))
        if repeated:
            self.repeated_stops += 1
            return
        self._wake()
        self._publish_safety(force=True)


def run(config: EdgeConfig) -> None:
    EdgeAgent(config).run_forever()


__all__ = ["AgentAlreadyOnline", "EdgeAgent", "run"]
