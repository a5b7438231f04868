"""``iorthand bridge mqtt``: the mapping rules (pure), and both directions through a real Zenoh router and Debian's
mosquitto started here (plain, and with TLS + a client certificate + a password), with paho-mqtt as the client."""

from __future__ import annotations

import dataclasses
import itertools
import json
import logging
import os
import queue
import shutil
import socket
import ssl
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import pytest

from iorthand import channels, keys
from iorthand.config import ConfigError, from_dict, load
from iorthand.protocol import ForceLevelState, RobotState, SensorReading, VideoFrame
from iorthand.security import acl, certs
from iorthand.transport import free_port
from iorthand_cloud.bridge.config import BridgeConfig, MappingConfig, MqttConfig
from iorthand_cloud.bridge.mapping import (
    InRoute,
    KeyTemplate,
    LatestThrottle,
    MappingError,
    OutRoute,
    RateLimits,
    Refused,
    TopicTemplate,
    check_bridge_key,
    check_routes,
    compile_route,
    to_json,
)
from iorthand_cloud.bridge.mqtt import MqttBridge, make_client
from iorthand_operator.console.model import vitals_line
from tests.conftest import ROOT, stop_process, wait_until

MOSQUITTO = shutil.which("mosquitto") or ("/usr/sbin/mosquitto" if Path("/usr/sbin/mosquitto").exists() else None)
MOSQUITTO_PASSWD = shutil.which("mosquitto_passwd")
NOW = 1_700_000_000_000_000_000

HEART = {"name": "heart-rate", "direction": "in", "topic": "site/{robot}/vitals/heart_rate",
         "key": "iorthand/{robot}/sensor/vital", "qos": 1, "max_hz": 100.0,
         "fields": {"name": "heart_rate", "unit": "bpm", "source": "monitor"}, "bounds": {"value": [20, 250]}}
ROBOTS = ["sim1", "sim2", "sim3"]  # an 'in' mapping serves the robots its bridge names
STATE_OUT = {"name": "robot-state", "direction": "out", "key": "iorthand/{robot}/state/robot",
             "topic": "site/{robot}/robot_state", "qos": 1, "max_hz": 10.0}


# ------------------------------------------------------------------------------------------------ pure: templates


def test_topic_templates_name_the_robot_level() -> None:
    t = TopicTemplate.parse("site/{robot}/robot_state")
    assert t.topic("sim1") == "site/sim1/robot_state"
    assert t.subscription == "site/+/robot_state"
    assert t.robot_of("site/sim1/robot_state") == "sim1"
    assert t.robot_of("site/sim1/other") is None and t.robot_of("site/sim1/robot_state/x") is None
    fixed = TopicTemplate.parse("ward3/bed2/hr")
    assert fixed.robot_of("ward3/bed2/hr") == "" and fixed.subscription == "ward3/bed2/hr"
    assert t.overlaps(TopicTemplate.parse("site/sim1/robot_state"))
    assert not t.overlaps(TopicTemplate.parse("site/sim1/force"))


@pytest.mark.parametrize(("topic", "why"), [
    ("site/+/state", "wildcard"), ("site/#", "wildcard"), ("$SYS/x", "broker's own space"), ("", "empty"),
    ("/site/x", "empty level"), ("site//x", "empty level"), ("site/{robot}/{robot}", "more than once"),
    ("site/r{robot}/x", "whole level"), ("site/{operator}/x", "only placeholder"),
])
def test_bad_topic_templates_are_refused(topic: str, why: str) -> None:
    with pytest.raises(MappingError, match=why):
        TopicTemplate.parse(topic)


def test_key_templates_are_rows_of_the_table() -> None:
    k = KeyTemplate.parse("iorthand/{robot}/state/robot")
    assert k.channel is channels.STATE_ROBOT and k.message is RobotState
    assert k.expr == "iorthand/*/state/robot" and k.key("sim1") == "iorthand/sim1/state/robot"
    one = KeyTemplate.parse("iorthand/sim1/sensor/vital")
    assert one.robot == "sim1" and one.expr == "iorthand/sim1/sensor/vital" and one.key("other") == one.expr


@pytest.mark.parametrize(("key", "why"), [
    ("iorthand/{robot}/cmd/twist", "operator commands"),
    ("iorthand/{robot}/cmd/stop", "operator commands"),
    ("iorthand/{robot}/cmd/anything_new", "operator commands"),
    ("iorthand/{robot}/control/acquire", "control queries"),
    ("iorthand/{robot}/control/arm", "control queries"),
    ("iorthand/{robot}/alive/edge", "liveliness"),
    ("iorthand/{robot}/alive/operator", "liveliness"),
    ("iorthand/{robot}/state/nothing", "not a stream of the table"),
    ("iorthand/*/state/robot", "wildcard"),
    ("iorthand/{robot}/**", "wildcard"),
    ("iorthand/sim1-replay/sensor/vital", "reserved for replayed"),
    ("iorthand/{robot}", r"iorthand/\{robot\}/<suffix>"),
    ("other/{robot}/state/robot", r"iorthand/\{robot\}/<suffix>"),
])
def test_keys_no_mapping_may_touch_are_refused_with_why(key: str, why: str) -> None:
    with pytest.raises(MappingError, match=why):
        KeyTemplate.parse(key)


# ------------------------------------------------------------------------------------------------ pure: routes


@pytest.mark.parametrize(("direction", "key", "why"), [
    ("in", "iorthand/{robot}/cmd/twist", "cmd/"),
    ("in", "iorthand/{robot}/control/acquire", "control/"),
    ("in", "iorthand/{robot}/alive/edge", "alive/"),
    ("in", "iorthand/{robot}/state/robot", "written only by edge, replay"),
    ("in", "iorthand/{robot}/markers", "written only by edge, replay"),
    ("out", "iorthand/{robot}/cmd/twist", "cmd/"),
    ("out", "iorthand/{robot}/video/camera", "VideoFrame, whose data is binary"),
    ("out", "iorthand/{robot}/video/ultrasound", "binary"),
])
def test_routes_the_bridge_may_not_run_are_refused_naming_the_mapping(direction: str, key: str, why: str) -> None:
    with pytest.raises(MappingError, match=f"mapping 'm1': .*{why}"):
        compile_route("m1", direction, key, "site/{robot}/x")


def test_templates_must_agree_on_the_robot() -> None:
    with pytest.raises(MappingError, match="every robot would share one topic"):
        compile_route("m", "out", "iorthand/{robot}/state/robot", "site/robot_state")
    with pytest.raises(MappingError, match="names robot 'sim1'"):
        compile_route("m", "in", "iorthand/sim1/sensor/vital", "site/{robot}/hr", fixed={"name": "hr"})
    route = compile_route("m", "in", "iorthand/sim1/sensor/vital", "ward3/bed2/hr")
    assert isinstance(route, InRoute) and route.key_for("ward3/bed2/hr") == "iorthand/sim1/sensor/vital"


@pytest.mark.parametrize(("kwargs", "why"), [
    ({"qos": 2}, "QoS 0 or 1"),
    ({"max_hz": 0.0}, "max_hz"),
    ({"fixed": {"colour": "red"}}, "'colour' is not a field"),
    ({"fixed": {"unit": "x" * 17}}, "SensorReading.unit"),
    ({"fixed": {"value": "high"}}, "SensorReading.value"),
    ({"bounds": {"name": [0, 1]}}, "not a numeric field"),
    ({"bounds": {"value": [10, 5]}}, "low <= high"),
    ({"retain": True}, "retain belongs to 'out'"),
])
def test_in_mapping_settings_are_checked(kwargs: dict[str, Any], why: str) -> None:
    with pytest.raises(MappingError, match=why):
        compile_route("m", "in", "iorthand/{robot}/sensor/vital", "site/{robot}/hr", **kwargs)


def test_colliding_mappings_are_refused() -> None:
    hr = compile_route("hr", "in", "iorthand/{robot}/sensor/vital", "site/{robot}/hr")
    hr_one = compile_route("hr1", "in", "iorthand/sim1/sensor/vital", "site/sim1/hr")
    state = compile_route("state", "out", "iorthand/{robot}/state/robot", "site/{robot}/hr")
    with pytest.raises(MappingError, match="can be one MQTT topic"):
        check_routes([hr, hr_one])  # a reading would be published twice
    with pytest.raises(MappingError, match="can be one MQTT topic"):
        check_routes([hr, state])  # the bridge would read back its own output
    with pytest.raises(MappingError, match="two mappings have this name"):
        check_routes([hr, dataclasses.replace(hr_one, name="hr", topic=TopicTemplate.parse("other/hr"))])


def test_the_run_time_key_check_allows_only_the_bridges_keys() -> None:
    assert check_bridge_key("iorthand/sim1/sensor/vital") is channels.SENSOR_VITAL
    for key, why in [("iorthand/sim1/cmd/twist", "cmd/"), ("iorthand/sim1/cmd/stop", "cmd/"),
                     ("iorthand/sim1/control/arm", "control/"), ("iorthand/sim1/alive/edge", "alive/"),
                     ("iorthand/sim1/state/robot", "written only by"),
                     ("iorthand/sim1-replay/sensor/vital", "reserved for replayed"),
                     ("iorthand/_twin/sensor/vital", "not a robot key")]:
        with pytest.raises(MappingError, match=why):
            check_bridge_key(key)


def _heart(**changes: Any) -> InRoute:
    kw: dict[str, Any] = {"fixed": {"name": "heart_rate", "unit": "bpm"}, "bounds": {"value": [20, 250]},
                          "robots": ("sim1",), **changes}
    route = compile_route("hr", "in", "iorthand/{robot}/sensor/vital", "site/{robot}/hr", **kw)
    assert isinstance(route, InRoute)
    return route


def test_a_json_reading_becomes_a_sensor_reading() -> None:
    route = _heart()
    msg = route.reading(b'{"value": 72, "source": "polar-h10"}', NOW)
    assert isinstance(msg, SensorReading)
    assert (msg.name, msg.value, msg.unit, msg.source, msg.t) == ("heart_rate", 72.0, "bpm", "polar-h10", NOW)
    timed = route.reading(json.dumps({"value": 71.5, "unit": "bpm", "source": "s", "t": NOW - 10**9}).encode(), NOW)
    assert timed.t == NOW - 10**9 and timed.value == 71.5
    assert route.key_for("site/sim1/hr") == "iorthand/sim1/sensor/vital"
    assert route.required == ["value", "source"]


@pytest.mark.parametrize(("payload", "why"), [
    (b"72 bpm", "not JSON"),
    (b"\xff\xfe{}", "not UTF-8"),
    (b'{"value": NaN, "source": "s"}', "NaN is not a number JSON allows"),
    (b'{"value": Infinity, "source": "s"}', "Infinity"),
    (b'{"value": 1e400, "source": "s"}', "not a finite number"),
    (b"[72]", "expected a JSON object"),
    (b'{"value": "72", "source": "s"}', "SensorReading.value: expected float, got str"),
    (b'{"value": true, "source": "s"}', "SensorReading.value: expected float, got bool"),
    (b'{"value": 400, "source": "s"}', r"value 400 is outside the plausible range \[20, 250\]"),
    (b'{"value": 19.9, "source": "s"}', "outside the plausible range"),
    (b'{"value": 72, "source": "s", "unit": "Hz"}', "unit 'Hz' differs from the mapping's 'bpm'"),
    (b'{"value": 72, "source": "s", "deadman": true}', "unknown field 'deadman'"),
    (b'{"value": 72, "source": "s", "seq": 5}', "unknown field 'seq'"),
    (b'{"value": 72}', "missing field 'source'"),
    (b'{"value": 72, "source": "' + b"x" * 65 + b'"}', "SensorReading.source: length 65 exceeds 64"),
    (b'{"value": 72, "source": "s", "t": 1.5}', "t must be an integer"),
    (b'{"value": 72, "source": "s", "t": 1}', "s old"),
    (b'{"value": 72, "source": "s", "t": 1700000100000000000}', "in the future"),
    (b'{"value": ' + b"9" * 30 + b', "source": "s"}', "SensorReading.value"),
    (b"[" * 5000 + b"]" * 5000, "exceeds the mapping's limit"),
    (b"{" * 1000, "not JSON|nested"),
])
def test_malformed_readings_are_refused_with_the_reason(payload: bytes, why: str) -> None:
    with pytest.raises(Refused, match=why):
        _heart().reading(payload, NOW)


def test_retained_and_foreign_robots_are_refused() -> None:
    route = _heart()
    with pytest.raises(Refused, match="retained"):
        route.reading(b'{"value": 72, "source": "s"}', NOW, retained=True)
    timed = json.dumps({"value": 72, "source": "s", "t": NOW - 10**9}).encode()  # a retained copy needs its time
    assert _heart(accept_retained=True).reading(timed, NOW, retained=True).value == 72
    with pytest.raises(Refused, match="not one of the bridge's robots"):
        route.key_for("site/sim2/hr")
    with pytest.raises(Refused, match="robot id 'Not A Robot' is invalid"):
        route.key_for("site/Not A Robot/hr")
    with pytest.raises(Refused, match="reserved for replayed"):
        _heart(robots=()).key_for("site/sim1-replay/hr")


def test_out_routes_subscribe_only_the_robots_bridged() -> None:
    every = compile_route("s", "out", "iorthand/{robot}/state/robot", "site/{robot}/state")
    assert isinstance(every, OutRoute) and every.exprs == ["iorthand/*/state/robot"]
    assert every.topic_for("iorthand/sim1-replay/state/robot") == "site/sim1-replay/state"  # named as a replay
    some = compile_route("s", "out", "iorthand/{robot}/state/robot", "site/{robot}/state", robots=["b", "a"])
    assert isinstance(some, OutRoute) and some.exprs == ["iorthand/a/state/robot", "iorthand/b/state/robot"]
    with pytest.raises(Refused, match="not one of the bridge's robots"):
        some.topic_for("iorthand/c/state/robot")


def test_out_json_carries_the_decoded_fields() -> None:
    state = RobotState(tcp_pose=[0.3, 0.01, 0.2, 3.14, 0.0, 0.0], mode="sim", cmd_seq=4).stamp(9, NOW)
    data = json.loads(to_json(RobotState.decode(state.encode())))
    assert data["v"] == 1 and data["seq"] == 9 and data["t"] == NOW
    assert data["tcp_pose"] == [0.3, 0.01, 0.2, 3.14, 0.0, 0.0] and data["mode"] == "sim" and data["cmd_seq"] == 4
    # Every field but the signature, which signs the bytes on Zenoh and means nothing in a JSON copy.
    assert set(data) == {"v", *(f.name for f in dataclasses.fields(RobotState))} - {"mac"}
    with pytest.raises(TypeError):  # bytes: why video is refused at configuration time
        to_json(VideoFrame(width=1, height=1, data=b"\xff").stamp(1))


def test_the_throttle_sends_at_most_max_hz_and_always_the_newest() -> None:
    th = LatestThrottle(10.0)
    sent: list[tuple[float, int]] = []
    for i in range(125):  # 125 Hz for one second
        now = i / 125
        if (item := th.offer(i, now)) is not None:
            sent.append((now, item))
        if (item := th.poll(now)) is not None:
            sent.append((now, item))
    while th.due() is not None:
        now = th.due()
        sent.append((now, th.poll(now)))
    times = [t for t, _ in sent]
    assert all(b - a >= 0.1 - 1e-9 for a, b in itertools.pairwise(times)), times
    assert 10 <= len(sent) <= 11 and sent[-1][1] == 124  # the last state is not lost
    assert th.superseded == 125 - len(sent)
    limiter = RateLimits(2.0, max_keys=4)
    assert [limiter.take("a", t) for t in (0.0, 0.2, 0.49, 0.5, 0.9, 1.0)] == [True, False, False, True, False, True]


# ------------------------------------------------------------------------------------------------ configuration


def test_the_example_configuration_loads() -> None:
    cfg = load(ROOT / "configs" / "bridge-mqtt.yaml", BridgeConfig)
    routes = {r.name: r for r in cfg.routes()}
    assert isinstance(routes["robot-state"], OutRoute) and routes["robot-state"].max_hz < 125
    assert isinstance(routes["heart-rate"], InRoute) and routes["heart-rate"].message is SensorReading


@pytest.mark.parametrize(("key", "why"), [
    ("iorthand/{robot}/cmd/twist", "operator commands"),
    ("iorthand/{robot}/control/acquire", "control queries"),
    ("iorthand/{robot}/alive/operator", "liveliness space"),
])
def test_a_configuration_mapping_into_commands_or_control_is_refused(key: str, why: str) -> None:
    data = {"mappings": [STATE_OUT, {**HEART, "name": "evil", "key": key}]}
    with pytest.raises(ConfigError, match=why) as err:
        from_dict(data, BridgeConfig, source="bridge.yaml")
    assert err.value.source == "bridge.yaml" and err.value.key == "mappings[1]"
    assert "mapping 'evil'" in str(err.value)
    # A configuration built in code skips the loader's checks: the bridge refuses it when it is made.
    cfg = BridgeConfig(mappings=[MappingConfig(**{**HEART, "name": "evil", "key": key})])
    with pytest.raises(MappingError, match=f"mapping 'evil'.*{why}"):
        MqttBridge(cfg)


def test_the_command_refuses_a_bad_configuration(tmp_path: Path) -> None:
    bad = tmp_path / "bridge.yaml"
    bad.write_text(json.dumps({"mappings": [{**HEART, "name": "evil", "key": "iorthand/{robot}/control/arm"}]}))
    run = subprocess.run([sys.executable, "-m", "iorthand_cloud.bridge.cli", "bridge", "mqtt", "--config", str(bad)],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2, run.stderr
    assert "mappings[0]: mapping 'evil'" in run.stderr and "control/" in run.stderr


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("pki")
    certs.init_ca(d)
    certs.issue(d, "router", hosts=["127.0.0.1"])  # the broker's certificate (the only serverAuth role)
    certs.issue(d, "bridge")  # the bridge's client certificate: a role of its own
    (d / "bridge.password").write_text("s3cret\n")
    return d


def _tls_mqtt(pki: Path, port: int = 8883, password_file: str = "bridge.password", **tls: Any) -> MqttConfig:
    data = {"host": "127.0.0.1", "port": port, "username": "bridge", "password_file": str(pki / password_file),
            "tls": {"ca": str(pki / "ca.pem"), "certificate": str(pki / "bridge.pem"),
                    "private_key": str(pki / "bridge.key"), **tls}}
    return from_dict(data, MqttConfig, source="<test>")


def test_credentials_and_tls_reach_paho(pki: Path) -> None:
    from iorthand_cloud.bridge.mqtt import read_password

    cfg = _tls_mqtt(pki)
    client = make_client(cfg, read_password(cfg.password_file))
    assert client._username == b"bridge" and client._password == b"s3cret"  # the newline is not the password's
    ctx = client._ssl_context
    assert isinstance(ctx, ssl.SSLContext) and ctx.verify_mode == ssl.CERT_REQUIRED and ctx.check_hostname
    assert make_client(_tls_mqtt(pki, verify_name=False))._ssl_context.check_hostname is False
    assert cfg.warnings() == []
    with pytest.raises(ConfigError, match=r"tls\.ca: no such file"):
        make_client(_tls_mqtt(pki, ca=str(pki / "nope.pem")))
    with pytest.raises(ConfigError, match="password_file: cannot read"):
        read_password(pki / "nope.password")
    with pytest.raises(ConfigError, match="certificate and private_key go together"):
        _tls_mqtt(pki, private_key=None)
    with pytest.raises(ConfigError, match="needs a password_file"):
        from_dict({"username": "bridge"}, MqttConfig)
    plain = from_dict({"host": "broker.example.org", "username": "u", "password_file": "/p"}, MqttConfig)
    assert [k for k, _ in plain.warnings()] == ["mqtt.tls"]  # a password in clear across the network


def test_the_acl_lets_the_bridge_write_only_sensor_readings() -> None:
    dep = acl.Deployment(robots=["r1"], operators={"alice": ["r1"]}, bridge=True)
    dep.check()
    ac = acl.acl_rules(dep)
    rules = {r["id"]: r for r in ac["rules"]}
    mine = [rules[rid] for p in ac["policies"] if "bridge" in p["subjects"] for rid in p["rules"]]
    puts = [ke for r in mine if "ingress" in r["flows"]
            and set(r["messages"]) & {"put", "delete", "declare_queryable", "reply", "query", "liveliness_token"}
            for ke in r["key_exprs"]]
    assert puts == ["iorthand/r1/sensor/**"]
    assert "bridge" not in {s["id"] for s in acl.acl_rules(acl.Deployment(robots=["r1"]))["subjects"]}
    certs.check_name("bridge")
    with pytest.raises(ValueError, match="bridge: true needs robots"):
        acl.Deployment(bridge=True).check()


# ------------------------------------------------------------------------------------------------ real broker


class Mosquitto:
    def __init__(self, workdir: Path, extra: str = "", port: int | None = None) -> None:
        self.port = port or free_port()
        conf = workdir / f"mosquitto-{self.port}.conf"
        # As root, mosquitto would switch to its own user and could not read the test's 0600 key files.
        user = "user root\n" if os.geteuid() == 0 else ""
        conf.write_text(f"listener {self.port} 127.0.0.1\n{extra}persistence false\n{user}log_dest stderr\n")
        self.log = (workdir / f"mosquitto-{self.port}.log").open("w")
        self.proc = subprocess.Popen([MOSQUITTO, "-c", str(conf)], stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 15
        while True:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                    return
            except OSError:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    self.stop()
                    why = (workdir / f"mosquitto-{self.port}.log").read_text()
                    raise RuntimeError(f"mosquitto did not start: {why}") from None
                time.sleep(0.05)

    def stop(self) -> None:
        stop_process(self.proc)
        self.log.close()


@pytest.fixture
def broker_factory(tmp_path: Path) -> Iterator[Callable[..., Mosquitto]]:
    if MOSQUITTO is None:
        pytest.skip("Debian's mosquitto is not installed (apt-get install -y mosquitto)")
    started: list[Mosquitto] = []

    def make(extra: str = "allow_anonymous true\n") -> Mosquitto:
        b = Mosquitto(tmp_path, extra)
        started.append(b)
        return b

    yield make
    for b in started:
        b.stop()


class Probe:
    """A paho client of the test: what it receives, queued; publishing waits for the broker's ack (QoS 1)."""

    def __init__(self, port: int, subscribe: str | None = None, **tls: Any) -> None:
        self.messages: queue.Queue[mqtt.MQTTMessage] = queue.Queue()
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"probe-{port}-{time.monotonic_ns()}")
        if tls:
            self.client.username_pw_set(tls.pop("username"), tls.pop("password"))
            self.client.tls_set(**tls)
        self.client.on_message = lambda c, u, m: self.messages.put(m)
        ready = queue.Queue()
        self.client.on_subscribe = lambda *a: ready.put(True)
        self.client.on_connect = lambda c, u, f, rc, p: c.subscribe(subscribe, 1) if subscribe else ready.put(True)
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()
        ready.get(timeout=10)

    def publish(self, topic: str, payload: bytes | str, retain: bool = False) -> None:
        self.client.publish(topic, payload, qos=1, retain=retain).wait_for_publish(5)

    def received(self, timeout: float = 0.0, count: int | None = None) -> list[mqtt.MQTTMessage]:
        """What arrives within ``timeout`` (or until ``count`` messages have)."""
        out: list[mqtt.MQTTMessage] = []
        deadline = time.monotonic() + timeout
        while count is None or len(out) < count:
            try:
                out.append(self.messages.get(timeout=max(0.0, deadline - time.monotonic())))
            except queue.Empty:
                return out
        return out

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


@pytest.fixture
def bridge_factory(router_endpoint: str) -> Iterator[Callable[..., MqttBridge]]:
    bridges: list[MqttBridge] = []

    def make(port: int, mappings: list[dict[str, Any]], mqtt_cfg: dict[str, Any] | None = None,
             connect: bool = True, **extra: Any) -> MqttBridge:
        data = {"zenoh": {"mode": "client", "connect": [router_endpoint]},
                "mqtt": {"host": "127.0.0.1", "port": port, "client_id": f"bridge-{len(bridges)}", **(mqtt_cfg or {})},
                "robots": ROBOTS, "mappings": mappings, **extra}
        bridge = MqttBridge(from_dict(data, BridgeConfig, source="<test>"))
        bridges.append(bridge)
        bridge.start()
        if connect:
            assert bridge.wait_connected(10), bridge.last_error
        return bridge

    yield make
    for b in bridges:
        b.shutdown()


class ZenohSink:
    def __init__(self, session: Any, key: str) -> None:
        self.samples: queue.Queue[tuple[str, bytes]] = queue.Queue()
        self.sub = session.declare_subscriber(key, lambda s: self.samples.put((str(s.key_expr), s.payload.to_bytes())))

    def reached_from(self, session: Any, probe_key: str, timeout: float = 10.0) -> None:
        """Put on ``probe_key`` (one the sink takes) from ``session`` until one arrives, then forget them: a put made
        before the sink's subscription has reached that session through the router is lost (a loaded CI run)."""
        deadline = time.monotonic() + timeout
        while not self.all(wait=0.1):
            assert time.monotonic() < deadline, f"the sink's subscription did not reach the session in {timeout} s"
            session.put(probe_key, b"")
        self.all(wait=0.2)

    def all(self, wait: float = 0.0) -> list[tuple[str, bytes]]:
        time.sleep(wait)
        out = []
        while not self.samples.empty():
            out.append(self.samples.get())
        return out


def _deliver(probe: Probe, topic: str, payload: str, sink: ZenohSink, timeout: float = 10.0) -> list[tuple[str, bytes]]:
    """Publish until the bridge's put reaches ``sink`` (its Zenoh publisher may be declared after our first try)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        probe.publish(topic, payload)
        if got := sink.all(wait=0.3):
            return got
    raise AssertionError(f"nothing reached Zenoh from {topic} within {timeout} s")


def test_robot_state_goes_out_as_json_at_most_max_hz(broker_factory, bridge_factory, session_factory) -> None:
    broker = broker_factory()
    bridge = bridge_factory(broker.port, [STATE_OUT, {"name": "level", "direction": "out", "qos": 1,
                                                      "key": "iorthand/{robot}/state/force_level",
                                                      "topic": "site/{robot}/force_level"}])
    probe = Probe(broker.port, "site/#")
    pub = session_factory().declare_publisher("iorthand/sim1/state/robot")

    def state(seq: int) -> bytes:
        return RobotState(tcp_pose=[0.3 + seq * 1e-4, 0.01, 0.2, 3.14, 0.0, 0.0], mode="sim", cmd_seq=seq).stamp(seq).encode()

    wait_until(lambda: pub.put(state(1)) or not probe.messages.empty(), timeout=10, message="the first state on MQTT")
    probe.received(0.3)
    start = time.monotonic()
    seq = 1
    while time.monotonic() - start < 1.5:  # a 100 Hz stream, as the edge's 125 Hz
        seq += 1
        pub.put(state(seq))
        time.sleep(0.01)
    elapsed = time.monotonic() - start
    got = probe.received(1.0)
    assert 2 <= len(got) <= elapsed * 10 + 2, (len(got), elapsed)  # max_hz 10 of ~100: the broker is not flooded
    assert {m.topic for m in got} == {"site/sim1/robot_state"}
    last = json.loads(got[-1].payload)
    assert last["seq"] == seq and last["cmd_seq"] == seq and last["mode"] == "sim"  # the newest state is never lost
    assert last["tcp_pose"] == pytest.approx([0.3 + seq * 1e-4, 0.01, 0.2, 3.14, 0.0, 0.0]) and last["v"] == 1
    assert bridge.stats["robot-state"].rate_limited > 0 and bridge.stats["robot-state"].refused == 0
    # Another key, another topic; an undecodable sample is refused, counted and never published.
    level = session_factory().declare_publisher("iorthand/sim1/state/force_level")
    level.put(b"\xc1 not msgpack")
    wait_until(lambda: bridge.stats["level"].refused == 1, message="the garbage refused")
    level.put(ForceLevelState(level=2, stale=False, value=8.5).stamp(3).encode())
    msg = probe.received(5.0, count=1) + probe.received(0.3)
    assert [m.topic for m in msg] == ["site/sim1/force_level"]
    assert json.loads(msg[0].payload)["level"] == 2 and json.loads(msg[0].payload)["value"] == 8.5
    probe.close()


def test_a_vital_sign_on_mqtt_arrives_on_zenoh_as_a_sensor_reading(broker_factory, bridge_factory, session_factory,
                                                                   operator_factory) -> None:
    broker = broker_factory()
    bridge = bridge_factory(broker.port, [HEART])
    sink = ZenohSink(session_factory(), "iorthand/**")
    console = operator_factory()  # what the terminal console and the web page show it from
    probe = Probe(broker.port)
    got = _deliver(probe, "site/sim1/vitals/heart_rate", json.dumps({"value": 72, "unit": "bpm"}), sink)
    key, payload = got[0]
    assert key == "iorthand/sim1/sensor/vital" == keys.RobotKeys("sim1").key(channels.SENSOR_VITAL.suffix)
    reading = SensorReading.decode(payload)
    assert (reading.name, reading.value, reading.unit, reading.source) == ("heart_rate", 72.0, "bpm", "monitor")
    assert reading.seq >= 1 and abs(reading.t - time.time_ns()) < 10e9
    probe.publish("site/sim1/vitals/heart_rate", json.dumps({"value": 80}))
    wait_until(lambda: bool(got := sink.all()) and SensorReading.decode(got[-1][1]).value == 80.0, message="80 bpm")
    assert bridge.stats["heart-rate"].refused == 0 and bridge.blocked == 0
    wait_until(lambda: "heart_rate" in console.vitals and console.vitals["heart_rate"][0].value == 80.0,
               message="the vital sign on the operator's console")
    assert vitals_line(console.vitals, time.monotonic()) == "heart_rate 80 bpm"
    probe.close()


def test_the_console_line_says_how_old_a_vital_sign_is() -> None:
    hr = SensorReading(name="heart_rate", value=72.0, unit="bpm")
    spo2 = SensorReading(name="spo2", value=98.0, unit="%")
    line = vitals_line({"spo2": (spo2, 100.0), "heart_rate": (hr, 90.0)}, now=101.0)
    assert line == "heart_rate 72 bpm (11 s old) · spo2 98 %"
    assert vitals_line({}, now=1.0) == ""


BAD = [
    ("site/sim1/vitals/heart_rate", "72 bpm", "not JSON"),
    ("site/sim1/vitals/heart_rate", '{"value": NaN}', "NaN"),
    ("site/sim1/vitals/heart_rate", '{"value": 1e999}', "not a finite number"),
    ("site/sim1/vitals/heart_rate", "[72]", "expected a JSON object"),
    ("site/sim1/vitals/heart_rate", '{"value": "72"}', "expected float, got str"),
    ("site/sim1/vitals/heart_rate", '{"value": 400}', "plausible range"),
    ("site/sim1/vitals/heart_rate", '{"value": 72, "unit": "Hz"}', "differs from the mapping's 'bpm'"),
    ("site/sim1/vitals/heart_rate", '{"value": 72, "linear": [1, 0, 0]}', "unknown field 'linear'"),
    ("site/Sim 1/vitals/heart_rate", '{"value": 72}', "robot id 'Sim 1' is invalid"),
]


def test_malformed_mqtt_input_is_refused_counted_and_logged(broker_factory, bridge_factory, session_factory,
                                                             caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="iorthand.bridge")
    broker = broker_factory()
    bridge = bridge_factory(broker.port, [HEART])
    sink = ZenohSink(session_factory(), "iorthand/**")
    probe = Probe(broker.port)
    _deliver(probe, "site/sim1/vitals/heart_rate", '{"value": 60}', sink)  # the path works
    for topic, payload, _ in BAD:
        probe.publish(topic, payload)
    probe.publish("site/sim1/vitals/heart_rate", '{"value": 61}')  # after them, in order (QoS 1, one topic)
    wait_until(lambda: bridge.stats["heart-rate"].refused == len(BAD), message=f"{len(BAD)} refusals")
    time.sleep(0.3)
    values = [SensorReading.decode(p).value for _, p in sink.all()]
    assert values[-1] == 61.0 and set(values) <= {60.0, 61.0}  # nothing refused was published
    assert bridge.stats["heart-rate"].last_refusal.endswith(BAD[-1][2] + ": expected 1-64 characters of [a-z0-9_-]")
    first = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert first and BAD[0][2] in first[0] and "mapping 'heart-rate'" in first[0]  # the reason is in the log
    probe.close()


def test_the_run_time_check_blocks_a_key_the_configuration_check_missed(broker_factory, router_endpoint: str,
                                                                         session_factory) -> None:
    """Defence in depth: even if a route pointing at cmd/ got past the configuration (a bug), nothing is put."""
    broker = broker_factory()
    cfg = from_dict({"mqtt": {"port": broker.port}, "robots": ROBOTS, "mappings": [HEART]}, BridgeConfig,
                    source="<test>")
    sink = ZenohSink(session_factory(), "iorthand/**")
    rogue = MqttBridge(cfg, session=session_factory())
    route = rogue.routes[0]
    assert isinstance(route, InRoute)
    twist = dataclasses.replace(channels.SENSOR_VITAL, suffix=channels.CMD_TWIST.suffix)  # what a bug could make
    rogue.routes = [dataclasses.replace(route, key=KeyTemplate("iorthand/{robot}/cmd/twist", None, twist))]
    rogue.start()
    try:
        assert rogue.wait_connected(10), rogue.last_error
        probe = Probe(broker.port)
        deadline = time.monotonic() + 5
        while rogue.blocked == 0 and time.monotonic() < deadline:
            probe.publish("site/sim1/vitals/heart_rate", '{"value": 72}')
            time.sleep(0.2)
        assert rogue.blocked >= 1 and rogue.stats["heart-rate"].forwarded == 0
        assert sink.all(wait=0.3) == []  # nothing reached iorthand/sim1/cmd/twist (or anywhere)
        probe.close()
    finally:
        rogue.shutdown()


def test_the_recorder_records_the_vital_sign(broker_factory, bridge_factory, session_factory, router_endpoint: str,
                                             tmp_path: Path) -> None:
    from iorthand_cloud.recorder import client
    from iorthand_cloud.recorder.config import RecorderConfig
    from iorthand_cloud.recorder.reader import iter_records
    from iorthand_cloud.recorder.service import RecorderService

    rec = RecorderService(from_dict({"zenoh": {"mode": "client", "connect": [router_endpoint]},
                                     "output_dir": str(tmp_path / "rec"), "fsync": False}, RecorderConfig))
    rec.start()
    try:
        broker = broker_factory()
        bridge_factory(broker.port, [HEART])
        s = session_factory()
        assert client.start(s, session_id="vitals").ok
        probe = Probe(broker.port)
        _deliver(probe, "site/sim1/vitals/heart_rate", '{"value": 66}', ZenohSink(s, "iorthand/*/sensor/vital"))
        wait_until(lambda: rec.status.messages >= 1, message="the reading recorded")
        assert client.stop(s).ok
        probe.close()
    finally:
        rec.shutdown()
    vital = [r for r in iter_records(tmp_path / "rec" / "vitals") if r.key == "iorthand/sim1/sensor/vital"]
    assert vital and not vital[0].malformed and SensorReading.decode(vital[0].data).value == 66.0


def test_tls_broker_with_client_certificate_and_password(broker_factory, bridge_factory, session_factory,
                                                         pki: Path) -> None:
    if MOSQUITTO_PASSWD is None:
        pytest.skip("mosquitto_passwd is not installed (Debian's mosquitto package)")
    passwords = pki / "mosquitto.passwd"
    subprocess.run([MOSQUITTO_PASSWD, "-c", "-b", str(passwords), "bridge", "s3cret"], check=True, capture_output=True)
    os.chmod(passwords, 0o600)
    broker = broker_factory(
        f"allow_anonymous false\npassword_file {passwords}\ncafile {pki / 'ca.pem'}\ncertfile {pki / 'router.pem'}\n"
        f"keyfile {pki / 'router.key'}\nrequire_certificate true\n")
    tls = {"username": "bridge", "password_file": str(pki / "bridge.password"),
           "tls": {"ca": str(pki / "ca.pem"), "certificate": str(pki / "bridge.pem"), "private_key": str(pki / "bridge.key")}}
    bridge_factory(broker.port, [HEART], tls)
    sink = ZenohSink(session_factory(), "iorthand/**")
    probe = Probe(broker.port, username="bridge", password="s3cret", ca_certs=str(pki / "ca.pem"),
                  certfile=str(pki / "bridge.pem"), keyfile=str(pki / "bridge.key"))
    got = _deliver(probe, "site/sim1/vitals/heart_rate", '{"value": 90}', sink)
    assert SensorReading.decode(got[0][1]).value == 90.0
    probe.close()
    # The same broker refuses a wrong password, and the bridge says why.
    (pki / "wrong.password").write_text("guess\n")
    wrong = bridge_factory(broker.port, [HEART], {**tls, "password_file": str(pki / "wrong.password")}, connect=False)
    wait_until(lambda: bool(wrong.last_error), timeout=10, message="the broker's refusal")
    assert not wrong.connected.is_set() and "refused the connection" in wrong.last_error
