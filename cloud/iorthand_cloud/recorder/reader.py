"""Reading a session: its segments' messages merged in receive-time order, with decoding for analysis."""

from __future__ import annotations

import heapq
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, ChunkIndex, Message
from mcap.stream_reader import StreamReader, breakup_chunk

from iorthand_cloud.recorder.manifest import Manifest
from iorthand_cloud.recorder.segments import MALFORMED_META

# What the recorder writes is bounded (a chunk holds at most chunk_kb, at most 32 MiB, plus one message of at most
# 8 MiB), and reading holds at once only the chunks whose times overlap. A file beyond these bounds was not written
# by the recorder: a few kB of zstd can declare gigabytes, and reading it would exhaust the machine's memory.
MAX_CHUNK_BYTES = 64 * 2**20
MAX_OVERLAPPING_CHUNK_BYTES = 256 * 2**20


class SegmentError(ValueError):
    """A segment that cannot be read safely; the message names the file and what was wrong."""


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


def stream_of(path: Path) -> str:
    """``video-0003.mcap`` → ``video``."""
    return path.name.rsplit("-", 1)[0]


def _iter_file(path: Path, start: int | None, end: int | None,
               topics: Collection[str] | None = None) -> Iterator[Record]:
    stream = stream_of(path)
    with path.open("rb") as f:
        try:
            reader = make_reader(f)
            summary = reader.get_summary()
        except Exception:  # no footer yet (a segment being written) or a torn one: its complete records
            f.seek(0)
            yield from _iter_unfinished(f, path, stream, start, end, topics)
            return
        check_chunks(path, summary.chunk_indexes if summary is not None else [])
        # With topics, the chunks' message indexes let the reader skip the other channels' messages.
        wanted = list(topics) if topics is not None else None
        for _schema, channel, message in reader.iter_messages(topics=wanted, starting_at=start, ending_before=end,
                                                              log_time_order=True):
            yield Record(
                key=channel.topic, log_time=message.log_time, publish_time=message.publish_time,
                sequence=message.sequence, data=message.data,
                malformed=channel.metadata.get(MALFORMED_META) == "true", stream=stream,
            )


def stream_records(f: Any, path: Path) -> Iterator[Any]:
    """The records of an MCAP file read front to back (one without a footer too), each chunk's size checked
    before it is decompressed (:class:`SegmentError`)."""
    for chunk_or_record in StreamReader(f, skip_magic=False, emit_chunks=True).records:
        if isinstance(chunk_or_record, Chunk):
            _check_chunk_size(path, f"the chunk ending at byte {f.tell()}", chunk_or_record.uncompressed_size)
            yield from breakup_chunk(chunk_or_record)
        else:
            yield chunk_or_record


def _iter_unfinished(f: Any, path: Path, stream: str, start: int | None, end: int | None,
                     topics: Collection[str] | None = None) -> Iterator[Record]:
    """The complete records of a segment without a footer, in receive-time order (the torn tail is left out)."""
    channels: dict[int, Channel] = {}
    out: list[Record] = []
    try:
        for record in stream_records(f, path):
            _keep(record, channels, out, stream, start, end, topics)
    except SegmentError:
        raise
    except Exception:  # the torn tail: everything before it was taken
        pass
    out.sort(key=lambda r: r.log_time)
    yield from out


def _keep(record: Any, channels: dict[int, Channel], out: list[Record], stream: str, start: int | None,
          end: int | None, topics: Collection[str] | None) -> None:
    if isinstance(record, Channel):
        channels[record.id] = record
    elif isinstance(record, Message) and record.channel_id in channels:
        if (start is not None and record.log_time < start) or (end is not None and record.log_time >= end):
            return
        ch = channels[record.channel_id]
        if topics is not None and ch.topic not in topics:
            return
        out.append(Record(key=ch.topic, log_time=record.log_time, publish_time=record.publish_time,
                          sequence=record.sequence, data=record.data,
                          malformed=ch.metadata.get(MALFORMED_META) == "true", stream=stream))


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
