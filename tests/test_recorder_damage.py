"""Segments read front to back (no summary: a crashed or live recorder's, or a crafted one) and repaired: memory
bounded whatever the file declares, a damaged record length told apart from a torn tail, nothing skipped
silently. Found by a review of the recorder's readers."""

from __future__ import annotations

import io
import random
import struct
import tracemalloc
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from iorthand.protocol import ForceSample
from iorthand_cloud.recorder import reader
from iorthand_cloud.recorder.reader import CorruptSegment, SegmentError, iter_records
from iorthand_cloud.recorder.repair import repair_segment

FORCE = "iorthand/sim1/state/force"


def _without_summary(data: bytes) -> bytes:
    """The footer's summary_start set to 0: a finished file without a summary, read front to back."""
    return data[: -8 - 20] + struct.pack("<Q", 0) + data[-8 - 12 :]


def _big_chunks(times: list[int], mib: int) -> bytes:
    """One chunk per time, each a message of ``mib`` MiB of zeros: a few kB of zstd on disk."""
    out = io.BytesIO()
    w = Writer(out, compression=CompressionType.ZSTD, chunk_size=2**31)
    w.start("iorthand", "crafted")
    channel = w.register_channel(FORCE, "msgpack", 0)
    for i, t in enumerate(times, 1):
        w.add_message(channel, t, b"\0" * (mib * 2**20), t, i)
        w.flush()  # (a flush ends the chunk, as the recorder's does)
    w.finish()
    return _without_summary(out.getvalue())


def test_a_segment_without_summary_is_read_one_chunk_at_a_time(tmp_path: Path) -> None:
    """Before, every message was read into memory to be sorted: 12 chunks of 2 MiB (a 6 kB file) held 24 MiB at
    once, and a crafted file of many capped chunks (64 MiB each) any amount (8 × 60 MiB: 420 MiB more RSS for a
    17 kB file). In time order, as the recorder writes, one chunk is held at a time."""
    (tmp_path / "telemetry-0001.mcap").write_bytes(_big_chunks(list(range(1, 13)), 2))
    tracemalloc.start()
    try:
        sequences = [r.sequence for r in iter_records(tmp_path)]
        _now, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert sequences == list(range(1, 13))
    assert peak < 9 * 2**20, f"{peak / 2**20:.1f} MiB held to read 2 MiB chunks"


def test_chunks_out_of_time_order_are_refused_beyond_the_bound(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Chunks whose times go backwards must all be held to be put in order: beyond the bound (here lowered to
    8 MiB, to keep the test small) the file is refused, named; before, it was read whole into memory."""
    monkeypatch.setattr(reader, "MAX_OVERLAPPING_CHUNK_BYTES", 8 * 2**20)
    (tmp_path / "telemetry-0001.mcap").write_bytes(_big_chunks(list(range(12, 0, -1)), 2))
    with pytest.raises(SegmentError, match=r"telemetry-0001.mcap: its chunks are out of time order .* 8 MiB"):
        list(iter_records(tmp_path))


def test_messages_out_of_order_come_back_in_receive_time_order(tmp_path: Path) -> None:
    """Within the bound, chunks whose times overlap or go back (receive times taken by two Zenoh threads) are
    read in receive-time order, equal times in file order, as before."""
    rng = random.Random(7)
    times = [10_000 + t * 1000 + rng.randrange(-3000, 3000) for t in range(2000)] + [500_000] * 5
    out = io.BytesIO()
    w = Writer(out, compression=CompressionType.ZSTD, chunk_size=512)
    w.start("iorthand", "crafted")
    channel = w.register_channel(FORCE, "msgpack", 0)
    for i, t in enumerate(times):
        w.add_message(channel, t, ForceSample(force=[0.0, 0.0, 1.0]).stamp(i + 1).encode(), t, i + 1)
    w.finish()
    (tmp_path / "telemetry-0001.mcap").write_bytes(_without_summary(out.getvalue()))
    expected = [i + 1 for i, _t in sorted(enumerate(times), key=lambda e: e[1])]
    assert [r.sequence for r in iter_records(tmp_path)] == expected
    window = [r.sequence for r in iter_records(tmp_path, start=400_000, end=600_000)]
    assert window == [s for s in expected if 400_000 <= times[s - 1] < 600_000]


def _segment(stream: str = "telemetry") -> tuple[bytes, list]:
    """A recorder's segment without its footer (killed after its last flush): 2000 force samples in chunks
    of 4 kB (zstd), or 200 pictures of random bytes (uncompressed, like JPEG); and its chunk indexes."""
    out = io.BytesIO()
    video = stream == "video"
    w = Writer(out, compression=CompressionType.NONE if video else CompressionType.ZSTD, chunk_size=4096)
    w.start("iorthand", "crafted")
    channel = w.register_channel("iorthand/sim1/video/camera" if video else FORCE, "msgpack", 0)
    rng = random.Random(3)
    for seq in range(1, 201 if video else 2001):
        data = rng.randbytes(3000) if video else ForceSample(force=[0.0, 0.0, 2.0]).stamp(seq).encode()
        w.add_message(channel, seq * 5_000_000, data, seq * 5_000_000, seq)
    w.finish()
    data = out.getvalue()
    chunks = make_reader(io.BytesIO(data)).get_summary().chunk_indexes
    end = chunks[-1].chunk_start_offset + chunks[-1].chunk_length + chunks[-1].message_index_length
    return data[:end], chunks


@pytest.mark.parametrize("bit", [62, 40, 20, 12, 1])
def test_a_record_length_damaged_in_the_middle_keeps_the_file_as_it_was(tmp_path: Path, bit: int) -> None:
    """A bit flip in the length of chunk 3 of 34. Before: a length past the end of the file was taken for a torn
    tail (bits 62, 40, 20: the repair dropped chunks 3-33 and deleted the original), and one that stayed inside
    (bits 12, 1) skipped the records it covered, as mcap skips padding, without a word."""
    data, chunks = _segment()
    at = chunks[3].chunk_start_offset
    damaged = bytearray(data)
    (length,) = struct.unpack_from("<Q", damaged, at + 1)
    struct.pack_into("<Q", damaged, at + 1, length ^ (1 << bit))
    path = tmp_path / "telemetry-0001.mcap"
    path.write_bytes(bytes(damaged))
    with pytest.raises(CorruptSegment, match=rf"telemetry-0001.mcap: the record at byte {at} says it is"):
        list(iter_records(tmp_path))
    res = repair_segment(path)
    assert "its length is damaged" in res.damage
    assert res.original == tmp_path / "telemetry-0001.mcap.orig" and res.original.read_bytes() == bytes(damaged)
    assert [r.sequence for r in iter_records(tmp_path)] == list(range(1, chunks[3].message_start_time // 5_000_000))


@pytest.mark.parametrize("stream", ["telemetry", "video"])
def test_a_torn_tail_is_still_repaired_without_keeping_the_original(tmp_path: Path, stream: str) -> None:
    """Cut anywhere in the last chunk or the message index after it (a kill in the middle of a flush): a torn
    tail, as before: the whole chunks are kept and nothing else."""
    data, chunks = _segment(stream)
    last = chunks[-1]
    before = last.message_start_time // 5_000_000 - 1  # the messages of the whole chunks
    cuts = [1, 5, 9, 20, 40, 60, last.chunk_length // 2, last.chunk_length - 1, last.chunk_length + 5]
    cuts += [last.chunk_length + last.message_index_length - 3]
    path = tmp_path / f"{stream}-0001.mcap"
    for cut in cuts:
        path.write_bytes(data[: last.chunk_start_offset + cut])
        res = repair_segment(path)
        whole = before + (last.chunk_start_offset + cut >= last.chunk_start_offset + last.chunk_length) * (
            last.message_end_time // 5_000_000 - before
        )
        assert (res.original, res.damage, res.messages) == (None, "", whole), f"cut at {cut}"
        assert not any(p.suffix in (".orig", ".repair") for p in tmp_path.iterdir())


def test_a_record_of_no_known_kind_is_damage_not_skipped(tmp_path: Path) -> None:
    """A bit flip in a chunk's opcode: mcap's reader skips records it does not know, so the chunk's messages were
    left out without a word; the recorder writes none such."""
    data, chunks = _segment()
    damaged = bytearray(data)
    damaged[chunks[5].chunk_start_offset] ^= 0x40
    (tmp_path / "telemetry-0001.mcap").write_bytes(bytes(damaged))
    with pytest.raises(CorruptSegment, match=rf"byte {chunks[5].chunk_start_offset} is damaged: its kind \(opcode "):
        list(iter_records(tmp_path))


def test_a_file_cut_inside_its_magic_is_a_torn_tail(tmp_path: Path) -> None:
    """A recorder killed as it opened a segment."""
    data, _chunks = _segment()
    path = tmp_path / "telemetry-0001.mcap"
    path.write_bytes(data[:5])
    assert repair_segment(path).original is None and list(iter_records(tmp_path)) == []
    path.write_bytes(b"PK\x03\x04" + data[4:])  # not an MCAP file
    with pytest.raises(CorruptSegment, match="not an MCAP file"):
        list(iter_records(tmp_path))


def test_damage_in_the_foxglove_copy_is_said_in_the_manifest(tmp_path: Path) -> None:
    """Found by a review: a repair that stopped at damage in the session's Foxglove copy kept the original file
    but said so only in the log; the session's manifest (what report and export show) said nothing."""
    from iorthand_cloud.recorder import manifest as mf
    from iorthand_cloud.recorder.repair import repair_if_crashed

    data, chunks = _segment()
    (tmp_path / "telemetry-0001.mcap").write_bytes(data)  # the session's own segment: torn after its last chunk
    (tmp_path / "foxglove").mkdir()
    damaged = bytearray(data)
    at = chunks[4].chunk_start_offset + chunks[4].chunk_length // 2
    damaged[at : at + 8] = bytes(b ^ 0xFF for b in damaged[at : at + 8])  # inside chunk 4's compressed data
    (tmp_path / "foxglove" / "foxglove-0001.mcap").write_bytes(bytes(damaged))
    mf.Manifest(session_id="f").write(tmp_path)
    mf.release_writer_lock(tmp_path)  # as the kernel does for a killed process
    said = repair_if_crashed(tmp_path)
    assert "repaired 1 segment" in said
    error = mf.Manifest.read(tmp_path).error
    assert f"foxglove-0001.mcap: the chunk at byte {chunks[4].chunk_start_offset} is damaged" in error, error
    assert "kept as foxglove-0001.mcap.orig" in error and (tmp_path / "foxglove" / "foxglove-0001.mcap.orig").exists()


def test_a_manifest_that_cannot_be_read_is_kept_beside_the_one_rebuilt(tmp_path: Path) -> None:
    """Found by a review: a manifest that could not be read (here: cut short, as by a disk that failed) was replaced
    by one rebuilt from the segments, and the original was lost without a word. It is now kept (as a damaged
    segment is: ``.orig``, or the next free name), and the log, the command's output and the new manifest say so."""
    from iorthand_cloud.recorder import manifest as mf
    from iorthand_cloud.recorder.repair import repair_if_crashed

    data, _ = _segment()
    (tmp_path / "telemetry-0001.mcap").write_bytes(data)  # torn after its last chunk: the recorder was killed
    mf.Manifest(session_id="m", operator="dr-house").write(tmp_path)
    original = (tmp_path / mf.MANIFEST).read_bytes()
    (tmp_path / mf.MANIFEST).write_bytes(original[: len(original) // 2])
    (tmp_path / "manifest.json.orig").write_bytes(b"an earlier original")  # from an earlier rebuild: left alone
    mf.release_writer_lock(tmp_path)  # as the kernel does for a killed process
    said = repair_if_crashed(tmp_path)
    assert "its manifest could not be read (" in said and "kept as manifest.json.orig.1, a new one rebuilt" in said, said
    assert "repaired 1 segment" in said, said
    assert (tmp_path / "manifest.json.orig.1").read_bytes() == original[: len(original) // 2]
    assert (tmp_path / "manifest.json.orig").read_bytes() == b"an earlier original"
    rebuilt = mf.Manifest.read(tmp_path)
    assert "kept as manifest.json.orig.1" in rebuilt.error, rebuilt.error

    # Whole segments and a manifest that is not JSON at all: the manifest is all there was to repair.
    (tmp_path / mf.MANIFEST).write_bytes(b"\x00garbage")
    said = repair_if_crashed(tmp_path)
    assert said.startswith("its manifest could not be read (") and "kept as manifest.json.orig.2" in said, said
    assert (tmp_path / "manifest.json.orig.2").read_bytes() == b"\x00garbage"
