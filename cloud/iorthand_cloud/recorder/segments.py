"""MCAP segment files: one :class:`Stream` per kind of data (zstd telemetry, uncompressed video), each split
into numbered segments by size and duration.

Each message is stored as received, with ``log_time`` = the recorder's receive time, ``publish_time`` = the
source time ``t`` carried by the message, and ``sequence`` = the publisher's sequence number (MCAP keeps 32
bits: at 125 Hz that wraps after a year). :meth:`Stream.flush` ends the current chunk and hands it to the
kernel (and the disk, with ``fsync``): a killed recorder loses at most what arrived since the last flush.
Errors (``OSError``: full disk, missing folder) are raised to the caller, which stops the recording.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from mcap.writer import CompressionType, Writer

PROFILE = "iorthand"
LIBRARY = "iorthand-recorder"
MALFORMED_META = "iorthand.malformed"
# A segment's summary restates its schemas and channels and indexes each chunk (~90 bytes, plus 10 per channel in
# the chunk) and attachment: 180 kB for a 10-minute segment (segment_max_s) of one robot's telemetry at the default
# flush_interval (1 200 chunks of 7 channels), 2 MB for all the segments of an hour's session with its video;
# 3.9 MB at the shortest flush_interval (20 ms: 30 000 chunks). A reader takes at most MAX_SUMMARY_BYTES of one
# (reader.read_index; mcap's reader, which parsed them whole, took 640 MiB for 87 MB of crafted chunk index
# records, and the check 7-17 s for 63 MiB when this bound was 64 MiB); a larger one was not written by the
# recorder, because it starts a new segment once its estimate of the summary reaches SUMMARY_ROLL_BYTES (small
# chunks, many keys, long segments: settings that no size bound on the segment alone keeps readable).
# The recorder rolls at a quarter of what a reader takes; the reader's bound stays above the 16 MiB at which the
# releases before this one rolled, so that their segments stay readable.
SUMMARY_ROLL_BYTES = 4 * 2**20
MAX_SUMMARY_BYTES = 24 * 2**20
CHUNK_INDEX_BYTES, CHUNK_INDEX_CHANNEL_BYTES = 100, 10  # an upper estimate of a chunk index record's size
MESSAGE_RECORD_BYTES = 31  # a message record's fields besides its data (its share of a chunk's size)
# The streams of a session, each its own series of segments: video (uncompressed) apart from the rest (zstd), so
# a reader that wants one does not read the other.
TELEMETRY, VIDEO = "telemetry", "video"
# Video (JPEG, H.264) is compressed already: zstd would spend CPU on it for nothing.
COMPRESSION = {TELEMETRY: CompressionType.ZSTD, VIDEO: CompressionType.NONE}


@dataclass(frozen=True)
class ChannelSpec:
    """A channel: the key plus how its bytes are encoded; malformed payloads of a key get their own channel
    (same topic, metadata ``iorthand.malformed``) so a reader decoding the normal one never meets garbage.
    ``extra_metadata``: more channel metadata (a Foxglove channel names the raw key it is made from)."""

    topic: str
    encoding: str
    schema_name: str = ""
    schema_encoding: str = ""
    schema_data: bytes = b""
    malformed: bool = False
    extra_metadata: tuple[tuple[str, str], ...] = ()

    @property
    def metadata(self) -> dict[str, str]:
        meta = dict(self.extra_metadata)
        if self.malformed:
            meta[MALFORMED_META] = "true"
        return meta


@dataclass(frozen=True)
class Attachment:
    name: str
    media_type: str
    data: bytes
    create_time: int = 0


class Segment:
    """One open MCAP file."""

    def __init__(
        self, path: Path, compression: CompressionType, chunk_size: int, attachments: list[Attachment],
        opener: Callable[[Path], BinaryIO] | None = None, clock: Callable[[], int] = time.time_ns,
    ) -> None:
        self.path = path
        self.file: BinaryIO = opener(path) if opener else path.open("xb")
        self.writer = Writer(self.file, chunk_size=chunk_size, compression=compression)
        self.writer.start(profile=PROFILE, library=LIBRARY)
        self._schemas: dict[str, int] = {}
        self._channels: dict[ChannelSpec, int] = {}
        self.messages = 0
        self._chunk_size = chunk_size
        self._flushes = 0  # each ends a chunk
        self._bytes = 0  # written into chunks, uncompressed: a chunk ends at chunk_size too
        self.opened_t = clock()
        self.opened_mono = time.monotonic()
        for att in attachments:
            now = clock()
            self.writer.add_attachment(att.create_time or now, now, att.name, att.media_type, att.data)

    def channel(self, spec: ChannelSpec) -> int:
        cid = self._channels.get(spec)
        if cid is None:
            sid = 0
            if spec.schema_name:
                sid = self._schemas.get(spec.schema_name, 0)
                if not sid:
                    sid = self.writer.register_schema(spec.schema_name, spec.schema_encoding, spec.schema_data)
                    self._schemas[spec.schema_name] = sid
            cid = self.writer.register_channel(spec.topic, spec.encoding, sid, spec.metadata)
            self._channels[spec] = cid
        return cid

    def write(self, spec: ChannelSpec, log_time: int, publish_time: int, seq: int, data: bytes) -> None:
        self.writer.add_message(self.channel(spec), log_time, data, publish_time, seq & 0xFFFFFFFF)
        self.messages += 1
        self._bytes += MESSAGE_RECORD_BYTES + len(data)

    @property
    def summary_estimate(self) -> int:
        """Bytes, at least, that closing this segment now would write as its summary's chunk indexes: a chunk for
        every flush and every chunk_size written, each indexed with every channel (an upper bound per chunk)."""
        chunks = self._flushes + self._bytes // self._chunk_size + 1
        return chunks * (CHUNK_INDEX_BYTES + CHUNK_INDEX_CHANNEL_BYTES * len(self._channels))

    def flush(self, fsync: bool) -> None:
        self.writer.flush()
        self._flushes += 1
        if fsync:
            os.fsync(self.file.fileno())

    @property
    def size(self) -> int:
        return self.file.tell()

    def close(self, fsync: bool = True) -> None:
        try:
            self.writer.finish()
            self.file.flush()
            if fsync:
                os.fsync(self.file.fileno())
        finally:
            self.file.close()


@dataclass
class Stream:
    """A sequence of segments ``<name>-0001.mcap``, ``<name>-0002.mcap``… in ``folder``. ``make_folder``: create
    ``folder`` when the first segment opens (a subfolder written only if data comes); the session folder itself
    is never re-created, so one removed under a recording stops it with an error."""

    name: str
    folder: Path
    compression: CompressionType
    max_bytes: int
    max_seconds: float
    chunk_size: int
    attachments: list[Attachment] = field(default_factory=list)
    on_open: Callable[[Segment], None] | None = None
    on_close: Callable[[Segment], None] | None = None
    opener: Callable[[Path], BinaryIO] | None = None
    clock: Callable[[], int] = time.time_ns  # wall time, ns (the recording's: see service.RecordingClock)
    current: Segment | None = None
    index: int = 0
    dirty: bool = False
    closed: list[Path] = field(default_factory=list)
    make_folder: bool = False

    def open_next(self) -> Segment:
        if self.make_folder and self.index == 0:
            self.folder.mkdir(exist_ok=True)
        self.index += 1
        seg = Segment(self.folder / f"{self.name}-{self.index:04d}.mcap", self.compression, self.chunk_size,
                      self.attachments, self.opener, self.clock)
        self.current = seg
        if self.on_open:
            self.on_open(seg)
        return seg

    def write(self, spec: ChannelSpec, log_time: int, publish_time: int, seq: int, data: bytes) -> None:
        seg = self.current or self.open_next()
        seg.write(spec, log_time, publish_time, seq, data)
        self.dirty = True

    def flush(self, fsync: bool) -> None:
        """Flush, then start a new segment if this one is full (checked here, where the size is exact), or its
        summary would grow past what a reader takes."""
        seg = self.current
        if seg is None or not self.dirty:
            return
        seg.flush(fsync)
        self.dirty = False
        if (seg.size >= self.max_bytes or seg.summary_estimate >= SUMMARY_ROLL_BYTES
                or time.monotonic() - seg.opened_mono >= self.max_seconds):
            self.close()

    def close(self, fsync: bool = True) -> None:
        seg, self.current = self.current, None
        self.dirty = False
        if seg is not None:
            self.closed.append(seg.path)
            try:
                seg.close(fsync)
            finally:
                if self.on_close:
                    self.on_close(seg)

    def abandon(self) -> None:
        """Close the file without a footer after an error (the next start's repair recovers it)."""
        seg, self.current = self.current, None
        if seg is not None:
            with contextlib.suppress(OSError):
                seg.file.close()
