"""Clients that recover (issue 24): what an operator must do before the robot moves again, and headless clients
(``move``, ``script``) that do it themselves and complete their motion after a dead link or a lost lease."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from iorthand import keys
from iorthand.protocol import SafetyStatus, Status, StopCommand
from iorthand.transport import ZenohConfig, open_session
from iorthand_operator import recovery
from iorthand_operator.bench.linkemu import LinkEmulator, LinkProfile
from iorthand_operator.client import OperatorClient
from iorthand_operator.script import Script, ScriptStep, run_script
from iorthand_operator.scripted import move
from tests.conftest import wait_until


def status(code: Status, owner: str = "me", armed: bool = True, reason: str = "") -> SafetyStatus:
    return SafetyStatus(armed=armed, owner=owner, status=code, reason=reason)


@pytest.mark.parametrize(("safety", "owner_held", "fresh", "step"), [
    (None, True, True, recovery.Step.WAIT),
    (status(Status.OK), True, True, recovery.Step.NONE),
    (status(Status.OK, armed=False), True, True, recovery.Step.WAIT),
    (status(Status.OK, owner="alice"), False, False, recovery.Step.WAIT),
    (status(Status.IDLE, owner=""), False, False, recovery.Step.ACQUIRE),
    (status(Status.OWNER_LOST, owner=""), True, True, recovery.Step.ACQUIRE),  # the client does not know yet
    (status(Status.FAULT), True, True, recovery.Step.ACQUIRE),
    (status(Status.STOPPED), True, False, recovery.Step.PRESS),  # a press held through the stop: not fresh
    (status(Status.STOPPED), True, True, recovery.Step.NONE),  # pressed afresh: on its way
    (status(Status.LINK_GAP), True, False, recovery.Step.PRESS),
    (status(Status.NO_DEADMAN), True, False, recovery.Step.PRESS),
])
def test_the_next_step_follows_what_the_edge_says(safety, owner_held, fresh, step) -> None:
    assert recovery.next_step("me", owner_held, safety, fresh).step is step


def test_a_sender_that_is_down_is_what_the_operator_waits_for() -> None:
    """Whatever the edge says, nothing moves the robot while this console's commands cannot go out."""
    why = "the command sender process was killed by SIGKILL: no command goes out"
    for safety in (status(Status.OK), status(Status.LINK_GAP), status(Status.IDLE, owner="")):
        step = recovery.next_step("me", True, safety, True, sender_down=why)
        assert step == recovery.NextStep(recovery.Step.WAIT, why)
    assert recovery.hint(recovery.next_step("me", True, status(Status.OK), True, why), "E", "SPACE", True) == why


def test_a_press_from_before_the_grant_or_the_senders_restart_must_be_made_again() -> None:
    """Its commands say "released" whatever the edge's status (a restart slower than the release tail sends none:
    the edge shows a command timeout, which by itself asks for nothing)."""
    for code in (Status.COMMAND_TIMEOUT, Status.NO_DEADMAN, Status.OK):
        step = recovery.next_step("me", True, status(code), False, old_press=True)
        assert step.step is recovery.Step.PRESS and "started again" in step.why, step
    assert recovery.next_step("me", True, status(Status.COMMAND_TIMEOUT), False).step is recovery.Step.NONE


def test_the_hint_names_the_key() -> None:
    press = recovery.NextStep(recovery.Step.PRESS, "stop from nurse")
    assert recovery.hint(press, "E", "SPACE", toggle=True) == "press SPACE to move again (stop from nurse)"
    assert recovery.hint(press, "E", "button 4", toggle=False).startswith("release button 4 and press it again")
    acquire = recovery.NextStep(recovery.Step.ACQUIRE, "lease of 'me' expired")
    assert recovery.hint(acquire, "E", "SPACE", toggle=True) == "press E to take control (lease of 'me' expired)"
    assert recovery.hint(recovery.NextStep(recovery.Step.NONE, ""), "E", "SPACE", True) == ""


@pytest.fixture
def relayed_client(router_endpoint, edge_factory):
    """The edge on the router directly; the operator through a relay that can black the link out."""
    edge = edge_factory("sim1")
    host, port = router_endpoint.split("/", 1)[1].rsplit(":", 1)
    emu = LinkEmulator(("127.0.0.1", 0), (host, int(port)), LinkProfile(0.0, 0.0)).start()
    session = open_session(ZenohConfig(mode="client", connect=[f"tcp/127.0.0.1:{emu.port}"], lease_ms=2000,
                                       shared_memory=False))
    client = OperatorClient(session, "sim1", "op1")
    client.wait_for_state()
    yield edge, emu, client
    client.close()
    session.close()
    emu.close()


def _blackout_after(emu: LinkEmulator, client: OperatorClient, moved_s: float, seconds: float) -> threading.Thread:
    """Black the link out for ``seconds`` once the robot has moved for about ``moved_s``."""
    def run() -> None:
        deadline = time.monotonic() + 20
        while sum(e.accepted and e.status != Status.NO_DEADMAN for e in list(client.echoes)) < 60 * moved_s and \
                time.monotonic() < deadline:
            time.sleep(0.01)
        emu.blackout(True)
        time.sleep(seconds)
        emu.blackout(False)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


@pytest.mark.slow
def test_move_completes_its_motion_after_a_3_s_blackout(relayed_client) -> None:
    edge, emu, client = relayed_client
    client.start()
    client.acquire()
    x0 = client.robot_state.tcp_pose[0]
    grants = client._key_gen
    blackout = _blackout_after(emu, client, 0.5, 3.0)
    result = move(client, np.array([0.005, 0.0, 0.0]), np.zeros(3), 2.0, patience=20.0)
    blackout.join()
    assert result["completed"], result
    # The edge let control go during the blackout: granted anew (by the client's lease renewal, which retries
    # until the lease can have run out, or by the move's own acquire), and the move pressed afresh under it.
    assert client._key_gen > grants and result["recoveries"], result["recoveries"]
    # 2 s at 5 mm/s: the distance the operator asked for, dead link or not (the edge stopped during it).
    assert client.robot_state.tcp_pose[0] - x0 == pytest.approx(0.010, abs=0.002)
    assert edge.supervisor.counters.stops >= 1  # the edge did stop the robot while the link was dead


@pytest.mark.slow
def test_move_completes_its_motion_after_a_lease_lost_on_a_slow_start(router_endpoint, edge_factory,
                                                                        operator_factory) -> None:
    """The client acquired, then took longer than the lease to send its first command (a loaded machine): the
    edge took control back; the move acquires again and completes."""
    edge = edge_factory("sim1")
    client = operator_factory("sim1", "op1")
    client.wait_for_state()
    client.acquire()
    time.sleep(edge.config.safety.lease + 1.0)  # no renewal, no command: the lease runs out
    assert edge.supervisor.owner == ""
    grants = client._key_gen
    client.start()
    x0 = client.robot_state.tcp_pose[0]
    result = move(client, np.array([0.005, 0.0, 0.0]), np.zeros(3), 1.0, patience=10.0)
    assert result["completed"], result
    assert client._key_gen > grants  # control was granted anew (by the renewal or the move's own acquire)...
    assert result["recoveries"], result  # ...and the move pressed afresh under it
    assert client.robot_state.tcp_pose[0] - x0 == pytest.approx(0.005, abs=0.0015)


@pytest.mark.slow
def test_a_script_completes_its_motion_after_a_3_s_blackout(relayed_client) -> None:
    _edge, emu, client = relayed_client
    client.start()
    client.acquire()
    y0 = client.robot_state.tcp_pose[1]
    grants = client._key_gen
    script = Script(name="scan", steps=[ScriptStep(twist=[0.0, 0.005, 0.0, 0.0, 0.0, 0.0], duration=2.0),
                                        ScriptStep(wait=0.3)], patience=20.0)
    blackout = _blackout_after(emu, client, 0.5, 3.0)
    result = run_script(client, script)
    blackout.join()
    step = result["steps"][0]
    assert client._key_gen > grants and step["recoveries"], step  # granted anew, pressed afresh (as above)
    assert client.robot_state.tcp_pose[1] - y0 == pytest.approx(0.010, abs=0.002), result


def _driving(edge_factory, operator_factory):
    """An edge for sim1, and op1's client holding control with its sender started."""
    edge = edge_factory("sim1")
    client = operator_factory("sim1", "op1")
    client.wait_for_state()
    client.acquire()
    client.start()
    return edge, client


def _nurse_stops(session_factory, edge, reason: str) -> None:
    """A stop from another session (the nurse at the patient), and the robot stopped by it."""
    nurse = session_factory().declare_publisher(keys.RobotKeys("sim1").key(keys.CMD_STOP))
    nurse.put(StopCommand(operator="nurse", reason=reason).stamp(1).encode())
    wait_until(lambda: not np.any(edge._commanded), 2.0, message="the robot stopped")


def test_a_headless_move_stopped_by_somebody_ends_and_does_not_resume(edge_factory, operator_factory,
                                                                      session_factory) -> None:
    """Found by a red-team run of the operator side: `iorthand operator move` pressed afresh by itself after a
    nurse's stop, and the robot moved again 0.29 s later. A stop that comes during the motion ends it."""
    edge, client = _driving(edge_factory, operator_factory)
    out: list[dict] = []
    t = threading.Thread(target=lambda: out.append(move(client, np.array([0.005, 0.0, 0.0]), np.zeros(3), 3.0,
                                                        patience=5.0)))
    t.start()
    wait_until(lambda: np.any(edge._commanded), 5.0, message="the move under way")
    time.sleep(0.3)
    _nurse_stops(session_factory, edge, "patient moved")
    x = client.robot_state.tcp_pose[0]
    t.join(10)
    assert out and not out[0]["completed"], out
    assert any(r.startswith("stopped: stop from 'nurse'") for r in out[0]["recoveries"]), out[0]["recoveries"]
    time.sleep(0.5)
    assert client.robot_state.tcp_pose[0] == pytest.approx(x, abs=5e-4)  # it did not move again


@pytest.mark.parametrize("when", ["during a motion", "during a wait"])
def test_a_stop_from_somebody_else_ends_the_script(edge_factory, operator_factory, session_factory, when: str) -> None:
    """Found by a red-team run of the operator side: a nurse's stop during a script ended that step only; the
    next motion pressed afresh by itself and moved 4.9 mm. The script was the intent for what came before the
    stop, not after it."""
    edge, client = _driving(edge_factory, operator_factory)
    twist = [0.005, 0.0, 0.0, 0.0, 0.0, 0.0]
    script = Script(name="scan", patience=5.0, steps=[
        ScriptStep(twist=twist, duration=1.5), ScriptStep(wait=1.5), ScriptStep(twist=twist, duration=1.0)])
    out: list[dict] = []
    t = threading.Thread(target=lambda: out.append(run_script(client, script)))
    t.start()
    wait_until(lambda: np.any(edge._commanded), 5.0, message="the first motion under way")
    if when == "during a wait":
        wait_until(lambda: not np.any(edge._commanded), 5.0, message="the wait step")
    time.sleep(0.3)
    _nurse_stops(session_factory, edge, "patient coughed")
    x = client.robot_state.tcp_pose[0]
    t.join(15)
    time.sleep(0.5)
    assert client.robot_state.tcp_pose[0] == pytest.approx(x, abs=5e-4)  # nothing moved after it
    summary = out[0]
    assert summary["ended_by_stop"].startswith("stop from 'nurse'"), summary["ended_by_stop"]
    assert len(summary["steps"]) == (1 if when == "during a motion" else 2), summary["steps"]


def test_a_scripts_own_stop_step_is_not_a_stop_from_somebody_else(edge_factory, operator_factory) -> None:
    """Its stop reaches the edge and comes back as the edge's status while the next step already drives: that
    motion is what the script asked after its stop, and it runs to its end."""
    _, client = _driving(edge_factory, operator_factory)
    x0 = client.robot_state.tcp_pose[0]
    summary = run_script(client, Script(name="stop-then-go", patience=5.0, steps=[
        ScriptStep(action="stop", reason="script's own stop"),
        ScriptStep(twist=[0.005, 0.0, 0.0, 0.0, 0.0, 0.0], duration=1.0)]))
    assert not summary["ended_by_stop"] and len(summary["steps"]) == 2
    assert client.robot_state.tcp_pose[0] - x0 == pytest.approx(0.005, abs=0.001), summary["steps"]


def test_a_console_that_hears_nothing_from_the_edge_says_so_instead_of_nothing_to_do(relayed_client) -> None:
    """Found by a red-team run of the operator side: the hint came from the last safety status however old, so with
    the link dead it went on saying that nothing stood between the operator and motion."""
    _edge, emu, client = relayed_client
    client.start()
    client.acquire()
    client.set_twist([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=False)
    time.sleep(0.2)
    client.set_twist([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)  # a fresh press: nothing stands in the way
    wait_until(lambda: client.next_step().step is recovery.Step.NONE, 5.0, message="ready to move")
    emu.blackout(True)
    try:
        wait_until(lambda: client.next_step().step is recovery.Step.WAIT, 5.0, message="the edge's silence said")
        assert "no safety status from the edge for" in client.next_step().why
    finally:
        emu.blackout(False)


def test_driving_is_judged_on_the_monotonic_clock(edge_factory, operator_factory, monkeypatch) -> None:
    """Found by a red-team run of the operator side: the wall clock stepped back (NTP) made the last echo look
    fresh for the size of the step, and a headless motion's checks for a halt or a stop were blind meanwhile."""
    import iorthand_operator.client as client_module

    _, client = _driving(edge_factory, operator_factory)
    client.set_twist([0.002, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)
    wait_until(client.driving, 5.0, message="driving")
    client.muted = True  # no command goes out any more: the last echo ages
    real = time.time_ns
    monkeypatch.setattr(client_module.time, "time_ns", lambda: real() - 5_000_000_000)  # the clock steps back 5 s
    time.sleep(0.3)
    assert not client.driving()
