"""Perception and video in a process of their own, so that they never take the control loop's CPU or GIL.

The synthetic camera, the ultrasound simulator, ArUco detection and JPEG encoding were most of the edge's CPU
(a profile of the demo: 47 %, 17 %, 8 % and 5 % of the samples; the commands 0.5 %). In the agent's process
they shared the GIL with the control loop, which then missed its deadlines on a loaded machine. Here they run
in a child of the agent that opens its own Zenoh session from the edge config and publishes on the same keys
as before (``markers``, ``video/camera``, ``video/ultrasound``): the twin, the recorder and the operator see no
difference.

What they need from the control process arrives through Zenoh, like any other subscriber's: the TCP pose at a
frame's time (``state/robot`` into a :class:`PoseHistory`), the servo angles (``state/servo``) and the contact
force of the simulated ultrasound image (``state/force_level``; with no force sensor, the phantom's contact
computed from ``state/robot``), and who holds control (``state/safety``: the video's bitrate follows that
operator's reports, :func:`sets_bitrate`). They wait in Zenoh's own ring buffers (``RingChannel``: no Python callback, no
thread woken per sample) and are decoded when a frame needs them (:meth:`MediaService.pose_at` and the others
drain the rings first): a burst of ~8 robot states per camera frame instead of 125 wake-ups a second, each of
which made a state cost ~0.5 ms on this VM instead of 0.04.

The child (``spawn``: a fresh interpreter, never a fork of a process that holds Zenoh threads) runs at a lower
CPU priority (nice :data:`MEDIA_NICE`) and dies with its parent (PR_SET_PDEATHSIG and a parent-pid check). The
agent's side, :class:`MediaProcess`, restarts it after a crash with back-off and logs why it ended; while it is
down the agent publishes the reason on the video and marker keys so that the twin clears the picture instead of
freezing it. Perception and video are not safety-critical: nothing here can stop or fault the robot.
"""

from __future__ import annotations

import contextlib
import logging
import math
import multiprocessing as mp
import os
import sys
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import cv2
import numpy as np
import zenoh

from iorthand import keys, logs
from iorthand.process import enter_child, exit_reason, name_thread
from iorthand.protocol import (
    DecodeError,
    ForceLevelState,
    Markers,
    RejectCounter,
    RobotState,
    SafetyStatus,
    ServoState,
    VideoFeedback,
    VideoFrame,
)
from iorthand.security.identity import operator_in_key
from iorthand.transport import Worker, open_session, publisher
from iorthand_edge.config import EdgeConfig
from iorthand_edge.force import contact_wrench
from iorthand_edge.perception.history import PoseHistory, ServoHistory, servo_max_age
from iorthand_edge.perception.pipeline import PerceptionPipeline
from iorthand_edge.video import VideoError, VideoStream, make_source

log = logging.getLogger("iorthand.edge.media")

MEDIA_NICE = 10  # the child's niceness: on a busy 2-4 core computer the kernel runs the control process first
# (Measured, benchmarks/results/command_path_media_priority.json, one interleaved run: with 30 fps video the
# command p99 was 6.9 ms at nice 10, 6.8 at nice 19 and 3.7 with SCHED_IDLE, against 1.8 without video. SCHED_IDLE
# was not taken: one noisy run (the bare echo's p99 doubled in that phase), still over the 1.3x target, and a
# SCHED_IDLE process runs only when nothing else wants the CPU, so any busy process would freeze the video.)
RESTART_MIN_S = 1.0  # back-off before restarting a crashed child, doubling up to RESTART_MAX_S
RESTART_MAX_S = 30.0
STOP_GRACE_S = 3.0  # s the child gets to close its camera and session after the stop flag
STABLE_S = 30.0  # a child that ran this long before crashing starts the back-off from RESTART_MIN_S again
RING_SIZE = 512  # state samples kept per key until a frame asks: 4 s of state/robot at 125 Hz
# The viewers' reports kept until a stream's next frame (each viewer sends ~1 a second per stream, and one at once
# when it needs a keyframe). A flood pushes real reports out, and costs Zenoh's ring, not a Python callback each.
FEEDBACK_RING = 64
FORCE_MAX_AGE = 0.5  # s: an older force level (or none) counts as no contact for the ultrasound image
_PARENT_CHECK_S = 0.25


def sets_bitrate(owner: str, sender: str) -> bool:
    """Whether a viewer's report moves the stream's bitrate. One stream serves every viewer, and it followed the
    worst: a watcher on a poor link (or any granted session's loss reports, one a second) cut the picture of the
    operator driving the robot from 2 000 to 200 kbit/s. While someone holds control the stream follows that
    operator's reports (and the sender's own congestion signals); the others' still get their keyframes."""
    return not owner or sender == owner


def needs_media(config: EdgeConfig) -> bool:
    return config.video is not None or config.perception is not None


def check_config(config: EdgeConfig) -> None:
    """Raise what the child would fail on at start, so that a bad calibration or video section still refuses to
    start the agent (as when the pipeline was built in the agent) instead of looping through restarts."""
    if config.perception is not None:
        # The pipeline's constructor loads and checks the calibration files (PerceptionError says why).
        PerceptionPipeline(config.perception, lambda _t: None, lambda _t: None, lambda _m: None)
    if config.video is not None:
        for name, stream in (("camera", config.video.camera), ("ultrasound", config.video.ultrasound)):
            if stream is None or stream.source != "perception":
                continue
            if config.perception is None:
                raise VideoError("video source 'perception' needs the perception section (its camera feeds the video)")
            # The stream sends the perception camera's images as they are: an H.264 encoder takes only the size
            # it was opened with, and a JPEG stream's configured size would misstate what it sends.
            size = config.perception.camera.image_size()
            if size is not None and tuple(size) != (stream.width, stream.height):
                raise VideoError(
                    f"video.{name} ({stream.width}×{stream.height}) takes its frames from the perception camera, "
                    f"which delivers {size[0]}×{size[1]}: set video.{name}.width/height to {size[0]} and {size[1]}"
                )


# ---------------------------------------------------------------------------------------------------------
# The child.


class MediaService:
    """Everything that runs in the child: the state subscriptions, the perception pipeline, the video streams."""

    def __init__(self, config: EdgeConfig) -> None:
        self.config = config
        self.keys = keys.RobotKeys(config.robot_id)
        self.stop = threading.Event()  # the video streams' stop
        self.rejects = RejectCounter()
        self._rings: dict[str, Any] = {}  # key → its subscriber with a RingChannel, drained on demand
        self._drain_lock = threading.Lock()  # the camera and the ultrasound threads both drain
        self._robot: RobotState | None = None
        self._force = (0.0, -math.inf)  # (contact force N, time.monotonic() it arrived)
        self._servo_last: ServoState | None = None
        self._owner = ""  # who holds control (state/safety): while someone does, only its reports set the bitrate
        self._last_reject_log: dict[str, float] = {}
        self._pub_markers: Any = None
        p = config.perception
        self.poses = PoseHistory(p.history_span, p.max_extrapolation) if p is not None else None
        # Servo angles older than a few of the servo unit's heartbeats are unknown, not held (history.py).
        self.servos = (ServoHistory(p.history_span, servo_max_age(config.servos.publish_hz))
                       if p is not None and config.servos is not None else None)
        self.perception: PerceptionPipeline | None = None
        if p is not None:
            self.perception = PerceptionPipeline(p, self.pose_at, self.servo_angles_at, self._publish_markers)
        self.video: list[VideoStream] = []
        if config.video is not None:
            shared = self.perception.next_image if self.perception is not None else None
            for name, suffix, stream in (("camera", keys.VIDEO_CAMERA, config.video.camera),
                                         ("ultrasound", keys.VIDEO_ULTRASOUND, config.video.ultrasound)):
                if stream is not None:
                    self.video.append(VideoStream(name, suffix, stream, make_source(stream, self.contact_force, shared)))
        self._feedback: Any = None  # the viewers' reports on the H.264 streams: a subscriber with a RingChannel
        self._handlers: dict[str, Callable[[bytes], None]] = {}
        simulated_us = any(s.config.source == "ultrasound_sim" for s in self.video)
        if self.poses is not None or (simulated_us and config.force is None and config.phantom is not None):
            self._handlers[self.keys.key(keys.STATE_ROBOT)] = self._on_robot
        if self.servos is not None:
            self._handlers[self.keys.key(keys.STATE_SERVO)] = self._on_servo
        if simulated_us and config.force is not None:
            self._handlers[self.keys.key(keys.STATE_FORCE_LEVEL)] = self._on_force_level
        if any(s.bitrate is not None for s in self.video):
            self._handlers[self.keys.key(keys.STATE_SAFETY)] = self._on_safety

    # -- what the control process tells us, through Zenoh ---------------------------------------------------

    def _drain(self) -> None:
        """Decode the state samples that arrived since the last call, in order; malformed ones are counted."""
        with self._drain_lock:
            for key, ring in self._rings.items():
                while (sample := ring.try_recv()) is not None:
                    self._handle(key, sample.payload.to_bytes())

    def _handle(self, key: str, payload: bytes) -> None:
        try:
            self._handlers[key](payload)
        except DecodeError as exc:
            n = self.rejects.add(key, str(exc))
            now = time.monotonic()
            if now - self._last_reject_log.get(key, -math.inf) >= 5.0:
                self._last_reject_log[key] = now
                log.warning("media: rejected malformed message on %s (%d so far): %s", key, n, exc)

    def _on_robot(self, payload: bytes) -> None:
        msg = RobotState.decode(payload)
        self._robot = msg
        if self.poses is not None:
            self.poses.add_pose(msg.t, msg.tcp_pose)

    def _on_servo(self, payload: bytes) -> None:
        msg = ServoState.decode(payload)
        assert self.servos is not None and self.config.servos is not None
        last = self._servo_last
        if last is not None and (msg.pan, msg.tilt) != (last.pan, last.tilt):
            # The servos publish at every tick in which they moved, and only every 1/publish_hz otherwise: one
            # tick before this message they were still where the previous one said. Without this sample the
            # history would spread the move over the whole quiet interval before it.
            held = msg.t - int(1e9 / self.config.servos.rate_hz)
            if held > last.t:
                self.servos.add(held, last.pan, last.tilt)
        self.servos.add(msg.t, msg.pan, msg.tilt)
        self._servo_last = msg

    def _on_safety(self, payload: bytes) -> None:
        self._owner = SafetyStatus.decode(payload).owner

    def _on_force_level(self, payload: bytes) -> None:
        msg = ForceLevelState.decode(payload)
        self._force = (0.0 if msg.stale else msg.value, time.monotonic())

    def pose_at(self, t_ns: int) -> np.ndarray | None:
        """T_base_tcp at a frame's time; None while the robot state does not cover it."""
        assert self.poses is not None
        self._drain()
        return self.poses.at(t_ns)

    def servo_angles_at(self, t_ns: int) -> tuple[float, float] | None:
        """(pan, tilt) at a frame's time; None until the servos have said where they are. Without servos the
        camera is fixed at the chain's zero (``perception.geometry.pan_zero``/``tilt_zero``)."""
        if self.servos is not None:
            self._drain()
            return self.servos.at(t_ns)
        assert self.config.perception is not None
        return self.config.perception.geometry.pan_zero, self.config.perception.geometry.tilt_zero

    def contact_force(self) -> float:
        """The contact force (N) the simulated ultrasound image responds to: the force sensor's level quantity,
        or with no sensor the simulated phantom's contact at the robot's pose."""
        self._drain()
        if self.config.force is not None:
            value, at = self._force
            return value if time.monotonic() - at <= FORCE_MAX_AGE else 0.0
        robot = self._robot
        if self.config.phantom is not None and robot is not None:
            return float(np.linalg.norm(contact_wrench(self.config.phantom, robot.tcp_pose, robot.tcp_speed)[:3]))
        return 0.0

    def _drain_feedback(self) -> None:
        """The viewers' reports that arrived since the last call, each handed to its stream (which only notes it).
        Run by each stream before it encodes a frame: a keyframe request waits at most one frame period. A Python
        callback per report let a flood of them take the process's GIL: the camera froze (0.5 frames/s of 15)."""
        if self._feedback is None or (sample := self._feedback.try_recv()) is None:
            return
        self._drain()  # state/safety: who holds control now
        with self._drain_lock:
            while sample is not None:
                self._on_feedback(sample)
                sample = self._feedback.try_recv()

    def _on_feedback(self, sample: zenoh.Sample) -> None:
        try:
            msg = VideoFeedback.decode(sample.payload.to_bytes())
        except DecodeError:
            return  # a report moves nothing: a garbled one is simply not taken into account
        # With bound keys the router vouches for the name in the key; without, the report's is a claim.
        sender = msg.operator
        if self.config.bind_operator_keys:
            sender = operator_in_key(str(sample.key_expr), keys.CMD_VIDEO_FEEDBACK) or ""
        for stream in self.video:
            if stream.name == msg.stream:
                stream.on_feedback(msg, sets_bitrate=sets_bitrate(self._owner, sender))

    def _publish_markers(self, msg: Markers) -> None:
        if self._pub_markers is not None:
            self._pub_markers.put(msg.encode())

    # -- running ---------------------------------------------------------------------------------------------

    def run(self, stop_flag: Any, parent_pid: int, conn: Connection) -> None:
        """Until the parent sets ``stop_flag`` or dies."""
        zenoh_config = (self.config.video.zenoh if self.config.video is not None else None) or self.config.zenoh
        session = open_session(zenoh_config, stop=self.stop)
        try:
            if self.perception is not None:
                self._pub_markers = publisher(session, self.keys.key(keys.MARKERS))
            # A few seconds of each (the pose history spans 2 s); when full, the oldest go.
            self._rings = {key: session.declare_subscriber(key, zenoh.handlers.RingChannel(RING_SIZE))
                           for key in self._handlers}
            if any(stream.h264 is not None for stream in self.video):
                # The viewers' reports on the H.264 streams (keyframe requests, loss, delay); with bound keys on
                # each operator's own key.
                bound = "/*" if self.config.bind_operator_keys else ""
                self._feedback = session.declare_subscriber(self.keys.key(keys.CMD_VIDEO_FEEDBACK) + bound,
                                                            zenoh.handlers.RingChannel(FEEDBACK_RING))
            if self.perception is not None:
                self.perception.start()
            for stream in self.video:
                stream.before_send = self._drain_feedback
                stream.start(session, self.keys, self.stop)
            conn.send(("up", os.getpid()))
            while not self.stop.wait(_PARENT_CHECK_S):
                if stop_flag.value:
                    break
                if os.getppid() != parent_pid:
                    log.warning("media: the edge agent (pid %d) is gone: exiting", parent_pid)
                    os._exit(0)
        finally:
            self.stop.set()
            if self.perception is not None:
                self.perception.stop()
            for stream in self.video:
                stream.join()
            for ring in [*self._rings.values(), *([self._feedback] if self._feedback is not None else [])]:
                ring.undeclare()
            session.close()


def media_main(config: EdgeConfig, parent_pid: int, pdeathsig: bool, stop_flag: Any, conn: Connection,
               log_level: int) -> None:
    """The child's entry point (a fresh interpreter)."""
    enter_child(parent_pid, pdeathsig)  # not Linux: the parent-pid check in run() still ends us
    # ps and top show the process by this name, and each of its threads that does not name itself (all start later).
    name_thread("iorthand-media")
    # Before any thread starts, so that every thread of the child (Zenoh's too) inherits it.
    with contextlib.suppress(AttributeError, OSError):
        os.setpriority(os.PRIO_PROCESS, 0, MEDIA_NICE)
    # One OpenCV thread: a frame has 66 ms and needs ~5; OpenCV's pool of one thread per core spent 20-25 % more
    # CPU on the same frames (waking and synchronising its workers), on the cores the control process needs.
    cv2.setNumThreads(1)
    # The child writes to the agent's stderr (inherited): the same lines as `iorthand edge` logs.
    logs.setup(log_level)
    code = 0
    try:
        MediaService(config).run(stop_flag, parent_pid, conn)
    except BaseException as exc:
        log.exception("media process failed")
        with contextlib.suppress(OSError):
            conn.send(("failed", f"{type(exc).__name__}: {exc}"))
        code = 1
    finally:
        logs.flush()
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)


# ---------------------------------------------------------------------------------------------------------
# The agent's side.


class MediaProcess:
    """Starts the media child, restarts it after a crash (back-off :data:`RESTART_MIN_S` doubling to
    :data:`RESTART_MAX_S`), and stops it: a flag, then SIGTERM, then SIGKILL, so no orphan is left.

    ``session``: the agent's control session, used only while the child is down, to tell the video and marker
    subscribers why the picture stopped (a few bytes once per restart)."""

    def __init__(self, config: EdgeConfig) -> None:
        check_config(config)
        self.config = config
        self.keys = keys.RobotKeys(config.robot_id)
        self._ctx = mp.get_context("spawn")  # never fork a process that holds Zenoh threads
        # A shared byte, not an mp.Event: a child killed while waiting on an Event's condition leaves it broken
        # for the parent (multiprocessing asserts in notify), and a killed child is what this class handles.
        self._stop_flag = self._ctx.RawValue("b", 0)
        self.proc: Any = None
        self.restarts = 0
        self.last_exit = ""  # why the child last ended, as logged
        self._watcher: Worker | None = None
        self._stopping = threading.Event()  # the watcher's: no restart once set
        self._session: zenoh.Session | None = None

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None and self.proc.is_alive() else None

    def start(self, session: zenoh.Session | None) -> None:
        """Start the child and the ``edge-media`` thread that watches it; returns at once."""
        self._session = session
        self._stopping.clear()
        self._stop_flag.value = 0
        self._watcher = Worker("edge-media", self._watch, self._stopping)
        self._watcher.start()

    def _spawn(self) -> Connection:
        recv, send = self._ctx.Pipe(duplex=False)
        self.proc = self._ctx.Process(
            target=media_main, name="iorthand-media", daemon=True,
            # PDEATHSIG follows the thread that starts the child: this watcher, which lives as long as the agent
            # wants the child.
            args=(self.config, os.getpid(), True, self._stop_flag, send, log.getEffectiveLevel()),
        )
        self.proc.start()
        send.close()  # the child holds the only write end: EOF here when it exits
        return recv

    def _watch(self, stop: threading.Event) -> None:
        backoff = RESTART_MIN_S
        while not stop.is_set():
            conn = self._spawn()
            started = time.monotonic()
            said = ""
            while not stop.is_set():
                try:
                    if conn.poll(0.2):
                        kind, text = conn.recv()
                        if kind == "up":
                            log.info("media process %d up (perception, video)", text)
                        else:
                            said = text
                    elif not self.proc.is_alive():
                        break
                except (EOFError, OSError):
                    break  # the child closed its end: it is exiting
            conn.close()
            if stop.is_set():
                # The child ends here, in the thread that started it: once this thread is gone, PDEATHSIG would
                # end the child before it could close its camera and session.
                self._end_child()
                return
            self.proc.join(2.0)
            if self.proc.is_alive():  # closed its pipe yet still there: hung in its exit; it is restarted anyway
                self.proc.kill()
                self.proc.join(1.0)
            ran = time.monotonic() - started
            if ran >= STABLE_S:
                backoff = RESTART_MIN_S
            self.restarts += 1
            self.last_exit = exit_reason(self.proc.exitcode, said)
            log.error("media process (perception, video) %s after %.1f s: restarting it in %.0f s; the robot's "
                      "control is not affected", self.last_exit, ran, backoff)
            self._announce(f"media process {self.last_exit}; restarting in {backoff:.0f} s")
            stop.wait(backoff)
            backoff = min(backoff * 2, RESTART_MAX_S)

    def _announce(self, reason: str) -> None:
        """Tell the video and marker subscribers why their stream stopped (the twin clears the picture)."""
        if self._session is None:
            return
        try:
            if self.config.perception is not None:
                msg = Markers(failure=reason[:256]).stamp(0)
                publisher(self._session, self.keys.key(keys.MARKERS)).put(msg.encode())
            video = self.config.video
            for name, suffix, stream in (("camera", keys.VIDEO_CAMERA, video and video.camera),
                                         ("ultrasound", keys.VIDEO_ULTRASOUND, video and video.ultrasound)):
                if stream:
                    # The stream's encoding: a viewer of an H.264 stream shows the notice as one of its frames.
                    frame = VideoFrame(source=name, width=stream.width, height=stream.height, encoding=stream.codec,
                                       failure=reason[:256])
                    publisher(self._session, self.keys.key(suffix)).put(frame.stamp(0).encode())
        except zenoh.ZError as exc:
            log.warning("could not publish why the media process stopped: %s", exc)

    def stop(self) -> None:
        """Stop the watcher and the child (no restart); returns when the child is gone."""
        self._stopping.set()
        self._stop_flag.value = 1
        if self._watcher is not None:
            self._watcher.join(STOP_GRACE_S + 3.0)
        self._end_child()  # the watcher's job, unless it crashed or hung

    def _end_child(self) -> None:
        """The stop flag, then SIGTERM, then SIGKILL: the child is gone when this returns."""
        self._stop_flag.value = 1
        proc = self.proc
        if proc is None or not proc.is_alive():
            return
        proc.join(STOP_GRACE_S)
        if proc.is_alive():
            log.warning("media process %d did not stop within %.0f s: terminating it", proc.pid, STOP_GRACE_S)
            proc.terminate()
            proc.join(1.0)
        if proc.is_alive():
            proc.kill()
            proc.join(1.0)
