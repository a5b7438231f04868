"""Link statistics: RTT percentiles, jitter, loss from sequence numbers, grading (pure); and what the operator
client feeds them (against a real router and a simulated edge)."""

from __future__ import annotations

import math
import time
from types import ModuleType

import pytest

from iorthand.transport import ZenohConfig, open_session
from iorthand_operator.bench.linkemu import LinkEmulator, LinkProfile
from iorthand_operator.client import OperatorClient
from iorthand_operator.link import BAD, GOOD, NONE, WARN, LinkThresholds, LinkWindow, gap_loss, grade, jitter
from tests.conftest import wait_until

MS = 1_000_000


def test_empty_window_is_no_data_never_good() -> None:
    q = LinkWindow().snapshot(10**12)
    assert math.isnan(q.rtt_p50_ms) and math.isnan(q.jitter_ms) and math.isnan(q.uplink_loss)
    assert q.overall(LinkThresholds()) == NONE


def test_rtt_percentiles_and_jitter_over_window() -> None:
    w = LinkWindow(window_s=1.0, echo_grace_s=0.1)
    t0 = 10**12
    for i in range(100):  # RTT 10 ms, every tenth 30 ms
        sent = t0 + i * 10 * MS
        rtt = 30 if i % 10 == 9 else 10
        w.sent(i + 1, sent)
        w.echoed(i + 1, sent, sent + rtt * MS)
    q = w.snapshot(t0 + 999 * MS)
    assert q.rtt_p50_ms == pytest.approx(10.0)
    assert q.rtt_p95_ms == pytest.approx(30.0)
    assert q.jitter_ms == pytest.approx(jitter([30.0 if i % 10 == 9 else 10.0 for i in range(100)]))
    assert q.uplink_loss == 0.0
    # The window slides: 0.5 s later only the newer half counts.
    assert w.snapshot(t0 + 1500 * MS).echoes < 60


def test_uplink_loss_counts_only_commands_past_the_grace() -> None:
    w = LinkWindow(window_s=5.0, echo_grace_s=0.5)
    t0 = 10**12
    for i in range(1, 101):
        w.sent(i, t0 + i * MS)
        if i % 4:  # every fourth is lost
            w.echoed(i, t0 + i * MS, t0 + i * MS + 5 * MS)
    w.sent(101, t0 + 900 * MS)  # just sent, echo not due yet
    q = w.snapshot(t0 + 1000 * MS)
    assert q.uplink_loss == pytest.approx(0.25)


def test_gap_loss_from_sequence_numbers() -> None:
    assert gap_loss([1, 2, 3, 4]) == 0.0
    assert gap_loss([1, 2, 4, 5]) == pytest.approx(0.2)  # 3 missing of 5
    assert gap_loss([1, 1, 2]) == 0.0  # duplicates are not loss
    assert gap_loss([10, 11, 1, 2]) == 0.0  # the publisher restarted
    assert math.isnan(gap_loss([5]))


def test_downlink_loss_from_state_sequences() -> None:
    w = LinkWindow(window_s=5.0)
    t0 = 10**12
    for i, seq in enumerate([1, 2, 3, 5, 6, 7, 8, 9, 10, 11]):
        w.state(seq, t0 + i * MS)
    assert w.snapshot(t0 + 20 * MS).downlink_loss == pytest.approx(1 / 11)


def test_a_dead_downlink_reads_100_percent_and_old_round_trips_their_age() -> None:
    """Found by a review of the operator side: gaps were counted only between states that arrived, so 1.4 s after
    the last state the downlink read 0 % and the RTT its last healthy 20 ms, all green, until the window emptied."""
    w, t = LinkWindow(window_s=5.0), LinkThresholds()
    t0 = 10**12
    for i in range(125):  # a healthy second: states at 125 Hz, every command echoed after 20 ms
        w.state(i, t0 + i * 8 * MS)
        w.sent(i, t0 + i * 8 * MS)
        w.echoed(i, t0 + i * 8 * MS, t0 + i * 8 * MS + 20 * MS)
    last = t0 + 124 * 8 * MS
    q = w.snapshot(last + 100 * MS)
    assert q.downlink_loss == 0.0 and q.overall(t) == GOOD
    q = w.snapshot(last + 1400 * MS)  # then nothing for 1.4 s
    assert q.downlink_loss == 1.0 and q.overall(t) == BAD
    assert q.no_state_s == pytest.approx(1.4)
    assert q.rtt_old_s == pytest.approx(1.38) and q.rtt_p95_ms == pytest.approx(20.0)  # said to be that old
    assert q.grades(t)["downlink_loss"] == BAD and q.grades(t)["rtt"] == BAD and q.grades(t)["jitter"] == NONE
    assert w.snapshot(last + 100 * MS).rtt_old_s == 0.0
    # The bound is the caller's (the console's state_stale_after): under it, still a link.
    assert w.snapshot(last + 1400 * MS, state_stale_after=2.0).downlink_loss == 0.0


def test_echoes_that_still_arrive_are_current_whatever_the_state_stream() -> None:
    w = LinkWindow(window_s=5.0)
    t0 = 10**12
    w.state(1, t0)
    for i in range(100):  # the state stream dead, the echoes (another key) still coming
        w.sent(i, t0 + i * 10 * MS)
        w.echoed(i, t0 + i * 10 * MS, t0 + i * 10 * MS + 15 * MS)
    q = w.snapshot(t0 + 1000 * MS)
    assert q.downlink_loss == 1.0 and q.rtt_old_s == 0.0 and q.grades(LinkThresholds())["rtt"] == GOOD
    # Before the first state nothing says one is coming: no figure, not a dead link.
    assert math.isnan(LinkWindow().snapshot(t0).downlink_loss)


def test_grades_against_thresholds() -> None:
    t = LinkThresholds(rtt_warn_ms=50, rtt_bad_ms=100)
    assert grade(10, 50, 100) == GOOD
    assert grade(60, 50, 100) == WARN
    assert grade(150, 50, 100) == BAD
    assert grade(math.nan, 50, 100) == NONE
    with pytest.raises(ValueError):
        LinkThresholds(loss_warn=0.5, loss_bad=0.1).check()
    w = LinkWindow()
    w.sent(1, 0)
    w.echoed(1, 0, 120 * MS)
    assert w.snapshot(200 * MS).grades(t)["rtt"] == BAD


def test_a_window_nobody_reads_stays_bounded() -> None:
    """A scripted operator runs for hours without asking for a snapshot: what is two windows old is dropped."""
    w = LinkWindow(window_s=1.0)
    t0 = 10**12
    for i in range(60 * 600):  # ten minutes of 60 Hz sends, echoes and states
        t = t0 + i * 16 * MS
        w.sent(i, t)
        w.echoed(i, t, t + 5 * MS)
        w.state(i, t)
    kept = len(w._sent) + len(w._echoes) + len(w._states) + len(w._answers)
    assert kept <= 4 * 2 * 64, kept  # ~2 s of each at 60 Hz


def test_a_new_grant_counts_its_own_commands_only() -> None:
    """Each grant's commands are seq 1, 2, ...: an earlier grant's echo is no answer to a new grant's command."""
    w = LinkWindow(window_s=5.0, echo_grace_s=0.1)
    t0 = 10**12
    for i in range(1, 101):  # grant 1: every command echoed
        w.sent((i, t0 + i * MS), t0 + i * MS)
        w.echoed((i, t0 + i * MS), t0 + i * MS, t0 + i * MS + MS)
    w.new_grant()
    t1 = t0 + 200 * MS
    for i in range(1, 51):  # grant 2, same sequence numbers: nothing arrives
        w.sent((i, t1 + i * MS), t1 + i * MS)
    w.echoed((3, t0 + 3 * MS), t0 + 3 * MS, t1 + 60 * MS)  # a late echo of grant 1's command 3
    q = w.snapshot(t1 + 400 * MS)
    assert q.uplink_loss == 1.0 and q.sent == 50


class _SteppedWallClock(ModuleType):
    """The ``time`` module with its wall clock ``offset_s`` away: NTP stepping this machine's clock (root could step
    the real one; a test cannot)."""

    def __init__(self, offset_s: float) -> None:
        super().__init__("time")
        self._offset_ns = int(offset_s * 1e9)

    def __getattr__(self, name: str) -> object:
        return getattr(time, name)

    def time_ns(self) -> int:
        return time.time_ns() + self._offset_ns

    def time(self) -> float:
        return self.time_ns() / 1e9


def test_round_trips_are_timed_on_the_monotonic_clock(edge_factory, operator_factory, monkeypatch) -> None:
    """Found by a review of the operator side: the wall clock stepped back 0.5 s between a command's send and its
    echo made the RTT -499 ms (measured on the code before; and an hour-long step back held an hour of sends in the
    window). Here the client's wall clock is 0.5 s behind the one that stamps the commands, as for every command in
    flight at a step."""
    import iorthand_operator.client as client_module

    edge_factory()
    client = operator_factory()
    client.wait_for_state()
    client.start()
    client.acquire()
    client.set_twist([0.0] * 3, [0.0] * 3, deadman=True)  # a held deadman: a command every tick, each echoed
    wait_until(lambda: client.echo_count > 10, 5.0, message="echoes")
    monkeypatch.setattr(client_module, "time", _SteppedWallClock(-0.5))
    mark = client.echo_count
    wait_until(lambda: client.echo_count > mark + 60, 5.0, message="echoes after the step")
    rtts = [e.rtt_ms for e in client.echoes_since(mark)]
    assert min(rtts) >= 0.0 and max(rtts) < 250.0, (min(rtts), max(rtts))
    q = client.link_quality()
    assert 0.0 <= q.rtt_p50_ms <= q.rtt_p95_ms < 250.0, q


def test_a_dead_link_after_a_new_grant_reads_as_total_loss(router_endpoint, edge_factory) -> None:
    """Found by a review of the operator side: sends and echoes were matched by the sequence number alone, which
    restarts with each grant, so after a new grant on a dead link every command found an echo of the grant before
    and the uplink loss read 0 % (measured on the code before: 0.0 with 90 commands sent into the dead link)."""
    edge_factory("sim1")
    host, port = router_endpoint.split("/", 1)[1].rsplit(":", 1)
    emu = LinkEmulator(("127.0.0.1", 0), (host, int(port)), LinkProfile(0.0, 0.0)).start()
    session = open_session(ZenohConfig(mode="client", connect=[f"tcp/127.0.0.1:{emu.port}"], lease_ms=2000,
                                       shared_memory=False))
    client = OperatorClient(session, "sim1", "op1")
    try:
        client.wait_for_state()
        client.start()
        client.acquire()
        client.set_twist([0.0] * 3, [0.0] * 3, deadman=True)
        wait_until(lambda: client.echo_count >= 150, 10.0, message="150 echoes under the first grant")
        assert client.link_quality().uplink_loss == 0.0
        client.release()
        client.acquire()  # a new grant: its commands are seq 1, 2, ... again
        client.set_twist([0.0] * 3, [0.0] * 3, deadman=True)  # pressed afresh
        emu.blackout(True)  # the link dies: nothing sent from here on is echoed
        marks = client.sent_count, client.echo_count
        time.sleep(1.5)
        q = client.link_quality()
        sent, echoed = client.sent_count - marks[0], client.echo_count - marks[1]
    finally:
        emu.blackout(False)
        client.close()
        session.close()
        emu.close()
    assert sent > 60 and echoed <= 3, (sent, echoed)  # (an echo may have been on its way as the link died)
    # All but the few commands of the new grant that crossed before the link died.
    assert q.uplink_loss > 0.9, q
