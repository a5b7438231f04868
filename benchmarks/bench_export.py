"""Export benchmark → JSON (default benchmarks/results/export.json): the time of ``iorthand export`` of a 10-minute
session to each format (rrd, ros2, lerobot), and the sizes.

The session is generated, not recorded in real time: :class:`~iorthand_cloud.recorder.simulate.SyntheticSession`'s
own message builders (state 125 Hz, force 100 Hz and level changes, markers 30 Hz, commands 60 Hz and their
echoes, safety 20 Hz, force level 10 Hz, camera JPEG 640×480 30 fps), plus an ultrasound stream as the edge's
default configuration sends it (JPEG 480×360 at 15 fps), are called in time order on a virtual clock and their
payloads written straight into the recorder's segment streams (:mod:`~iorthand_cloud.recorder.segments`: zstd
telemetry, uncompressed video, the recorder's channel schemas and routing) with a manifest whose per-key
statistics are counted as the recorder counts them. What the exporters read is what a recording holds; only
the receive times are synthetic (source time + 1 ms) and nothing crosses Zenoh, which the export does not
involve. Ten minutes are generated in about a minute instead of ten. Five episodes of 116 s are marked with
``episode-start``/``episode-end`` annotations, as an operator would.

Each export is the command a user runs (``iorthand export SESSION --format F``) in a fresh process, timed from
start to exit (imports included: lerobot's take ~4 s), after one untimed read of the session so that every
run starts with the files in the page cache. Target: ≤ 30 s each. Besides the three formats with their
defaults (rrd: images thinned to 5 fps; ros2: MCAP storage; lerobot: 30 fps, full size, the recorded JPEGs as
its MJPEG video), LeRobot at half the picture size (every picture decoded and encoded again), and LeRobot's own
h264 encoder (JPEG decode, h264 with GOP 2, per-frame image statistics: ~10 ms per 640×480 frame and stream) at
full and half size and at 10 fps.

``--video h264`` makes the camera and the ultrasound H.264, as the edge sends them by default (its own encoder at
its default bitrate; benchmarks/results/export-h264.json): a LeRobot export then decodes every frame and encodes
each picture as a JPEG.

Usage: ``python benchmarks/bench_export.py [--minutes 10] [--video jpeg|h264] [--runs rrd,ros2,lerobot,...]
[--keep] [--out FILE]``. With ``--runs`` (``--formats``) naming some of the runs, the results of the others are
kept from the existing output file if it was for the same session (length and video; each run says when it was
measured, ``measured_at``).
"""

from __future__ import annotations

import argparse
import contextlib
import heapq
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import zenoh
from mcap.writer import CompressionType

from iorthand import keys
from iorthand import protocol as proto
from iorthand.protocol import Sequencer, VideoFrame, message_type_for
from iorthand_cloud.recorder import manifest as mf
from iorthand_cloud.recorder import simulate
from iorthand_cloud.recorder.config import RecorderConfig
from iorthand_cloud.recorder.reader import iter_records
from iorthand_cloud.recorder.schemas import MESSAGE_ENCODING, SCHEMA_ENCODING, schema_bytes
from iorthand_cloud.recorder.segments import ChannelSpec, Segment, Stream

ROOT = Path(__file__).resolve().parent.parent
ROBOT = "sim1"
ULTRASOUND = (480, 360, 15.0)  # configs/edge-sim.yaml: video.ultrasound
RECV_LATENCY_NS = 1_000_000
EPISODE_S, EPISODE_MARGIN_S = 120.0, 2.0
TARGET_S = 30.0


class _Clock:
    """The virtual time the builders stamp their messages with."""

    def __init__(self, start_ns: int) -> None:
        self.now = start_ns

    def __call__(self) -> int:
        return self.now


class _Publisher:
    def __init__(self, key: str, sink: Callable[[str, bytes], None]) -> None:
        self.key, self._sink = key, sink

    def put(self, payload: bytes) -> None:
        self._sink(self.key, payload)


class _Session:
    """What SyntheticSession needs of a Zenoh session: publishers, here writing into the recording."""

    def __init__(self, sink: Callable[[str, bytes], None]) -> None:
        self._sink = sink

    def declare_publisher(self, key: str, **_qos: Any) -> _Publisher:
        return _Publisher(key, self._sink)


@contextlib.contextmanager
def _virtual_time(clock: _Clock) -> Iterator[None]:
    """Stamp messages (``Message.stamp`` → ``protocol.now_ns``) and echo receive times (``simulate.time``) with
    the virtual clock, for this generation only."""
    saved_now, saved_time = proto.now_ns, simulate.time
    shim = type("VirtualTime", (), {"time_ns": staticmethod(clock), "monotonic": staticmethod(time.monotonic),
                                    "sleep": staticmethod(time.sleep)})
    proto.now_ns = clock
    simulate.time = shim  # type: ignore[assignment]
    try:
        yield
    finally:
        proto.now_ns, simulate.time = saved_now, saved_time


class _Recording:
    """A session folder written as the recorder writes one (routing, channels, statistics, manifest)."""

    def __init__(self, folder: Path, session_id: str, start_ns: int) -> None:
        cfg = RecorderConfig()
        folder.mkdir(parents=True)
        self.folder = folder
        self.manifest = mf.Manifest(session_id=session_id, operator="sim-operator", robots=[ROBOT],
                                    note="phantom scan (generated for bench_export)", start_t=start_ns,
                                    start_iso=mf.iso(start_ns), software=mf.software_versions())
        self._video = [zenoh.KeyExpr(e) for e in cfg.video_key_exprs]
        self._specs: dict[str, ChannelSpec] = {}

        def on_open(seg: Segment) -> None:
            self.manifest.segments.append(mf.SegmentInfo(file=seg.path.name, stream=seg.path.name.rsplit("-", 1)[0],
                                                         compression="", opened_t=seg.opened_t))

        self.streams = {
            name: Stream(name=name, folder=folder, compression=comp, max_bytes=int(mb * 1024 * 1024),
                         max_seconds=1e9, chunk_size=cfg.chunk_kb * 1024, on_open=on_open)
            for name, comp, mb in (("telemetry", CompressionType.ZSTD, cfg.segment_max_mb),
                                   ("video", CompressionType.NONE, cfg.video_segment_max_mb))
        }
        self._flush_at = start_ns

    def write(self, key: str, payload: bytes, msg: proto.Message, recv_ns: int) -> None:
        spec = self._specs.get(key)
        if spec is None:
            cls = type(msg)
            spec = self._specs[key] = ChannelSpec(key, MESSAGE_ENCODING, cls.__name__, SCHEMA_ENCODING,
                                                  schema_bytes(cls))
        video = any(x.intersects(zenoh.KeyExpr(key)) for x in self._video)
        stream = self.streams["video" if video else "telemetry"]
        stream.write(spec, recv_ns, msg.t, msg.seq, payload)
        if key != keys.service_key(keys.RECORDER, keys.RECORDER_ANNOTATIONS):
            stats = self.manifest.keys.setdefault(key, mf.KeyStats(type=type(msg).__name__))
            stats.observe(len(payload), recv_ns, msg.seq)
        else:
            self.manifest.annotations += 1
        if recv_ns - self._flush_at >= 500_000_000:  # the recorder flushes (ends a chunk) every 0.5 s
            self._flush_at = recv_ns
            for s in self.streams.values():
                s.flush(fsync=False)

    def close(self, stop_ns: int) -> None:
        for s in self.streams.values():
            s.close(fsync=False)
        self.manifest.status, self.manifest.stop_t, self.manifest.stop_iso = mf.COMPLETE, stop_ns, mf.iso(stop_ns)
        self.manifest.write(self.folder, fsync=False)


class _H264Video:
    """Camera or ultrasound frames as the edge sends them with ``video.codec: h264`` (its default): its own encoder
    and frame builder (:func:`~iorthand_edge.video.stream.encode_frame`) at its default bitrate and keyframe
    interval, over a cycle of synthetic pictures (:func:`simulate.make_jpegs`, decoded)."""

    def __init__(self, source: str, width: int, height: int, fps: float) -> None:
        import cv2
        import numpy as np

        from iorthand_edge.video.config import StreamConfig
        from iorthand_edge.video.h264 import H264Encoder

        self.source = source
        self.config = StreamConfig(width=width, height=height, fps=fps)
        self.encoder = H264Encoder(width, height, fps, 1000 * self.config.bitrate_kbps, self.config.keyframe_interval)
        self.images = [cv2.imdecode(np.frombuffer(j, np.uint8), cv2.IMREAD_COLOR)
                       for j in simulate.make_jpegs(8, width, height)]

    def frame(self, seq: int, t_ns: int) -> bytes:
        from iorthand_edge.video.stream import Captured, encode_frame

        frame = encode_frame(self.source, Captured(seq, t_ns, self.images[seq % len(self.images)]), self.config,
                             self.encoder)
        assert frame is not None  # zerolatency: one access unit per picture
        return frame.encode()


def generate(folder: Path, minutes: float, video: str = "jpeg") -> dict[str, Any]:
    """Write a session of ``minutes`` into ``folder`` with ``video`` (jpeg, h264) frames; returns what was
    generated."""
    t_gen = time.perf_counter()
    duration = minutes * 60.0
    start_ns = time.time_ns()
    clock = _Clock(start_ns)
    rec = _Recording(folder, folder.name, start_ns)

    def sink(key: str, payload: bytes) -> None:
        cls = message_type_for(key)
        assert cls is not None, key
        rec.write(key, payload, cls.decode(payload), clock.now + RECV_LATENCY_NS)

    us_key = keys.RobotKeys(ROBOT).key(keys.VIDEO_ULTRASOUND)
    us_jpegs = simulate.make_jpegs(8, ULTRASOUND[0], ULTRASOUND[1])
    us_seq = Sequencer()
    ann_key = keys.service_key(keys.RECORDER, keys.RECORDER_ANNOTATIONS)
    ann_seq = Sequencer()

    def ultrasound(_t: float) -> None:
        n = us_seq.next()
        if h264:
            sink(us_key, h264[keys.VIDEO_ULTRASOUND].frame(n, clock.now))
            return
        frame = VideoFrame(source="ultrasound", width=ULTRASOUND[0], height=ULTRASOUND[1],
                           data=us_jpegs[n % len(us_jpegs)]).stamp(n)
        sink(us_key, frame.encode())

    cam_key = keys.RobotKeys(ROBOT).key(keys.VIDEO_CAMERA)
    cam_seq = Sequencer()

    def camera_h264(_t: float) -> None:
        n = cam_seq.next()
        sink(cam_key, h264[keys.VIDEO_CAMERA].frame(n, clock.now))

    h264 = {keys.VIDEO_CAMERA: _H264Video("camera", 640, 480, simulate.RATES[keys.VIDEO_CAMERA]),
            keys.VIDEO_ULTRASOUND: _H264Video("ultrasound", *ULTRASOUND)} if video == "h264" else {}

    marks: list[tuple[float, str, list[str]]] = []
    k = 0
    while (k + 1) * EPISODE_S <= duration:
        marks += [(k * EPISODE_S + EPISODE_MARGIN_S, f"scan {k + 1} of the phantom", ["episode-start"]),
                  ((k + 1) * EPISODE_S - EPISODE_MARGIN_S, "", ["episode-end"])]
        k += 1

    with _virtual_time(clock):
        sim = simulate.SyntheticSession(_Session(sink), ROBOT, duration)  # type: ignore[arg-type]
        handlers: dict[str, Callable[[float], None]] = {
            keys.STATE_ROBOT: sim._robot, keys.STATE_FORCE: sim._force, keys.MARKERS: sim._markers,
            keys.CMD_TWIST: sim._twist, keys.STATE_SAFETY: sim._safety, keys.STATE_FORCE_LEVEL: sim._force_level,
            keys.VIDEO_CAMERA: camera_h264 if h264 else sim._video,
        }
        rates = {**{s: sim.rates[s] for s in handlers}, keys.VIDEO_ULTRASOUND: ULTRASOUND[2]}
        handlers[keys.VIDEO_ULTRASOUND] = ultrasound
        due = [(0.0, suffix) for suffix, rate in rates.items() if rate > 0]
        heapq.heapify(due)
        mark_i = 0
        while due:
            t, suffix = heapq.heappop(due)
            if t >= duration:
                continue
            clock.now = start_ns + int(t * 1e9)
            while mark_i < len(marks) and marks[mark_i][0] <= t:
                at, text, tags = marks[mark_i]
                ann = proto.Annotation(author="operator", text=text, tags=tags).stamp(ann_seq.next(),
                                                                                      t=start_ns + int(at * 1e9))
                rec.write(ann_key, ann.encode(), ann, ann.t + RECV_LATENCY_NS)
                mark_i += 1
            handlers[suffix](t)
            heapq.heappush(due, (t + 1.0 / rates[suffix], suffix))
    stop_ns = start_ns + int(duration * 1e9) + RECV_LATENCY_NS
    rec.close(stop_ns)
    totals = mf.totals(rec.manifest.keys)
    return {
        "minutes": minutes, "video": video, "messages": totals["messages"], "bytes": totals["bytes"],
        "per_key": {k: v.messages for k, v in sorted(rec.manifest.keys.items())},
        "episodes_marked": len(marks) // 2, "session_mb_on_disk": round(_size(folder) / 1e6, 1),
        "generate_s": round(time.perf_counter() - t_gen, 1),
    }


def _size(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


# Each run: the export command's options. The first three are the formats as a user gets them by default (LeRobot:
# the recorded JPEGs as its MJPEG video); the others show what a scaled picture costs (decoded and encoded again)
# and what LeRobot's own encoder (decode, h264 GOP 2, statistics per frame) costs, also at a smaller size or rate.
RUNS: dict[str, list[str]] = {
    "rrd": ["--format", "rrd"],
    "ros2": ["--format", "ros2"],
    "lerobot": ["--format", "lerobot"],
    "lerobot_half_size": ["--format", "lerobot", "--image-scale", "0.5"],
    "lerobot_h264": ["--format", "lerobot", "--vcodec", "h264"],
    "lerobot_h264_half_size": ["--format", "lerobot", "--vcodec", "h264", "--image-scale", "0.5"],
    "lerobot_h264_half_size_10fps": ["--format", "lerobot", "--vcodec", "h264", "--image-scale", "0.5", "--fps", "10"],
}


def bench_format(folder: Path, run: str, out: Path) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "iorthand.cli", "--log-level", "warning", "export", str(folder), *RUNS[run],
           "--out", str(out)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=3600)
    elapsed = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    # CPU seconds (both cores, the export's threads included): what the run costs, far less sensitive than the wall
    # time to the other work on this shared machine.
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}): {r.stderr.strip()[-2000:]}")
    return {"options": " ".join(RUNS[run]), "seconds": round(elapsed, 2), "cpu_seconds": round(cpu, 1),
            "meets_target": elapsed <= TARGET_S,
            "mb": round(_size(out) / 1e6, 1), "said": r.stdout.strip().splitlines()[-1],
            "load_avg_after": [round(x, 2) for x in os.getloadavg()],
            "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def _kept_runs(out: Path, runs: list[str], minutes: float, video: str) -> dict[str, Any]:
    """The results in ``out`` of the runs not run this time, if measured on a session as long with the same video
    (same generator)."""
    try:
        before = json.loads(out.read_text())
    except (OSError, ValueError):
        return {}
    session = before.get("session", {})
    if session.get("minutes") != minutes or session.get("video", "jpeg") != video:
        return {}
    return {run: res for run, res in before.get("exports", {}).items() if run not in runs}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=10.0)
    p.add_argument("--runs", "--formats", default=",".join(RUNS),
                   help=f"comma-separated, of: {', '.join(RUNS)} (the others' results are kept from --out)")
    p.add_argument("--video", choices=["jpeg", "h264"], default="jpeg",
                   help="the session's camera and ultrasound frames (h264: as the edge sends them by default)")
    p.add_argument("--keep", action="store_true", help="keep the generated session and the exports")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "export.json"))
    args = p.parse_args()
    runs = args.runs.split(",")
    if unknown := [r for r in runs if r not in RUNS]:
        p.error(f"unknown run(s): {', '.join(unknown)}")
    results: dict[str, Any] = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "load_avg_at_start": [round(x, 2) for x in os.getloadavg()]},
        "target_s": TARGET_S,
    }
    tmp = Path(tempfile.mkdtemp(prefix="bench-export-"))
    try:
        folder = tmp / "ten-minutes"
        results["session"] = generate(folder, args.minutes, args.video)
        print(json.dumps({"session": results["session"]}, indent=1), flush=True)
        for _ in iter_records(folder):  # untimed: every export starts with the files in the page cache
            pass
        results["exports"] = {}
        for run in runs:
            out = tmp / (f"export-{run}" if run != "rrd" else "export.rrd")
            results["exports"][run] = bench_format(folder, run, out)
            print(json.dumps({run: results["exports"][run]}, indent=1), flush=True)
    finally:
        if args.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    out = Path(args.out)
    kept = _kept_runs(out, runs, args.minutes, args.video)
    results["exports"] = {run: results["exports"].get(run) or kept[run] for run in RUNS
                          if run in results["exports"] or run in kept}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1) + "\n")
    print(f"results: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
