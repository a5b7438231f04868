"""Route planning in a process of its own, beside the control process.

A plan is inverse kinematics at every few millimetres of the path, in Python: up to ~2 s of CPU for the longest
sweep. Planned in the control process it held the GIL against the control loop: back-to-back previews of that
sweep stretched the gaps between robot states from 8 ms to 36 ms (four missed cycles; a deadman stop waits for
the loop). Here the edge's planner thread waits for a child, which holds no lock of the control process's, at a
lower CPU priority than it (the media process's), and dies with the edge.

The child starts at the first plan (~0.25 s) and is replaced after one that overran ``timeout``. One that ends
by itself (the out-of-memory killer) is reaped and logged with why at once, and replaced at the next plan.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import threading
from collections.abc import Mapping, Sequence
from multiprocessing.connection import Connection
from typing import Any

from numpy.typing import ArrayLike

from iorthand import motion
from iorthand.process import enter_child, exit_reason, name_thread

log = logging.getLogger("iorthand.edge.planner")

PLANNER_NICE = 10  # as the media process (iorthand_edge.media.MEDIA_NICE): the control process runs first
PLAN_TIMEOUT_S = 10.0  # five times the longest sweep's plan here: beyond it the planner is stuck, not slow


class PlanningTimeout(TimeoutError):
    """A plan overran its time; the child that planned it was stopped."""


def _enter_planner(parent_pid: int) -> None:
    enter_child(parent_pid)
    name_thread("iorthand-planner")
    with contextlib.suppress(AttributeError, OSError):
        os.setpriority(os.PRIO_PROCESS, 0, PLANNER_NICE)


class PlannerProcess:
    """:func:`iorthand.motion.plan_route` in a spawned child, one plan at a time (the caller: one thread)."""

    def __init__(self, timeout: float = PLAN_TIMEOUT_S) -> None:
        self.timeout = timeout
        self._child: multiprocessing.process.BaseProcess | None = None
        self._conn: Connection | None = None
        # One thread at a time collects a child's exit status: two waiting at once (the reaper and close()), the
        # loser's waitpid failed and the child read as alive after it had ended (a test's is_alive, under load).
        self._collect = threading.Lock()

    def plan_route(self, name: str, current: ArrayLike, limits: motion.Limits, poses: Mapping[str, Sequence[float]],
                   *args: Any, **kwargs: Any) -> motion.Route:
        """:func:`iorthand.motion.plan_route`'s answer; PlanningTimeout if it takes longer than ``timeout``."""
        request = ((name, current, limits, poses, *args), kwargs)
        conn = self._conn or self._start()
        try:
            conn.send(request)
        except OSError:
            # It ended since the last plan (logged by _reap; is_alive cannot tell, as the reaper may have taken its
            # exit status first): nothing of this plan was done, a new child plans it.
            self.close()
            conn = self._start()
            conn.send(request)
        if not conn.poll(self.timeout):
            self.close()
            log.error("planning %r took longer than %g s: planner restarted", name, self.timeout)
            raise PlanningTimeout(f"planning {name!r} took longer than {self.timeout:g} s")
        try:
            ok, answer = conn.recv()
        except EOFError:
            self.close()
            raise RuntimeError(f"the planner process ended while planning {name!r}") from None
        if not ok:
            raise answer  # planning's own exception, as it would have been raised here
        return answer  # type: ignore[no-any-return]

    def _start(self) -> Connection:
        context = multiprocessing.get_context("spawn")
        self._conn, theirs = context.Pipe()
        self._child = context.Process(target=_serve, args=(theirs, os.getpid()), name="iorthand-planner", daemon=True)
        self._child.start()
        theirs.close()
        threading.Thread(target=self._reap, args=(self._child,), name="edge-planner-reap", daemon=True).start()
        return self._conn

    def _reap(self, child: multiprocessing.process.BaseProcess) -> None:
        """Wait for ``child`` to end. Killed between plans (the OOM killer), it stayed a zombie and unmentioned
        until the next preview, which may never come: now it is reaped, and logged with why, at once."""
        name_thread("edge-planner-reap")
        multiprocessing.connection.wait([child.sentinel])  # ended (its status not collected yet)
        with self._collect:
            child.join()
        if self._child is child:  # not ended by close()
            log.error("the planner process %s: a new one starts at the next plan", exit_reason(child.exitcode))

    def close(self) -> None:
        child, self._child = self._child, None  # first: its reaper then knows that it was ended on purpose
        if child is not None:
            child.kill()
            with self._collect:
                child.join(2.0)
        if self._conn is not None:
            self._conn.close()
            self._conn = None


def _serve(conn: Connection, parent_pid: int) -> None:
    """The child: plan what arrives, answer (True, route) or (False, the exception), until the pipe closes."""
    _enter_planner(parent_pid)
    while True:
        try:
            args, kwargs = conn.recv()
        except EOFError:
            return
        try:
            conn.send((True, motion.plan_route(*args, **kwargs)))
        except Exception as exc:  # a bug in planning: raised in the edge's planner thread, logged there
            conn.send((False, exc))


__all__ = ["PLAN_TIMEOUT_S", "PlannerProcess", "PlanningTimeout"]
