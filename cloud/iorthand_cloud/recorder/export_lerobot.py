"""``iorthand export SESSION --format lerobot``: one robot's session as a LeRobotDataset v3 (parquet + mp4 +
``meta/``), written with lerobot's own metadata, parquet and statistics code, offline (``HF_HUB_OFFLINE=1``:
nothing is fetched from or pushed to a hub).

Features, at a fixed rate (``fps``, default 30, the camera's rate):

- ``observation.state`` (float32 × 15): the TCP pose ``[x, y, z, rx, ry, rz]`` (m, rotation vector in rad, UR's
  base frame), the six joint angles (rad, base to wrist) and the contact force ``[fx, fy, fz]`` (N, in the tool
  frame); names in :data:`STATE_NAMES`.
- ``action`` (float32 × 6): the applied twist ``[vx, vy, vz, wx, wy, wz]`` (m/s, rad/s, base frame) from
  ``state/applied``: what the supervisor let through of the operator's command, not what was asked.
- ``observation.images.camera``, ``observation.images.ultrasound``: mp4 videos (PyAV), at the size of the recorded
  frames or ``image_scale`` (½, ¼) of it, for each video key the session has.

Video codec (``vcodec``). ``mjpeg``, the default: every frame a JPEG in the mp4, so a recorded JPEG frame goes in
as it is, without being decoded or encoded (a packet copy, microseconds), and a picture held over several frame
times (the ultrasound at 15 fps in a 30 fps dataset) is the same JPEG again; only pictures that are not such a
JPEG are encoded (quality :data:`JPEG_QUALITY`): H.264 pictures (decoded with PyAV, every frame in recorded
order, as a P-frame needs those before it), scaled pictures, black ones. Every frame is a keyframe, so a
training loader seeks to any frame directly; the files are about as large as the recording's JPEG video.
The image statistics come from a sample of the frames as LeRobot samples them (:func:`sample_indices`), decoded
at 1/8 size (LeRobot subsamples them to ~150 px). Each episode's frames are written in slices of
:data:`SLICE_S` by worker processes, one per core, each reading from :data:`LOOKBACK_S` before its slice (the
picture held there; the keyframe an H.264 slice decodes from) and joined per episode; a slice gives what a
walk through the whole episode gives (tested). ``h264`` and ``libsvtav1`` (LeRobot's own default): every frame
decoded and handed to LeRobot's encoder (GOP 2) and its per-frame image statistics, ~10 ms per 640×480 frame
and stream: smaller files, an export many times slower (benchmarks/results/export.json).

Sampling. Frame ``k`` of an episode is at ``t_k = start + k / fps`` (source times, the edge's clock). The state,
the force and each image are the newest sample at or before ``t_k`` (sample and hold). The action of frame
``k`` is the newest applied twist at or before ``t_{k+1}``: what the operator did after seeing frame ``k``, as
LeRobot pairs an observation with the action that follows it; an applied twist older than the edge's default
command timeout (150 ms) counts as zero, because after it the edge has stopped the robot. An image whose latest
frame is a failure notice (the source is down) is black: a frozen picture must not pass for a live one. So is
an H.264 picture that cannot be decoded: before the stream's first keyframe (up to :data:`LOOKBACK_S` before the
exported range, with ``mjpeg``; within it, with LeRobot's encoders), and after a
failure notice or a frame missing from the recording until the next keyframe
(:class:`~iorthand_cloud.recorder.export_ros2.H264Sync`); and a picture held :data:`HOLD_MAX_S` with no newer
frame or notice at all (the source, or the edge, went silent). A dataset starts when every stream has a first sample
(a frame or a notice, decodable or not), and ends with the first stream to end.

Episodes come from annotations (``iorthand annotate TEXT --tag episode-start`` / ``--tag episode-end``): a start
opens an episode whose task is the annotation's text; an end closes it; a start while one is open closes that
one there and opens the next; the last one open ends with the session. An end with no episode open is ignored
(with a warning). Without any such tag the whole session (or ``--start``/``--end`` range) is one episode.
The task of an episode whose start has no text, and of a session without episode tags: ``--task``, else the
text of the latest annotation tagged ``task``, else the session's note, else :data:`DEFAULT_TASK`.

Conversion (episodes, frame times, sample and hold) is pure; :func:`export_lerobot` reads the numbers first,
then the video (decoding only the JPEG frames it has to, and every H.264 frame) and writes.
"""

from __future__ import annotations

import functools
import io
import os
import shutil
import time
from collections import deque
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from iorthand import keys
from iorthand.protocol import Annotation, AppliedCommand, ForceSample, RobotState, VideoFrame
from iorthand_cloud.recorder.export_ros2 import (
    ANNOTATIONS_KEY,
    JOINT_NAMES,
    Decoded,
    ExportError,
    H264Sync,
    export_target,
    iter_decoded,
    session_robots,
    time_window,
)

DEFAULT_FPS = 30
EPISODE_START, EPISODE_END, TASK_TAG = "episode-start", "episode-end", "task"
DEFAULT_TASK = "teleoperated ultrasound scan"
ACTION_MAX_AGE_NS = 150_000_000  # the edge's default command timeout (DESIGN.md, deadman)
STATE_NAMES = [
    *(f"tcp_{c}" for c in ("x", "y", "z", "rx", "ry", "rz")),
    *(f"q_{name.removesuffix('_joint')}" for name in JOINT_NAMES),
    "force_x", "force_y", "force_z",
]
ACTION_NAMES = ["vx", "vy", "vz", "wx", "wy", "wz"]
VIDEO_KEYS = (keys.VIDEO_CAMERA, keys.VIDEO_ULTRASOUND)
VCODECS = ("mjpeg", "h264", "libsvtav1")  # mjpeg: JPEGs as they are (see the module's docstring)
JPEG_QUALITY = 90  # for the pictures the mjpeg track has to encode
SLICE_S = 30.0  # s of frames per task of the mjpeg writer: the tasks of every episode and stream run in parallel
HOLD_MAX_S = 10.0  # s a picture is held with no newer frame or notice; then black (the source went silent)
KEYFRAME_MAX_S = 10.0  # the edge's longest keyframe interval (the bound of its video.keyframe_interval)
# s read before a slice: the frame held at its start, and for H.264 the keyframe its pictures are decoded from.
LOOKBACK_S = max(HOLD_MAX_S, KEYFRAME_MAX_S)
LATE_S = 2.0  # s read after a slice's last frame time: frames received later than that after their source time
IMAGE_SCALES = (1.0, 0.5, 0.25)  # the ratios a JPEG decoder shrinks by for free (see _HeldVideo)
ROBOT_TYPE = "ur"
# What this export needs beyond iorthand-cloud. lerobot 0.4.4 is the newest for Python 3.11, installed without its
# declared dependencies (they pin rerun-sdk 0.26 and OpenCV, which iorthand pins otherwise); torchvision must
# match torch's build, and LeRobotDataset decodes video with torchcodec, which needs FFmpeg's shared libraries.
INSTALL = ("pip install torch==2.14.1 torchvision==0.29.1 torchcodec==0.17.0 'datasets>=4,<5' "
           "'huggingface-hub>=0.34.2,<0.36' 'accelerate>=1.10,<2' 'av>=15,<16' 'jsonlines>=4,<5' pandas && "
           "pip install --no-deps lerobot==0.4.4 (and, to read the videos back, Debian's libavcodec59 "
           "libavformat59 libavutil57 libswscale6 libswresample4 libavdevice59 libavfilter8)")
AV_INSTALL = "pip install 'av>=15,<16'"  # PyAV: decodes recorded H.264 video (the edge has it, the cloud need not)


def image_feature(suffix: str) -> str:
    """``video/camera`` → ``observation.images.camera``."""
    return f"observation.images.{suffix.rsplit('/', 1)[-1]}"


# --------------------------------------------------------------------------------------------------- pure parts


@dataclass(frozen=True)
class Episode:
    start: int  # source time, ns: the first frame's
    end: int  # source time, ns: no frame after it
    task: str


def default_task(annotations: Sequence[Annotation], note: str) -> str:
    """The latest annotation tagged ``task``, else the session's note, else :data:`DEFAULT_TASK`."""
    tagged = [a.text.strip() for a in sorted(annotations, key=lambda a: a.t) if TASK_TAG in a.tags and a.text.strip()]
    return tagged[-1] if tagged else note.strip() or DEFAULT_TASK


def episodes_from_annotations(annotations: Sequence[Annotation], first: int, last: int, task: str,
                              warnings: list[str] | None = None) -> list[Episode]:
    """Episodes within [first, last] (ns) from the ``episode-start``/``episode-end`` annotations (see the module's
    docstring); ``task`` is for episodes whose start gives none. Episodes left empty by the clipping are dropped."""
    marks = sorted((a for a in annotations if EPISODE_START in a.tags or EPISODE_END in a.tags), key=lambda a: a.t)
    if not marks:
        return [Episode(first, last, task)] if last >= first else []
    spans: list[Episode] = []
    open_at: Annotation | None = None
    for a in marks:
        if open_at is not None:
            spans.append(Episode(open_at.t, a.t, open_at.text.strip() or task))
            open_at = None
        elif EPISODE_END in a.tags and EPISODE_START not in a.tags and warnings is not None:
            warnings.append(f"annotation {a.text!r} ends an episode, but none was open: ignored")
        if EPISODE_START in a.tags:
            open_at = a
    if open_at is not None:
        spans.append(Episode(open_at.t, last, open_at.text.strip() or task))
    out = []
    for ep in spans:
        clipped = Episode(max(ep.start, first), min(ep.end, last), ep.task)
        if clipped.end > clipped.start:
            out.append(clipped)
        elif warnings is not None:
            warnings.append(f"episode {ep.task!r} has no data within the exported range: left out")
    return out


def frame_times(start: int, end: int, fps: int) -> np.ndarray:
    """``start + k/fps`` (ns) for every k with a time at or before ``end``."""
    n = (end - start) * fps // 1_000_000_000 + 1
    return start + (np.arange(n, dtype=np.int64) * 1_000_000_000) // fps


@dataclass
class Series:
    """A recorded stream as arrays: source times (ns, sorted) and one row of values per sample."""

    times: np.ndarray
    values: np.ndarray

    @classmethod
    def of(cls, times: list[int], rows: list[Sequence[float]], width: int) -> Series:
        t = np.asarray(times, dtype=np.int64)
        v = np.asarray(rows, dtype=np.float64).reshape(-1, width)
        order = np.argsort(t, kind="stable")  # receive order is not always source order
        return cls(t[order], v[order])

    def __len__(self) -> int:
        return len(self.times)

    def held(self, at: np.ndarray, max_age: int | None = None) -> np.ndarray:
        """The newest row at or before each time of ``at``; zeros before the first sample or, with ``max_age``,
        where the newest sample is older than that (ns)."""
        idx = np.searchsorted(self.times, at, side="right") - 1
        out = np.zeros((len(at), self.values.shape[1]))
        if not len(self.times):  # (a stream never recorded: a session without commands has no applied ones)
            return out
        ok = idx >= 0
        if max_age is not None:
            ok &= (at - self.times[np.maximum(idx, 0)]) <= max_age
        out[ok] = self.values[idx[ok]]
        return out


def observations(state: Series, force: Series | None, applied: Series, times: np.ndarray,
                 fps: int) -> tuple[np.ndarray, np.ndarray]:
    """``observation.state`` and ``action`` (float32) at ``times``: see the module's docstring."""
    s = state.held(times)
    f = force.held(times) if force is not None else np.zeros((len(times), 3))
    period = 1_000_000_000 // fps
    a = applied.held(times + period, max_age=ACTION_MAX_AGE_NS)
    return np.hstack([s, f]).astype(np.float32), a.astype(np.float32)


# --------------------------------------------------------------------------------------------------- reading


@dataclass
class _VideoExtent:
    first: int  # source time of its first frame, ns
    last: int
    width: int  # of its first frame (a failure notice carries the configured size too)
    height: int
    frames: int  # recorded frames, failure notices included
    streams: set[str]  # the recorder's streams they are in (segments.VIDEO, unless its configuration says otherwise)


@dataclass
class _Session:
    state: Series  # tcp_pose (6) + q (6)
    force: Series | None
    applied: Series
    annotations: list[Annotation]
    video: dict[str, _VideoExtent]  # by key suffix


def _gather(folder: Path, lo: int | None, hi: int | None, robot: str) -> _Session:
    """Pass 1: the numeric streams of ``robot`` as arrays, the annotations, and the extent of each video."""
    st_t: list[int] = []
    st: list[list[float]] = []
    f_t: list[int] = []
    f: list[list[float]] = []
    a_t: list[int] = []
    a: list[list[float]] = []
    anns: list[Annotation] = []
    video: dict[str, _VideoExtent] = {}
    wanted = {keys.STATE_ROBOT, keys.STATE_FORCE, keys.STATE_APPLIED, *VIDEO_KEYS}
    topics = [ANNOTATIONS_KEY, *(keys.RobotKeys(robot).key(s) for s in wanted)]  # the others' messages are skipped
    for d in iter_decoded(folder, lo, hi, suffixes=wanted, topics=topics):
        msg = d.msg
        if isinstance(msg, Annotation):
            anns.append(msg)
        elif d.robot != robot:
            continue
        elif isinstance(msg, RobotState):
            st_t.append(msg.t)
            st.append([*msg.tcp_pose, *msg.q])
        elif isinstance(msg, ForceSample):
            f_t.append(msg.t)
            f.append(msg.force)
        elif isinstance(msg, AppliedCommand):
            a_t.append(msg.t)
            a.append(msg.applied)
        elif isinstance(msg, VideoFrame):
            v = video.get(d.suffix)
            if v is None:
                video[d.suffix] = _VideoExtent(msg.t, msg.t, msg.width, msg.height, 1, {d.stream})
            else:
                v.first, v.last, v.frames = min(v.first, msg.t), max(v.last, msg.t), v.frames + 1
                v.streams.add(d.stream)
    return _Session(Series.of(st_t, st, 12), Series.of(f_t, f, 3) if f_t else None, Series.of(a_t, a, 6), anns,
                    video)


class _VideoDemux:
    """Pass 2: every video stream of one robot from a single read of the session, in receive order, handed out
    per stream. A stream that needs its next frame pulls records until one comes; the other streams' frames met
    on the way wait in their queue, which stays short because the streams are interleaved in time (and a
    stream that has had all its frames, counted in pass 1, pulls nothing more)."""

    def __init__(self, records: Iterator[Decoded], robot: str, counts: dict[str, int]) -> None:
        self._records = records
        self._robot = robot
        self._left = dict(counts)
        self._queues: dict[str, deque[VideoFrame]] = {s: deque() for s in counts}

    def next(self, suffix: str) -> VideoFrame | None:
        q = self._queues[suffix]
        while not q and self._left[suffix] > 0:
            d = next(self._records, None)
            if d is None:
                break
            if d.robot == self._robot and d.suffix in self._queues and isinstance(d.msg, VideoFrame):
                self._queues[d.suffix].append(d.msg)
                self._left[d.suffix] -= 1
        return q.popleft() if q else None


class _H264Pictures:
    """One recorded H.264 stream decoded with PyAV, every frame in recorded order; a frame that cannot be decoded
    (see :class:`H264Sync`) gives no picture."""

    def __init__(self, suffix: str) -> None:
        try:
            import av
        except ImportError as exc:
            raise ExportError(f"the session's {suffix} video is H.264: decoding it needs the Python package "
                              f"'av' (PyAV), which is not installed: {AV_INSTALL}") from exc
        self._error, self._packet = av.error.FFmpegError, av.Packet
        self._codec = av.CodecContext.create("h264", "r")
        self._codec.thread_type = "SLICE"  # frame threads would hand each picture out frames later
        self.sync = H264Sync()
        self.undecodable = 0

    def feed(self, frame: VideoFrame) -> Any:
        """The picture (``av.VideoFrame``) of ``frame``, or None: a failure notice, or not decodable."""
        if not self.sync.admit(frame):
            return None
        try:
            pictures = self._codec.decode(self._packet(frame.data))
        except self._error:
            self.undecodable += 1
            self.sync.lose()
            self._codec.flush_buffers()
            return None
        return pictures[-1] if pictures else None


_STALE = object()  # a held picture not converted yet


class _HeldVideo:
    """One video stream walked in time order: the frame held at each asked time, black where the source had no
    picture (a failure notice, or a frame that does not decode), as an RGB array at the dataset's size
    (:meth:`at`) or as a JPEG (:meth:`jpeg_at`), each converted once per held frame. A JPEG frame is decoded only
    when an RGB array of it is asked for, or when it cannot go into a JPEG track as it is; H.264 frames are
    all decoded, as they come."""

    def __init__(self, frames: Callable[[], VideoFrame | None], width: int, height: int, suffix: str = "") -> None:
        self._frames = frames
        self._next = frames()
        self._held: Any = None  # a JPEG VideoFrame, a decoded H.264 picture (av.VideoFrame), or None: black
        self._held_t = 0  # the source time of the frame held, ns
        self._image: Any = None  # the held picture as RGB (None: black), or _STALE
        self._jpeg: bytes | None = None  # … and as a JPEG, once asked for
        self._h264: _H264Pictures | None = None
        self._suffix = suffix
        self.size = (width, height)
        self.black = np.zeros((height, width, 3), dtype=np.uint8)
        self._black_jpeg: bytes | None = None
        self._bad_jpegs = 0

    @property
    def undecodable(self) -> int:
        """Frames that did not decode (corrupt): black pictures."""
        return self._bad_jpegs + (self._h264.undecodable if self._h264 is not None else 0)

    @property
    def left_out(self) -> int:
        """H.264 frames that could not be decoded where they are (before a keyframe): black pictures."""
        return self._h264.sync.left_out if self._h264 is not None else 0

    def _advance(self, t: int) -> None:
        while self._next is not None and self._next.t <= t:
            frame, self._next = self._next, self._frames()
            if frame.encoding == "h264":
                if self._h264 is None:
                    self._h264 = _H264Pictures(self._suffix)
                self._held = self._h264.feed(frame)
            else:
                self._held = frame
            self._held_t = frame.t
            self._image, self._jpeg = _STALE, None

    def _silent(self, t: int) -> bool:
        """No frame, not even a failure notice, for :data:`HOLD_MAX_S` before ``t``: the source is gone."""
        return t - self._held_t > HOLD_MAX_S * 1e9

    def hold(self, t: int) -> None:
        """Take in the frames up to ``t`` (ns) without converting the one held there."""
        self._advance(t)

    def at(self, t: int) -> np.ndarray:
        self._advance(t)
        if self._silent(t):
            return self.black
        if self._image is _STALE:
            self._image = self._decode(self._held)
        return self._image if self._image is not None else self.black

    def jpeg_at(self, t: int) -> bytes:
        self._advance(t)
        if self._silent(t):
            self._black_jpeg = self._black_jpeg or _jpeg(self.black)
            return self._black_jpeg
        if self._jpeg is None:
            if isinstance(self._held, VideoFrame) and _fits_as_is(self._held, self.size):
                self._jpeg = self._held.data
            else:
                image = self.at(t)
                if image is self.black:
                    self._black_jpeg = self._black_jpeg or _jpeg(self.black)
                    self._jpeg = self._black_jpeg
                else:
                    self._jpeg = _jpeg(image)
        return self._jpeg

    def _decode(self, held: Any) -> np.ndarray | None:
        if held is None:
            return None
        if not isinstance(held, VideoFrame):  # a decoded H.264 picture: to RGB at the dataset's size
            w, h = self.size
            return held.to_ndarray(format="rgb24", width=w, height=h)
        return self._decode_jpeg(held)

    def _decode_jpeg(self, frame: VideoFrame) -> np.ndarray | None:
        from PIL import Image

        if frame.failure or not frame.data:
            return None
        try:
            img = Image.open(io.BytesIO(frame.data))
            img.draft("RGB", self.size)  # a JPEG shrinks by 1/2, 1/4 or 1/8 while it decodes: far cheaper
            img = img.convert("RGB")
        except Exception:  # a corrupt frame of any kind: no picture rather than a crash mid-export
            self._bad_jpegs += 1
            return None
        if img.size != self.size:
            img = img.resize(self.size)
        return np.asarray(img)


def _fits_as_is(frame: VideoFrame, size: tuple[int, int]) -> bool:
    """A recorded JPEG that can be a frame of the dataset's JPEG track as it is: a picture (not a failure notice),
    complete (the end marker is there), colour at the dataset's size, and chroma 4:2:0 (the track's one pixel
    format). Only the headers are read: a picture whose coded data is damaged past them goes in as recorded."""
    from PIL import Image, JpegImagePlugin

    if frame.failure or not frame.data.startswith(b"\xff\xd8") or not frame.data.endswith(b"\xff\xd9"):
        return False
    try:
        img = Image.open(io.BytesIO(frame.data))
        return (img.format == "JPEG" and img.mode == "RGB" and img.size == size
                and JpegImagePlugin.get_sampling(img) == 2)
    except Exception:  # not a JPEG it can read: decoded instead, which says so (black, counted)
        return False


def _jpeg(image: np.ndarray) -> bytes:
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(image).save(out, "JPEG", quality=JPEG_QUALITY, subsampling=2)  # 2: 4:2:0
    return out.getvalue()


class _JpegTrack:
    """Frames of one video feature as MJPEG in an mp4 (PyAV): frame k is the k-th JPEG added, at k/fps, each a
    keyframe. The frames whose index is in ``sampled`` are kept (:attr:`samples`) for the statistics."""

    def __init__(self, path: Path, fps: int, size: tuple[int, int], sampled: Collection[int] = ()) -> None:
        from fractions import Fraction

        import av

        path.parent.mkdir(parents=True, exist_ok=True)
        self._packet = av.Packet
        self._container = av.open(str(path), "w", format="mp4")
        self._stream = self._container.add_stream("mjpeg", rate=fps)
        self._stream.width, self._stream.height = size
        self._stream.pix_fmt = "yuvj420p"
        self._time_base = Fraction(1, fps)
        self._stream.time_base = self._time_base
        self._sampled = set(sampled)
        self.samples: list[bytes] = []
        self.count = 0

    def add(self, jpeg: bytes) -> None:
        packet = self._packet(jpeg)
        packet.stream = self._stream
        packet.pts = packet.dts = self.count
        packet.time_base = self._time_base
        packet.is_keyframe = True
        self._container.mux(packet)
        if self.count in self._sampled:
            self.samples.append(jpeg)
        self.count += 1

    def close(self) -> None:
        self._container.close()


def _picture_stats(samples: Sequence[bytes]) -> dict[str, np.ndarray]:
    """Sampled JPEG frames' statistics in LeRobot's form: per channel, in [0, 1], shape (3, 1, 1). Large pictures
    are decoded at 1/8 size (the JPEG decoder's cheapest scale; LeRobot subsamples them to ~150 px): channel
    statistics hardly change, their cost drops 4× (its quantiles are histograms over every value)."""
    from lerobot.datasets.compute_stats import get_feature_stats
    from PIL import Image

    pictures = []
    for data in samples:
        img = Image.open(io.BytesIO(data))
        if max(img.size) >= 300:
            img.draft("RGB", (img.width // 8, img.height // 8))
        pictures.append(np.asarray(img.convert("RGB")).transpose(2, 0, 1))
    stats = get_feature_stats(np.stack(pictures), axis=(0, 2, 3), keepdims=True)
    return {k: v if k == "count" else np.squeeze(v / 255.0, axis=0) for k, v in stats.items()}


@dataclass(frozen=True)
class _Slice:
    """A task: the frames of one video stream at ``times`` (ns) as a JPEG track in ``path``."""

    folder: Path
    robot: str
    suffix: str
    streams: tuple[str, ...]  # the recorder's streams its frames are in
    size: tuple[int, int]
    fps: int
    times: np.ndarray
    path: Path
    sampled: tuple[int, ...]  # indices into ``times`` whose frames are kept for the statistics
    counted_after: int  # ns: frames after this that do not decode are counted (the previous slice's last time)


@dataclass
class _SliceDone:
    frames: int
    samples: list[bytes]
    undecodable: int
    left_out: int


def _write_slice(job: _Slice) -> _SliceDone:
    """One slice, in a worker process: the stream read from :data:`LOOKBACK_S` before its first frame time (the
    frame held there; for H.264, the keyframe its pictures are decoded from, which a slice starting mid-way
    through a group of pictures needs) to :data:`LATE_S` after its last, walked as :class:`_HeldVideo` walks it.
    Frames that do not decode are counted after ``counted_after``, so that each is counted by one slice."""
    first, last = int(job.times[0]), int(job.times[-1])
    frames = (d.msg for d in iter_decoded(job.folder, first - int(LOOKBACK_S * 1e9), last + int(LATE_S * 1e9),
                                           suffixes={job.suffix}, streams=job.streams,
                                           topics=[keys.RobotKeys(job.robot).key(job.suffix)])
              if isinstance(d.msg, VideoFrame))
    video = _HeldVideo(lambda: next(frames, None), *job.size, job.suffix)
    video.hold(min(job.counted_after, first - 1))  # the lookback: decoded where it must be, not written
    undecodable, left_out = video.undecodable, video.left_out
    track = _JpegTrack(job.path, job.fps, job.size, job.sampled)
    try:
        for t in job.times.tolist():
            track.add(video.jpeg_at(t))
    finally:
        track.close()
    return _SliceDone(track.count, track.samples, video.undecodable - undecodable, video.left_out - left_out)


class _Rows:
    """The dataset's parquet rows, episode after episode, in LeRobot's files (``data_path``): a new file when the
    current one would pass ``data_files_size_in_mb``. The rows are built as LeRobot builds them (a
    ``datasets.Dataset`` with its features), without its per-row image embedding pass, which costs ~1 ms a row
    and has nothing to embed here (the pictures are in the videos)."""

    def __init__(self, meta: Any) -> None:
        self._meta = meta
        self._chunk, self._file = 0, 0
        self._writer: Any = None
        self._bytes = 0

    def write(self, columns: dict[str, np.ndarray]) -> dict[str, int]:
        import datasets
        import pyarrow.parquet as pq
        from lerobot.datasets.utils import get_hf_features_from_features, update_chunk_file_indices

        features = get_hf_features_from_features(self._meta.features)
        table = datasets.Dataset.from_dict({k: columns[k] for k in features}, features=features,
                                           split="train").with_format("arrow")[:]
        if self._writer is not None and (self._bytes + table.nbytes) / 1e6 >= self._meta.data_files_size_in_mb:
            self.close()
            self._chunk, self._file = update_chunk_file_indices(self._chunk, self._file, self._meta.chunks_size)
        if self._writer is None:
            path = self._meta.root / self._meta.data_path.format(chunk_index=self._chunk, file_index=self._file)
            path.parent.mkdir(parents=True, exist_ok=True)
            self._writer = pq.ParquetWriter(path, schema=table.schema, compression="snappy", use_dictionary=True)
        self._writer.write_table(table)
        self._bytes += table.nbytes
        first = int(columns["index"][0])
        return {"data/chunk_index": self._chunk, "data/file_index": self._file,
                "dataset_from_index": first, "dataset_to_index": first + len(table)}

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer, self._bytes = None, 0


# --------------------------------------------------------------------------------------------------- writing


@dataclass
class LeRobotExport:
    path: Path
    fps: int
    frames: int
    episodes: list[Episode]
    features: dict[str, dict[str, Any]]
    warnings: list[str] = field(default_factory=list)


def _pick_robot(folder: Path, robot: str | None) -> str:
    robots = session_robots(folder)
    if robot is not None:
        if robot not in robots:
            raise ExportError(f"robot {robot!r} is not in this session (it has: {', '.join(robots) or 'none'})")
        return robot
    if len(robots) != 1:
        raise ExportError(f"the session has robots {', '.join(robots) or '(none)'}: choose one with --robot"
                          if robots else "the session has no robot's data")
    return robots[0]


def _wait_for_room(dataset: Any) -> None:
    """LeRobot's streaming encoder drops a frame (with a log line) when its queue stays full for 0.1 s, which a
    loaded machine can cause; offline, we wait for room instead. Its queues are internal: if they are not where
    0.4 keeps them, this waits for nothing and the frame count check after writing still catches a drop."""
    encoder = getattr(dataset, "_streaming_encoder", None)
    for q in getattr(encoder, "_frame_queues", {}).values():
        while q.full():
            time.sleep(0.002)


def _video_frame_counts(root: Path, video_features: Sequence[str]) -> dict[str, int]:
    import av

    out = {}
    for feature in video_features:
        n = 0
        for path in sorted((root / "videos" / feature).rglob("*.mp4")):
            with av.open(str(path)) as container:
                n += container.streams.video[0].frames
        out[feature] = n
    return out


def _quiet_libraries() -> None:
    """No progress bars from datasets and no FFmpeg encoder statistics on the terminal: LeRobot hands FFmpeg's
    logging back to FFmpeg's own stderr printer after each video, so FFmpeg's own threshold is what counts."""
    import av
    import datasets

    datasets.disable_progress_bars()
    av.logging.set_libav_level(av.logging.ERROR)


def _write_encoded(ds: Any, episodes: list[Episode], data: _Session, folder: Path, lo: int | None, hi: int | None,
                   robot: str, sizes: dict[str, tuple[int, int]], fps: int) -> tuple[int, dict[str, list[int]]]:
    """Every frame through LeRobot's ``add_frame``, the video streams read together in one pass
    (:class:`_VideoDemux`): its streaming encoder encodes the pictures and takes their statistics. Returns what
    :func:`_write_jpeg_tracks` returns."""
    streams = set().union(*(data.video[s].streams for s in sizes))  # only these are read
    demux = _VideoDemux(iter_decoded(folder, lo, hi, suffixes=set(sizes), streams=streams), robot,
                        {s: data.video[s].frames for s in sizes})
    videos = {s: _HeldVideo(functools.partial(demux.next, s), *size, s) for s, size in sizes.items()}
    frames = 0
    for ep in episodes:
        times = frame_times(ep.start, ep.end, fps)
        state, action = observations(data.state, data.force, data.applied, times, fps)
        for i, t in enumerate(times.tolist()):
            frame: dict[str, Any] = {"observation.state": state[i], "action": action[i], "task": ep.task}
            for suffix, video in videos.items():
                frame[image_feature(suffix)] = video.at(t)
            _wait_for_room(ds)
            ds.add_frame(frame)
        ds.save_episode()
        frames += len(times)
    return frames, {s: [v.undecodable, v.left_out] for s, v in videos.items()}


def _slices(times: np.ndarray, fps: int) -> list[np.ndarray]:
    size = max(1, int(SLICE_S * fps))
    return [times[i:i + size] for i in range(0, len(times), size)]


def _write_jpeg_tracks(ds: Any, episodes: list[Episode], data: _Session, folder: Path, robot: str,
                       sizes: dict[str, tuple[int, int]], fps: int) -> tuple[int, dict[str, list[int]]]:
    """Each episode's videos as JPEG tracks, written in slices of :data:`SLICE_S` by a pool of worker processes
    (one per core: decoding H.264 and encoding JPEGs is most of the work, and Python threads would share one
    core) and joined into a file per episode and feature (``videos/<feature>/chunk-…/file-…``, from 0 s: a
    LeRobot v3 episode may have its own file); each episode's columns at once (:class:`_Rows`); its metadata and
    statistics through LeRobot's ``meta.save_episode`` (which writes ``meta/``). Returns the number of frames
    and, per stream, the frames that did not decode and those left out before a keyframe."""
    import multiprocessing
    import tempfile
    from concurrent.futures import ProcessPoolExecutor

    from lerobot.datasets.compute_stats import compute_episode_stats, sample_indices
    from lerobot.datasets.utils import update_chunk_file_indices
    from lerobot.datasets.video_utils import concatenate_video_files

    meta = ds.meta
    columns = {k: ft for k, ft in meta.features.items() if ft["dtype"] not in ("video", "image", "string")}
    work = Path(tempfile.mkdtemp(prefix="slices-", dir=meta.root))
    jobs: dict[tuple[int, str], list[_Slice]] = {}
    episode_times = [frame_times(ep.start, ep.end, fps) for ep in episodes]
    for index, times in enumerate(episode_times):
        sampled = sample_indices(len(times))
        for suffix, size in sizes.items():
            parts, offset = jobs.setdefault((index, suffix), []), 0
            for n, part in enumerate(_slices(times, fps)):
                local = tuple(i - offset for i in sampled if offset <= i < offset + len(part))
                parts.append(_Slice(folder, robot, suffix, tuple(sorted(data.video[suffix].streams)), size, fps,
                                    part, work / f"{index}-{suffix.replace('/', '_')}-{n}.mp4", local,
                                    int(times[offset - 1]) if offset else int(part[0]) - 1))
                offset += len(part)
    counts: dict[str, list[int]] = {suffix: [0, 0] for suffix in sizes}
    rows = _Rows(meta)
    frames, place = 0, (0, 0)
    workers = min(os.cpu_count() or 1, max(1, sum(map(len, jobs.values()))))
    # forkserver: workers forked from a clean process, not from this one with torch and its threads loaded
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("forkserver"))
    try:
        futures = {key: [pool.submit(_write_slice, job) for job in parts] for key, parts in jobs.items()}
        for index, (ep, times) in enumerate(zip(episodes, episode_times, strict=True)):
            if index:
                place = update_chunk_file_indices(*place, meta.chunks_size)
            n = len(times)
            stats: dict[str, Any] = {}
            metadata: dict[str, Any] = {"episode_index": index}
            for suffix in sizes:
                feature = image_feature(suffix)
                results = [f.result() for f in futures[index, suffix]]
                if sum(r.frames for r in results) != n:
                    raise ExportError(f"{feature}, episode {index}: {sum(r.frames for r in results)} frames "
                                      f"written of {n}")
                target = meta.root / meta.video_path.format(video_key=feature, chunk_index=place[0],
                                                            file_index=place[1])
                target.parent.mkdir(parents=True, exist_ok=True)
                parts = [job.path for job in jobs[index, suffix]]
                if len(parts) == 1:
                    shutil.move(parts[0], target)
                else:
                    concatenate_video_files(parts, target)  # a remux: every frame is a keyframe
                stats[feature] = _picture_stats([j for r in results for j in r.samples])
                counts[suffix][0] += sum(r.undecodable for r in results)
                counts[suffix][1] += sum(r.left_out for r in results)
                metadata.update({f"videos/{feature}/chunk_index": place[0],
                                 f"videos/{feature}/file_index": place[1],
                                 f"videos/{feature}/from_timestamp": 0.0,
                                 f"videos/{feature}/to_timestamp": n / fps})
            state, action = observations(data.state, data.force, data.applied, times, fps)
            meta.save_episode_tasks([ep.task])
            episode = {"observation.state": state, "action": action,
                       "timestamp": (np.arange(n) / fps).astype(np.float32), "frame_index": np.arange(n),
                       "episode_index": np.full(n, index),
                       "index": np.arange(meta.total_frames, meta.total_frames + n),
                       "task_index": np.full(n, meta.get_task_index(ep.task))}
            stats.update(compute_episode_stats(episode, columns))
            metadata.update(rows.write(episode))
            if index == 0:
                meta.update_video_info()  # codec, size, pixel format: read from episode 0's files
            meta.save_episode(index, n, [ep.task], stats, metadata)
            frames += n
    finally:
        pool.shutdown(cancel_futures=True)  # after a failure, the slices not started are not written
        rows.close()
        shutil.rmtree(work, ignore_errors=True)
    return frames, counts


def export_lerobot(session: str | Path, out: str | Path | None = None, start: float | None = None,
                   end: float | None = None, fps: int = DEFAULT_FPS, robot: str | None = None,
                   task: str | None = None, vcodec: str = VCODECS[0], image_scale: float = 1.0) -> LeRobotExport:
    """Write the dataset folder (refusing one that exists); ``start``/``end`` are seconds from the session's
    first message."""
    if vcodec not in VCODECS:
        raise ExportError(f"video codec {vcodec!r} is not one of {', '.join(VCODECS)}")
    if not 1 <= fps <= 120:
        raise ExportError(f"fps {fps} is not within 1..120")
    if image_scale not in IMAGE_SCALES:
        raise ExportError(f"image scale {image_scale:g} is not one of {', '.join(f'{x:g}' for x in IMAGE_SCALES)}")
    folder, manifest, path = export_target(session, out, "lerobot")
    robot = _pick_robot(folder, robot)
    lo, hi = time_window(folder, start, end)
    data = _gather(folder, lo, hi, robot)
    if not len(data.state):
        raise ExportError(f"no robot state of {robot} in the exported range: nothing to export")
    streams = [data.state, *([data.force] if data.force is not None else [])]
    first = max([s.times[0] for s in streams] + [v.first for v in data.video.values()])
    last = min([s.times[-1] for s in streams] + [v.last for v in data.video.values()])
    warnings: list[str] = []
    if data.force is None:
        warnings.append(f"no force samples of {robot}: the force in observation.state is zero")
    if last <= first:
        raise ExportError("the streams of the session do not overlap in time: nothing to export")
    fallback = task.strip() if task and task.strip() else default_task(data.annotations, manifest.note)
    episodes = episodes_from_annotations(data.annotations, int(first), int(last), fallback, warnings)
    if task and task.strip():  # --task names the task of every episode
        episodes = [Episode(e.start, e.end, fallback) for e in episodes]
    if not episodes:
        raise ExportError("no episode has data within the exported range")

    features: dict[str, dict[str, Any]] = {
        "observation.state": {"dtype": "float32", "shape": (len(STATE_NAMES),), "names": STATE_NAMES},
        "action": {"dtype": "float32", "shape": (len(ACTION_NAMES),), "names": ACTION_NAMES},
    }
    for suffix in VIDEO_KEYS:
        if suffix in data.video:
            v = data.video[suffix]
            w, h = int(v.width * image_scale), int(v.height * image_scale)
            w, h = w - w % 2, h - h % 2  # yuv420p needs even sides
            features[image_feature(suffix)] = {"dtype": "video", "shape": (h, w, 3),
                                               "names": ["height", "width", "channels"]}

    # Before lerobot (and huggingface_hub) are imported: they read it once, at import.
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    _quiet_libraries()
    sizes = {s: features[image_feature(s)]["shape"][1::-1] for s in VIDEO_KEYS if s in data.video}
    try:
        # mjpeg: no LeRobot encoder (the tracks are written here); it still needs a codec name it knows.
        ds = LeRobotDataset.create(f"iorthand/{manifest.session_id}", fps, features, root=path,
                                   robot_type=ROBOT_TYPE, use_videos=True,
                                   vcodec="h264" if vcodec == "mjpeg" else vcodec,
                                   streaming_encoding=vcodec != "mjpeg", encoder_queue_maxsize=16)
        if vcodec == "mjpeg":
            frames, counts = _write_jpeg_tracks(ds, episodes, data, folder, robot, sizes, fps)
        else:
            frames, counts = _write_encoded(ds, episodes, data, folder, lo, hi, robot, sizes, fps)
        ds.finalize()
        written = _video_frame_counts(path, [image_feature(s) for s in sizes])
        short = {k: n for k, n in written.items() if n != frames}
        if short:
            lost = ", ".join(f"{k}: {n} of {frames}" for k, n in short.items())
            raise ExportError(f"the video encoder lost frames ({lost}): the dataset was removed; try again on a "
                              "less loaded machine")
    except BaseException:
        shutil.rmtree(path, ignore_errors=True)  # ours: it did not exist before; half a dataset misleads
        raise
    for suffix, (undecodable, left_out) in counts.items():
        if undecodable:
            warnings.append(f"{undecodable} {suffix} frame(s) did not decode: black in the dataset")
        if left_out:
            warnings.append(f"{left_out} {suffix} H.264 frame(s) came before a keyframe (where the range or "
                            "the recording starts, or after a missing frame) and cannot be decoded: black in the "
                            "dataset while they are held")
    return LeRobotExport(path, fps, frames, episodes, features, warnings)
