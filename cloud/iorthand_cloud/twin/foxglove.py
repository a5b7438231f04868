"""The twin's live view in the Foxglove app: the recorder's Foxglove channels, served over the Foxglove
WebSocket protocol by foxglove-sdk's server (``foxglove: {enabled: true}`` in the twin's config).

The channels, topics and frames are those of :mod:`iorthand_cloud.foxglove_channels` (the same conversion the
recorder writes into ``<session>/foxglove/``), so a live view and a recording open with the same Foxglove
layout. Each channel is advertised when its first message arrives (a robot that never spoke has none).

Threads, as in the rest of the twin: the Zenoh callbacks only queue (state on a drop-oldest inbox, video on a
small one of its own so big frames never delay poses and safety logs); ``twin-foxglove`` and
``twin-foxglove-video`` decode, convert and hand the bytes to the server, whose own threads (in Rust) send them.
The server queues per client and drops for a client that reads too slowly (foxglove-sdk sends lossily); logging
into it never blocks on a client.

The server is read-only: it advertises no capability, so clients can subscribe, not publish, call services or
set parameters. It declares Zenoh subscribers of its own: the rerun side's rate gates and lazy decoding stay as
they are, and neither view waits for the other.

A video failure notice has no picture, and an image panel keeps the last one it was given: the converter puts a
"VIDEO FAILED" picture on the image topic for it (``FoxgloveConverter(failure_pictures=True)``), here as in a
recording, so a frozen picture never passes for a live one.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from typing import Any

import foxglove
import zenoh

from iorthand import keys
from iorthand.protocol import DecodeError, message_type_for
from iorthand.transport import Inbox, Worker
from iorthand_cloud.foxglove_channels import VIDEO_TOPICS, FoxgloveChannel, FoxgloveConverter

from .config import FoxgloveLiveConfig

log = logging.getLogger("iorthand.twin.foxglove")

SERVER_NAME = "iorthand twin"


class FoxgloveLive:
    """Start with :meth:`start` on the twin's Zenoh session; :meth:`stop` ends the server and the threads."""

    def __init__(self, config: FoxgloveLiveConfig) -> None:
        self.config = config
        self.context = foxglove.Context()  # its own: nothing else of this process logs into these channels
        self.server: foxglove.WebSocketServer | None = None
        self._stop = threading.Event()
        self._state = Inbox(config.queue, keep="newest")
        self._video = Inbox(8, keep="newest")
        self._channels: dict[FoxgloveChannel, foxglove.Channel] = {}
        self._lock = threading.Lock()  # two worker threads create channels
        self._declared: list[Any] = []
        self._workers: list[Worker] = []
        self.sent = 0  # messages handed to the server
        self.rejected = 0  # payloads that failed to decode (never converted)
        self.errors = 0  # conversions that failed

    @property
    def port(self) -> int:
        return self.server.port if self.server is not None else 0

    @property
    def url(self) -> str:
        """The address the Foxglove app opens ("Open connection" → Foxglove WebSocket)."""
        scheme = "wss" if self.config.tls_cert else "ws"
        return f"{scheme}://{self.config.host}:{self.port}" if self.server is not None else ""

    def start(self, session: zenoh.Session) -> None:
        cfg = self.config
        tls: dict[str, bytes] = {}
        if cfg.tls_cert is not None and cfg.tls_key is not None:
            tls = {"tls_cert": cfg.tls_cert.read_bytes(), "tls_key": cfg.tls_key.read_bytes()}
        try:
            self.server = foxglove.start_server(name=SERVER_NAME, host=cfg.host, port=cfg.port, context=self.context,
                                                **tls)
        except Exception as exc:  # the SDK raises its own error types: say where it failed to listen
            raise RuntimeError(f"Foxglove server cannot listen on {cfg.host}:{cfg.port}: {exc}") from exc
        state, video = self._state, self._video

        def on_state(sample: zenoh.Sample) -> None:
            state.put((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

        def on_video(sample: zenoh.Sample) -> None:
            video.put((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

        for suffix in FoxgloveConverter.SUFFIXES:
            if suffix in VIDEO_TOPICS and not cfg.video:
                continue
            self._declared.append(session.declare_subscriber(
                keys.all_robots(suffix), on_video if suffix in VIDEO_TOPICS else on_state))
        for name, inbox in (("twin-foxglove", state), ("twin-foxglove-video", video)):
            w = Worker(name, lambda stop, inbox=inbox: self._loop(stop, inbox), self._stop)
            w.start()
            self._workers.append(w)
        log.info("Foxglove live view on %s", self.url)

    def stop(self) -> None:
        self._stop.set()
        for inbox in (self._state, self._video):
            inbox.close()
        for w in self._workers:
            w.join(timeout=3.0)
        for d in self._declared:
            with contextlib.suppress(zenoh.ZError):
                d.undeclare()
        self._declared.clear()
        if self.server is not None:
            self.server.stop()
            self.server = None

    # ------------------------------------------------------------------ the worker threads

    def _loop(self, stop: threading.Event, inbox: Inbox) -> None:
        conv = FoxgloveConverter(video=self.config.video)  # one per thread: its state is per key
        while not stop.is_set():
            item = inbox.get(timeout=0.2)
            if item is None:
                continue
            for key, payload, recv_ns in [item, *inbox.drain()]:
                self._forward(conv, key, payload, recv_ns)

    def _forward(self, conv: FoxgloveConverter, key: str, payload: bytes, recv_ns: int) -> None:
        cls = message_type_for(key)
        if cls is None or not conv.handles(key):
            return
        try:
            msg = cls.decode(payload)
        except DecodeError as exc:
            self.rejected += 1
            if self.rejected == 1 or self.rejected % 1000 == 0:
                log.warning("%d malformed payloads not served (latest on %s: %s)", self.rejected, key, exc)
            return
        try:
            out = conv.convert(key, msg)
        except Exception as exc:  # a conversion bug costs that message, never the live view (or the twin)
            self.errors += 1
            if self.errors == 1 or self.errors % 1000 == 0:
                log.error("Foxglove conversion of %s failed (%d so far): %r", key, self.errors, exc)
            return
        for m in out:
            self._channel(m.channel).log(m.data, log_time=recv_ns)
            self.sent += 1

    def _channel(self, ch: FoxgloveChannel) -> foxglove.Channel:
        channel = self._channels.get(ch)
        if channel is None:
            with self._lock:
                channel = self._channels.get(ch)
                if channel is None:
                    schema = foxglove.Schema(name=ch.schema_name, encoding=ch.schema_encoding, data=ch.schema)
                    channel = self._channels[ch] = foxglove.Channel(
                        ch.topic, schema=schema, message_encoding=ch.message_encoding, context=self.context,
                        metadata=ch.metadata)
        return channel


__all__ = ["SERVER_NAME", "FoxgloveLive"]
