"""The MQTT bridge's configuration (``configs/bridge-mqtt.yaml``), validated by :mod:`iorthand.config`.

Every mapping is compiled (:func:`iorthand_cloud.bridge.mapping.compile_route`) while the file loads, so a mapping
into ``cmd/``, ``control/`` or ``alive/``, onto a key the bridge may not write, or of video, fails before anything
connects, with the file, the mapping's place (``mappings[2]``), its name and why.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import re
from pathlib import Path
from typing import Any

from iorthand.config import setting
from iorthand.transport import ZenohConfig, client_config
from iorthand_cloud.bridge.mapping import MAX_KEYS, Direction, InRoute, Route, check_routes, compile_route

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
CLIENT_ID = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


@dataclasses.dataclass
class MqttTlsConfig:
    """TLS to the broker (paths to PEM files). ``certificate`` and ``private_key``: a client certificate, for a
    broker that requires one (``require_certificate true`` in mosquitto)."""

    ca: Path = setting(help="the CA certificate that signed the broker's")
    certificate: Path | None = setting(None, help="this bridge's certificate (e.g. bridge.pem)")
    private_key: Path | None = setting(None, help="its private key (mode 0600)")
    verify_name: bool = setting(True, help="check that the broker's certificate names mqtt.host (keep it on)")

    def check(self) -> None:
        if (self.certificate is None) != (self.private_key is None):
            raise ValueError("certificate and private_key go together (a client certificate needs its key)")


@dataclasses.dataclass
class MqttConfig:
    host: str = setting("127.0.0.1", help="the broker's host name or address")
    port: int = setting(1883, lo=1, hi=65535, help="1883 plain, 8883 with TLS by convention")
    client_id: str = setting("iorthand-bridge", help="unique per broker: a second client with it disconnects the first")
    protocol: str = setting("3.1.1", choices=("3.1.1", "5"))
    keepalive: int = setting(30, lo=5, hi=3600, help="s: the broker drops a silent bridge after 1.5 times this")
    username: str = ""
    password_file: Path | None = setting(None, help="a file holding the password (mode 0600), never the YAML")
    tls: MqttTlsConfig | None = None
    queue: int = setting(1000, lo=0, help="QoS 1 messages kept while the broker is away (0: no limit)")

    def check(self) -> None:
        if not self.host:
            raise ValueError("host: the broker's host name or address")
        if not CLIENT_ID.match(self.client_id):
            raise ValueError(f"client_id {self.client_id!r}: 1-64 characters of [A-Za-z0-9_.-]")
        if self.username and self.password_file is None:
            raise ValueError(f"username {self.username!r} needs a password_file (a file with the password, mode 0600)")
        if self.password_file is not None and not self.username:
            raise ValueError("password_file needs a username")

    def warnings(self) -> list[tuple[str, str]]:
        """Settings that load but weaken the link (logged at start)."""
        out = []
        if self.password_file is not None and self.tls is None and not _loopback(self.host):
            out.append(("mqtt.tls", f"none: the password to {self.host} crosses the network in clear text"))
        if self.tls is not None and not self.tls.verify_name:
            out.append(("mqtt.tls.verify_name", "off: any certificate of the CA can pose as the broker"))
        return out


def _loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclasses.dataclass
class MappingConfig:
    """One key ↔ topic mapping (see :mod:`iorthand_cloud.bridge.mapping`)."""

    name: str = setting(help="names the mapping in logs, counters and errors")
    direction: str = setting(choices=[d.value for d in Direction], help="out: Zenoh → MQTT; in: MQTT → Zenoh")
    key: str = setting(help="iorthand/{robot}/<suffix>, a key of the table of channels")
    topic: str = setting(help="MQTT topic template, {robot} a whole level, e.g. site/{robot}/robot_state")
    qos: int = setting(0, choices=(0, 1), help="MQTT QoS: 0 at most once, 1 at least once")
    max_hz: float = setting(10.0, lo=0.01, hi=1000.0, help="per robot: out sends the newest at this rate, in drops the excess")
    retain: bool = setting(False, help="out: the broker keeps the last message for late subscribers")
    fields: dict[str, Any] = setting(default_factory=dict, help="in: fields the mapping sets (name, unit, source)")
    bounds: dict[str, list[float]] = setting(default_factory=dict, help="in: plausible [low, high] per numeric field")
    max_age_s: float = setting(60.0, lo=0.001, help="in: a reading with an older sensor time t is refused")
    max_future_s: float = setting(5.0, lo=0.0, help="in: and one from further in the future")
    accept_retained: bool = setting(False, help="in: take the broker's retained (old) message at subscription")
    max_payload: int = setting(4096, lo=2, hi=65536, help="in: bytes of one MQTT message")

    def route(self, robots: list[str] | tuple[str, ...] = ()) -> Route:
        return compile_route(
            self.name, self.direction, self.key, self.topic, qos=self.qos, max_hz=self.max_hz, retain=self.retain,
            fixed=self.fields, bounds=self.bounds, max_age_s=self.max_age_s, max_future_s=self.max_future_s,
            accept_retained=self.accept_retained, max_payload=self.max_payload, robots=robots,
        )

    def check(self) -> None:
        self.route()  # MappingError is a ValueError: the loader names the file and mappings[i]


@dataclasses.dataclass
class BridgeConfig:
    zenoh: ZenohConfig = dataclasses.field(default_factory=lambda: client_config(DEFAULT_CONNECT))
    mqtt: MqttConfig = dataclasses.field(default_factory=MqttConfig)
    robots: list[str] = setting(default_factory=list, help="the robots bridged, at most 256 (empty: every robot, "
                                "for 'out' mappings only: an 'in' mapping with {robot} needs them named)")
    mappings: list[MappingConfig] = setting(default_factory=list)
    stats_interval_s: float = setting(60.0, lo=1.0, help="s between the counters in the log")

    def routes(self) -> list[Route]:
        if len(set(self.robots)) > MAX_KEYS:
            raise ValueError(f"robots: {len(set(self.robots))} named, at most {MAX_KEYS} (run another bridge for more)")
        routes = [m.route(self.robots) for m in self.mappings]
        check_routes(routes)
        return routes

    def warnings(self) -> list[tuple[str, str]]:
        """Settings that load but weaken the bridge (logged at start, printed by --check)."""
        out = self.mqtt.warnings()
        payloads = [r.max_payload for r in self.routes() if isinstance(r, InRoute)]
        if payloads and self.mqtt.protocol != "5":
            out.append(("mqtt.protocol", (
                f"{self.mqtt.protocol} cannot tell the broker the largest message the bridge takes: the broker sends "
                f"it messages of any size (up to 256 MB), each read whole into memory before max_payload refuses it. "
                f'Set "message_size_limit {max(payloads)}" (bytes: the largest max_payload of the in mappings) in '
                'the broker\'s mosquitto.conf, or use protocol "5"')))
        return out

    def check(self) -> None:
        if not self.mappings:
            raise ValueError("mappings: at least one mapping (out: Zenoh → MQTT, in: MQTT → Zenoh)")
        self.routes()


__all__ = ["BridgeConfig", "MappingConfig", "MqttConfig", "MqttTlsConfig"]
