"""What a router and its clients say in their logs (what journalctl shows a hospital engineer).

A client whose router goes away says so, and says when it is back (iorthand.transport._say_router_links): Zenoh
reconnects by itself and says nothing, and an edge whose router restarted looked alive in its own log while no
command could reach it. A router listening in clear beyond the loopback says so at start. Real routers in their
own processes."""

from __future__ import annotations

import logging
import subprocess
import sys

import pytest

from iorthand.transport import ZenohConfig, open_session
from tests.conftest import RouterProcess, free_port, stop_process, wait_until


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


@pytest.mark.parametrize(("listen", "warned"), [("tcp/0.0.0.0", True), ("tcp/127.0.0.1", False)])
def test_a_router_listening_in_clear_beyond_the_loopback_says_so_at_start(listen: str, warned: bool) -> None:
    endpoint = f"{listen}:{free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "iorthand.cli", "router", "--listen", endpoint],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert proc.stdout is not None
        said = []
        for line in proc.stdout:
            said.append(line)
            if "router ready" in line:
                break
        text = "".join(said)
        assert "router ready" in text, text
        assert (f"listening in clear on {endpoint}, reachable from the network" in text) is warned, text
    finally:
        stop_process(proc)
