"""Link quality over a sliding window: command→echo round trip (p50/p95), jitter and loss. Pure logic.

The operator sends twists with sequence numbers; the edge echoes every one it receives on ``state/applied``
(accepted or refused). From that:

- **RTT**: echo receive time − send time, both on this machine's monotonic clock (no clock sync needed, and a
  wall clock stepped by NTP between a send and its echo cannot make a round trip negative or an hour long).
- **Jitter**: the mean absolute difference of consecutive RTTs (RFC 3550's idea, without its smoothing),
  i.e. how irregular the delay is — what trips a deadman timeout, more than a constant delay does.
- **Uplink loss**: commands sent in the window that were never echoed. A command counts only once it is
  older than ``echo_grace`` (its echo may still be on its way), so a healthy link reads 0 %, not a few %.
  Sends and echoes are matched by the command's identity (the client's: its sequence number and its own time
  stamp, both of which the echo carries back), never by the sequence alone: that restarts with every grant of
  control, and an earlier grant's echoes matched the new grant's commands (a dead uplink read 0 %). A new grant
  (:meth:`LinkWindow.new_grant`) starts the count afresh: the loss shown is that of the commands that can move
  the robot now.
- **Downlink loss**: gaps in the edge's ``state/robot`` sequence numbers — and 100 % once no state has arrived
  for longer than ``state_stale_after`` (gaps are counted only between states that arrived, so a dead link read
  0 %). The round trips measured before then are old: when the newest echo is older than that bound too, the
  figures carry its age (``rtt_old_s``) and are graded by it (a dead link showed its last healthy RTT for a window).

Everything takes explicit monotonic times (ns) so tests drive it without a clock. The console colours each figure
against :class:`LinkThresholds`.
"""

from __future__ import annotations

import itertools
import math
import threading
from collections import deque
from collections.abc import Hashable
from dataclasses import dataclass

from iorthand import stats

GOOD, WARN, BAD, NONE = "good", "warn", "bad", "none"
GRADE_COLOURS = {GOOD: "green", WARN: "yellow", BAD: "red", NONE: "grey50"}
# s without a robot state after which there is no fresh state: the console's default (ConsoleSettings) and the
# link figures' (the edge publishes its state at 125 Hz; half a second of none is a dead downlink, not a gap).
STATE_STALE_S = 0.5


@dataclass
class LinkThresholds:
    """Above ``*_warn`` a figure shows yellow, above ``*_bad`` red. Defaults suit a 150 ms edge timeout."""

    rtt_warn_ms: float = 80.0
    rtt_bad_ms: float = 150.0
    jitter_warn_ms: float = 10.0
    jitter_bad_ms: float = 30.0
    loss_warn: float = 0.01  # fraction
    loss_bad: float = 0.05

    def check(self) -> None:
        for name, warn, bad in (
            ("rtt", self.rtt_warn_ms, self.rtt_bad_ms),
            ("jitter", self.jitter_warn_ms, self.jitter_bad_ms),
            ("loss", self.loss_warn, self.loss_bad),
        ):
            if warn > bad:
                raise ValueError(f"{name}: the warning threshold {warn} exceeds the bad one {bad}")


@dataclass(frozen=True)
class LinkQuality:
    """One snapshot of the window. NaN figures mean "no data" (shown grey, never green)."""

    rtt_p50_ms: float
    rtt_p95_ms: float
    jitter_ms: float
    uplink_loss: float  # fraction of commands sent and not echoed
    downlink_loss: float  # fraction of state messages missing (sequence gaps)
    echoes: int
    sent: int
    # s since the newest robot state when that is longer than the bound (downlink_loss is then 1), else 0
    no_state_s: float = 0.0
    # s since the newest echo when no state is fresh and no echo is either: the RTT and jitter figures are that
    # old (what they say is the link as it was, not as it is), else 0
    rtt_old_s: float = 0.0

    def grades(self, t: LinkThresholds) -> dict[str, str]:
        # Old round trips are graded by their age: at least that long, for all anyone here can tell.
        rtt = 1e3 * self.rtt_old_s if self.rtt_old_s else self.rtt_p95_ms
        return {
            "rtt": grade(rtt, t.rtt_warn_ms, t.rtt_bad_ms),
            "jitter": NONE if self.rtt_old_s else grade(self.jitter_ms, t.jitter_warn_ms, t.jitter_bad_ms),
            "uplink_loss": grade(self.uplink_loss, t.loss_warn, t.loss_bad),
            "downlink_loss": grade(self.downlink_loss, t.loss_warn, t.loss_bad),
        }

    def overall(self, t: LinkThresholds) -> str:
        gs = list(self.grades(t).values())
        for g in (BAD, WARN):
            if g in gs:
                return g
        return NONE if all(g == NONE for g in gs) or math.isnan(self.rtt_p95_ms) else GOOD


def grade(value: float, warn: float, bad: float) -> str:
    if value is None or math.isnan(value):
        return NONE
    if value > bad:
        return BAD
    if value > warn:
        return WARN
    return GOOD


def jitter(rtts: list[float]) -> float:
    """Mean absolute difference of consecutive values; NaN with fewer than two."""
    if len(rtts) < 2:
        return math.nan
    return sum(abs(b - a) for a, b in itertools.pairwise(rtts)) / (len(rtts) - 1)


def gap_loss(seqs: list[int]) -> float:
    """Fraction of sequence numbers missing between the first and last of ``seqs`` (duplicates ignored;
    a restart — a sequence going backwards — starts a new run). NaN with fewer than two."""
    if len(seqs) < 2:
        return math.nan
    expected = received = 0
    run_start = prev = seqs[0]
    count = 1
    for s in seqs[1:]:
        if s == prev:
            continue
        if s < prev:  # the publisher restarted: close this run
            expected += prev - run_start + 1
            received += count
            run_start, count = s, 1
        else:
            count += 1
        prev = s
    expected += prev - run_start + 1
    received += count
    return max(0.0, 1.0 - received / expected) if expected else math.nan


class LinkWindow:
    """Thread-safe sliding window of sends, echoes and state sequence numbers (monotonic times in ns). A send is
    named by ``cmd``, anything hashable that identifies that one command (not only its sequence number)."""

    def __init__(self, window_s: float = 5.0, echo_grace_s: float = 0.5) -> None:
        self.window_ns = int(window_s * 1e9)
        self.grace_ns = int(echo_grace_s * 1e9)
        self._lock = threading.Lock()
        self._sent: deque[tuple[int, Hashable]] = deque()  # (send ns, cmd)
        # cmd → rtt ns, or None while unanswered, for the commands in _sent (an echo of any other is no answer)
        self._answers: dict[Hashable, int | None] = {}
        self._echoes: deque[tuple[int, float]] = deque()  # (echo ns, rtt ms), arrival order
        self._states: deque[tuple[int, int]] = deque()  # (receive ns, seq)
        # Newest arrivals, kept past the window: how long the link has been silent is what a dead one shows.
        self._last_state_ns: int | None = None
        self._last_echo_ns: int | None = None

    # Each insert also drops what is two windows old (amortised O(1)): a client nobody asks for a snapshot (a
    # scripted operator running for hours) must not keep every send, echo and state it ever saw. Two windows, not
    # one: a snapshot may be taken a little behind the newest insert (an echo stamped after it was asked for).
    def sent(self, cmd: Hashable, t_ns: int) -> None:
        with self._lock:
            self._sent.append((t_ns, cmd))
            self._answers.setdefault(cmd, None)
            self._trim(t_ns - self.window_ns)

    def echoed(self, cmd: Hashable, sent_ns: int, echo_ns: int) -> None:
        with self._lock:
            if cmd in self._answers:
                self._answers[cmd] = echo_ns - sent_ns
            self._echoes.append((echo_ns, (echo_ns - sent_ns) / 1e6))
            self._last_echo_ns = max(echo_ns, self._last_echo_ns or echo_ns)
            self._trim(echo_ns - self.window_ns)

    def new_grant(self) -> None:
        """A new grant of control: the commands sent under the one before can move nothing any more, and their
        echoes answered them only; the loss counts the new grant's commands from here (the round trips measured
        stay: they are the link's, whatever the grant)."""
        with self._lock:
            self._sent.clear()
            self._answers.clear()

    def state(self, seq: int, t_ns: int) -> None:
        with self._lock:
            self._states.append((t_ns, seq))
            self._last_state_ns = max(t_ns, self._last_state_ns or t_ns)
            self._trim(t_ns - self.window_ns)

    def _trim(self, now_ns: int) -> None:
        cut = now_ns - self.window_ns
        while self._sent and self._sent[0][0] < cut:
            _, cmd = self._sent.popleft()
            self._answers.pop(cmd, None)
        while self._echoes and self._echoes[0][0] < cut:
            self._echoes.popleft()
        while self._states and self._states[0][0] < cut:
            self._states.popleft()

    def snapshot(self, now_ns: int, state_stale_after: float = STATE_STALE_S) -> LinkQuality:
        """The figures at ``now_ns``; no robot state for longer than ``state_stale_after`` s is a dead downlink
        (before the first state there is no downlink figure at all: nothing says one is coming)."""
        with self._lock:
            self._trim(now_ns)
            rtts = [r for _, r in self._echoes]
            due = [cmd for t, cmd in self._sent if t <= now_ns - self.grace_ns]
            missing = sum(1 for cmd in due if self._answers.get(cmd) is None)
            state_seqs = [s for _, s in self._states]
            sent = len(self._sent)
            last_state, last_echo = self._last_state_ns, self._last_echo_ns
        no_state = rtt_old = 0.0
        if last_state is not None and (now_ns - last_state) / 1e9 > state_stale_after:
            no_state = (now_ns - last_state) / 1e9
            if rtts and last_echo is not None and (now_ns - last_echo) / 1e9 > state_stale_after:
                rtt_old = (now_ns - last_echo) / 1e9
        return LinkQuality(
            rtt_p50_ms=stats.percentile(rtts, 50),
            rtt_p95_ms=stats.percentile(rtts, 95),
            jitter_ms=jitter(rtts),
            uplink_loss=missing / len(due) if due else math.nan,
            downlink_loss=1.0 if no_state else gap_loss(state_seqs),
            echoes=len(rtts),
            sent=sent,
            no_state_s=no_state,
            rtt_old_s=rtt_old,
        )
