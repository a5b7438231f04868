"""The processes a benchmark starts, one role each: ``python -m iorthand_operator.bench.roles ROLE ...``.

Roles run in separate processes (possibly in separate network namespaces) so that each side has its own GIL
and Zenoh runtime, as on real hosts. Measuring roles write one JSON file (``--out``) with raw timestamps; the
orchestrator computes statistics from them (``bench.stats``). Every role has a time bound (``--max-seconds``)
and stops cleanly on SIGTERM.

Ping/echo (``zenoh-ping``/``zenoh-echo``, ``mqtt-ping``/``mqtt-echo``) is the transport comparison: the same
Python code path on both transports, payload ``msgpack([seq, t1, pad])`` echoed as ``[seq, t1, t2, t3, pad]``,
t1..t4 as in NTP. ``operator-probe`` drives the real edge agent through ``OperatorClient`` and records the
edge's ``state/applied`` echo of every command; ``state-monitor`` records ``state/robot`` (blackout stops).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import queue
import random
import signal
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zenoh

from iorthand import keys
from iorthand.protocol import (
    AppliedCommand,
    ControlReply,
    ControlRequest,
    ForceSample,
    Markers,
    RobotState,
    SafetyStatus,
    Sequencer,
    TwistCommand,
    VideoFrame,
)
from iorthand.security import auth
from iorthand.transport import (
    COMMAND,
    QOS_BY_KEY,
    QosProfile,
    ZenohConfig,
    open_session,
    publisher,
    query,
)
from iorthand_operator.client import OperatorClient
from iorthand_operator.recovery import Step

log = logging.getLogger("iorthand.bench.roles")

PING_KEY = "iorthand/_bench/ping"
PONG_KEY = "iorthand/_bench/pong"
MEASURE_SEQ0 = 1_000_000  # measured pings start here; warm-up pings are below

QOS = {
    "command": COMMAND,
    "frame": QosProfile(zenoh.Priority.DATA_LOW, zenoh.CongestionControl.BLOCK),  # whole frames, none dropped
    "default": QosProfile(zenoh.Priority.DEFAULT, zenoh.CongestionControl.DROP),
}


def _stop_event(max_seconds: float) -> threading.Event:
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    if max_seconds > 0:
        timer = threading.Timer(max_seconds, stop.set)
        timer.daemon = True
        timer.start()
    return stop


def _zenoh(args: argparse.Namespace) -> zenoh.Session:
    cfg = ZenohConfig(
        mode=args.mode, connect=list(args.connect or []), listen=list(args.listen or []), shared_memory=False,
        connect_retry_s=30.0,
    )
    return open_session(cfg)


def _write(path: str, data: dict[str, Any]) -> None:
    tmp = Path(path + ".tmp")
    tmp.write_text(json.dumps(data))
    os.replace(tmp, path)


def _sleep_until(t: float, stop: threading.Event) -> None:
    delay = t - time.monotonic()
    if delay > 0:
        stop.wait(delay)


class PingRecorder:
    """Fixed-rate pings, warm-up until the first echo, then ``duration`` seconds measured."""

    def __init__(self, size: int) -> None:
        self.pad = random.Random(7).randbytes(max(0, size))
        self.sent: list[int] = []
        self.records: list[list[int]] = []
        self.warm = threading.Event()
        self._lock = threading.Lock()

    def payload(self, seq: int) -> bytes:
        return msgpack.packb([seq, time.time_ns(), self.pad])

    def on_pong(self, data: bytes) -> None:
        t4 = time.time_ns()
        seq, t1, t2, t3, _ = msgpack.unpackb(data)
        if seq < MEASURE_SEQ0:
            self.warm.set()
            return
        with self._lock:
            self.records.append([seq, t1, t2, t3, t4])

    def run(self, send: Any, rate: float, duration: float, stop: threading.Event, warmup_s: float = 20.0) -> str:
        seq = 0
        deadline = time.monotonic() + warmup_s
        while not self.warm.is_set() and time.monotonic() < deadline and not stop.is_set():
            seq += 1
            send(self.payload(seq))
            self.warm.wait(0.05)
        if not self.warm.is_set():
            return "no echo during warm-up"
        stop.wait(0.3)  # let the warm-up pongs drain
        period = 1.0 / rate
        t0 = time.monotonic()
        n = 0
        while not stop.is_set() and time.monotonic() - t0 < duration:
            seq = MEASURE_SEQ0 + n
            self.sent.append(seq)
            send(self.payload(seq))
            n += 1
            _sleep_until(t0 + n * period, stop)
        stop.wait(1.0)  # late echoes still count (their latency shows it)
        return "ok"

    def result(self, **meta: Any) -> dict[str, Any]:
        with self._lock:
            return {**meta, "sent": self.sent, "records": list(self.records)}


# ------------------------------------------------------------------------------------------------ Zenoh


def zenoh_echo(args: argparse.Namespace) -> int:
    stop = _stop_event(args.max_seconds)
    session = _zenoh(args)
    qos = QOS[args.qos]
    pub = session.declare_publisher(PONG_KEY, priority=qos.priority, congestion_control=qos.congestion, express=qos.express)

    def on_ping(sample: zenoh.Sample) -> None:
        # Echo from the callback: the shortest path, and the same as the MQTT echo does (fair comparison).
        t2 = time.time_ns()
        seq, t1, pad = msgpack.unpackb(sample.payload.to_bytes())
        pub.put(msgpack.packb([seq, t1, t2, time.time_ns(), pad]))

    sub = session.declare_subscriber(PING_KEY, on_ping)
    print("echo ready", flush=True)
    stop.wait()
    sub.undeclare()
    session.close()
    return 0


def zenoh_ping(args: argparse.Namespace) -> int:
    stop = _stop_event(args.max_seconds)
    session = _zenoh(args)
    qos = QOS[args.qos]
    rec = PingRecorder(args.size)
    pub = session.declare_publisher(PING_KEY, priority=qos.priority, congestion_control=qos.congestion, express=qos.express)
    sub = session.declare_subscriber(PONG_KEY, lambda s: rec.on_pong(s.payload.to_bytes()))
    status = rec.run(pub.put, args.rate, args.duration, stop)
    _write(args.out, rec.result(status=status, transport="zenoh", mode=args.mode, qos=args.qos, size=args.size, rate=args.rate))
    sub.undeclare()
    session.close()
    return 0 if status == "ok" else 1


# ------------------------------------------------------------------------------------------------ MQTT


def _mqtt_client(name: str, port: int, topic: str, on_message: Any) -> Any:
    import paho.mqtt.client as mqtt

    subscribed = threading.Event()
    client = mqtt.Client(callback_api_version=mqtt.CallbackAPIVersion.VERSION2, client_id=f"{name}-{os.getpid()}")
    client.on_message = lambda c, u, msg: on_message(msg.payload)
    client.on_subscribe = lambda *a: subscribed.set()
    client.on_connect = lambda c, u, f, rc, p: c.subscribe(topic, qos=0)
    client.connect("127.0.0.1", port, keepalive=30)
    sock = client.socket()
    if sock is not None:  # as Zenoh does: no Nagle delay on a latency-sensitive link
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    client.loop_start()
    if not subscribed.wait(15.0):
        raise RuntimeError(f"MQTT broker on port {port} did not confirm the subscription")
    return client


def mqtt_echo(args: argparse.Namespace) -> int:
    stop = _stop_event(args.max_seconds)
    holder: dict[str, Any] = {}

    def on_ping(data: bytes) -> None:
        t2 = time.time_ns()
        seq, t1, pad = msgpack.unpackb(data)
        holder["c"].publish("iorthand/_bench/pong", msgpack.packb([seq, t1, t2, time.time_ns(), pad]), qos=0)

    holder["c"] = _mqtt_client("echo", args.port, "iorthand/_bench/ping", on_ping)
    print("echo ready", flush=True)
    stop.wait()
    holder["c"].loop_stop()
    holder["c"].disconnect()
    return 0


def mqtt_ping(args: argparse.Namespace) -> int:
    stop = _stop_event(args.max_seconds)
    rec = PingRecorder(args.size)
    client = _mqtt_client("ping", args.port, "iorthand/_bench/pong", rec.on_pong)
    status = rec.run(lambda p: client.publish("iorthand/_bench/ping", p, qos=0), args.rate, args.duration, stop)
    _write(args.out, rec.result(status=status, transport="mqtt", mode="broker", qos="0", size=args.size, rate=args.rate))
    client.loop_stop()
    client.disconnect()
    return 0 if status == "ok" else 1


# ------------------------------------------------------------------------------------------------ load


def synthetic_jpeg(width: int = 640, height: int = 480, quality: int = 85, seed: int = 0) -> bytes:
    """A real JPEG of a textured scene (gradients, shapes, sensor noise): sizes like a camera's at that
    resolution and quality, without a camera. Pillow comes with matplotlib."""
    from io import BytesIO

    from PIL import Image

    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width]
    img = np.stack([(x * 255 // width), (y * 255 // height), ((x + y) * 127 // (width + height)) + 60], axis=-1)
    for _ in range(30):
        cx, cy, r = rng.integers(0, width), rng.integers(0, height), rng.integers(10, 80)
        img[(x - cx) ** 2 + (y - cy) ** 2 < r * r] = rng.integers(0, 255, 3)
    img = np.clip(img + rng.normal(0, 12, img.shape), 0, 255).astype(np.uint8)
    buf = BytesIO()
    Image.fromarray(img, "RGB").save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


def video_pub(args: argparse.Namespace) -> int:
    """The edge camera: JPEG frames at ``fps`` on video/camera, its own session, video QoS."""
    stop = _stop_event(args.max_seconds)
    session = _zenoh(args)
    k = keys.RobotKeys(args.robot)
    pub = publisher(session, k.key(keys.VIDEO_CAMERA))
    frames = [synthetic_jpeg(quality=args.quality, seed=i) for i in range(4)]
    print(f"video ready {len(frames[0])} bytes per frame", flush=True)
    period, t0, n = 1.0 / args.fps, time.monotonic(), 0
    while not stop.is_set():
        msg = VideoFrame(width=640, height=480, data=frames[n % len(frames)]).stamp(n + 1)
        pub.put(msg.encode())
        n += 1
        _sleep_until(t0 + n * period, stop)
    session.close()
    return 0


def video_sub(args: argparse.Namespace) -> int:
    """The operator's video view: receives every frame (a ring channel drained by a worker, as the console
    must) and counts them, so the video really crosses the routers."""
    stop = _stop_event(args.max_seconds)
    session = _zenoh(args)
    k = keys.RobotKeys(args.robot)
    sub = session.declare_subscriber(k.key(keys.VIDEO_CAMERA), zenoh.handlers.RingChannel(4))
    frames = nbytes = 0
    print("video-sub ready", flush=True)
    t0 = time.monotonic()
    while not stop.is_set():
        sample = sub.try_recv()
        if sample is None:
            stop.wait(0.005)
            continue
        frames += 1
        nbytes += len(sample.payload)
    dt = time.monotonic() - t0
    if args.out:
        _write(args.out, {"frames": frames, "bytes": nbytes, "seconds": dt, "fps": frames / dt if dt else 0.0})
    session.close()
    return 0


def video_probe(args: argparse.Namespace) -> int:
    """A viewer of the camera stream across the emulated link, as the twin or a console is: every frame's
    sequence, capture time, arrival, size and keyframe flag; H.264 decoded (a frame counts as delivered only if it
    decodes: after a lost frame nothing does until the next keyframe). It reports to the edge once a second and
    asks for a keyframe when it needs one (VideoFeedback), as the web console does."""
    from iorthand.protocol import VideoFeedback
    from iorthand_edge.video.h264 import KEYFRAME_REQUEST_HOLD_S, H264Decoder  # where the edge's packages are

    stop = _stop_event(args.max_seconds)
    session = _zenoh(args)
    k = keys.RobotKeys(args.robot)
    # Arrival is stamped in Zenoh's callback, as the command echoes' are: a polling loop would add up to its
    # sleep to every frame's delay. Decoding happens after, in this thread.
    arrived: queue.SimpleQueue[tuple[int, bytes]] = queue.SimpleQueue()
    sub = session.declare_subscriber(k.key(keys.VIDEO_CAMERA),
                                     lambda sample: arrived.put((time.time_ns(), sample.payload.to_bytes())))
    feedback = publisher(session, k.key(keys.CMD_VIDEO_FEEDBACK))
    seq = Sequencer()
    decoder = H264Decoder()
    frames: list[list[Any]] = []  # seq, capture t, arrival t, bytes, keyframe, decoded
    last_seq, received, lost, asked = 0, 0, 0, 0.0
    report_at = time.monotonic() + 1.0
    print("video-probe ready", flush=True)
    end = time.monotonic() + args.duration
    while not stop.is_set() and time.monotonic() < end:
        try:
            arrival, payload = arrived.get(timeout=0.05)
        except queue.Empty:
            arrival, payload = 0, b""
        now = time.monotonic()
        if now >= report_at:
            recent = sorted(f[2] - f[1] for f in frames[-received:]) if received else []
            p90 = recent[int(0.9 * (len(recent) - 1))] / 1e9 if recent else -1.0
            feedback.put(VideoFeedback(operator=args.operator_id, received=received, lost=lost,
                                       delay_p90=min(3600.0, max(0.0, p90)) if recent else -1.0).stamp(seq.next()).encode())
            received, lost, report_at = 0, 0, now + 1.0
        if not arrival:
            continue
        frame = VideoFrame.decode(payload)
        if frame.failure:
            continue
        gap = bool(last_seq) and frame.seq > last_seq + 1
        lost += frame.seq - last_seq - 1 if gap else 0
        received += 1
        last_seq = frame.seq
        decoded = True
        if frame.encoding == "h264":
            decoded = bool(decoder.decode(frame.data, frame.keyframe, gap=gap))
            # Again while none comes (the edge answers one request per hold: the keyframe may be lost too).
            if not decoded and now - asked > KEYFRAME_REQUEST_HOLD_S:
                feedback.put(VideoFeedback(operator=args.operator_id, keyframe=True).stamp(seq.next()).encode())
                asked = now
        frames.append([frame.seq, frame.t, arrival, len(payload), frame.keyframe, decoded])
    if args.out:
        _write(args.out, {"frames": frames, "encoding": frame.encoding if frames else ""})
    sub.undeclare()
    session.close()
    return 0


def state_pub(args: argparse.Namespace) -> int:
    """The edge's other streams that the agent does not publish yet: force at 100 Hz, markers at 30 Hz."""
    stop = _stop_event(args.max_seconds)
    session = _zenoh(args)
    k = keys.RobotKeys(args.robot)
    force = publisher(session, k.key(keys.STATE_FORCE))
    markers = publisher(session, k.key(keys.MARKERS))
    print("state ready", flush=True)
    t0, n = time.monotonic(), 0
    while not stop.is_set():
        force.put(ForceSample(force=[0.1, 0.2, 3.0], torque=[0.0, 0.0, 0.01]).stamp(n + 1).encode())
        if n % 3 == 0:
            markers.put(Markers(frames=n, fps=30.0).stamp(n // 3 + 1).encode())
        n += 1
        _sleep_until(t0 + n * 0.01, stop)
    session.close()
    return 0


# ------------------------------------------------------------------------------------------------ operator


class BenchClient(OperatorClient):
    """An OperatorClient that also logs every command it sends (seq, t) and every echo with the edge's
    timestamps (t2 = recv_t, t3 = the echo's own stamp). The client keeps only a bounded map of sent
    commands and shares its sequence counter with control requests, so loss needs this log."""

    def __init__(self, *args: Any, shared_cpu: bool = False, **kwargs: Any) -> None:
        self.bench_sent: list[tuple[int, int]] = []
        self.bench_echo: list[tuple[bytes, int]] = []
        self.shared_cpu = shared_cpu
        if shared_cpu:
            # Many operators on one 2-core machine (scale runs): a spinning real-time sender times twenty would
            # take the cores from the routers being measured. Same schedule, sleeping only.
            kwargs["realtime"] = False
            kwargs["spin"] = False
        super().__init__(*args, **kwargs)
        self._bench_sub = self.session.declare_subscriber(self.keys.key(keys.STATE_APPLIED), self._bench_on_applied)

    def _record_send(self, seq: int, t_ns: int, mono: float, grant: int, deadman: bool) -> None:
        super()._record_send(seq, t_ns, mono, grant, deadman)
        with self._lock:
            self.bench_sent.append((seq, t_ns))

    def _bench_on_applied(self, sample: zenoh.Sample) -> None:
        self.bench_echo.append((sample.payload.to_bytes(), time.time_ns()))  # decoded after the run

    def close(self) -> None:
        self._bench_sub.undeclare()
        super().close()


def _echo_records(echoes: list[tuple[bytes, int]], operator_id: str) -> list[list[Any]]:
    """Raw ``state/applied`` echoes (payload, arrival ns) → this operator's rows
    ``[cmd_seq, t1, t2, t3, t4, accepted, status]``, decoded after the run to keep callbacks short."""
    out = []
    for data, t4 in list(echoes):
        msg = AppliedCommand.decode(data)
        if msg.operator == operator_id:
            out.append([msg.cmd_seq, msg.cmd_t, msg.recv_t, msg.t, t4, msg.accepted, msg.status])
    return out


def _acquire(client: BenchClient | LightOperator, stop: threading.Event, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not stop.is_set() and time.monotonic() < deadline:
        try:
            client.acquire()
            return True
        except Exception as exc:  # refused, no answer yet, or a timed-out query: try again
            log.info("acquire %s: %s", client.keys.robot, exc)
            stop.wait(0.3)
    return False


def operator_probe(args: argparse.Namespace) -> int:
    """One operator per robot in ``--robots`` (each with its own session, as separate consoles would have):
    acquire, hold the deadman and move back and forth along y at ``--speed`` for ``--duration`` seconds,
    re-acquiring whenever control is lost (after a long blackout). Writes every command and echo."""
    stop = _stop_event(args.max_seconds)
    robots = args.robots.split(",")
    clients: list[BenchClient] = []
    events: list[list[Any]] = []
    try:
        for i, robot in enumerate(robots):
            session = _zenoh(args)
            clients.append(BenchClient(session, robot, f"{args.operator_id}-{i}", rate_hz=args.rate,
                                       shared_cpu=args.shared_cpu))
        for c in clients:
            c.wait_for_state(timeout=60.0)
            if not _acquire(c, stop, 30.0):
                raise RuntimeError(f"could not acquire {c.keys.robot}")
            c.start()
        print("probe ready", flush=True)
        t0 = time.monotonic()
        direction = 1.0
        next_flip = t0 + args.flip_s
        for c in clients:
            c.set_twist([0.0, direction * args.speed, 0.0], np.zeros(3), deadman=True)
        while not stop.is_set() and time.monotonic() - t0 < args.duration:
            stop.wait(0.2)
            now = time.monotonic()
            if now >= next_flip:
                direction, next_flip = -direction, now + args.flip_s
                for c in clients:
                    c.set_twist([0.0, direction * args.speed, 0.0], np.zeros(3), deadman=True)
            for c in clients:
                # After a stop, a long gap, a lost grant or a new one (the client's lease renewal re-acquires
                # by itself once the edge let control go) the edge waits for control and a fresh press of the
                # deadman: the client takes that step, as a headless move does (OperatorClient.recover).
                step = c.recover()
                if step.step in (Step.ACQUIRE, Step.PRESS):
                    events.append([time.time_ns(), c.keys.robot, step.step.value, step.why])
        for c in clients:
            c.set_twist(np.zeros(3), np.zeros(3), deadman=False)
        # Wait for the last echoes: until none has arrived for 1 s (a CPU stall can hold them), at most 5 s.
        deadline = time.monotonic() + 5.0
        last = -1
        while time.monotonic() < deadline and not stop.is_set():
            n = sum(len(c.bench_echo) for c in clients)
            if n == last:
                break
            last = n
            stop.wait(1.0)
        out = {
            "robots": {
                c.keys.robot: {
                    "operator": c.operator_id, "rate": args.rate,
                    "sent": list(c.bench_sent), "records": _echo_records(c.bench_echo, c.operator_id),
                    "edge": {"received": c.safety.received, "applied": c.safety.applied, "rejected": c.safety.rejected}
                    if c.safety else {},
                }
                for c in clients
            },
            "events": events,
        }
        _write(args.out, out)
        return 0
    finally:
        for c in clients:
            # Closing during a blackout may time out; the session close below must still run.
            with contextlib.suppress(Exception):
                c.close()
            c.session.close()


def state_monitor(args: argparse.Namespace) -> int:
    """Records the edge's state/robot stream: (t, cmd_seq, cmd_recv_t, moving, arrival) per state."""
    stop = _stop_event(args.max_seconds)
    session = _zenoh(args)
    rows: list[tuple[int, int, int, bool, int]] = []

    def on_state(sample: zenoh.Sample) -> None:
        arrival = time.time_ns()
        m = RobotState.decode(sample.payload.to_bytes())
        rows.append((m.t, m.cmd_seq, m.cmd_recv_t, bool(any(m.commanded)), arrival))

    sub = session.declare_subscriber(keys.RobotKeys(args.robot).key(keys.STATE_ROBOT), on_state)
    print("monitor ready", flush=True)
    stop.wait(args.duration)
    sub.undeclare()
    _write(args.out, {"states": list(rows)})
    session.close()
    return 0


class LightRobot:
    """A light stand-in for one edge agent (scale runs): the same keys, messages and QoS — state/robot at
    125 Hz, state/safety at 20 Hz, a state/applied echo for every twist, acquire/release answered — with no
    supervisor or robot model behind them. A full ``iorthand edge`` costs ~8 % of a core idle; twenty of them
    saturate this 2-core machine before the router is tested. Each robot has its own session (own link to
    the router), as separate end-effector computers would."""

    def __init__(self, session: zenoh.Session, robot: str) -> None:
        self.session = session
        self.keys = k = keys.RobotKeys(robot)
        self.owner = ""
        self.last_seq = 0
        self.last_recv = 0
        self.commanded = [0.0] * 6
        self._seq = {"robot": 0, "safety": 0, "applied": 0}
        self._lock = threading.Lock()
        self.pub_state = publisher(session, k.key(keys.STATE_ROBOT))
        self.pub_safety = publisher(session, k.key(keys.STATE_SAFETY))
        self.pub_applied = publisher(session, k.key(keys.STATE_APPLIED))
        self._decl = [
            session.declare_subscriber(k.key(keys.CMD_TWIST), self._on_twist),
            session.declare_queryable(k.key(keys.CONTROL_ACQUIRE), lambda q: self._on_control(q, True)),
            session.declare_queryable(k.key(keys.CONTROL_RELEASE), lambda q: self._on_control(q, False)),
        ]

    def _next(self, name: str) -> int:
        self._seq[name] += 1
        return self._seq[name]

    def _on_twist(self, sample: zenoh.Sample) -> None:
        t2 = time.time_ns()
        cmd = TwistCommand.decode(sample.payload.to_bytes())
        with self._lock:
            ok = cmd.operator == self.owner and cmd.seq > self.last_seq
            if ok:
                self.last_seq, self.last_recv = cmd.seq, t2
                self.commanded = [*cmd.linear, *cmd.angular] if cmd.deadman else [0.0] * 6
            echo = AppliedCommand(operator=cmd.operator, cmd_seq=cmd.seq, cmd_t=cmd.t, recv_t=t2,
                                  applied=self.commanded if ok else [0.0] * 6, accepted=ok,
                                  status="ok" if ok else "not_owner").stamp(self._next("applied"))
        self.pub_applied.put(echo.encode())

    def _on_control(self, query: zenoh.Query, acquire: bool) -> None:
        try:
            req = ControlRequest.decode(query.payload.to_bytes() if query.payload is not None else b"")
            with self._lock:
                if acquire:
                    if self.owner != req.operator:
                        self.last_seq = 0
                    self.owner = req.operator
                elif self.owner == req.operator:
                    self.owner = ""
            reply = ControlReply(ok=True, reason="granted" if acquire else "released", owner=self.owner, lease=3.0)
            query.reply(query.key_expr, reply.stamp(0).encode())
        finally:
            query.drop()

    def tick(self, n: int) -> None:
        with self._lock:
            state = RobotState(commanded=self.commanded, mode="running", cmd_seq=self.last_seq,
                               cmd_recv_t=self.last_recv).stamp(self._next("robot"))
            owner = self.owner
        self.pub_state.put(state.encode())
        if n % 6 == 0:  # ≈ 20 Hz
            self.pub_safety.put(SafetyStatus(armed=True, owner=owner, status="ok").stamp(self._next("safety")).encode())


def robot_farm(args: argparse.Namespace) -> int:
    """Light simulated robots (see :class:`LightRobot`), one session each, one 125 Hz loop for all."""
    stop = _stop_event(args.max_seconds)
    robots = [LightRobot(_zenoh(args), r) for r in args.robots.split(",")]
    print("farm ready", flush=True)
    t0, n = time.monotonic(), 0
    while not stop.is_set():
        for r in robots:
            r.tick(n)
        n += 1
        _sleep_until(t0 + n / 125.0, stop)
    for r in robots:
        r.session.close()
    return 0


class LightOperator:
    """A light stand-in for one operator console (scale runs): its own session, a liveliness token, control
    acquired by query, a ``TwistCommand`` stream with the command QoS, and subscriptions to what a console
    watches (state/robot, state/safety, state/applied), so the router forwards every stream as in a real
    deployment. Received state is counted, not decoded; echoes are stored raw and decoded after the run. A
    full ``OperatorClient`` costs ~5 % of a core; twenty of them (plus twenty robots) measure this 2-core
    machine's scheduler rather than the router (``--operators client`` measures that case)."""

    def __init__(self, session: zenoh.Session, robot: str, operator_id: str) -> None:
        self.session = session
        self.keys = k = keys.RobotKeys(robot)
        self.operator_id = operator_id
        self.seq = Sequencer()
        self.key = b""  # the grant's key from the acquire reply: signs every command
        self.control_seq = 0
        self.sent: list[tuple[int, int]] = []
        self.echoes: list[tuple[bytes, int]] = []
        self.states = 0
        # Receive time of the newest robot state: a light stand-in for its source time (it decodes nothing),
        # so the age each command states leaves out the edge→operator transit.
        self.state_at_ns = 0
        self.pub_twist = publisher(session, k.key(keys.CMD_TWIST), QOS_BY_KEY[keys.CMD_TWIST])
        self._token = session.liveliness().declare_token(k.alive_operator(operator_id))
        self._decl = [
            session.declare_subscriber(k.key(keys.STATE_ROBOT), self._on_robot_state),
            session.declare_subscriber(k.key(keys.STATE_SAFETY), self._on_state),
            session.declare_subscriber(k.key(keys.STATE_APPLIED), self._on_applied),
        ]

    def _on_state(self, sample: zenoh.Sample) -> None:
        self.states += 1

    def _on_robot_state(self, sample: zenoh.Sample) -> None:
        self.states += 1
        self.state_at_ns = time.time_ns()

    def _on_applied(self, sample: zenoh.Sample) -> None:
        self.echoes.append((sample.payload.to_bytes(), time.time_ns()))

    def acquire(self) -> None:
        self.control_seq += 1
        req = ControlRequest(operator=self.operator_id).stamp(self.control_seq)
        if self.key:  # renewing our own grant
            auth.sign(self.key, auth.context(self.keys.robot, keys.CONTROL_ACQUIRE), req)
        replies = query(self.session, self.keys.key(keys.CONTROL_ACQUIRE), req.encode(), timeout=2.0)
        reply = ControlReply.decode(replies[0]) if replies else None
        if reply is None or not reply.ok:
            raise RuntimeError(f"{self.keys.robot}: control not granted")
        if reply.key:  # a new grant: new sequences, and its first command releases the deadman (as a client's)
            self.key, self.seq, self.control_seq = reply.key, Sequencer(), 0
            self.send([0.0, 0.0, 0.0], deadman=False)

    def send(self, linear: list[float], deadman: bool) -> None:
        t = time.time_ns()
        age = (t - self.state_at_ns) / 1e9 if self.state_at_ns else -1.0
        cmd = TwistCommand(operator=self.operator_id, linear=linear, angular=[0.0, 0.0, 0.0], deadman=deadman,
                           state_age=age).stamp(self.seq.next(), t)
        payload = auth.sign(self.key, auth.context(self.keys.robot, keys.CMD_TWIST), cmd).encode()
        self.sent.append((cmd.seq, cmd.t))
        self.pub_twist.put(payload)


def operator_farm(args: argparse.Namespace) -> int:
    """Light operators (see :class:`LightOperator`), one per robot in ``--robots``, one session each; one loop
    sends every operator's twist at ``--rate``, the operators spread evenly over the period (as independent
    consoles' clocks would be), reversing direction every ``--flip-s``."""
    stop = _stop_event(args.max_seconds)
    robots = args.robots.split(",")
    ops = [LightOperator(_zenoh(args), r, f"{args.operator_id}-{i}") for i, r in enumerate(robots)]
    for op in ops:
        if not _acquire(op, stop, 60.0):
            raise RuntimeError(f"could not acquire {op.keys.robot}")
    print("probe ready", flush=True)
    period = 1.0 / args.rate
    slot = period / len(ops)
    t0, n = time.monotonic(), 0
    while not stop.is_set() and time.monotonic() - t0 < args.duration:
        y = args.speed if int((time.monotonic() - t0) / args.flip_s) % 2 == 0 else -args.speed
        for i, op in enumerate(ops):
            _sleep_until(t0 + n * period + i * slot, stop)
            op.send([0.0, y, 0.0], True)
        n += 1
        _sleep_until(t0 + n * period, stop)
    for op in ops:
        op.send([0.0, 0.0, 0.0], False)
    stop.wait(1.0)  # the last echoes
    out = {
        "robots": {
            op.keys.robot: {"operator": op.operator_id, "rate": args.rate, "sent": op.sent,
                            "records": _echo_records(op.echoes, op.operator_id),
                            "states_received": op.states}
            for op in ops
        },
        "events": [],
    }
    _write(args.out, out)
    for op in ops:
        op.session.close()
    return 0


ROLES = {
    "robot-farm": robot_farm,
    "operator-farm": operator_farm,
    "zenoh-echo": zenoh_echo,
    "zenoh-ping": zenoh_ping,
    "mqtt-echo": mqtt_echo,
    "mqtt-ping": mqtt_ping,
    "video-pub": video_pub,
    "video-sub": video_sub,
    "state-pub": state_pub,
    "operator-probe": operator_probe,
    "state-monitor": state_monitor,
    "video-probe": video_probe,
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m iorthand_operator.bench.roles")
    p.add_argument("role", choices=sorted(ROLES))
    p.add_argument("--mode", default="client", choices=["client", "peer"])
    p.add_argument("--connect", action="append")
    p.add_argument("--listen", action="append")
    p.add_argument("--port", type=int, default=1883, help="MQTT broker port")
    p.add_argument("--qos", default="command", choices=sorted(QOS))
    p.add_argument("--size", type=int, default=64, help="ping padding, bytes")
    p.add_argument("--rate", type=float, default=60.0, help="Hz")
    p.add_argument("--duration", type=float, default=10.0, help="s measured")
    p.add_argument("--robot", default="sim1")
    p.add_argument("--robots", default="sim1", help="comma-separated robot ids (operator-probe)")
    p.add_argument("--operator-id", default="bench")
    p.add_argument("--shared-cpu", action="store_true",
                   help="operator-probe: many operators share this machine (no real-time spinning sender)")
    p.add_argument("--speed", type=float, default=0.005, help="m/s of the probe's motion")
    p.add_argument("--flip-s", type=float, default=2.0, help="s between direction changes")
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--quality", type=int, default=85, help="JPEG quality of the synthetic frames")
    p.add_argument("--out", default="")
    p.add_argument("--max-seconds", type=float, default=600.0)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    code = ROLES[args.role](args)
    os._exit(code)  # Zenoh's runtime threads can delay interpreter exit; the output is already written


if __name__ == "__main__":
    sys.exit(main())
