"""Recorder service: start/stop through queries on a real router, storage format, gaps, malformed input,
annotations, error reporting, crash repair."""

from __future__ import annotations

import dataclasses
import io
import struct
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import pytest
import zenoh
from mcap.reader import make_reader
from mcap.records import ChunkIndex
from mcap.writer import CompressionType, IndexType, Writer

from iorthand import keys
from iorthand.config import from_dict
from iorthand.protocol import Annotation, ForceSample, RecorderStatus, TwistCommand, VideoFrame
from iorthand.transport import query
from iorthand_cloud.recorder import client
from iorthand_cloud.recorder import manifest as mf
from iorthand_cloud.recorder.config import RecorderConfig, ReportConfig
from iorthand_cloud.recorder.reader import (
    MAX_CHUNK_BYTES,
    SegmentError,
    check_chunks,
    iter_records,
    segment_files,
)
from iorthand_cloud.recorder.report import build_report, md_text, missing_where
from iorthand_cloud.recorder.segments import VIDEO
from iorthand_cloud.recorder.service import RecorderService
from tests.conftest import wait_until


def recorder_config(endpoint: str, out: Path, **extra: object) -> RecorderConfig:
    data = {"zenoh": {"mode": "client", "connect": [endpoint]}, "output_dir": str(out), "fsync": False, **extra}
    return from_dict(data, RecorderConfig, source="<test>")


@pytest.fixture
def recorder_factory(router_endpoint: str, tmp_path: Path):
    services: list[RecorderService] = []

    def make(**extra: object) -> RecorderService:
        svc = RecorderService(recorder_config(router_endpoint, tmp_path / "rec", **extra))
        svc.start()
        services.append(svc)
        return svc

    yield make
    for svc in services:
        svc.shutdown()


def _force(seq: int, fz: float = 1.0) -> bytes:
    return ForceSample(force=[0.0, 0.0, fz]).stamp(seq).encode()


def test_records_messages_with_times_sequence_and_gaps(recorder_factory, session_factory, tmp_path: Path) -> None:
    svc = recorder_factory()
    s = session_factory()
    pub = s.declare_publisher("iorthand/sim1/state/force")
    vid = s.declare_publisher("iorthand/sim1/video/camera")
    time.sleep(0.3)  # the subscription propagates to the router
    reply = client.start(s, session_id="t1", operator="alice", robots=["sim1"])
    assert reply.ok and reply.recording, reply.reason
    seqs = [1, 2, 3, 6, 7]  # 4 and 5 missing: one gap of two
    for seq in seqs:
        pub.put(_force(seq))
    pub.put(b"\xc1 garbage")  # not msgpack: stored raw, counted malformed
    frame = VideoFrame(width=4, height=2, data=b"\xff\xd8jpeg\xff\xd9").stamp(1)
    vid.put(frame.encode())
    wait_until(lambda: svc.status.messages >= 7, message="7 messages recorded")
    ann = client.annotate(s, "probe slipped", author="alice", tags=["slip"], score=3.0)  # on annotate/alice
    assert ann.ok, ann.reason
    # An author other than the one its key names (which the router binds to a certificate) is refused, not stored.
    forged = Annotation(author="bob", text="bob's words").stamp(1).encode()
    replies = query(s, keys.service_key(keys.RECORDER, keys.RECORDER_ANNOTATE, "alice"), forged, timeout=5.0)
    refused = RecorderStatus.decode(replies[0])
    assert not refused.ok and "'bob'" in refused.reason and "'alice''s key" in refused.reason, refused.reason
    stopped = client.stop(s)
    assert stopped.ok and not stopped.recording and stopped.closed_t >= stopped.first_message_t > 0
    folder = tmp_path / "rec" / "t1"
    m = mf.Manifest.read(folder)
    assert m.status == mf.COMPLETE and m.operator == "alice" and m.robots == ["sim1"]
    force = m.keys["iorthand/sim1/state/force"]
    assert (force.messages, force.malformed, force.gaps, force.missing) == (6, 1, 1, 2)
    assert force.type == "ForceSample"
    assert m.keys["iorthand/sim1/video/camera"].messages == 1
    assert m.annotations == 1 and m.config["output_dir"].endswith("rec")
    names = sorted(p.name for p in segment_files(folder))
    assert names == ["telemetry-0001.mcap", "video-0001.mcap"]
    # Telemetry is zstd-compressed, video is not; both have footers and schemas.
    with (folder / "telemetry-0001.mcap").open("rb") as f:
        summary = make_reader(f).get_summary()
        assert summary is not None
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        assert "ForceSample" in {sc.name for sc in summary.schemas.values()}
    with (folder / "video-0001.mcap").open("rb") as f:
        summary = make_reader(f).get_summary()
        assert {c.compression for c in summary.chunk_indexes} == {""}
    records = list(iter_records(folder))
    good = [r for r in records if r.key.endswith("state/force") and not r.malformed]
    assert [r.sequence for r in good] == seqs
    assert all(r.publish_time == ForceSample.decode(r.data).t and r.log_time >= r.publish_time for r in good)
    bad = [r for r in records if r.malformed]
    assert len(bad) == 1 and bad[0].data == b"\xc1 garbage"
    # A reader may take only some streams or keys: the others' segments and messages are not read.
    assert {r.key for r in iter_records(folder, streams=[VIDEO])} == {"iorthand/sim1/video/camera"}
    only_force = list(iter_records(folder, topics=["iorthand/sim1/state/force"]))
    assert [r.sequence for r in only_force if not r.malformed] == seqs and len(only_force) == 6
    anns = [r for r in records if r.key == keys.service_key(keys.RECORDER, keys.RECORDER_ANNOTATIONS)]
    decoded = Annotation.decode(anns[0].data)
    assert decoded.text == "probe slipped" and decoded.tags == ["slip"] and decoded.score == 3.0
    # The report says where the messages went missing, not only how many.
    data = build_report(folder, ReportConfig(plots=False), tmp_path / "report")
    assert data["recording"]["missing_by_key"] == {"iorthand/sim1/state/force": 2}
    assert "2 missing by sequence (1 gaps; on state/force 2)" in (tmp_path / "report" / "report.md").read_text()


def test_commands_on_an_operators_own_key_are_recorded_typed_and_counted_by_the_report(
        recorder_factory, session_factory, tmp_path: Path) -> None:
    """With bind_operator_keys (DEPLOY.md's default) an operator commands on ``cmd/twist/<operator>``: the recorder
    stored those commands untyped (raw bytes, no schema) and the report counted none, so a secured deployment's
    report had no teleoperation time from the commands (it fell back to the session's span)."""
    svc = recorder_factory()
    s = session_factory()
    pub = s.declare_publisher(keys.RobotKeys("sim1").key(f"{keys.CMD_TWIST}/alice"))
    time.sleep(0.3)
    assert client.start(s, session_id="bound").ok
    for seq in range(1, 41):  # 0.4 s of held deadman at 100 Hz, then 10 released
        cmd = TwistCommand(operator="alice", linear=[0.01, 0.0, 0.0], deadman=seq <= 30).stamp(seq)
        pub.put(cmd.encode())
        time.sleep(0.01)
    wait_until(lambda: svc.status.messages >= 40, message="40 commands recorded")
    assert client.stop(s).ok
    folder = tmp_path / "rec" / "bound"
    with (folder / "telemetry-0001.mcap").open("rb") as f:
        summary = make_reader(f).get_summary()
        assert summary is not None
        assert {sc.name for sc in summary.schemas.values()} >= {"TwistCommand"}
    data = build_report(folder, ReportConfig(plots=False), tmp_path / "report")
    figures = data["robots"]["sim1"]
    assert figures["commands"] == 40 and figures["malformed"] == 0, figures
    assert 0.2 < figures["index"]["t_t"] < 0.45, figures["index"]  # the 30 held commands, not the session


def test_where_messages_went_missing_most_first() -> None:
    lost = {"iorthand/a/state/force": 2, "iorthand/a/video/camera": 5, "iorthand/a/markers": 1, "iorthand/a/state/robot": 3}
    assert missing_where(lost) == "video/camera 5, state/robot 3, state/force 2 and 1 more keys"
    assert missing_where({"iorthand/a/markers": 1}) == "markers 1"


def test_status_and_refusals(recorder_factory, session_factory) -> None:
    recorder_factory()
    s = session_factory()
    time.sleep(0.2)
    assert not client.status(s).recording
    assert not client.stop(s).ok  # nothing to stop
    assert not client.annotate(s, "nothing recording").ok
    assert client.start(s, session_id="a").ok
    again = client.start(s, session_id="b")
    assert not again.ok and "already recording" in again.reason
    st = client.status(s)
    assert st.recording and st.session == "a"
    assert client.stop(s).ok


def test_unwritable_folder_is_reported_on_status(router_endpoint, session_factory, tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the output folder should be")
    svc = RecorderService(recorder_config(router_endpoint, blocker / "rec"))
    svc.start()
    try:
        s = session_factory()
        seen: list[RecorderStatus] = []
        s.declare_subscriber(keys.service_key(keys.RECORDER, keys.RECORDER_STATUS),
                             lambda sample: seen.append(RecorderStatus.decode(sample.payload.to_bytes())))
        time.sleep(0.3)
        reply = client.start(s, session_id="x")
        assert not reply.ok and "cannot record" in reply.reason
        wait_until(lambda: any(st.error and "cannot record" in st.error for st in seen), message="status error")
    finally:
        svc.shutdown()


class _FullDisk:
    """A file that accepts ``limit`` bytes, then fails like a full disk."""

    def __init__(self, path: Path, limit: int) -> None:
        self._f = path.open("xb")
        self._left = limit

    def write(self, data: bytes) -> int:
        import errno

        if len(data) > self._left:
            raise OSError(errno.ENOSPC, "No space left on device", str(self._f.name))
        self._left -= len(data)
        return self._f.write(data)

    def __getattr__(self, name: str):
        return getattr(self._f, name)


def test_full_disk_stops_recording_with_a_clear_error(router_endpoint, session_factory, tmp_path: Path) -> None:
    svc = RecorderService(recorder_config(router_endpoint, tmp_path / "rec", flush_interval=0.05),
                          opener=lambda p: _FullDisk(p, 4000))
    svc.start()
    try:
        s = session_factory()
        seen: list[RecorderStatus] = []
        s.declare_subscriber(keys.service_key(keys.RECORDER, keys.RECORDER_STATUS),
                             lambda sample: seen.append(RecorderStatus.decode(sample.payload.to_bytes())))
        pub = s.declare_publisher("iorthand/sim1/state/force")
        time.sleep(0.3)
        assert client.start(s, session_id="full").ok
        for seq in range(1, 400):
            pub.put(_force(seq))
            time.sleep(0.001)
        wait_until(lambda: any("disk full" in st.error for st in seen), message="disk-full status")
        assert not svc.recording
        m = mf.Manifest.read(tmp_path / "rec" / "full")
        assert m.status == mf.FAILED and "disk full" in m.error
    finally:
        svc.shutdown()


def test_unknown_keys_are_stored_raw(recorder_factory, session_factory, tmp_path: Path) -> None:
    svc = recorder_factory()
    s = session_factory()
    time.sleep(0.3)
    assert client.start(s, session_id="raw").ok
    s.put("iorthand/_twin/sim1/whatever", msgpack.packb({"seq": 5, "x": 1}))
    wait_until(lambda: svc.status.messages >= 1)
    client.stop(s)
    m = mf.Manifest.read(tmp_path / "rec" / "raw")
    st = m.keys["iorthand/_twin/sim1/whatever"]
    assert st.messages == 1 and st.malformed == 0 and st.type == ""


def test_segments_rotate_by_size_and_carry_calibration(recorder_factory, session_factory, tmp_path: Path) -> None:
    from iorthand_cloud.recorder.reader import attachments

    calib = tmp_path / "camera.yaml"
    calib.write_text("image_size: [640, 480]\nmethod: test\n")
    svc = recorder_factory(segment_max_mb=0.002, flush_interval=0.05, calibration_files=[str(calib)])
    s = session_factory()
    pub = s.declare_publisher("iorthand/sim1/state/force")
    time.sleep(0.3)
    assert client.start(s, session_id="rot").ok
    for seq in range(1, 601):
        pub.put(_force(seq, fz=float(seq % 13)))
        if seq % 50 == 0:
            time.sleep(0.06)  # let flushes (and so rotations) happen
    wait_until(lambda: svc.status.messages >= 600, message="600 messages")
    assert client.stop(s).ok
    folder = tmp_path / "rec" / "rot"
    files = segment_files(folder)
    assert len(files) >= 3
    m = mf.Manifest.read(folder)
    assert [seg.file for seg in m.segments] == [p.name for p in files]
    assert all(seg.status == "closed" for seg in m.segments)
    assert [r.sequence for r in iter_records(folder)] == list(range(1, 601))
    assert attachments(folder)["camera.yaml"] == calib.read_bytes()
    assert m.attachments == ["camera.yaml"] and m.keys["iorthand/sim1/state/force"].missing == 0


def test_a_flood_of_new_keys_is_counted_as_dropped_and_the_recording_goes_on(recorder_factory, session_factory,
                                                                              tmp_path: Path) -> None:
    """Anyone who may publish can name new keys: beyond max_keys they are not recorded but counted, so the writer
    never falls behind the real streams (30 000 new robot ids put it 70 s behind before, and a shutdown then
    lost the backlog of the real stream while the manifest said 0 dropped)."""
    svc = recorder_factory(max_keys=20)
    s = session_factory()
    legit = s.declare_publisher("iorthand/sim1/state/force")
    time.sleep(0.3)
    assert client.start(s, session_id="flood", robots=["sim1"]).ok
    for seq in range(1, 101):
        for i in range(10):
            s.put(f"iorthand/z{seq}-{i}/state/force", _force(1))
        legit.put(_force(seq))  # after the flood filled max_keys: the requested robot has a quota of its own
    wait_until(lambda: svc.status.messages + svc.status.dropped == 1100, 10, message="every sample recorded or counted")
    assert client.stop(s).ok
    m = mf.Manifest.read(tmp_path / "rec" / "flood")
    assert len(m.keys) == 21 and len(m.robots) == 21 and m.keys["iorthand/sim1/state/force"].messages == 100
    assert m.dropped == 1100 - mf.totals(m.keys)["messages"] == 1100 - 100 - 20


def test_a_shutdown_that_cannot_wait_for_the_backlog_counts_it(router_endpoint, session_factory, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """A backlog longer than a shutdown waits is counted as dropped, and one thread closes the files: before, the
    queued samples vanished (manifest: 0 dropped) and a second thread closed the segments under the writer."""
    from iorthand_cloud.recorder import service as service_module

    monkeypatch.setattr(service_module, "SHUTDOWN_DRAIN_S", 0.3)
    svc = RecorderService(recorder_config(router_endpoint, tmp_path / "rec"))
    write = svc._write_sample

    def slow_disk(*args: object) -> None:  # a disk that takes 5 ms a sample: the backlog takes 10 s to write
        time.sleep(0.005)
        write(*args)

    svc._write_sample = slow_disk  # type: ignore[method-assign]
    on_sample = svc._on_sample
    arrived = [0]

    def counting(sample: zenoh.Sample) -> None:  # the recorder's own callback, counted
        arrived[0] += str(sample.key_expr) == "iorthand/sim1/state/force"
        on_sample(sample)

    svc._on_sample = counting  # type: ignore[method-assign]
    svc.start()
    s = session_factory()
    # BLOCK: a burst of 2000 puts must not be thinned by the transport on a loaded machine (with the default DROP,
    # a CI run saw fewer than 2000 reach the recorder in 10 s); what this test counts is the recorder's own drops.
    pub = s.declare_publisher("iorthand/sim1/state/force", congestion_control=zenoh.CongestionControl.BLOCK,
                              reliability=zenoh.Reliability.RELIABLE)
    time.sleep(0.3)
    assert client.start(s, session_id="backlog").ok
    for seq in range(1, 2001):
        pub.put(_force(seq))
    wait_until(lambda: svc.status.messages >= 20, 5, message="the writer under way")
    # Every sample queued before the shutdown (a loaded machine took more than 0.5 s to deliver them all: 172 were
    # still on their way in a CI run, and neither recorded nor queued).
    wait_until(lambda: arrived[0] >= 2000, 30, message="every sample arrived at the recorder")
    t0 = time.monotonic()
    svc.shutdown()
    assert time.monotonic() - t0 < 2.0
    m = mf.Manifest.read(tmp_path / "rec" / "backlog")
    recorded = m.keys["iorthand/sim1/state/force"].messages
    assert m.status == mf.COMPLETE and 0 < recorded < 2000 and m.dropped == 2000 - recorded
    assert sum(1 for _ in iter_records(tmp_path / "rec" / "backlog")) == recorded  # segments closed, readable


def test_text_from_the_wire_is_inert_in_markdown() -> None:
    assert md_text("a | b\n## Robot x") == "a \\| b\\\\n\\#\\# Robot x"
    assert md_text("<script>alert(1)</script> [x](y) **b**") == (
        "&lt;script&gt;alert(1)&lt;/script&gt; \\[x\\](y) \\*\\*b\\*\\*")
    assert md_text("bell\x07 esc\x1b[31m") == "bell\\\\x07 esc\\\\x1b\\[31m"
    assert len(md_text("x" * 10_000)) == 501


def test_a_hostile_session_cannot_write_into_its_report(recorder_factory, session_factory, tmp_path: Path) -> None:
    """What a participant put on the wire (operator name, annotations, robot ids, a forged source time) is text
    in report.md, and neither breaks the report nor its figures (found by a red-team run: a fake status line
    and a <script> in the report, a 300-character robot id that failed the report with "File name too long",
    and one twist stamped 2^62 ns that made a 3 s teleoperation last 89 years)."""
    svc = recorder_factory()
    s = session_factory()
    time.sleep(0.3)
    assert client.start(s, session_id="hostile", operator="eve\n- status: **complete** <script>alert(1)</script>").ok
    twist = s.declare_publisher(keys.RobotKeys("sim1").key(keys.CMD_TWIST))
    t0 = time.time_ns()
    for seq in range(1, 31):
        twist.put(TwistCommand(operator="alice", deadman=True).stamp(seq, t0 + seq * 100_000_000).encode())
    twist.put(TwistCommand(operator="alice", deadman=True).stamp(31, 2**62).encode())
    s.put("iorthand/" + "r" * 300 + "/state/force", _force(1))
    s.put("iorthand/Robot <img src=x onerror=alert(1)>/state/force", _force(1))
    assert client.annotate(s, "ok | **100 %** |\n## Robot sim1 — corrected\x1b[2J", author="dr <b>x</b>").ok
    wait_until(lambda: svc.status.messages >= 33, message="every message recorded")  # (and the annotation)
    assert client.stop(s).ok
    data = build_report(tmp_path / "rec" / "hostile", ReportConfig(plots=True), tmp_path / "report")
    report = (tmp_path / "report" / "report.md").read_text()
    assert list(data["robots"]) == ["sim1"] and data["recording"]["foreign_keys"] == 2
    sim1 = data["robots"]["sim1"]
    assert sim1["implausible_time"] == 1 and sim1["index"]["t_t"] < 5.0
    assert "<script" not in report and "<img" not in report and "<b>" not in report and "\x1b" not in report
    headings = [line for line in report.splitlines() if line.startswith("#")]
    assert headings == ["# Session hostile", "## Robot sim1", "## Annotations"]
    assert not [line for line in report.splitlines() if line.startswith("- status")][1:]  # no forged status line
    assert "eve\\\\n\\- status" not in report and "eve\\\\n- status: \\*\\*complete" in report


def _chunk(start_s: float, end_s: float, mib: int) -> ChunkIndex:
    return ChunkIndex(message_start_time=int(start_s * 1e9), message_end_time=int(end_s * 1e9),
                      chunk_start_offset=0, chunk_length=0, message_index_offsets={}, message_index_length=0,
                      compression="zstd", compressed_size=1, uncompressed_size=mib * 2**20)


def test_a_segment_whose_chunks_would_take_more_memory_than_the_recorder_writes_is_refused() -> None:
    """Chunks one after the other are read one at a time; chunks whose times overlap are decompressed together."""
    check_chunks(Path("t.mcap"), [_chunk(i, i + 0.9, 60) for i in range(20)])  # 1.2 GiB, 60 MiB at a time
    check_chunks(Path("t.mcap"), [_chunk(0, 1, 60), _chunk(1, 2, 60), _chunk(0.5, 1.5, 60)])  # 180 MiB at once
    with pytest.raises(SegmentError, match=r"t.mcap: the chunk at byte 0 declares 65 MiB uncompressed"):
        check_chunks(Path("t.mcap"), [_chunk(0, 1, 65)])
    with pytest.raises(SegmentError, match=r"chunks whose times overlap hold 300 MiB"):
        check_chunks(Path("t.mcap"), [_chunk(0, 10, 60) for _ in range(5)])


def _bomb(index_types: IndexType = IndexType.ALL) -> bytes:
    """A segment of a few kB holding one zstd chunk of 300 MiB."""
    out = io.BytesIO()
    w = Writer(out, compression=CompressionType.ZSTD, chunk_size=2**31, index_types=index_types)
    w.start("iorthand", "crafted")
    channel = w.register_channel("iorthand/sim1/state/force", "msgpack", 0)
    w.add_message(channel, time.time_ns(), b"\0" * (300 * 2**20), time.time_ns(), 1)
    w.finish()
    return out.getvalue()


def _without_summary(data: bytes) -> bytes:
    """The footer's summary_start set to 0: "no summary", so mcap's reader would read the file front to back."""
    out = bytearray(data)
    struct.pack_into("<Q", out, len(data) - 8 - 20, 0)  # footer: opcode, length, summary_start, ... magic
    return bytes(out)


@pytest.mark.parametrize("variant", ["footer", "torn", "no summary", "no chunk index"])
def test_a_decompression_bomb_is_refused_by_name_before_it_is_decompressed(recorder_factory, session_factory,
                                                                          tmp_path: Path, variant: str) -> None:
    """Found by a red-team run: a 20 kB segment whose zstd chunk unpacked to 600 MiB took `iorthand report` to
    1.33 GB and `export` to 2 GB. A segment with its footer, one without (which the report repairs first), and
    (a later run) ones whose footer has no summary or whose summary has no chunk index: mcap's reader then
    decompressed every chunk unchecked (300 MiB chunk in a 10 kB file: report at 697 MB, exit status 0)."""
    footer = variant != "torn"
    recorder_factory()
    s = session_factory()
    time.sleep(0.3)
    assert client.start(s, session_id="bomb").ok
    s.put("iorthand/sim1/state/force", _force(1))
    time.sleep(0.5)
    assert client.stop(s).ok
    data = {"no summary": lambda: _without_summary(_bomb()),
            "no chunk index": lambda: _bomb(IndexType.NONE)}.get(variant, _bomb)()
    assert len(data) < 100_000
    folder = tmp_path / "rec" / "bomb"
    baseline = _report_in_child(folder, tmp_path / "baseline")
    assert baseline.status == 0, baseline.stderr
    (folder / "telemetry-0099.mcap").write_bytes(data if footer else data[:-200])
    bombed = _report_in_child(folder, tmp_path / "report")
    if footer:  # a finished segment: the report refuses the session and says why
        assert bombed.status == 1, (bombed.stdout, bombed.stderr)
    else:  # one left unfinished: the repair before the report sets it aside, says so, and reads the rest
        assert bombed.status == 0 and "report:" in bombed.stdout, (bombed.stdout, bombed.stderr)
        assert "set aside as telemetry-0099.mcap.refused" in bombed.stderr, bombed.stderr
        assert (folder / "telemetry-0099.mcap.refused").read_bytes() == data[:-200]
        assert mf.Manifest.read(folder).status == mf.COMPLETE
    assert "telemetry-0099.mcap" in bombed.stderr and "declares 300 MiB uncompressed" in bombed.stderr, bombed.stderr
    assert f"{MAX_CHUNK_BYTES // 2**20} MiB" in bombed.stderr and "Traceback" not in bombed.stderr, bombed.stderr
    print(f"\npeak RSS of the report: {baseline.peak_mb:.0f} MB, with the bomb {bombed.peak_mb:.0f} MB")
    assert bombed.peak_mb < baseline.peak_mb + 100  # it decompressed 300 MiB before


@dataclasses.dataclass
class _Run:
    status: int
    stdout: str
    stderr: str
    peak_mb: float


# A child started from this (large) process by vfork inherits its peak RSS at exec; a child forked by a small
# process starts from that process's size. So a small Python process runs the command and says its peak (kB).
_PEAK_RSS = ("import os, subprocess, sys\n"
             "p = subprocess.Popen(sys.argv[1:], preexec_fn=os.getpid)  # (a real fork: no vfork)\n"
             "_, status, usage = os.wait4(p.pid, 0)\n"
             "print(f'peak-rss-kb={usage.ru_maxrss}', file=sys.stderr)\n"
             "sys.exit(os.waitstatus_to_exitcode(status))\n")


def _report_in_child(folder: Path, out: Path) -> _Run:
    """`iorthand report` in a child process, with its peak RSS (the kernel's, for that child alone)."""
    proc = subprocess.run([sys.executable, "-c", _PEAK_RSS, sys.executable, "-m", "iorthand.cli", "report",
                           str(folder), "--out", str(out)], capture_output=True, text=True, timeout=120)
    stderr, _, peak = proc.stderr.rpartition("peak-rss-kb=")
    return _Run(proc.returncode, proc.stdout, stderr, int(peak) / 1024)


def test_a_replay_shortens_a_long_silence_in_the_recording_and_says_so(session_factory, tmp_path: Path) -> None:
    """Found by a red-team run: a file whose times jump by ten years made the replay wait, without a word."""
    from iorthand_cloud.recorder.replay import MAX_GAP_S, Replayer

    folder = tmp_path / "gap"
    folder.mkdir()
    t0 = time.time_ns()
    times = [t0 + i * 100_000_000 for i in range(5)] + [t0 + 3600 * 10**9 + i * 100_000_000 for i in range(5)]
    with (folder / "telemetry-0001.mcap").open("wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start("iorthand", "crafted")
        channel = w.register_channel("iorthand/sim1/state/force", "msgpack", 0)
        for seq, t in enumerate(times, 1):
            w.add_message(channel, t, _force(seq), t, seq)
        w.finish()
    sent: list[float] = []
    rp = Replayer(session_factory(), folder, speed=10.0, on_publish=lambda _r: sent.append(time.monotonic()))
    stats = rp.run()
    assert stats.published == 10
    assert stats.gaps_shortened == pytest.approx(3600 - 0.4 - MAX_GAP_S, abs=0.01)
    assert sent[5] - sent[4] == pytest.approx(MAX_GAP_S / 10, abs=0.2)  # the silence, shortened
    assert sent[9] - sent[5] == pytest.approx(0.04, abs=0.2)  # what follows keeps its timing


def test_a_replay_skips_the_keys_of_invalid_robot_ids_and_goes_on(recorder_factory, session_factory,
                                                                  tmp_path: Path) -> None:
    """A recording made on an open router may hold anyone's keys: one with an invalid robot id ended the replay
    with a traceback before (and the exit status said success)."""
    from iorthand_cloud.recorder.replay import Replayer

    svc = recorder_factory()
    s = session_factory()
    time.sleep(0.3)
    assert client.start(s, session_id="mixed").ok
    s.put("iorthand/EVIL/state/force", _force(1))
    for seq in range(1, 6):
        s.put("iorthand/sim1/state/force", _force(seq))
    wait_until(lambda: svc.status.messages >= 6, message="every message recorded")
    assert client.stop(s).ok
    stats = Replayer(s, tmp_path / "rec" / "mixed", speed=50.0).run()
    assert stats.published == 5 and set(stats.per_key) == {"iorthand/sim1-replay/state/force"}
