"""The adapter of ``iorthand bridge mqtt``: one Zenoh session, one paho-mqtt client, the routes of
:mod:`iorthand_cloud.bridge.mapping` between them.

- out: a Zenoh callback only queues the raw sample (:class:`iorthand.transport.Inbox`); a worker thread keeps the
  newest per robot (:class:`LatestThrottle`), decodes what goes out and publishes its JSON. A 125 Hz robot state
  is decoded at ``max_hz``, not at 125 Hz. While the broker is away the newest JSON of each topic is held (the
  ones it replaces are counted dropped) and sent at the next connection: the broker never gets a stale backlog.
- in: an MQTT v5 broker is told the largest packet the bridge takes (:func:`max_packet_size`, from the mappings'
  ``max_payload``) and drops a larger message for the bridge instead of sending it (paho reads a message whole
  before any check: 16 MB cost the bridge ~50 MB of memory); with 3.1.1 only the broker's own limit helps, and the
  start log says which to set. The QoS 1 messages the broker numbered for the bridge and never sent are counted
  (:class:`BrokerNumbering`). paho's network thread drops what exceeds ``max_hz`` per robot (:class:`RateLimits`,
  before parsing: a flood costs a lookup per message), checks the rest (:meth:`InRoute.reading`), and publishes on Zenoh through
  :meth:`MqttBridge._put`, which checks the key once more (:func:`check_bridge_key`): even a bug in the mapping
  code cannot put on a key the bridge's role does not write.
  Refusals are counted per mapping and logged with their reason (at most one line per mapping every few
  seconds under a flood), and nothing refused reaches Zenoh.

Per-key state is bounded: an 'in' mapping serves the robots the configuration names (at most ``MAX_KEYS``), and
an 'out' throttle is forgotten only once it is the same as a new one; while ``MAX_KEYS`` are busy a new key's
sample is dropped as over the rate, never a busy robot's throttle (which let keys taking turns pass everything).

paho reconnects on its own (1 s doubling to 30 s) and re-subscribes at every connection; a broker that refuses
the bridge (bad password, certificate) is logged with its reason and retried, like a router that is not up yet.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import ssl
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import zenoh
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from iorthand.config import ConfigError
from iorthand.protocol import DecodeError, Message, Sequencer
from iorthand.transport import Inbox, open_session, publisher
from iorthand_cloud.bridge.config import BridgeConfig, MqttConfig
from iorthand_cloud.bridge.mapping import (
    MAX_KEYS,
    InRoute,
    LatestThrottle,
    MappingError,
    OutRoute,
    RateLimits,
    Refused,
    check_bridge_key,
    max_packet_size,
    to_json,
)

log = logging.getLogger("iorthand.bridge")
LOG_EVERY_S = 5.0  # at most one refusal line per mapping this often: a flooding sensor must not fill the disk
OUT_INBOX = 1024  # Zenoh samples queued for the worker (the newest are kept)


def read_password(path: Path) -> str:
    """The password in ``path`` (one line; a trailing newline is not part of it)."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError("mqtt", "password_file", f"cannot read {path}: {getattr(exc, 'strerror', None) or exc}") from None
    password = text.rstrip("\r\n")
    if not password:
        raise ConfigError("mqtt", "password_file", f"{path} is empty")
    return password


def make_client(cfg: MqttConfig, password: str | None = None) -> mqtt.Client:
    """A paho client with the broker settings of ``cfg``: protocol, client id, user and password, TLS."""
    protocol = mqtt.MQTTv5 if cfg.protocol == "5" else mqtt.MQTTv311
    client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=cfg.client_id, protocol=protocol)
    if cfg.username:
        client.username_pw_set(cfg.username, password)
    if cfg.tls is not None:
        tls = cfg.tls
        for name, path in (("ca", tls.ca), ("certificate", tls.certificate), ("private_key", tls.private_key)):
            if path is not None and not Path(path).is_file():
                raise ConfigError("mqtt", f"tls.{name}", f"no such file {path}")
        try:
            client.tls_set(ca_certs=str(tls.ca), certfile=str(tls.certificate) if tls.certificate else None,
                           keyfile=str(tls.private_key) if tls.private_key else None,
                           cert_reqs=ssl.CERT_REQUIRED, tls_version=ssl.PROTOCOL_TLS_CLIENT)
        except (ssl.SSLError, OSError) as exc:
            raise ConfigError("mqtt", "tls", f"the certificate files do not load: {exc}") from None
        if not tls.verify_name:
            client.tls_insecure_set(True)
    client.reconnect_delay_set(min_delay=1, max_delay=30)
    client.max_queued_messages_set(cfg.queue)
    return client


@dataclasses.dataclass
class MappingStats:
    forwarded: int = 0  # crossed the bridge
    refused: int = 0  # invalid (in: bad JSON, shape, bounds, age; out: undecodable), or a robot not bridged
    rate_limited: int = 0  # in: over max_hz, dropped; out: replaced by a newer sample while waiting its turn
    dropped: int = 0  # not sent: replaced while the broker was away (or no room to hold it), refused by paho, the
    # Zenoh session closing
    last_refusal: str = ""


def connect_properties(cfg: MqttConfig, max_packet: int) -> Properties | None:
    """MQTT v5: the CONNECT property telling the broker the largest packet the bridge takes (3.1.1 has none)."""
    if cfg.protocol != "5":
        return None
    properties = Properties(PacketTypes.CONNECT)
    properties.MaximumPacketSize = max_packet
    return properties


MAX_PACKET_ID = 65535
SKIP_WINDOW = MAX_PACKET_ID // 2  # a larger jump is a numbering that started again, not messages withheld


class BrokerNumbering:
    """The packet ids of the QoS 1 messages the broker sends the bridge, which it numbers in order (1, 2, ... 65535,
    1): an id skipped is a message the broker numbered for the bridge and then did not send — larger than the
    maximum packet size the bridge announced, or over the broker's queue for the bridge — which MQTT does not
    otherwise tell. mosquitto numbers so; a broker that numbers otherwise shows no skip beyond ``SKIP_WINDOW``.
    QoS 0 messages carry no id: what the broker drops of them cannot be known."""

    def __init__(self) -> None:
        self.skipped = 0
        self._last = 0

    def restart(self) -> None:
        """A new connection: the bridge keeps no session (clean start, no expiry), and a new one is numbered from 1."""
        self._last = 0

    def observe(self, mid: int, qos: int, dup: bool) -> int:
        """The ids skipped before ``mid`` (counted in :attr:`skipped`)."""
        if qos == 0 or dup or mid == self._last:  # a resent message repeats its id
            return 0
        gap = (mid - self._last - 1) % MAX_PACKET_ID
        self._last = mid
        if gap >= SKIP_WINDOW:
            return 0
        self.skipped += gap
        return gap


class MqttBridge:
    """The running bridge. ``session``: an open Zenoh session to use (tests); otherwise one is opened from the
    configuration and closed at :meth:`shutdown`."""

    def __init__(self, cfg: BridgeConfig, session: zenoh.Session | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg = cfg
        self.routes = cfg.routes()  # checked again: a config built in code did not pass through the loader
        self.session = session
        self._own_session = session is None
        self._clock = clock
        self.stats = {r.name: MappingStats() for r in self.routes}
        self.blocked = 0  # puts refused by the run-time key check: a bug if ever non-zero
        self.unrouted = 0  # MQTT messages no mapping takes (a topic that is not UTF-8)
        self.max_packet = max_packet_size(self.routes)  # announced to an MQTT v5 broker
        self.numbering = BrokerNumbering()  # QoS 1 messages the broker numbered for the bridge and did not send
        self.connected = threading.Event()
        self.last_error = ""  # why the broker refused or dropped the bridge, last time
        self.stop_event = threading.Event()
        self.client: mqtt.Client | None = None
        self._lock = threading.Lock()  # stats and per-key state: paho's thread and the worker share them
        self._inbox = Inbox(maxlen=OUT_INBOX, keep="newest")
        # out: (route index, key) → its throttle; at most MAX_KEYS, an idle one forgotten (_pump)
        self._throttles: dict[tuple[int, str], LatestThrottle] = {}
        self._limits = {r.name: RateLimits(r.max_hz, MAX_KEYS) for r in self.routes if isinstance(r, InRoute)}
        # in: per key, bounded by the configuration (the robots named, which check_routes requires, and keys of
        # mappings that name one robot): never forgotten, so a key's sequence never starts again
        self._publishers: dict[str, Any] = {}
        self._sequencers: dict[str, Sequencer] = {}
        self._held: dict[str, tuple[OutRoute, bytes]] = {}  # out, broker away: topic → the newest JSON; ≤ MAX_KEYS
        self._last_log: dict[str, tuple[float, int]] = {}  # per mapping: when its last refusal was logged, the count
        self._numbering_logged = (-LOG_EVERY_S, 0)  # the same for what the broker did not deliver
        self._declared: list[Any] = []
        self._worker: threading.Thread | None = None

    # ------------------------------------------------------------------------------------------------ life

    def start(self) -> None:
        for key, problem in self.cfg.warnings():
            log.warning("%s: %s", key, problem)
        mq = self.cfg.mqtt
        password = read_password(mq.password_file) if mq.password_file is not None else None
        client = make_client(mq, password)
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_connect_fail = self._on_connect_fail
        client.on_message = self._on_unrouted
        for route in self.routes:
            if isinstance(route, InRoute):
                client.message_callback_add(route.topic.subscription, functools.partial(self._on_mqtt, route))
        self.client = client
        if self.session is None:
            self.session = open_session(self.cfg.zenoh, self.stop_event)
        for index, route in enumerate(self.routes):
            if isinstance(route, OutRoute):
                on_sample = functools.partial(self._on_sample, index, route.message.MAX_BYTES)
                self._declared += [self.session.declare_subscriber(e, on_sample) for e in route.exprs]
        self._worker = threading.Thread(target=self._pump, name="bridge-out", daemon=True)
        self._worker.start()
        client.connect_async(mq.host, mq.port, mq.keepalive, properties=connect_properties(mq, self.max_packet))
        client.loop_start()
        log.info("bridge: %d mappings, broker %s:%d%s, MQTT %s%s", len(self.routes), mq.host, mq.port,
                 " (TLS)" if mq.tls else "", mq.protocol,
                 f" (maximum packet size {self.max_packet} bytes: the broker drops larger messages for the bridge)"
                 if mq.protocol == "5" else "")
        for r in self.routes:
            arrow = f"{', '.join(r.exprs)} → {r.topic.text}" if isinstance(r, OutRoute) else f"{r.topic.subscription} → {r.key.text}"
            log.info("  %s %s: %s (QoS %d, %g Hz)", r.name, "out" if isinstance(r, OutRoute) else "in", arrow, r.qos,
                     r.max_hz)

    def wait_connected(self, timeout: float) -> bool:
        return self.connected.wait(timeout)

    def shutdown(self) -> None:
        self.stop_event.set()
        self._inbox.close()
        if self.client is not None:
            self.client.disconnect()
            self.client.loop_stop()
        if self._worker is not None:
            self._worker.join(timeout=5.0)
        with self._lock:
            for d in [*self._declared, *self._publishers.values()]:
                with contextlib.suppress(zenoh.ZError):
                    d.undeclare()
            self._declared.clear()
            self._publishers.clear()
        if self.session is not None and self._own_session:
            self.session.close()
            self.session = None
        log.info("bridge stopped: %s", self.summary())

    def run_forever(self) -> None:
        self.start()
        try:
            while not self.stop_event.wait(self.cfg.stats_interval_s):
                log.info("bridge: %s", self.summary())
        finally:
            self.shutdown()

    def summary(self) -> str:
        with self._lock:
            parts = [f"{name} {s.forwarded} sent, {s.refused} refused, {s.rate_limited} rate-limited, {s.dropped} dropped"
                     for name, s in self.stats.items()]
        if self.numbering.skipped:
            parts.append(f"{self.numbering.skipped} QoS 1 messages the broker did not deliver")
        if self.blocked:
            parts.append(f"{self.blocked} puts blocked by the key check")
        return "; ".join(parts)

    # ------------------------------------------------------------------------------------------------ MQTT

    def _on_connect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        if reason.is_failure:
            self._broker_problem(f"the broker refused the connection: {reason}")
            return
        subscriptions = [(r.topic.subscription, r.qos) for r in self.routes if isinstance(r, InRoute)]
        if subscriptions:  # at every connection: a broker without a persistent session forgot them
            client.subscribe(subscriptions)
        with self._lock:
            self.numbering.restart()
        self.last_error = ""
        self.connected.set()  # before taking what is held: a _send from now on publishes instead of holding
        log.info("connected to the MQTT broker %s:%d", self.cfg.mqtt.host, self.cfg.mqtt.port)
        with self._lock:
            held = list(self._held.items())
            self._held.clear()
        for topic, (route, data) in held:
            self._publish(route, topic, data)

    def _on_disconnect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        was = self.connected.is_set()
        self.connected.clear()
        if not self.stop_event.is_set() and was:
            self._broker_problem(f"disconnected from the broker: {reason}")

    def _on_connect_fail(self, client: mqtt.Client, userdata: Any) -> None:
        self._broker_problem(f"cannot reach the broker at {self.cfg.mqtt.host}:{self.cfg.mqtt.port}")

    def _broker_problem(self, why: str) -> None:
        if why != self.last_error:  # paho retries every few seconds: say it once per cause
            log.warning("%s (paho retries)", why)
        self.last_error = why

    def _numbered(self, message: mqtt.MQTTMessage) -> None:
        """Count the messages the broker numbered before ``message`` and did not send, and say so (at most a line
        every few seconds)."""
        now = self._clock()
        with self._lock:
            if not self.numbering.observe(message.mid, message.qos, bool(message.dup)):
                return
            last, count_then = self._numbering_logged
            if now - last < LOG_EVERY_S:
                return
            self._numbering_logged = (now, self.numbering.skipped)
            skipped = self.numbering.skipped - count_then
        log.warning("the broker did not deliver %d QoS 1 message(s) it numbered for the bridge: larger than the "
                    "%d bytes the bridge takes (mosquitto logs \"Dropping too large outgoing PUBLISH for %s\"), or "
                    "over its queue for the bridge", skipped, self.max_packet, self.cfg.mqtt.client_id)

    def _on_unrouted(self, client: mqtt.Client, userdata: Any, message: mqtt.MQTTMessage) -> None:
        self._numbered(message)
        with self._lock:
            self.unrouted += 1
        log.debug("an MQTT message no mapping takes (topic not UTF-8?)")

    def _on_mqtt(self, route: InRoute, client: mqtt.Client, userdata: Any, message: mqtt.MQTTMessage) -> None:
        try:
            self._numbered(message)
            self._take(route, message)
        except Exception:  # a bug here must not stop paho's network thread (and with it every mapping)
            log.exception("mapping %r: error handling a message", route.name)
            self._refuse(route, "internal error (see the log)")

    def _take(self, route: InRoute, message: mqtt.MQTTMessage) -> None:
        try:
            key = route.key_for(message.topic)
        except Refused as exc:
            self._refuse(route, f"{message.topic}: {exc}")
            return
        limits = self._limits[route.name]
        with self._lock:  # asked before parsing: a flood on one topic costs a lookup per message, not a JSON parse
            if not limits.ready(key, self._clock()):
                self.stats[route.name].rate_limited += 1
                return
        try:
            reading = route.reading(message.payload, time.time_ns(), bool(message.retain))
        except Refused as exc:
            self._refuse(route, f"{message.topic}: {exc}")
            return
        with self._lock:
            if not limits.take(key, self._clock()):
                self.stats[route.name].rate_limited += 1
                return
        self._put(route, key, reading)

    def _put(self, route: InRoute, key: str, msg: Message) -> None:
        """Publish ``msg`` on ``key`` — only if the bridge's role may write it (defence in depth: the mapping
        was checked at configuration time, and this is checked again for every message)."""
        try:
            check_bridge_key(key)
        except MappingError as exc:
            with self._lock:
                self.blocked += 1
            log.error("mapping %r: refused to publish on %s: %s", route.name, key, exc)
            return
        assert self.session is not None
        with self._lock:
            if key not in self._publishers:
                self._publishers[key] = publisher(self.session, key)
                self._sequencers[key] = Sequencer()
            pub = self._publishers[key]
            seq = self._sequencers[key].next()  # per key: the recorder counts gaps and restarts by it
        try:
            pub.put(msg.stamp(seq, msg.t).encode())
        except (zenoh.ZError, ValueError) as exc:
            with self._lock:
                self.stats[route.name].dropped += 1
            log.warning("mapping %r: not published on %s: %s", route.name, key, exc)
            return
        with self._lock:
            self.stats[route.name].forwarded += 1

    # ------------------------------------------------------------------------------------------------ Zenoh → MQTT

    def _on_sample(self, index: int, max_bytes: int, sample: zenoh.Sample) -> None:
        size = len(sample.payload)
        if size > max_bytes:  # refused before it is copied out of Zenoh's buffers
            self._refuse(self.routes[index], f"{sample.key_expr}: payload of {size} bytes exceeds {max_bytes}")
            return
        self._inbox.put((index, str(sample.key_expr), sample.payload.to_bytes()), size)

    def _pump(self) -> None:
        while not self.stop_event.is_set():
            with self._lock:
                dues = [d for t in self._throttles.values() if (d := t.due()) is not None]
            wait = 0.5 if not dues else max(0.0, min(dues) - self._clock())
            item = self._inbox.get(timeout=min(wait, 0.5))
            ready: list[tuple[int, str, bytes]] = []
            now = self._clock()
            with self._lock:
                if item is not None:
                    self._offer(item, now, ready)
                for slot, throttle in list(self._throttles.items()):
                    if (payload := throttle.poll(now)) is not None:
                        ready.append((*slot, payload))
                    elif throttle.idle(now):  # the same as a new one: its slot is freed and nothing is lost
                        del self._throttles[slot]
            for index, key, payload in ready:
                route = self.routes[index]
                assert isinstance(route, OutRoute)  # only out routes subscribe (start)
                self._send(route, key, payload)

    def _offer(self, item: tuple[int, str, bytes], now: float, ready: list[tuple[int, str, bytes]]) -> None:
        """Hand a sample to its key's throttle (under the lock); into ``ready`` if it may go now."""
        index, key, payload = item
        route = self.routes[index]
        throttle = self._throttles.get((index, key))
        if throttle is None:
            if len(self._throttles) >= MAX_KEYS:
                # Every slot holds a key within its turn or with a sample waiting: a new key is dropped like a sample
                # over the rate. Forgetting the least recently used instead let 257 keys taking turns reset each
                # other's throttle (every sample passed) and lost the sample a robot had waiting.
                self.stats[route.name].rate_limited += 1
                return
            throttle = self._throttles[(index, key)] = LatestThrottle(route.max_hz)
        before = throttle.superseded
        if throttle.offer(payload, now) is not None:
            ready.append(item)
        self.stats[route.name].rate_limited += throttle.superseded - before

    def _send(self, route: OutRoute, key: str, payload: bytes) -> None:
        try:
            topic = route.topic_for(key)
            data = to_json(route.message.decode(payload))
        except (Refused, DecodeError, TypeError, ValueError) as exc:
            self._refuse(route, f"{key}: {exc}")
            return
        with self._lock:
            if not self.connected.is_set():
                # Held, the newest per topic, for the next connection: handed to paho, a QoS 1 message would wait
                # in its queue with every one before it, and the broker would get the whole backlog, stale.
                if self._held.pop(topic, None) is not None:
                    self.stats[route.name].dropped += 1
                elif len(self._held) >= MAX_KEYS:  # the topics held keep their place: no newcomer pushes one out
                    self.stats[route.name].dropped += 1
                    return
                self._held[topic] = (route, data)
                return
        self._publish(route, topic, data)

    def _publish(self, route: OutRoute, topic: str, data: bytes) -> None:
        assert self.client is not None
        info = self.client.publish(topic, data, qos=route.qos, retain=route.retain)
        with self._lock:
            if info.rc == mqtt.MQTT_ERR_SUCCESS:
                self.stats[route.name].forwarded += 1
            else:
                self.stats[route.name].dropped += 1

    # ------------------------------------------------------------------------------------------------ refusals

    def _refuse(self, route: OutRoute | InRoute, reason: str) -> None:
        now = self._clock()
        with self._lock:
            stats = self.stats[route.name]
            stats.refused += 1
            stats.last_refusal = reason
            last, count_then = self._last_log.get(route.name, (-LOG_EVERY_S, 0))
            if now - last < LOG_EVERY_S:
                return
            self._last_log[route.name] = (now, stats.refused)
            unlogged = stats.refused - count_then - 1
        log.warning("mapping %r refused %s%s", route.name, reason,
                    f" ({unlogged} more refused since the last line)" if unlogged > 0 else "")


__all__ = ["MAX_KEYS", "BrokerNumbering", "MappingStats", "MqttBridge", "connect_properties", "make_client",
           "read_password"]
