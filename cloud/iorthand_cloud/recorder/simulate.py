"""A synthetic robot session at full rate, for recorder tests and benchmarks.

Publishes every stream of one robot with the real message classes at the rates of DESIGN.md (state 125 Hz,
force 100 Hz, markers 30 Hz, commands and their echoes 60 Hz, safety 20 Hz, force level 10 Hz and on change,
camera JPEG 640×480 at 30 fps on a separate session) from one scheduler thread. The contact force follows a
scripted, repeating profile, so the events a session report must find (contact time, caution and danger
warnings, deadman stops, refusals) are known exactly: :func:`expected_events`.

By default every publisher uses ``CongestionControl.BLOCK``: the benchmark measures the recorder, not the
network's drop policy (video is DROP on a real link, and its gaps would then be the network's).

Run as a process: ``python -m iorthand_cloud.recorder.simulate --connect EP --duration S --out summary.json``.
"""

from __future__ import annotations

import argparse
import heapq
import io
import json
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import zenoh

from iorthand import keys
from iorthand.protocol import (
    AppliedCommand,
    ForceLevelState,
    ForceSample,
    MarkerPose,
    Markers,
    RobotState,
    SafetyStatus,
    Sequencer,
    Status,
    TwistCommand,
    VideoFrame,
)
from iorthand.transport import QOS_BY_KEY, client_config, open_session

# (seconds, force N) segments of the repeating contact profile. With the default thresholds (contact 1 N,
# caution 6 N, danger 8 N) one 10 s period holds 6 s of contact, one rising edge into caution (0→1 at 4 s)
# and two into danger (1→2 at 5 s, 0→2 at 7 s); 2→1 at 7.5 s is a falling edge and counts nothing.
FORCE_SCRIPT: tuple[tuple[float, float], ...] = (
    (2.0, 0.2), (2.0, 4.0), (1.0, 7.0), (1.0, 9.0), (1.0, 4.0), (0.5, 9.0), (0.5, 7.0), (2.0, 0.2),
)
DEADMAN_WINDOW = (9.0, 9.5)  # s of each period: the operator releases the deadman (refusals, a deadman stop)
RATES = {
    keys.STATE_ROBOT: 125.0, keys.STATE_FORCE: 100.0, keys.MARKERS: 30.0, keys.CMD_TWIST: 60.0,
    keys.STATE_SAFETY: 20.0, keys.STATE_FORCE_LEVEL: 10.0, keys.VIDEO_CAMERA: 30.0,
}


def _period() -> float:
    return sum(d for d, _ in FORCE_SCRIPT)


def force_at(t: float) -> float:
    """The scripted contact force (N, along −z of the tool) at ``t`` s from the start."""
    phase = t % _period()
    for duration, value in FORCE_SCRIPT:
        if phase < duration:
            return value
        phase -= duration
    return FORCE_SCRIPT[-1][1]


def level_of(force: float, caution: float = 6.0, danger: float = 8.0) -> int:
    return 2 if force > danger else 1 if force > caution else 0


def in_deadman_window(t: float) -> bool:
    phase = t % _period()
    return DEADMAN_WINDOW[0] <= phase < DEADMAN_WINDOW[1]


def expected_events(duration: float, contact_threshold: float = 1.0) -> dict[str, float]:
    """Contact time and warning counts of the script over [0, duration), computed from the script itself."""
    contact, red, yellow, stops = 0.0, 0, 0, 0
    t, prev_level = 0.0, 0
    while t < duration:
        for seg, value in FORCE_SCRIPT:
            end = min(t + seg, duration)
            if end <= t:
                break
            lvl = level_of(value)
            if lvl == 2 and prev_level < 2:
                red += 1
            if lvl == 1 and prev_level < 1:
                yellow += 1
            prev_level = lvl
            if value > contact_threshold:
                contact += end - t
            t = end
    p = _period()
    full, rest = divmod(duration, p)
    stops = int(full) + (1 if rest > DEADMAN_WINDOW[0] else 0)
    return {"contact_time": contact, "omega_R": red, "omega_Y": yellow, "deadman_stops": stops}


def make_jpegs(n: int = 8, width: int = 640, height: int = 480) -> list[bytes]:
    """Camera-like JPEG frames (~60 KB at 640×480, quality 80): gradients plus sensor noise."""
    from PIL import Image

    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:height, 0:width]
    out = []
    for i in range(n):
        img = np.stack([(x / width * 255 + 10 * i) % 255, (y / height * 255) % 255, ((x + y) / 4) % 255], -1)
        img = np.clip(img + rng.normal(0, 12, img.shape), 0, 255).astype("uint8")
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, "JPEG", quality=80)
        out.append(buf.getvalue())
    return out


@dataclass
class SimStats:
    published: dict[str, int] = field(default_factory=dict)
    last_seq: dict[str, int] = field(default_factory=dict)
    start_ns: int = 0
    end_ns: int = 0
    late_ms_max: float = 0.0


class SyntheticSession:
    """Publishes one robot's streams until :meth:`stop` or ``duration`` s. ``rates`` overrides RATES (a rate of 0
    leaves a stream out)."""

    def __init__(
        self, session: zenoh.Session, robot: str = "sim1", duration: float = 10.0,
        rates: dict[str, float] | None = None, video_session: zenoh.Session | None = None,
        lossless: bool = True, operator: str = "sim-operator",
    ) -> None:
        self.keys = keys.RobotKeys(robot)
        self.duration = duration
        self.rates = {**RATES, **(rates or {})}
        self.operator = operator
        self.stats = SimStats()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._seq: dict[str, Sequencer] = {}
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._level = 0
        self._state_t = 0  # the newest robot state's stamp (ns)
        self._t0 = 0.0
        self._jpegs = make_jpegs() if self.rates.get(keys.VIDEO_CAMERA) else []
        suffixes = [*self.rates, keys.STATE_APPLIED]
        for suffix in suffixes:
            qos = QOS_BY_KEY[suffix]
            s = video_session if (suffix == keys.VIDEO_CAMERA and video_session is not None) else session
            congestion = zenoh.CongestionControl.BLOCK if lossless else qos.congestion
            self._pubs[suffix] = s.declare_publisher(
                self.keys.key(suffix), priority=qos.priority, congestion_control=congestion, express=qos.express
            )
            self._seq[suffix] = Sequencer()

    # ------------------------------------------------------------------ running

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="synthetic-session", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    def run(self) -> SimStats:
        self._run()
        return self.stats

    def _put(self, suffix: str, msg: Callable[[int], bytes]) -> None:
        seq = self._seq[suffix].next()
        self._pubs[suffix].put(msg(seq))
        self.stats.published[suffix] = self.stats.published.get(suffix, 0) + 1
        self.stats.last_seq[suffix] = seq

    def _run(self) -> None:
        handlers: dict[str, Callable[[float], None]] = {
            keys.STATE_ROBOT: self._robot, keys.STATE_FORCE: self._force, keys.MARKERS: self._markers,
            keys.CMD_TWIST: self._twist, keys.STATE_SAFETY: self._safety,
            keys.STATE_FORCE_LEVEL: self._force_level, keys.VIDEO_CAMERA: self._video,
        }
        self._t0 = time.monotonic()
        self.stats.start_ns = time.time_ns()
        due = [(self._t0, suffix) for suffix, rate in self.rates.items() if rate > 0 and suffix in handlers]
        heapq.heapify(due)
        while due and not self._stop.is_set():
            when, suffix = heapq.heappop(due)
            if when - self._t0 >= self.duration:
                continue
            delay = when - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                self.stats.late_ms_max = max(self.stats.late_ms_max, -delay * 1000)
            handlers[suffix](when - self._t0)
            heapq.heappush(due, (when + 1.0 / self.rates[suffix], suffix))
        self.stats.end_ns = time.time_ns()

    # ------------------------------------------------------------------ streams

    def _robot(self, t: float) -> None:
        a = 0.3 * t
        pose = [0.3 + 0.05 * math.cos(a), 0.05 * math.sin(a), 0.2, math.pi, 0.0, 0.0]
        speed = [-0.015 * math.sin(a), 0.015 * math.cos(a), 0.0, 0.0, 0.0, 0.0]
        state = RobotState(tcp_pose=pose, tcp_speed=speed, q=[0.0, -1.57, 1.57, -1.57, -1.57, 0.0], commanded=speed,
                           mode="sim", robot_time=t)
        self._put(keys.STATE_ROBOT, lambda seq: state.stamp(seq).encode())
        self._state_t = state.t  # what the operator's screen shows next (TwistCommand.view_t)

    def _force(self, t: float) -> None:
        f = force_at(t)
        self._put(keys.STATE_FORCE, lambda seq: ForceSample(force=[0.01, -0.02, -f]).stamp(seq).encode())
        level = level_of(f)
        if level != self._level:  # the edge publishes a level change at once, not at the next 10 Hz tick
            self._level = level
            self._force_level(t)

    def _force_level(self, t: float) -> None:
        f = force_at(t)
        self._put(keys.STATE_FORCE_LEVEL, lambda seq: ForceLevelState(
            level=level_of(f), stale=False, value=f, quantity="fz").stamp(seq).encode())

    def _markers(self, t: float) -> None:
        eye = [1.0, 0, 0, 0.3, 0, 1.0, 0, 0.0, 0, 0, 1.0, 0.0, 0, 0, 0, 1.0]
        ms = [MarkerPose(id=i, pose=eye, raw=eye, reprojection_error=0.3, pixel_size=60.0) for i in range(3)]
        self._put(keys.MARKERS, lambda seq: Markers(markers=ms, frames=seq, fps=30.0, processing_ms=7.0)
                  .stamp(seq).encode())

    def _twist(self, t: float) -> None:
        deadman = not in_deadman_window(t)
        lin = [0.005, 0.0, 0.0] if deadman else [0.0, 0.0, 0.0]
        cmd = TwistCommand(operator=self.operator, linear=lin, deadman=deadman, view_t=self._state_t
                           ).stamp(self._seq[keys.CMD_TWIST].next())
        self._pubs[keys.CMD_TWIST].put(cmd.encode())
        self.stats.published[keys.CMD_TWIST] = self.stats.published.get(keys.CMD_TWIST, 0) + 1
        self.stats.last_seq[keys.CMD_TWIST] = cmd.seq
        recv = time.time_ns()
        status = Status.OK if deadman else Status.NO_DEADMAN
        self._put(keys.STATE_APPLIED, lambda seq: AppliedCommand(
            operator=self.operator, cmd_seq=cmd.seq, cmd_t=cmd.t, recv_t=recv, applied=[*lin, 0.0, 0.0, 0.0],
            accepted=deadman, status=status, reason="" if deadman else "deadman released").stamp(seq).encode())

    def _safety(self, t: float) -> None:
        stopped = in_deadman_window(t)
        self._put(keys.STATE_SAFETY, lambda seq: SafetyStatus(
            armed=True, owner=self.operator, deadman=not stopped, profile="remote", linear_limit=0.008,
            angular_limit=0.1, status=Status.COMMAND_TIMEOUT if stopped else Status.OK,
            reason="no fresh command" if stopped else "", force_level=self._level, force_stale=False,
        ).stamp(seq).encode())

    def _video(self, t: float) -> None:
        frame = self._jpegs[self.stats.published.get(keys.VIDEO_CAMERA, 0) % len(self._jpegs)]
        self._put(keys.VIDEO_CAMERA, lambda seq: VideoFrame(width=640, height=480, data=frame).stamp(seq).encode())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--connect", required=True)
    p.add_argument("--robot", default="sim1")
    p.add_argument("--duration", type=float, default=10.0)
    p.add_argument("--no-video", action="store_true")
    p.add_argument("--lossy", action="store_true", help="use each key's own congestion control (DROP for video)")
    p.add_argument("--out", help="write the summary JSON here (default: stdout)")
    args = p.parse_args(argv)
    cfg = client_config(args.connect)
    session, video = open_session(cfg), open_session(cfg)
    try:
        sim = SyntheticSession(session, args.robot, args.duration, video_session=video, lossless=not args.lossy,
                               rates={keys.VIDEO_CAMERA: 0.0} if args.no_video else None)
        print("synthetic session ready", flush=True)
        time.sleep(0.5)  # subscriptions of the router reach our publishers
        stats = sim.run()
    finally:
        video.close()
        session.close()
    elapsed = min(args.duration, (stats.end_ns - stats.start_ns) / 1e9)
    summary = {**stats.__dict__, "expected": expected_events(elapsed)}
    text = json.dumps(summary, indent=1)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text)
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
