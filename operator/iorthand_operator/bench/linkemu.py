"""A userspace link emulator: a TCP relay that holds each chunk for a profile's delay while keeping order, and
a UDP relay that does the same to datagrams and loses some.

This machine's kernel has no ``netem``, and Zenoh and MQTT links are TCP, so delay and jitter are added at the
stream level: every chunk read from one side is released to the other side at
``max(arrival + delay, release time of the previous chunk)``. Taking the maximum keeps the byte stream in order
(TCP never reorders what the application sees), so jitter shows up the way it does on a real TCP link: late
chunks hold back the ones behind them. A "stall" (probability per chunk) adds a long extra delay to one chunk —
what a lost segment and its retransmission look like to a TCP receiver (head-of-line blocking on 4G).

The datagram relay (``--udp``) carries Zenoh's UDP links (best-effort traffic: the video). It applies the same
delay and jitter, in order, and the profile's stall probability as the loss of one packet: a datagram of n
packets of the link's MTU is lost with probability 1 - (1 - p)^n, as on the radio link whose lost segments TCP
retransmits in the stall. Nothing resends a lost datagram; the datagrams behind it are not held back.

A blackout holds every chunk until it ends (a TCP connection over a dead radio keeps its bytes and delivers
them late, in a burst); in namespaces the WAN benchmark blacks out with nftables drop rules instead.

Run alone: ``python -m iorthand_operator.bench.linkemu --listen 127.0.0.1:0 --connect 127.0.0.1:7447
--delay-ms 15 --jitter-ms 5``; SIGUSR1 starts a blackout, SIGUSR2 ends it, SIGTERM stops.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import random
import signal
import socket
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass

log = logging.getLogger("iorthand.bench.linkemu")

_CHUNK = 65536
# Payload bytes of one IP packet of a datagram on an Ethernet-sized link (1500 - 20 IP - 8 UDP): a larger datagram
# travels as fragments and is lost if any of them is.
PACKET_PAYLOAD = 1472


@dataclass(frozen=True)
class LinkProfile:
    """One direction of a link: one-way ``delay_ms`` ± ``jitter_ms`` (uniform), and with probability
    ``stall_prob`` per chunk an extra ``stall_ms`` (a retransmission stall)."""

    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    stall_prob: float = 0.0
    stall_ms: float = 0.0

    def __post_init__(self) -> None:
        if self.delay_ms < 0 or self.jitter_ms < 0 or self.stall_ms < 0:
            raise ValueError("delay, jitter and stall must not be negative")
        if not 0.0 <= self.stall_prob <= 1.0:
            raise ValueError("stall_prob must be within 0..1")

    @property
    def is_zero(self) -> bool:
        return self.delay_ms == 0 and self.jitter_ms == 0 and (self.stall_prob == 0 or self.stall_ms == 0)


class DelayLine:
    """Release times for successive chunks of one direction: delayed, jittered, never out of order."""

    def __init__(self, profile: LinkProfile, rng: random.Random) -> None:
        self.profile = profile
        self._rng = rng
        self._last_release = -float("inf")

    def sample_delay(self, stalls: bool = True) -> float:
        """One chunk's own delay in seconds (before the in-order constraint); without ``stalls`` (a datagram: a
        lost one is gone, see :meth:`lost`) delay and jitter only."""
        p = self.profile
        d = p.delay_ms
        if p.jitter_ms:
            d += self._rng.uniform(-p.jitter_ms, p.jitter_ms)
        if stalls and p.stall_prob and self._rng.random() < p.stall_prob:
            d += p.stall_ms
        return max(0.0, d) / 1000.0

    def release_time(self, arrival: float, stalls: bool = True) -> float:
        release = max(arrival + self.sample_delay(stalls), self._last_release)
        self._last_release = release
        return release

    def lost(self, size: int) -> bool:
        """Whether a datagram of ``size`` bytes is lost: each of its packets with the stall probability."""
        p = self.profile.stall_prob
        if not p:
            return False
        packets = max(1, -(-size // PACKET_PAYLOAD))
        return self._rng.random() < 1.0 - (1.0 - p) ** packets


class _Pipe:
    """One direction of one relayed connection: a reader thread stamps chunks, a writer thread releases them."""

    def __init__(self, name: str, src: socket.socket, dst: socket.socket, line: DelayLine, emu: LinkEmulator) -> None:
        self.src, self.dst, self.line, self.emu = src, dst, line, emu
        self._queue: deque[tuple[float, bytes | None]] = deque()
        self._cond = threading.Condition()
        self.done = threading.Event()
        self._threads = [
            threading.Thread(target=self._read, name=f"{name}-rd", daemon=True),
            threading.Thread(target=self._write, name=f"{name}-wr", daemon=True),
        ]

    def start(self) -> None:
        for t in self._threads:
            t.start()

    def _read(self) -> None:
        try:
            while True:
                data = self.src.recv(_CHUNK)
                now = time.monotonic()
                if not data:
                    break
                with self._cond:
                    self._queue.append((self.line.release_time(now), data))
                    self._cond.notify()
        except OSError:
            pass
        with self._cond:
            self._queue.append((0.0, None))  # end of stream, after everything already queued
            self._cond.notify()

    def _write(self) -> None:
        try:
            while True:
                with self._cond:
                    while not self._queue:
                        self._cond.wait()
                    release, data = self._queue.popleft()
                if data is None:
                    with contextlib.suppress(OSError):
                        self.dst.shutdown(socket.SHUT_WR)
                    break
                while True:
                    wait = release - time.monotonic()
                    if self.emu.blacked_out.is_set():
                        self.emu.resumed.wait(0.05)  # hold everything while the link is down
                        continue
                    if wait <= 0:
                        break
                    time.sleep(min(wait, 0.05))
                self.dst.sendall(data)
                self.emu.count(len(data))
        except OSError:
            pass
        finally:
            self.done.set()


class LinkEmulator:
    """Relays every connection made to ``listen`` to ``target``, delaying each direction by its profile."""

    def __init__(
        self,
        listen: tuple[str, int],
        target: tuple[str, int],
        up: LinkProfile,
        down: LinkProfile | None = None,
        seed: int = 1,
    ) -> None:
        self.target = target
        self.up = up
        self.down = down if down is not None else up
        self._rng = random.Random(seed)
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._server.bind(listen)
        self._server.listen(64)
        self.address: tuple[str, int] = self._server.getsockname()
        self.blacked_out = threading.Event()
        self.resumed = threading.Event()
        self.resumed.set()
        self._closed = threading.Event()
        self._lock = threading.Lock()
        self._sockets: list[socket.socket] = []
        self.connections = 0
        self.bytes_relayed = 0
        self._accept_thread = threading.Thread(target=self._accept, name="linkemu-accept", daemon=True)

    @property
    def port(self) -> int:
        return self.address[1]

    def start(self) -> LinkEmulator:
        self._accept_thread.start()
        return self

    def count(self, n: int) -> None:
        with self._lock:
            self.bytes_relayed += n

    def blackout(self, on: bool) -> None:
        """Hold (on) or release (off) all traffic in both directions of every connection."""
        if on:
            self.resumed.clear()
            self.blacked_out.set()
        else:
            self.blacked_out.clear()
            self.resumed.set()

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                client, _ = self._server.accept()
            except OSError:
                return
            try:
                upstream = socket.create_connection(self.target, timeout=5.0)
                upstream.settimeout(None)
            except OSError as exc:
                log.warning("cannot reach %s:%d: %s", *self.target, exc)
                client.close()
                continue
            for s in (client, upstream):
                # The emulator adds delay on purpose; Nagle would add its own, uncontrolled.
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self.connections += 1
                n = self.connections
                self._sockets += [client, upstream]
                # Each direction gets its own random stream, derived from the seed: runs are repeatable.
                lines = (DelayLine(self.up, random.Random(self._rng.random())), DelayLine(self.down, random.Random(self._rng.random())))
            for name, src, dst, line in ((f"c{n}-up", client, upstream, lines[0]), (f"c{n}-down", upstream, client, lines[1])):
                _Pipe(name, src, dst, line, self).start()

    def close(self) -> None:
        self._closed.set()
        self.blackout(False)
        with contextlib.suppress(OSError):
            # close() alone does not wake a thread blocked in accept() on Linux; shutdown() does, and the
            # port stops accepting at once.
            self._server.shutdown(socket.SHUT_RDWR)
        with contextlib.suppress(OSError):
            self._server.close()
        if self._accept_thread.is_alive():
            self._accept_thread.join(timeout=2.0)
        with self._lock:
            for s in self._sockets:
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)
                s.close()
            self._sockets.clear()

    def __enter__(self) -> LinkEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


class _DatagramDirection:
    """One direction of the datagram relay: datagrams queued with their release time, sent in order by one thread."""

    def __init__(self, name: str, line: DelayLine, relay: DatagramRelay) -> None:
        self.line, self.relay = line, relay
        self._queue: deque[tuple[float, bytes, socket.socket, tuple[str, int] | None]] = deque()
        self._cond = threading.Condition()
        self.thread = threading.Thread(target=self._write, name=f"{name}-wr", daemon=True)

    def push(self, data: bytes, out: socket.socket, to: tuple[str, int] | None) -> None:
        now = time.monotonic()
        with self._cond:
            if self.relay.blacked_out.is_set() or self.line.lost(len(data)):
                self.relay.count_lost()
                return
            self._queue.append((self.line.release_time(now, stalls=False), data, out, to))
            self._cond.notify()

    def _write(self) -> None:
        while not self.relay.closed.is_set():
            with self._cond:
                while not self._queue and not self.relay.closed.is_set():
                    self._cond.wait(0.2)
                if not self._queue:
                    continue
                release, data, out, to = self._queue.popleft()
            wait = release - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            with contextlib.suppress(OSError):  # a peer gone, a full buffer: a datagram lost, as on a link
                if to is None:
                    out.send(data)
                else:
                    out.sendto(data, to)
                self.relay.count(len(data))


class DatagramRelay:
    """Relays the datagrams sent to ``listen`` to ``target`` and the answers back, each direction delayed and
    thinned by its profile. Each sender address gets its own socket towards the target (its own flow there)."""

    def __init__(self, listen: tuple[str, int], target: tuple[str, int], up: LinkProfile,
                 down: LinkProfile | None = None, seed: int = 1) -> None:
        self.target = target
        rng = random.Random(seed)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(listen)
        self.address: tuple[str, int] = self._sock.getsockname()
        self.blacked_out = threading.Event()
        self.closed = threading.Event()
        self._lock = threading.Lock()
        self._flows: dict[tuple[str, int], socket.socket] = {}
        self.datagrams = self.bytes_relayed = self.datagrams_lost = 0
        self._up = _DatagramDirection("udp-up", DelayLine(up, random.Random(rng.random())), self)
        self._down = _DatagramDirection("udp-down", DelayLine(down if down is not None else up,
                                                              random.Random(rng.random())), self)
        self._threads = [threading.Thread(target=self._read_clients, name="udp-rd", daemon=True),
                         self._up.thread, self._down.thread]

    @property
    def port(self) -> int:
        return self.address[1]

    def start(self) -> DatagramRelay:
        for t in self._threads:
            t.start()
        return self

    def count(self, n: int) -> None:
        with self._lock:
            self.datagrams += 1
            self.bytes_relayed += n

    def count_lost(self) -> None:
        with self._lock:
            self.datagrams_lost += 1

    def blackout(self, on: bool) -> None:
        """Lose (on) or carry again (off) every datagram: a dead radio keeps no datagrams for later."""
        (self.blacked_out.set if on else self.blacked_out.clear)()

    def _flow(self, client: tuple[str, int]) -> socket.socket:
        with self._lock:
            flow = self._flows.get(client)
            if flow is None:
                flow = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                flow.connect(self.target)
                self._flows[client] = flow
                threading.Thread(target=self._read_target, args=(flow, client), name="udp-rd-target",
                                 daemon=True).start()
            return flow

    def _read_clients(self) -> None:
        while not self.closed.is_set():
            try:
                data, client = self._sock.recvfrom(_CHUNK)
            except OSError:
                return
            self._up.push(data, self._flow(client), None)

    def _read_target(self, flow: socket.socket, client: tuple[str, int]) -> None:
        while not self.closed.is_set():
            try:
                data = flow.recv(_CHUNK)
            except OSError:  # closed, or the target refused (ICMP port unreachable): keep listening until closed
                if self.closed.is_set():
                    return
                time.sleep(0.05)
                continue
            self._down.push(data, self._sock, client)

    def close(self) -> None:
        self.closed.set()
        with self._lock:
            socks = [self._sock, *self._flows.values()]
            self._flows.clear()
        for s in socks:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            s.close()
        for t in self._threads:
            if t.is_alive():
                t.join(timeout=2.0)

    def __enter__(self) -> DatagramRelay:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


def _hostport(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit() or int(port) > 65535:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT (port 0-65535), got {text!r}")
    return host, int(port)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The emulator's options, for this module's own command line and for ``iorthand bench linkemu``."""
    p.add_argument("--listen", type=_hostport, required=True, help="HOST:PORT to accept on (port 0: any free one)")
    p.add_argument("--udp", action="store_true", help="relay datagrams (a Zenoh UDP link) instead of TCP connections; "
                   "the stall probability is then the loss of each packet")
    p.add_argument("--connect", type=_hostport, required=True, help="HOST:PORT each accepted connection is relayed to")
    p.add_argument("--delay-ms", type=float, default=0.0, help="one-way delay of each direction")
    p.add_argument("--jitter-ms", type=float, default=0.0, help="± this much, uniform, order kept")
    p.add_argument("--stall-prob", type=float, default=0.0, help="probability per chunk of a retransmission stall")
    p.add_argument("--stall-ms", type=float, default=0.0, help="length of a stall")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--max-seconds", type=float, default=3600.0, help="exit after this long (a time bound)")


def run(args: argparse.Namespace) -> int:
    """Relay until SIGTERM/SIGINT or ``max_seconds``; SIGUSR1 starts a blackout, SIGUSR2 ends it."""
    prof = LinkProfile(args.delay_ms, args.jitter_ms, args.stall_prob, args.stall_ms)
    emu: LinkEmulator | DatagramRelay = (DatagramRelay if args.udp else LinkEmulator)(
        args.listen, args.connect, prof, seed=args.seed).start()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGUSR1, lambda *_: emu.blackout(True))
    signal.signal(signal.SIGUSR2, lambda *_: emu.blackout(False))
    kind = "datagrams" if args.udp else "tcp"
    print(f"linkemu ready {emu.address[0]}:{emu.port} -> {args.connect[0]}:{args.connect[1]} {prof} ({kind})", flush=True)
    stop.wait(args.max_seconds)
    emu.close()
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m iorthand_operator.bench.linkemu", description=__doc__.splitlines()[0])
    add_arguments(p)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
