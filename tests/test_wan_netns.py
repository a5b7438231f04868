"""Bounded tests of the WAN namespaces: create, connect across the veth, black out with nftables, restore,
remove; and the choice between the kernel's netem and the project's relay. Skip with a clear message when not root
or when ``ip netns`` cannot be used. This machine's kernel has no netem: here the netem tests check that tc takes
every profile's arguments and that the kernel alone refuses them; on a kernel with netem they check the delay."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from iorthand_operator.bench.linkemu import LinkProfile
from iorthand_operator.bench.procs import Unavailable, run_cleanups
from iorthand_operator.bench.wan import PROFILES, Namespaces, Plan, choose_emulator, netem_args, run_profile

SERVER = "import socket;s=socket.socket();s.bind(('0.0.0.0',18000));s.listen();import time;time.sleep(30)"
CLIENT = "import socket,sys;socket.create_connection((sys.argv[2],18000),timeout=float(sys.argv[1])).close()"
# One TCP connect is one round trip (SYN, SYN-ACK): its time in ms.
TIMED = ("import socket,sys,time;t=time.perf_counter();socket.create_connection((sys.argv[1],18000),timeout=5).close();"
         "print((time.perf_counter()-t)*1000)")


def _connect(ns: str, timeout: float, host: str = "10.201.1.1") -> bool:
    r = subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-c", CLIENT, str(timeout), host], capture_output=True,
                       timeout=timeout + 10)
    return r.returncode == 0


def _namespaces() -> Namespaces:
    ok, why = Namespaces.available()
    if not ok:
        pytest.skip(f"WAN namespaces unavailable: {why}")
    return Namespaces(tag=f"t{int(time.time()) % 10000}").create()


def test_namespaces_link_blackout_and_cleanup() -> None:
    ns = _namespaces()
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


def test_every_profile_gets_past_tc_and_the_netem_probe_agrees_with_the_kernel() -> None:
    # tc parses netem's options itself: a wrong one is its usage error (exit 1). Only then does the kernel answer,
    # and a kernel without netem says the qdisc kind is unknown (exit 2).
    ns = _namespaces()
    try:
        has_netem, why = Namespaces.netem_available()
        for name, profile in PROFILES.items():
            argv = ["tc", "-n", ns.edge, "qdisc", "replace", "dev", ns.veth["edge"], "root",
                    *netem_args(profile.link, profile.rate)]
            r = subprocess.run(argv, capture_output=True, text=True, timeout=10)
            if has_netem:
                assert r.returncode == 0, f"{name}: {r.stderr}"
            else:
                assert r.returncode == 2 and "unknown" in r.stderr, f"{name}: tc itself refused {argv}: {r.stderr}"
        if has_netem:
            ns.emulate(PROFILES["lan"].link, PROFILES["4g"].link, PROFILES["4g"].rate)
            for netns, dev in ((ns.op, ns.veth["op"]), (ns.cloud, ns.veth["cloud_op"]), (ns.edge, ns.veth["edge"]),
                               (ns.cloud, ns.veth["cloud_edge"])):
                shown = subprocess.run(["tc", "-n", netns, "qdisc", "show", "dev", dev], capture_output=True,
                                       text=True, timeout=10).stdout
                assert "netem" in shown, f"{dev}: {shown}"
        else:
            assert why.startswith("this kernel has no netem qdisc") and "unknown" in why
            with pytest.raises(subprocess.CalledProcessError):
                ns.emulate(PROFILES["lan"].link, PROFILES["4g"].link, PROFILES["4g"].rate)
    finally:
        ns.destroy()


def test_the_emulator_follows_what_the_machine_has(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ValueError, match="unknown link emulator 'tc'"):
        choose_emulator("tc", force_loopback=False)
    with pytest.raises(Unavailable, match="--emulator netem needs network namespaces: loopback requested"):
        choose_emulator("netem", force_loopback=True)
    assert choose_emulator("auto", force_loopback=True)[:2] == (False, False)
    ok, why = Namespaces.available()
    if not ok:
        pytest.skip(f"WAN namespaces unavailable: {why}")
    assert choose_emulator("relay", force_loopback=False)[:2] == (True, False)
    has_netem, netem_why = Namespaces.netem_available()
    if has_netem:
        assert choose_emulator("auto", force_loopback=False)[:2] == (True, True)
        assert choose_emulator("netem", force_loopback=False)[:2] == (True, True)
        return
    capsys.readouterr()
    namespaces, netem, said = choose_emulator("auto", force_loopback=False)
    assert (namespaces, netem) == (True, False) and netem_why in said
    assert "no netem qdisc" in capsys.readouterr().out  # the user is told what was fallen back from
    with pytest.raises(Unavailable, match="--emulator netem: this kernel has no netem qdisc"):
        choose_emulator("netem", force_loopback=False)


def test_netem_delays_each_direction_of_the_edge_link() -> None:
    ns = _namespaces()
    server = None
    try:
        has_netem, why = Namespaces.netem_available()
        if not has_netem:
            pytest.skip(f"{why}: the relay carries the delay on this machine (tests/test_linkemu.py)")
        ns.emulate(LinkProfile(0.0), LinkProfile(20.0), "")
        server = subprocess.Popen(["ip", "netns", "exec", ns.cloud, sys.executable, "-c", SERVER])
        deadline = time.monotonic() + 10
        while not _connect(ns.op, 1.0):
            assert time.monotonic() < deadline, "operator namespace cannot reach the cloud namespace"
            time.sleep(0.1)

        def connect_ms(netns: str, host: str) -> float:
            r = subprocess.run(["ip", "netns", "exec", netns, sys.executable, "-c", TIMED, host], capture_output=True,
                               text=True, timeout=15, check=True)
            return float(r.stdout)

        edge = min(connect_ms(ns.edge, "10.201.2.1") for _ in range(3))
        operator = min(connect_ms(ns.op, "10.201.1.1") for _ in range(3))
        assert edge >= 39.0, f"20 ms each way on the edge link, yet a round trip took {edge:.1f} ms"
        assert operator < 20.0, f"the operator link has no delay, yet a round trip took {operator:.1f} ms"
    finally:
        if server is not None:
            server.kill()
            server.wait(5)
        ns.destroy()


def test_the_netem_layout_carries_commands_and_blackouts_without_relays(tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """The whole WAN run as netem lays it out: the operator and the edge-site router dial the cloud router across
    the veths, with no relay, and blackouts are nftables drops. On a kernel without netem the qdiscs cannot exist,
    so this test leaves the veths unshaped (the one thing it replaces); on a kernel with netem it shapes them."""
    ns = _namespaces()
    try:
        if not Namespaces.netem_available()[0]:
            monkeypatch.setattr(Namespaces, "emulate", lambda self, *link: None)
        result = run_profile(tmp_path, PROFILES["blackout"], Plan(duration=0.0, trials=2), ns, netem=True)
    finally:
        ns.destroy()
        run_cleanups()
    assert result["emulator"] == "netem"
    assert not (tmp_path / "wan-blackout" / "relay-edge.log").exists(), "a relay was started"
    assert result["rtt_ms"]["count"] > 100 and result["rtt_ms"]["p50"] < 50.0
    for trial in result["trials"]:
        assert trial["moving_before"] and trial["stayed_stopped"], trial
        assert trial["stop_after_last_command_ms"] is not None, trial
        assert trial["operator_echo_after_ms"] is not None and trial["motion_resumed_after_ms"] is not None, trial
