"""Route planning in the edge's planner process (iorthand_edge.planner): the same plans as in-process, a plan
that overruns refused with why, and the child replaced after it."""

from __future__ import annotations

import logging
import math
import multiprocessing
import os
import signal
import threading
from pathlib import Path

import numpy as np
import pytest

from iorthand import motion
from iorthand_edge.goto import GotoConfig, GotoController
from iorthand_edge.planner import PlannerProcess, PlanningTimeout
from tests.conftest import wait_until

LIMITS = motion.Limits(0.03, 0.2, 0.25, (0.1, -0.3, 0.02), (0.45, 0.3, 0.45))
HERE = np.array([0.30, 0.0, 0.20, math.pi, 0.0, 0.0])
LONGEST_SWEEP = {"lanes": 50, "width": 0.15, "pitch": 0.001}  # ~1.7 s of planning here


@pytest.fixture
def planner():
    p = PlannerProcess()
    yield p
    p.close()


def test_a_plan_from_the_planner_process_is_the_plan_made_here(planner) -> None:
    params = {"lanes": 3, "width": 0.04, "pitch": 0.01}
    before = {p.pid for p in multiprocessing.active_children()}
    there = planner.plan_route("sweep", HERE, LIMITS, {}, None, 0.05, 0.1, None, params)
    started = [p for p in multiprocessing.active_children() if p.pid not in before]
    assert len(started) == 1 and started[0].pid != os.getpid()  # the planner's child, started by the first plan
    here = motion.plan_route("sweep", HERE, LIMITS, {}, None, 0.05, 0.1, None, params)
    assert there.summary() == here.summary()


def test_a_plan_that_overruns_is_refused_and_the_planner_starts_again(planner) -> None:
    planner.timeout = 0.2
    with pytest.raises(PlanningTimeout, match=r"planning 'sweep' took longer than 0.2 s"):
        planner.plan_route("sweep", HERE, LIMITS, {}, None, 0.05, 0.1, None, LONGEST_SWEEP)
    planner.timeout = 30.0
    assert planner.plan_route("sweep", HERE, LIMITS, {}, None, 0.05, 0.1, None, {"lanes": 2}).ok


def test_the_goto_controller_refuses_a_preview_whose_plan_overran(planner) -> None:
    planner.timeout = 0.2
    ctl = GotoController(GotoConfig(), LIMITS.workspace_min, LIMITS.workspace_max, planner=planner.plan_route)
    pv = ctl.preview("sweep", "alice", HERE, 0.0, LIMITS, params=LONGEST_SWEEP)
    assert not pv.ok and not pv.token
    assert pv.plan.reason == "planning 'sweep' took longer than 0.2 s: refused"


def test_a_planner_that_dies_while_planning_refuses_that_preview_and_the_next_one_plans(planner) -> None:
    """Found while checking previews in the secured deployment: the planner's child killed while it planned (the
    kernel's out-of-memory killer on a Pi, say) raised in the edge's planner thread, whose crash stopped the whole
    edge (no more robot states). Now that preview is refused with why, and the next one starts a new child."""
    ctl = GotoController(GotoConfig(), LIMITS.workspace_min, LIMITS.workspace_max, planner=planner.plan_route)
    assert ctl.preview("sweep", "alice", HERE, 0.0, LIMITS, params={"lanes": 2}).ok  # the child is up
    child = planner._child
    assert child is not None and child.pid is not None
    threading.Timer(0.3, os.kill, (child.pid, signal.SIGKILL)).start()
    pv = ctl.preview("sweep", "alice", HERE, 0.0, LIMITS, params=LONGEST_SWEEP)
    assert not pv.ok and not pv.token
    assert pv.plan.reason == "planning failed: RuntimeError: the planner process ended while planning 'sweep'"
    again = ctl.preview("sweep", "alice", HERE, 0.0, LIMITS, params={"lanes": 2})
    assert again.ok and again.token and planner._child is not None and planner._child.pid != child.pid


def test_a_planner_that_died_between_previews_is_started_again_for_the_next_one(planner) -> None:
    """Killed while idle (the out-of-memory killer between two previews): every later preview failed with
    BrokenPipeError until the edge restarted, and with them the retreat to the safe pose."""
    ctl = GotoController(GotoConfig(), LIMITS.workspace_min, LIMITS.workspace_max, planner=planner.plan_route)
    assert ctl.preview("sweep", "alice", HERE, 0.0, LIMITS, params={"lanes": 2}).ok
    child = planner._child
    assert child is not None and child.pid is not None
    os.kill(child.pid, signal.SIGKILL)
    child.join(5.0)
    pv = ctl.preview("sweep", "alice", HERE, 0.0, LIMITS, params={"lanes": 2})
    assert pv.ok and pv.token, pv.plan.reason
    assert planner._child is not None and planner._child.pid != child.pid


def test_a_planner_killed_between_plans_is_reaped_and_said_at_once(planner, caplog) -> None:
    """Found by a red-team run: the planner's child killed while idle (the out-of-memory killer) stayed a zombie,
    and nothing said so, until the next preview, which may never come. Now it is reaped, and logged with why, at
    once; the next plan starts a new child."""
    assert planner.plan_route("sweep", HERE, LIMITS, {}, None, 0.05, 0.1, None, {"lanes": 2}).ok
    child = planner._child
    assert child is not None and child.pid is not None
    with caplog.at_level(logging.ERROR, logger="iorthand.edge.planner"):
        os.kill(child.pid, signal.SIGKILL)
        wait_until(lambda: not Path(f"/proc/{child.pid}").exists(), 5.0, message="the killed planner reaped")
        wait_until(lambda: "the planner process was killed by SIGKILL" in caplog.text, 5.0, message="the log line")
    assert planner.plan_route("sweep", HERE, LIMITS, {}, None, 0.05, 0.1, None, {"lanes": 2}).ok
    assert planner._child is not None and planner._child.pid != child.pid


def test_a_planner_closed_on_purpose_is_not_reported_as_ended(planner, caplog) -> None:
    assert planner.plan_route("sweep", HERE, LIMITS, {}, None, 0.05, 0.1, None, {"lanes": 2}).ok
    child = planner._child
    assert child is not None
    with caplog.at_level(logging.ERROR, logger="iorthand.edge.planner"):
        planner.close()
        child.join(5.0)
        assert not child.is_alive()
    assert "the planner process" not in caplog.text


def test_a_preview_the_stopped_planner_cannot_answer_reaches_the_operator_with_why(
        edge_factory, operator_factory, router_endpoint, tmp_path: Path) -> None:
    """Found by a review: with the edge's planner stopped, a preview reached the operator as "query … failed:
    Timeout" after the client's 2 s query timeout, before the edge could refuse it (PLAN_TIMEOUT_S, 10 s). A real
    edge, its planner's child SIGSTOPped, a real twin in between (its preview_timeout above the edge's bound): the
    owner reads the edge's refusal; a client that gives up sooner reads that the planner did not answer."""
    from iorthand.config import from_dict
    from iorthand_cloud.twin.config import TwinConfig
    from iorthand_cloud.twin.service import TwinService
    from iorthand_edge.planner import PLAN_TIMEOUT_S
    from iorthand_operator.client import ControlRefused

    edge = edge_factory()
    twin = TwinService(from_dict({"zenoh": {"mode": "client", "connect": [router_endpoint]}, "preview_timeout": 15.0,
                                  "viewer": {"serve": False, "save": str(tmp_path / "twin.rrd")}},
                                 TwinConfig, source="<test>"))
    twin.start()
    child = None
    try:
        alice = operator_factory(operator_id="alice")
        alice.wait_for_state()
        alice.acquire()
        assert alice.preview_pose("home").ok  # the planner's child is up
        child = edge._planner._child
        assert child is not None and child.pid is not None
        os.kill(child.pid, signal.SIGSTOP)
        answers: list[object] = []

        def preview() -> None:
            try:
                answers.append(alice.preview_pose("home"))
            except RuntimeError as exc:  # (the old client's bare "Timeout")
                answers.append(exc)

        owner = threading.Thread(target=preview)
        owner.start()
        # Another console that waits only 1 s: the planner (and the twin, waiting for it) cannot answer by then.
        bob = operator_factory(operator_id="bob", plan_timeout=1.0)
        with pytest.raises(ControlRefused, match=r"^the edge's planner did not answer the preview of 'home' within 1 s"):
            bob.preview_pose("home")
        owner.join(PLAN_TIMEOUT_S + 10.0)
        assert not owner.is_alive()
        (reply,) = answers
        assert not isinstance(reply, Exception), f"the owner read {reply!r}"
        assert not reply.ok and reply.reason == f"planning 'home' took longer than {PLAN_TIMEOUT_S:g} s: refused"
    finally:
        if child is not None and child.is_alive():
            os.kill(child.pid, signal.SIGCONT)
        twin.shutdown()
