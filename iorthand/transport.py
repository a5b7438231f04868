"""Zenoh sessions and QoS profiles.

:func:`open_session` builds a session for ``router``, ``client`` or ``peer`` mode from a :class:`ZenohConfig`
(endpoints, lease, scouting off by default) and retries with back-off while no router answers. The QoS of
every key is a column of the table of channels (:mod:`iorthand.channels`), looked up in :data:`QOS_BY_KEY`;
:func:`publisher` applies it.

Zenoh's Python callbacks share one receive path per session: a slow callback stalls every subscriber of the
session. So callbacks here only hand data over (:class:`Inbox`), and work happens in named worker threads.
"""

from __future__ import annotations

import json
import logging
import queue
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from iorthand import channels, keys
from iorthand.config import ConfigError, setting
from iorthand.process import REALTIME_PRIORITY, name_thread, raise_priority
from iorthand.protocol import MAX_PAYLOAD, MAX_VIDEO_PAYLOAD, RejectCounter

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class QosProfile:
    priority: zenoh.Priority
    congestion: zenoh.CongestionControl
    express: bool = False
    best_effort: bool = False  # see VIDEO
    # How routers forward a BLOCK message to each subscriber (Zenoh's qos.network names; see forwarding_rules):
    # "" as it was published. A router forwards with the publisher's congestion control, so with BLOCK the
    # thread reading the publisher's link waits for room in the slowest subscriber's queue (up to 5 s).
    forwarded: str = ""

    @property
    def reliability(self) -> zenoh.Reliability:
        return zenoh.Reliability.BEST_EFFORT if self.best_effort else zenoh.Reliability.RELIABLE


COMMAND = QosProfile(zenoh.Priority.REAL_TIME, zenoh.CongestionControl.DROP, express=True)
# Forwarded as published (BLOCK), although a subscriber of commands that stops reading then holds up the
# operator's link at the router: Zenoh's "block_first" keeps one message of a priority in flight per link and
# drops the next if it waits more than 1 ms, so on a router short of CPU a stop that follows a servo set-point
# could be dropped. A stop is never dropped; the edge's deadman stops the robot if the commands stall.
CONTROL = QosProfile(zenoh.Priority.REAL_TIME, zenoh.CongestionControl.BLOCK, express=True)
STATE = QosProfile(zenoh.Priority.INTERACTIVE_HIGH, zenoh.CongestionControl.DROP)
# BLOCK at the edge (a status is never dropped from its own queue); dropped when forwarded to a subscriber whose
# link is full: the edge sends the status again at its rate, so that subscriber gets the newest when it reads again.
SAFETY = QosProfile(zenoh.Priority.INTERACTIVE_HIGH, zenoh.CongestionControl.BLOCK, forwarded="drop")
DATA = QosProfile(zenoh.Priority.DATA, zenoh.CongestionControl.DROP)
# BLOCK: a full uplink makes the edge's put wait (it then skips frames at the source and lowers the H.264 bitrate)
# instead of dropping frames in the sender's queue, which spoils an H.264 stream until its next keyframe.
# BEST_EFFORT: where a datagram link exists (a QUIC link with mixed_rel=1, or a UDP link beside TCP between
# routers: see DATAGRAM_LINK_META), Zenoh sends the frames as datagrams, so a packet lost on a radio link costs the
# frames up to the next keyframe (the viewer asks for one) instead of holding every frame behind it for a
# retransmission (4G, `iorthand bench wan`: p99 frame delay 205 ms over the link's own on TCP). On a TCP or TLS
# link best effort changes nothing: TCP delivers every byte.
VIDEO = QosProfile(zenoh.Priority.DATA_LOW, zenoh.CongestionControl.BLOCK, best_effort=True)

# What each QoS profile named by the table of channels is on the wire.
QOS_PROFILES: dict[channels.Qos, QosProfile] = {
    channels.Qos.COMMAND: COMMAND,
    channels.Qos.CONTROL: CONTROL,
    channels.Qos.STATE: STATE,
    channels.Qos.SAFETY: SAFETY,
    channels.Qos.DATA: DATA,
    channels.Qos.VIDEO: VIDEO,
}


def qos_by_key(table: Iterable[channels.Channel] = channels.TABLE) -> dict[str, QosProfile]:
    """The QoS of every stream of the table of channels, by key suffix."""
    return {c.suffix: QOS_PROFILES[c.qos] for c in table if c.qos is not None}


QOS_BY_KEY: dict[str, QosProfile] = qos_by_key()


@dataclass
class TlsConfig:
    """Zenoh TLS settings (paths to PEM files). ``mtls`` makes both sides present a certificate: a client must
    set it too, or Zenoh sends no certificate and an mTLS router refuses the link.

    ``verify_name`` checks that the router's certificate names the host dialled. Keep it on: with a private
    CA, skipping it lets any certificate of that CA pose as the router (Zenoh warns "Skipping name
    verification"). ``iorthand certs issue router --host NAME`` puts the names in the certificate."""

    root_ca: Path | None = setting(None, help="the deployment's CA certificate (ca.pem)")
    certificate: Path | None = setting(None, help="this role's certificate (e.g. edge-<robot>.pem)")
    private_key: Path | None = setting(None, help="its private key (mode 0600)")
    mtls: bool = True
    verify_name: bool = True


@dataclass
class ZenohConfig:
    mode: str = setting("client", choices=("client", "peer", "router"))
    connect: list[str] = setting(default_factory=list)
    listen: list[str] = setting(default_factory=list)
    lease_ms: int = setting(2000, lo=500, hi=60_000, help="transport lease: a silent link is dropped after it")
    multicast_scouting: bool = False
    shared_memory: bool = setting(True, help="off to model a WAN between sites on one host")
    connect_retry_s: float = setting(30.0, lo=0.0, help="how long open_session retries before giving up")
    tls: TlsConfig | None = None
    username: str = ""
    password_file: Path | None = None
    extra: dict[str, Any] = setting(default_factory=dict, help="raw Zenoh config entries, key path → value")

    def check(self) -> None:
        if self.mode == "client" and not self.connect:
            raise ValueError("connect: a client needs at least one router endpoint, e.g. tcp/127.0.0.1:7447")
        for ep in [*self.connect, *self.listen]:
            check_endpoint(ep)
            if ep.startswith("udp/"):
                # A session whose only link is UDP would send its commands and state as datagrams too: lost
                # without a word, and in clear.
                raise ValueError(f"endpoint {ep!r}: UDP carries nothing reliably and nothing encrypted; use tcp/ or "
                                 f"tls/, or quic/HOST:PORT?mixed_rel=1 for datagrams (iorthand router --datagrams "
                                 f"adds UDP links between routers)")
            if ep.startswith(("tls/", "quic/")) and self.tls is None:
                raise ValueError(f"endpoint {ep!r} needs a tls section (root_ca, certificate, private_key)")
        if self.username and self.password_file is None:
            raise ValueError(f"username {self.username!r} needs a password_file (a file with the password, mode 0600)")


def check_endpoint(endpoint: str) -> None:
    """A Zenoh endpoint PROTOCOL/HOST:PORT (metadata after ``?`` or ``#`` allowed); ValueError naming it if not."""
    form = f"endpoint {endpoint!r} must look like tcp/HOST:PORT or tls/HOST:PORT"
    protocol, address = _endpoint_parts(endpoint)
    if not protocol or not address:
        raise ValueError(form)
    if protocol in ("tcp", "tls", "udp", "quic", "ws"):
        host, _, port = address.rpartition(":")
        if not host or not port.isdigit() or int(port) > 65535:
            raise ValueError(f"{form}: {port!r} is not a port number (0-65535)" if host else form)


def _endpoint_parts(endpoint: str) -> tuple[str, str]:
    """PROTOCOL and ADDRESS of PROTOCOL/ADDRESS?METADATA#CONFIG."""
    protocol, _, rest = endpoint.partition("/")
    return protocol, re.split(r"[?#]", rest, maxsplit=1)[0]


def zenoh_config(cfg: ZenohConfig, entries: dict[str, Any] | None = None) -> zenoh.Config:
    """The zenoh.Config for our settings (kept as a plain dict first, so it can be logged and tested)."""
    zc = zenoh.Config()
    for path, value in (zenoh_entries(cfg) if entries is None else entries).items():
        zc.insert_json5(path, json.dumps(value))
    return zc


# The largest message a client or peer session accepts from the network (Zenoh's default: 1 GiB). Zenoh drops
# a larger one while it reassembles the fragments, so it is never held whole, and the link and everything else
# on it carry on. None of our messages is larger than a video frame; the headroom is the key and Zenoh's
# headers. Only what a session receives is limited: it still sends messages of any size. A role that receives
# commands alone sets a smaller one in ``extra`` (the edge: iorthand_edge.config.EDGE_RX_MAX_MESSAGE).
RX_MAX_MESSAGE_KEY = "transport/link/rx/max_message_size"
RX_MAX_MESSAGE = MAX_VIDEO_PAYLOAD + MAX_PAYLOAD


def zenoh_entries(cfg: ZenohConfig) -> dict[str, Any]:
    entries: dict[str, Any] = {
        "mode": cfg.mode,
        "scouting/multicast/enabled": cfg.multicast_scouting,
        "transport/link/tx/lease": cfg.lease_ms,
        "transport/shared_memory/enabled": cfg.shared_memory,
        **{f"{TX_QUEUE_SIZE_KEY}/{priority}": size for priority, size in TX_QUEUE_SIZE.items()},
    }
    if cfg.shared_memory:
        entries[SHM_POOL_SIZE_KEY] = SHM_POOL_SIZE
    if cfg.mode != "router":
        entries["scouting/gossip/enabled"] = False
        entries[RX_MAX_MESSAGE_KEY] = RX_MAX_MESSAGE  # a router forwards its sites' messages, whatever they are
    if cfg.connect:
        entries["connect/endpoints"] = list(cfg.connect)
    if cfg.listen:
        entries["listen/endpoints"] = list(cfg.listen)
    if cfg.tls is not None:
        tls = cfg.tls
        if tls.root_ca:
            entries["transport/link/tls/root_ca_certificate"] = str(tls.root_ca)
        # Key names checked against eclipse-zenoh 1.10.2 (Config.insert_json5 rejects unknown keys). A router
        # presents listen_*, a client connect_*; a peer does both, so it gets both.
        if cfg.mode in ("router", "peer"):
            if tls.certificate:
                entries["transport/link/tls/listen_certificate"] = str(tls.certificate)
            if tls.private_key:
                entries["transport/link/tls/listen_private_key"] = str(tls.private_key)
        if cfg.mode in ("client", "peer"):
            if tls.certificate:
                entries["transport/link/tls/connect_certificate"] = str(tls.certificate)
            if tls.private_key:
                entries["transport/link/tls/connect_private_key"] = str(tls.private_key)
        entries["transport/link/tls/enable_mtls"] = tls.mtls
        entries["transport/link/tls/verify_name_on_connect"] = tls.verify_name
        # A certificate that expires while connected ends the link rather than living on until a restart.
        entries["transport/link/tls/close_link_on_expiration"] = True
    if cfg.username:
        entries["transport/auth/usrpwd/user"] = cfg.username
        if cfg.password_file:
            # The password lives in its own 0600 file, never in the YAML (which is shared and versioned).
            entries["transport/auth/usrpwd/password"] = Path(cfg.password_file).read_text().strip()
    entries.update(cfg.extra)
    return entries


class ConnectError(RuntimeError):
    """No session could be opened. ``diagnosis`` (an :class:`iorthand.security.diagnose.Diagnosis`) says why."""

    def __init__(self, message: str, diagnosis: Any = None) -> None:
        super().__init__(message)
        self.diagnosis = diagnosis


# Back-off of open_session: 0.1 s doubling to this cap. Low enough that an edge started before its router
# connects well within 2 s of the router appearing (plug-and-play); a refused connect costs ~1 ms.
MAX_RETRY_DELAY = 0.5
_RELOG_EVERY = 30.0  # s between "still no router" lines: a Pi waiting all night must not fill its SD card


class _Diagnoser(threading.Thread):
    """Runs the diagnosis of a failed connection in the background, so retries are not delayed by it."""

    def __init__(self, cfg: ZenohConfig, entries: dict[str, Any]) -> None:
        super().__init__(name="zenoh-diagnose", daemon=True)
        self._cfg, self._entries = cfg, entries
        self.result: Any = None

    def run(self) -> None:
        from iorthand.security.diagnose import diagnose

        try:
            self.result = diagnose(self._cfg, self._entries)
        except Exception as exc:  # a diagnosis must never take the caller down
            log.debug("diagnosis failed: %s", exc)
            return
        log.warning("zenoh: %s", self.result.message())


def open_session(cfg: ZenohConfig, stop: threading.Event | None = None) -> zenoh.Session:
    """Open a Zenoh session, retrying with back-off (0.1 s doubling to 0.5 s) for ``connect_retry_s``.

    zenoh.open() in client mode raises at once when no router answers; an edge that starts before its router
    must keep trying (plug-and-play). ``stop`` aborts the retries. Zenoh only says "Unable to connect to any
    of [...]": at the first failure a background diagnosis (pre-checks of the certificate files, then one
    probe connection with Zenoh's log at warn in a child process) logs which endpoint, which certificate and
    the likely cause, and the final :class:`ConnectError` carries it.
    """
    try:
        cfg.check()  # settings given on a command line did not pass through the YAML loader's check
    except ValueError as exc:
        raise ConfigError("settings", "zenoh", str(exc)) from None
    try:
        entries = zenoh_entries(cfg)
    except OSError as exc:
        raise ConnectError(f"cannot read {exc.filename}: {exc.strerror}") from None
    zc = zenoh_config(cfg, entries)
    deadline = time.monotonic() + cfg.connect_retry_s
    delay = 0.1
    attempt = 0
    diagnoser: _Diagnoser | None = None
    last_log = time.monotonic()
    while True:
        attempt += 1
        try:
            session = zenoh.open(zc)
            if attempt > 1:
                log.info("connected to %s after %d attempts", ", ".join(cfg.connect), attempt)
            if cfg.mode == "client":
                _say_router_links(session, ", ".join(cfg.connect))
            return session
        except zenoh.ZError as exc:
            if diagnoser is None and cfg.mode == "client":
                diagnoser = _Diagnoser(cfg, entries)
                diagnoser.start()
                log.warning("no router at %s yet (%s); retrying", ", ".join(cfg.connect), str(exc).split(" at ", 1)[0])
            if time.monotonic() >= deadline or (stop is not None and stop.is_set()):
                diag = None
                if diagnoser is not None:
                    diagnoser.join(timeout=20.0)
                    diag = diagnoser.result
                why = diag.message() if diag is not None else f"cannot reach a Zenoh router at {', '.join(cfg.connect)}: {exc}"
                raise ConnectError(f"{why} (gave up after {attempt} attempts)", diag) from None
            if time.monotonic() - last_log > _RELOG_EVERY:
                last_log = time.monotonic()
                log.warning("still no router at %s (attempt %d)", ", ".join(cfg.connect), attempt)
            if stop is not None:
                stop.wait(delay)
            else:
                time.sleep(delay)
            delay = min(delay * 2, MAX_RETRY_DELAY)


def _say_router_links(session: zenoh.Session, where: str) -> None:
    """Log when the link to the router drops and when it is back. Zenoh reconnects by itself and says nothing:
    an edge whose router went away looked alive in its log (journalctl on the Pi) while nothing reached it. The
    listener lives as long as the session."""

    def on_event(event: zenoh.TransportEvent) -> None:
        if event.transport.whatami != zenoh.WhatAmI.ROUTER:
            return
        if event.kind == zenoh.SampleKind.DELETE:
            log.warning("lost the link to the router at %s: nothing goes out or comes in until it is back; "
                        "reconnecting", where)
        else:
            log.info("linked to the router at %s again", where)

    session.info.declare_transport_events_listener(on_event, history=False)


def publisher(session: zenoh.Session, key: str, qos: QosProfile | None = None) -> zenoh.Publisher:
    """Declare a publisher with the QoS of its key (looked up from the key's suffix unless given)."""
    if qos is None:
        _, suffix = keys.split_key(key)
        qos = QOS_BY_KEY[suffix]
    return session.declare_publisher(
        key, priority=qos.priority, congestion_control=qos.congestion, express=qos.express, reliability=qos.reliability
    )


_CLOSED = object()  # what close() hands a waiting worker


class Inbox:
    """A bounded hand-over from a Zenoh callback to the one worker thread that consumes it.

    ``keep="newest"`` drops the oldest items when full (streams: only the latest matters); ``keep="oldest"``
    refuses new items when full (nothing already queued is lost); ``keep="newest_per_key"`` holds one item per
    key (an item's first element), the newest, and drops the oldest key's when ``maxlen`` keys wait (set-point
    commands: a flood on one key replaces its own, never another key's). Full means ``maxlen`` items, or, with
    ``max_bytes``, that many payload bytes (as given to :meth:`put`): a count alone lets a queue of video
    frames grow to gigabytes while a writer stalls. Dropped items are counted, and so are items refused before
    they were queued (:meth:`refuse`: too large to take at all), with the last reason.

    ``reserve`` (with ``keep="oldest"``): room for that many items put ``ahead`` beyond ``maxlen``; they are taken
    before the others. What the owner of the robot asks must not wait behind, or be refused for, a queue that
    others filled.

    A worker that waits for an item sleeps in a C-level ``SimpleQueue.get``, and :meth:`put` hands it the item
    there directly; items that arrive while it works wait in the bounded queue. This hand-over is on the command
    path: a ``Condition`` (a waiter list and a new lock per wait, in Python) made each wake-up about 10 µs slower
    on the project's VM (``benchmarks/README.md``).
    """

    def __init__(self, maxlen: int = 256, keep: str = "newest", max_bytes: int | None = None, reserve: int = 0) -> None:
        if keep not in ("newest", "oldest", "newest_per_key"):
            raise ValueError("keep must be 'newest', 'oldest' or 'newest_per_key'")
        if reserve and keep != "oldest":
            raise ValueError("a reserve is for keep='oldest' (the others never refuse an item)")
        self.reserve = reserve
        self._ahead = 0  # items put ahead, at the front of _items
        self._items: deque[tuple[Any, int]] = deque()
        self._maxlen = maxlen
        self._max_bytes = max_bytes
        self._keep = keep
        self._lock = threading.Lock()
        self._handover: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._waiting = False  # the worker waits on _handover, the queue empty: the next put goes there
        self.nbytes = 0
        self.dropped = 0
        self.refused = 0
        self.last_refusal = ""
        self.closed = False

    def refuse(self, reason: str) -> None:
        """Count an item that was refused before it reached the queue, and why."""
        with self._lock:
            self.refused += 1
            self.last_refusal = reason

    def _full(self, nbytes: int) -> bool:
        if len(self._items) - self._ahead >= self._maxlen:
            return True
        # An empty inbox takes any one item, however large: nothing can be stuck outside forever.
        return self._max_bytes is not None and bool(self._items) and self.nbytes + nbytes > self._max_bytes

    def put(self, item: Any, nbytes: int = 0, ahead: bool = False) -> bool:
        """Queue ``item``; False when a full ``keep="oldest"`` inbox refused it (counted in ``dropped``).
        ``ahead``: before every item not put ahead, in the reserve while it has room."""
        with self._lock:
            if self._waiting:  # (the queue is empty) straight to the waiting worker, under the lock: see get
                self._waiting = False
                self._handover.put(item)
                return True
            if ahead and self._ahead < self.reserve:
                self._items.insert(self._ahead, (item, nbytes))
                self._ahead += 1
                self.nbytes += nbytes
                return True
            if self._full(nbytes) and self._keep == "oldest":
                self.dropped += 1
                return False
            if self._keep == "newest_per_key":
                for i, (queued, queued_bytes) in enumerate(self._items):
                    if queued[0] == item[0]:
                        del self._items[i]
                        self.nbytes -= queued_bytes
                        self.dropped += 1
                        break
            while self._items and self._full(nbytes):
                self._pop()
                self.dropped += 1
            self._items.append((item, nbytes))
            self.nbytes += nbytes
            return True

    def _pop(self) -> Any:
        item, nbytes = self._items.popleft()
        self.nbytes -= nbytes
        self._ahead = max(0, self._ahead - 1)
        return item

    def get(self, timeout: float | None = None) -> Any | None:
        """The next item, or None after ``timeout`` or once closed and empty."""
        with self._lock:
            if self._items:
                return self._pop()
            if self.closed or (timeout is not None and timeout <= 0):
                return None
            self._waiting = True
        try:
            item = self._handover.get(timeout=timeout)
        except queue.Empty:
            with self._lock:
                if self._waiting:  # nothing came
                    self._waiting = False
                    return None
                # A put (or close) handed something over as the wait ended: it is there already (put under the
                # lock), unless a second worker, which this class is not for, took it.
                try:
                    item = self._handover.get_nowait()
                except queue.Empty:
                    return self._pop() if self._items else None
        return None if item is _CLOSED else item

    def drain(self) -> list[Any]:
        with self._lock:
            items = [item for item, _ in self._items]
            self._items.clear()
            self.nbytes = 0
            self._ahead = 0
            return items

    def close(self) -> None:
        with self._lock:
            self.closed = True
            if self._waiting:
                self._waiting = False
                self._handover.put(_CLOSED)

    def __len__(self) -> int:
        return len(self._items)


def subscribe(session: zenoh.Session, key: str, inbox: Inbox, max_payload: int = MAX_PAYLOAD,
              rejects: RejectCounter | None = None, monotonic: bool = False) -> zenoh.Subscriber:
    """Subscribe ``key``; the callback only queues ``(key, payload bytes, receive time ns)``, with the payload's
    size for the inbox's ``max_bytes``; ``monotonic``: also the receive time on the monotonic clock (s), for a
    consumer that times from it (a wall clock step between receipt and handling would move the receipt).

    A payload larger than ``max_payload`` (a command's limit by default) is refused in the callback, before it
    is copied out of Zenoh's buffers, with a reason that names its size: counted by the inbox
    (:meth:`Inbox.refuse`) and in ``rejects``. Copied first, each one is a Python object of its size that the
    decoder refuses anyway, and a queue of them holds its maxlen times that size."""

    def on_sample(sample: zenoh.Sample) -> None:
        key, size = str(sample.key_expr), len(sample.payload)
        if size > max_payload:
            reason = f"payload of {size} bytes exceeds the limit of {max_payload} bytes"
            inbox.refuse(reason)
            if rejects is not None:
                rejects.add(key, reason)
            return
        item = (key, sample.payload.to_bytes(), time.time_ns(), time.monotonic()) if monotonic else \
            (key, sample.payload.to_bytes(), time.time_ns())
        if not inbox.put(item, size) and rejects is not None:
            rejects.add(key, f"dropped: the inbox is full ({len(inbox)} waiting)")

    return session.declare_subscriber(key, on_sample)


class Worker(threading.Thread):
    """A named daemon thread that runs ``target(stop_event)``; logs and records a crash instead of hiding it.
    The kernel shows its name too (:func:`~iorthand.process.name_thread`). ``realtime``: ask for SCHED_FIFO (see
    :func:`raise_priority`)."""

    def __init__(self, name: str, target: Callable[[threading.Event], None], stop: threading.Event,
                 realtime: bool = False) -> None:
        super().__init__(name=name, daemon=True)
        self._target_fn = target
        self._stop_event = stop
        self._realtime = realtime
        self.priority = "normal"
        self.error: BaseException | None = None

    def run(self) -> None:
        name_thread(self.name)
        self.priority = raise_priority(self._realtime)
        if self._realtime and self.priority != "SCHED_FIFO":
            log.info("%s runs at %s priority (LimitRTPRIO=%d or root gives it SCHED_FIFO)",
                     self.name, self.priority, REALTIME_PRIORITY)
        try:
            self._target_fn(self._stop_event)
        except BaseException as exc:  # a dead worker must be visible, never silent
            self.error = exc
            log.exception("worker %s crashed", self.name)
            self._stop_event.set()


def query(session: zenoh.Session, key: str, payload: bytes, timeout: float = 2.0, every_answer: bool = False,
          until: Callable[[bytes], bool] | None = None) -> list[bytes]:
    """Send a query and collect the ok replies' payloads (errors are raised with their text). ``every_answer``:
    no consolidation, so that a caller expecting one answerer sees every session that answered. ``until``: stop
    waiting at the first reply it accepts (returned last), whatever else is still to come."""
    consolidation = zenoh.ConsolidationMode.NONE if every_answer else None
    replies = session.get(key, payload=payload, timeout=timeout, consolidation=consolidation)
    out: list[bytes] = []
    for reply in replies:
        if reply.ok is not None:
            out.append(reply.ok.payload.to_bytes())
            if until is not None and until(out[-1]):
                break
        else:
            raise RuntimeError(f"query {key} failed: {reply.err.payload.to_bytes().decode(errors='replace')}")
    return out


def load_router_config(path: Path) -> zenoh.Config:
    """A router's JSON5 configuration file, as Zenoh reads it (also usable by a stock zenohd)."""
    try:
        return zenoh.Config.from_file(str(path))
    except zenoh.ZError as exc:
        raise ConfigError(str(path), "", f"not a valid Zenoh configuration: {exc}") from None


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# Send queues per priority, in batches, for every session (routers, edges, operators, services). Zenoh's
# default holds 2 batches and each express command takes a whole one, so when a process's send thread stalls
# (CPU, I/O) for more than two command periods, the next commands are dropped (CongestionControl.DROP waits
# 1 ms) while the sender's own loop runs on time. Measured:
# - a router forwarding 20 robots through a mesh of three routers on 2 cores (`iorthand bench scale`): 20–29 of
#   18,020 commands lost with the default; with these, none in most runs and 1 in a run on a noisier host;
# - an operator whose send thread stalled 40–55 ms in the 2-hour soak lost 2 twists of 3 sent meanwhile (the
#   edge never saw them); tests/test_transport_stall.py stalls it 100 ms at 60 Hz: 32–37 of 180 lost with the
#   default, none with these.
# Batches are allocated lazily, only when a stall needs them. The twists held through a stall reach the edge
# together and late: it applies them in order at once (the newest sets the velocity) and drops any older than
# the supervisor's max_command_age.
TX_QUEUE_SIZE = {"real_time": 8, "interactive_high": 4}
TX_QUEUE_SIZE_KEY = "transport/link/tx/queue/size"

# The shared-memory pool of a session that sends large messages (≥ 3 KB) to processes on its own host. Zenoh's
# default is 16 MiB per sending session (a router forwarding a remote site's video makes one too); every process
# that receives from it maps it, and its RSS counts each page it has touched, up to the whole pool. Our largest
# messages are video frames of tens of KB, and receivers copy them out in the callback, so few are in flight; a
# message that does not fit goes over the link as usual. Measured with the default: a burst of 300 frames of
# 60 KB, forwarded by a router from a site without shared memory, grew the recorder's RSS by 17.7 MB at once, as
# in the 2-hour soak's simultaneous step in router, recorder and twin (tests/test_shared_memory.py).
SHM_POOL_SIZE = 4 * 1024 * 1024
SHM_POOL_SIZE_KEY = "transport/shared_memory/transport_optimization/pool_size"

# Sessions a router lets open at once before the handshake is done (Zenoh's default: 100). Anyone who reaches a
# plain tcp/ listener can hold that many connections idle until they time out (10 s): 150 from one address made
# the router refuse every new session at once (an edge back from a blip, an operator). (The tls/ listener did not
# lock out with 1 000 idle or half-begun handshakes.) 1024 cost a few MB, and a legit client still connected
# within 0.4-1.9 s with 300-600 held. deploy/router/nftables.conf caps what one address may hold (DEPLOY.md §2).
ACCEPT_PENDING = 1024
ACCEPT_PENDING_KEY = "transport/unicast/accept_pending"

ROUTER_LEASE_MS = 2000
# A router that dials another (an edge site's router → the cloud) announces a longer lease than the router it
# dials (DIALING_LEASE_EXTRA_MS more), so that after a silent outage the dialer always gives up first and the
# other side learns it from the dialer's close. With equal leases both sides expire at the same instant, and
# Zenoh 1.10 can then merge the dialer's reconnection into its own dying transport while the dialled router
# opens a new one: declarations stop flowing one way, and the edge saw neither the operator's token nor its
# subscriptions for 45 s and 84 s (2 of about 100 blackout trials of `iorthand bench wan`; none in 143 with
# these leases).
DIALING_LEASE_EXTRA_MS = 1000


def announced_lease(lease_ms: int, dials: bool) -> int:
    """The lease a router announces: the site-wide ``lease_ms``, and DIALING_LEASE_EXTRA_MS more if it dials."""
    return lease_ms + DIALING_LEASE_EXTRA_MS if dials else lease_ms


# Datagram links between routers: a router that dials another over TCP may add a UDP link to the same host and
# port, for best-effort messages only (the video, QoS VIDEO), so that a packet lost on the way costs a frame
# instead of holding back the stream behind it; the router it dials listens on UDP too and admits a second link
# per transport. Zenoh picks the link by each message's reliability: everything reliable stays on TCP. UDP is
# not encrypted: with TLS the datagram link is QUIC's (``quic/HOST:PORT?mixed_rel=1`` instead of ``tls/``).
DATAGRAM_LINK_META = "rel=0"
DATAGRAM_MAX_LINKS = 2
MAX_LINKS_KEY = "transport/unicast/max_links"


def datagram_endpoint(endpoint: str) -> str:
    """The UDP endpoint beside ``tcp/HOST:PORT`` (metadata dropped); ValueError naming why for any other."""
    protocol, hostport = _endpoint_parts(endpoint)
    if protocol == "tcp":
        return f"udp/{hostport}"
    if protocol == "tls":
        raise ValueError(f"endpoint {endpoint!r}: UDP datagrams would carry the video in clear beside TLS; "
                         f"use quic/{hostport}?mixed_rel=1 instead (QUIC's datagrams are encrypted)")
    raise ValueError(f"endpoint {endpoint!r}: a datagram link goes beside a tcp/HOST:PORT endpoint")


def with_datagram_links(listen: list[str], connect: list[str]) -> tuple[list[str], list[str]]:
    """The endpoints of a router with datagram links: a UDP listener on each TCP listener's address, and a UDP
    link (best effort only) beside each TCP link it dials."""
    return ([*listen, *(datagram_endpoint(e) for e in listen)],
            [*connect, *(f"{datagram_endpoint(e)}?{DATAGRAM_LINK_META}" for e in connect)])


def rate_limits(robots: Iterable[str] = ("*",)) -> list[dict[str, Any]]:
    """The router's ``downsampling`` section: each session's puts on a capped channel (``Channel.max_rate``) of
    each robot, at most that many a second; Zenoh drops the rest at the router's ingress. The cap is per session
    (per link), so one operator's flood costs its own messages only, never another's.

    In the deployment's router (the generated configuration, which operators connect to) and the shipped
    configs/router.json5. Not in a router that dials another: its one link carries every operator's messages,
    where a cap would let one operator's flood drop the owner's. Nor in the built-in router of :func:`router_settings`
    (tests, the demo, benchmarks: on the edge's own machine): there, with two CPU hogs, the UR driver saw more
    false faults with the caps than without (benchmarks/README.md), for a reason not found."""
    rules = [{"key_expr": f"{keys.ROOT}/{robot}/{c.suffix}/**", "freq": c.max_rate}
             for robot in robots for c in channels.TABLE if c.max_rate]
    return [{"flows": ["ingress"], "messages": ["put"], "rules": rules}]


def forwarding_rules(table: Iterable[channels.Channel] = channels.TABLE) -> list[dict[str, Any]]:
    """The router's ``qos.network`` section: the channels whose profile says how they are ``forwarded`` (the
    edge's safety status and force level: dropped for a subscriber whose link is full), so that a subscriber
    that stops reading (a console whose callback hung, its keep-alives still flowing) holds up nobody. Without
    it, about 40 s after a console hung the router stopped forwarding the edge's state to everyone for 5 s and
    the edge lost its link (tests/test_router_fanout.py). Best-effort video needs no rule: Zenoh never blocks
    on it. Egress only: what the edge's own queue does with its messages is its own QoS."""
    by_mode: dict[str, list[str]] = {}
    for c in table:
        if c.qos is not None and QOS_PROFILES[c.qos].forwarded:
            by_mode.setdefault(QOS_PROFILES[c.qos].forwarded, []).append(f"{keys.ROOT}/*/{c.suffix}")
    return [{"id": f"forward-{mode.replace('_', '-')}", "messages": ["put"], "flows": ["egress"], "key_exprs": exprs,
             "overwrite": {"congestion_control": mode}} for mode, exprs in sorted(by_mode.items())]


def router_settings(listen: list[str], connect: list[str] | None = None, lease_ms: int | None = None,
                    shared_memory: bool = True, datagrams: bool = False) -> dict[str, Any]:
    """A plain router's configuration as a dict (written as JSON, it is a JSON5 file a stock zenohd reads).
    The lease defaults to ROUTER_LEASE_MS, longer for a router that connects to others (:func:`announced_lease`).
    ``shared_memory=False`` models a router on its own host: two routers on one machine otherwise negotiate
    shared memory and hand large payloads over through it, which no link between sites can do. ``datagrams``:
    UDP links beside the TCP ones (:func:`with_datagram_links`)."""
    lease_ms = lease_ms or announced_lease(ROUTER_LEASE_MS, bool(connect))
    if datagrams:
        listen, connect = with_datagram_links(listen, connect or [])
    cfg: dict[str, Any] = {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        # rx: nothing legitimate is larger than a video frame; Zenoh's default (1 GiB) lets one sender make the
        # router reassemble and forward gigabytes.
        "transport": {"link": {"tx": {"lease": lease_ms, "queue": {"size": dict(TX_QUEUE_SIZE)}},
                               "rx": {"max_message_size": RX_MAX_MESSAGE}}},
    }
    cfg["transport"]["shared_memory"] = ({"transport_optimization": {"pool_size": SHM_POOL_SIZE}} if shared_memory
                                         else {"enabled": False})
    cfg["transport"]["unicast"] = {"accept_pending": ACCEPT_PENDING}
    if datagrams:
        cfg["transport"]["unicast"]["max_links"] = DATAGRAM_MAX_LINKS
    cfg["qos"] = {"network": forwarding_rules()}
    if connect:
        cfg["connect"] = {"endpoints": list(connect)}
    return cfg


def router_json5(endpoint: str) -> str:
    """A minimal loopback router configuration (tests, demo)."""
    return json.dumps(router_settings([endpoint]))


def client_config(endpoint: str, **overrides: Any) -> ZenohConfig:
    return ZenohConfig(mode="client", connect=[endpoint], **overrides)


__all__ = [
    "COMMAND",
    "QOS_BY_KEY",
    "QOS_PROFILES",
    "ConnectError",
    "Inbox",
    "QosProfile",
    "Worker",
    "ZenohConfig",
    "announced_lease",
    "client_config",
    "datagram_endpoint",
    "open_session",
    "publisher",
    "query",
    "subscribe",
]
