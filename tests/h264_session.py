"""A session whose camera streams H.264, recorded through a real router by the real recorder, for the export tests.

The camera is the edge's own: its test pattern (:class:`PatternSource`) encoded by the edge's encoder through
the edge's own frame builder (:func:`iorthand_edge.video.stream.encode_frame` with :class:`H264Encoder`: Annex B
access units, keyframe flags, failure notices that ask for a keyframe), numbered as the edge's sender numbers
what it sends, and published on a separate session with BLOCK. Beside it, the synthetic session's other streams
(state, force, markers, commands, safety) with no JPEG camera.

The camera's script, in s from the start of the recording:

- the stream runs already: its first :data:`PRE_ROLL` frames (a keyframe first) went out before, so the
  recording starts inside a group of pictures, and its first keyframe is the encoder's second (about 0.7 s);
- keyframes every :data:`KEYFRAME_INTERVAL` s, and at once after a failure;
- within :data:`FAILURE`: failure notices (no picture), as the edge sends them while its camera is away;
- at :data:`LOST`: one frame lost on the way (sent, so it has its ``seq``, but never received).

:func:`decodable` says, plainly, which recorded frames a decoder can take; the exporters must agree with it.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from iorthand import keys
from iorthand.protocol import VideoFrame
from iorthand.transport import QOS_BY_KEY, client_config, free_port, open_session, router_json5
from iorthand_cloud.recorder import client
from iorthand_cloud.recorder.reader import iter_records
from iorthand_cloud.recorder.service import RecorderService
from iorthand_cloud.recorder.simulate import SyntheticSession
from iorthand_edge.video.config import StreamConfig
from iorthand_edge.video.h264 import H264Encoder
from iorthand_edge.video.sources import PatternSource
from iorthand_edge.video.stream import Captured, encode_frame
from tests.test_recorder import recorder_config

ROBOT = "sim1"
SIZE = (320, 240)
FPS = 30.0
KEYFRAME_INTERVAL = 1.0
PRE_ROLL = 10  # frames sent before the recording started
FAILURE = (1.5, 1.9)
FAILURE_TEXT = "no frame from video device '0' for 2 s"
LOST = 2.5
SECONDS = 4.0
CAMERA_KEY = keys.RobotKeys(ROBOT).key(keys.VIDEO_CAMERA)


@dataclass
class H264Recorded:
    folder: Path
    images: dict[int, np.ndarray] = field(default_factory=dict)  # seq → the BGR picture encoded as that frame
    lost_seq: int = 0  # the frame lost on the way


def _camera(pub: zenoh.Publisher, seconds: float, t0: float, stop: threading.Event, rec: H264Recorded) -> None:
    w, h = SIZE
    config = StreamConfig(width=w, height=h, fps=FPS, codec="h264", keyframe_interval=KEYFRAME_INTERVAL)
    encoder = H264Encoder(w, h, FPS, 1000 * config.bitrate_kbps, KEYFRAME_INTERVAL)
    source = PatternSource(w, h)
    seq = 0
    for _ in range(PRE_ROLL):  # sent before the recording started
        seq += 1
        assert encode_frame("camera", Captured(seq, time.time_ns(), source.grab()), config, encoder) is not None
    n = 0
    while not stop.is_set() and (now := time.monotonic() - t0) < seconds:
        seq += 1
        if FAILURE[0] <= now < FAILURE[1]:
            frame = encode_frame("camera", Captured(seq, time.time_ns(), None, FAILURE_TEXT), config, encoder)
        else:
            image = source.grab()
            rec.images[seq] = image
            frame = encode_frame("camera", Captured(seq, time.time_ns(), image), config, encoder)
        assert frame is not None and frame.seq == seq  # zerolatency: one access unit per picture
        if now >= LOST and not rec.lost_seq:
            rec.lost_seq = seq  # lost on the way
        else:
            pub.put(frame.encode())
        n += 1
        time.sleep(max(0.0, t0 + n / FPS - time.monotonic()))


def record_h264_session(out: Path, session_id: str, seconds: float = SECONDS) -> H264Recorded:
    """Record ``seconds`` of the session (see the module's docstring) into ``out/session_id``."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(zenoh.Config.from_json5(router_json5(endpoint)))
    svc = RecorderService(recorder_config(endpoint, out))
    svc.start()
    s, video = open_session(client_config(endpoint)), open_session(client_config(endpoint))
    stop = threading.Event()
    rec = H264Recorded(out / session_id)
    sim = None
    try:
        sim = SyntheticSession(s, ROBOT, seconds, rates={keys.VIDEO_CAMERA: 0.0})
        qos = QOS_BY_KEY[keys.VIDEO_CAMERA]
        pub = video.declare_publisher(CAMERA_KEY, priority=qos.priority, congestion_control=zenoh.CongestionControl.BLOCK)
        time.sleep(0.3)  # the recorder's subscriptions reach our publishers
        assert client.start(s, session_id=session_id, operator="sim-operator", robots=[ROBOT]).ok
        t0 = time.monotonic()
        cam = threading.Thread(target=_camera, args=(pub, seconds, t0, stop, rec), daemon=True)
        sim.start()
        cam.start()
        sim.join(seconds + 10)
        cam.join(seconds + 10)
        time.sleep(0.3)  # the last samples reach the recorder before it closes
        assert client.stop(s).ok
        pub.undeclare()
    finally:
        stop.set()
        if sim is not None:
            sim.stop()
        video.close()
        s.close()
        svc.shutdown()
        router.close()
    return rec


def camera_frames(folder: Path, lo: int | None = None, hi: int | None = None) -> list[VideoFrame]:
    """The recorded camera frames and failure notices, in recorded order (receive times in [lo, hi))."""
    return [VideoFrame.decode(r.data) for r in iter_records(folder, lo, hi) if r.key == CAMERA_KEY]


def decodable(frames: list[VideoFrame]) -> list[VideoFrame]:
    """The frames a decoder can take: from a keyframe on, until a failure notice or a gap in ``seq``."""
    out: list[VideoFrame] = []
    synced, prev = False, None
    for f in frames:
        if f.failure or (prev is not None and f.seq != prev + 1):
            synced = False
        prev = f.seq
        if not f.failure:
            synced = synced or f.keyframe
            if synced:
                out.append(f)
    return out
