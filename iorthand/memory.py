"""Giving freed memory back to the system (glibc's malloc), for long-running roles that must not keep what a
burst of input made them allocate.

glibc keeps freed memory in its arenas for reuse and returns only a free chunk at the very top of a heap.
Every thread that allocates under contention gets an arena of its own (up to 8 per core): Zenoh's receive
threads, the Python threads that decode what they receive. After a flood of hostile input the edge held on to
what the flood had made it allocate: 10 s after 100 000 malformed messages and 20 payloads of 10 MB its RSS
was still 30 MB above the start, with 16–25 MB of it free in malloc's arenas (mallinfo2) while malloc's
memory in use was back where it started (benchmarks/bench_flood_memory.py, with the size limits of
:mod:`iorthand.transport` in place). With the trimmer running in the edge: 9.3 MB above (peak +16.8 MB).

:class:`Trimmer` calls ``malloc_trim(0)``, which also releases the free pages inside a heap, when malloc holds
markedly more free memory than in steady state and RSS has grown: during a burst and after it. In steady
state that does not happen and nothing is trimmed (a trim locks each arena while it walks it: 0.2 ms with
nothing to return, 7 ms returning 30 MB). Where the C library is not
glibc (or older than 2.33) it does nothing. Fewer arenas (``MALLOC_ARENA_MAX=2``) retained less too, but
would have to be set in every environment the edge runs in, and make Zenoh's threads share an arena's lock.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import threading

log = logging.getLogger(__name__)

_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]


def _glibc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        libc = ctypes.CDLL(name)
    except OSError:
        return None
    # musl and others have neither; glibc before 2.33 has no mallinfo2: nothing to watch and return this way.
    if not (hasattr(libc, "malloc_trim") and hasattr(libc, "mallinfo2")):
        return None
    libc.mallinfo2.restype = _MallInfo2
    return libc


_LIBC = _glibc()


def release_free_memory() -> bool:
    """Return the free memory of every arena to the system; True if some was returned."""
    return _LIBC is not None and bool(_LIBC.malloc_trim(0))


def malloc_free_bytes() -> int:
    """Bytes that malloc holds free in its arenas (returned to the system or not); 0 without glibc."""
    return int(_LIBC.mallinfo2().fordblks) if _LIBC is not None else 0


def rss_bytes() -> int:
    """This process's resident set size (Linux; 0 where /proc is not there)."""
    try:
        with open("/proc/self/statm", "rb") as f:
            return int(f.read().split()[1]) * _PAGE
    except (OSError, IndexError, ValueError):
        return 0


class Trimmer(threading.Thread):
    """A daemon thread that calls :func:`release_free_memory` when there is something to return: malloc holds
    ``slack`` bytes more free than its lowest (the steady state's working slack) *and* RSS has grown by
    ``slack / 2`` since the last trim (or the start), checked every ``interval`` s.

    Both are needed. Free memory alone stays high after a flood, since the heap it leaves is fragmented, and
    would trim at every check; RSS alone misses what a burst frees as it ends (queues draining: RSS does not
    change). And a trim is not once and for all: steady-state allocations land in the fragmented free space
    and bring its pages back (measured: RSS 104 → 120 MB in 30 s after a flood), so trims follow as RSS grows
    again, each returning what came back. ``trims`` counts them; ``stop()`` ends the thread."""

    def __init__(self, interval: float = 2.0, slack: int = 8 * 2**20) -> None:
        super().__init__(name="memory-trimmer", daemon=True)
        self.interval = interval
        self.slack = slack
        self.trims = 0
        self._stop_event = threading.Event()

    def start(self) -> None:
        # The baseline is taken here, in the caller's thread, when it starts us: taken in run() it could come
        # after what the caller allocates next, and a burst already in RSS would never count as growth.
        self._floor, self._level = malloc_free_bytes(), rss_bytes()
        super().start()

    def run(self) -> None:
        if _LIBC is None:
            return
        floor, level = self._floor, self._level
        while not self._stop_event.wait(self.interval):
            free, rss = malloc_free_bytes(), rss_bytes()
            floor = min(floor, free)
            if free <= floor + self.slack or rss <= level + self.slack // 2:
                level = min(level, rss)
                continue
            release_free_memory()
            self.trims += 1
            level = rss_bytes()
            log.info("returned %.1f MB of freed memory to the system (RSS %.1f MB)", (rss - level) / 2**20,
                     level / 2**20)

    def stop(self) -> None:
        self._stop_event.set()
