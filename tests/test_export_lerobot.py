"""``iorthand export --format lerobot``: a session recorded through a real router becomes a LeRobotDataset v3 that
lerobot's own ``LeRobotDataset`` loads: the episodes the annotations mark, at a fixed rate, the state, force and
applied twist held at each frame time, the camera's and the ultrasound's pictures (black while the source
failed). The pure parts (episodes, frame times, sample and hold) are checked on their own, without lerobot.
A session whose camera streams H.264 (``tests/h264_session.py``) gives the pictures the edge encoded, black
where the stream cannot be decoded (before its first keyframe, a failure, a lost frame until the next keyframe).

Without lerobot (or torch) installed, the tests that need it skip and say so."""

from __future__ import annotations

import io
import json
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from iorthand import keys
from iorthand.protocol import Annotation, AppliedCommand, ForceSample, RobotState, VideoFrame
from iorthand_cloud.recorder.export_lerobot import (
    ACTION_MAX_AGE_NS,
    ACTION_NAMES,
    DEFAULT_TASK,
    STATE_NAMES,
    Episode,
    ExportError,
    Series,
    default_task,
    episodes_from_annotations,
    export_lerobot,
    frame_times,
    observations,
)
from iorthand_cloud.recorder.reader import iter_records
from tests import h264_session as h264
from tests.conftest import iorthand_cmd
from tests.test_export_ros2 import FAILURE, ROBOT, Recorded, record_session

S = 1_000_000_000


def _ann(t: float, text: str = "", *tags: str) -> Annotation:
    return Annotation(author="op", text=text, tags=list(tags)).stamp(1, t=int(t * S))


# ------------------------------------------------------------------------------------------------- pure parts


def test_episodes_follow_the_start_and_end_annotations() -> None:
    warnings: list[str] = []
    anns = [_ann(30, "second", "episode-start"), _ann(2, "first scan", "episode-start"), _ann(10, "", "episode-end"),
            _ann(12, "stray", "episode-end"), _ann(20, "", "episode-start"), _ann(25, "a note")]
    eps = episodes_from_annotations(anns, first=1 * S, last=40 * S, task="default", warnings=warnings)
    assert eps == [Episode(2 * S, 10 * S, "first scan"), Episode(20 * S, 30 * S, "default"),
                   Episode(30 * S, 40 * S, "second")]
    assert warnings == ["annotation 'stray' ends an episode, but none was open: ignored"]
    # Clipped to the exported range; an episode left empty is dropped with a warning.
    eps = episodes_from_annotations(anns, first=5 * S, last=25 * S, task="t", warnings=warnings)
    assert eps == [Episode(5 * S, 10 * S, "first scan"), Episode(20 * S, 25 * S, "t")]
    assert warnings[-1] == "episode 'second' has no data within the exported range: left out"
    # No episode tags: the whole range is one episode.
    assert episodes_from_annotations([_ann(3, "x")], 1 * S, 9 * S, "t") == [Episode(1 * S, 9 * S, "t")]


def test_the_default_task() -> None:
    assert default_task([_ann(1, "old", "task"), _ann(5, "scan the liver", "task"), _ann(9, "no tag")],
                        "note") == "scan the liver"
    assert default_task([_ann(1, "no tag")], "  left flank ") == "left flank"
    assert default_task([], "") == DEFAULT_TASK


def test_the_command_line_offers_what_the_exporters_take() -> None:
    from iorthand.cli import build_parser
    from iorthand_cloud.recorder import export_lerobot as lr
    from iorthand_cloud.recorder import export_ros2

    export = build_parser()._subparsers._group_actions[0].choices["export"]  # type: ignore[union-attr]
    opts = {a.dest: a for a in export._actions}
    assert opts["format"].choices == ["rrd", "ros2", "lerobot"] and opts["format"].default == "rrd"
    assert tuple(opts["storage"].choices) == export_ros2.STORAGES
    assert tuple(opts["vcodec"].choices) == lr.VCODECS and tuple(opts["image_scale"].choices) == lr.IMAGE_SCALES
    assert opts["vcodec"].default == lr.VCODECS[0] == "mjpeg"
    assert opts["fps"].default == lr.DEFAULT_FPS


def test_frame_times_are_fixed_rate_and_end_at_the_end() -> None:
    assert frame_times(10 * S, 11 * S, 4).tolist() == [10 * S + k * S // 4 for k in range(5)]
    ts = frame_times(5, 5 + S - 1, 30)
    assert len(ts) == 30 and ts[-1] <= 5 + S - 1
    assert np.all(np.diff(frame_times(0, 60 * S, 30)) // 1000 == 33_333)


def test_state_is_held_and_the_action_is_the_twist_that_follows() -> None:
    state = Series.of([10, 20, 30], [[float(i)] * 12 for i in (1, 2, 3)], 12)
    force = Series.of([5, 25], [[1.0, 0, 0], [2.0, 0, 0]], 3)
    p = S // 10  # the frame period at 10 fps
    t2 = 15 + p + ACTION_MAX_AGE_NS + 100  # the operator resumes after a pause longer than the command timeout
    applied = Series.of([t2, 15], [[0.7] + [0.0] * 5, [0.5] + [0.0] * 5], 6)  # receive order ≠ time order
    times = np.array([10, 29, 15 + ACTION_MAX_AGE_NS - p, 16 + ACTION_MAX_AGE_NS - p, t2 - p - 1, t2 - p],
                     dtype=np.int64)
    obs, act = observations(state, force, applied, times, fps=10)
    assert obs.dtype == act.dtype == np.float32 and obs.shape == (6, 15) and act.shape == (6, 6)
    assert obs[:2, 0].tolist() == [1.0, 2.0] and obs[:2, 11].tolist() == [1.0, 2.0]
    assert obs[:2, 12].tolist() == [1.0, 2.0] and obs[2:, 0].tolist() == [3.0] * 4
    # The action of a frame is the twist in force one period later: fresh, exactly as old as the timeout, older
    # (the edge has stopped the robot: zero), still older, and the first twist after the pause.
    assert act[:, 0].tolist() == pytest.approx([0.5, 0.5, 0.5, 0.0, 0.0, 0.7])
    no_force, _ = observations(state, None, applied, times, fps=10)
    assert not no_force[:, 12:].any() and (no_force[:, :12] == obs[:, :12]).all()


def test_a_session_without_commands_has_zero_actions() -> None:
    """Found by a review of the readers: a recording of a robot that no operator drove (no applied commands) made
    ``export --format lerobot`` end in an IndexError traceback."""
    state = Series.of([10, 20], [[1.0] * 12, [2.0] * 12], 12)
    obs, act = observations(state, None, Series.of([], [], 6), np.array([10, 20], dtype=np.int64), fps=10)
    assert obs[:, 0].tolist() == [1.0, 2.0] and act.shape == (2, 6) and not act.any()


def _h264_frames(n: int, size: tuple[int, int]) -> tuple[list[VideoFrame], dict[int, np.ndarray]]:
    """``n`` frames of the edge's pattern through the edge's encoder (keyframes every 10 frames), 10 ms apart;
    the first 3 dropped (a recording that starts inside a group of pictures), frames 12-13 failure notices."""
    from iorthand_edge.video.config import StreamConfig
    from iorthand_edge.video.h264 import H264Encoder
    from iorthand_edge.video.sources import PatternSource
    from iorthand_edge.video.stream import Captured, encode_frame

    config = StreamConfig(width=size[0], height=size[1], fps=100.0, codec="h264", keyframe_interval=0.1)
    encoder, source = H264Encoder(*size, 100.0, 2_000_000, 0.1), PatternSource(*size)
    frames, images = [], {}
    for seq in range(1, n + 1):
        t = seq * 10_000_000
        if seq in (12, 13):
            frame = encode_frame("camera", Captured(seq, t, None, "unplugged"), config, encoder)
        else:
            images[seq] = source.grab()
            frame = encode_frame("camera", Captured(seq, t, images[seq]), config, encoder)
        if seq > 3:
            frames.append(frame)
    return frames, images


def test_h264_pictures_are_decoded_in_order_and_held_black_where_they_cannot_be() -> None:
    from iorthand_cloud.recorder.export_lerobot import _HeldVideo

    frames, images = _h264_frames(40, (160, 120))
    assert [f.seq for f in frames if f.keyframe] == [11, 14, 24, 34]  # 11: the edge's next; 14: after the failure
    it = iter(frames)
    video = _HeldVideo(lambda: next(it, None), 80, 60, "video/camera")  # half size
    for seq in range(4, 41, 3):  # asked at a third of the rate: every frame is decoded all the same
        img = video.at(seq * 10_000_000 + 5_000_000).astype(np.float64)
        assert img.shape == (60, 80, 3)
        if seq < 11 or seq in (12, 13):  # before the first keyframe; the failure notices
            assert not img.any(), seq
        else:
            errors = {k: np.abs(img - np.asarray(Image.fromarray(v[..., ::-1]).resize((80, 60)))).mean()
                      for k, v in images.items()}
            assert min(errors, key=errors.__getitem__) == seq and errors[seq] < 12, (seq, sorted(errors.values())[:2])
    assert video.left_out == 7 and video.undecodable == 0  # seq 4-10


def test_a_picture_is_held_until_the_source_has_been_silent_too_long() -> None:
    from iorthand_cloud.recorder.export_lerobot import HOLD_MAX_S, _HeldVideo

    picture = np.full((48, 64, 3), 200, np.uint8)
    out = io.BytesIO()
    Image.fromarray(picture).save(out, "JPEG", quality=95)
    frames = iter([VideoFrame(width=64, height=48, data=out.getvalue()).stamp(1, t=1_000_000_000)])
    video = _HeldVideo(lambda: next(frames, None), 64, 48, "video/camera")
    held = 1_000_000_000 + int(HOLD_MAX_S * 1e9)
    assert video.at(held).mean() > 190  # the last picture, as long as nothing says the source is gone …
    assert not video.at(held + 1).any()  # … then nothing at all, not even a failure notice: black
    assert Image.open(io.BytesIO(video.jpeg_at(held + 1))).convert("L").getextrema()[1] < 5


def test_jpeg_frames_go_into_the_jpeg_track_as_they_are_only_when_they_fit() -> None:
    from iorthand_cloud.recorder.export_lerobot import _HeldVideo

    def jpeg(size: tuple[int, int], mode: str = "RGB", value: int = 120, subsampling: int = 2) -> bytes:
        out = io.BytesIO()
        Image.new(mode, size, value).save(out, "JPEG", quality=90, **({"subsampling": subsampling} if mode == "RGB" else {}))
        return out.getvalue()

    good = jpeg((64, 48))
    cases = [  # (frame data or a failure notice, what the track gets)
        (good, "as is"),
        (good[: len(good) // 2], "black"),  # truncated: no end marker, does not decode
        (jpeg((128, 96), value=60), "encoded"),  # another size: decoded, scaled, encoded at the dataset's
        (jpeg((64, 48), "L", 200), "encoded"),  # grey: the track's frames are colour
        (jpeg((64, 48), subsampling=0), "encoded"),  # 4:4:4: the track is 4:2:0
        ("camera unplugged", "black"),
    ]
    frames = iter([VideoFrame(width=64, height=48, data=c, failure="").stamp(i, t=i * 10)
                   if isinstance(c, bytes) else VideoFrame(width=64, height=48, failure=c).stamp(i, t=i * 10)
                   for i, (c, _) in enumerate(cases, 1)])
    video = _HeldVideo(lambda: next(frames, None), 64, 48, "video/camera")
    for i, (data, expected) in enumerate(cases, 1):
        out = video.jpeg_at(i * 10)
        picture = np.asarray(Image.open(io.BytesIO(out)).convert("RGB"), dtype=np.float64)
        assert picture.shape == (48, 64, 3), i
        if expected == "as is":
            assert out == data
        elif expected == "black":
            assert picture.max() < 8, i
        else:
            assert out != data and abs(picture.mean() - np.asarray(Image.open(io.BytesIO(data)).convert("RGB")).mean()) < 3
    assert video.undecodable == 1  # the truncated one, said in the export's warnings


def test_an_h264_session_without_pyav_is_said_in_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    from iorthand_cloud.recorder.export_lerobot import _HeldVideo

    monkeypatch.setitem(sys.modules, "av", None)  # import av → ImportError
    frames = iter([VideoFrame(width=2, height=2, encoding="h264", data=b"\0\0\0\1", keyframe=True).stamp(1, t=5)])
    video = _HeldVideo(lambda: next(frames, None), 2, 2, "video/camera")
    with pytest.raises(ExportError, match=r"^the session's video/camera video is H.264: decoding it needs the Python "
                                          r"package 'av' \(PyAV\), which is not installed: pip install 'av>=15,<16'$"):
        video.at(10)


# ------------------------------------------------------------------------------------------------- a recorded session

SECONDS = 4.0
US_FAILURE = (2.6, 3.0)
ANNOTATIONS = [
    (0.5, "scan the left flank", ["episode-start"]),
    (1.7, "", ["episode-end"]),
    (2.0, "stray end", ["episode-end"]),
    (2.3, "second pass", ["episode-start"]),
]


@pytest.fixture(scope="module")
def lerobot_dataset() -> Any:
    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # before huggingface_hub is imported: offline, no hub
    return pytest.importorskip(
        "lerobot.datasets.lerobot_dataset",
        reason="lerobot (0.4.4, with torch, torchvision and torchcodec) is not installed: the LeRobot export needs it")


@pytest.fixture(scope="module")
def video_decoding(lerobot_dataset: Any) -> None:
    """LeRobotDataset decodes its videos with torchcodec, which loads FFmpeg's shared libraries."""
    pytest.importorskip("torchcodec", reason="torchcodec is not installed: LeRobotDataset cannot decode videos")
    try:
        from torchcodec.decoders import VideoDecoder  # noqa: F401  # loads FFmpeg
    except (ImportError, RuntimeError, OSError) as exc:
        pytest.skip(f"torchcodec cannot load FFmpeg's libraries (Debian: libavcodec59 and its siblings): {exc}")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory, lerobot_dataset: Any) -> Iterator[Recorded]:
    yield record_session(tmp_path_factory.mktemp("rec"), "learned", SECONDS, ANNOTATIONS, US_FAILURE,
                         note="phantom, left side")


def _decoded(folder: Path, suffix: str, cls: type) -> list[Any]:
    key = keys.RobotKeys(ROBOT).key(suffix)
    out = [cls.decode(r.data) for r in iter_records(folder) if r.key == key]
    return sorted(out, key=lambda m: m.t)


def _held(msgs: list[Any], t: int) -> Any:
    return [m for m in msgs if m.t <= t][-1]


def _rgb(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), dtype=np.float64)


@pytest.mark.slow
def test_a_recorded_session_as_a_lerobot_dataset(recorded: Recorded, lerobot_dataset: Any, video_decoding: None,
                                                 tmp_path: Path) -> None:
    folder = recorded.folder
    result = export_lerobot(folder, tmp_path / "ds")
    anns = [Annotation.decode(r.data) for r in iter_records(folder) if r.key.endswith("/annotations")]
    starts = [a.t for a in anns if "episode-start" in a.tags]
    ends = [a.t for a in anns if "episode-end" in a.tags]
    assert [e.task for e in result.episodes] == ["scan the left flank", "second pass"]
    assert [e.start for e in result.episodes] == starts and result.episodes[0].end == ends[0]
    assert any("'stray end' ends an episode, but none was open" in w for w in result.warnings)

    ds = lerobot_dataset.LeRobotDataset(f"iorthand/{folder.name}", root=tmp_path / "ds")
    assert ds.fps == 30 and ds.num_episodes == 2 and ds.num_frames == result.frames
    lengths = [len(frame_times(e.start, e.end, 30)) for e in result.episodes]
    assert [ep["length"] for ep in ds.meta.episodes] == lengths
    assert abs(lengths[0] - 1.2 * 30) <= 2  # 0.5 s → 1.7 s
    f = ds.meta.features
    assert f["observation.state"]["shape"] == (15,) and f["observation.state"]["names"] == STATE_NAMES
    assert f["action"]["shape"] == (6,) and f["action"]["names"] == ACTION_NAMES
    assert f["observation.images.camera"]["dtype"] == "video"
    assert f["observation.images.camera"]["shape"] == (480, 640, 3)
    assert f["observation.images.ultrasound"]["shape"] == (360, 480, 3)
    assert list(ds.meta.tasks.index) == ["scan the left flank", "second pass"]

    states = _decoded(folder, keys.STATE_ROBOT, RobotState)
    forces = _decoded(folder, keys.STATE_FORCE, ForceSample)
    applied = _decoded(folder, keys.STATE_APPLIED, AppliedCommand)
    camera = _decoded(folder, keys.VIDEO_CAMERA, VideoFrame)
    ultrasound = _decoded(folder, keys.VIDEO_ULTRASOUND, VideoFrame)
    # Frames: first and last of each episode, one inside, and two in the ultrasound's failure window.
    fail_t = next(u.t for u in ultrasound if u.failure)
    k = -(-(fail_t - result.episodes[1].start) * 30 // S) + 1  # the second frame time after the failure began
    assert 0 < k < lengths[1] - 1
    black = 0
    for index in (0, 17, lengths[0] - 1, lengths[0], lengths[0] + k, lengths[0] + k + 1, ds.num_frames - 1):
        item = ds[index]
        ep = result.episodes[int(item["episode_index"])]
        t = ep.start + int(item["frame_index"]) * S // 30
        assert float(item["timestamp"]) == pytest.approx(int(item["frame_index"]) / 30, abs=1e-4)
        assert item["task"] == ep.task
        s, fs = _held(states, t), _held(forces, t)
        np.testing.assert_allclose(item["observation.state"].numpy(), [*s.tcp_pose, *s.q, *fs.force], rtol=1e-6)
        a = _held(applied, t + S // 30)
        assert t + S // 30 - a.t <= ACTION_MAX_AGE_NS
        np.testing.assert_allclose(item["action"].numpy(), a.applied, rtol=1e-6)
        # The picture is the camera frame held at t: nearer to it than to any other picture of the session.
        img = item["observation.images.camera"].numpy().transpose(1, 2, 0) * 255.0
        assert img.shape == (480, 640, 3)
        held = _held(camera, t).data
        errors = {d: np.abs(img - _rgb(d)).mean() for d in {c.data for c in camera}}
        assert min(errors, key=errors.__getitem__) == held and errors[held] < 15, sorted(errors.values())[:3]
        us = _held(ultrasound, t)
        us_img = item["observation.images.ultrasound"].numpy().transpose(1, 2, 0) * 255.0
        if us.failure:
            assert us.failure == FAILURE and us_img.mean() < 2.0  # black, not the last picture frozen
            black += 1
        else:
            assert np.abs(us_img - _rgb(us.data)).mean() < 15
    assert black == 2
    # mjpeg: the recorded camera JPEGs are the video's frames byte for byte (nothing decoded or re-encoded).
    import av  # LeRobot's own dependency
    assert ds.meta.features["observation.images.camera"]["info"]["video.codec"] == "mjpeg"
    for ep_index, ep in enumerate(result.episodes):
        video = tmp_path / "ds" / ds.meta.get_video_file_path(ep_index, "observation.images.camera")
        with av.open(str(video)) as container:
            packets = [bytes(p) for p in container.demux(video=0) if p.size]
        assert len(packets) == lengths[ep_index]
        for frame_index in (0, 17, lengths[ep_index] - 1):
            assert packets[frame_index] == _held(camera, ep.start + frame_index * S // 30).data


@pytest.mark.slow
def test_half_size_at_ten_frames_a_second_with_lerobots_h264(recorded: Recorded, lerobot_dataset: Any,
                                                             video_decoding: None, tmp_path: Path) -> None:
    result = export_lerobot(recorded.folder, tmp_path / "small", fps=10, image_scale=0.5, task="phantom study",
                            vcodec="h264")
    ds = lerobot_dataset.LeRobotDataset(f"iorthand/{recorded.folder.name}", root=tmp_path / "small")
    assert ds.fps == 10 and ds.meta.features["observation.images.camera"]["shape"] == (240, 320, 3)
    assert [e.task for e in result.episodes] == ["phantom study"] * 2
    assert ds.num_frames == sum(len(frame_times(e.start, e.end, 10)) for e in result.episodes)
    assert tuple(ds[3]["observation.images.camera"].shape) == (3, 240, 320)
    assert ds.meta.features["observation.images.camera"]["info"]["video.codec"] == "h264"


@pytest.mark.slow
def test_mistakes_are_said_in_one_line(recorded: Recorded, tmp_path: Path) -> None:
    with pytest.raises(ExportError, match=r"robot 'nosuch' is not in this session \(it has: sim1\)"):
        export_lerobot(recorded.folder, tmp_path / "x", robot="nosuch")
    assert not (tmp_path / "x").exists()
    (tmp_path / "taken").mkdir()
    for args, said in ((["--robot", "nosuch"], "robot 'nosuch' is not in this session (it has: sim1)"),
                       (["--out", str(tmp_path / "taken")], f"{tmp_path / 'taken'} exists already"),
                       (["--start", "100"], "no robot state of sim1 in the exported range")):
        r = subprocess.run(iorthand_cmd("export", str(recorded.folder), "--format", "lerobot", *args),
                           capture_output=True, text=True, timeout=120)
        assert (r.returncode, "Traceback" in r.stderr) == (1, False), r.stderr
        assert said in r.stderr


# ------------------------------------------------------------------------------------------------- H.264 camera


@pytest.fixture(scope="module")
def h264_recorded(tmp_path_factory: pytest.TempPathFactory, lerobot_dataset: Any) -> Iterator[h264.H264Recorded]:
    yield h264.record_h264_session(tmp_path_factory.mktemp("rec264"), "learned-h264")


@pytest.mark.slow
def test_an_h264_camera_gives_its_pictures_and_black_where_they_cannot_be_decoded(
        h264_recorded: h264.H264Recorded, lerobot_dataset: Any, video_decoding: None, tmp_path: Path) -> None:
    folder = h264_recorded.folder
    result = export_lerobot(folder, tmp_path / "ds")
    (ep,) = result.episodes
    ds = lerobot_dataset.LeRobotDataset(f"iorthand/{folder.name}", root=tmp_path / "ds")
    assert ds.num_frames == result.frames == len(frame_times(ep.start, ep.end, 30))
    w, h = h264.SIZE
    assert ds.meta.features["observation.images.camera"]["shape"] == (h, w, 3)
    assert "observation.images.ultrasound" not in ds.meta.features

    frames = sorted(h264.camera_frames(folder), key=lambda f: f.t)
    good = {f.seq for f in h264.decodable(h264.camera_frames(folder))}
    assert any(f"{len(frames) - sum(1 for f in frames if f.failure) - len(good)} video/camera H.264 frame(s) came "
               "before a keyframe" in w for w in result.warnings), result.warnings
    # Every frame time, by what the stream holds there: a decodable picture, a failure notice, or a frame that
    # cannot be decoded (before the first keyframe, or after the lost one until the next keyframe).
    kinds: dict[str, list[int]] = {"picture": [], "failure": [], "undecodable": []}
    for i, t in enumerate(frame_times(ep.start, ep.end, 30).tolist()):
        held = _held(frames, t)
        kinds["picture" if held.seq in good else "failure" if held.failure else "undecodable"].append(i)
    before = [k for k in kinds["undecodable"] if k < kinds["failure"][0]]
    after = [k for k in kinds["undecodable"] if k > kinds["failure"][-1]]
    assert before[0] == 0 and len(before) > 10 and len(after) > 3  # the start, and after the lost frame
    chosen = {*kinds["picture"][::12], kinds["picture"][-1], kinds["failure"][1], *before[::7], after[-1]}
    for index in sorted(chosen):
        item = ds[index]
        t = ep.start + int(item["frame_index"]) * S // 30
        img = item["observation.images.camera"].numpy().transpose(1, 2, 0) * 255.0
        assert img.shape == (h, w, 3)
        held = _held(frames, t)
        if index in kinds["picture"]:
            # The picture the edge encoded as the frame held at t: nearer to it than to any other it encoded.
            errors = {seq: np.abs(img - bgr[..., ::-1]).mean() for seq, bgr in h264_recorded.images.items()}
            best = min(errors, key=errors.__getitem__)
            assert best == held.seq and errors[best] < 15, (index, held.seq, best, errors[best])
        else:
            assert img.mean() < 2.0, (index, held.seq, held.failure)  # black, not a frozen or broken picture
    # Half size at 10 frames a second: the decoded pictures are scaled as they are converted.
    small = export_lerobot(folder, tmp_path / "small", fps=10, image_scale=0.5)
    ds = lerobot_dataset.LeRobotDataset(f"iorthand/{folder.name}", root=tmp_path / "small")
    assert ds.meta.features["observation.images.camera"]["shape"] == (h // 2, w // 2, 3)
    index = len(frame_times(ep.start, ep.end, 10)) - 3
    held = _held(frames, small.episodes[0].start + index * S // 10)
    assert held.seq in good
    img = ds[index]["observation.images.camera"].numpy().transpose(1, 2, 0) * 255.0
    source = np.asarray(Image.fromarray(h264_recorded.images[held.seq][..., ::-1]).resize((w // 2, h // 2)))
    assert np.abs(img - source).mean() < 15


@pytest.mark.slow
def test_a_video_written_in_slices_is_the_video_written_whole(h264_recorded: h264.H264Recorded, recorded: Recorded,
                                                              lerobot_dataset: Any, video_decoding: None,
                                                              monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The mjpeg writer cuts each episode's frames into slices that worker processes write side by side, each
    reading from before its first frame: slices starting inside an H.264 group of pictures, or on a held JPEG,
    give the frames, warnings and statistics of one slice."""
    import av

    from iorthand_cloud.recorder import export_lerobot as lr

    def packets(root: Path, feature: str) -> list[bytes]:
        out = []
        for video in sorted((root / "videos" / feature).rglob("*.mp4")):
            with av.open(str(video)) as container:
                out += [bytes(p) for p in container.demux(video=0) if p.size]
        return out

    for name, folder in (("h264", h264_recorded.folder), ("jpeg", recorded.folder)):
        whole = export_lerobot(folder, tmp_path / f"{name}-whole")
        monkeypatch.setattr(lr, "SLICE_S", 0.35)  # 10 frames a slice: several per episode
        sliced = export_lerobot(folder, tmp_path / f"{name}-sliced")
        monkeypatch.undo()
        assert sliced.frames == whole.frames and sliced.warnings == whole.warnings, name
        for feature in (f for f, ft in whole.features.items() if ft["dtype"] == "video"):
            a, b = packets(whole.path, feature), packets(sliced.path, feature)
            assert len(a) == whole.frames and a == b, (name, feature)
        stats = [json.loads((r.path / "meta" / "stats.json").read_text()) for r in (whole, sliced)]
        assert stats[0]["observation.images.camera"] == stats[1]["observation.images.camera"], name
        # The joined slices keep their frame times: LeRobot decodes the same picture at every index.
        datasets = [lerobot_dataset.LeRobotDataset(f"iorthand/{folder.name}", root=r.path) for r in (whole, sliced)]
        for index in (0, 9, 10, 11, 25, whole.frames - 1):
            a, b = (ds[index]["observation.images.camera"].numpy() for ds in datasets)
            assert np.array_equal(a, b), (name, index)
