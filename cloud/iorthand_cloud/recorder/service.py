"""The recorder service: Zenoh traffic → a session folder of MCAP segments and a manifest.

Subscriptions on the configured key expressions are declared once, at start-up, so that starting a recording
only opens a file (MUTUAL's scripted recorder took 639 ms to start because it subscribed then). Zenoh
callbacks only hand data over: samples go into a bounded :class:`~iorthand.transport.Inbox` (``keep="oldest"``:
nothing already queued is lost; a full queue is counted as ``dropped``) and queries into the same queue, so one
writer thread owns the files and sees starts, samples and stops in arrival order. The status query is
answered from the callback with bytes the writer thread prepared (answering must not wait behind a backlog).

A write error (full disk, folder gone) stops the recording and is published on ``iorthand/_recorder/status``
with the reason; the files written so far are kept (the next start-up repairs a segment left without footer).

Foxglove channels (``foxglove.enabled``): the writer thread also converts each decoded message with
:class:`~iorthand_cloud.foxglove_channels.FoxgloveConverter` and writes the result into its own stream,
``<session>/foxglove/foxglove-NNNN.mcap`` (topics and frames: :mod:`iorthand_cloud.foxglove_channels`). The raw
msgpack segments stay the source of truth and are written first; the Foxglove files sit in a subfolder that
every reader of the raw segments (report, replay, export, repair) ignores, and the manifest counts only raw
messages. A conversion that fails is counted and logged, never allowed to stop the raw recording. The
conversion runs here, never in a Zenoh callback: the receive path only queues, as before. And it yields to the
raw recording: while the writer is behind (a tenth of ``inbox_max`` queued), messages are recorded raw only,
counted in ``foxglove_skipped``, so that the queue never fills and refuses raw samples because of it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import logging
import os
import re
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import BinaryIO

import zenoh
from mcap.writer import CompressionType

from iorthand import keys
from iorthand.config import to_dict
from iorthand.protocol import (
    Annotation,
    DecodeError,
    Message,
    RecorderRequest,
    RecorderStatus,
    Sequencer,
    message_type_for,
)
from iorthand.transport import Inbox, Worker, open_session
from iorthand_cloud.foxglove_channels import FoxgloveChannel, FoxgloveConverter
from iorthand_cloud.recorder import manifest as mf
from iorthand_cloud.recorder.config import RecorderConfig
from iorthand_cloud.recorder.reader import MAX_ATTACHMENT_BYTES, MAX_ATTACHMENTS_BYTES, SegmentError
from iorthand_cloud.recorder.repair import has_footer, repair_all, repair_segment, set_aside
from iorthand_cloud.recorder.schemas import MESSAGE_ENCODING, RAW_ENCODING, SCHEMA_ENCODING, schema_bytes
from iorthand_cloud.recorder.segments import COMPRESSION, TELEMETRY, VIDEO, Attachment, ChannelSpec, Segment, Stream

log = logging.getLogger("iorthand.recorder")

SESSION_ID = re.compile(r"[A-Za-z0-9_.-]{1,64}")  # (fullmatch: "$" would let a trailing newline through)
SKIP = "skip"  # a route: not recorded
SHUTDOWN_DRAIN_S = 10.0  # s a shutdown waits for the writer to record its backlog (and again to close)
FOXGLOVE = "foxglove"  # the stream of Foxglove channels, and the subfolder of a session it is written into


def recorder_key(name: str) -> str:
    return keys.service_key(keys.RECORDER, name)


def session_id_problem(session_id: str) -> str:
    """Why ``session_id`` cannot name a session folder, "" when it can."""
    if not SESSION_ID.fullmatch(session_id):
        return "expected 1-64 of [A-Za-z0-9_.-]"
    if session_id in (".", ".."):
        return "it names the output folder or its parent, not a folder of its own"
    return ""


def _keyed_author(query: zenoh.Query | None) -> str | None:
    """The author an annotation's key names (``annotate/<author>``), None on the plain ``annotate`` key."""
    if query is None:
        return None
    _, sep, author = str(query.key_expr).partition(recorder_key(keys.RECORDER_ANNOTATE) + "/")
    return author if sep else None


@dataclass
class _Control:
    action: str
    query: zenoh.Query | None
    payload: bytes = b""
    recv_mono: int = 0  # time.monotonic_ns() at receipt: made a wall time by the recording's clock


@dataclass(frozen=True)
class RecordingClock:
    """The times a recording writes (receive times, start and stop): the wall clock read once, at the start,
    plus the monotonic time since. A step of the wall clock during the recording (NTP, an operator) would
    otherwise make a negative duration and receive times out of order."""

    wall0: int
    mono0: int

    @classmethod
    def start(cls) -> RecordingClock:
        return cls(time.time_ns(), time.monotonic_ns())

    def wall(self, mono_ns: int) -> int:
        """The wall time of a ``time.monotonic_ns()`` reading."""
        return self.wall0 + mono_ns - self.mono0

    def __call__(self) -> int:
        return self.wall(time.monotonic_ns())


@dataclass
class _Recording:
    folder: Path
    manifest: mf.Manifest
    streams: dict[str, Stream]
    started_t: int
    clock: RecordingClock
    first_message_t: int = 0
    seg_info: dict[str, mf.SegmentInfo] = field(default_factory=dict)
    last_manifest: float = 0.0
    foxglove: FoxgloveConverter | None = None  # one per recording: its "on change" state starts afresh
    robot_ids: set[str] = field(default_factory=set)  # manifest.robots as a set (a new key is checked against it)
    requested: frozenset[str] = frozenset()  # the robots the start request named: their keys have a quota apart
    keys_of_others: int = 0  # keys of robots the start request did not name (and of no robot)
    unrecorded: int = 0  # samples taken off the queue but not recorded: beyond max_keys, or left at shutdown

    def keys_held(self, requested: bool) -> int:
        """How many keys this recording keeps of the robots its start request named (or, False, of the others)."""
        return len(self.manifest.keys) - self.keys_of_others if requested else self.keys_of_others


class RecorderError(RuntimeError):
    pass


class RecorderService:
    """Run with :meth:`start` / :meth:`shutdown` (or :meth:`run_forever`). ``opener`` replaces how segment
    files are opened (tests inject a full disk)."""

    def __init__(
        self, config: RecorderConfig, session: zenoh.Session | None = None,
        opener: Callable[[Path], BinaryIO] | None = None,
    ) -> None:
        self.config = config
        self.stop_event = threading.Event()
        self._own_session = session is None
        self.session = session
        self._opener = opener
        self._inbox = Inbox(config.inbox_max, keep="oldest", max_bytes=int(config.inbox_max_mb * 1e6))
        self._accepting = False
        self._rec: _Recording | None = None
        self._route: dict[str, str] = {}
        self._specs: dict[tuple[str, bool], ChannelSpec] = {}
        self._exprs = [zenoh.KeyExpr(e) for e in config.key_exprs]
        self._video = [zenoh.KeyExpr(e) for e in config.video_key_exprs]
        self._exclude = [zenoh.KeyExpr(e) for e in config.exclude_key_exprs]
        self._status_seq = Sequencer()
        self._status_lock = threading.Lock()
        self._status = RecorderStatus(reason="idle")
        self._status_bytes = self._status.stamp(self._status_seq.next()).encode()
        self._last_error = ""
        self._dropped_at_start = 0
        self._abandon = False  # set by a shutdown that can wait no longer for the writer's backlog
        self._worker: Worker | None = None
        self._declared: list[object] = []
        self.repaired: dict[str, list] = {}
        self._fox_specs: dict[FoxgloveChannel, ChannelSpec] = {}
        self.foxglove_errors = 0  # messages whose conversion failed (their raw copy was recorded)
        self.foxglove_skipped = 0  # messages recorded raw only, while the writer was behind
        self._fox_behind_at = max(1, config.inbox_max // 10)
        self.last_session: Path | None = None
        self.launch_session = ""
        mf.software_versions()  # warm the cache: the first lookup is slow  # the session id of start_on_launch ("" = a generated one)

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        root = self.config.output_dir
        try:
            self.repaired = repair_all(root)
        except OSError as exc:  # an unreadable folder must not stop the service; starting will report it
            log.error("cannot check %s for sessions to repair: %s", root, exc)
        for name, results in self.repaired.items():
            log.warning("session %s was not closed: repaired %d segment(s), %d messages recovered", name,
                        len(results), sum(r.messages for r in results))
        self._repair_foxglove(root)
        if self.session is None:
            self.session = open_session(self.config.zenoh, stop=self.stop_event)
        s = self.session
        self._pub_status = s.declare_publisher(recorder_key(keys.RECORDER_STATUS))
        self._declared = [s.declare_subscriber(e, self._on_sample) for e in self.config.key_exprs]
        for action in (keys.RECORDER_START, keys.RECORDER_STOP, keys.RECORDER_ANNOTATE):
            self._declared.append(s.declare_queryable(recorder_key(action), self._query_handler(action)))
        # annotate/<author>: the author's own key (client.annotate), which the router binds to its certificate.
        self._declared.append(s.declare_queryable(recorder_key(f"{keys.RECORDER_ANNOTATE}/*"),
                                                  self._query_handler(keys.RECORDER_ANNOTATE)))
        self._declared.append(s.declare_queryable(recorder_key(keys.RECORDER_STATUS), self._on_status_query))
        self._worker = Worker("recorder-writer", self._writer_loop, self.stop_event)
        self._worker.start()
        if self.config.start_on_launch:
            self._accepting = True
            payload = RecorderRequest(session=self.launch_session).stamp(0).encode() if self.launch_session else b""
            self._inbox.put(_Control(keys.RECORDER_START, None, payload, time.monotonic_ns()))
        log.info("recorder up: recording %s into %s (start/stop on %s)", ", ".join(self.config.key_exprs),
                 root, recorder_key("{start,stop,annotate,status}"))

    def _repair_foxglove(self, root: Path) -> None:
        """Foxglove segments of unfinished sessions (a killed recorder, a full disk) get their footer back too:
        :func:`repair_all` repairs the session folder's own segments only. Until then the Foxglove app reads
        a footer-less file all the same, unindexed."""
        try:
            folders = [p.parent for p in root.glob(f"*/{FOXGLOVE}")] if root.is_dir() else []
        except OSError:
            return
        for folder in sorted(folders):
            try:
                status = mf.Manifest.read(folder).status
            except (OSError, ValueError):
                status = None
            if status == mf.COMPLETE or (status == mf.RECORDING and mf.writer_alive(folder, quiet_for=0.0)):
                continue  # closed cleanly, or another live process is writing it: never touched
            for path in sorted((folder / FOXGLOVE).glob("*.mcap")):
                try:
                    if not has_footer(path):
                        res = repair_segment(path)
                        log.warning("repaired %s: %d messages recovered", path, res.messages)
                except OSError as exc:
                    log.error("%s: cannot repair (%s)", path, exc)
                except SegmentError as exc:
                    set_aside(path, exc)

    def run_forever(self) -> None:
        self.start()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: self.stop_event.set())
        print("recorder ready", flush=True)
        self.stop_event.wait()
        self.shutdown()

    def shutdown(self) -> None:
        """Stop: a recording in progress is closed cleanly (footer, manifest ``complete``)."""
        self.stop_event.set()
        self._accepting = False
        if self._worker is not None:
            self._worker.join(timeout=SHUTDOWN_DRAIN_S)  # the writer records what is queued, then closes
            if self._worker.is_alive():  # a backlog too long to wait for: the writer counts it and closes
                self._abandon = True
                self._worker.join(timeout=SHUTDOWN_DRAIN_S)
        if self._worker is not None and self._worker.is_alive():
            # Never two threads on one file: the segments keep what reached them, and the next start repairs them.
            log.error("the recorder's writer did not stop within %g s: its segments are left as they are",
                      2 * SHUTDOWN_DRAIN_S)
        elif self._rec is not None:  # the worker crashed before it closed the recording
            self._stop_recording(None, "recorder shutting down")
        if self.last_session is not None and not (self._worker is not None and self._worker.is_alive()):
            # Whatever became of the last recording's manifest, no one writes it any more: readers may repair it.
            mf.release_writer_lock(self.last_session)
        for d in self._declared:
            with contextlib.suppress(zenoh.ZError):
                d.undeclare()  # type: ignore[attr-defined]
        if self.session is not None and self._own_session:
            self.session.close()
        self.session = None
        log.info("recorder stopped")

    @property
    def recording(self) -> bool:
        return self._rec is not None

    @property
    def status(self) -> RecorderStatus:
        with self._status_lock:
            return dataclasses.replace(self._status)

    # ------------------------------------------------------------------ Zenoh callbacks: hand over only

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if self._accepting:
            data = sample.payload.to_bytes()
            self._inbox.put((str(sample.key_expr), data, time.monotonic_ns()), len(data))

    def _query_handler(self, action: str) -> Callable[[zenoh.Query], None]:
        def handler(query: zenoh.Query) -> None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            if action == keys.RECORDER_START:
                self._accepting = True  # samples after this query queue behind it, so none is missed
            self._inbox.put(_Control(action, query, payload, time.monotonic_ns()))
            if action == keys.RECORDER_STOP:
                self._accepting = False

        return handler

    def _on_status_query(self, query: zenoh.Query) -> None:
        with self._status_lock:
            payload = self._status_bytes
        try:
            query.reply(query.key_expr, payload)
        finally:
            query.drop()

    # ------------------------------------------------------------------ the writer thread

    def _writer_loop(self, stop: threading.Event) -> None:
        cfg = self.config
        next_flush = time.monotonic() + cfg.flush_interval
        next_status = time.monotonic()
        while True:
            if stop.is_set() and (self._rec is None or len(self._inbox) == 0 or self._abandon):
                break
            now = time.monotonic()
            timeout = min(next_flush, next_status) - now if self._rec is not None else min(0.2, next_status - now)
            item = self._inbox.get(timeout=max(0.0, timeout))
            if isinstance(item, _Control):
                self._handle_control(item)
            elif item is not None and self._rec is not None:
                self._write_sample(*item)
            now = time.monotonic()
            if self._rec is not None and now >= next_flush:
                self._flush()
                next_flush = now + cfg.flush_interval
            if now >= next_status:
                self._publish_status()
                next_status = now + cfg.status_interval
        if self._rec is not None:
            if self._abandon:
                self._discard_queue(self._rec, "recorder shutting down")
            self._stop_recording(None, "recorder shutting down")

    def _discard_queue(self, rec: _Recording, reason: str) -> None:
        """What is still queued when the recording must end at once (a shutdown that could not wait for the
        backlog, a write error): queries are refused with ``reason``, samples counted as dropped."""
        left = 0
        for item in self._inbox.drain():
            if isinstance(item, _Control):
                self._refuse(item.query, reason)
            elif self._routing(item[0]) != SKIP:  # (what is never recorded is no loss)
                left += 1
        rec.unrecorded += left
        if left:
            log.error("session %s: %d queued samples not recorded (%s; counted as dropped)",
                      rec.manifest.session_id, left, reason)

    def _handle_control(self, item: _Control) -> None:
        if item.action == keys.RECORDER_START:
            self._start_recording(item)
        elif item.action == keys.RECORDER_STOP:
            self._stop_recording(item.query, "stopped on request")
        elif item.action == keys.RECORDER_ANNOTATE:
            self._annotate(item)

    def _reply(self, query: zenoh.Query | None, status: RecorderStatus) -> None:
        if query is None:
            return
        try:
            query.reply(query.key_expr, status.stamp(self._status_seq.next()).encode())
        except zenoh.ZError as exc:
            log.warning("could not answer %s: %s", query.key_expr, exc)
        finally:
            query.drop()

    def _refuse(self, query: zenoh.Query | None, reason: str) -> None:
        log.warning("refused: %s", reason)
        st = self._make_status()
        st.ok, st.reason = False, reason
        self._reply(query, st)

    # ------------------------------------------------------------------ start / stop

    def _start_recording(self, item: _Control) -> None:
        if self._rec is not None:
            self._refuse(item.query, f"already recording session {self._rec.manifest.session_id}")
            return
        try:
            req = RecorderRequest.decode(item.payload) if item.payload else RecorderRequest()
        except DecodeError as exc:
            self._accepting = False
            self._refuse(item.query, f"malformed start request: {exc}")
            return
        clock = RecordingClock.start()
        now = clock.wall0
        session_id = req.session or (
            f"{self.config.session_prefix}-{datetime.now().strftime('%Y%m%d-%H%M%S')}-{now // 1_000_000 % 1000:03d}"
        )
        problem = session_id_problem(session_id)
        if problem:
            self._accepting = False
            self._refuse(item.query, f"session id {session_id[:80]!r} is invalid: {problem}")
            return
        folder = self.config.output_dir / session_id
        attachments, warnings = self._calibration_attachments()
        manifest = mf.Manifest(
            session_id=session_id, operator=req.operator, robots=sorted(set(req.robots)), note=req.note,
            start_t=now, start_iso=mf.iso(now), software=mf.software_versions(), config=to_dict(self.config),
            attachments=[a.name for a in attachments], error="; ".join(warnings),
        )
        rec = _Recording(folder, manifest, {}, started_t=now, clock=clock, robot_ids=set(manifest.robots),
                         requested=frozenset(manifest.robots))
        try:
            folder.mkdir(parents=True, exist_ok=False)
            rec.streams = {
                TELEMETRY: self._stream(rec, TELEMETRY, COMPRESSION[TELEMETRY], self.config.segment_max_mb, attachments),
                VIDEO: self._stream(rec, VIDEO, COMPRESSION[VIDEO], self.config.video_segment_max_mb, []),
            }
            if self.config.foxglove.enabled:
                rec.streams[FOXGLOVE] = self._foxglove_stream(rec, attachments)
                rec.foxglove = FoxgloveConverter(video=self.config.foxglove.video)
            rec.streams[TELEMETRY].open_next()  # starting only opens a file
        except OSError as exc:
            self._accepting = False
            for st in rec.streams.values():
                st.abandon()
            reason = f"cannot record into {folder}: {_describe(exc)}"
            self._set_error(reason)
            self._refuse(item.query, reason)
            self._publish_status()
            return
        self._rec = rec
        self._last_error = ""
        self._dropped_at_start = self._inbox.dropped
        self.last_session = folder
        rec.last_manifest = time.monotonic()
        log.info("recording session %s into %s (operator %r)", session_id, folder, req.operator)
        st = self._make_status()
        st.reason = f"recording {session_id}"
        self._reply(item.query, st)
        # After the reply (it is not needed to answer): a folder with segments and no manifest is repaired too.
        try:
            manifest.write(folder, fsync=False, opener=self._opener)
        except OSError as exc:
            self._fail(f"cannot write the manifest of {session_id}: {_describe(exc)}")
            return
        self._publish_status()

    def _stream(self, rec: _Recording, name: str, compression: CompressionType, max_mb: float,
                attachments: list[Attachment]) -> Stream:
        def on_open(seg: Segment) -> None:
            info = mf.SegmentInfo(file=seg.path.name, stream=name, compression=compression.name.lower(),
                                  opened_t=seg.opened_t)
            rec.seg_info[seg.path.name] = info
            rec.manifest.segments.append(info)

        def on_close(seg: Segment) -> None:
            info = rec.seg_info[seg.path.name]
            info.closed_t, info.messages, info.status = rec.clock(), seg.messages, "closed"
            with contextlib.suppress(OSError):
                info.bytes = seg.path.stat().st_size

        return Stream(
            name=name, folder=rec.folder, compression=compression, max_bytes=int(max_mb * 1024 * 1024),
            max_seconds=self.config.segment_max_s, chunk_size=self.config.chunk_kb * 1024,
            attachments=attachments, on_open=on_open, on_close=on_close, opener=self._opener, clock=rec.clock,
        )

    def _foxglove_stream(self, rec: _Recording, attachments: list[Attachment]) -> Stream:
        """One file for all the Foxglove channels, so the app shows a session from one file. Uncompressed when
        it holds the pictures: zstd does not shrink JPEG or H.264 and took 1.5 ms of CPU per 150 kB frame here
        (the raw video files are uncompressed for the same reason); the telemetry it then leaves uncompressed
        is a few per cent of the video's bytes. Its segments are not listed in the manifest, which describes
        the raw recording only."""
        compression = CompressionType.NONE if self.config.foxglove.video else CompressionType.ZSTD
        return Stream(
            name=FOXGLOVE, folder=rec.folder / FOXGLOVE, compression=compression,
            max_bytes=int(self.config.video_segment_max_mb * 1024 * 1024), max_seconds=self.config.segment_max_s,
            chunk_size=self.config.chunk_kb * 1024, attachments=attachments, opener=self._opener, make_folder=True,
            clock=rec.clock,
        )

    def _calibration_attachments(self) -> tuple[list[Attachment], list[str]]:
        """The calibration files to attach to each segment, and a warning for each that is not. Readers refuse
        larger attachments (reader.MAX_ATTACHMENT_BYTES each, MAX_ATTACHMENTS_BYTES together): one is not
        attached rather than making the session unreadable (a path to a device, such as /dev/zero, never ends)."""
        out: list[Attachment] = []
        warnings: list[str] = []
        taken = 0
        for path in self.config.calibration_files:
            try:
                with path.open("rb") as f:
                    data = f.read(MAX_ATTACHMENT_BYTES + 1)
                    mtime = os.fstat(f.fileno()).st_mtime_ns
            except OSError as exc:
                warnings.append(f"calibration file {path} not attached: {_describe(exc)}")
                log.warning("%s", warnings[-1])
                continue
            if len(data) > MAX_ATTACHMENT_BYTES or taken + len(data) > MAX_ATTACHMENTS_BYTES:
                warnings.append(f"calibration file {path} not attached: larger than "
                                f"{MAX_ATTACHMENT_BYTES // 2**20} MiB, or with the files before it than "
                                f"{MAX_ATTACHMENTS_BYTES // 2**20} MiB (not a calibration)")
                log.warning("%s", warnings[-1])
                continue
            taken += len(data)
            out.append(Attachment(path.name, "application/yaml" if path.suffix in (".yaml", ".yml")
                                  else "application/octet-stream", data, int(mtime)))
        return out, warnings

    def _stop_recording(self, query: zenoh.Query | None, reason: str) -> None:
        rec = self._rec
        if rec is None:
            self._refuse(query, "not recording" + (f" (last error: {self._last_error})" if self._last_error else ""))
            return
        try:
            for stream in rec.streams.values():
                # No fsync before the reply: the footer is in the kernel's hands (safe from a killed process);
                # the fsyncs (~10 ms each here) follow the reply instead of delaying it.
                stream.close(fsync=False)
        except OSError as exc:
            self._fail(f"cannot close the segments of {rec.manifest.session_id}: {_describe(exc)}")
            self._refuse(query, self._last_error)
            return
        closed = rec.clock()
        m = rec.manifest
        m.status, m.stop_t, m.stop_iso = mf.COMPLETE, closed, mf.iso(closed)
        m.dropped = self._dropped(rec)
        st = self._make_status()
        st.closed_t, st.reason = closed, reason
        self._rec = None
        self._accepting = False
        st.recording = False
        try:  # before the reply: a report run as soon as stop returns must find the final manifest
            self._write_final_manifest(rec, fsync=False)
        finally:
            mf.release_writer_lock(rec.folder)
        self._reply(query, st)
        t = mf.totals(m.keys)
        log.info("session %s closed (%s): %d messages, %d malformed, %d missing by sequence, %d dropped",
                 m.session_id, reason, t["messages"], t["malformed"], t["missing"], m.dropped)
        self._publish_status()
        if self.config.fsync:
            paths = [p for s in rec.streams.values() for p in s.closed] + [rec.folder / mf.MANIFEST]
            _fsync(paths)

    def _fail(self, reason: str) -> None:
        """Stop the recording after an error, keep what was written, and say so everywhere."""
        rec, self._rec = self._rec, None
        self._accepting = False
        self._set_error(reason)
        log.error("recording stopped: %s", reason)
        if rec is not None:
            try:
                # What waited in the queue is answered and counted, never silently thrown away.
                self._discard_queue(rec, f"recording {rec.manifest.session_id} stopped: {reason}")
                for stream in rec.streams.values():
                    try:
                        stream.close()
                    except OSError:
                        stream.abandon()
                m = rec.manifest
                stopped = rec.clock()
                m.status, m.error, m.stop_t, m.stop_iso = mf.FAILED, reason, stopped, mf.iso(stopped)
                m.dropped = self._dropped(rec)
                self._write_final_manifest(rec, fsync=True)
            finally:
                mf.release_writer_lock(rec.folder)  # no longer written: readers may repair it
        self._publish_status()

    def _write_final_manifest(self, rec: _Recording, fsync: bool) -> None:
        """The manifest with its final status; when the disk refuses it, the reason goes where a later repair
        finds it (:func:`~iorthand_cloud.recorder.manifest.note_failure`), so the session does not read as a
        crash."""
        m = rec.manifest
        try:
            m.write(rec.folder, fsync=fsync, opener=self._opener)
            return
        except OSError as exc:
            log.error("session %s: manifest not written: %s", m.session_id, _describe(exc))
            note = m.error if m.status == mf.FAILED else ""
            note = (f"{note}; " if note else "") + f"final manifest not written: {_describe(exc)}"
        try:
            mf.note_failure(rec.folder, note)
        except OSError as exc:
            log.error("session %s: the failure could not be noted either: %s", m.session_id, _describe(exc))

    def _set_error(self, reason: str) -> None:
        self._last_error = reason

    # ------------------------------------------------------------------ samples

    def _routing(self, key: str) -> str:
        route = self._route.get(key)
        if route is None:
            try:
                ke = zenoh.KeyExpr(key)
                if any(x.intersects(ke) for x in self._exclude):
                    route = SKIP
                elif any(x.intersects(ke) for x in self._video):
                    route = VIDEO
                else:
                    route = TELEMETRY
            except zenoh.ZError:
                route = TELEMETRY
            if len(self._route) >= 2 * self.config.max_keys:  # a cache: keys named by a flood must not pile up
                self._route.clear()
            self._route[key] = route
        return route

    def _spec(self, key: str, malformed: bool) -> ChannelSpec:
        spec = self._specs.get((key, malformed))
        if spec is None:
            cls = None if malformed else message_type_for(key)
            if key == recorder_key(keys.RECORDER_ANNOTATIONS):
                cls = Annotation
            if cls is None:
                spec = ChannelSpec(key, RAW_ENCODING, malformed=malformed)
            else:
                spec = ChannelSpec(key, MESSAGE_ENCODING, cls.__name__, SCHEMA_ENCODING, schema_bytes(cls))
            if len(self._specs) >= 4 * self.config.max_keys:  # a cache too (two per key), across recordings
                self._specs.clear()
            self._specs[(key, malformed)] = spec
        return spec

    def _write_sample(self, key: str, payload: bytes, recv_mono: int) -> None:
        rec = self._rec
        assert rec is not None
        recv_ns = rec.clock.wall(recv_mono)
        route = self._routing(key)
        if route == SKIP:
            return
        stats = rec.manifest.keys.get(key)
        if stats is None:
            robot = keys.robot_of(key)
            requested = robot in rec.requested
            if rec.keys_held(requested) >= self.config.max_keys:
                self._unrecorded(rec, key)
                return
        cls = message_type_for(key)
        seq: int | None = None
        t = recv_ns
        malformed = False
        msg = None
        if cls is not None:
            try:
                msg = cls.decode(payload)
                seq, t = msg.seq, msg.t or recv_ns
            except DecodeError as exc:
                malformed = True
                if stats is None or stats.malformed == 0:
                    log.warning("malformed payload on %s stored raw: %s", key, exc)
        if stats is None:
            stats = rec.manifest.keys[key] = mf.KeyStats(type=cls.__name__ if cls else "")
            rec.keys_of_others += not requested
            if robot and robot not in rec.robot_ids:
                rec.robot_ids.add(robot)
                rec.manifest.robots = sorted(rec.robot_ids)
        stats.observe(len(payload), recv_ns, seq, malformed)
        stream = rec.streams[route]
        try:
            stream.write(self._spec(key, malformed), recv_ns, t, seq or 0, payload)
            if not rec.first_message_t:
                # The first message goes to disk at once: "start" is complete when data is in the file.
                stream.flush(fsync=False)
                rec.first_message_t = rec.clock()
            if msg is not None and rec.foxglove is not None:
                if len(self._inbox) >= self._fox_behind_at:  # behind: the raw recording first
                    self._skip_foxglove(key)
                else:
                    stream = rec.streams[FOXGLOVE]  # (the error below then names this file)
                    self._write_foxglove(rec.foxglove, stream, key, msg, recv_ns, seq or 0)
        except OSError as exc:
            self._fail(f"cannot write {stream.current.path if stream.current else rec.folder}: {_describe(exc)}")

    def _unrecorded(self, rec: _Recording, key: str) -> None:
        """A sample on a key beyond ``max_keys``: counted among the dropped, never recorded. Anyone who may
        publish can name new keys, and each one costs memory, a channel in the file and a line in the manifest.
        The robots the start request named have a quota of their own, so that a flood of other keys before
        their edges publish cannot leave them out."""
        rec.unrecorded += 1
        if rec.unrecorded == 1 or rec.unrecorded % 10_000 == 0:
            log.warning("session %s records at most %d keys (max_keys): %d samples on other keys not recorded, "
                        "counted as dropped (latest on %r)", rec.manifest.session_id, self.config.max_keys,
                        rec.unrecorded, key[:200])

    def _dropped(self, rec: _Recording) -> int:
        """The samples of this recording that the recorder lost: its queue full, keys beyond max_keys, and
        what was still queued when a shutdown could wait no longer."""
        return self._inbox.dropped - self._dropped_at_start + rec.unrecorded

    def _skip_foxglove(self, key: str) -> None:
        self.foxglove_skipped += 1
        if self.foxglove_skipped == 1 or self.foxglove_skipped % 10_000 == 0:
            log.warning("the writer is behind (%d queued): %d messages recorded raw only, without their Foxglove "
                        "channels (latest on %s)", len(self._inbox), self.foxglove_skipped, key)

    def _write_foxglove(self, conv: FoxgloveConverter, stream: Stream, key: str, msg: Message, recv_ns: int,
                        seq: int) -> None:
        """The Foxglove messages made from ``msg``, with the raw message's receive time and sequence (so each
        lines up with its source in time and order). Write errors (OSError) are the caller's: same disk."""
        try:
            out = conv.convert(key, msg, recv_ns)  # log time: a recording converts the same way again
        except Exception as exc:  # a conversion bug must never cost the raw recording, which is already written
            self.foxglove_errors += 1
            if self.foxglove_errors == 1 or self.foxglove_errors % 1000 == 0:
                log.error("Foxglove conversion of %s failed (%d so far; raw copies kept): %r", key,
                          self.foxglove_errors, exc)
            return
        for m in out:
            spec = self._fox_specs.get(m.channel)
            if spec is None:
                ch = m.channel
                spec = self._fox_specs[ch] = ChannelSpec(
                    ch.topic, ch.message_encoding, ch.schema_name, ch.schema_encoding, ch.schema,
                    extra_metadata=tuple(ch.metadata.items()))
            stream.write(spec, recv_ns, m.t, seq, m.data)

    def _annotate(self, item: _Control) -> None:
        rec = self._rec
        try:
            ann = Annotation.decode(item.payload)
        except DecodeError as exc:
            self._refuse(item.query, f"malformed annotation: {exc}")
            return
        keyed = _keyed_author(item.query)
        if keyed is not None and ann.author != keyed:
            self._refuse(item.query, f"annotation by {ann.author[:64]!r} sent on {keyed!r}'s key: an annotation's author "
                         "is the one its key names (the router lets only that operator's certificate use it)")
            return
        if rec is None:
            self._refuse(item.query, "no recording in progress: the annotation was not stored")
            return
        key = recorder_key(keys.RECORDER_ANNOTATIONS)
        recv_ns = rec.clock.wall(item.recv_mono)
        try:
            rec.streams[TELEMETRY].write(self._spec(key, False), recv_ns, ann.t or recv_ns, ann.seq, item.payload)
            if rec.foxglove is not None:
                self._write_foxglove(rec.foxglove, rec.streams[FOXGLOVE], key, ann, recv_ns, ann.seq)
        except OSError as exc:
            self._fail(f"cannot write an annotation: {_describe(exc)}")
            self._refuse(item.query, self._last_error)
            return
        rec.manifest.annotations += 1
        log.info("annotation by %r: %r", ann.author, ann.text[:80])  # repr: a newline in it forges no log line
        st = self._make_status()
        st.reason = "annotation stored"
        self._reply(item.query, st)

    def _flush(self) -> None:
        rec = self._rec
        if rec is None:
            return
        try:
            for stream in rec.streams.values():
                stream.flush(self.config.fsync)
            if time.monotonic() - rec.last_manifest >= self.config.manifest_interval:
                rec.manifest.dropped = self._dropped(rec)
                rec.manifest.write(rec.folder, fsync=self.config.fsync, opener=self._opener)
                rec.last_manifest = time.monotonic()
        except OSError as exc:
            self._fail(f"cannot write session {rec.manifest.session_id}: {_describe(exc)}")

    # ------------------------------------------------------------------ status

    def _make_status(self) -> RecorderStatus:
        rec = self._rec
        if rec is None:
            return RecorderStatus(ok=not self._last_error, reason="idle", error=self._last_error,
                                  dropped=self._inbox.dropped)
        t = mf.totals(rec.manifest.keys)
        return RecorderStatus(
            ok=True, reason="recording", recording=True, session=rec.manifest.session_id, path=str(rec.folder),
            messages=t["messages"], bytes=t["bytes"], malformed=t["malformed"], gaps=t["missing"],
            dropped=self._dropped(rec), started_t=rec.started_t,
            first_message_t=rec.first_message_t,
        )

    def _publish_status(self) -> None:
        st = self._make_status()
        if self._rec is None and self.last_session is not None:
            st.session, st.path = self.last_session.name, str(self.last_session)
        payload = st.stamp(self._status_seq.next()).encode()
        with self._status_lock:
            self._status, self._status_bytes = st, payload
        try:
            self._pub_status.put(payload)
        except zenoh.ZError as exc:
            log.warning("status not published: %s", exc)


def _fsync(paths: list[Path]) -> None:
    for p in paths:
        try:
            fd = os.open(p, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        except OSError as exc:
            log.warning("fsync %s: %s", p, exc)


def _describe(exc: OSError) -> str:
    if exc.errno == errno.ENOSPC:
        return f"disk full ({exc.strerror})"
    if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return f"folder not writable ({exc.strerror}: {exc.filename or ''})"
    return f"{exc.strerror or exc} ({exc.filename or ''})".replace(" ()", "")
