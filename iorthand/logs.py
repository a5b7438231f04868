"""Where every iorthand process's log lines go: its stderr (journald under systemd), never blocking the caller.

A write to stderr blocks once nobody reads it: a terminal paused with Ctrl-S, ``iorthand edge | less`` scrolled
back, a log collector that stalls. Written from the calling thread, as ``logging.basicConfig`` does, the first
line logged after that froze whichever thread logged it, and the edge stopped answering operators (its control
requests timed out, ``tests/test_edge_process_faults.py``). Here a caller only queues its line (formatted, so
the record holds no reference to live objects); one writer thread writes them. A line that finds the queue full,
or that stderr refuses, is counted, and the count is written as soon as stderr takes lines again: no thread waits
for the terminal, and no line is lost without a word while the process runs (at its end it waits up to
``DRAIN_AT_EXIT_S`` for stderr to take what is left)."""

from __future__ import annotations

import atexit
import logging
import logging.handlers
import os
import queue
import sys
import threading

from iorthand.process import name_thread

FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
# Lines waiting for stderr: about 2 MB of typical lines, minutes of the edge's logging at its worst.
MAX_PENDING = 10_000
# How long a process that ends waits for its waiting lines to be written (stderr may never take them).
DRAIN_AT_EXIT_S = 1.0


class _Writer(logging.Handler):
    """Writes queued lines to the stderr file descriptor; counts what it refused and what the queue had no room
    for. By ``os.write``, not through ``sys.stderr``: a thread blocked in ``sys.stderr`` holds its buffer's lock,
    and the interpreter's own flush of it at exit then waits for ever (the process never ended)."""

    def __init__(self, fd: int) -> None:
        super().__init__()
        self.fd = fd
        self.lost = 0  # by the queue (full) and by stderr (an error): said at the next line that is written
        self._lock_lost = threading.Lock()

    def add_lost(self, count: int = 1) -> None:
        with self._lock_lost:
            self.lost += count

    def handle(self, record: logging.LogRecord) -> bool:
        with self._lock_lost:
            lost, self.lost = self.lost, 0
        if lost:
            note = logging.makeLogRecord({
                "name": __name__, "levelno": logging.WARNING, "levelname": "WARNING", "lines_lost_before": lost,
                "msg": f"{lost} log line(s) lost: stderr was not taking them (blocked, full or closed)"})
            self.emit(note)
        # Not Handler.handle: it holds the handler's lock around the write, and logging's own shutdown at exit takes
        # that lock. One thread writes: no lock is needed.
        if self.filter(record):
            self.emit(record)
            return True
        return False

    def emit(self, record: logging.LogRecord) -> None:
        try:
            data = (self.format(record) + "\n").encode(errors="backslashreplace")
            while data:
                data = data[os.write(self.fd, data):]
        except Exception:  # an OSError of the stream, or a record that cannot be formatted
            self.handleError(record)

    def handleError(self, record: logging.LogRecord) -> None:
        # Not reported: the report would go to stderr, the very stream that failed. A failed note of lost lines
        # gives its count back.
        self.add_lost(getattr(record, "lines_lost_before", 1))


class _Queueing(logging.handlers.QueueHandler):
    """Puts a formatted line on the queue without waiting: a full queue loses the line, counted."""

    def __init__(self, lines: queue.Queue[logging.LogRecord | threading.Event], writer: _Writer) -> None:
        super().__init__(lines)
        self._writer = writer

    def enqueue(self, record: logging.LogRecord) -> None:
        try:
            self.queue.put_nowait(record)
        except queue.Full:
            self._writer.add_lost()


_pending: queue.Queue[logging.LogRecord | threading.Event] | None = None  # set by setup()


def setup(level: int | str) -> None:
    """Log at ``level`` and above to stderr through a writer thread (see the module's docstring). Call it once,
    at the start of a process, before its threads start. As ``logging.basicConfig``, it leaves a logging that is
    already set up (a test's, when a command runs in its process) as it is."""
    global _pending
    root = logging.getLogger()
    if root.handlers:
        return
    level = level if isinstance(level, int) else level.upper()
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):  # no stderr, or one that is no file (a harness's capture)
        logging.basicConfig(level=level, format=FORMAT)
        return
    root.setLevel(level)
    lines: queue.Queue[logging.LogRecord | threading.Event] = queue.Queue(MAX_PENDING)
    writer = _Writer(fd)
    writer.setFormatter(logging.Formatter(FORMAT))
    root.addHandler(_Queueing(lines, writer))

    def write() -> None:
        name_thread("log-writer")
        while True:
            item = lines.get()
            if isinstance(item, threading.Event):
                item.set()  # a flush: every line before it is written
            else:
                writer.handle(item)

    threading.Thread(target=write, name="log-writer", daemon=True).start()
    _pending = lines
    atexit.register(flush)


def flush(timeout: float = DRAIN_AT_EXIT_S) -> None:
    """Wait up to ``timeout`` for the lines logged so far to be written: before ``os._exit`` (atexit does it for
    a normal exit). Gives up after ``timeout`` if stderr does not take them."""
    if _pending is None:
        return
    written = threading.Event()
    try:
        _pending.put(written, timeout=timeout)
    except queue.Full:
        return
    written.wait(timeout)
