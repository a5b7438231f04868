"""Recorder faults found by a red-team review: a disk that fills up, write errors with a queue behind them,
session ids that name no folder of their own, a wall clock that steps."""

from __future__ import annotations

import errno
import io
import os
import struct
import subprocess
import threading
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from iorthand.config import from_dict
from iorthand.protocol import ForceSample, VideoFrame
from iorthand_cloud.recorder import client
from iorthand_cloud.recorder import manifest as mf
from iorthand_cloud.recorder.config import RecorderConfig
from iorthand_cloud.recorder.reader import CorruptSegment, SegmentError, iter_records
from iorthand_cloud.recorder.repair import repair_if_crashed, repair_segment
from iorthand_cloud.recorder.service import RecorderService
from tests.conftest import small_disk, wait_until


def _config(endpoint: str, out: Path, **extra: object) -> RecorderConfig:
    data = {"zenoh": {"mode": "client", "connect": [endpoint]}, "output_dir": str(out), "fsync": False, **extra}
    return from_dict(data, RecorderConfig, source="<test>")


def _recording_force(session_factory, session_id: str):
    """A session that publishes force samples, with a recording started under ``session_id``."""
    s = session_factory()
    pub = s.declare_publisher("iorthand/sim1/state/force")
    time.sleep(0.3)  # the recorder's subscription reaches the router first
    assert client.start(s, session_id=session_id).ok
    return s, pub


def _force(seq: int) -> bytes:
    return ForceSample(force=[0.0, 0.0, 2.0]).stamp(seq).encode()


def _writer_lock_free(folder: Path) -> bool:
    """Whether no process holds the session's writer lock, asked of another process (this one's own locks do not
    show to flock from here)."""
    probe = ("import fcntl, os, sys\n"
             "fd = os.open(sys.argv[1], os.O_RDWR)\n"
             "try:\n    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)\nexcept BlockingIOError:\n    sys.exit(1)\n")
    import sys

    return subprocess.run([sys.executable, "-c", probe, str(folder / mf.WRITER_LOCK)]).returncode == 0


@pytest.fixture
def small_tmpfs(tmp_path: Path):
    """A 1 MiB tmpfs: a disk that really fills up, for the manifest as well as the segments (root only)."""
    with small_disk(tmp_path, "1m") as mnt:
        yield mnt


def test_a_full_disk_releases_the_session_and_keeps_the_reason(router_endpoint, session_factory,
                                                              small_tmpfs: Path) -> None:
    """Found by a red-team run: when the disk was too full for the final manifest too, the recorder kept the
    writer lock (after shutdown as well), so readers took the session for a live one and never repaired it; a
    later repair called it a crash, and manifest.json.tmp was left behind."""
    svc = RecorderService(_config(router_endpoint, small_tmpfs / "rec", flush_interval=0.05,
                                  foxglove={"enabled": False}))
    svc.start()
    try:
        s = session_factory()
        video = s.declare_publisher("iorthand/sim1/video/camera")
        time.sleep(0.3)
        assert client.start(s, session_id="full", robots=["sim1"]).ok
        folder = small_tmpfs / "rec" / "full"
        for seq in range(1, 40):  # 40 × 60 kB of noise into 1 MiB
            video.put(VideoFrame(width=4, height=2, data=os.urandom(60_000)).stamp(seq).encode())
            time.sleep(0.01)
        wait_until(lambda: not svc.recording and "disk full" in svc.status.error, 5, message="the disk-full stop")
        assert not (folder / (mf.MANIFEST + ".tmp")).exists()
        assert mf.Manifest.read(folder).status == mf.RECORDING  # the disk had no room for the final one
        assert _writer_lock_free(folder) and not mf.writer_alive(folder, quiet_for=0.0)
        for seg in folder.glob("video-*.mcap"):  # room again (what an operator would do)
            seg.unlink()
        assert "repaired" in repair_if_crashed(folder)
        m = mf.Manifest.read(folder)
        assert m.status == mf.FAILED and "disk full" in m.error and "crash" not in m.error, m.error
    finally:
        svc.shutdown()
    assert Path(small_tmpfs / "rec" / "full").resolve() not in mf._writer_locks


def test_a_manifest_that_cannot_be_written_leaves_no_temporary_file(tmp_path: Path) -> None:
    def full(path: Path) -> io.BufferedWriter:
        f = path.open("xb")
        f.close()
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    m = mf.Manifest(session_id="x", status=mf.COMPLETE)
    with pytest.raises(OSError, match="No space"):
        m.write(tmp_path, fsync=False, opener=full)
    assert list(tmp_path.iterdir()) == []
    m.write(tmp_path, fsync=False)
    assert mf.Manifest.read(tmp_path).status == mf.COMPLETE


class _SlowFullDisk(io.FileIO):
    """Segment files whose writes, once ``armed``, take 1.5 s and then fail like a full disk: the queue fills
    behind the failing write (the manifest, small, still fits)."""

    armed = threading.Event()

    def write(self, data) -> int:  # type: ignore[override]
        if self.armed.is_set():
            time.sleep(1.5)
            raise OSError(errno.ENOSPC, "No space left on device", self.name)
        return super().write(data)


def test_what_was_queued_at_a_write_error_is_answered_and_counted(router_endpoint, session_factory,
                                                                  tmp_path: Path) -> None:
    """Found by a red-team run: a write error threw the queue away: an annotation waiting in it was never
    answered ("no recorder answered") and the samples in it were lost while the manifest said 0 dropped."""
    _SlowFullDisk.armed.clear()
    svc = RecorderService(_config(router_endpoint, tmp_path / "rec", foxglove={"enabled": False}),
                          opener=lambda p: _SlowFullDisk(p, "xb") if p.suffix == ".mcap" else p.open("xb"))
    svc.start()
    try:
        s, pub = _recording_force(session_factory, "dr")
        _SlowFullDisk.armed.set()
        pub.put(_force(1))  # the first message is flushed at once: the writer blocks on it
        time.sleep(0.2)
        for seq in range(2, 52):
            pub.put(_force(seq))
        reply = client.annotate(s, "probe slipped", author="alice")
        assert not reply.ok and "disk full" in reply.reason, reply.reason
        wait_until(lambda: not svc.recording, message="the recording stopped")
    finally:
        svc.shutdown()
        _SlowFullDisk.armed.clear()
    m = mf.Manifest.read(tmp_path / "rec" / "dr")
    assert m.status == mf.FAILED and "disk full" in m.error
    assert m.dropped == 50 and mf.totals(m.keys)["messages"] == 1  # 1 taken, written in vain; 50 left queued


@pytest.mark.parametrize("session_id", ["abc\n", ".", ".."])
def test_a_session_id_that_names_no_folder_of_its_own_is_refused(router_endpoint, session_factory, tmp_path: Path,
                                                                 session_id: str) -> None:
    """Found by a red-team run: "abc\\n" was accepted (re.match with "$"); "." and ".." passed the pattern and
    failed later as "File exists"."""
    svc = RecorderService(_config(router_endpoint, tmp_path / "rec", foxglove={"enabled": False}))
    svc.start()
    try:
        s = session_factory()
        time.sleep(0.3)
        reply = client.start(s, session_id=session_id)
        assert not reply.ok and f"session id {session_id!r} is invalid" in reply.reason, reply.reason
        assert client.start(s, session_id="abc").ok  # and the recorder goes on
        assert client.stop(s).ok
    finally:
        svc.shutdown()
    assert sorted(p.name for p in (tmp_path / "rec").iterdir()) == ["abc"]


# ---------------------------------------------------------------------------- segments that lie or are damaged


def _one_big_chunk(mib: int) -> bytes:
    out = io.BytesIO()
    w = Writer(out, compression=CompressionType.ZSTD, chunk_size=2**31)
    w.start("iorthand", "crafted")
    channel = w.register_channel("iorthand/sim1/state/force", "msgpack", 0)
    w.add_message(channel, 1, b"\0" * (mib * 2**20), 1, 1)
    w.finish()
    return out.getvalue()


def _patch_size(data: bytes, new: int, after: int = 0) -> bytes:
    """The chunk's uncompressed size, wherever it is said from byte ``after`` on, set to ``new``."""
    old = make_reader(io.BytesIO(data)).get_summary().chunk_indexes[0].uncompressed_size
    needle, out = struct.pack("<Q", old), bytearray(data)
    at = out.find(needle, after)
    assert at >= 0
    while at >= 0:
        out[at:at + 8] = struct.pack("<Q", new)
        at = out.find(needle, at + 8)
    return bytes(out)


def test_a_chunk_index_that_understates_its_chunk_is_not_trusted(tmp_path: Path) -> None:
    """Found by a red-team review: the size check read the chunk index alone, which a crafted file may make say
    anything; the chunk's own size was then decompressed unchecked."""
    data = _one_big_chunk(65)
    summary_start = struct.unpack_from("<Q", data, len(data) - 8 - 20)[0]
    (tmp_path / "telemetry-0001.mcap").write_bytes(_patch_size(data, 1000, after=summary_start))
    with (tmp_path / "telemetry-0001.mcap").open("rb") as f:
        assert make_reader(f).get_summary().chunk_indexes[0].uncompressed_size == 1000  # the index understates
    with pytest.raises(SegmentError, match=r"telemetry-0001.mcap: the chunk at byte \d+ declares 65 MiB"):
        list(iter_records(tmp_path))


def test_a_zstd_frame_larger_than_its_chunk_declares_is_refused(tmp_path: Path) -> None:
    """zstd allocates what its frame header says, whatever size the chunk around it declares."""
    data = _patch_size(_one_big_chunk(65), 1000)  # the chunk and its index both say 1000 bytes
    (tmp_path / "telemetry-0001.mcap").write_bytes(data)
    with pytest.raises(SegmentError, match=r"telemetry-0001.mcap: the chunk at byte \d+ .*zstd frame.*65 MiB"):
        list(iter_records(tmp_path))


def _session_file(path: Path) -> bytes:
    """2000 force samples in chunks of 4 kB, as the recorder writes them."""
    out = io.BytesIO()
    w = Writer(out, compression=CompressionType.ZSTD, chunk_size=4096)
    w.start("iorthand", "crafted")
    channel = w.register_channel("iorthand/sim1/state/force", "msgpack", 0)
    for seq in range(1, 2001):
        w.add_message(channel, seq * 5_000_000, _force(seq), seq * 5_000_000, seq)
    w.finish()
    path.write_bytes(out.getvalue())
    return out.getvalue()


def _damage_chunk(data: bytes, n: int) -> tuple[bytes, int, int]:
    """Eight bytes inverted inside the compressed data of chunk ``n``; returns the bytes, that chunk's offset
    and the time of its first message."""
    ci = make_reader(io.BytesIO(data)).get_summary().chunk_indexes[n]
    out = bytearray(data)
    mid = ci.chunk_start_offset + ci.chunk_length - ci.compressed_size // 2 - 20
    for j in range(mid, mid + 8):
        out[j] ^= 0xFF
    return bytes(out), ci.chunk_start_offset, ci.message_start_time


@pytest.mark.parametrize("summary", [True, False])
def test_a_damaged_chunk_is_refused_naming_the_file_and_the_chunk(tmp_path: Path, summary: bool) -> None:
    """Found by a red-team run: eight inverted bytes in a zstd chunk were read without a word (one record's time
    off by 3.47 s) and report and export said success: CRCs were never checked. Through the index, and front
    to back (a file without a summary)."""
    path = tmp_path / "telemetry-0001.mcap"
    data, offset, _t = _damage_chunk(_session_file(path), 5)
    if not summary:
        data = data[:-8 - 20] + struct.pack("<Q", 0) + data[-8 - 12:]  # the footer's summary_start: none
    path.write_bytes(data)
    with pytest.raises(CorruptSegment, match=rf"telemetry-0001.mcap: the chunk at byte {offset} is damaged"):
        list(iter_records(tmp_path))


def test_a_repair_stopped_by_damage_keeps_the_file_as_it_was(tmp_path: Path) -> None:
    """A segment without footer whose chunk 5 is damaged: the repair keeps what precedes the damage and, since
    what follows may be good (unlike a torn tail), the original file beside it; before, it replaced it."""
    path = tmp_path / "telemetry-0001.mcap"
    data = _session_file(path)
    cut = make_reader(io.BytesIO(data)).get_summary().chunk_indexes[8].chunk_start_offset + 30
    damaged, _offset, t5 = _damage_chunk(data, 5)
    path.write_bytes(damaged[:cut])  # no footer: a torn tail inside chunk 8 as well
    res = repair_segment(path)
    assert res.original == tmp_path / "telemetry-0001.mcap.orig" and res.original.read_bytes() == damaged[:cut]
    assert "is damaged" in res.damage
    before = t5 // 5_000_000 - 1  # the messages of chunks 0-4
    assert [r.sequence for r in iter_records(tmp_path)] == list(range(1, before + 1))
    # A torn tail alone: nothing is kept but the repaired file.
    path.write_bytes(data[:cut])
    res = repair_segment(path)
    assert res.original is None and res.lost_bytes > 0 and not (tmp_path / "telemetry-0001.mcap.repair").exists()
    assert len(list(iter_records(tmp_path))) == res.messages > before


def test_a_wall_clock_step_during_a_recording_keeps_times_in_order(router_endpoint, session_factory,
                                                                    tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """Found by a red-team run: the host's clock stepping back 5 s (NTP) mid-session gave a negative duration
    and receive times out of order (read back, the samples after the step came first)."""
    svc = RecorderService(_config(router_endpoint, tmp_path / "rec", foxglove={"enabled": False}))
    svc.start()
    try:
        s, pub = _recording_force(session_factory, "cs")
        real, t0 = time.time_ns, time.time_ns()
        for seq in range(1, 101):
            if seq == 51:
                wait_until(lambda: svc.status.messages >= 50, message="the samples before the step recorded")
                monkeypatch.setattr(time, "time_ns", lambda: real() - 5_000_000_000)  # the step, this process
            pub.put(ForceSample(force=[0.0, 0.0, 2.0]).stamp(seq, t0 + seq * 10_000_000).encode())
            time.sleep(0.002)
        wait_until(lambda: svc.status.messages >= 100, message="every sample recorded")
        assert client.stop(s).ok
    finally:
        svc.shutdown()
    folder = tmp_path / "rec" / "cs"
    m = mf.Manifest.read(folder)
    assert 0 < m.stop_t - m.start_t < 30e9
    records = list(iter_records(folder))
    assert [r.sequence for r in records] == list(range(1, 101))
    assert all(m.start_t <= r.log_time <= m.stop_t for r in records)


def test_a_repair_names_the_type_of_each_key(tmp_path: Path) -> None:
    """Found by a red-team review: statistics recomputed by a repair had every key's type empty."""
    data = _session_file(tmp_path / "telemetry-0001.mcap")
    (tmp_path / "telemetry-0001.mcap").write_bytes(data[:len(data) // 2])  # a killed recorder's segment
    mf.Manifest(session_id="k", keys={"iorthand/sim1/state/force": mf.KeyStats(type="ForceSample")}).write(tmp_path)
    mf.release_writer_lock(tmp_path)  # as the kernel does for a killed process
    assert "repaired 1 segment" in repair_if_crashed(tmp_path)
    m = mf.Manifest.read(tmp_path)
    assert m.status == mf.RECOVERED and m.keys["iorthand/sim1/state/force"].type == "ForceSample"
