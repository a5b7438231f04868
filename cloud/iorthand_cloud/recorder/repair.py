"""Crash repair: segments a killed recorder left without a footer are rewritten from their readable part.

A segment is readable up to the last complete record (the writer flushes whole chunks at least once a second,
so a kill -9 loses at most the chunk in progress). The rewrite goes to a temporary file that replaces the
original only when complete; the manifest's statistics are then recomputed from the files themselves (the
manifest on disk may be up to one ``manifest_interval`` old) and the session is marked ``recovered`` (or
``failed``, with the reason, when its recorder stopped on an error it could not write into the manifest: see
:func:`~iorthand_cloud.recorder.manifest.note_failure`). A damaged record (a CRC that does not match, a length
that is not what its fields take) stops the rewrite too, but what follows it may be good: the file as it was is
kept beside the repaired one. A length that runs past the end of the file is a torn tail only when the record is
cut short by its own fields too, could be one the recorder writes, and no whole chunk follows it
(:func:`~iorthand_cloud.recorder.reader.stream_records`); otherwise it is damage.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from iorthand_cloud.recorder import manifest as mf
from iorthand_cloud.recorder.reader import (
    MAX_SUMMARY_BYTES,
    CorruptSegment,
    SegmentError,
    TornTail,
    has_footer,
    iter_records,
    open_segment,
    segment_files,
    stream_of,
    stream_records,
)
from iorthand_cloud.recorder.segments import COMPRESSION, LIBRARY, PROFILE

log = logging.getLogger("iorthand.recorder")


@dataclass
class RepairResult:
    path: Path
    messages: int
    lost_bytes: int
    original: Path | None = None  # the file as it was, kept when the repair stopped at damage, not at a torn tail
    damage: str = ""

    @property
    def damage_note(self) -> str:
        """What stopped the repair and where the file as it was is kept ("" when it stopped at a torn tail)."""
        return f"{self.damage} (the file as it was is kept as {self.original.name})" if self.original else ""


def repair_segment(path: Path) -> RepairResult:
    """Rewrite ``path`` from its readable records; returns what was recovered. Reading stops at a torn tail
    (what a killed writer leaves: dropped) or at a damaged record (a CRC that does not match...): then what
    follows may be good, so the file as it was is kept beside the repaired one (``<name>.orig``)."""
    tmp = path.with_suffix(".mcap.repair")
    compression = COMPRESSION.get(stream_of(path), CompressionType.ZSTD)
    messages = 0
    good_offset = 0
    damage: CorruptSegment | None = None
    try:
        # (a link is refused unread: what it points to is no file of this session to read or replace)
        with open_segment(path) as src, tmp.open("wb") as dst:
            size = os.fstat(src.fileno()).st_size
            writer = Writer(dst, compression=compression)
            writer.start(profile=PROFILE, library=LIBRARY)
            schemas: dict[int, int] = {}
            channels: dict[int, int] = {}
            defined = 0  # bytes of the schemas and channels the repaired file's summary will repeat
            try:
                for record in stream_records(src, path):
                    if isinstance(record, Schema) and record.id not in schemas:  # (once each: ids are 16 bits)
                        defined += len(record.name) + len(record.encoding) + len(record.data)
                        schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)
                    elif isinstance(record, Channel) and record.id not in channels:
                        defined += len(record.topic) + sum(len(k) + len(v) for k, v in record.metadata.items())
                        channels[record.id] = writer.register_channel(
                            record.topic, record.message_encoding, schemas.get(record.schema_id, 0), record.metadata
                        )
                    elif isinstance(record, Message):
                        if record.channel_id not in channels:  # (a writer defines a channel before its first message)
                            raise CorruptSegment(f"{path}: a message on channel {record.channel_id} before byte "
                                                 f"{src.tell()}, which the file does not define before it")
                        writer.add_message(channels[record.channel_id], record.log_time, record.data,
                                           record.publish_time, record.sequence)
                        messages += 1
                    elif isinstance(record, Attachment):
                        writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type,
                                              record.data)
                    elif isinstance(record, Metadata):
                        writer.add_metadata(record.name, record.metadata)
                    if defined > MAX_SUMMARY_BYTES:  # (held in memory until the end, and unreadable after it)
                        raise SegmentError(f"{path}: its schemas and channels take more than the "
                                           f"{MAX_SUMMARY_BYTES // 2**20} MiB of a summary the recorder writes: not "
                                           "repaired (it was not written by the recorder)")
                    good_offset = src.tell()
            except TornTail as exc:  # everything before it was taken
                log.info("%s", exc)
            except CorruptSegment as exc:
                damage = exc
            writer.finish()
            dst.flush()
            os.fsync(dst.fileno())
    except BaseException:  # a file the recorder did not write (SegmentError: left as it is), a write error
        tmp.unlink(missing_ok=True)
        raise
    original = None
    if damage is not None:
        original = path.with_name(path.name + ".orig")
        os.replace(path, original)
        log.error("%s; what follows byte %d is not in the repaired file: the file as it was is kept as %s",
                  damage, good_offset, original.name)
    os.replace(tmp, path)
    return RepairResult(path, messages, max(0, size - good_offset), original, str(damage or ""))


def recompute_stats(folder: Path) -> tuple[dict[str, mf.KeyStats], int, int | None]:
    """Per-key statistics, annotation count and last receive time, from the segment files."""
    from iorthand import keys
    from iorthand.protocol import message_type_for

    stats: dict[str, mf.KeyStats] = {}
    annotations = 0
    last: int | None = None
    ann_key = keys.service_key(keys.RECORDER, keys.RECORDER_ANNOTATIONS)
    for rec in iter_records(folder):
        last = rec.log_time
        if rec.key == ann_key:
            annotations += 1
            continue
        st = stats.get(rec.key)
        if st is None:
            cls = message_type_for(rec.key)  # as the recorder names it (the segments do not say it for all keys)
            st = stats[rec.key] = mf.KeyStats(type=cls.__name__ if cls else "")
        st.observe(len(rec.data), rec.log_time, None if rec.malformed or not rec.sequence else rec.sequence,
                   malformed=rec.malformed)
    return stats, annotations, last


def set_aside(path: Path, why: SegmentError) -> Path:
    """A file among the segments that the recorder did not write (:class:`SegmentError`) is renamed, so that the
    session's other segments can be read, and kept for whoever wants to look at it."""
    aside = path.with_name(path.name + ".refused")
    os.replace(path, aside)
    log.error("%s; set aside as %s", why, aside.name)
    return aside


def keep_unreadable_manifest(folder: Path) -> Path:
    """Rename a manifest that cannot be read to the first free name of ``manifest.json.orig``,
    ``manifest.json.orig.1``, …: a new one is rebuilt from the segments, and the original (its operator, its
    annotations' times, the recorder's own counters) stays for whoever wants to look at it."""
    path = folder / mf.MANIFEST
    kept = path.with_name(path.name + ".orig")
    n = 0
    while kept.exists():  # an earlier rebuild's original stays too
        n += 1
        kept = path.with_name(f"{path.name}.orig.{n}")
    os.replace(path, kept)
    return kept


def repair_session(folder: Path) -> list[RepairResult]:
    """Repair every footer-less segment of one session and bring its manifest up to date."""
    return _repair_session(folder)[0]


def _repair_session(folder: Path) -> tuple[list[RepairResult], str]:
    """:func:`repair_session`, and what was done with a manifest that could not be read ("" when it was read)."""
    results: list[RepairResult] = []
    damaged: list[str] = []
    rebuilt = ""
    try:
        manifest = mf.Manifest.read(folder)
    except FileNotFoundError as exc:
        log.warning("%s: no manifest (%s); rebuilding one from the segments", folder, exc)
        manifest = mf.Manifest(session_id=folder.name)
    except (OSError, ValueError) as exc:
        kept = keep_unreadable_manifest(folder)
        rebuilt = f"its manifest could not be read ({exc}): kept as {kept.name}, a new one rebuilt from the segments"
        log.warning("%s: %s", folder, rebuilt)
        manifest = mf.Manifest(session_id=folder.name)
        damaged.append(rebuilt)  # said in the new manifest too (the report shows its error)
    by_file = {s.file: s for s in manifest.segments}
    for path in segment_files(folder):
        if has_footer(path):
            seg = by_file.get(path.name)
            if seg is not None and seg.status == "open":
                seg.status = "closed"
            continue
        try:
            res = repair_segment(path)
        except OSError as exc:
            log.error("%s: cannot repair (%s)", path, exc)
            if path.name in by_file:
                by_file[path.name].status = "unreadable"
            continue
        except SegmentError as exc:
            set_aside(path, exc)
            if path.name in by_file:
                by_file[path.name].status = "refused"
            continue
        results.append(res)
        log.warning("repaired %s: %d messages recovered, %d bytes of torn tail dropped",
                    path, res.messages, res.lost_bytes)
        seg = by_file.get(path.name)
        if seg is None:
            stream = stream_of(path)
            seg = mf.SegmentInfo(file=path.name, stream=stream,
                                 compression=COMPRESSION.get(stream, CompressionType.ZSTD).name.lower(), opened_t=0)
            manifest.segments.append(seg)
            by_file[path.name] = seg
        seg.status, seg.recovered_messages, seg.lost_bytes = "repaired", res.messages, res.lost_bytes
        seg.messages, seg.bytes = res.messages, path.stat().st_size
        if res.damage_note:
            damaged.append(res.damage_note)
    # The Foxglove copy of the session (iorthand_cloud.foxglove_channels), in its own subfolder: made whole too.
    for path in segment_files(folder / "foxglove"):
        if not has_footer(path):
            try:
                res = repair_segment(path)
            except SegmentError as exc:
                set_aside(path, exc)
                damaged.append(f"{exc}: set aside as {path.name}.refused")
                continue
            if res.damage_note:  # (said in the manifest, as the session's own segments' damage is)
                damaged.append(res.damage_note)
    stats, annotations, last = recompute_stats(folder)
    # The dropped counter is the recorder's own and cannot be rebuilt from the files: keep the last one written.
    manifest.keys, manifest.annotations = stats, annotations
    if manifest.status == mf.RECORDING:
        # A recorder that could not write its final manifest (full disk) left the reason in its lock file.
        failure = mf.failure_note(folder)
        manifest.status = mf.FAILED if failure else mf.RECOVERED
        manifest.stop_t = last
        manifest.stop_iso = mf.iso(last)
        why = failure or "the recorder stopped without closing this session (crash or kill)"
        manifest.error = f"{manifest.error}; {why}" if manifest.error else why
    if damaged:
        manifest.error = "; ".join([manifest.error, *damaged] if manifest.error else damaged)
    manifest.repaired = manifest.repaired or bool(results)
    manifest.write(folder)
    return results, rebuilt


def repair_if_crashed(folder: Path) -> str:
    """Make a session readable before reading it (``iorthand report``, ``export``): one its recorder left
    unfinished (killed, crashed: no live writer) is repaired here and now; one still being recorded is left
    alone (readers take its segments as far as they are written). Returns what was done, for the user ("" when
    the session was whole)."""
    folder = Path(folder)
    files = segment_files(folder)
    try:
        status = mf.Manifest.read(folder).status
    except FileNotFoundError:
        if not files:
            raise  # "... is not a recorded session": nothing to repair either
        status = None
    except (OSError, ValueError):
        status = None  # an unreadable manifest: rebuilt from the segments
    torn = [p for p in files if not has_footer(p)]
    if status in (mf.COMPLETE, mf.RECOVERED) and not torn:
        return ""
    if status == mf.RECORDING and mf.writer_alive(folder):
        return "still being recorded: read as far as it is written"
    if not torn and status is not None and status != mf.RECORDING:
        return ""
    results, rebuilt = _repair_session(folder)
    if rebuilt and not torn:  # the segments were whole: the manifest was all there was to repair
        return rebuilt
    kept = sum(r.messages for r in results)
    damaged = "".join(f"; {r.damage_note}" for r in results if r.damage_note)
    return (f"{rebuilt + '; ' if rebuilt else ''}the recorder stopped without closing this session: repaired "
            f"{len(results)} segment(s), {kept} messages kept, {sum(r.lost_bytes for r in results)} bytes of torn "
            f"tail dropped{damaged}")


def repair_all(root: Path) -> dict[str, list[RepairResult]]:
    """Repair every unfinished session under ``root`` (sessions left ``recording`` or ``failed``)."""
    out: dict[str, list[RepairResult]] = {}
    if not root.is_dir():
        return out
    for folder in sorted(p for p in root.iterdir() if p.is_dir()):
        manifest_path = folder / mf.MANIFEST
        status = None
        if manifest_path.exists():
            try:
                status = mf.Manifest.read(folder).status
            except (OSError, ValueError):
                status = None
        if status in (mf.COMPLETE, mf.RECOVERED):
            continue
        try:
            files = segment_files(folder)
            if not manifest_path.exists() and not files:
                continue
            if status == mf.FAILED and all(has_footer(p) for p in files):
                continue
        except SegmentError as exc:
            log.error("%s: not repaired: %s", folder, exc)
            continue
        if status == mf.RECORDING and mf.writer_alive(folder, quiet_for=0.0):
            log.warning("%s is being recorded by another live process: not repaired", folder)
            continue
        try:
            out[folder.name] = repair_session(folder)
        except SegmentError as exc:  # one session that cannot be read must not stop the others (nor the service)
            log.error("%s: not repaired: %s", folder, exc)
    return out
