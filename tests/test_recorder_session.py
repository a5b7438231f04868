"""A scripted full-rate session recorded end to end: the report finds the script's events, replay republishes
with the original timing on the original keys, export writes a .rrd; and a recorder killed with SIGKILL loses
at most the last second, repaired at the next start."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh

from iorthand import keys
from iorthand.transport import client_config, free_port, open_session, router_json5
from iorthand_cloud.recorder import client
from iorthand_cloud.recorder import manifest as mf
from iorthand_cloud.recorder.config import ReportConfig
from iorthand_cloud.recorder.reader import iter_records
from iorthand_cloud.recorder.repair import has_footer
from iorthand_cloud.recorder.replay import Replayer
from iorthand_cloud.recorder.report import build_report
from iorthand_cloud.recorder.service import RecorderService
from iorthand_cloud.recorder.simulate import RATES, SyntheticSession, expected_events
from tests.conftest import wait_until
from tests.test_recorder import recorder_config

SIM_SECONDS = 10.0  # one period of the force script


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path]]:
    """A router, a recorder and a 10 s synthetic session (no video); yields (endpoint, session folder)."""
    out = tmp_path_factory.mktemp("rec")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(zenoh.Config.from_json5(router_json5(endpoint)))
    svc = RecorderService(recorder_config(endpoint, out))
    svc.start()
    s = open_session(client_config(endpoint))
    try:
        sim = SyntheticSession(s, "sim1", SIM_SECONDS, rates={keys.VIDEO_CAMERA: 0.0})
        time.sleep(0.3)
        assert client.start(s, session_id="scripted", operator="sim-operator").ok
        sim.run()
        time.sleep(0.2)
        client.annotate(s, "end of script", author="tester", tags=["done"])
        assert client.stop(s).ok
        yield endpoint, out / "scripted"
    finally:
        s.close()
        svc.shutdown()
        router.close()


def test_no_gaps_and_report_matches_the_script(recorded) -> None:
    _, folder = recorded
    m = mf.Manifest.read(folder)
    totals = mf.totals(m.keys)
    assert m.status == mf.COMPLETE and totals["missing"] == 0 and totals["malformed"] == 0 and m.dropped == 0
    data = build_report(folder, ReportConfig(contact_threshold=1.0))
    r = data["robots"]["sim1"]
    ev = expected_events(SIM_SECONDS)
    assert r["index"]["omega_R"] == ev["omega_R"] and r["index"]["omega_Y"] == ev["omega_Y"]
    assert r["index"]["tau"] == pytest.approx(ev["contact_time"], rel=0.02)
    assert r["deadman_stops"] == ev["deadman_stops"]
    assert r["refusals"].get("deadman_released", 0) > 0
    assert r["command_latency_ms"]["count"] > 0
    # The age of the operator's picture, on the edge's clock alone: every command that names a state (the script's
    # first may come before its first state) joined with its echo, and at the median no older than the script's
    # state period (125 Hz) plus the time to send the command.
    view = r["view_age_ms"]
    assert r["command_latency_ms"]["count"] - 1 <= view["count"] <= r["command_latency_ms"]["count"], view
    assert 0.0 <= view["p50"] < 1000.0 / RATES[keys.STATE_ROBOT] + 5.0, view
    assert "age of the operator's picture" in (folder / "report" / "report.md").read_text()
    out = folder / "report"
    assert {"report.md", "report.json", "force_sim1.png", "trajectory_sim1.png"} <= {p.name for p in out.iterdir()}
    assert json.loads((out / "report.json").read_text())["annotations"][0]["text"] == "end of script"
    assert "performance index" in (out / "report.md").read_text()


def test_replay_republishes_with_original_timing(recorded) -> None:
    endpoint, folder = recorded
    s = open_session(client_config(endpoint))
    got: list[tuple[str, bytes, float]] = []
    try:
        s.declare_subscriber("iorthand/sim1-replay/**", lambda smp: got.append(
            (str(smp.key_expr), smp.payload.to_bytes(), time.monotonic())))
        time.sleep(0.3)
        speed = 4.0
        rp = Replayer(s, folder, speed=speed, key_filter=["iorthand/*/state/**"])
        stats = rp.run()
        wait_until(lambda: len(got) >= stats.published, timeout=5.0, message="every replayed message")
    finally:
        s.close()
    original = [r for r in iter_records(folder) if r.key.startswith("iorthand/sim1/state/")]
    # Same bytes, same order, on the same keys of the robot's replay id.
    assert [(k, d) for k, d, _ in got] == [(r.key.replace("/sim1/", "/sim1-replay/"), r.data) for r in original]
    span_orig = (original[-1].log_time - original[0].log_time) / 1e9
    span_replay = got[-1][2] - got[0][2]
    assert span_replay == pytest.approx(span_orig / speed, rel=0.15)
    # Timing inside the session too: the message at the middle arrives at the middle.
    mid = len(original) // 2
    assert (got[mid][2] - got[0][2]) == pytest.approx((original[mid].log_time - original[0].log_time) / 1e9 / speed,
                                                      abs=0.15)


def test_replay_never_sends_operator_commands(recorded) -> None:
    """The recording holds the operator's twists; republished into a live deployment they could drive a robot
    whose owner is the same operator again. Replay withholds them, and refuses a filter that asks only for them."""
    endpoint, folder = recorded
    recorded_commands = sum(1 for r in iter_records(folder) if keys.is_command_key(r.key))
    assert recorded_commands > 100
    s = open_session(client_config(endpoint))
    commands: list[str] = []
    states: list[str] = []
    try:
        s.declare_subscriber(keys.ALL_COMMANDS, lambda smp: commands.append(str(smp.key_expr)))
        s.declare_subscriber(keys.all_robots(keys.STATE_ROBOT), lambda smp: states.append(str(smp.key_expr)))
        time.sleep(0.3)
        stats = Replayer(s, folder, speed=20.0).run()  # no filter: everything that may be replayed
        wait_until(lambda: len(states) >= stats.per_key["iorthand/sim1-replay/state/robot"], timeout=5.0, message="states")
        time.sleep(0.2)
        assert commands == [] and stats.commands_withheld == recorded_commands
        assert not any(keys.is_command_key(k) for k in stats.per_key)
        with pytest.raises(ValueError, match="never publishes operator commands"):
            Replayer(s, folder, key_filter=["iorthand/sim1/cmd/**"])
    finally:
        s.close()


def test_a_replay_never_publishes_as_a_robot(recorded) -> None:
    """Robot sim1 goes out as sim1-replay, an id no edge may take: with sim1's edge online or not, no console
    and no twin can take the recording for the robot. ``--as`` picks another replay id, never a robot's."""
    endpoint, folder = recorded
    edge, s = open_session(client_config(endpoint)), open_session(client_config(endpoint))
    live: list[str] = []
    replayed: dict[str, list[tuple[str, bytes]]] = {"sim1-replay": [], "lyon-replay": []}
    try:
        token = edge.liveliness().declare_token(keys.RobotKeys("sim1").key(keys.ALIVE_EDGE))
        s.declare_subscriber("iorthand/sim1/**", lambda smp: live.append(str(smp.key_expr)))
        for robot, got in replayed.items():
            s.declare_subscriber(f"iorthand/{robot}/**",
                                 lambda smp, got=got: got.append((str(smp.key_expr), smp.payload.to_bytes())))
        time.sleep(0.3)
        default = Replayer(s, folder, speed=20.0, key_filter=["iorthand/sim1/state/**"]).run()
        wait_until(lambda: len(replayed["sim1-replay"]) >= default.published, timeout=5.0, message="the replay")
        renamed = Replayer(s, folder, speed=20.0, key_filter=["iorthand/sim1/state/**"],
                           rename={"sim1": "lyon-replay"}).run()
        wait_until(lambda: len(replayed["lyon-replay"]) >= renamed.published, timeout=5.0, message="the renamed replay")
        time.sleep(0.2)
        token.undeclare()
    finally:
        s.close()
        edge.close()
    original = [r for r in iter_records(folder) if r.key.startswith("iorthand/sim1/state/")]
    assert live == []
    for robot, got in replayed.items():
        assert got == [(r.key.replace("iorthand/sim1/", f"iorthand/{robot}/"), r.data) for r in original]
    with pytest.raises(ValueError, match=r"rename sim1=sim2: 'sim2' does not end in '-replay'.*'sim2-replay'"):
        Replayer(s, folder, rename={"sim1": "sim2"})
    with pytest.raises(ValueError, match="rename sim1=Bad!: robot id 'Bad!' is invalid"):
        Replayer(s, folder, rename={"sim1": "Bad!"})


def test_export_rrd(recorded) -> None:
    from iorthand_cloud.recorder.export import export_rrd

    _, folder = recorded
    path, n = export_rrd(folder, folder / "part.rrd", start=1.0, end=3.0)
    assert n > 100 and path.stat().st_size > 1000
    # As the other exports, never over a file that exists (it replaced one silently).
    size = path.stat().st_size
    with pytest.raises(FileExistsError, match=r"part\.rrd exists already"):
        export_rrd(folder, path)
    assert path.stat().st_size == size


def test_kill9_loses_at_most_a_second_and_is_repaired(router_endpoint, session_factory, tmp_path: Path) -> None:
    cfg = tmp_path / "recorder.yaml"
    out = tmp_path / "rec"
    cfg.write_text(yaml.safe_dump({"zenoh": {"mode": "client", "connect": [router_endpoint]},
                                   "output_dir": str(out), "flush_interval": 0.5}))
    proc = subprocess.Popen(
        [sys.executable, "-m", "iorthand.cli", "recorder", "--config", str(cfg), "--start-now", "--session", "k"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
    )
    try:
        s = session_factory()
        wait_until(lambda: (out / "k" / mf.MANIFEST).exists(), timeout=20, message="recorder started")
        sim = SyntheticSession(s, "sim1", 30.0, rates={keys.VIDEO_CAMERA: 0.0, keys.MARKERS: 0.0})
        sim.start()
        time.sleep(3.0)
        kill_ns = time.time_ns()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(5)
        sim.stop()
        sim.join(2)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    seg = out / "k" / "telemetry-0001.mcap"
    assert not has_footer(seg)
    svc = RecorderService(recorder_config(router_endpoint, out))
    svc.start()  # repairs what the killed one left
    svc.shutdown()
    assert has_footer(seg)
    m = mf.Manifest.read(out / "k")
    assert m.status == mf.RECOVERED and m.repaired and m.segments[0].status == "repaired"
    last = max(r.log_time for r in iter_records(out / "k"))
    assert kill_ns - last <= 1_000_000_000, f"lost {(kill_ns - last) / 1e9:.3f} s"
    assert mf.totals(m.keys)["missing"] == 0


def test_cli_report_and_annotate(recorded, tmp_path: Path) -> None:
    endpoint, folder = recorded
    out = subprocess.run(
        [sys.executable, "-m", "iorthand.cli", "report", str(folder), "--out", str(tmp_path / "r")],
        capture_output=True, text=True, timeout=60,
    )
    assert out.returncode == 0, out.stderr
    assert "φ" in out.stdout and (tmp_path / "r" / "report.md").exists()
    # No recording in progress: annotate says so and fails, rather than dropping the note silently.
    ann = subprocess.run([sys.executable, "-m", "iorthand.cli", "annotate", "late note", "--connect", endpoint],
                         capture_output=True, text=True, timeout=60)
    assert ann.returncode == 1 and "no recording in progress" in ann.stdout


def test_replay_drives_the_twin(recorded, tmp_path: Path) -> None:
    """A replayed session looks live to the twin, as its replay id: the snapshot ends on the last recorded state."""
    import numpy as np

    from iorthand.protocol import ForceLevelState, RobotState
    from iorthand_cloud.twin.service import TwinService
    from tests.conftest import twin_config
    from tests.test_twin_service import snapshot

    endpoint, folder = recorded
    twin = TwinService(twin_config(endpoint, tmp_path))
    twin.start()
    s = open_session(client_config(endpoint))
    try:
        time.sleep(0.3)
        Replayer(s, folder, speed=4.0, key_filter=["iorthand/*/state/**"]).run()
        records = list(iter_records(folder))
        last_state = RobotState.decode([r for r in records if r.key == "iorthand/sim1/state/robot"][-1].data)
        last_level = ForceLevelState.decode([r for r in records if r.key == "iorthand/sim1/state/force_level"][-1].data)
        wait_until(lambda: snapshot(s, "sim1-replay").robot_seq == last_state.seq, timeout=5.0, message="the twin caught up")
        snap = snapshot(s, "sim1-replay")
        assert snap.known
        assert np.allclose(snap.tcp_pose, last_state.tcp_pose)
        assert snap.force_level == last_level.level and snap.force_stale == last_level.stale
    finally:
        s.close()
        twin.shutdown()


def test_export_shows_why_a_video_stopped_instead_of_its_last_picture(monkeypatch, tmp_path: Path) -> None:
    """Recorded failure notices of a video stream become one WARN line and a cleared picture in the .rrd, and
    the return of pictures an INFO line; an image is never logged from a notice (it has no data)."""
    from types import SimpleNamespace

    import rerun as rr

    from iorthand.protocol import VideoFrame
    from iorthand_cloud.recorder import export
    from iorthand_cloud.recorder.reader import Record

    key = keys.RobotKeys("sim1").key(keys.VIDEO_CAMERA)
    jpeg = b"\xff\xd8\xff\xd9"
    frames = [(jpeg, ""), (b"", "no frame from video device '0' for 2 s"), (b"", "no frame from video device '0' for 2 s"),
              (jpeg, "")]
    records = [Record(key, (i + 1) * 10**9, (i + 1) * 10**9, i + 1,
                      VideoFrame(width=2, height=2, data=data, failure=failure).stamp(i + 1, (i + 1) * 10**9).encode(),
                      False, "video") for i, (data, failure) in enumerate(frames)]
    logged: list[tuple[str, Any]] = []

    class Spy:
        def __init__(self, *_: Any, **__: Any) -> None: ...
        def save(self, _: str) -> None: ...
        def set_time(self, *_: Any, **__: Any) -> None: ...
        def flush(self) -> None: ...
        def disconnect(self) -> None: ...
        def log(self, path: str, item: Any) -> None:
            logged.append((path, item))

    monkeypatch.setattr(export, "iter_records", lambda *_: iter(records))
    monkeypatch.setattr(export, "export_target",
                        lambda session, out, *_, **__: (tmp_path, SimpleNamespace(session_id="s"), tmp_path / "s.rrd"))
    monkeypatch.setattr(export.rr, "RecordingStream", Spy)
    export.export_rrd(tmp_path, tmp_path / "s.rrd", video_fps=0.0)
    kinds = [type(item).__name__ for _, item in logged]
    assert kinds == ["EncodedImage", "TextLog", "Clear", "Clear", "TextLog", "EncodedImage"], kinds
    texts = [(str(item.level.as_arrow_array()[0]), str(item.text.as_arrow_array()[0])) for _, item in logged
             if isinstance(item, rr.TextLog)]
    assert texts == [("WARN", "camera video has no frames: no frame from video device '0' for 2 s (the edge retries)"),
                     ("INFO", "camera video back: frames flow again")]


def test_report_repairs_a_session_whose_recorder_was_killed_without_restarting_it(
        router_endpoint, session_factory, tmp_path: Path) -> None:
    """``iorthand report`` on the folder of a recorder killed with SIGKILL: no recorder restart, the report
    repairs the session itself (the writer's lock died with it) and loses at most the last second."""
    cfg = tmp_path / "recorder.yaml"
    out = tmp_path / "rec"
    cfg.write_text(yaml.safe_dump({"zenoh": {"mode": "client", "connect": [router_endpoint]},
                                   "output_dir": str(out), "flush_interval": 0.5}))
    proc = subprocess.Popen(
        [sys.executable, "-m", "iorthand.cli", "recorder", "--config", str(cfg), "--start-now", "--session", "k"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
    )
    try:
        s = session_factory()
        wait_until(lambda: (out / "k" / mf.MANIFEST).exists(), timeout=20, message="recorder started")
        assert mf.writer_alive(out / "k")  # recording: a reader leaves it alone
        sim = SyntheticSession(s, "sim1", 30.0, rates={keys.VIDEO_CAMERA: 0.0, keys.MARKERS: 0.0})
        sim.start()
        time.sleep(3.0)
        kill_ns = time.time_ns()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(5)
        sim.stop()
        sim.join(2)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    folder = out / "k"
    assert not has_footer(folder / "telemetry-0001.mcap") and not mf.writer_alive(folder)
    done = subprocess.run([sys.executable, "-m", "iorthand.cli", "report", str(folder)], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    report = json.loads((folder / "report" / "report.json").read_text())
    assert report["recording"]["repair"].startswith("the recorder stopped without closing this session: repaired")
    assert report["status"] == mf.RECOVERED and report["duration_s"] >= 2.0
    assert has_footer(folder / "telemetry-0001.mcap")
    last = max(r.log_time for r in iter_records(folder))
    assert kill_ns - last <= 1_000_000_000, f"lost {(kill_ns - last) / 1e9:.3f} s"


def test_a_report_of_a_session_still_recording_reads_it_and_touches_nothing(router_endpoint, session_factory,
                                                                           tmp_path: Path) -> None:
    svc = RecorderService(recorder_config(router_endpoint, tmp_path / "rec"))
    svc.start()
    s = session_factory()
    sim = SyntheticSession(s, "sim1", 30.0, rates={keys.VIDEO_CAMERA: 0.0, keys.MARKERS: 0.0})
    time.sleep(0.3)
    assert client.start(s, session_id="live").ok
    sim.start()
    try:
        time.sleep(2.0)
        folder = svc.config.output_dir / "live"
        before = {p.name: p.stat().st_size for p in folder.glob("*.mcap")}
        data = build_report(folder, ReportConfig(plots=False), tmp_path / "report")
        assert data["recording"]["repair"] == "still being recorded: read as far as it is written"
        assert data["robots"]["sim1"]["index"]["t_t"] > 0.5  # it read what is written so far
        assert mf.Manifest.read(folder).status == mf.RECORDING
        assert all(folder.joinpath(n).stat().st_size >= size for n, size in before.items())  # nothing rewritten
    finally:
        sim.stop()
        sim.join(2)
        assert client.stop(s).ok
        svc.shutdown()


@pytest.mark.slow
def test_export_rrd_logs_an_h264_camera_as_a_video_stream_from_its_first_keyframe(tmp_path: Path) -> None:
    """A session whose camera streams H.264 (tests/h264_session.py): the .rrd holds a VideoStream (H.264 codec,
    static) whose samples are the recorded access units a decoder can take, in order, never thinned by
    ``video_fps``; failure notices and the lost frame clear the picture. Read back with rerun's chunk reader."""
    import rerun as rr
    from rerun.chunk import RrdReader

    from iorthand_cloud.recorder.export import export_rrd
    from tests import h264_session as h264

    rec = h264.record_h264_session(tmp_path / "rec", "rrd-h264")
    entity = "/sim1/video/camera"

    def read(path: Path) -> tuple[list[tuple[int, bytes]], list[int], list[str]]:
        """The entity's samples (time, data; in time order), the times it is cleared at, the robot's events."""
        codecs: list[Any] = []
        samples: list[tuple[int, bytes, bool]] = []
        clears: list[int] = []
        events: list[str] = []
        for chunk in RrdReader(str(path)).stream():
            batch = chunk.to_record_batch().to_pydict()
            if chunk.entity_path == entity and chunk.is_static:
                codecs += batch["VideoStream:codec"]
            elif chunk.entity_path == entity and "VideoStream:sample" in batch:
                samples += [(t.value, bytes(s[0]), k[0]) for t, s, k in zip(
                    batch["time"], batch["VideoStream:sample"], batch["VideoStream:is_keyframe"], strict=True)]
            elif chunk.entity_path == entity:
                assert set(batch) == {"rerun.controls.RowId", "log_time", "time", "Clear:is_recursive"}
                clears += [t.value for t in batch["time"]]
            elif chunk.entity_path == "/sim1/events":
                events += [str(x[0]) for x in batch["TextLog:text"]]
        assert codecs == [[rr.VideoCodec.H264.value]]  # once, static
        samples.sort()
        assert [k for _, _, k in samples] == [data in keyframe_data for _, data, _ in samples]
        return [(t, data) for t, data, _ in samples], sorted(clears), events

    frames = h264.camera_frames(rec.folder)
    expected = h264.decodable(frames)
    keyframe_data = {f.data for f in frames if f.keyframe}
    assert not frames[0].keyframe and len(expected) > 40
    path, _ = export_rrd(rec.folder, tmp_path / "all.rrd", video_fps=1.0)  # thins JPEG only
    samples, clears, events = read(path)
    assert samples == [(f.t, f.data) for f in expected]
    failures = [f.t for f in frames if f.failure]
    lost_next = next(f.t for f in frames if f.seq == rec.lost_seq + 1)
    assert clears == [*failures, lost_next]
    assert events == [f"camera video has no frames: {h264.FAILURE_TEXT} (the edge retries)",
                      "camera video back: frames flow again",
                      f"camera video: 1 frame(s) missing before frame {rec.lost_seq + 1}: no picture until the next "
                      "keyframe"]
    # A range cut inside a group of pictures starts at the next keyframe.
    t0 = next(iter_records(rec.folder)).log_time
    in_range = h264.camera_frames(rec.folder, t0 + 1_000_000_000, t0 + 3_500_000_000)
    part = h264.decodable(in_range)
    assert not in_range[0].keyframe and part[0].keyframe and part[0].seq > in_range[0].seq
    path, _ = export_rrd(rec.folder, tmp_path / "part.rrd", start=1.0, end=3.5)
    samples, _, _ = read(path)
    assert samples == [(f.t, f.data) for f in part]


def test_export_rrd_holds_every_recorded_row_in_columns(recorded, monkeypatch, tmp_path: Path) -> None:
    """The .rrd against the recording's own messages, read back with rerun's chunk reader: per entity, one row
    per message logged (at its source time), with its values; the columnar batches (made small here, so that
    every entity is sent in several) change nothing."""
    import numpy as np
    from rerun.chunk import RrdReader

    from iorthand.protocol import Annotation, ForceLevelState, ForceSample, Markers, RobotState, SafetyStatus
    from iorthand_cloud.recorder import export

    _, folder = recorded
    monkeypatch.setattr(export, "BATCH_ROWS", 100)
    monkeypatch.setattr(export, "PATH_BATCH", 3)
    path, logged = export.export_rrd(folder, tmp_path / "all.rrd")
    rows: dict[str, list[tuple[int, dict[str, Any]]]] = {}
    for chunk in RrdReader(str(path)).stream():
        if chunk.is_static:
            continue
        batch = chunk.to_record_batch().to_pydict()
        names = [c for c in batch if c not in ("rerun.controls.RowId", "log_time", "time")]
        assert len(batch["log_time"]) == len(batch["time"])  # as log stamps it
        for i, t in enumerate(batch["time"]):
            rows.setdefault(chunk.entity_path, []).append((t.value, {c: batch[c][i] for c in names}))
    for r in rows.values():
        r.sort(key=lambda row: row[0])

    def decoded(cls: Any, suffix: str, changes_only: bool = False) -> list[Any]:
        """The key's messages, in source-time order (safety: the status changes, as received)."""
        key = f"iorthand/sim1/{suffix}"
        out = [cls.decode(r.data) for r in iter_records(folder) if r.key == key]
        if changes_only:
            out = [m for i, m in enumerate(out) if i == 0 or out[i - 1].status != m.status]
        return sorted(out, key=lambda m: m.t)

    states = decoded(RobotState, keys.STATE_ROBOT)
    forces = decoded(ForceSample, keys.STATE_FORCE)
    levels = decoded(ForceLevelState, keys.STATE_FORCE_LEVEL)
    all_markers = decoded(Markers, keys.MARKERS)
    markers = [m for m in all_markers if m.markers]
    safety = decoded(SafetyStatus, keys.STATE_SAFETY)
    changes = decoded(SafetyStatus, keys.STATE_SAFETY, changes_only=True)
    annotations = [Annotation.decode(r.data) for r in iter_records(folder) if r.key.endswith("/annotations")]
    assert len(states) > 1000 and len(forces) > 800 and levels and markers and len(changes) > 1 and annotations

    def series(entity: str, component: str) -> list[tuple[int, Any]]:
        return [(t, row[component]) for t, row in rows[entity]]

    for i, axis in enumerate("xyz"):
        assert series(f"/sim1/tcp/{axis}", "Scalars:scalars") == [(m.t, [m.tcp_pose[i]]) for m in states]
        assert series(f"/sim1/force/f{axis}", "Scalars:scalars") == [(m.t, [m.force[i]]) for m in forces]
    assert series("/sim1/force/norm", "Scalars:scalars") == [(m.t, [float(np.linalg.norm(m.force))]) for m in forces]
    assert series("/sim1/force/level", "Scalars:scalars") == [(m.t, [-1.0 if m.stale else float(m.level)])
                                                              for m in levels]
    tcp = rows["/sim1/world/tcp"]
    assert [t for t, _ in tcp] == [m.t for m in states]
    for (_, row), m in zip(tcp, states, strict=True):
        p = np.asarray(m.tcp_pose)
        angle = float(np.linalg.norm(p[3:6]))
        (axis, radians), = [(a["axis"], a["angle"]) for a in row["Transform3D:rotation_axis_angle"]]
        assert np.array_equal(np.float32(row["Transform3D:translation"]), np.float32([p[:3]]))
        assert np.array_equal(np.float32(axis), np.float32(p[3:6] if angle > 0 else [0, 0, 1]))
        assert np.float32(radians) == np.float32(angle)
    trail = [(m.t, m.tcp_pose[:3]) for m in states]
    strips = rows["/sim1/world/path"]
    assert [t for t, _ in strips] == [trail[k - 1][0] for k in range(25, len(trail) + 1, 25)]
    for (_, row), k in zip(strips, range(25, len(trail) + 1, 25), strict=True):
        (strip,) = row["LineStrips3D:strips"]
        assert np.array_equal(np.float32(strip), np.float32([xyz for _, xyz in trail[max(0, k - 2000):k]]))
    points = rows["/sim1/world/markers"]
    assert [t for t, _ in points] == [m.t for m in markers]
    for (_, row), m in zip(points, markers, strict=True):
        assert row["Points3D:labels"] == [str(x.id) for x in m.markers]
        assert np.array_equal(np.float32(row["Points3D:positions"]),
                              np.float32([[x.pose[3], x.pose[7], x.pose[11]] for x in m.markers]))
        assert np.float32(row["Points3D:radii"]).tolist() == [np.float32(0.005)]
    assert [(t, row["TextLog:text"]) for t, row in rows["/sim1/safety"]] == [
        (m.t, [f"{m.status}: {m.reason}"]) for m in changes]
    assert len(rows["/annotations"]) == len(annotations)
    assert set(rows) == {"/sim1/tcp/x", "/sim1/tcp/y", "/sim1/tcp/z", "/sim1/force/fx", "/sim1/force/fy",
                         "/sim1/force/fz", "/sim1/force/norm", "/sim1/force/level", "/sim1/world/tcp",
                         "/sim1/world/path", "/sim1/world/markers", "/sim1/safety", "/annotations"}
    # "logged" counts every message of these types (as before the columns), shown or not
    assert logged == len(states) + len(forces) + len(levels) + len(all_markers) + len(safety) + len(annotations)
