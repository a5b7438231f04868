"""The process sender (iorthand_operator.sender): the fixed-rate twist stream from a child process with its own
Zenoh session, through a real router on loopback to a simulated robot. Bounds are generous (a loaded 2-core
machine delays what the test *sees*, not what it checks)."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import psutil
import pytest

from iorthand.transport import client_config
from iorthand_operator.client import SENDER_LOSSES, OperatorClient
from iorthand_operator.inputs.base import InputDevice, InputSample
from iorthand_operator.recovery import NextStep, Step
from iorthand_operator.sender import ProcessSender
from tests.conftest import wait_until


@pytest.fixture
def proc_operator(router_endpoint, operator_factory):
    """Operator clients with the process sender (as the console and CLI build them), closed after the test."""

    def make(**kwargs: object) -> OperatorClient:
        return operator_factory(sender_config=client_config(router_endpoint), **kwargs)

    return make


def driving(op: OperatorClient) -> OperatorClient:
    """Wait for the robot, take control and start the sender."""
    op.wait_for_state()
    op.acquire()
    op.start()
    return op


def commanded(edge) -> np.ndarray:
    return np.asarray(edge._commanded)


def test_process_sender_moves_the_robot_and_records_echoes(edge_factory, proc_operator) -> None:
    edge = edge_factory()
    op = driving(proc_operator())
    assert op.sender_process is not None and op.sender_process.is_alive()
    assert op.sender_process.pid != psutil.Process().pid
    applied0 = edge.supervisor.counters.applied
    op.set_twist([0.005, 0, 0], [0, 0, 0], deadman=True)
    wait_until(lambda: edge.supervisor.counters.applied > applied0 + 30, timeout=10, message="commands applied")
    wait_until(lambda: np.any(commanded(edge)), timeout=5, message="robot moving")
    wait_until(lambda: len(op.echoes) > 20, timeout=5, message="echoes")
    assert op.sent_count >= len(op.echoes) > 20
    assert all(e.accepted for e in list(op.echoes)[-10:])
    assert all(0 < e.rtt_ms < 1000 for e in list(op.echoes))
    assert op.last_sent_ns > 0 and len(op.send_times) == op.sent_count
    assert op.link_quality().echoes > 0
    # Release: the tail of deadman=False zero twists, then quiet.
    op.set_twist([0, 0, 0], [0, 0, 0], deadman=False)
    wait_until(lambda: not np.any(commanded(edge)), timeout=5, message="robot stopped")
    time.sleep(op.release_tail + 0.3)
    n = op.sent_count
    time.sleep(0.3)
    assert op.sent_count == n  # quiet after the release tail


def test_frozen_ui_releases_the_deadman(edge_factory, proc_operator) -> None:
    edge = edge_factory()
    op = driving(proc_operator(ui_timeout=0.5))
    op.set_twist([0.005, 0, 0], [0, 0, 0], deadman=True)
    wait_until(lambda: np.any(commanded(edge)), timeout=10, message="robot moving")
    op._proc_sender.heartbeat_suspended = True  # the UI freezes with the deadman held
    frozen = time.monotonic()
    wait_until(lambda: not np.any(commanded(edge)), timeout=5, message="robot stopped after the UI froze")
    stopped_after = time.monotonic() - frozen
    bound = op.ui_timeout + edge.config.safety.command_timeout
    print(f"\nfrozen UI → commanded zero after {1000 * stopped_after:.0f} ms (bound {1000 * bound:.0f} ms)")
    assert stopped_after < bound + 1.0  # generous: a loaded machine delays what we see
    assert stopped_after > 0.3  # it was the heartbeat timeout, not something else
    # The child went quiet after the release tail (no more sends while the UI stays frozen).
    time.sleep(op.release_tail + 0.3)
    n = op.sent_count
    time.sleep(0.4)
    assert op.sent_count == n
    assert op.echoes[-1].status != "" and op.sender_process.is_alive()


def test_muted_silences_the_process_sender(edge_factory, proc_operator) -> None:
    edge = edge_factory()
    op = driving(proc_operator())
    op.set_twist([0.005, 0, 0], [0, 0, 0], deadman=True)
    wait_until(lambda: np.any(commanded(edge)), timeout=10, message="robot moving")
    op.muted = True
    wait_until(lambda: op.safety is not None and op.safety.status == "command_timeout", timeout=5,
               message="command timeout at the edge")
    n = op.sent_count
    time.sleep(0.3)
    assert op.sent_count == n
    assert not np.any(commanded(edge))
    op.muted = False
    wait_until(lambda: op.sent_count > n + 5, timeout=5, message="sending again")


def test_close_leaves_no_child_process(edge_factory, proc_operator) -> None:
    edge_factory()
    op = proc_operator()
    op.start()
    proc = op.sender_process
    pid = proc.pid
    assert psutil.pid_exists(pid)
    t0 = time.monotonic()
    op.close()
    assert time.monotonic() - t0 < 10
    assert not proc.is_alive()
    assert not psutil.pid_exists(pid) or psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    assert pid not in [c.pid for c in psutil.Process().children(recursive=True)]


def test_thread_sender_unchanged_without_config(edge_factory, operator_factory) -> None:
    edge = edge_factory()
    op = driving(operator_factory())
    assert op.sender_process is None
    op.set_twist([0.005, 0, 0], [0, 0, 0], deadman=True)
    wait_until(lambda: np.any(commanded(edge)), timeout=10, message="robot moving")
    wait_until(lambda: len(op.echoes) > 5, timeout=5, message="echoes")


class _HangingPad(InputDevice):
    """An input device whose read hangs on request (a driver read that never returns), the enable held and the
    stick deflected: no real device hangs on purpose, so this one stands in for it."""

    name = "hanging pad"

    def __init__(self) -> None:
        self.hang, self.free = threading.Event(), threading.Event()

    def poll(self, now: float) -> InputSample:
        if self.hang.is_set():
            self.free.wait(10.0)
        return InputSample(np.array([0.004, 0.0, 0.0, 0.0, 0.0, 0.0]), True, True, "enable held", [])

    def release_deadman(self) -> None:
        pass

    def close(self) -> None:
        self.free.set()


@pytest.mark.parametrize("sender", ["thread", "process"])
def test_a_console_whose_input_thread_stalls_lets_go_of_the_deadman(edge_factory, operator_factory, proc_operator,
                                                                   sender: str) -> None:
    """Found by a red-team run: the heartbeat came from the client's own threads (and from every robot state the
    process sender was given), none of which carries the operator's intent: with the console's input thread hung
    and the enable held, the robot moved 12 mm in 3 s. The console's input is now its sign of life."""
    from iorthand_operator.console.controller import ConsoleController

    edge = edge_factory()
    op = driving(operator_factory(ui_timeout=0.5) if sender == "thread" else proc_operator(ui_timeout=0.5))
    pad = _HangingPad()
    console = ConsoleController(op, pad)
    console.start()
    try:
        wait_until(lambda: np.any(commanded(edge)), timeout=10, message="robot moving")
        pad.hang.set()
        hung = time.monotonic()
        wait_until(lambda: not np.any(commanded(edge)), timeout=5, message="robot stopped after the input hung")
        stopped_after = time.monotonic() - hung
        x = op.robot_state.tcp_pose[0]
        time.sleep(1.0)
        assert op.robot_state.tcp_pose[0] == pytest.approx(x, abs=5e-4)  # and stays stopped
        assert stopped_after < op.ui_timeout + edge.config.safety.command_timeout + 1.0  # generous: a loaded host
    finally:
        pad.free.set()
        console.stop()


def test_a_slow_lease_reply_does_not_read_as_a_frozen_ui(edge_factory, operator_factory) -> None:
    """The lease renewal is a query that can wait on the network; the heartbeat that says "this process is
    alive" must not wait with it. Each renewal here takes 0.8 s (longer than ui_timeout): with the heartbeat on
    the renewal's thread the sender released the deadman ("operator UI silent") and the robot stopped. The edge's
    command timeout is long so that only a release by the operator's side can stop the robot in this test."""
    edge = edge_factory(safety={"profile": "local", "command_timeout": 1.0})
    op = operator_factory(ui_timeout=0.5)  # the thread sender
    renewals: list[float] = []
    acquire = op.acquire

    def slow_acquire(profile: str = ""):
        if op.owner:  # a renewal, not the first acquire
            time.sleep(0.8)
            renewals.append(time.monotonic())
        return acquire(profile)

    op.acquire = slow_acquire
    driving(op)
    op.set_twist([0.005, 0, 0], [0, 0, 0], deadman=True)
    wait_until(lambda: np.any(commanded(edge)), timeout=10, message="robot moving")
    still: list[bool] = []
    end = time.monotonic() + 3.0
    while time.monotonic() < end:
        still.append(bool(np.any(commanded(edge))))
        time.sleep(0.02)
    assert renewals, f"no renewal in 3 s (lease {op.lease} s)"
    assert all(still), f"the robot stopped in {still.count(False)} of {len(still)} samples while the lease renewed"
    assert op.owner


def test_a_client_started_a_while_after_it_was_made_does_not_read_as_a_frozen_ui(edge_factory, operator_factory,
                                                                                  caplog) -> None:
    """A client made, then started later than ``ui_timeout`` (a script that waits for the robot and takes control
    first, a benchmark that starts its load): starting it is a sign of life. Its first tick used to find the
    construction's heartbeat stale and log "operator UI silent" (once per run of bench_cpu_hogs.py)."""
    edge_factory()
    op = operator_factory(ui_timeout=0.5)  # the thread sender
    op.wait_for_state()
    op.acquire()
    op.set_twist([0.005, 0, 0], [0, 0, 0], deadman=True)
    time.sleep(0.7)
    with caplog.at_level("WARNING", logger="iorthand.operator"):
        op.start()
        wait_until(lambda: op.sent_count >= 10, timeout=5, message="ten commands")
    assert not [r.getMessage() for r in caplog.records if "UI silent" in r.getMessage()]


def test_the_lease_is_renewed_while_the_sender_process_starts(edge_factory, proc_operator, monkeypatch) -> None:
    """The sender process's start-up can take longer than the edge's lease on a loaded machine (a clone's CI run
    saw one take seconds). The lease renewal runs meanwhile: the operator never loses control while it starts."""
    from iorthand_operator.sender import ProcessSender

    edge = edge_factory(safety={"auto_arm": True, "lease": 1.0})
    op = proc_operator()
    op.wait_for_state()
    op.acquire()
    start_once = ProcessSender._start_once

    def slow_start_once(self, timeout: float) -> None:
        time.sleep(2.5)  # 2.5 leases
        start_once(self, timeout)

    monkeypatch.setattr(ProcessSender, "_start_once", slow_start_once)
    owners: list[str] = []
    watching = True

    def watch() -> None:
        while watching:
            owners.append(edge.supervisor.owner)
            time.sleep(0.02)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        op.start()
    finally:
        watching = False
        watcher.join(timeout=1)
    assert owners and all(o == op.operator_id for o in owners), \
        f"control lost during the start-up in {sum(o != op.operator_id for o in owners)} of {len(owners)} samples"
    assert op.owner


def test_a_sender_process_that_dies_is_started_again_and_only_a_fresh_press_moves_the_robot(
        edge_factory, proc_operator) -> None:
    """The console's sender process is killed while the operator drives: the robot stops (the edge's deadman),
    the console says how the sender ended, another one starts and goes on with the grant's sequence (its commands
    are accepted, not refused as replays), and the press held through all this moves nothing until the operator
    releases the deadman and presses it again."""
    edge = edge_factory()
    op = driving(proc_operator())
    op.set_twist([0.01, 0.0, 0.0], np.zeros(3), deadman=True)
    wait_until(lambda: commanded(edge)[0] > 0.005, 10.0, message="the robot moving")
    first = op._proc_sender.proc
    os.kill(first.pid, signal.SIGKILL)
    wait_until(lambda: not commanded(edge).any(), 5.0, message="the robot stopping without commands")
    wait_until(lambda: any(e.kind == "sender" and "SIGKILL" in e.reason for e in op.events), 5.0,
               message="an event naming how the sender ended")
    last_seq = op._proc_sender.last_sent[1]  # (the dead child's records are all read when its loss is told)
    wait_until(lambda: op._proc_sender.proc is not first and op._proc_sender.alive() and not op.sender_down, 30.0,
               message="another sender process")
    assert any(e.status == "restarted" for e in op.events), list(op.events)
    deadline = time.monotonic() + 1.5  # the operator still holds the deadman pressed before the restart
    while time.monotonic() < deadline:
        assert not commanded(edge).any(), "a press held through the restart moved the robot"
        time.sleep(0.02)
    assert op.next_step().step is Step.PRESS, op.next_step()
    op.set_twist(np.zeros(3), np.zeros(3), deadman=False)
    time.sleep(0.1)
    op.set_twist([0.01, 0.0, 0.0], np.zeros(3), deadman=True)
    wait_until(lambda: commanded(edge)[0] > 0.005, 5.0, message="a fresh press moving the robot")
    echoes = [e for e in list(op.echoes) if e.seq > last_seq]  # the new sender's: none refused as a replay
    assert echoes and all(e.accepted for e in echoes), [(e.seq, e.status) for e in echoes]


def test_a_sender_process_that_fails_says_why(router_endpoint) -> None:
    """A child that fails names its error to the parent (it used to end with exit code 0 and no word)."""
    sender = ProcessSender(client_config(router_endpoint), "iorthand/sim1/cmd//twist", "sim1", "op", 60.0, 0.3, 0.5, False,
                           threading.Lock(), lambda *_: None)
    with pytest.raises(RuntimeError, match=r"ZError: Invalid Key Expr .iorthand/sim1/cmd//twist."):
        sender.start(timeout=30.0)
    assert not sender.alive()


def test_a_sender_process_that_keeps_dying_makes_the_console_give_control_up(edge_factory, proc_operator) -> None:
    """The third death of the sender in a minute: no other is started, and control goes, so that a console that
    can command may take it; the console says why and that it must be restarted."""
    edge = edge_factory()
    op = driving(proc_operator())
    for death in range(SENDER_LOSSES):
        proc = op._proc_sender.proc
        os.kill(proc.pid, signal.SIGKILL)
        if death < SENDER_LOSSES - 1:
            wait_until(lambda proc=proc: op._proc_sender.proc is not proc and op._proc_sender.alive()
                       and not op.sender_down, 30.0, message=f"the sender started again after death {death + 1}")
    wait_until(lambda: edge.supervisor.owner == "", 10.0, message="control given up")
    assert not op.owner and f"failed {SENDER_LOSSES} times" in op.sender_down, op.sender_down
    assert op.next_step() == NextStep(Step.WAIT, op.sender_down)
    assert any(e.status == "failed" for e in op.events), list(op.events)
    time.sleep(1.0)
    assert op._proc_sender.proc is proc and not op._proc_sender.alive()  # none started after the last
