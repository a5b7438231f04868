"""Reading a session: its segments' messages merged in receive-time order, with decoding for analysis."""

from __future__ import annotations

import bisect
import contextlib
import dataclasses
import errno
import heapq
import io
import itertools
import os
import stat
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

from iorthand_cloud.recorder.manifest import Manifest
from iorthand_cloud.recorder.segments import MALFORMED_META, MAX_SUMMARY_BYTES

# What the recorder writes is bounded (a chunk holds at most chunk_kb, at most 32 MiB, plus one message of at most
# 8 MiB), and reading holds at once only the chunks whose times overlap. A file beyond these bounds was not written
# by the recorder: a few kB of zstd can declare gigabytes, and reading it would exhaust the machine's memory.
MAX_CHUNK_BYTES = 64 * 2**20
MAX_OVERLAPPING_CHUNK_BYTES = 256 * 2**20
# The longest record the recorder writes: a chunk (its data, uncompressed at worst, and its fields); a record
# (an attachment: the calibration files) is far shorter.
MAX_RECORD_BYTES = MAX_CHUNK_BYTES + 2**20
# A calibration file the recorder attaches (refused beyond it: service.RecorderService), and all of a session's
# attachments read together (:func:`attachments`): a camera's or a hand-eye calibration is a few kB.
MAX_ATTACHMENT_BYTES = 16 * 2**20
MAX_ATTACHMENTS_BYTES = 64 * 2**20
# The longest record that is not a chunk, message or attachment (a schema, channel, metadata or index record):
# the recorder's are below 100 kB (a Foxglove schema; a chunk index or statistics record naming every channel).
# mcap's reader turns a map's entries into a dict at ~10 times their size on disk.
MAX_SMALL_RECORD_BYTES = 4 * 2**20


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
    _check_overlap(path, array("Q", (c.message_start_time for c in chunks)),
                   array("Q", (c.message_end_time for c in chunks)), array("Q", (c.uncompressed_size for c in chunks)))


def _check_overlap(path: Path, starts: array[int], ends: array[int], sizes: array[int]) -> None:
    """:func:`check_chunks`' bound on chunks whose times overlap, from the chunks' times and sizes alone."""
    by_start = sorted(range(len(starts)), key=starts.__getitem__)
    by_end = sorted(range(len(ends)), key=ends.__getitem__)
    held, most, ended = 0, 0, 0
    for i in by_start:
        # A chunk leaves only before the chunks that start after its end: touching chunks count as overlapping
        # (the stricter).
        while ended < len(by_end) and ends[by_end[ended]] < starts[i]:
            held -= sizes[by_end[ended]]
            ended += 1
        held += sizes[i]
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
    """A session folder's segments, in order. A ``*.mcap`` there that is not a regular file is refused by name,
    unread: a FIFO (opening it blocks), a device (it may never end), and a symbolic link, whatever it points to.
    The recorder writes no link; one brings a file from elsewhere into the session, which reading would take as
    its own (another session's segment) or quote in its refusal (the first bytes of a key file, in a report and
    a manifest). Before, FIFOs and devices were left out without a word and links followed. :func:`open_segment`
    checks the same on the file it opens."""
    out = []
    for path in sorted(folder.glob("*.mcap")):
        try:
            mode = path.lstat().st_mode
        except OSError as exc:
            raise SegmentError(f"{path}: cannot be read ({exc.strerror})") from None
        if not stat.S_ISREG(mode):
            raise SegmentError(_not_a_segment(path, mode))
        out.append(path)
    return out


def _not_a_segment(path: Path, mode: int) -> str:
    kind = ("a symbolic link" if stat.S_ISLNK(mode) else "a directory" if stat.S_ISDIR(mode) else
            "a FIFO" if stat.S_ISFIFO(mode) else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else
            "not a file")
    return f"{path}: {kind}, not a segment file: not read"


def open_segment(path: Path) -> BinaryIO:
    """A segment opened for reading, or :class:`SegmentError` by name when it is not a regular file, unread: the
    check of :func:`segment_files` made on the file opened itself (a link put in a segment's place after the
    folder was listed is not followed; a FIFO does not block the open)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError as exc:
        if exc.errno == errno.ELOOP:  # O_NOFOLLOW's answer for a link
            raise SegmentError(_not_a_segment(path, stat.S_IFLNK)) from None
        raise
    f = os.fdopen(fd, "rb")
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        f.close()
        raise SegmentError(_not_a_segment(path, mode))
    return f


def segment_topics(folder: str | Path) -> set[str]:
    """The topics of a session's segments' channels: from the summary of a finished segment, from a front to
    back read of one without (a segment being written)."""
    topics: set[str] = set()
    for path in segment_files(session_dir(folder)):
        with open_segment(path) as f:
            index = _index(f, path, chunks=False)
            if index is not None and index.channels:
                topics.update(c.topic for c in index.channels.values())
                continue
            f.seek(0)
            with contextlib.suppress(TornTail):  # (the channels before it are kept)
                for record in stream_records(f, path):
                    if isinstance(record, Channel):
                        topics.add(record.topic)
    return topics


class NoFooter(Exception):
    """The file does not end with a footer: a segment being written, or one its writer left (killed)."""


@dataclass
class SegmentIndex:
    """What reading takes from a segment's summary, held compactly: its channels (each with its topic, encoding
    and the malformed mark only: a crafted channel's metadata may be any size), the chunks wanted (start and end
    times, offset and uncompressed size, in summary order), how many chunks it indexes in all, and where its
    attachment index records are."""

    channels: dict[int, Channel]
    chunks_indexed: int = 0
    starts: array[int] = dataclasses.field(default_factory=lambda: array("Q"))
    ends: array[int] = dataclasses.field(default_factory=lambda: array("Q"))
    offsets: array[int] = dataclasses.field(default_factory=lambda: array("Q"))
    sizes: array[int] = dataclasses.field(default_factory=lambda: array("Q"))
    attachment_indexes: array[int] = dataclasses.field(default_factory=lambda: array("Q"))


# A footer record (opcode, length, summary start, summary offset start, summary CRC), then the closing magic.
_FOOTER = struct.Struct("<BQQQI")
# What a summary holds (the MCAP specification): a chunk or message in one is not read.
_SUMMARY_RECORDS = frozenset({Opcode.SCHEMA, Opcode.CHANNEL, Opcode.CHUNK_INDEX, Opcode.ATTACHMENT_INDEX,
                              Opcode.METADATA_INDEX, Opcode.STATISTICS, Opcode.SUMMARY_OFFSET})


def read_index(f: Any, path: Path, start: int | None = None, end: int | None = None,
               topics: Collection[str] | None = None, chunks: bool = True) -> SegmentIndex | None:
    """A finished segment's summary, read in bounded memory: its size checked (:data:`MAX_SUMMARY_BYTES`), its
    CRC, each record's kind, size and fields; the chunks kept are those whose times (``start``/``end``) and
    channels (``topics``) are wanted (none unless ``chunks``). None when the footer says there is no summary.
    Raises :class:`NoFooter`, :class:`CorruptSegment` (a damaged summary: the data section may be whole), or
    :class:`SegmentError` (a summary the recorder does not write)."""
    fd = f.fileno()
    size = os.fstat(fd).st_size
    footer_at = size - _FOOTER.size - len(_MAGIC)
    tail = os.pread(fd, _FOOTER.size + len(_MAGIC), footer_at) if footer_at >= len(_MAGIC) else b""
    if len(tail) != _FOOTER.size + len(_MAGIC) or tail[_FOOTER.size:] != _MAGIC:
        raise NoFooter(f"{path}: no footer")
    opcode, length, summary_start, _offsets_start, crc = _FOOTER.unpack_from(tail)
    if opcode != Opcode.FOOTER or length != _FOOTER.size - _HEAD.size:
        raise NoFooter(f"{path}: no footer")
    if summary_start == 0:
        return None
    if not len(_MAGIC) <= summary_start <= footer_at:
        raise CorruptSegment(f"{path}: its footer says its summary begins at byte {summary_start}, outside the "
                             f"file's {footer_at} bytes before it: the footer is damaged")
    if footer_at - summary_start > MAX_SUMMARY_BYTES:
        raise SegmentError(f"{path}: its summary is {(footer_at - summary_start) / 2**20:.0f} MiB, more than the "
                           f"{MAX_SUMMARY_BYTES // 2**20} MiB of any the recorder writes: not read (it was not "
                           "written by the recorder)")
    if crc:
        got = _crc_of(fd, summary_start, footer_at + _FOOTER.size - 4)
        if got != crc:
            raise CorruptSegment(f"{path}: its summary is damaged (its CRC does not match: {got:#010x}, "
                                 f"{crc:#010x} written)")
    index = SegmentIndex(channels={})
    # Each chunk index points to a chunk of its own in the data section: no more of them than it can hold, so the
    # work of reading a summary is bounded by the data it indexes, not by what the summary claims.
    most_chunks = (summary_start - len(_MAGIC)) // _CHUNK_MIN_BYTES
    for at, opcode, body in _summary_records(fd, path, summary_start, footer_at):
        if opcode == Opcode.CHUNK_INDEX:  # (the many: checked by their fields alone, kept in the second pass)
            if index.chunks_indexed == most_chunks:
                raise SegmentError(f"{path}: its summary indexes more chunks than the {summary_start} bytes before "
                                   f"it can hold ({most_chunks}, of {_CHUNK_MIN_BYTES} bytes at least each): not "
                                   "read (it was not written by the recorder)")
            _chunk_index(path, at, body)
            index.chunks_indexed += 1
            continue
        record = _summary_parse(path, at, opcode, body)
        if isinstance(record, Channel):
            index.channels[record.id] = _slim(record)
        elif isinstance(record, AttachmentIndex):
            index.attachment_indexes.append(at)
    # A second pass, once every channel is known (the recorder writes them first, a crafted file need not).
    for at, opcode, body in _summary_records(fd, path, summary_start, footer_at) if chunks else ():
        if opcode == Opcode.CHUNK_INDEX:
            first, last, offset, size, channel_map = _chunk_index(path, at, body)
            if _chunk_wanted(first, last, channel_map, index.channels, start, end, topics):
                index.starts.append(first)
                index.ends.append(last)
                index.offsets.append(offset)
                index.sizes.append(size)
    return index


def _crc_of(fd: int, begin: int, end: int) -> int:
    crc, at = 0, begin
    while at < end:
        block = os.pread(fd, min(2**20, end - at), at)
        if not block:
            break
        crc, at = zlib.crc32(block, crc), at + len(block)
    return crc


# A summary is read in blocks of this size (a record at a time took three reads each: most of the time of a
# large one went to them).
_SUMMARY_BLOCK = 2**20


def _summary_records(fd: int, path: Path, begin: int, end: int) -> Iterator[tuple[int, int, bytes]]:
    """(offset, opcode, body) of each record of a summary section, read in blocks, each checked: a kind a summary
    holds, a length within the section and below :data:`MAX_SMALL_RECORD_BYTES` (its fields are the caller's to
    check: :func:`_summary_parse`, :func:`_chunk_index`)."""
    block, block_at = b"", begin  # the bytes of the section from block_at on, as far as read
    at = begin
    while at < end:
        if at + _HEAD.size > end:
            raise CorruptSegment(f"{path}: its summary is damaged: it ends inside the record at byte {at}")
        if at + _HEAD.size > block_at + len(block):
            block, block_at = _summary_block(fd, path, at, end, _HEAD.size)
        opcode, length = _HEAD.unpack_from(block, at - block_at)
        if opcode not in _SUMMARY_RECORDS:
            kind = Opcode(opcode).name.lower().replace("_", " ") if opcode in _READERS or opcode == Opcode.MESSAGE \
                else f"opcode {opcode:#04x}"
            raise SegmentError(f"{path}: its summary holds a record of a kind a summary does not hold ({kind}) at "
                               f"byte {at}: not read (it was not written by the recorder)")
        if at + _HEAD.size + length > end:
            raise CorruptSegment(f"{path}: its summary is damaged: the record at byte {at} says it is {length} "
                                 "bytes long, past the summary's end")
        _check_summary_record_length(path, at, length)
        after = at + _HEAD.size + length
        if after > block_at + len(block):
            block, block_at = _summary_block(fd, path, at, end, _HEAD.size + length)
        yield at, opcode, block[at - block_at + _HEAD.size:after - block_at]
        at = after


def _summary_block(fd: int, path: Path, at: int, end: int, need: int) -> tuple[bytes, int]:
    """The summary's bytes from ``at`` on: at least ``need`` of them (one record, within the section), as many as a
    block holds."""
    block = os.pread(fd, min(max(need, _SUMMARY_BLOCK), end - at), at)
    if len(block) < need:  # (the file shrank under the reader)
        raise CorruptSegment(f"{path}: its summary is damaged: it ends inside the record at byte {at}")
    return block, at


def _check_summary_record_length(path: Path, at: int, length: int) -> None:
    if length > MAX_SMALL_RECORD_BYTES:
        raise SegmentError(f"{path}: its summary's record at byte {at} is {length} bytes long, more than the "
                           f"{MAX_SMALL_RECORD_BYTES // 2**20} MiB of any the recorder writes: not read (it was "
                           "not written by the recorder)")


def _summary_parse(path: Path, at: int, opcode: int, body: bytes) -> Any:
    """The summary record at ``at``, parsed by mcap's reader: fields that take its whole length."""
    try:
        record, used = _parse(opcode, body, len(body))
    except (EndOfFile, *_PARSE_ERRORS) as exc:
        raise CorruptSegment(f"{path}: its summary is damaged: the record at byte {at}: {exc!r}") from None
    if used != len(body):
        raise CorruptSegment(f"{path}: its summary is damaged: the record at byte {at} says it is {len(body)} bytes "
                             f"long, its own fields {used}")
    return record


def _summary_record(fd: int, path: Path, at: int) -> Any:
    """The summary record at ``at``, read on its own (an attachment's index entry)."""
    opcode, length = _HEAD.unpack(os.pread(fd, _HEAD.size, at))
    _check_summary_record_length(path, at, length)
    return _summary_parse(path, at, opcode, os.pread(fd, length, at + _HEAD.size))


# A chunk index record's fields (the MCAP specification), read here rather than by mcap's reader, which takes
# ~9 µs for one (a field at a time): a summary holds a chunk index for every chunk, up to ~190 000 in one of
# MAX_SUMMARY_BYTES. Message start and end times, chunk start offset and length, the message index
# offsets' length in bytes (then the offsets, 10 bytes each: channel id, offset); then the message index length
# and the compression's length (then its name); then the compressed and uncompressed sizes.
_CHUNK_INDEX_HEAD = struct.Struct("<QQQQI")
_CHUNK_INDEX_MIDDLE = struct.Struct("<QI")
_CHUNK_INDEX_TAIL = struct.Struct("<QQ")
_CHANNEL_OFFSET = struct.Struct("<HQ")


def _chunk_index(path: Path, at: int, body: bytes) -> tuple[int, int, int, int, bytes]:
    """A chunk index record's message start and end times, chunk start offset, uncompressed size and message
    index offsets (:data:`_CHANNEL_OFFSET` each), its fields checked as mcap's reader does: each whole, a
    compression name in UTF-8, and together the record's whole length."""
    try:
        first, last, offset, _length, map_bytes = _CHUNK_INDEX_HEAD.unpack_from(body)
        map_at = _CHUNK_INDEX_HEAD.size
        if map_bytes % _CHANNEL_OFFSET.size:
            raise ValueError(f"its message index offsets take {map_bytes} bytes, not a whole number of entries")
        _index_length, name_length = _CHUNK_INDEX_MIDDLE.unpack_from(body, map_at + map_bytes)
        name_at = map_at + map_bytes + _CHUNK_INDEX_MIDDLE.size
        if name_at + name_length > len(body):
            raise EndOfFile()
        body[name_at:name_at + name_length].decode()
        _compressed, size = _CHUNK_INDEX_TAIL.unpack_from(body, name_at + name_length)
    except (EndOfFile, *_PARSE_ERRORS) as exc:
        raise CorruptSegment(f"{path}: its summary is damaged: the record at byte {at}: {exc!r}") from None
    used = name_at + name_length + _CHUNK_INDEX_TAIL.size
    if used != len(body):
        raise CorruptSegment(f"{path}: its summary is damaged: the record at byte {at} says it is {len(body)} bytes "
                             f"long, its own fields {used}")
    return first, last, offset, size, body[map_at:map_at + map_bytes]


def _slim(channel: Channel) -> Channel:
    """A channel as reading keeps it: its metadata reduced to the malformed mark (all a record needs)."""
    meta = {MALFORMED_META: "true"} if channel.metadata.get(MALFORMED_META) == "true" else {}
    return dataclasses.replace(channel, metadata=meta) if meta != channel.metadata else channel


def _index(f: Any, path: Path, start: int | None = None, end: int | None = None,
           topics: Collection[str] | None = None, chunks: bool = True) -> SegmentIndex | None:
    """:func:`read_index`, None where there is none to read by: no footer yet (a segment being written) or a
    damaged summary (the data section, read front to back, is checked record by record)."""
    try:
        return read_index(f, path, start, end, topics, chunks)
    except (NoFooter, CorruptSegment):
        return None


def has_footer(path: Path) -> bool:
    """Whether a segment was finished: it ends with a footer and its summary, if it has one, is whole (a summary
    the recorder does not write counts as finished: reading it refuses it by name). Raises
    :class:`SegmentError` for a path that is no regular file, unread (:func:`open_segment`)."""
    try:
        f = open_segment(path)
    except OSError:
        return False
    with f:
        try:
            read_index(f, path, chunks=False)
        except (NoFooter, CorruptSegment, OSError):
            return False
        except SegmentError:
            return True
    return True


def stream_of(path: Path) -> str:
    """``video-0003.mcap`` → ``video``."""
    return path.name.rsplit("-", 1)[0]


def _iter_file(path: Path, start: int | None, end: int | None,
               topics: Collection[str] | None = None) -> Iterator[Record]:
    stream = stream_of(path)
    with open_segment(path) as f:
        index = _index(f, path, start, end, topics)
        if index is None or not index.chunks_indexed:
            # No index to seek with (mcap's own reader would then decompress every chunk unchecked): front to
            # back, each chunk's own size checked.
            f.seek(0)
            yield from _iter_linear(f, path, stream, start, end, topics)
            return
        yield from _iter_indexed(f, path, stream, index, start, end, topics)


def _iter_indexed(f: BinaryIO, path: Path, stream: str, index: SegmentIndex, start: int | None, end: int | None,
                  topics: Collection[str] | None) -> Iterator[Record]:
    """The messages of a finished segment in receive-time order, through its chunk index: only the chunks whose
    times and channels are wanted are read, each checked (size, CRC) before it is used. Chunks whose times
    overlap are decompressed together, as mcap's reader does; those that follow one another, one at a time."""
    order = sorted(range(len(index.offsets)), key=index.offsets.__getitem__)
    for a, b in itertools.pairwise(order):
        if index.offsets[a] == index.offsets[b]:  # (it would be read, and its messages given, twice)
            raise CorruptSegment(f"{path}: its chunk index lists the chunk at byte {index.offsets[a]} twice: the "
                                 "summary is damaged")
    # The index's sizes are the chunks' own claims repeated: a crafted index may understate them.
    sizes = array("Q", (max(size, _declared_size(f, path, offset))
                        for size, offset in zip(index.sizes, index.offsets, strict=True)))
    _check_overlap(path, index.starts, index.ends, sizes)
    # Chunks by (first message's time, offset), each read when the messages held are no earlier than its start:
    # messages come out by (time, chunk offset, position in the chunk).
    order.sort(key=index.starts.__getitem__)
    held: list[tuple[int, int, int, Record]] = []
    held_cost = 0
    for k in order:
        offset = index.offsets[k]
        while held and (held[0][0], held[0][1]) < (index.starts[k], offset):
            held_cost -= len(held[0][3].data) + _HELD_OVERHEAD
            yield heapq.heappop(held)[3]
        f.seek(offset)
        chunk = _read_chunk(f, path, offset)
        where, cost = f"the chunk at byte {offset}", 0
        for i, record in enumerate(_chunk_records(path, where, chunk)):
            if not isinstance(record, Message):
                continue
            channel = index.channels.get(record.channel_id)
            if channel is None:
                raise CorruptSegment(f"{path}: the chunk at byte {offset} holds a message on channel "
                                     f"{record.channel_id}, which the file does not define")
            if ((start is not None and record.log_time < start) or (end is not None and record.log_time >= end)
                    or (topics is not None and channel.topic not in topics)):
                continue
            heapq.heappush(held, (record.log_time, offset, i, _record(channel, record, stream)))
            cost += len(record.data) + _HELD_OVERHEAD
            if cost > MAX_OVERLAPPING_CHUNK_BYTES:
                raise _held_too_much(path, where, cost)
        held_cost += cost
        if held_cost > MAX_OVERLAPPING_CHUNK_BYTES:
            raise _held_too_much(path, f"the chunks whose times overlap up to byte {offset}", held_cost)
    while held:
        yield heapq.heappop(held)[3]


def _chunk_wanted(first: int, last: int, channel_map: bytes, channels: dict[int, Channel], start: int | None,
                  end: int | None, topics: Collection[str] | None) -> bool:
    """Whether a chunk holds messages wanted: its times (``first`` to ``last``) and the channels of its message
    index offsets (``channel_map``, :data:`_CHANNEL_OFFSET` each)."""
    if (start is not None and last < start) or (end is not None and first >= end):
        return False
    if topics is None or not channel_map:  # (without message indexes, only reading tells)
        return True
    return any(ch in channels and channels[ch].topic in topics for ch, _ in _CHANNEL_OFFSET.iter_unpack(channel_map))


# A chunk record: opcode, record length, message start and end times, uncompressed size, CRC, compression.
_CHUNK_HEAD = struct.Struct("<BQQQQII")
# The shortest chunk record: its head, no compression name, the records' length (8 bytes) and no records.
_CHUNK_MIN_BYTES = _CHUNK_HEAD.size + 8


def _declared_size(f: BinaryIO, path: Path, offset: int) -> int:
    """The largest size the chunk an index entry points to declares, read from its head alone: its own
    uncompressed size, and its zstd frame's content size."""
    f.seek(offset)
    head = f.read(_CHUNK_HEAD.size)
    if len(head) < _CHUNK_HEAD.size or head[0] != Opcode.CHUNK:
        raise CorruptSegment(f"{path}: the chunk index points to byte {offset}, where no chunk is")
    *_, size, _crc, name_len = _CHUNK_HEAD.unpack(head)
    name = f.read(min(name_len, 16))
    f.read(8)  # the compressed data's length
    where = f"the chunk at byte {offset}"
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


def _chunk_records(path: Path, where: str, chunk: Chunk) -> Iterator[Any]:
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
        data = zstandard.decompress(chunk.data, chunk.uncompressed_size) if chunk.compression else chunk.data
    except zstandard.ZstdError as exc:
        raise CorruptSegment(f"{path}: {where} is damaged: {exc!r}") from None
    if len(data) != chunk.uncompressed_size:
        raise CorruptSegment(f"{path}: {where} is damaged: it holds {len(data)} bytes, {chunk.uncompressed_size} "
                             "declared")
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise CorruptSegment(f"{path}: {where} is damaged (its CRC does not match: {zlib.crc32(data):#010x}, "
                             f"{chunk.uncompressed_crc:#010x} written)")
    return _inner_records(path, where, data)


# A message record's fields before its data: channel id, sequence, log time, publish time.
_MESSAGE_HEAD = struct.Struct("<HIQQ")


def _inner_records(path: Path, where: str, data: bytes) -> Iterator[Any]:
    """The records of a chunk's data, one at a time: the schemas, channels and messages a chunk holds, each of
    the length its fields take (mcap's reader skipped records of other kinds without a word, and turned a
    channel's metadata of any size into a dict)."""
    at = 0
    while at < len(data):
        if at + _HEAD.size > len(data):
            raise CorruptSegment(f"{path}: {where} is damaged: its data ends inside the head of a record")
        opcode, length = _HEAD.unpack_from(data, at)
        body = at + _HEAD.size
        if body + length > len(data):
            raise CorruptSegment(f"{path}: {where} is damaged: a record at byte {at} of its data says it is "
                                 f"{length} bytes long, past the end of the chunk")
        if opcode == Opcode.MESSAGE and length >= _MESSAGE_HEAD.size:
            channel_id, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(data, body)
            yield Message(channel_id=channel_id, sequence=sequence, log_time=log_time, publish_time=publish_time,
                          data=data[body + _MESSAGE_HEAD.size:body + length])
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL) and length <= MAX_SMALL_RECORD_BYTES:
            try:
                record, used = _parse(opcode, data[body:body + length], length)
            except (EndOfFile, *_PARSE_ERRORS) as exc:
                raise CorruptSegment(f"{path}: {where} is damaged: the record at byte {at} of its data: "
                                     f"{exc!r}") from None
            if used != length:
                raise CorruptSegment(f"{path}: {where} is damaged: the record at byte {at} of its data says it is "
                                     f"{length} bytes long, its own fields {used}")
            yield record
        else:
            what = "none a chunk holds" if opcode not in (Opcode.MESSAGE, Opcode.SCHEMA, Opcode.CHANNEL) else \
                f"{length} bytes long, which none of its kind is"
            raise CorruptSegment(f"{path}: {where} is damaged: the record at byte {at} of its data (opcode "
                                 f"{opcode:#04x}) is {what}")
        at = body + length


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
# The longest top-level record of each kind the recorder writes; any other kind, MAX_SMALL_RECORD_BYTES.
_LONGEST = {Opcode.CHUNK: MAX_RECORD_BYTES, Opcode.MESSAGE: MAX_RECORD_BYTES,
            Opcode.ATTACHMENT: MAX_ATTACHMENT_BYTES + 2**20}  # (with its name and media type)


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
    if held > _LONGEST.get(opcode, MAX_SMALL_RECORD_BYTES):  # (and parsing it could take ~10 times that)
        why = f"the file holds {held} bytes after its head, more than any record of its kind the recorder writes"
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
        if length > _LONGEST.get(opcode, MAX_SMALL_RECORD_BYTES):
            raise CorruptSegment(f"{path}: {where} says it is {length} bytes long, more than any record of its "
                                 f"kind ({Opcode(opcode).name.lower()}) the recorder writes: its length is damaged "
                                 "(or the recorder did not write it)")
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


# Memory a message held for reordering takes beyond its data (the record, its place in the heap): measured.
_HELD_OVERHEAD = 450


def _held_too_much(path: Path, where: str, cost: int) -> SegmentError:
    """The refusal of a chunk whose messages, held to be put in time order, would take more memory than any
    the recorder writes (it writes at most ~100 000 messages a second, and ends a chunk at least every second)."""
    return SegmentError(f"{path}: the messages of {where} would take {cost / 2**20:.0f} MiB to hold (with "
                        f"~{_HELD_OVERHEAD} bytes each beyond their data), more than the "
                        f"{MAX_OVERLAPPING_CHUNK_BYTES // 2**20} MiB a recording's segment needs: not read (it was "
                        "not written by the recorder)")


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
            where = f"the chunk at byte {at}" if isinstance(top, Chunk) else f"the message at byte {at}"
            inner = _chunk_records(path, where, top) if isinstance(top, Chunk) else [top]
            kept: list[Record] = []
            cost = 0
            for x in inner:
                record = _keep(x, channels, stream, start, end, topics, path, where)
                if record is not None:
                    kept.append(record)
                    cost += len(record.data) + _HELD_OVERHEAD
                    if cost > MAX_OVERLAPPING_CHUNK_BYTES:
                        raise _held_too_much(path, where, cost)
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
          topics: Collection[str] | None, path: Path, where: str) -> Record | None:
    if isinstance(record, Channel):
        channels[record.id] = _slim(record)
    elif isinstance(record, Message):
        if record.channel_id not in channels:  # (a writer defines a channel before its first message)
            raise CorruptSegment(f"{path}: {where} holds a message on channel {record.channel_id}, which the file "
                                 "does not define before it")
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
    """The files attached to a session's segments (the calibration files), by name: each read once, checked (its
    size, its CRC), at most :data:`MAX_ATTACHMENT_BYTES` each and :data:`MAX_ATTACHMENTS_BYTES` together."""
    out: dict[str, bytes] = {}
    for path in segment_files(session_dir(folder)):
        with open_segment(path) as f:
            index = _index(f, path, chunks=False)
            if index is None:  # no summary to seek with: front to back
                f.seek(0)
                with contextlib.suppress(TornTail):  # (the attachments before it are kept)
                    for record in stream_records(f, path):
                        if isinstance(record, Attachment) and record.name not in out:
                            _check_attachment(path, record.name, len(record.data), out)
                            out[record.name] = record.data
                continue
            for at in index.attachment_indexes:
                entry = _summary_record(f.fileno(), path, at)
                if entry.name in out:
                    continue
                _check_attachment(path, entry.name, entry.data_size, out)
                out[entry.name] = _read_attachment(f, path, entry)
    return out


def _check_attachment(path: Path, name: str, size: int, taken: dict[str, bytes]) -> None:
    if size > MAX_ATTACHMENT_BYTES:
        raise SegmentError(f"{path}: its attachment {name[:80]!r} is {size / 2**20:.0f} MiB, more than the "
                           f"{MAX_ATTACHMENT_BYTES // 2**20} MiB of any the recorder attaches: not read (it was "
                           "not written by the recorder)")
    if size + sum(len(d) for d in taken.values()) > MAX_ATTACHMENTS_BYTES:
        raise SegmentError(f"{path}: its attachment {name[:80]!r} would bring the session's attachments over "
                           f"{MAX_ATTACHMENTS_BYTES // 2**20} MiB, more than the recorder attaches: not read (it "
                           "was not written by the recorder)")


def _read_attachment(f: Any, path: Path, entry: AttachmentIndex) -> bytes:
    """The data of the attachment an index entry points to, as long as the entry says and its CRC checked."""
    where = f"the attachment {entry.name[:80]!r} at byte {entry.offset}"
    head = os.pread(f.fileno(), _HEAD.size, entry.offset)
    if len(head) < _HEAD.size or head[0] != Opcode.ATTACHMENT or _HEAD.unpack(head)[1] + _HEAD.size != entry.length:
        raise CorruptSegment(f"{path}: the attachment index points to byte {entry.offset}, where no attachment of "
                             f"{entry.length} bytes is")
    length = entry.length - _HEAD.size
    body = os.pread(f.fileno(), length, entry.offset + _HEAD.size)
    try:
        record, used = _parse(Opcode.ATTACHMENT, body, length)
    except (EndOfFile, *_PARSE_ERRORS) as exc:
        raise CorruptSegment(f"{path}: {where} is damaged: {exc!r}") from None
    (crc,) = struct.unpack_from("<I", body, used - 4)
    if used != length or record.name != entry.name or len(record.data) != entry.data_size:
        raise CorruptSegment(f"{path}: {where} is not the one its index describes: the file is damaged")
    if crc and zlib.crc32(memoryview(body)[: used - 4]) != crc:
        raise CorruptSegment(f"{path}: {where} is damaged (its CRC does not match)")
    return record.data
