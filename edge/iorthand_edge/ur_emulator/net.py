"""TCP plumbing shared by the servers: listeners that can be unbound ("link lost") or hung, and a registry
of open client sockets that fault injection can cut."""

from __future__ import annotations

import contextlib
import logging
import socket
import struct
import threading
from collections.abc import Callable

log = logging.getLogger("iorthand_edge.ur_emulator")

Handler = Callable[[socket.socket, tuple[str, int]], None]


class Registry:
    """Open client sockets, so that a link drop or shutdown can close them all at once."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._socks: set[socket.socket] = set()
        self._parked: list[socket.socket] = []  # accepted while hung, never served

    def add(self, sock: socket.socket) -> None:
        with self._lock:
            self._socks.add(sock)

    def discard(self, sock: socket.socket) -> None:
        with self._lock:
            self._socks.discard(sock)

    def park(self, sock: socket.socket) -> None:
        with self._lock:
            self._parked.append(sock)

    def close_all(self, include_parked: bool = True) -> int:
        with self._lock:
            socks = list(self._socks)
            self._socks.clear()
            if include_parked:
                socks += self._parked
                self._parked.clear()
        for s in socks:
            close_quietly(s)
        return len(socks)

    def release_parked(self) -> None:
        with self._lock:
            parked, self._parked = self._parked, []
        for s in parked:
            close_quietly(s)


def close_quietly(sock: socket.socket) -> None:
    # shutdown() first: it wakes a thread blocked in recv() on this socket and sends FIN at once.
    with contextlib.suppress(OSError):
        sock.shutdown(socket.SHUT_RDWR)
    with contextlib.suppress(OSError):
        sock.close()


def set_send_timeout(sock: socket.socket, seconds: float) -> None:
    """Bound blocking sends (SO_SNDTIMEO) while recv() stays blocking: a client that stops reading must not
    stall the emulator forever."""
    sec = int(seconds)
    usec = int((seconds - sec) * 1e6)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, struct.pack("ll", sec, usec))


class Listener:
    """Accept loop on ``host:port``; each client is served by ``handler`` in its own thread.

    ``is_hung()`` → accepted sockets are parked (TCP handshake completes, nothing is ever answered), which
    is what a controller whose software hangs looks like. :meth:`unbind` closes the listening socket so
    that new connections are refused (link lost) until :meth:`bind` is called again.
    """

    def __init__(self, name: str, host: str, port: int, handler: Handler, registry: Registry,
                 is_hung: Callable[[], bool]) -> None:
        self.name, self.host, self.port = name, host, port
        self._handler = handler
        self._registry = registry
        self._is_hung = is_hung
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def bind(self) -> None:
        if self._sock is not None:
            return
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # rebinding after a link drop
        s.bind((self.host, self.port))
        s.listen(16)
        s.settimeout(0.1)  # accept() polls so that unbind()/stop() never wait on a blocked accept
        self.port = s.getsockname()[1]
        self._sock = s
        self._stop.clear()
        self._thread = threading.Thread(target=self._accept_loop, args=(s,), name=f"ur-emu-{self.name}",
                                        daemon=True)
        self._thread.start()

    def unbind(self) -> None:
        s, self._sock = self._sock, None
        self._stop.set()
        if s is not None:
            # shutdown() wakes a blocked accept() at once (EINVAL on Linux): a link drop must take effect now,
            # not after the accept poll (joining four listeners one poll each made drop_link take ~150 ms).
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._thread = None
        if s is not None:
            s.close()

    def _accept_loop(self, s: socket.socket) -> None:
        while not self._stop.is_set():
            try:
                conn, addr = s.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.settimeout(None)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if self._is_hung():
                log.info("%s: connection from %s parked (hung)", self.name, addr)
                self._registry.park(conn)
                continue
            self._registry.add(conn)
            threading.Thread(target=self._serve, args=(conn, addr), name=f"ur-emu-{self.name}-client",
                             daemon=True).start()

    def _serve(self, conn: socket.socket, addr: tuple[str, int]) -> None:
        try:
            self._handler(conn, addr)
        except (ConnectionError, OSError) as exc:
            log.debug("%s: client %s gone: %s", self.name, addr, exc)
        except Exception:
            log.exception("%s: handler for %s failed", self.name, addr)
        finally:
            self._registry.discard(conn)
            close_quietly(conn)
