"""The userspace link emulator on 127.0.0.1: delay, order under jitter, blackout, clean close; and its datagram relay:
delay, loss per packet, nothing held behind a loss."""

from __future__ import annotations

import contextlib
import random
import socket
import subprocess
import threading
import time
from collections.abc import Iterator

import pytest

from iorthand_operator.bench.linkemu import PACKET_PAYLOAD, DatagramRelay, DelayLine, LinkEmulator, LinkProfile
from tests.conftest import iorthand_cmd


@pytest.fixture
def echo_server() -> Iterator[tuple[str, int]]:
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    stop = threading.Event()

    def serve(conn: socket.socket) -> None:
        with conn:
            while data := conn.recv(65536):
                conn.sendall(data)

    def accept() -> None:
        while not stop.is_set():
            try:
                conn, _ = srv.accept()
            except OSError:
                return
            threading.Thread(target=serve, args=(conn,), daemon=True).start()

    threading.Thread(target=accept, daemon=True).start()
    yield srv.getsockname()
    stop.set()
    srv.close()


@pytest.fixture
def udp_echo() -> Iterator[tuple[str, int]]:
    srv = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    srv.bind(("127.0.0.1", 0))

    def serve() -> None:
        while True:
            try:
                data, peer = srv.recvfrom(65536)
                srv.sendto(data, peer)
            except OSError:
                return

    threading.Thread(target=serve, daemon=True).start()
    yield srv.getsockname()
    srv.close()


def _recv_exactly(s: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        chunk = s.recv(n - len(buf))
        if not chunk:
            break
        buf += chunk
    return buf


def test_delay_line_keeps_order_and_bounds() -> None:
    line = DelayLine(LinkProfile(20.0, 15.0), random.Random(3))
    releases = [line.release_time(i * 0.001) for i in range(500)]
    assert releases == sorted(releases)  # never out of order
    assert all(r >= i * 0.001 + 0.005 - 1e-9 for i, r in enumerate(releases))  # at least delay − jitter
    own = [line.sample_delay() for _ in range(2000)]
    assert min(own) >= 0.005 and max(own) <= 0.035


def test_stall_adds_head_of_line_delay() -> None:
    line = DelayLine(LinkProfile(1.0, 0.0, stall_prob=1.0, stall_ms=100.0), random.Random(1))
    assert line.sample_delay() == pytest.approx(0.101)


def test_profile_rejects_nonsense() -> None:
    with pytest.raises(ValueError):
        LinkProfile(-1.0)
    with pytest.raises(ValueError):
        LinkProfile(1.0, stall_prob=2.0)


def test_relay_adds_delay_both_ways(echo_server: tuple[str, int]) -> None:
    with LinkEmulator(("127.0.0.1", 0), echo_server, LinkProfile(25.0)) as emu, \
            socket.create_connection(("127.0.0.1", emu.port), timeout=5) as s:
        t0 = time.monotonic()
        s.sendall(b"ping")
        assert _recv_exactly(s, 4) == b"ping"
        rtt = time.monotonic() - t0
    assert rtt >= 0.050  # 25 ms each way
    assert rtt < 2.0


def test_relay_preserves_stream_under_jitter(echo_server: tuple[str, int]) -> None:
    payload = b"".join(i.to_bytes(4, "big") for i in range(5000))
    with LinkEmulator(("127.0.0.1", 0), echo_server, LinkProfile(5.0, 5.0, 0.05, 20.0), seed=5) as emu:
        with socket.create_connection(("127.0.0.1", emu.port), timeout=10) as s:
            for k in range(0, len(payload), 700):  # many small writes → many chunks with their own delays
                s.sendall(payload[k:k + 700])
                time.sleep(0.0005)
            assert _recv_exactly(s, len(payload)) == payload
        deadline = time.monotonic() + 2.0  # the writer counts just after its last send
        while emu.bytes_relayed < 2 * len(payload) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert emu.bytes_relayed == 2 * len(payload)


def test_blackout_holds_traffic_then_delivers(echo_server: tuple[str, int]) -> None:
    with LinkEmulator(("127.0.0.1", 0), echo_server, LinkProfile()) as emu, \
            socket.create_connection(("127.0.0.1", emu.port), timeout=5) as s:
        s.sendall(b"a")
        assert _recv_exactly(s, 1) == b"a"
        emu.blackout(True)
        s.sendall(b"b")
        s.settimeout(0.3)
        with pytest.raises(TimeoutError):
            s.recv(1)
        emu.blackout(False)
        s.settimeout(5)
        assert _recv_exactly(s, 1) == b"b"


def test_close_ends_connections(echo_server: tuple[str, int]) -> None:
    emu = LinkEmulator(("127.0.0.1", 0), echo_server, LinkProfile()).start()
    s = socket.create_connection(("127.0.0.1", emu.port), timeout=5)
    s.sendall(b"x")
    assert _recv_exactly(s, 1) == b"x"
    emu.close()
    s.settimeout(5)
    assert s.recv(1) == b""  # the relay shut the connection down
    s.close()
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", emu.port), timeout=1).close()


def test_the_bench_command_runs_the_relay(echo_server: tuple[str, int]) -> None:
    argv = iorthand_cmd("bench", "linkemu", "--listen", "127.0.0.1:0", "--connect", f"{echo_server[0]}:{echo_server[1]}",
                        "--delay-ms", "25", "--max-seconds", "30")
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert proc.stdout is not None
        ready = proc.stdout.readline()
        assert ready.startswith("linkemu ready 127.0.0.1:"), ready
        port = int(ready.split()[2].rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
            t0 = time.monotonic()
            s.sendall(b"ping")
            assert _recv_exactly(s, 4) == b"ping"
            assert time.monotonic() - t0 >= 0.050  # 25 ms each way
        proc.terminate()
        assert proc.wait(10) == 0
    finally:
        proc.kill()
        proc.wait(10)


def test_datagram_loss_is_per_packet_and_datagrams_never_stall() -> None:
    line = DelayLine(LinkProfile(10.0, 0.0, stall_prob=0.05, stall_ms=200.0), random.Random(7))
    small = sum(line.lost(100) for _ in range(20_000)) / 20_000
    big = sum(line.lost(6 * PACKET_PAYLOAD) for _ in range(20_000)) / 20_000  # six packets
    assert small == pytest.approx(0.05, abs=0.01)
    assert big == pytest.approx(1 - 0.95 ** 6, abs=0.015)
    # A datagram that gets through is delayed by the link only: a loss holds nothing back.
    assert {line.sample_delay(stalls=False) for _ in range(1000)} == {0.010}
    assert not DelayLine(LinkProfile(10.0), random.Random(1)).lost(60_000)


def test_datagram_relay_delays_both_ways(udp_echo: tuple[str, int]) -> None:
    with DatagramRelay(("127.0.0.1", 0), udp_echo, LinkProfile(25.0)) as relay, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(5)
        t0 = time.monotonic()
        s.sendto(b"ping", ("127.0.0.1", relay.port))
        data, _ = s.recvfrom(100)
        rtt = time.monotonic() - t0
    assert data == b"ping"
    assert 0.050 <= rtt < 2.0  # 25 ms each way


def test_datagram_relay_loses_some_keeps_order_and_holds_none_back(udp_echo: tuple[str, int]) -> None:
    with DatagramRelay(("127.0.0.1", 0), udp_echo, LinkProfile(5.0, 3.0, 0.1, 200.0), seed=3) as relay, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(1.0)
        sent: dict[int, float] = {}
        got: list[tuple[int, float]] = []

        def receive() -> None:  # stamps arrivals while the sender runs
            with contextlib.suppress(TimeoutError):
                while True:
                    data, _ = s.recvfrom(100)
                    got.append((int.from_bytes(data, "big"), time.monotonic()))

        reader = threading.Thread(target=receive)
        reader.start()
        for i in range(300):
            sent[i] = time.monotonic()
            s.sendto(i.to_bytes(4, "big"), ("127.0.0.1", relay.port))
            time.sleep(0.002)
        reader.join(10)
        lost = relay.datagrams_lost
    seqs = [i for i, _ in got]
    assert seqs == sorted(seqs)  # in order, like the TCP relay
    # 10 % per direction: about 19 % of the round trips lost, and every one the relay counted.
    assert 0.08 < 1 - len(got) / 300 < 0.32
    assert lost == 300 - len(got)
    # No 200 ms stall behind a loss: every echo came back within the delay and jitter (plus this VM's scheduling).
    assert max(t - sent[i] for i, t in got) < 0.1


def test_datagram_blackout_loses_everything(udp_echo: tuple[str, int]) -> None:
    with DatagramRelay(("127.0.0.1", 0), udp_echo, LinkProfile()) as relay, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(0.3)
        relay.blackout(True)
        s.sendto(b"a", ("127.0.0.1", relay.port))
        with pytest.raises(TimeoutError):
            s.recvfrom(10)
        relay.blackout(False)
        s.settimeout(5)
        s.sendto(b"b", ("127.0.0.1", relay.port))
        assert s.recvfrom(10)[0] == b"b"  # "a" never arrives: nothing was kept for later
