"""A client whose router goes away says so, and says when it is back (iorthand.transport._say_router_links).

Zenoh reconnects by itself and says nothing: an edge whose router restarted looked alive in its own log (what
journalctl shows on the Pi) while no command could reach it. A real router in its own process, stopped and
started again on the same port."""

from __future__ import annotations

import logging

import pytest

from iorthand.transport import ZenohConfig, open_session
from tests.conftest import RouterProcess, wait_until


def test_a_client_says_when_its_router_goes_and_when_it_is_back(router_process: RouterProcess,
                                                               caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="iorthand.transport")
    where = router_process.endpoint
    session = open_session(ZenohConfig(mode="client", connect=[where]))
    try:
        assert "lost the link" not in caplog.text
        router_process.stop()
        wait_until(lambda: f"lost the link to the router at {where}: nothing goes out or comes in until it is back"
                   in caplog.text, timeout=10.0, message="the loss said")
        router_process.start()
        wait_until(lambda: f"linked to the router at {where} again" in caplog.text, timeout=15.0,
                   message="the return said")
    finally:
        session.close()
