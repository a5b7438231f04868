"""Segments crafted to exhaust the memory of whoever reads them (a recording copied from elsewhere and opened with
``iorthand report``, replay or export): their summary and their attachments. Found by a review of the recorder's
readers; each is refused by name before it takes memory, or read as it is."""

from __future__ import annotations

import dataclasses
import io
import os
import re
import struct
import tracemalloc
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Metadata
from mcap.writer import CompressionType, Writer

from iorthand.config import from_dict
from iorthand.protocol import ForceSample
from iorthand_cloud.recorder import reader
from iorthand_cloud.recorder.config import RecorderConfig
from iorthand_cloud.recorder.reader import CorruptSegment, SegmentError, attachments, iter_records, segment_topics
from iorthand_cloud.recorder.repair import has_footer, repair_segment
from iorthand_cloud.recorder.segments import MAX_SUMMARY_BYTES

FORCE = "iorthand/sim1/state/force"
CALIBRATION = b"camera_matrix: [600, 0, 320, 0, 600, 240, 0, 0, 1]\n"


def _segment(attached: bytes = CALIBRATION) -> bytes:
    """A finished segment as the recorder writes it: 100 force samples in chunks of 4 kB, a calibration file."""
    out = io.BytesIO()
    w = Writer(out, compression=CompressionType.ZSTD, chunk_size=4096)
    w.start("iorthand", "crafted")
    w.add_attachment(1, 1, "camera.yaml", "application/yaml", attached)
    channel = w.register_channel(FORCE, "msgpack", 0)
    for seq in range(1, 101):
        w.add_message(channel, seq * 10_000_000, ForceSample(force=[0.0, 0.0, 1.0]).stamp(seq).encode(),
                      seq * 10_000_000, seq)
    w.finish()
    return out.getvalue()


def _records(*records: Any) -> bytes:
    b = RecordBuilder()
    for r in records:
        r.write(b)
    return b.end()


def _with_summary(data: bytes, summary: bytes) -> bytes:
    """``data`` (a finished segment) with its summary replaced by ``summary`` (the footer's CRC 0: not checked)."""
    (start,) = struct.unpack_from("<Q", data, len(data) - 8 - 20)
    return data[:start] + summary + _records(Footer(start, 0, 0)) + data[-8:]


def _peak(read: Callable[[], Any]) -> tuple[Any, float]:
    """What ``read`` returns (or the exception it raises) and the most memory it held at once, MiB."""
    tracemalloc.start()
    try:
        try:
            out: Any = read()
        except Exception as exc:  # (returned: the test says which it expects)
            out = exc
        return out, tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


def test_a_summary_larger_than_the_recorder_writes_is_refused_unread(tmp_path: Path) -> None:
    """Before, mcap's reader parsed any summary whole: 1 M chunk index records (87 MB) took the report to
    1.1 GB and has_footer (the repair's first look at every segment) to 640 MiB; then, within a bound of 64 MiB,
    63 MiB of them took 7-17 s to check. The recorder's own are a few hundred kB (180 kB for 10 minutes of a
    robot's telemetry, at most a few MiB: segments.SUMMARY_ROLL_BYTES); beyond MAX_SUMMARY_BYTES (24 MiB) the
    segment is refused by name, unread."""
    bound = MAX_SUMMARY_BYTES // 2**20
    data = _segment()
    summary = make_reader(io.BytesIO(data)).get_summary()
    one = _records(summary.chunk_indexes[0])
    path = tmp_path / "telemetry-0001.mcap"
    path.write_bytes(_with_summary(data, _records(*summary.channels.values()) + one * (63 * 2**20 // len(one))))
    refused, peak = _peak(lambda: list(iter_records(tmp_path)))
    assert isinstance(refused, SegmentError), refused
    assert (f"telemetry-0001.mcap: its summary is 63 MiB, more than the {bound} MiB of any the recorder writes"
            in str(refused))
    assert peak < 4, f"{peak:.0f} MiB held to refuse it"
    assert has_footer(path)  # finished: a repair leaves it as it is, the reading refuses it
    with pytest.raises(SegmentError, match="its summary is 63 MiB"):
        attachments(tmp_path)


def test_a_summary_indexing_more_chunks_than_its_file_holds_is_refused_after_as_many(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Checking a crafted summary of 63 MiB of chunk index records took 7-17 s (each parsed twice by mcap's
    reader, a field at a time), however little data it indexed. Each chunk index points to a chunk of its own:
    one of 15 MiB over a 3.5 kB data section (room for 72 chunks) is refused once it has indexed more chunks than
    that, after reading as many; the work of checking a summary follows the data it indexes."""
    data = _segment()
    summary = make_reader(io.BytesIO(data)).get_summary()
    one = _records(summary.chunk_indexes[0])
    path = tmp_path / "telemetry-0001.mcap"
    path.write_bytes(_with_summary(data, _records(*summary.channels.values()) + one * (15 * 2**20 // len(one))))
    (data_section,) = struct.unpack_from("<Q", data, len(data) - 8 - 20)  # where the summary begins
    room = (data_section - len(_MAGIC)) // (struct.calcsize("<BQQQQII") + 8)  # a chunk record with nothing in it
    parsed = []
    chunk_index = reader._chunk_index
    monkeypatch.setattr(reader, "_chunk_index", lambda *args: parsed.append(1) or chunk_index(*args))
    for read in (lambda: segment_topics(tmp_path), lambda: list(iter_records(tmp_path)), lambda: attachments(tmp_path)):
        parsed.clear()
        with pytest.raises(SegmentError, match=rf"telemetry-0001.mcap: its summary indexes more chunks than the "
                                               rf"{data_section} bytes before it can hold \({room}, of 49 bytes at "
                                               r"least each\): not read"):
            read()
        assert len(parsed) == room
    assert has_footer(path)  # (finished: the reading refuses it)


def test_chunk_indexes_are_read_as_mcaps_reader_reads_them() -> None:
    """The summary's chunk indexes are parsed here, not by mcap's reader (8 times slower): every record it
    accepts, mcap's reader reads with the same fields; every one it refuses, mcap's reader refuses or reads with
    message index offsets that are not whole entries (the recorder writes none)."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    records = [_records(ChunkIndex(message_start_time=5 + i, message_end_time=9 + i, chunk_start_offset=100 * i,
                                   chunk_length=77, message_index_offsets={c: 1000 + c for c in range(i)},
                                   message_index_length=31 * i, compression=("", "zstd", "zst\u00e9")[i % 3],
                                   compressed_size=40, uncompressed_size=2**40 + i))[9:] for i in range(5)]

    def outcome(parse: Callable[[bytes], Any], body: bytes) -> Any:
        try:
            return parse(body)
        except (CorruptSegment, EndOfFile, struct.error, UnicodeDecodeError, ValueError, McapError):
            return None

    def ours(body: bytes) -> Any:
        first, last, offset, size, channel_map = reader._chunk_index(Path("x.mcap"), 0, body)
        return first, last, offset, size, {c for c, _ in struct.iter_unpack("<HQ", channel_map)}

    def mcaps(body: bytes) -> Any:
        c, used = reader._parse(Opcode.CHUNK_INDEX, body, len(body))
        if used != len(body):  # (the length check of reader._summary_parse)
            return None
        return c.message_start_time, c.message_end_time, c.chunk_start_offset, c.uncompressed_size, set(
            c.message_index_offsets)

    @settings(max_examples=3000, deadline=None, derandomize=True)
    @given(st.sampled_from(records), st.integers(0, 120), st.binary(min_size=0, max_size=6), st.booleans())
    def check(record: bytes, at: int, patch: bytes, cut: bool) -> None:
        body = record[:at] if cut else record[:at] + patch + record[at + len(patch):]
        got, expected = outcome(ours, body), outcome(mcaps, body)
        if got is not None:
            assert got == expected
        elif expected is not None:
            assert struct.unpack_from("<I", body, 32)[0] % 10, body  # the offsets: not whole entries

    for record in records:
        assert outcome(ours, record) == outcome(mcaps, record) is not None
    check()


def test_a_large_summary_within_the_bound_is_held_compactly(tmp_path: Path) -> None:
    """30 000 chunk index records (2.6 MB): mcap's reader held ~512 bytes for each (15 MiB, 640 MiB for the 87 MB
    above); read here, a few bytes each, and their chunks are checked before one is read (these point where no
    chunk is). (A 2 MiB attachment makes the data section long enough to hold as many chunks.)"""
    data = _segment(attached=bytes(2 * 2**20))
    summary = make_reader(io.BytesIO(data)).get_summary()
    first = summary.chunk_indexes[0]
    entries = [dataclasses.replace(first, chunk_start_offset=first.chunk_start_offset + i,
                                   message_start_time=i * 10, message_end_time=i * 10 + 5) for i in range(30_000)]
    (tmp_path / "telemetry-0001.mcap").write_bytes(_with_summary(data, _records(*summary.channels.values(),
                                                                                  *entries)))
    del entries
    topics, peak = _peak(lambda: segment_topics(tmp_path))
    assert topics == {FORCE}
    assert peak < 3, f"{peak:.0f} MiB held to read the channels"
    refused, peak = _peak(lambda: list(iter_records(tmp_path)))
    assert isinstance(refused, CorruptSegment), refused
    assert f"the chunk index points to byte {first.chunk_start_offset + 1}, where no chunk is" in str(refused)
    assert peak < 6, f"{peak:.0f} MiB held to read the index"


def test_a_chunk_in_the_summary_is_refused_not_decompressed(tmp_path: Path) -> None:
    """A summary holds indexes, never data; mcap's reader decompressed a chunk found in one, unchecked (60 MiB
    here, any size in a crafted file), and the read went on as if nothing were there."""
    data = _segment()
    summary = make_reader(io.BytesIO(data)).get_summary()
    inner = _records(*summary.channels.values())
    message = struct.pack("<BQHIQQ", Opcode.MESSAGE, 22 + 60 * 2**20, 1, 1, 5, 5)
    payload = inner + message + b"\0" * (60 * 2**20)
    bomb = Chunk(message_start_time=5, message_end_time=5, uncompressed_size=len(payload), uncompressed_crc=0,
                 compression="zstd", data=zstandard.ZstdCompressor().compress(payload))
    del payload
    tail = _records(*summary.channels.values(), *summary.chunk_indexes, bomb)
    assert len(tail) < 100_000
    (tmp_path / "telemetry-0001.mcap").write_bytes(_with_summary(data, tail))
    refused, peak = _peak(lambda: list(iter_records(tmp_path)))
    assert isinstance(refused, SegmentError), refused
    assert "telemetry-0001.mcap: its summary holds a record of a kind a summary does not hold (chunk)" in str(refused)
    assert peak < 4, f"{peak:.0f} MiB held to refuse it"


def _attachment_index(data: bytes) -> int:
    """Where the segment's attachment index entry is."""
    return data.rindex(_records(make_reader(io.BytesIO(data)).get_summary().attachment_indexes[0]))


def test_an_attachment_larger_than_the_recorder_attaches_is_refused_before_it_is_read(tmp_path: Path) -> None:
    """An index that declares a huge attachment, or an attachment that is one: before, read whole, whatever its
    size (mcap's reader); the recorder attaches calibration files of at most 16 MiB."""
    data = _segment()
    at = _attachment_index(data)
    declared = bytearray(data)
    struct.pack_into("<Q", declared, at + 9 + 32, 2**40)  # its data size (after offset, length and two times)
    struct.pack_into("<I", declared, len(declared) - 8 - 4, 0)  # the summary's CRC: not checked
    (tmp_path / "telemetry-0001.mcap").write_bytes(bytes(declared))
    with pytest.raises(SegmentError, match=r"telemetry-0001.mcap: its attachment 'camera.yaml' is 1048576 MiB, "
                                           r"more than the 16 MiB"):
        attachments(tmp_path)
    (tmp_path / "telemetry-0001.mcap").write_bytes(_segment(b"\0" * (17 * 2**20)))
    refused, peak = _peak(lambda: attachments(tmp_path))
    assert isinstance(refused, SegmentError) and "'camera.yaml' is 17 MiB, more than the 16 MiB" in str(refused)
    assert peak < 4, f"{peak:.0f} MiB held to refuse it"


def test_a_damaged_attachment_is_refused_not_returned(tmp_path: Path) -> None:
    """mcap's reader skips an attachment's CRC: a calibration file with a flipped bit came back as if whole."""
    data = bytearray(_segment())
    at = bytes(data).index(CALIBRATION)
    data[at + 5] ^= 0x01
    (tmp_path / "telemetry-0001.mcap").write_bytes(bytes(data))
    with pytest.raises(CorruptSegment, match=r"telemetry-0001.mcap: the attachment 'camera.yaml' at byte \d+ is "
                                             r"damaged \(its CRC does not match\)"):
        attachments(tmp_path)
    (tmp_path / "telemetry-0001.mcap").write_bytes(_segment())
    (tmp_path / "telemetry-0002.mcap").write_bytes(b"")  # killed as it opened: mcap's EndOfFile, a traceback
    assert attachments(tmp_path) == {"camera.yaml": CALIBRATION}


def test_a_calibration_file_larger_than_a_reader_takes_is_not_attached(tmp_path: Path) -> None:
    """The bound the readers keep is the recorder's too: a file it would refuse to read back is not attached (the
    recording goes on, and says why); before, any size was attached."""
    from iorthand_cloud.recorder.service import RecorderService

    (tmp_path / "camera.yaml").write_bytes(CALIBRATION)
    with (tmp_path / "huge.bin").open("wb") as f:
        f.truncate(17 * 2**20)
    cfg = from_dict({"calibration_files": [str(tmp_path / "huge.bin"), str(tmp_path / "camera.yaml")]},
                    RecorderConfig, source="<test>")
    attached, warnings = RecorderService(cfg)._calibration_attachments()
    assert [(a.name, a.data) for a in attached] == [("camera.yaml", CALIBRATION)]
    assert len(warnings) == 1 and f"calibration file {tmp_path / 'huge.bin'} not attached: larger than 16 MiB" in (
        warnings[0])


# ------------------------------------------------------------------------------------------- the data section


def _file(chunk_records: bytes, summary: bool = True, declared: int | None = None) -> bytes:
    """A segment of one zstd chunk holding ``chunk_records`` (its channel 1: the force key), with or without a
    summary that indexes it; the chunk declares ``declared`` bytes uncompressed if given."""
    channel = Channel(id=1, schema_id=0, topic=FORCE, message_encoding="msgpack", metadata={})
    declared = len(chunk_records) if declared is None else declared
    chunk = Chunk(message_start_time=5, message_end_time=5, uncompressed_size=declared,
                  uncompressed_crc=zlib.crc32(chunk_records), compression="zstd",
                  data=zstandard.ZstdCompressor().compress(chunk_records))
    head = _MAGIC + _records(Header(profile="iorthand", library="crafted"))
    body = _records(chunk, DataEnd(data_section_crc=0))
    index = ChunkIndex(message_start_time=5, message_end_time=5, chunk_start_offset=len(head),
                       chunk_length=len(_records(chunk)), message_index_offsets={}, message_index_length=0,
                       compression="zstd", compressed_size=len(chunk.data), uncompressed_size=declared)
    tail = _records(channel, index) if summary else b""
    start = len(head) + len(body)
    return head + body + tail + _records(Footer(start if summary else 0, 0, 0)) + _MAGIC


_MAGIC = b"\x89MCAP0\r\n"


def _message(channel: int = 1, t: int = 5, data: bytes = b"") -> bytes:
    return struct.pack("<BQHIQQ", Opcode.MESSAGE, 22 + len(data), channel, 1, t, t) + data


@pytest.mark.parametrize("summary", [True, False])
def test_a_chunk_of_tiny_messages_is_refused_before_they_are_held(tmp_path: Path, summary: bool,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """Messages without data, held to be put in time order, take ~450 bytes each: a chunk of 64 MiB (the most
    allowed) holds 2 M of them, ~1 GB. Before, mcap's reader made all of a chunk's messages at once and the reader
    held them all, whatever the bound; here 300 000 (9 MiB), with the bound lowered to 16 MiB to keep the test
    small (before: ~200 MiB). The recorder ends a chunk every second at most, and writes at most ~100 000
    messages a second."""
    monkeypatch.setattr(reader, "MAX_OVERLAPPING_CHUNK_BYTES", 16 * 2**20)
    channel = _records(Channel(id=1, schema_id=0, topic=FORCE, message_encoding="msgpack", metadata={}))
    (tmp_path / "telemetry-0001.mcap").write_bytes(_file(channel + _message() * 300_000, summary))
    refused, peak = _peak(lambda: list(iter_records(tmp_path)))
    assert isinstance(refused, SegmentError), type(refused)
    assert re.search(r"telemetry-0001.mcap: the messages of the chunk at byte \d+ would take 16 MiB to hold",
                     str(refused)), refused
    assert peak < 40, f"{peak:.0f} MiB held to refuse it"  # (9 MiB of chunk, and up to 16 MiB held)


@pytest.mark.parametrize("summary", [True, False])
def test_records_a_chunk_does_not_hold_are_damage_not_skipped_or_parsed(tmp_path: Path, summary: bool) -> None:
    """mcap's reader skipped a record of another kind in a chunk without a word (the messages after it lost their
    place), and turned a channel's metadata of any size into a dict (4 M entries: ~600 MiB)."""
    metadata = _records(Metadata(name="m", metadata={"k": "v"}))
    path = tmp_path / "telemetry-0001.mcap"
    channel = _records(Channel(id=1, schema_id=0, topic=FORCE, message_encoding="msgpack", metadata={}))
    path.write_bytes(_file(channel + metadata + _message(), summary))
    with pytest.raises(CorruptSegment, match=r"telemetry-0001.mcap: the chunk at byte \d+ is damaged: the record "
                                             r"at byte \d+ of its data \(opcode 0x0c\) is none a chunk holds"):
        list(iter_records(tmp_path))
    huge = Channel(id=1, schema_id=0, topic=FORCE, message_encoding="msgpack",
                   metadata={f"{i:07d}": "" for i in range(4_000_000)})
    path.write_bytes(_file(_records(huge) + _message(), summary))
    del huge
    refused, peak = _peak(lambda: list(iter_records(tmp_path)))
    assert isinstance(refused, CorruptSegment), refused
    assert re.search(r"\(opcode 0x04\) is \d+ bytes long, which none of its kind is", str(refused)), refused
    assert peak < 140, f"{peak:.0f} MiB held to refuse it"  # (the 57 MiB chunk, compressed and not)


def test_a_metadata_record_larger_than_the_recorder_writes_is_not_parsed(tmp_path: Path) -> None:
    """A segment read front to back (no summary) parsed each record whole: 3 M metadata entries (45 MB) made a
    dict of ~400 MiB. Records other than chunks, messages and attachments are at most 4 MiB."""
    out = io.BytesIO()
    w = Writer(out, compression=CompressionType.ZSTD)
    w.start("iorthand", "crafted")
    w.add_message(w.register_channel(FORCE, "msgpack", 0), 5, b"\x80", 5, 1)
    w.add_metadata("m", {f"{i:07d}": "" for i in range(3_000_000)})
    w.finish()
    data = out.getvalue()
    (tmp_path / "telemetry-0001.mcap").write_bytes(data[:-8 - 20] + struct.pack("<Q", 0) + data[-8 - 12:])
    refused, peak = _peak(lambda: list(iter_records(tmp_path)))
    assert isinstance(refused, CorruptSegment), refused
    assert re.search(r"the record at byte \d+ says it is \d+ bytes long, more than any record of its kind "
                     r"\(metadata\) the recorder writes", str(refused)), refused
    assert peak < 8, f"{peak:.0f} MiB held to refuse it"
    # Cut inside it (a file without footer): to tell a torn tail from damage, its fields were parsed (~400 MiB).
    at = data.index(b"0000000") - 22  # the record's head: opcode, length, its name "m", the map's length, a key's
    (length,) = struct.unpack_from("<Q", data, at + 1)
    assert data[at] == Opcode.METADATA
    (tmp_path / "telemetry-0001.mcap").write_bytes(data[:at + 9 + length - 100])
    refused, peak = _peak(lambda: list(iter_records(tmp_path)))
    assert isinstance(refused, CorruptSegment) and "more than any record of its kind the recorder writes" in str(
        refused), refused
    assert peak < 8, f"{peak:.0f} MiB held to refuse it"


def test_a_message_on_a_channel_never_defined_is_damage_not_dropped(tmp_path: Path) -> None:
    """Front to back (a segment being written, or killed), a message whose channel the file never defined was
    left out without a word, by the reader and by the repair (which then deleted the file as it was)."""
    channel = _records(Channel(id=1, schema_id=0, topic=FORCE, message_encoding="msgpack", metadata={}))
    path = tmp_path / "telemetry-0001.mcap"
    data = _file(channel + _message(1, 5, b"\x80") + _message(9, 6, b"\x80"), summary=False)
    path.write_bytes(data)
    with pytest.raises(CorruptSegment, match=r"telemetry-0001.mcap: the chunk at byte \d+ holds a message on "
                                             r"channel 9, which the file does not define"):
        list(iter_records(tmp_path))
    res = repair_segment(path)
    assert "a message on channel 9" in res.damage and res.original is not None
    assert res.original.read_bytes() == data


def test_a_segment_that_is_no_regular_file_is_refused_by_name(tmp_path: Path) -> None:
    """A FIFO (opening it blocks), a link to /dev/zero (never ends), a link to nothing: before, left out without a
    word (the session read as if it had no such segment)."""
    (tmp_path / "telemetry-0001.mcap").write_bytes(_segment())
    for make, kind in [(lambda p: os.mkfifo(p), "a FIFO"), (lambda p: p.symlink_to("/dev/zero"), "a symbolic link"),
                       (lambda p: p.symlink_to(tmp_path / "gone"), "a symbolic link")]:
        odd = tmp_path / "telemetry-0002.mcap"
        make(odd)
        with pytest.raises(SegmentError, match=rf"telemetry-0002.mcap: {kind}, not a segment file: not read"):
            list(iter_records(tmp_path))
        # (the service's start-up looks at its Foxglove segments one by one)
        with pytest.raises(SegmentError, match=rf"telemetry-0002.mcap: {kind}, not a segment file: not read"):
            has_footer(odd)
        odd.unlink()
    assert len(list(iter_records(tmp_path))) == 100


def test_a_segment_linked_to_a_file_elsewhere_is_refused_by_name_unread(tmp_path: Path) -> None:
    """A segment that is a symbolic link to a readable file: before, followed. A key file's first 8 bytes were
    quoted in the refusal ("not an MCAP file (it begins b'-----BEG')"), and ``iorthand report`` wrote them into
    the session's manifest and report while it "repaired" the link into an empty segment; another session's
    segment was read as this session's own. The recorder writes no link: now every reader and the repair refuse
    it by name, without opening what it points to, and leave the session and the file as they were."""
    from iorthand_cloud.recorder import manifest as mf
    from iorthand_cloud.recorder.repair import repair_all, repair_if_crashed

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    key = elsewhere / "recorder.key"
    key.write_bytes(b"-----BEGIN PRIVATE KEY-----\nMIIEvQIBADANBgkqhkiG9w0BAQEFAASC\n")
    other = elsewhere / "telemetry-0001.mcap"  # another session's segment: readable, and not this session's
    other.write_bytes(other_data := _segment())
    session = tmp_path / "recordings" / "s1"
    session.mkdir(parents=True)
    mf.Manifest(session_id="s1").write(session)  # "recording": its recorder was killed, so a reader repairs it
    mf.release_writer_lock(session)
    (session / "telemetry-0001.mcap").write_bytes(_segment())
    link = session / "telemetry-0002.mcap"
    for target in (key, other):
        link.symlink_to(target)
        said = rf"{re.escape(str(link))}: a symbolic link, not a segment file: not read"
        for read in (lambda: list(iter_records(session)), lambda: segment_topics(session),
                     lambda: attachments(session), lambda: has_footer(link), lambda: repair_segment(link),
                     lambda: repair_if_crashed(session), lambda: reader.open_segment(link)):
            with pytest.raises(SegmentError, match=said) as refused:
                read()
            assert "-----BEG" not in str(refused.value)
        assert repair_all(session.parent) == {}  # (said in the log, the other sessions repaired)
        assert link.is_symlink() and sorted(p.name for p in session.iterdir()) == [
            ".writer.lock", "manifest.json", "telemetry-0001.mcap", "telemetry-0002.mcap"]
        assert b"-----BEG" not in (session / "manifest.json").read_bytes()
        link.unlink()
    assert key.read_bytes().startswith(b"-----BEGIN") and other.read_bytes() == other_data


def test_one_unreadable_session_does_not_stop_the_start_up_repair(tmp_path: Path) -> None:
    """The recorder repairs its unfinished sessions as it starts: one whose segment it must refuse (a chunk that
    declares 65 MiB) stopped the service before (SegmentError out of repair_all); now it is left as it is, said,
    and the others repaired."""
    from iorthand_cloud.recorder import manifest as mf
    from iorthand_cloud.recorder.repair import repair_all

    for name in ("a-bad", "b-good"):
        (tmp_path / name).mkdir()
        mf.Manifest(session_id=name).write(tmp_path / name)  # "recording": its recorder was killed
        mf.release_writer_lock(tmp_path / name)
        (tmp_path / name / "telemetry-0001.mcap").write_bytes(_segment())
    channel = _records(Channel(id=1, schema_id=0, topic=FORCE, message_encoding="msgpack", metadata={}))
    (tmp_path / "a-bad" / "telemetry-0002.mcap").write_bytes(_file(channel + _message(), declared=65 * 2**20))
    repaired = repair_all(tmp_path)
    assert list(repaired) == ["b-good"]
    assert mf.Manifest.read(tmp_path / "b-good").status == mf.RECOVERED
    assert mf.Manifest.read(tmp_path / "a-bad").status == mf.RECORDING


@pytest.mark.parametrize(("manifest", "said"), [
    ("[1, 2]", "the manifest is list, not dict"),
    ('{"session_id": "s", "keys": [1]}', "keys is a JSON list, not dict[str, KeyStats]"),
    ('{"session_id": "s", "keys": {"k": 5}}', "keys['k'] is int, not dict"),
    ('{"session_id": "s", "segments": [{"x": 1}]}', "a segment has no file, stream, compression, opened_t"),
    ('{"session_id": "s", "start_t": "soon"}', "start_t is a JSON str, not int"),
    ('{"session_id": "s", "keys": {"k": {"messages": "many"}}}', "messages is a JSON str, not int"),
    ('{"session_id": "s", "note": ' + "[" * 100_000 + "]" * 100_000 + "}", "not a manifest (RecursionError"),
])
def test_a_hostile_manifest_is_refused_by_name(tmp_path: Path, manifest: str, said: str) -> None:
    """Before: a TypeError, AttributeError or RecursionError out of Manifest.read, or later out of the report's
    sums (a traceback from ``iorthand report`` / ``export``)."""
    from iorthand_cloud.recorder.manifest import Manifest, ManifestError

    (tmp_path / "manifest.json").write_text(manifest)
    with pytest.raises(ManifestError) as refused:
        Manifest.read(tmp_path)
    assert str(refused.value).startswith(f"{tmp_path / 'manifest.json'}: ") and said in str(refused.value)


def test_the_recorder_starts_a_new_segment_before_its_summary_passes_what_a_reader_takes(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Small chunks (a flush every 20 ms, chunk_kb 4) and many keys fill a summary with chunk indexes long before a
    segment reaches its size bound: the writer's own files would be refused by its reader. It rolls over on its
    estimate of the summary instead (here scaled down 400 times: 40 kB), and every segment reads."""
    from iorthand_cloud.recorder import segments
    from iorthand_cloud.recorder.segments import COMPRESSION, TELEMETRY, ChannelSpec, Stream

    monkeypatch.setattr(segments, "SUMMARY_ROLL_BYTES", 40_000)
    stream = Stream("telemetry", tmp_path, COMPRESSION[TELEMETRY], max_bytes=256 * 2**20, max_seconds=3600,
                    chunk_size=4096)
    specs = [ChannelSpec(f"iorthand/sim1/sensor/k{i}", "json") for i in range(50)]
    estimates = []
    for flush in range(200):
        for i, spec in enumerate(specs):
            stream.write(spec, flush * 20_000_000 + i, flush, flush, b"{}")
        assert stream.current is not None
        estimates.append(stream.current.summary_estimate)
        stream.flush(fsync=False)
    stream.close(fsync=False)
    assert len(stream.closed) >= 4 and max(estimates) < 40_000 + 2 * (100 + 50 * 10)
    for path in stream.closed:
        with path.open("rb") as f:
            index = reader.read_index(f, path)
        assert index is not None and index.chunks_indexed >= 1
        data = path.read_bytes()
        summary_start = struct.unpack_from("<Q", data, len(data) - 8 - 29 + 9)[0]  # the footer, then the magic
        assert len(data) - 8 - 29 - summary_start < 40_000 + 50 * 200  # its chunk indexes, channels, statistics
