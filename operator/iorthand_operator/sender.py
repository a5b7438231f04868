"""The operator's command sender in its own process, so a busy UI in the client's interpreter cannot starve it.

A Python thread that must wake every 16.7 ms shares the GIL with the console: measured with a busy console
(benchmarks/bench_sender.py) the thread sender's jitter p99 was 74 ms with gaps up to 134 ms. This module runs
the fixed-rate loop in a child process (``spawn``: a fresh interpreter, never a fork of a process holding Zenoh
threads) that opens its own Zenoh session, publishes ``TwistCommand`` on the client's twist key with the same
QoS, and does nothing else.

Parent → child: a small shared array written under a seqlock (even generation = stable) by the parent's
``set_twist``, ``muted`` and a heartbeat thread. The child never blocks on the parent: a snapshot it cannot
read consistently in a few tries is replaced by its previous one.

Safety: if the parent's heartbeat is older than ``ui_timeout`` the child treats the deadman as released (zero
twists with ``deadman=False`` for ``release_tail``, then quiet): a frozen UI must not keep the robot moving.
The child exits when the parent dies (PR_SET_PDEATHSIG, a parent-pid check every tick, a broken pipe).

Child → parent: one record per send (seq, send time, monotonic send instant, grant, deadman flag) through a pipe,
written before the put, so the parent can match the edge's echo to its send time exactly as with the thread sender
and show what the stream sends; and, if the child fails, why (``E``), before it exits with code 1.

A child that ends while the parent did not ask it to (killed, crashed) is reported to the parent
(``on_lost``, with how it ended), which may start another with :meth:`ProcessSender.start`: the new child goes on
with the grant's sequence where the records say the last one left it (the edge refuses a sequence that goes back).

What each tick sends is decided in one place for both senders, :class:`CommandStream` (the deadman released
when the UI is silent, the quiet tail after a release, a sequence that restarts with every grant of control,
the age of the robot state the operator sees, the signature with the grant's key); :func:`run_fixed_rate`
keeps the schedule for both.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import multiprocessing as mp
import os
import struct
import sys
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any

from iorthand import keys
from iorthand.process import enter_child, exit_reason, raise_priority
from iorthand.protocol import TWIST_FRAMES, TwistCommand
from iorthand.security import auth

log = logging.getLogger("iorthand.operator.sender")

# Shared array layout (doubles). The grant's key (bytes) is in a second array, written under the same seqlock.
_GEN, _TWIST, _DEADMAN, _MUTED, _RELEASED, _HEARTBEAT, _STOP, _STATE_T, _KEY_GEN, _PRESSED, _PRESS_FROM, _HALTED, _FRAME = (
    0, 1, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17)
_SIZE = 18
_FIELDS = {"deadman": _DEADMAN, "muted": _MUTED, "released_at": _RELEASED, "heartbeat": _HEARTBEAT, "stop": _STOP,
           "state_t": _STATE_T, "key_gen": _KEY_GEN, "pressed_at": _PRESSED, "press_from": _PRESS_FROM, "halted_at": _HALTED,
           "frame": _FRAME}
# seq, t (ns), monotonic send instant (s), the grant (key_gen) seq counts in, the command's deadman flag
_RECORD = struct.Struct("<qqdd?")
# The most a command's state_age may say (the protocol's bound, s): an edge whose clock reads 1970 stamps its
# states 56 years before ours, and a command saying so was malformed at the edge, dropped unanswered: the operator
# never heard why nothing moved. At the bound it arrives, and the edge's refusal names the clocks.
_STATE_AGE_MAX = next(f.metadata["hi"] for f in dataclasses.fields(TwistCommand) if f.name == "state_age")


@contextlib.contextmanager
def _real_std_streams():
    """multiprocessing hands sys.stderr's fd to its helpers; a UI that captures the streams (textual) has none:
    use the process's real streams while the child starts."""
    saved = sys.stdout, sys.stderr
    try:
        for name in ("stdout", "stderr"):
            try:
                ok = getattr(sys, name).fileno() >= 0
            except (AttributeError, OSError, ValueError):
                ok = False
            if not ok and getattr(sys, f"__{name}__", None) is not None:
                setattr(sys, name, getattr(sys, f"__{name}__"))
        yield
    finally:
        sys.stdout, sys.stderr = saved


class CommandStream:
    """What the sender sends at each tick, for the thread and the process sender alike. No I/O.

    ``next`` gets the client's current intent and returns the signed command to send and its payload, or None (quiet: the
    deadman released for longer than ``release_tail``, muted, or no key yet). The deadman counts as released
    while the UI's heartbeat is older than ``ui_timeout`` (a frozen UI must not keep the robot moving). Each new
    key (a new grant of control) restarts the sequence at 1, as the edge expects, and its first command is a
    release: the edge moves nothing under a grant before it has seen the deadman released and pressed. A press
    that began before ``press_from`` (the grant: the client re-acquired by itself, after an edge restart or a lost
    lease; or the restart of a sender process that died) counts as released until the operator releases and
    presses again. A press that begins after the edge halted in a state that waits for a fresh press
    (``halted_at``: a stop, a long gap) is that fresh intent: if no release has gone out since the halt, this tick
    sends one, and the press the next."""

    def __init__(self, robot: str, operator_id: str, release_tail: float, ui_timeout: float) -> None:
        self.operator_id = operator_id
        self.release_tail = release_tail
        self.ui_timeout = ui_timeout
        self.ctx = auth.context(robot, keys.CMD_TWIST)
        self.seq = 0
        self.key_gen = -1.0  # the grant whose commands ``seq`` counts
        self._release_first = False
        self._stale_since: float | None = None
        self._release_sent_at = -math.inf  # monotonic time of the last command with the deadman released

    def next(self, now: float, twist: Any, deadman: bool, released_at: float, muted: bool, heartbeat: float,
             state_t: float, key_gen: float, key: bytes, pressed_at: float = 0.0,
             press_from: float = 0.0, halted_at: float = -math.inf,
             frame: str = "base") -> tuple[TwistCommand, bytes] | None:
        if now - heartbeat > self.ui_timeout:  # the UI is frozen (or gone): release the deadman
            if self._stale_since is None:
                self._stale_since = now
                log.warning("operator UI silent for %.2f s: releasing the deadman", now - heartbeat)
            released_at = self._stale_since if deadman else released_at
            deadman = False
        else:
            self._stale_since = None
        if key_gen != self.key_gen:
            self.key_gen, self.seq, self._release_first = key_gen, 0, True
        if deadman and pressed_at < press_from:  # held from before the grant (or restart): no intent to move now
            deadman, released_at = False, max(released_at, press_from)
        if muted or not key:
            return None
        if self._release_first:
            self._release_first, deadman = False, False
        elif deadman and pressed_at > halted_at > self._release_sent_at:
            deadman = False  # a fresh press after a halt: the release the edge waits for goes first
        elif not deadman and now - released_at > self.release_tail:
            return None  # quiet
        if not deadman:
            self._release_sent_at = now
        self.seq += 1
        t = time.time_ns()
        # The age of the newest robot state this operator has, on the edge's clock as the state was stamped
        # (-1: none yet, and the edge refuses motion).
        state_age = min(max(0.0, (t - state_t) / 1e9), _STATE_AGE_MAX) if state_t > 0 else -1.0
        lin, ang = ([float(v) for v in twist[:3]], [float(v) for v in twist[3:6]]) if deadman else ([0.0] * 3, [0.0] * 3)
        cmd = TwistCommand(operator=self.operator_id, linear=lin, angular=ang, deadman=deadman, state_age=state_age,
                           view_t=max(0, int(state_t)), frame=frame)
        return cmd, auth.seal(key, self.ctx, cmd.stamp(self.seq, t))

    def resume(self, key_gen: float, seq: int) -> None:
        """Go on with grant ``key_gen``'s sequence after ``seq`` (a sender process that died sent up to it): no
        release first, that grant's went out already. A different grant on the next tick starts afresh."""
        self.key_gen, self.seq, self._release_first = key_gen, seq, False


def run_fixed_rate(tick: Callable[[], bool], rate_hz: float, spin: bool, wait: Callable[[float], Any]) -> None:
    """Call ``tick`` on an absolute schedule until it returns False. ``wait(seconds)`` sleeps (an Event's wait,
    so a stop request ends it early); with ``spin`` the last ~1.5 ms are spun, as sleep alone overshoots by
    ~0.1–1 ms. An overrun resumes the schedule from now: never a burst."""
    period = 1.0 / rate_hz
    next_tick = time.monotonic()
    while tick():
        next_tick += period
        delay = next_tick - time.monotonic()
        if delay > 0:
            if not spin:
                wait(delay)
            elif delay > 0.002:
                wait(delay - 0.0015)
            while spin and time.monotonic() < next_tick:
                pass
        else:
            next_tick = time.monotonic()


class SharedCommand:
    """The parent's side of the shared arrays: a single writer at a time (the caller's lock), seqlocked."""

    def __init__(self, array: Any, key: Any) -> None:
        self.array = array
        self.key = key

    def write(self, **fields: Any) -> None:
        a = self.array
        g = a[_GEN]
        a[_GEN] = g + 1  # odd: being written
        for name, value in fields.items():
            if name == "twist":
                a[_TWIST:_TWIST + 6] = [float(v) for v in value]
            elif name == "key":
                self.key[:] = bytes(value).ljust(auth.KEY_BYTES, b"\0")[:auth.KEY_BYTES]
            else:
                a[_FIELDS[name]] = float(value)
        a[_GEN] = g + 2


def _read(array: Any, key: Any, last: tuple[list[float], bytes] | None) -> tuple[list[float], bytes] | None:
    """A consistent copy of the shared arrays, or ``last`` if the writer is mid-write (never wait for it)."""
    for _ in range(50):
        g1 = array[_GEN]
        if int(g1) % 2 == 0:
            vals, k = array[:], bytes(key[:])
            if array[_GEN] == g1:
                return vals, k
    return last


class ProcessSender:
    """Parent-side handle: starts the child, drains its send records, writes the heartbeat."""

    def __init__(
        self,
        zenoh_config: Any,
        twist_key: str,
        robot: str,
        operator_id: str,
        rate_hz: float,
        release_tail: float,
        ui_timeout: float,
        realtime: bool,
        lock: threading.Lock,
        on_record: Callable[[int, int, float, int, bool], None],  # (seq, t ns, monotonic instant, grant, deadman)
        on_lost: Callable[[str], None] | None = None,
        heartbeat_s: float = 0.05,
    ) -> None:
        self._ctx = mp.get_context("spawn")
        self.array = self._ctx.RawArray("d", _SIZE)
        self.key = self._ctx.RawArray("B", auth.KEY_BYTES)
        self.shared = SharedCommand(self.array, self.key)
        self._lock = lock  # the client's lock: serialises the parent's writers
        self._on_record = on_record
        self._on_lost = on_lost
        self._drain_lock = threading.Lock()
        self.heartbeat_s = heartbeat_s
        self.heartbeat_suspended = False  # test hook: models a frozen UI (no heartbeat, no set_twist)
        # The link thread beats for a headless client (its process alive is its sign of life); a console's
        # heartbeat comes with its input's twists instead (OperatorClient.beats_itself).
        self.link_beats = True
        self.priority = "normal"
        self._args = (zenoh_config, twist_key, robot, operator_id, rate_hz, release_tail, ui_timeout, realtime)
        self.proc: Any = None
        self._conn: Any = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._stopping = False  # stop() was asked: the child's end is no loss
        self._ready = threading.Event()  # the child said it is ready (drain)
        self.last_sent = (-1.0, 0)  # (grant, seq) of the last command a child sent (its record)
        self.said = ""  # what the child said before it ended, if it failed
        self.beat()

    def write(self, **fields: Any) -> None:
        """Write fields under the client's lock (caller holds it). A heartbeat only when one is among them (the
        operator's input writing its twist), unless suspended: the robot's state or the edge's safety status
        written on their own threads are no sign that the operator's side is alive."""
        if self.heartbeat_suspended:
            fields.pop("heartbeat", None)
        self.shared.write(**fields)

    def beat(self) -> None:
        if self.heartbeat_suspended:
            return
        with self._lock:
            self.shared.write(heartbeat=time.monotonic())

    def start(self, timeout: float = 30.0) -> None:
        """Start the child and wait until it is ready; a child that died before goes on with the sequence of
        :attr:`last_sent`. A child that ends during start-up without a word (exit code 0: it found its parent gone,
        or was sent SIGTERM) is started once more, and said so; a reason it gives, or a second silent end, is
        raised."""
        try:
            self._start_once(timeout)
        except _SilentExit as exc:
            log.warning("%s: starting it once more", exc)
            self._start_once(timeout)

    def _start_once(self, timeout: float) -> None:
        with self._lock:
            self.shared.write(stop=0.0)  # (a failed start stopped the one before)
        self._stop.clear()
        self._stopping = False
        self._ready.clear()
        self.said = ""
        recv, send = self._ctx.Pipe(duplex=False)
        pdeathsig = threading.current_thread() is threading.main_thread()  # PDEATHSIG follows the *thread*
        self.proc = self._ctx.Process(
            target=child_main, name="iorthand-sender", daemon=True,
            args=(send, self.array, self.key, *self._args, os.getpid(), pdeathsig, self.last_sent),
        )
        with _real_std_streams():
            self.proc.start()
        send.close()  # the child holds the only write end: EOF here when it exits
        self._conn = recv
        self._wait_ready(timeout)
        self._thread = threading.Thread(target=self._link, name="operator-sender-link", daemon=True)
        self._thread.start()

    def _wait_ready(self, timeout: float) -> None:
        """Wait for the child's "ready"; stop it and raise why it is not. Its messages are read by :meth:`drain`
        only, here as from an echo's callback: the child's first commands follow its "ready" at once, and an echo
        that drained the pipe first would otherwise have taken the "ready" from under this wait."""
        deadline = time.monotonic() + timeout
        while not self._ready.is_set():
            left = deadline - time.monotonic()
            conn = self._conn
            if conn is not None and left > 0:
                with contextlib.suppress(EOFError, OSError):
                    conn.poll(min(left, 0.2))
                self.drain()
                if self._ready.is_set():
                    return
            if self.said:
                self.stop()
                raise RuntimeError(f"sender process failed: {self.said}")
            if left <= 0:
                self.stop()
                raise RuntimeError(f"the sender process was not ready within {timeout:.0f} s")
            if self._conn is None or not self.proc.is_alive():  # it ended without a word
                self.stop()
                error = _SilentExit if self.proc.exitcode == 0 else RuntimeError
                raise error(f"the sender process {exit_reason(self.proc.exitcode)} during start-up")

    def drain(self) -> None:
        """Hand every record waiting in the pipe to ``on_record`` (from the link thread or an echo callback)."""
        conn = self._conn
        if conn is None:
            return
        with self._drain_lock:
            try:
                while conn.poll(0):
                    msg = conn.recv_bytes()
                    if msg[:1] == b"S":
                        seq, t_ns, mono, key_gen, deadman = _RECORD.unpack(msg[1:])
                        self.last_sent = (key_gen, seq)
                        self._on_record(seq, t_ns, mono, int(key_gen), deadman)
                    elif msg[:1] == b"R":
                        self.priority = msg[1:].decode()
                        self._ready.set()
                    elif msg[:1] == b"E":
                        self.said = msg[1:].decode(errors="replace")
            except (EOFError, OSError):
                self._conn = None

    def _link(self) -> None:
        last_beat = 0.0
        while not self._stop.is_set():
            conn = self._conn
            if conn is None:
                self._stop.wait(self.heartbeat_s)
            else:
                with contextlib.suppress(EOFError, OSError):
                    conn.poll(self.heartbeat_s)
                self.drain()
                if self._conn is None and not self._stopping:  # the child closed its end: it is gone
                    self._lost()
                    return
            now = time.monotonic()
            if self.link_beats and now - last_beat >= self.heartbeat_s:
                self.beat()
                last_beat = now

    def _lost(self) -> None:
        """The child ended without being asked to: reap it (stop(), for one hung in its exit) and tell ``on_lost``
        how it ended."""
        self.stop()
        reason = f"the command sender process {exit_reason(self.proc.exitcode, self.said)}"
        log.error("%s", reason)
        if self._on_lost is not None:
            self._on_lost(reason)

    def alive(self) -> bool:
        return self.proc is not None and self.proc.is_alive()

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the child (flag, then SIGTERM, then SIGKILL) and the link thread; no orphan survives."""
        self._stopping = True
        with self._lock:
            self.shared.write(stop=1.0)
        proc = self.proc
        if proc is not None:
            proc.join(timeout)
            if proc.is_alive():
                proc.terminate()
                proc.join(1.0)
            if proc.is_alive():
                proc.kill()
                proc.join(1.0)
        self.drain()
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(1.0)
        if self._conn is not None:
            with contextlib.suppress(OSError):
                self._conn.close()
            self._conn = None


class _SilentExit(RuntimeError):
    """The child ended during start-up with exit code 0 and no reason."""


# ---------------------------------------------------------------------- the child


def child_main(conn, array, key, zenoh_config, twist_key: str, robot: str, operator_id: str, rate_hz: float,
               release_tail: float, ui_timeout: float, realtime: bool, parent_pid: int, pdeathsig: bool,
               last_sent: tuple[float, int]) -> None:
    enter_child(parent_pid, pdeathsig)  # Ctrl-C goes to the UI; the parent stops us
    code = 0
    try:
        stream = CommandStream(robot, operator_id, release_tail, ui_timeout)
        if last_sent[0] >= 0:
            stream.resume(*last_sent)
        _child_loop(conn, array, key, zenoh_config, twist_key, stream, rate_hz, realtime, parent_pid)
    except BaseException as exc:  # a failure the parent must be told of, not an exit that looks like a clean one
        code = 1
        traceback.print_exc()
        with contextlib.suppress(OSError):
            conn.send_bytes(b"E" + f"{type(exc).__name__}: {exc}".encode())
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)  # not the interpreter's shutdown: it joins Zenoh's threads and can hang


def _child_loop(conn, array, key, zenoh_config, twist_key: str, stream: CommandStream, rate_hz: float,
                realtime: bool, parent_pid: int) -> None:
    from iorthand.transport import QOS_BY_KEY, open_session, publisher

    session = open_session(zenoh_config)  # a failure is the parent's to hear of (child_main)
    pub = None
    try:
        pub = publisher(session, twist_key, QOS_BY_KEY[keys.CMD_TWIST])
        priority = raise_priority(realtime)
        conn.send_bytes(b"R" + priority.encode())
        snap = _read(array, key, None) or ([0.0] * _SIZE, b"")
        done = threading.Event()

        def tick() -> bool:
            nonlocal snap
            snap = _read(array, key, snap) or snap
            if os.getppid() != parent_pid:
                os._exit(0)  # the parent died: no graceful close (its router link may be gone too)
            vals, k = snap
            if vals[_STOP]:
                return False
            out = stream.next(time.monotonic(), vals[_TWIST:_TWIST + 6], bool(vals[_DEADMAN]), vals[_RELEASED],
                              bool(vals[_MUTED]), vals[_HEARTBEAT], vals[_STATE_T], vals[_KEY_GEN],
                              k if any(k) else b"", vals[_PRESSED], vals[_PRESS_FROM], vals[_HALTED],
                              TWIST_FRAMES[int(vals[_FRAME])])
            if out is not None:
                cmd, payload = out
                conn.send_bytes(b"S" + _RECORD.pack(cmd.seq, cmd.t, time.monotonic(), stream.key_gen,
                                                          cmd.deadman))
                pub.put(payload)
            return True

        run_fixed_rate(tick, rate_hz, spin=True, wait=done.wait)
    except (BrokenPipeError, EOFError, OSError):
        pass  # the parent went away
    finally:
        if pub is not None:
            with contextlib.suppress(Exception):
                pub.undeclare()
        with contextlib.suppress(Exception):
            session.close()
