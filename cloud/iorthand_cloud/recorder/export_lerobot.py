"""``iorthand export SESSION --format lerobot``: one robot's session as a LeRobotDataset v3 (parquet + mp4 +
``meta/``), written with lerobot's own API (``LeRobotDataset.create`` / ``add_frame`` / ``save_episode`` /
``finalize``), offline (``HF_HUB_OFFLINE=1``: nothing is fetched from or pushed to a hub).

Features, at a fixed rate (``fps``, default 30, the camera's rate):

- ``observation.state`` (float32 × 15): the TCP pose ``[x, y, z, rx, ry, rz]`` (m, rotation vector in rad, UR's
  base frame), the six joint angles (rad, base to wrist) and the contact force ``[fx, fy, fz]`` (N, in the tool
  frame); names in :data:`STATE_NAMES`.
- ``action`` (float32 × 6): the applied twist ``[vx, vy, vz, wx, wy, wz]`` (m/s, rad/s, base frame) from
  ``state/applied``: what the supervisor let through of the operator's command, not what was asked.
- ``observation.images.camera``, ``observation.images.ultrasound``: mp4 videos (PyAV; h264 by default, or
  LeRobot's own default AV1), at the size of the recorded frames or ``image_scale`` (½, ¼) of it, for each video
  key the session has. Video is most of the export's time: per frame and stream, a JPEG decode, the h264
  encode (GOP 2, as LeRobot sets it) and LeRobot's image statistics (~3 ms, whatever the size). A lower rate
  is proportionally faster; a smaller picture saves decoding, encoding and disk, not the statistics.
  A recorded H.264 stream (the edge's default) is decoded with PyAV, every frame in recorded order (a P-frame
  needs those before it, so a lower rate saves no decoding there), ~0.3 ms a frame at 640×480.

Sampling. Frame ``k`` of an episode is at ``t_k = start + k / fps`` (source times, the edge's clock). The state,
the force and each image are the newest sample at or before ``t_k`` (sample and hold). The action of frame
``k`` is the newest applied twist at or before ``t_{k+1}``: what the operator did after seeing frame ``k``, as
LeRobot pairs an observation with the action that follows it; an applied twist older than the edge's default
command timeout (150 ms) counts as zero, because after it the edge has stopped the robot. An image whose latest
frame is a failure notice (the source is down) is black: a frozen picture must not pass for a live one. So is
an H.264 picture that cannot be decoded: before the stream's first keyframe in the exported range, and after a
failure notice or a frame missing from the recording until the next keyframe
(:class:`~iorthand_cloud.recorder.export_ros2.H264Sync`). A dataset starts when every stream has a first sample
(a frame or a notice, decodable or not), and ends with the first stream to end.

Episodes come from annotations (``iorthand annotate TEXT --tag episode-start`` / ``--tag episode-end``): a start
opens an episode whose task is the annotation's text; an end closes it; a start while one is open closes that
one there and opens the next; the last one open ends with the session. An end with no episode open is ignored
(with a warning). Without any such tag the whole session (or ``--start``/``--end`` range) is one episode.
The task of an episode whose start has no text, and of a session without episode tags: ``--task``, else the
text of the latest annotation tagged ``task``, else the session's note, else :data:`DEFAULT_TASK`.

Conversion (episodes, frame times, sample and hold) is pure; :func:`export_lerobot` reads the session twice
(the numbers first, then the video streams together in time order, decoding only the JPEG frames it uses and
every H.264 frame) and writes.
"""

from __future__ import annotations

import functools
import io
import os
import shutil
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from iorthand import keys
from iorthand.protocol import Annotation, AppliedCommand, ForceSample, RobotState, VideoFrame
from iorthand_cloud.recorder.export_ros2 import (
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
VCODECS = ("h264", "libsvtav1")
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
    for d in iter_decoded(folder, lo, hi, suffixes=wanted):
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
                video[d.suffix] = _VideoExtent(msg.t, msg.t, msg.width, msg.height, 1)
            else:
                v.first, v.last, v.frames = min(v.first, msg.t), max(v.last, msg.t), v.frames + 1
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


class _HeldVideo:
    """One video stream walked in time order: the frame held at each asked time, decoded once (RGB, the
    dataset's size), black where the source had no picture (a failure notice, or a frame that does not decode).
    JPEG frames are decoded only when held at an asked time; H.264 frames all, as they come."""

    def __init__(self, frames: Callable[[], VideoFrame | None], width: int, height: int, suffix: str = "") -> None:
        self._frames = frames
        self._next = frames()
        self._held: Any = None  # a JPEG VideoFrame, a decoded H.264 picture (av.VideoFrame), or None: black
        self._image: np.ndarray | None = None
        self._h264: _H264Pictures | None = None
        self._suffix = suffix
        self.size = (width, height)
        self.black = np.zeros((height, width, 3), dtype=np.uint8)
        self._bad_jpegs = 0

    @property
    def undecodable(self) -> int:
        """Frames that did not decode (corrupt): black pictures."""
        return self._bad_jpegs + (self._h264.undecodable if self._h264 is not None else 0)

    @property
    def left_out(self) -> int:
        """H.264 frames that could not be decoded where they are (before a keyframe): black pictures."""
        return self._h264.sync.left_out if self._h264 is not None else 0

    def at(self, t: int) -> np.ndarray:
        changed = False
        while self._next is not None and self._next.t <= t:
            frame, self._next = self._next, self._frames()
            if frame.encoding == "h264":
                if self._h264 is None:
                    self._h264 = _H264Pictures(self._suffix)
                self._held = self._h264.feed(frame)
            else:
                self._held = frame
            changed = True
        if changed:
            self._image = self._decode(self._held)
        return self._image if self._image is not None else self.black

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


def export_lerobot(session: str | Path, out: str | Path | None = None, start: float | None = None,
                   end: float | None = None, fps: int = DEFAULT_FPS, robot: str | None = None,
                   task: str | None = None, vcodec: str = "h264", image_scale: float = 1.0) -> LeRobotExport:
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
    suffixes = [s for s in VIDEO_KEYS if s in data.video]
    demux = _VideoDemux(iter_decoded(folder, lo, hi, suffixes=set(suffixes)), robot,
                        {s: data.video[s].frames for s in suffixes})
    videos = {s: _HeldVideo(functools.partial(demux.next, s), *features[image_feature(s)]["shape"][1::-1], s)
              for s in suffixes}
    frames = 0
    try:
        ds = LeRobotDataset.create(f"iorthand/{manifest.session_id}", fps, features, root=path,
                                   robot_type=ROBOT_TYPE, use_videos=True, vcodec=vcodec, streaming_encoding=True,
                                   encoder_queue_maxsize=16)
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
        ds.finalize()
        counts = _video_frame_counts(path, [image_feature(s) for s in videos])
        short = {k: n for k, n in counts.items() if n != frames}
        if short:
            lost = ", ".join(f"{k}: {n} of {frames}" for k, n in short.items())
            raise ExportError(f"the video encoder lost frames ({lost}): the dataset was removed; try again on a "
                              "less loaded machine")
    except BaseException:
        shutil.rmtree(path, ignore_errors=True)  # ours: it did not exist before; half a dataset misleads
        raise
    for suffix, video in videos.items():
        if video.undecodable:
            warnings.append(f"{video.undecodable} {suffix} frame(s) did not decode: black in the dataset")
        if video.left_out:
            warnings.append(f"{video.left_out} {suffix} H.264 frame(s) came before a keyframe (where the range or "
                            "the recording starts, or after a missing frame) and cannot be decoded: black in the "
                            "dataset while they are held")
    return LeRobotExport(path, fps, frames, episodes, features, warnings)
