"""Reading a session: its segments' messages merged in receive-time order, with decoding for analysis."""

from __future__ import annotations

import heapq
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack
from mcap.reader import make_reader
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from iorthand_cloud.recorder.manifest import Manifest
from iorthand_cloud.recorder.segments import MALFORMED_META


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
            reader.get_summary()
        except Exception:  # no footer yet (a segment being written) or a torn one: its complete records
            f.seek(0)
            yield from _iter_unfinished(f, stream, start, end, topics)
            return
        # With topics, the chunks' message indexes let the reader skip the other channels' messages.
        wanted = list(topics) if topics is not None else None
        for _schema, channel, message in reader.iter_messages(topics=wanted, starting_at=start, ending_before=end,
                                                              log_time_order=True):
            yield Record(
                key=channel.topic, log_time=message.log_time, publish_time=message.publish_time,
                sequence=message.sequence, data=message.data,
                malformed=channel.metadata.get(MALFORMED_META) == "true", stream=stream,
            )


def _iter_unfinished(f: Any, stream: str, start: int | None, end: int | None,
                     topics: Collection[str] | None = None) -> Iterator[Record]:
    """The complete records of a segment without a footer, in receive-time order (the torn tail is left out)."""
    channels: dict[int, Channel] = {}
    out: list[Record] = []
    try:
        for record in StreamReader(f, skip_magic=False).records:
            if isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message) and record.channel_id in channels:
                if (start is not None and record.log_time < start) or (end is not None and record.log_time >= end):
                    continue
                ch = channels[record.channel_id]
                if topics is not None and ch.topic not in topics:
                    continue
                out.append(Record(key=ch.topic, log_time=record.log_time, publish_time=record.publish_time,
                                  sequence=record.sequence, data=record.data,
                                  malformed=ch.metadata.get(MALFORMED_META) == "true", stream=stream))
    except Exception:  # the torn tail: everything before it was taken
        pass
    out.sort(key=lambda r: r.log_time)
    yield from out


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
