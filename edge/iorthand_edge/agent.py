"""The edge agent: the safety authority on the end-effector computer.

Threads (all named):
- ``control``: the control loop at the robot's rate — reads the robot, runs the supervisor's cycle (deadman
  timeout, limits), sends the twist, publishes ``state/robot`` and ``state/safety``.
- ``commands``: decodes twists as they arrive and applies them at once (low latency), publishing the
  supervisor's verdict on ``state/applied``.
- ``control-plane``: stop commands, ownership queries, operator liveliness, servo and torch commands and the
  force-zero request, in arrival order (only the owner may move the servos, switch the torch or zero the sensor).
- Optional components, each from its own config section and with its own named thread(s): ``edge-force``
  (sensor, warning levels; a change goes straight to the supervisor), ``edge-servos``, ``edge-torch``, and
  ``edge-video-<source>-capture/-send`` on a separate Zenoh session so video never delays control traffic.

Zenoh callbacks only queue bytes into bounded inboxes. The supervisor is shared under one lock; nothing outside
this process can move the robot except through it.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import signal
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh

from iorthand import geometry, keys, motion
from iorthand.cpu_latency import CpuLatencyHold
from iorthand.protocol import (
    AppliedCommand,
    ControlReply,
    ControlRequest,
    DecodeError,
    ForceLevel,
    Markers,
    RejectCounter,
    RobotState,
    SafetyStatus,
    Sequencer,
    ServoCommand,
    Status,
    StopCommand,
    TorchCommand,
    TwistCommand,
)
from iorthand.security import sdnotify
from iorthand.security.identity import CommandGate
from iorthand.transport import Inbox, Worker, open_session, publisher, subscribe
from iorthand_edge.actuators import ServoUnit, TorchUnit
from iorthand_edge.config import EdgeConfig
from iorthand_edge.force import LevelState, SensorError, contact_wrench, make_force_sensor
from iorthand_edge.force.monitor import ForceMonitor
from iorthand_edge.goto import GotoController, substitute
from iorthand_edge.perception.history import PoseHistory
from iorthand_edge.perception.pipeline import PerceptionPipeline
from iorthand_edge.robots import Robot, RobotFault, RobotReading, make_robot
from iorthand_edge.supervisor import Decision, Supervisor
from iorthand_edge.video import VideoStream, make_source

log = logging.getLogger("iorthand.edge")

# Twists waiting for the command thread: a flood keeps only the newest (each is a whole velocity command); the
# ones dropped unread are reported as SafetyStatus.superseded.
TWIST_QUEUE = 64

# Supervisor states that end a previewed move (it never resumes by itself; the operator previews again).
_HALTS = frozenset({
    Status.STOPPED, Status.FAULT, Status.OWNER_LOST, Status.FORCE_DANGER, Status.FORCE_STALE,
    Status.COMMAND_TIMEOUT, Status.DISARMED,
})


class RateLimitedLog:
    """Logs a repeated message once, then at most every ``interval`` seconds with a count (floods of garbage
    must not flood the log, but nothing is hidden)."""

    def __init__(self, logger: logging.Logger, interval: float = 5.0) -> None:
        self._log = logger
        self._interval = interval
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warning(self, key: str, msg: str) -> None:
        now = time.monotonic()
        if now - self._last.get(key, -math.inf) >= self._interval:
            extra = self._suppressed.pop(key, 0)
            self._log.warning("%s%s", msg, f" (+{extra} similar)" if extra else "")
            self._last[key] = now
        else:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1


class EdgeAgent:
    def __init__(self, config: EdgeConfig, robot: Robot | None = None) -> None:
        self.config = config
        self.keys = keys.RobotKeys(config.robot_id)
        self.robot = robot if robot is not None else make_robot(config.robot)
        self.period = self.robot.control_period
        self.supervisor = Supervisor(config.safety, period=self.period, force_required=config.force is not None)
        self.lock = threading.RLock()
        self.stop_event = threading.Event()
        self.rejects = RejectCounter()
        self.reading: RobotReading | None = None
        self._seq = {name: Sequencer() for name in ("robot", "safety", "applied")}
        self._commanded = np.zeros(6)
        self._last_cmd_seq = 0
        self._last_cmd_recv = 0
        self._last_safety: tuple[Any, ...] | None = None
        self._last_safety_pub = 0.0
        self._twists = Inbox(TWIST_QUEUE, keep="newest")
        self._control = Inbox(256, keep="oldest")
        self._workers: list[Worker] = []
        self._rlog = RateLimitedLog(log)
        self.session: zenoh.Session | None = None
        # Components (force, servos, perception, video) register per-cycle hooks here.
        self.cycle_hooks: list[Callable[[RobotReading], None]] = []
        self.force: ForceMonitor | None = None
        if config.force is not None:
            sensor = make_force_sensor(config.force.sensor, config.phantom, lambda: self.reading)
            self.force = ForceMonitor(config.force, sensor, self._on_force_change)
        self.servos = ServoUnit(config.servos) if config.servos is not None else None
        self.torch = TorchUnit(config.torch) if config.torch is not None else None
        self.video: list[VideoStream] = []
        if config.video is not None:
            for name, suffix, stream in (
                ("camera", keys.VIDEO_CAMERA, config.video.camera),
                ("ultrasound", keys.VIDEO_ULTRASOUND, config.video.ultrasound),
            ):
                if stream is not None:
                    shared = self._perception_image if config.perception is not None else None
                    source = make_source(stream, self._contact_force, shared)
                    self.video.append(VideoStream(name, suffix, stream, source))
        self.video_session: zenoh.Session | None = None
        self.gate = CommandGate(
            allowed=list(config.safety.allowed_operators),
            require_alive=config.require_operator_alive,
            bind_keys=config.bind_operator_keys,
        )
        self.goto = GotoController(config.goto, config.safety.workspace.min, config.safety.workspace.max)
        self.markers: dict[int, np.ndarray] = {}  # latest filtered T_base_marker per id (for above_marker:<id>)
        self.markers_at = -math.inf  # time.monotonic() when self.markers was set
        self.perception: PerceptionPipeline | None = None
        self.pose_history: PoseHistory | None = None
        if config.perception is not None:
            self.pose_history = PoseHistory(config.perception.history_span, config.perception.max_extrapolation)
            # Raises PerceptionError (a calibration for another image size, a corrupt file): refuse to start.
            self.perception = PerceptionPipeline(
                config.perception, self.pose_history.at, self._servo_angles_at, self._publish_markers
            )
            self.cycle_hooks.append(
                lambda r: self.pose_history.add(r.timestamp_ns, geometry.pose_to_matrix(r.tcp_pose))  # type: ignore[union-attr]
            )
        self.cycle_hooks.append(sdnotify.cycle_hook())  # systemd: READY once, then the watchdog from the loop
        self._local_server: socket.socket | None = None
        # Servos, torch and video stop with the agent but a crash of theirs must not stop the robot's control:
        # they get their own stop event. The force worker shares the agent's: losing it is a safety fault.
        self._aux_stop = threading.Event()
        self._cpu_latency: CpuLatencyHold | None = None

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        if self.config.cpu_latency_us is not None:
            self._cpu_latency = CpuLatencyHold(self.config.cpu_latency_us)
        self.robot.connect()
        self.reading = self.robot.read_state()
        self.session = open_session(self.config.zenoh, stop=self.stop_event)
        s, k = self.session, self.keys
        self._pub_robot = publisher(s, k.key(keys.STATE_ROBOT))
        self._pub_safety = publisher(s, k.key(keys.STATE_SAFETY))
        self._pub_applied = publisher(s, k.key(keys.STATE_APPLIED))
        self._pub_markers = publisher(s, k.key(keys.MARKERS))
        # With bound keys, operators command on .../cmd/twist/<id> and query .../control/<verb>/<id>, keys the
        # router's ACL grants only to that operator's certificate (iorthand.security.identity).
        bound = "/*" if self.config.bind_operator_keys else ""
        self._declared = [
            subscribe(s, k.key(keys.CMD_TWIST) + bound, self._twists),
            subscribe(s, k.key(keys.CMD_STOP), self._control),
            subscribe(s, k.key(keys.CMD_SERVO), self._control),
            subscribe(s, k.key(keys.CMD_TORCH), self._control),
            s.declare_queryable(k.key(keys.CONTROL_FORCE_ZERO) + bound, lambda q: self._control.put(("force_zero", q))),
            s.declare_queryable(k.key(keys.CONTROL_ACQUIRE) + bound, lambda q: self._control.put(("acquire", q))),
            s.declare_queryable(k.key(keys.CONTROL_RELEASE) + bound, lambda q: self._control.put(("release", q))),
            s.declare_queryable(k.key(keys.CONTROL_ARM) + bound, lambda q: self._control.put(("arm", q))),
            s.declare_queryable(k.key(keys.CONTROL_PREVIEW) + bound, lambda q: self._control.put(("preview", q))),
            s.declare_queryable(k.key(keys.CONTROL_GOTO) + bound, lambda q: self._control.put(("goto", q))),
            s.declare_queryable(k.key(keys.CONTROL_POSES) + bound, lambda q: self._control.put(("poses", q))),
            s.liveliness().declare_subscriber(k.alive_operators, self._on_operator_liveliness, history=True),
        ]
        self._token = s.liveliness().declare_token(k.key(keys.ALIVE_EDGE))
        # The control loop and the command path run at real-time priority where allowed (root on the Pi):
        # both block between short bursts, so they cannot starve the rest.
        for name, fn, rt in (("control", self._control_loop, True), ("commands", self._command_loop, True),
                             ("control-plane", self._control_plane_loop, False)):
            w = Worker(f"edge-{name}", fn, self.stop_event, realtime=rt and self.config.realtime)
            w.start()
            self._workers.append(w)
        self._start_components()
        self._start_local_socket()
        log.info(
            "edge agent %r up: robot %s, %s, armed=%s, profile %s (%.0f mm/s), CPU wake-up latency %s",
            self.config.robot_id, type(self.robot).__name__, ", ".join(self.config.zenoh.connect) or self.config.zenoh.mode,
            self.supervisor.armed, self.supervisor.profile, 1000 * self.supervisor.limits.linear,
            self._cpu_latency.state if self._cpu_latency else "as the host sets it",
        )
        for setting_name, why in self.config.warnings():
            log.warning("%s: %s", setting_name, why)

    def _start_components(self) -> None:
        assert self.session is not None
        if self.perception is not None:
            self.perception.start()
        if self.force is not None:
            self.force.start(self.session, self.keys, self.stop_event)
        for unit in (self.servos, self.torch):
            if unit is not None:
                unit.start(self.session, self.keys, self._aux_stop)
        if self.video:
            # Video gets a session of its own: its large samples then never share a receive path or a
            # transmission queue with commands (FACTS: a busy session delays everything on it).
            assert self.config.video is not None
            self.video_session = open_session(self.config.video.zenoh or self.config.zenoh, stop=self.stop_event)
            for stream in self.video:
                stream.start(self.video_session, self.keys, self._aux_stop)

    def _stop_components(self) -> None:
        self._aux_stop.set()
        if self.perception is not None:
            self.perception.stop()
        if self._local_server is not None:
            self._local_server.close()
        for comp in (self.force, self.servos, self.torch, *self.video):
            if comp is not None:
                comp.join()
        if self.video_session is not None:
            self.video_session.close()
            self.video_session = None

    def run_forever(self) -> None:
        self.start()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: self.stop_event.set())
        self.stop_event.wait()
        self.shutdown()

    def shutdown(self) -> None:
        self.stop_event.set()
        self._twists.close()
        self._control.close()
        for w in self._workers:
            w.join(timeout=2.0)
        self._stop_components()
        with self.lock:
            self.supervisor.disarm("edge agent shutting down")
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
        log.info("armed by local confirmation")
        self._publish_safety(force=True)

    def disarm(self, reason: str) -> None:
        with self.lock:
            self.supervisor.disarm(reason)
            self._drive(Decision([0.0] * 6, False, Status.DISARMED))
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
                conn.sendall((self.local_command(line) + "\n").encode())

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
            with self.lock:
                reading = self.robot.read_state()
                self.reading = reading
                fault = reading.fault or ("" if reading.connected else "robot link lost")
                if fault != self.supervisor.fault:
                    if fault:
                        log.error("robot fault: %s — stopping", fault)
                    self.supervisor.set_fault(fault)
                decision = self.supervisor.step(now, reading.tcp_pose)
                if self.goto.active and decision.status in _HALTS:
                    self._cancel_goto(decision.reason or decision.status)
                self._drive(decision)
                self._log_interventions()
                state = RobotState(
                    tcp_pose=reading.tcp_pose, tcp_speed=reading.tcp_speed, q=reading.q,
                    commanded=self._commanded, mode=reading.mode, connected=reading.connected,
                    fault=fault, robot_time=reading.robot_time,
                    cmd_seq=self._last_cmd_seq, cmd_recv_t=self._last_cmd_recv,
                ).stamp(self._seq["robot"].next(), reading.timestamp_ns)
            for hook in self.cycle_hooks:
                hook(reading)
            self._pub_robot.put(state.encode())
            self._publish_safety()
            now = time.monotonic()
            if now >= next_tick:  # this cycle was a tick (not an early wake for the deadman)
                next_tick += self.period
                if next_tick <= now:
                    next_tick = now + self.period  # overran: do not try to catch up with a burst
            # Wake at the next tick, or earlier when the deadman times out before it.
            wake = min(next_tick, self.supervisor.timeout_at() + 1e-4)
            if wake > now:
                stop.wait(wake - now)

    def _drive(self, decision: Decision) -> None:
        """Send the decided twist to the robot (caller holds the lock). A zero twist after motion is a stop
        with the configured deceleration; the UR driver keeps its watchdog kicked on its own."""
        twist = decision.twist
        try:
            if any(twist):
                self._commanded = self.robot.send_twist(twist, self.config.safety.max_linear_acceleration)
            elif self._commanded.any():
                self.robot.stop(self.config.safety.stop_deceleration)
                self._commanded = np.zeros(6)
        except RobotFault as exc:
            self._commanded = np.zeros(6)
            log.error("robot refused the command: %s — stopping", exc)
            self.supervisor.set_fault(str(exc))
            self.robot.stop(self.config.safety.stop_deceleration)

    def _log_interventions(self) -> None:
        """Log each safety intervention of the supervisor once, with its reason (caller holds the lock)."""
        if self.supervisor.interventions:
            for status, reason in self.supervisor.interventions:
                log.warning("safety intervention [%s]: %s", status, reason)
            self.supervisor.interventions.clear()

    # ------------------------------------------------------------------ components

    def _on_force_change(self, state: LevelState) -> None:
        """From the force thread: a new level or staleness goes to the supervisor and takes effect at once
        (not at the next control cycle)."""
        with self.lock:
            now = time.monotonic()
            self.supervisor.update_force(state.level, state.stale, now)
            pose = self.reading.tcp_pose if self.reading is not None else np.zeros(6)
            self._drive(self.supervisor.step(now, pose))
            self._log_interventions()
        self._publish_safety(force=True)

    def _perception_image(self) -> np.ndarray | None:
        return self.perception.latest_image if self.perception is not None else None

    def _servo_angles_at(self, t_ns: int) -> tuple[float, float]:
        """Servo angles (rad, as the servos report them) at a camera frame's time. Without servos the camera
        is fixed at the chain's zero (``perception.geometry.pan_zero``/``tilt_zero``)."""
        if self.servos is not None:
            return self.servos.servo_angles_at(t_ns)
        assert self.config.perception is not None
        return self.config.perception.geometry.pan_zero, self.config.perception.geometry.tilt_zero

    def _publish_markers(self, msg: Markers) -> None:
        """From the perception thread: publish, and keep the filtered poses for ``above_marker:<id>``."""
        self.markers, self.markers_at = {m.id: geometry.unflatten(m.pose) for m in msg.markers}, time.monotonic()
        self._pub_markers.put(msg.encode())

    def _fresh_markers(self) -> dict[int, np.ndarray]:
        """The marker poses a move may aim at: none once they are older than ``goto.marker_max_age`` (the
        camera failed or stalled, and the patient may have moved since)."""
        if time.monotonic() - self.markers_at > self.config.goto.marker_max_age:
            return {}
        return dict(self.markers)

    def _contact_force(self) -> float:
        """The contact force (N) the simulated ultrasound image responds to."""
        if self.force is not None:
            return 0.0 if self.force.state.stale else self.force.state.value
        reading = self.reading
        if self.config.phantom is not None and reading is not None:
            return float(np.linalg.norm(contact_wrench(self.config.phantom, reading.tcp_pose, reading.tcp_speed)[:3]))
        return 0.0

    def _publish_safety(self, force: bool = False) -> None:
        with self.lock:
            sv = self.supervisor
            c = sv.counters
            age = sv.command_age(time.monotonic())
            fields = (
                sv.armed, sv.arm_requested, sv.owner, sv.deadman, sv.profile, sv.status, sv.reason,
                tuple(sv.limits_hit), int(sv.force_level), sv.force_stale,
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
                malformed=self.rejects.total, superseded=self.twists_superseded, stops=c.stops,
            ).stamp(self._seq["safety"].next())
            # Put under the lock: two threads publishing at once must not reorder the sequence numbers.
            self._pub_safety.put(msg.encode())

    # ------------------------------------------------------------------ commands

    def _command_loop(self, stop: threading.Event) -> None:
        while not stop.is_set():
            item = self._twists.get(timeout=0.1)
            if item is None:
                continue
            echo = self.handle_twist(*item)
            if echo is not None:
                self._pub_applied.put(echo.encode())

    @property
    def twists_superseded(self) -> int:
        """Twist commands dropped unread: newer ones queued behind them while the command thread was busy."""
        return self._twists.dropped

    def handle_twist(self, key: str, payload: bytes, recv_ns: int) -> AppliedCommand | None:
        """Judge one twist command that arrived on ``key`` at ``recv_ns`` (wall clock, ns) and drive the robot
        with what the supervisor allows. Returns the echo for state/applied, refusals included; None for a
        malformed command, which is counted and logged (it names no operator to answer)."""
        try:
            cmd = TwistCommand.decode(payload)
        except DecodeError as exc:
            self.rejects.add(key, str(exc))
            self._rlog.warning(f"malformed:{key}", f"rejected malformed command on {key}: {exc}")
            return None
        ok, why = self.gate.check_command(key, keys.CMD_TWIST, cmd.operator)
        if not ok:
            # Refused at the door, before the supervisor: still answered, so the operator sees why.
            self.rejects.add(key, why)
            self._rlog.warning(f"gate:{key}", f"refused command from {cmd.operator!r}: {why}")
            return AppliedCommand(
                operator=cmd.operator, cmd_seq=cmd.seq, cmd_t=cmd.t, recv_t=recv_ns, accepted=False,
                status=Status.NOT_ALLOWED, reason=why[:200],
            ).stamp(self._seq["applied"].next())
        with self.lock:
            pose = self.reading.tcp_pose if self.reading is not None else np.zeros(6)
            now = time.monotonic()
            # The deadman timeout runs from when the command *arrived*, not from when this thread got to it.
            received = now - max(0.0, (time.time_ns() - recv_ns) / 1e9)
            if self.goto.active:
                cmd = self._goto_command(cmd, pose, now)
            decision = self.supervisor.on_command(cmd, recv_ns / 1e9, received, pose)
            if self.goto.active and not decision.accepted:
                self._cancel_goto(decision.reason)
            self._log_interventions()
            if decision.accepted:
                self._drive(decision)
                self._last_cmd_seq, self._last_cmd_recv = cmd.seq, recv_ns
            else:
                self._rlog.warning(f"refused:{decision.status}", f"refused command {cmd.seq} from {cmd.operator!r}: {decision.reason}")
            return AppliedCommand(
                operator=cmd.operator, cmd_seq=cmd.seq, cmd_t=cmd.t, recv_t=recv_ns,
                applied=self._commanded if decision.accepted else np.zeros(6),
                accepted=decision.accepted, status=decision.status, reason=decision.reason,
            ).stamp(self._seq["applied"].next())

    # ------------------------------------------------------------------ preview and goto (hold-to-run)

    def _goto_command(self, cmd: TwistCommand, pose: np.ndarray, now: float) -> TwistCommand:
        """While a previewed move runs, the operator holds the deadman and the edge supplies the velocity. A
        released deadman, another operator or a non-zero twist (the operator takes over) cancels it."""
        if not cmd.deadman:
            self._cancel_goto("deadman released")
        elif cmd.operator != self.goto.operator:
            self._cancel_goto(f"command from {cmd.operator!r} during {self.goto.operator!r}'s move")
        elif any(cmd.linear) or any(cmd.angular):
            self._cancel_goto("the operator took over with a manual twist")
        else:
            return substitute(cmd, self.goto.twist(pose, now))
        return cmd

    def _cancel_goto(self, reason: str) -> None:
        if self.goto.cancel(reason):
            log.warning("move cancelled: %s", reason)

    def _limits(self) -> motion.Limits:
        p = self.supervisor.limits
        return self.goto.limits(p.linear, p.angular, self.config.safety.max_linear_acceleration)

    def _on_poses(self, query: zenoh.Query) -> None:
        if self._request(query) is None:
            return
        names = [*self.config.goto.poses, "retract", *(f"above_marker:{i}" for i in sorted(self._fresh_markers()))]
        detail = json.dumps([{"name": n} for n in names])
        self._reply(query, True, f"{len(names)} poses", detail=detail)

    def _on_preview(self, query: zenoh.Query) -> None:
        req = self._request(query)
        if req is None:
            return
        with self.lock:
            reading = self.reading
            limits = self._limits()
        if reading is None:
            self._reply(query, False, "no robot state yet")
            return
        # Planning (IK along the path) takes up to ~0.2 s: outside the lock, on this control-plane thread.
        pv = self.goto.preview(req.name, req.operator, reading.tcp_pose, time.monotonic(), limits,
                               self._fresh_markers(), reading.q)
        (log.info if pv.ok else log.warning)("preview %r for %r: %s", req.name, req.operator, pv.plan.reason or "ok")
        self._reply(query, pv.ok, pv.plan.reason or f"preview of {req.name!r} accepted", detail=json.dumps(pv.detail()))

    def _on_goto(self, query: zenoh.Query) -> None:
        req = self._request(query)
        if req is None:
            return
        with self.lock:
            refusal = self._not_owner(req.operator)
            if refusal:
                ok, reason = False, refusal
            elif self.reading is None:
                ok, reason = False, "no robot state yet"
            else:
                ok, reason = self.goto.start(req.name, req.token, req.operator, self.reading.tcp_pose,
                                             time.monotonic(), self._limits())
        (log.info if ok else log.warning)("goto %r by %r: %s", req.name, req.operator, reason)
        self._reply(query, ok, reason)

    # ------------------------------------------------------------------ control plane

    def _on_operator_liveliness(self, sample: zenoh.Sample) -> None:
        operator = keys.operator_from_alive_key(str(sample.key_expr))
        if sample.kind == zenoh.SampleKind.DELETE:
            self._control.put(("operator_gone", operator))
        else:
            self._control.put(("operator_alive", operator))

    def _control_plane_loop(self, stop: threading.Event) -> None:
        handlers: dict[str, Callable[[Any], None]] = {
            "acquire": self._on_acquire,
            "release": self._on_release,
            "arm": self._on_arm,
            "operator_gone": self._on_operator_gone,
            "force_zero": self._on_force_zero,
            "operator_alive": self.gate.operator_alive,
            "preview": self._on_preview,
            "goto": self._on_goto,
            "poses": self._on_poses,
        }
        by_key = {self.keys.key(keys.CMD_SERVO): self._on_servo, self.keys.key(keys.CMD_TORCH): self._on_torch}
        while not stop.is_set():
            item = self._control.get(timeout=0.1)
            if item is None:
                continue
            if isinstance(item[0], str) and item[0] in handlers:
                handlers[item[0]](item[1])
            elif item[0] in by_key:
                by_key[item[0]](item)
            else:
                self._on_stop(item)

    def _request(self, query: zenoh.Query) -> ControlRequest | None:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        try:
            return ControlRequest.decode(payload)
        except DecodeError as exc:
            self.rejects.add(str(query.key_expr), str(exc))
            self._reply(query, False, f"malformed request: {exc}")
            return None

    def _reply(self, query: zenoh.Query, ok: bool, reason: str, **extra: Any) -> None:
        reply = ControlReply(ok=ok, reason=reason, owner=self.supervisor.owner, **extra).stamp(0)
        try:
            query.reply(query.key_expr, reply.encode())
        except zenoh.ZError as exc:
            log.warning("could not answer %s: %s", query.key_expr, exc)
        finally:
            query.drop()

    def _on_acquire(self, query: zenoh.Query) -> None:
        req = self._request(query)
        if req is None:
            return
        ok, reason = self.gate.check_acquire(str(query.key_expr), keys.CONTROL_ACQUIRE, req.operator)
        if not ok and req.operator not in self.gate.alive and self._operator_token_present(req.operator):
            # The operator's token and its acquire race through the router: ask Zenoh before refusing.
            self.gate.operator_alive(req.operator)
            ok, reason = self.gate.check_acquire(str(query.key_expr), keys.CONTROL_ACQUIRE, req.operator)
        if not ok:
            self.rejects.add(str(query.key_expr), reason)
        else:
            with self.lock:
                ok, reason = self.supervisor.acquire(req.operator, time.monotonic(), req.profile)
        (log.info if ok else log.warning)("acquire by %r: %s", req.operator, reason)
        self._reply(query, ok, reason, lease=self.config.safety.lease)
        self._publish_safety(force=True)

    def _operator_token_present(self, operator: str) -> bool:
        """Whether ``operator``'s liveliness token exists right now (a bounded liveliness query)."""
        if self.session is None or not self.config.require_operator_alive:
            return False
        try:
            replies = self.session.liveliness().get(self.keys.alive_operator(operator), timeout=0.5)
            return any(reply.ok is not None for reply in replies)
        except (zenoh.ZError, keys.KeyExprError):
            return False

    def _on_release(self, query: zenoh.Query) -> None:
        req = self._request(query)
        if req is None:
            return
        with self.lock:
            ok, reason = self.supervisor.release(req.operator)
        log.info("release by %r: %s", req.operator, reason)
        self._reply(query, ok, reason)
        self._publish_safety(force=True)

    def _on_arm(self, query: zenoh.Query) -> None:
        req = self._request(query)
        if req is None:
            return
        with self.lock:
            ok, reason = self.supervisor.request_arm(req.operator)
        log.info("arm request by %r: %s", req.operator, reason)
        self._reply(query, ok, reason)
        self._publish_safety(force=True)

    def _on_operator_gone(self, operator: str) -> None:
        self.gate.operator_gone(operator)
        with self.lock:
            if self.goto.operator == operator:
                self._cancel_goto(f"{operator!r} disappeared")
            lost = self.supervisor.owner_lost(operator, f"owner {operator!r} disappeared (liveliness lost)")
            if lost:
                self._drive(Decision([0.0] * 6, False, Status.OWNER_LOST))
        if lost:
            log.warning("owner %r lost: robot stopped, control released", operator)
            self._publish_safety(force=True)

    def _not_owner(self, operator: str) -> str:
        owner = self.supervisor.owner
        if operator == owner and owner:
            return ""
        return f"{operator!r} does not hold control" + (f" ({owner!r} does)" if owner else " (nobody does)")

    def _on_servo(self, item: tuple[str, bytes, int]) -> None:
        self._on_actuator(item, self.servos, ServoCommand, "servo", lambda cmd: self.servos.command(cmd.pan, cmd.tilt))  # type: ignore[union-attr]

    def _on_torch(self, item: tuple[str, bytes, int]) -> None:
        self._on_actuator(item, self.torch, TorchCommand, "torch", lambda cmd: self.torch.command(cmd.on, cmd.brightness))  # type: ignore[union-attr]

    def _on_actuator(self, item: tuple[str, bytes, int], unit: ServoUnit | TorchUnit | None,
                     cls: type[ServoCommand] | type[TorchCommand], name: str, apply: Callable[[Any], None]) -> None:
        """A servo or torch command: decoded, from the owner only; every refusal is published by the unit."""
        key, payload, _ = item
        if unit is None:
            self._rlog.warning(f"no-{name}", f"{name} command ignored: this robot has no {name} configured")
            return
        try:
            cmd = cls.decode(payload)
        except DecodeError as exc:
            self.rejects.add(key, str(exc))
            self._rlog.warning(f"malformed:{key}", f"rejected {name} command: {exc}")
            unit.reject(f"rejected: {exc}")
            return
        with self.lock:
            refusal = self._not_owner(cmd.operator)
        if refusal:
            self._rlog.warning(f"{name}-owner", f"{name} command refused: {refusal}")
            unit.reject(f"refused: {refusal}")
            return
        apply(cmd)

    def _on_force_zero(self, query: zenoh.Query) -> None:
        req = self._request(query)
        if req is None:
            return
        with self.lock:
            refusal = self._not_owner(req.operator)
        state = self.force.state if self.force is not None else None
        if self.force is None or state is None:
            ok, reason = False, "this robot has no force sensor"
        elif refusal:
            ok, reason = False, refusal
        elif state.stale or state.level != ForceLevel.SAFE:
            # Zeroing in contact would hide the contact force from every threshold afterwards.
            ok, reason = False, f"force sensor not zeroed: level {int(state.level)}{', stale' if state.stale else ''}; lift the tool out of contact first"
        else:
            try:
                self.force.zero()
                ok, reason = True, "force sensor zeroed"
            except SensorError as exc:
                ok, reason = False, f"force sensor not zeroed: {exc}"
        (log.info if ok else log.warning)("force zero by %r: %s", req.operator, reason)
        self._reply(query, ok, reason)

    def _on_stop(self, item: tuple[str, bytes, int]) -> None:
        key, payload, _ = item
        try:
            cmd = StopCommand.decode(payload)
        except DecodeError as exc:
            # A garbled stop is still a stop request: stopping is always the safe side.
            self.rejects.add(key, str(exc))
            cmd = StopCommand(operator="?", reason=f"malformed stop command ({exc.field})")
        with self.lock:
            self._cancel_goto(f"stop from {cmd.operator!r}")
            self.supervisor.stop(f"stop from {cmd.operator!r}: {cmd.reason}")
            self._drive(Decision([0.0] * 6, False, Status.STOPPED))
        log.warning("stop from %r: %s", cmd.operator, cmd.reason)
        self._publish_safety(force=True)


def run(config: EdgeConfig) -> None:
    EdgeAgent(config).run_forever()


__all__ = ["EdgeAgent", "run"]
