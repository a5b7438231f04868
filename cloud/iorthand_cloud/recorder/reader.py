"""Reading a session: its segments' messages merged in receive-time order, with decoding for analysis."""

from __future__ import annotations

import bisect
import contextlib
import dataclasses
import heapq
import io
import os
import struct
import zlib
from array import array
from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import msgpack
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.stream_reader import CRCValidationError, breakup_chunk
from mcap.summary import Summary

from iorthand_cloud.recorder.manifest import Manifest
from iorthand_cloud.recorder.segments import MALFORMED_META

# What the recorder writes is bounded (a chunk holds at most chunk_kb, at most 32 MiB, plus one message of at most
# 8 MiB), and reading holds at once only the chunks whose times overlap. A file beyond these bounds was not written
# by the recorder: a few kB of zstd can declare gigabytes, and reading it would exhaust the machine's memory.
MAX_CHUNK_BYTES = 64 * 2**20
MAX_OVERLAPPING_CHUNK_BYTES = 256 * 2**20
# The longest record the recorder writes: a chunk (its data, uncompressed at worst, and its fields); a record
# (an attachment: the calibration files) is far shorter.
MAX_RECORD_BYTES = MAX_CHUNK_BYTES + 2**20


class SegmentError(ValueError):
    """A segment that cannot be read safely; the message names the file and what was wrong."""


class CorruptSegment(SegmentError):
    """A segment whose bytes are not what was written (a CRC that does not match, a record that cannot be
    parsed); the message names the file and where."""


def check_chunks(path: Path, chunks: Collection[ChunkIndex]) -> None:
    """Refuses a segment whose chunks would take more memory to read than any the recorder writes: one chunk
    over :data:`MAX_CHUNK_BYTES` uncompressed, or chunks whose time ranges overlap (read together, in time order)
    over :data:`MAX_OVERLAPPING_CHUNK_BYTES` together."""
    for c in chunks:
        _check_chunk_size(path, f"the chunk at byte {c.chunk_start_offset}", c.uncompressed_size)
    held, most = 0, 0
    # Every chunk's start before any end at the same time: touching chunks count as overlapping (the stricter).
    for _t, delta in sorted([(c.message_start_time, c.uncompressed_size) for c in chunks]
                            + [(c.message_end_time, -c.uncompressed_size) for c in chunks],
                            key=lambda e: (e[0], e[1] < 0)):
        held += delta
        most = max(most, held)
    if most > MAX_OVERLAPPING_CHUNK_BYTES:
        raise SegmentError(f"{path}: chunks whose times overlap hold {most / 2**20:.0f} MiB uncompressed, more "
                           f"than the {MAX_OVERLAPPING_CHUNK_BYTES // 2**20} MiB a recording's segment needs: "
                           "not read (it was not written by the recorder)")


def _check_chunk_size(path: Path, chunk: str, size: int) -> None:
    if size > MAX_CHUNK_BYTES:
        raise SegmentError(f"{path}: {chunk} declares {size / 2**20:.0f} MiB uncompressed, more "
                           f"than the {MAX_CHUNK_BYTES // 2**20} MiB of any chunk the recorder writes: not read "
                           "(it was not written by the recorder)")


@dataclass(frozen=True)
class Record:
    key: str
    log_time: int  # receive time at the recorder, ns
    publish_time: int  # source time, ns
    sequence: int
    data: bytes
    malformed: bool
    stream: str


def session_dir(path: str | Path) -> Path:
    """A session folder from a path to it or to its manifest."""
    p = Path(path)
    return p.parent if p.is_file() else p


def segment_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.glob("*.mcap") if p.is_file())


def segment_topics(folder: str | Path) -> set[str]:
    """The topics of a session's segments' channels: from the summary of a finished segment, from a front to
    back read of one without (a segment being written)."""
    topics: set[str] = set()
    for path in segment_files(session_dir(folder)):
        with path.open("rb") as f:
            summary = _summary(f)
            if summary is not None and summary.channels:
                topics.update(c.topic for c in summary.channels.values())
                continue
            f.seek(0)
            with contextlib.suppress(TornTail):  # (the channels before it are kept)
                for record in stream_records(f, path):
                    if isinstance(record, Channel):
                        topics.add(record.topic)
    return topics


def _summary(f: BinaryIO) -> Summary | None:
    """A segment's summary; None without one, or with no footer yet (a segment being written) or a torn one."""
    try:
        return make_reader(f).get_summary()
    except Exception:
        return None


def stream_of(path: Path) -> str:
    """``video-0003.mcap`` → ``video``."""
    return path.name.rsplit("-", 1)[0]


def _iter_file(path: Path, start: int | None, end: int | None,
               topics: Collection[str] | None = None) -> Iterator[Record]:
    stream = stream_of(path)
    with path.open("rb") as f:
        summary = _summary(f)
        if summary is None or not summary.chunk_indexes:
            # No index to seek with (mcap's own reader would then decompress every chunk unchecked): front to
            # back, each chunk's own size checked.
            f.seek(0)
            yield from _iter_linear(f, path, stream, start, end, topics)
            return
        yield from _iter_indexed(f, path, stream, summary, start, end, topics)


def _iter_indexed(f: BinaryIO, path: Path, stream: str, summary: Summary, start: int | None, end: int | None,
                  topics: Collection[str] | None) -> Iterator[Record]:
    """The messages of a finished segment in receive-time order, through its chunk index: only the chunks whose
    times and channels are wanted are read, each checked (size, CRC) before it is used. Chunks whose times
    overlap are decompressed together, as mcap's reader does; those that follow one another, one at a time."""
    chunks = [c for c in summary.chunk_indexes if _chunk_wanted(c, summary, start, end, topics)]
    # The index's sizes are the chunks' own claims repeated: a crafted index may understate them.
    check_chunks(path, [dataclasses.replace(c, uncompressed_size=max(c.uncompressed_size, _declared_size(f, path, c)))
                        for c in chunks])
    # Ordered by (time, chunk offset, position in the chunk); a chunk enters at its first message's time.
    queue: list[tuple[int, int, int, Any]] = [(c.message_start_time, c.chunk_start_offset, -1, c) for c in chunks]
    heapq.heapify(queue)
    while queue:
        _t, offset, index, item = heapq.heappop(queue)
        if index >= 0:
            yield item
            continue
        f.seek(offset)
        chunk = _read_chunk(f, path, offset)
        for i, record in enumerate(_chunk_records(path, f"the chunk at byte {offset}", chunk)):
            if not isinstance(record, Message):
                continue
            channel = summary.channels.get(record.channel_id)
            if channel is None:
                raise CorruptSegment(f"{path}: the chunk at byte {offset} holds a message on channel "
                                     f"{record.channel_id}, which the file does not define")
            if ((start is not None and record.log_time < start) or (end is not None and record.log_time >= end)
                    or (topics is not None and channel.topic not in topics)):
                continue
            heapq.heappush(queue, (record.log_time, offset, i, _record(channel, record, stream)))


def _chunk_wanted(c: ChunkIndex, summary: Summary, start: int | None, end: int | None,
                  topics: Collection[str] | None) -> bool:
    if (start is not None and c.message_end_time < start) or (end is not None and c.message_start_time >= end):
        return False
    if topics is None or not c.message_index_offsets:  # (without message indexes, only reading tells)
        return True
    return any(ch in summary.channels and summary.channels[ch].topic in topics for ch in c.message_index_offsets)


# A chunk record: opcode, record length, message start and end times, uncompressed size, CRC, compression.
_CHUNK_HEAD = struct.Struct("<BQQQQII")


def _declared_size(f: BinaryIO, path: Path, c: ChunkIndex) -> int:
    """The largest size the chunk an index entry points to declares, read from its head alone: its own
    uncompressed size, and its zstd frame's content size."""
    f.seek(c.chunk_start_offset)
    head = f.read(_CHUNK_HEAD.size)
    if len(head) < _CHUNK_HEAD.size or head[0] != Opcode.CHUNK:
        raise CorruptSegment(f"{path}: the chunk index points to byte {c.chunk_start_offset}, where no chunk is")
    *_, size, _crc, name_len = _CHUNK_HEAD.unpack(head)
    name = f.read(min(name_len, 16))
    f.read(8)  # the compressed data's length
    where = f"the chunk at byte {c.chunk_start_offset}"
    _check_chunk_size(path, where, size)
    frame = _zstd_content_size(path, where, f.read(18)) if name == b"zstd" else 0
    _check_chunk_size(path, f"{where} (its zstd frame)", frame)
    return max(size, frame)


def _zstd_content_size(path: Path, where: str, data: bytes) -> int:
    """What a zstd frame says it holds (0 when it does not say): zstd allocates that much, whatever the chunk
    around it declares."""
    try:
        size = zstandard.frame_content_size(data)
    except zstandard.ZstdError as exc:
        raise CorruptSegment(f"{path}: {where} is damaged: {exc}") from None
    return max(size, 0)


def _read_chunk(f: BinaryIO, path: Path, offset: int) -> Chunk:
    try:
        if f.read(1) != bytes([Opcode.CHUNK]):
            raise CorruptSegment(f"{path}: the chunk index points to byte {offset}, where no chunk is")
        f.read(8)
        return Chunk.read(ReadDataStream(f))
    except (McapError, struct.error, UnicodeDecodeError) as exc:
        raise CorruptSegment(f"{path}: the chunk at byte {offset} is damaged: {exc!r}") from None


def _chunk_records(path: Path, where: str, chunk: Chunk) -> list[Any]:
    """The records of a chunk, its size checked before it is decompressed and its CRC after."""
    _check_chunk_size(path, where, chunk.uncompressed_size)
    if chunk.compression not in ("", "zstd"):
        raise SegmentError(f"{path}: {where} is compressed with {chunk.compression[:16]!r}, which the recorder "
                           "never uses: not read (it was not written by the recorder)")
    if chunk.compression == "zstd":
        frame = _zstd_content_size(path, where, chunk.data[:18])
        _check_chunk_size(path, f"{where} (its zstd frame)", frame)
        if frame and frame != chunk.uncompressed_size:
            raise SegmentError(f"{path}: {where} declares {chunk.uncompressed_size} bytes uncompressed, its zstd "
                               f"frame {frame}: not read (it was not written by the recorder)")
    try:
        return breakup_chunk(chunk, validate_crc=True)
    except CRCValidationError as exc:
        raise CorruptSegment(f"{path}: {where} is damaged (its CRC does not match: {exc})") from None
    except Exception as exc:  # zstd errors, records cut short: the bytes are not what was written
        raise CorruptSegment(f"{path}: {where} is damaged: {exc!r}") from None


def _record(channel: Channel, message: Message, stream: str) -> Record:
    return Record(key=channel.topic, log_time=message.log_time, publish_time=message.publish_time,
                  sequence=message.sequence, data=message.data,
                  malformed=channel.metadata.get(MALFORMED_META) == "true", stream=stream)


class TornTail(Exception):
    """The file ends inside a record: what a killed writer leaves (everything before it is whole)."""


_MAGIC = b"\x89MCAP0\r\n"
_HEAD = struct.Struct("<BQ")  # a record's opcode and the length of what follows
# How each kind of record is read (a message's data is what its length leaves after its fields).
_READERS: dict[int, Callable[[ReadDataStream], Any]] = {
    Opcode.HEADER: Header.read, Opcode.FOOTER: Footer.read, Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read, Opcode.CHUNK: Chunk.read, Opcode.MESSAGE_INDEX: MessageIndex.read,
    Opcode.CHUNK_INDEX: ChunkIndex.read, Opcode.ATTACHMENT: Attachment.read,
    Opcode.ATTACHMENT_INDEX: AttachmentIndex.read, Opcode.STATISTICS: Statistics.read,
    Opcode.METADATA: Metadata.read, Opcode.METADATA_INDEX: MetadataIndex.read,
    Opcode.SUMMARY_OFFSET: SummaryOffset.read, Opcode.DATA_END: DataEnd.read,
}
_PARSE_ERRORS = (McapError, struct.error, UnicodeDecodeError, ValueError)


class _Exact(ReadDataStream):
    """mcap's stream, which returns a short read as if it were whole: here running short is an error."""

    def read(self, length: int) -> bytes:
        data = super().read(length)
        if len(data) < length:
            raise EndOfFile()
        return data


def _parse(opcode: int, body: bytes, length: int) -> tuple[Any, int]:
    """The record ``body`` holds and how many of its bytes the record's own fields take."""
    stream = _Exact(io.BytesIO(body))
    record = Message.read(stream, length) if opcode == Opcode.MESSAGE else _READERS[opcode](stream)
    return record, stream.count


def _heads(f: Any, path: Path, size: int) -> Iterator[tuple[int, int, int]]:
    """(offset, opcode, length) of each record of the first ``size`` bytes of an MCAP file that the file holds
    whole, front to back up to the footer. Raises :class:`TornTail` where the file ends inside a record,
    :class:`CorruptSegment` where a record's length runs past the end but the record is not cut short (see
    :func:`_past_the_end`)."""
    fd = f.fileno()
    magic = os.pread(fd, len(_MAGIC), 0)
    if magic != _MAGIC:
        if len(magic) < len(_MAGIC) and _MAGIC.startswith(magic):
            raise TornTail(f"{path}: readable up to byte 0 of {size}")
        raise CorruptSegment(f"{path}: not an MCAP file (it begins {magic!r})")
    at = len(_MAGIC)
    while at < size:
        head = os.pread(fd, _HEAD.size, at)
        if len(head) < _HEAD.size:
            raise TornTail(f"{path}: readable up to byte {at} of {size}")
        opcode, length = _HEAD.unpack(head)
        if at + _HEAD.size + length > size:
            raise _past_the_end(f, path, at, opcode, length, size)
        yield at, opcode, length
        if opcode == Opcode.FOOTER:
            return
        at += _HEAD.size + length


def _past_the_end(f: Any, path: Path, at: int, opcode: int, length: int, size: int) -> Exception:
    """The verdict on a record whose length runs past the end of the file. A torn tail (a killed writer: the
    file ends inside the last record, which was being written; what is dropped was never whole) only when the
    record is cut short by its own fields too, the file holds no more after its head than the longest record
    the recorder writes, and no whole chunk follows its head. Otherwise its length is damaged (a bit flip), and
    the records after it may be whole: :class:`CorruptSegment`, so that a repair keeps the file as it was."""
    held = size - at - _HEAD.size
    why = ""
    if held > MAX_RECORD_BYTES:
        why = f"the file holds {held} bytes after its head, more than any record the recorder writes"
    elif opcode != Opcode.MESSAGE and opcode not in _READERS:
        why = f"its kind (opcode {opcode:#04x}) is none that MCAP knows"
    else:
        body = os.pread(f.fileno(), held, at + _HEAD.size)
        if opcode != Opcode.MESSAGE:  # (a message's own length is the record's: nothing to compare)
            with contextlib.suppress(*_PARSE_ERRORS):
                _record, used = _parse(opcode, body, held)
                why = f"its own fields end after {used} bytes, inside the file"
        if not why:
            chunk_at = _whole_chunk_in(body)
            if chunk_at is not None:
                why = f"a whole chunk follows its head at byte {at + _HEAD.size + chunk_at}"
    if not why:
        return TornTail(f"{path}: readable up to byte {at} of {size}")
    return CorruptSegment(f"{path}: the record at byte {at} says it is {length} bytes long, past the end of the "
                          f"file ({size} bytes), but {why}: its length is damaged, and what follows it may be whole")


def _whole_chunk_in(data: bytes) -> int | None:
    """Where in ``data`` a whole chunk record begins (its fields add up to its length and it ends inside
    ``data``), or None. A chance match in compressed bytes would need 8 length bytes that fit and fields that
    add up to them: far rarer than the one bit flip this looks for."""
    at = data.find(bytes([Opcode.CHUNK]))
    while at >= 0:
        if at + _HEAD.size <= len(data):
            _op, length = _HEAD.unpack_from(data, at)
            end = at + _HEAD.size + length
            if end <= len(data):
                with contextlib.suppress(*_PARSE_ERRORS):
                    chunk, used = _parse(Opcode.CHUNK, data[at + _HEAD.size:end], length)
                    if used == length and chunk.compression in ("", "zstd"):
                        return at
        at = data.find(bytes([Opcode.CHUNK]), at + 1)
    return None


def _top_records(f: Any, path: Path, size: int) -> Iterator[tuple[int, Any]]:
    """(offset, record) of each top-level record of the first ``size`` bytes of an MCAP file. Every record's
    length must be what its fields take: mcap's own reader skips any excess as padding, so a length made larger
    by a bit flip silently dropped the records it covered."""
    for at, opcode, length in _heads(f, path, size):
        where = f"the record at byte {at}"
        if opcode != Opcode.MESSAGE and opcode not in _READERS:
            raise CorruptSegment(f"{path}: {where} is damaged: its kind (opcode {opcode:#04x}) is none that MCAP "
                                 "knows")
        if length > MAX_RECORD_BYTES:
            raise CorruptSegment(f"{path}: {where} says it is {length} bytes long, more than any record the "
                                 "recorder writes: its length is damaged (or the recorder did not write it)")
        f.seek(at + _HEAD.size)
        try:
            record, used = _parse(opcode, f.read(length), length)
        except EndOfFile:
            raise CorruptSegment(f"{path}: {where} says it is {length} bytes long, its own fields more: its "
                                 "length is damaged, and what follows it may be whole") from None
        except _PARSE_ERRORS as exc:
            raise CorruptSegment(f"{path}: {where} is damaged: {exc!r}") from None
        if used != length:
            raise CorruptSegment(f"{path}: {where} says it is {length} bytes long, its own fields {used}: its "
                                 "length is damaged, and what follows it may be whole")
        if isinstance(record, DataEnd) and record.data_section_crc:
            _check_data_crc(f, path, at, record.data_section_crc)
        yield at, record


def _check_data_crc(f: Any, path: Path, end: int, expected: int) -> None:
    """The CRC of everything before the data end record (written by writers that compute it)."""
    crc, at = 0, 0
    while at < end:
        block = os.pread(f.fileno(), min(2**20, end - at), at)
        if not block:
            break
        crc, at = zlib.crc32(block, crc), at + len(block)
    if crc != expected:
        raise CorruptSegment(f"{path}: the data section is damaged (its CRC does not match: {crc:#010x}, "
                             f"{expected:#010x} written)")


def stream_records(f: Any, path: Path) -> Iterator[Any]:
    """The records of an MCAP file read front to back (one without a footer too), each chunk's size checked
    before it is decompressed and every CRC checked. Raises :class:`TornTail` where the file ends inside a
    record, :class:`CorruptSegment` at a complete record that is damaged (the rest of the file may be good)."""
    for at, record in _top_records(f, path, os.fstat(f.fileno()).st_size):
        if isinstance(record, Chunk):
            yield from _chunk_records(path, f"the chunk at byte {at}", record)
        else:
            yield record


# Memory a message held for reordering takes beyond its data (the record, its place in the heap).
_HELD_OVERHEAD = 200


def _start_times(f: Any, path: Path, size: int) -> array[int]:
    """The first receive time of each chunk and loose message of a file, in file order, from their heads alone
    (nothing decompressed: 8 bytes per record). Where the file ends early or is damaged, as far as it goes
    (reading it stops there too)."""
    out: array[int] = array("Q")
    fd = f.fileno()
    with contextlib.suppress(TornTail, CorruptSegment):
        for at, opcode, _length in _heads(f, path, size):
            if opcode == Opcode.CHUNK:  # message start time, first of the chunk's fields
                out.extend(struct.unpack("<Q", os.pread(fd, 8, at + _HEAD.size).ljust(8, b"\0")))
            elif opcode == Opcode.MESSAGE:  # channel id, sequence, then log time
                out.extend(struct.unpack("<Q", os.pread(fd, 8, at + _HEAD.size + 6).ljust(8, b"\0")))
    return out


def _iter_linear(f: Any, path: Path, stream: str, start: int | None, end: int | None,
                 topics: Collection[str] | None = None) -> Iterator[Record]:
    """The messages of a segment read front to back (one without a footer or without a chunk index), in
    receive-time order (a torn tail is left out). A message is held only until no later chunk can start before
    it (the heads say when each starts): the recorder writes in time order, so one chunk at a time is held;
    a file that would hold more than :data:`MAX_OVERLAPPING_CHUNK_BYTES` is refused (before, the whole file
    was decompressed into memory to be sorted, however many chunks of up to 64 MiB each it declared)."""
    size = os.fstat(f.fileno()).st_size
    later = _start_times(f, path, size)
    for i in range(len(later) - 2, -1, -1):  # the earliest start of each record and all after it
        later[i] = min(later[i], later[i + 1])
    channels: dict[int, Channel] = {}
    held: list[tuple[int, int, Record]] = []  # (receive time, file order, record): a heap
    held_bytes, order, timed = 0, 0, 0
    try:
        for at, top in _top_records(f, path, size):
            inner = _chunk_records(path, f"the chunk at byte {at}", top) if isinstance(top, Chunk) else [top]
            kept = [r for r in (_keep(x, channels, stream, start, end, topics) for x in inner) if r is not None]
            if not isinstance(top, (Chunk, Message)):
                continue
            timed += 1
            mark = later[timed] if timed < len(later) else None
            if not held:  # (the usual case, in time order: the chunk's messages go out without the heap)
                kept.sort(key=lambda r: r.log_time)
                n = len(kept) if mark is None else bisect.bisect_right(kept, mark, key=lambda r: r.log_time)
                yield from kept[:n]
                kept = kept[n:]
            for record in kept:
                heapq.heappush(held, (record.log_time, order, record))
                order += 1
                held_bytes += len(record.data) + _HELD_OVERHEAD
            while held and (mark is None or held[0][0] <= mark):
                held_bytes -= len(held[0][2].data) + _HELD_OVERHEAD
                yield heapq.heappop(held)[2]
            if held_bytes > MAX_OVERLAPPING_CHUNK_BYTES:
                raise SegmentError(f"{path}: its chunks are out of time order and read in order would hold "
                                   f"{held_bytes / 2**20:.0f} MiB at byte {at}, more than the "
                                   f"{MAX_OVERLAPPING_CHUNK_BYTES // 2**20} MiB a recording's segment needs: not "
                                   "read (it was not written by the recorder)")
    except TornTail:  # everything before it was taken
        pass
    while held:
        yield heapq.heappop(held)[2]


def _keep(record: Any, channels: dict[int, Channel], stream: str, start: int | None, end: int | None,
          topics: Collection[str] | None) -> Record | None:
    if isinstance(record, Channel):
        channels[record.id] = record
    elif isinstance(record, Message) and record.channel_id in channels:
        if (start is not None and record.log_time < start) or (end is not None and record.log_time >= end):
            return None
        ch = channels[record.channel_id]
        if topics is not None and ch.topic not in topics:
            return None
        return _record(ch, record, stream)
    return None


def iter_records(folder: str | Path, start: int | None = None, end: int | None = None,
                 streams: Collection[str] | None = None, topics: Collection[str] | None = None) -> Iterator[Record]:
    """Every message of a session in receive-time order; ``start``/``end`` are receive times in ns; ``streams``
    (:data:`~iorthand_cloud.recorder.segments.VIDEO`, ``TELEMETRY``) reads only those streams' segments, and
    ``topics`` only those keys."""
    files = [p for p in segment_files(session_dir(folder)) if streams is None or stream_of(p) in streams]
    return heapq.merge(*(_iter_file(p, start, end, topics) for p in files), key=lambda r: r.log_time)


def read_manifest(folder: str | Path) -> Manifest:
    return Manifest.read(session_dir(folder))


def decode_map(data: bytes) -> dict[str, Any] | None:
    """The msgpack map of a payload, or None (no validation: reports tolerate what the decoder would reject
    only after the decoder has had its say — callers use protocol classes where validation matters)."""
    try:
        out = msgpack.unpackb(data, raw=False)
    except Exception:  # garbage of any kind is simply not a map
        return None
    return out if isinstance(out, dict) else None


def attachments(folder: str | Path) -> dict[str, bytes]:
    out: dict[str, bytes] = {}
    for path in segment_files(session_dir(folder)):
        with path.open("rb") as f:
            for att in make_reader(f).iter_attachments():
                out.setdefault(att.name, att.data)
    return out
