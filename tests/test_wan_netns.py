"""One bounded test of the WAN namespaces: create, connect across the veth, black out with nftables, restore,
remove. Skips with a clear message when not root or when ``ip netns`` cannot be used."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from iorthand_operator.bench.wan import Namespaces

SERVER = "import socket;s=socket.socket();s.bind(('0.0.0.0',18000));s.listen();import time;time.sleep(30)"
CLIENT = "import socket,sys;socket.create_connection((sys.argv[2],18000),timeout=float(sys.argv[1])).close()"


def _connect(ns: str, timeout: float, host: str = "10.201.1.1") -> bool:
    r = subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-c", CLIENT, str(timeout), host], capture_output=True,
                       timeout=timeout + 10)
    return r.returncode == 0


def test_namespaces_link_blackout_and_cleanup() -> None:
    ok, why = Namespaces.available()
    if not ok:
        pytest.skip(f"WAN namespaces unavailable: {why}")
    ns = Namespaces(tag=f"t{int(time.time()) % 10000}").create()
    server = None
    try:
        server = subprocess.Popen(["ip", "netns", "exec", ns.cloud, sys.executable, "-c", SERVER])
        deadline = time.monotonic() + 10
        while not _connect(ns.op, 1.0):
            assert time.monotonic() < deadline, "operator namespace cannot reach the cloud namespace"
            time.sleep(0.1)
        ns.shape("10mbit")  # tbf on the edge link: accepted by the kernel
        assert _connect(ns.edge, 5.0, "10.201.2.1")
        ns.blackout(True)
        assert not _connect(ns.edge, 1.0, "10.201.2.1"), "the blackout let a connection through"
        out = subprocess.run(["ip", "netns", "exec", ns.edge, "nft", "list", "ruleset"], capture_output=True,
                             text=True, timeout=10).stdout
        assert "drop" in out
        ns.blackout(False)
        out = subprocess.run(["ip", "netns", "exec", ns.edge, "nft", "list", "ruleset"], capture_output=True,
                             text=True, timeout=10).stdout
        assert "drop" not in out
        assert _connect(ns.edge, 5.0, "10.201.2.1")
    finally:
        if server is not None:
            server.kill()
            server.wait(5)
        ns.destroy()
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, timeout=10).stdout
    assert ns.op not in listed and ns.cloud not in listed and ns.edge not in listed
