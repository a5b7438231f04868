"""Idle connections cannot lock everyone out of the router.

Found by trial (2026-11-29): anyone who reaches a router's plain tcp/ listener (a lab, a site's own network)
could open 150 TCP connections and send nothing; the router then refused every new session at once ("Unable to
connect") until they timed out 10 s later, and an attacker simply opens them again: an edge back from a blip, or
an operator, could not get in. (The tls/ listener did not lock out with 1 000 idle or half-begun handshakes.) Zenoh lets 100 sessions be in their handshake at a time by default; the routers now let 1024
(``iorthand.transport.ACCEPT_PENDING``), and ``deploy/router/nftables.conf`` caps the connections one address may
hold at 32 (docs/DEPLOY.md §2).
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time

import pytest
import zenoh

from iorthand_operator.bench.wan import Namespaces
from tests.conftest import ROOT

OPEN_SESSION = ("import json,sys,zenoh;zenoh.open(zenoh.Config.from_json5(json.dumps({'mode':'client',"
                "'connect':{'endpoints':[sys.argv[1]]},'scouting':{'multicast':{'enabled':False}}}))).close();print('in')")
# Opens argv[3] connections to argv[1]:argv[2], says how many the other side accepted, then holds them.
HOLD = ("import resource,socket,sys,time\n"
        "resource.setrlimit(resource.RLIMIT_NOFILE,(4096,4096))\n"
        "held=[]\n"
        "for _ in range(int(sys.argv[3])):\n"
        "    try: held.append(socket.create_connection((sys.argv[1],int(sys.argv[2])),timeout=2))\n"
        "    except OSError: pass\n"
        "print(len(held),flush=True)\n"
        "time.sleep(60)\n")


def _open_session(endpoint: str, ns: str | None = None) -> subprocess.CompletedProcess[str]:
    prefix = ["ip", "netns", "exec", ns] if ns else []
    return subprocess.run([*prefix, sys.executable, "-c", OPEN_SESSION, endpoint], capture_output=True, text=True,
                          timeout=30)


def test_a_hundred_and_fifty_idle_connections_do_not_lock_new_sessions_out(router_endpoint: str) -> None:
    port = int(router_endpoint.rsplit(":", 1)[1])
    idle = [socket.create_connection(("127.0.0.1", port)) for _ in range(150)]
    try:
        time.sleep(0.3)
        done = _open_session(router_endpoint)
        # Before: "Unable to connect to any of [tcp/127.0.0.1:…]" at once.
        assert done.returncode == 0 and "in" in done.stdout, done.stderr[-500:]
    finally:
        for s in idle:
            s.close()


def test_one_address_holds_at_most_32_connections_and_the_edge_still_gets_in(tmp_path) -> None:
    """The router in its own namespace with deploy/router/nftables.conf loaded; 1 100 connections from the operators'
    side (more than the router's ACCEPT_PENDING), then the edge's namespace opens a session."""
    ok, why = Namespaces.available()
    if not ok:
        pytest.skip(f"network namespaces unavailable: {why}")
    ns = Namespaces(tag=f"a{int(time.time()) % 10000}").create()
    procs: list[subprocess.Popen[str]] = []
    try:
        subprocess.run(["ip", "netns", "exec", ns.cloud, "nft", "-f", str(ROOT / "deploy" / "router" / "nftables.conf")],
                       check=True, timeout=10)
        config = tmp_path / "router.json5"
        # The shipped plain configuration's transport section, listening on every address of the namespace.
        transport = json.loads(zenoh.Config.from_file(str(ROOT / "configs" / "router.json5")).get_json("transport"))
        config.write_text(json.dumps({"mode": "router", "listen": {"endpoints": ["tcp/0.0.0.0:7447"]},
                                      "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
                                      "transport": transport}))
        router = subprocess.Popen(["ip", "netns", "exec", ns.cloud, sys.executable, "-m", "iorthand.cli", "router",
                                   "--config", str(config)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        procs.append(router)
        assert router.stdout is not None
        deadline = time.monotonic() + 20
        while "router ready" not in router.stdout.readline():
            assert time.monotonic() < deadline and router.poll() is None, "the router did not start"
        attacker = subprocess.Popen(["ip", "netns", "exec", ns.op, sys.executable, "-c", HOLD, "10.201.1.1", "7447",
                                     "1100"], stdout=subprocess.PIPE, text=True)
        procs.append(attacker)
        assert attacker.stdout is not None
        held = int(attacker.stdout.readline())
        assert held == 32, f"one address held {held} connections"
        done = _open_session("tcp/10.201.2.1:7447", ns.edge)
        assert done.returncode == 0 and "in" in done.stdout, done.stderr[-500:]
    finally:
        for p in procs:
            p.kill()
            p.wait(10)
        ns.destroy()
