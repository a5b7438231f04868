"""``iorthand bridge mqtt`` against a peer of a shared broker (a hospital's IoT broker has many devices on it): floods
over many robots, hostile JSON, retained copies of unknown age, and the broker going away while robot state flows.
Through a real Zenoh router and Debian's mosquitto, as tests/test_bridge_mqtt.py (whose fixtures these use)."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import paho.mqtt.client as mqtt
import pytest
import zenoh

from iorthand.config import ConfigError, from_dict
from iorthand.protocol import RobotState, SensorReading
from iorthand_cloud.bridge.config import BridgeConfig, MappingConfig
from iorthand_cloud.bridge.mapping import PUBLISH_OVERHEAD, InRoute, MappingError, RateLimits, Refused, to_json
from iorthand_cloud.bridge.mqtt import MAX_KEYS, BrokerNumbering, MqttBridge
from tests.conftest import wait_until
from tests.test_bridge_mqtt import (  # noqa: F401  (fixtures, found by name)
    HEART,
    NOW,
    STATE_OUT,
    Mosquitto,
    Probe,
    ZenohSink,
    _deliver,
    _heart,
    bridge_factory,
    broker_factory,
)


def _mqtt_message(topic: str, payload: bytes) -> mqtt.MQTTMessage:
    """A message as paho hands it to the bridge (what the broker delivered), for the bridge's own handler."""
    message = mqtt.MQTTMessage(topic=topic.encode())
    message.payload = payload
    return message


def _bridge(session: Any, clock: Callable[[], float], robots: tuple[str, ...] = ("sim1", "sim2"),
            **heart: Any) -> tuple[MqttBridge, InRoute]:
    """A bridge of HEART for ``robots`` on a real Zenoh session, without a broker: messages go to its handler."""
    bridge = MqttBridge(from_dict({"robots": list(robots), "mappings": [{**HEART, **heart}]}, BridgeConfig,
                                  source="<test>"), session=session, clock=clock)
    route = bridge.routes[0]
    assert isinstance(route, InRoute)
    return bridge, route


def test_a_flood_over_more_keys_than_the_limits_track_keeps_every_keys_rate_limit() -> None:
    """Per-robot limits forgotten least-recently-used let 300 robots in turn reset each other's: every message
    passed (900 of 900 at max_hz 1 within one window, where 300 were due). A limit is forgotten only once its window
    has passed, and a new key while ``max_keys`` are within theirs is refused, like an excess item."""
    limits = RateLimits(1.0, MAX_KEYS)
    keys = [f"r{i}" for i in range(MAX_KEYS + 44)]
    passed = [k for _ in range(3) for k in keys if limits.take(k, 100.0)]  # within one window
    assert passed == keys[:MAX_KEYS] and len(limits) == MAX_KEYS
    # The window has passed: each of those keys has its turn again; at most MAX_KEYS a window, still
    assert [k for k in keys if limits.take(k, 101.0)] == keys[:MAX_KEYS]


def test_an_in_mapping_whose_topic_chooses_the_robot_needs_the_robots_named() -> None:
    """With ``robots: []`` an 'in' mapping took any valid robot id an MQTT client put in the topic: 256 invented
    robots held every rate slot (a real device's readings were then dropped as over the rate), and evicted the real
    device's sequence counter, whose numbering started again at 1 (a "reset" in the recording, its numbers reused).
    The bridge now serves the robots its configuration names."""
    with pytest.raises(ConfigError, match=r"mapping 'heart-rate' takes the robot from the MQTT topic.*name the robots"):
        from_dict({"mappings": [HEART]}, BridgeConfig, source="<test>")
    with pytest.raises(MappingError, match="name the robots"):
        MqttBridge(BridgeConfig(mappings=[MappingConfig(**HEART)]))  # built in code, past the loader
    with pytest.raises(ConfigError, match=f"robots: {MAX_KEYS + 1} named, at most {MAX_KEYS}"):
        from_dict({"robots": [f"r{i}" for i in range(MAX_KEYS + 1)], "mappings": [HEART]}, BridgeConfig)
    # A mapping naming its robot in the key, and 'out' mappings (the robots' own streams), need no list.
    one = {**HEART, "key": "iorthand/sim1/sensor/vital", "topic": "ward3/bed2/heart_rate"}
    assert len(from_dict({"mappings": [one, STATE_OUT]}, BridgeConfig).routes()) == 2


def test_readings_for_robots_the_bridge_does_not_serve_cost_a_real_device_nothing(session_factory) -> None:
    """300 invented robots between a real device's readings: each refused by its id, before any rate slot, sequence
    counter or publisher is made for it; the device's readings all pass, numbered 1, 2, 3."""
    now = [100.0]
    session = session_factory()
    bridge, route = _bridge(session, lambda: now[0], robots=("sim1",), max_hz=1.0)
    sink = ZenohSink(session_factory(), "iorthand/*/sensor/vital")
    sink.reached_from(session, "iorthand/probe/sensor/vital")
    for _ in range(3):
        bridge._on_mqtt(route, None, None, _mqtt_message("site/sim1/vitals/heart_rate", b'{"value": 72}'))
        for i in range(MAX_KEYS + 44):
            bridge._on_mqtt(route, None, None, _mqtt_message(f"site/r{i}/vitals/heart_rate", b'{"value": 72}'))
        now[0] += 1.0
    stats = bridge.stats["heart-rate"]
    assert stats.forwarded == 3 and stats.rate_limited == 0 and stats.refused == 3 * (MAX_KEYS + 44)
    assert "not one of the bridge's robots" in stats.last_refusal
    assert len(bridge._limits["heart-rate"]) == 1 and list(bridge._sequencers) == ["iorthand/sim1/sensor/vital"]
    wait_until(lambda: len(sink.samples.queue) >= 3, message="the three readings on Zenoh")
    assert [(k, SensorReading.decode(p).seq) for k, p in sink.all(wait=0.3)] == [
        ("iorthand/sim1/sensor/vital", 1), ("iorthand/sim1/sensor/vital", 2), ("iorthand/sim1/sensor/vital", 3)]


def test_robot_state_of_more_robots_than_the_bridge_tracks_keeps_every_throttle(broker_factory,  # noqa: F811
                                                                                session_factory) -> None:
    """Out-direction throttles were forgotten least-recently-used: samples of 300 robot keys in turn evicted each
    other's throttle, so every sample went to the broker at once (900 of 900 within one turn of a 0.1 Hz mapping),
    and a real robot's throttle was evicted with the newest state it had waiting, which never went out. A throttle
    is now forgotten only when a new one would do the same (nothing waiting, its turn come), and a new key while
    MAX_KEYS are busy is dropped as over the rate. The clock stands still: one turn lasts the whole flood."""
    broker = broker_factory()
    now = [100.0]
    cfg = from_dict({"mqtt": {"port": broker.port, "client_id": "bridge-throttles"},
                     "mappings": [{**STATE_OUT, "max_hz": 0.1}]}, BridgeConfig, source="<test>")  # every robot
    bridge = MqttBridge(cfg, session=session_factory(), clock=lambda: now[0])
    probe = Probe(broker.port, "site/#")
    bridge.start()
    try:
        assert bridge.wait_connected(10), bridge.last_error
        zenoh_pub = session_factory()
        stats = bridge.stats["robot-state"]

        def put(robot: str, seq: int) -> None:
            state = RobotState(tcp_pose=[0.3, 0.0, 0.2, 3.14, 0.0, 0.0], mode="sim", cmd_seq=seq).stamp(seq)
            zenoh_pub.put(f"iorthand/{robot}/state/robot", state.encode(),
                          congestion_control=zenoh.CongestionControl.BLOCK)

        wait_until(lambda: put("sim1", 1) or stats.forwarded >= 1, timeout=10, message="sim1's first state sent")
        put("sim1", 2)  # within sim1's turn: waits
        wait_until(lambda: any(t.pending is not None for t in bridge._throttles.values()), message="sim1's waiting")
        base = stats.rate_limited
        flood = [f"r{i}" for i in range(MAX_KEYS + 44)]
        for round_ in range(3):
            for robot in flood:
                put(robot, round_)
        # 255 sent, 255 superseded, 255 waiting, 45 x 3 without a slot (before: 900 sent)
        wait_until(lambda: stats.forwarded + stats.rate_limited - base >= 1 + 2 * (MAX_KEYS - 1) + 45 * 3, timeout=20,
                   message="the flood taken")
        time.sleep(0.3)
        assert stats.forwarded == MAX_KEYS and len(bridge._throttles) == MAX_KEYS  # sim1's first, 255 of the flood
        now[0] += 10.0  # the turn has come: what waits goes, sim1's newest state among it
        wait_until(lambda: stats.forwarded >= 2 * MAX_KEYS - 1, message="the waiting states sent")
        sim1 = [json.loads(m.payload)["seq"] for m in probe.received(2.0) if m.topic == "site/sim1/robot_state"]
        assert sim1[-1] == 2 and len(sim1) == 2
    finally:
        probe.close()
        bridge.shutdown()


def test_readings_over_the_rate_are_dropped_before_they_are_parsed(session_factory,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """A flood on one topic cost a JSON parse and a message check per message (19 µs of CPU, 3 µs now)."""
    parsed: list[bytes] = []
    real = InRoute.reading

    def counted(self: InRoute, payload: bytes, now_ns: int, retained: bool = False) -> Any:
        parsed.append(payload)
        return real(self, payload, now_ns, retained)

    monkeypatch.setattr(InRoute, "reading", counted)
    bridge, route = _bridge(session_factory(), lambda: 100.0, max_hz=5.0)
    for _ in range(1000):
        bridge._on_mqtt(route, None, None, _mqtt_message("site/sim1/vitals/heart_rate", b'{"value": 72}'))
    assert bridge.stats["heart-rate"].forwarded == 1 and bridge.stats["heart-rate"].rate_limited == 999
    assert len(parsed) == 1
    # Garbage does not spend a sensor's turn: the valid reading after it still goes.
    bridge.stats["heart-rate"].forwarded = 0
    for payload in (b"72 bpm", b'{"value": 400}', b'{"value": 72}'):
        bridge._on_mqtt(route, None, None, _mqtt_message("site/sim2/vitals/heart_rate", payload))
    assert bridge.stats["heart-rate"].refused == 2 and bridge.stats["heart-rate"].forwarded == 1


def test_a_robot_level_naming_a_reserved_space_is_refused_as_input(session_factory,
                                                                   caplog: pytest.LogCaptureFixture) -> None:
    """``site/_twin/...``: ``_twin`` matches the robot id pattern but names the twin's space. It passed the input
    checks and reached the run-time key check, whose refusal counts a bug (``blocked``) and logs an error per
    message: a peer of the broker could fill the log at its own rate. It is now refused as input, like a bad id."""
    with pytest.raises(Refused, match="not a robot key"):
        _heart(robots=()).key_for("site/_twin/hr")
    caplog.set_level(logging.WARNING, logger="iorthand.bridge")
    bridge, route = _bridge(session_factory(), time.monotonic)
    for _ in range(1000):
        bridge._on_mqtt(route, None, None, _mqtt_message("site/_twin/vitals/heart_rate", b'{"value": 72}'))
    assert bridge.stats["heart-rate"].refused == 1000 and bridge.blocked == 0
    assert len([r for r in caplog.records if r.name == "iorthand.bridge"]) <= 2  # one line per mapping per 5 s


@pytest.mark.parametrize("payload", [
    b'{"value": 400, "value": 72, "source": "s"}',  # a reader that keeps the first sees 400, the bridge sent 72
    b'{"value": 72, "source": "s", "unit": "bpm", "unit": "Hz"}',
    b'{"value": 72, "source": "a", "source": "b"}',
])
def test_a_field_given_twice_is_refused(payload: bytes) -> None:
    with pytest.raises(Refused, match="appears twice"):
        _heart().reading(payload, NOW)


def test_a_retained_reading_without_its_time_is_refused_even_where_retained_copies_are_taken() -> None:
    """With accept_retained, a retained copy without ``t`` was stamped with the time it arrived: a reading of
    any age (the broker keeps it for ever) published as a live one."""
    route = _heart(accept_retained=True)
    with pytest.raises(Refused, match="retained message without t: its age is unknown"):
        route.reading(b'{"value": 72, "source": "s"}', NOW, retained=True)
    with pytest.raises(Refused, match="s old"):
        route.reading(json.dumps({"value": 72, "source": "s", "t": NOW - 61 * 10**9}).encode(), NOW, retained=True)
    fresh = json.dumps({"value": 72, "source": "s", "t": NOW - 10**9}).encode()
    assert route.reading(fresh, NOW, retained=True).value == 72
    assert route.reading(b'{"value": 72, "source": "s"}', NOW).t == NOW  # a live one is stamped when it arrives


def test_retained_readings_on_the_broker_at_start(broker_factory, bridge_factory,  # noqa: F811
                                                  session_factory) -> None:
    """What a bridge (re)starting finds retained on the broker: taken only with accept_retained and a fresh ``t``."""
    broker = broker_factory()
    probe = Probe(broker.port)
    probe.publish("site/sim1/vitals/heart_rate", '{"value": 70}', retain=True)  # no time: of unknown age
    probe.publish("site/sim2/vitals/heart_rate", json.dumps({"value": 71, "t": time.time_ns()}), retain=True)
    probe.publish("site/sim3/vitals/heart_rate", json.dumps({"value": 73, "t": time.time_ns() - 3600 * 10**9}),
                  retain=True)
    sink = ZenohSink(session_factory(), "iorthand/*/sensor/vital")
    bridge = bridge_factory(broker.port, [{**HEART, "accept_retained": True}])
    wait_until(lambda: bridge.stats["heart-rate"].refused == 2 and bridge.stats["heart-rate"].forwarded == 1,
               timeout=10, message="two retained copies refused, one taken")
    got = sink.all(wait=0.3)
    assert [(k, SensorReading.decode(p).value) for k, p in got] == [("iorthand/sim2/sensor/vital", 71.0)]
    probe.close()


def test_robot_state_while_the_broker_is_away_is_not_sent_as_a_backlog(broker_factory, bridge_factory,  # noqa: F811
                                                                       session_factory, tmp_path: Path) -> None:
    """paho queued every QoS 1 message while the broker was away and sent them all when it came back: 52 states
    per topic up to 5 s old after a 5 s outage (counted "dropped" meanwhile). Now the newest of each topic is held
    and sent at the next connection, and the ones it replaced are counted dropped."""
    broker = broker_factory("allow_anonymous true\nlog_type all\n")  # the broker logs each PUBLISH it receives
    port = broker.port
    out = {"name": "robot-state", "direction": "out", "key": "iorthand/{robot}/state/robot",
           "topic": "site/{robot}/robot_state", "qos": 1, "max_hz": 20.0, "retain": True}
    bridge = bridge_factory(port, [out])
    pub = session_factory().declare_publisher("iorthand/sim1/state/robot")

    def state(seq: int) -> bytes:
        return RobotState(tcp_pose=[0.3, 0.0, 0.2, 3.14, 0.0, 0.0], mode="sim", cmd_seq=seq).stamp(seq).encode()

    wait_until(lambda: pub.put(state(1)) or bridge.stats["robot-state"].forwarded >= 1, timeout=10,
               message="the first state on MQTT")
    broker.stop()
    wait_until(lambda: not bridge.connected.is_set(), message="the bridge sees the broker gone")
    last = 0
    for last in range(2, 42):  # 0.8 s at 50 Hz: 16 turns of a 20 Hz mapping
        pub.put(state(last))
        time.sleep(0.02)
    stats = bridge.stats["robot-state"]
    wait_until(lambda: stats.dropped + stats.rate_limited >= 39, message="the states while away counted")
    restarted = Mosquitto(tmp_path, "allow_anonymous true\nlog_type all\n", port=port)  # its log starts anew
    try:
        assert bridge.wait_connected(40), bridge.last_error
        log = tmp_path / f"mosquitto-{port}.log"
        wait_until(lambda: "site/sim1/robot_state" in log.read_text(), message="the held state received")
        time.sleep(0.5)  # anything else the bridge sends now arrives as well
        received = [line for line in log.read_text().splitlines() if "Received PUBLISH from bridge-" in line]
        assert len(received) == 1, received  # the newest alone, not the backlog
        probe = Probe(port, "site/#")  # retained: the one the broker has is the newest state
        msg = probe.received(5.0, count=1)
        assert json.loads(msg[0].payload)["seq"] == last and msg[0].retain
        probe.close()
    finally:
        restarted.stop()


def test_fields_a_newer_sender_adds_are_not_mirrored() -> None:
    """A display-only message decodes without fields this build does not know (``ignored``); its JSON copy carries
    the fields this build checked, never what a sender chose to add."""
    sent = msgpack.unpackb(SensorReading(name="hr", value=72.0, unit="bpm").stamp(3, NOW).encode())
    sent["later_field"] = {"x": [1] * 100}
    msg = SensorReading.decode(msgpack.packb(sent))
    assert msg.ignored == ("later_field",)
    assert json.loads(to_json(msg)) == {"v": 1, "seq": 3, "t": NOW, "name": "hr", "value": 72.0, "unit": "bpm",
                                        "source": ""}


def _padded(size: int) -> bytes:
    """A valid reading of exactly ``size`` bytes (JSON allows the spaces)."""
    head = b'{"value": 72'
    return head + b" " * (size - len(head) - 1) + b"}"


def test_an_mqtt_v5_bridge_tells_the_broker_the_largest_message_it_takes(broker_factory, bridge_factory,  # noqa: F811
                                                                        session_factory, tmp_path: Path) -> None:
    """paho reads a message whole before the bridge's max_payload refuses it: a 16 MB publish cost the bridge process
    ~50 MB at its peak (RSS 112 → 163 MB). Over MQTT v5 the bridge now announces its maximum packet size in CONNECT
    (max_payload, the longest topic of its robots, the headers), and the broker drops a larger message for the
    bridge without sending it (RSS +0.6 MB). The bridge counts it from the broker's numbering of QoS 1 messages."""
    broker = broker_factory("allow_anonymous true\nlog_type all\n")
    bridge = bridge_factory(broker.port, [HEART], {"protocol": "5"}, robots=["sim1"])
    sink = ZenohSink(session_factory(), "iorthand/*/sensor/vital")
    probe = Probe(broker.port)
    _deliver(probe, "site/sim1/vitals/heart_rate", '{"value": 60}', sink)
    stats = bridge.stats["heart-rate"]
    sent = stats.forwarded
    probe.publish("site/sim1/vitals/heart_rate", b"x" * 2**20)  # 1 MB: never sent to the bridge
    wait_until(lambda: probe.publish("site/sim1/vitals/heart_rate", _padded(4096)) or stats.forwarded > sent,
               message="the 4096-byte reading on Zenoh")  # the largest reading it takes still arrives
    assert stats.refused == 0  # before: refused, once read whole
    assert bridge.max_packet == 4096 + len("site/sim1/vitals/heart_rate") + PUBLISH_OVERHEAD
    assert bridge.client is not None and bridge.client._connect_properties.MaximumPacketSize == bridge.max_packet
    assert bridge.numbering.skipped == 1
    assert "1 QoS 1 messages the broker did not deliver" in bridge.summary()
    log = (tmp_path / f"mosquitto-{broker.port}.log").read_text()
    assert f"Dropping too large outgoing PUBLISH for {bridge.cfg.mqtt.client_id}" in log
    probe.close()


def test_an_mqtt_3_bridge_says_which_broker_limit_protects_it(broker_factory, bridge_factory,  # noqa: F811
                                                              caplog: pytest.LogCaptureFixture) -> None:
    """MQTT 3.1.1 has no way to announce a size: the start log names the broker's setting and its value, and with
    that setting the broker keeps a 1 MB message from the bridge."""
    caplog.set_level(logging.WARNING, logger="iorthand.bridge")
    cfg = from_dict({"robots": ["sim1"], "mappings": [HEART, {**HEART, "name": "spo2", "max_payload": 512,
                                                              "topic": "site/{robot}/vitals/spo2"}]}, BridgeConfig)
    assert [k for k, _ in cfg.warnings()] == ["mqtt.protocol"] and 'message_size_limit 4096"' in cfg.warnings()[0][1]
    cfg.mqtt.protocol = "5"
    assert cfg.warnings() == []
    broker = broker_factory("allow_anonymous true\nmessage_size_limit 4096\n")
    bridge = bridge_factory(broker.port, [HEART], robots=["sim1"])
    assert any('"message_size_limit 4096"' in r.getMessage() for r in caplog.records)
    probe = Probe(broker.port)
    stats = bridge.stats["heart-rate"]

    def deliver_largest(sent: int) -> None:
        wait_until(lambda: probe.publish("site/sim1/vitals/heart_rate", _padded(4096)) or stats.forwarded > sent,
                   message="the 4096-byte reading")

    deliver_largest(0)  # the bridge's subscription is in place
    probe.publish("site/sim1/vitals/heart_rate", b"x" * 2**20)
    deliver_largest(1)
    assert stats.refused == 0
    probe.close()


def test_the_broker_numbering_counts_what_it_withheld() -> None:
    numbering = BrokerNumbering()
    assert [numbering.observe(mid, 1, False) for mid in (1, 2, 4, 7)] == [0, 0, 1, 2]
    assert numbering.observe(7, 1, True) == 0 and numbering.observe(0, 0, False) == 0  # resent; QoS 0 has no id
    numbering.restart()
    assert numbering.observe(2, 1, False) == 1  # a new session starts at 1
    for mid in range(3, 65536):
        numbering.observe(mid, 1, False)
    assert numbering.observe(1, 1, False) == 0 and numbering.observe(3, 1, False) == 1  # 65535 wraps to 1
    assert numbering.observe(40000, 1, False) == 0  # a numbering of its own, not 39996 messages withheld
    assert numbering.skipped == 5
