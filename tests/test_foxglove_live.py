"""The twin's live Foxglove view: a websocket client speaking the Foxglove WebSocket protocol connects to the
twin's foxglove-sdk server, subscribes to channels and receives messages that decode with the schemas the
server advertised, while a full-rate synthetic robot publishes through a real router. Also: read-only, TLS,
and the configuration's refusals."""

from __future__ import annotations

import asyncio
import base64
import datetime as dt
import io
import ipaddress
import json
import math
import ssl
import struct
import threading
import time
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from google.protobuf import descriptor_pool, message_factory
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from PIL import Image

from iorthand import keys
from iorthand.config import ConfigError, from_dict
from iorthand.protocol import RobotState
from iorthand_cloud.recorder.simulate import SyntheticSession
from iorthand_cloud.twin.config import FoxgloveLiveConfig, TwinConfig
from iorthand_cloud.twin.foxglove import SERVER_NAME, FoxgloveLive
from iorthand_cloud.twin.service import TwinService
from tests.conftest import wait_until

SUBPROTOCOL = "foxglove.sdk.v1"  # what foxglove-sdk 0.30 and the current Foxglove app speak
MESSAGE_DATA = 0x01  # binary opcode: u8 op, u32 subscription id, u64 log time (ns), payload


class FoxgloveClient:
    """A minimal client of the Foxglove WebSocket protocol, as the app uses it: read serverInfo and the
    advertised channels, subscribe, collect message data per subscription."""

    def __init__(self, ws: aiohttp.ClientWebSocketResponse) -> None:
        self.ws = ws
        self.server_info: dict[str, Any] = {}
        self.channels: dict[int, dict[str, Any]] = {}
        self.statuses: list[dict[str, Any]] = []
        self.subscribed: dict[int, int] = {}  # subscription id → channel id
        self.received: dict[int, list[tuple[int, bytes]]] = {}

    def channel(self, topic: str) -> dict[str, Any] | None:
        return next((c for c in self.channels.values() if c["topic"] == topic), None)

    async def pump(self, timeout: float = 0.2) -> None:
        try:
            msg = await self.ws.receive(timeout=timeout)
        except TimeoutError:
            return
        if msg.type == aiohttp.WSMsgType.TEXT:
            data = json.loads(msg.data)
            if data["op"] == "serverInfo":
                self.server_info = data
            elif data["op"] == "advertise":
                self.channels.update({c["id"]: c for c in data["channels"]})
            elif data["op"] == "status":
                self.statuses.append(data)
        elif msg.type == aiohttp.WSMsgType.BINARY:
            assert msg.data[0] == MESSAGE_DATA
            sub, log_time = struct.unpack_from("<IQ", msg.data, 1)
            self.received.setdefault(sub, []).append((log_time, bytes(msg.data[13:])))
        else:
            raise AssertionError(f"the server closed the connection: {msg}")

    async def subscribe(self, topics: list[str], timeout: float = 10.0) -> dict[str, int]:
        deadline = time.monotonic() + timeout
        while any(self.channel(t) is None for t in topics):
            assert time.monotonic() < deadline, f"not advertised: {[t for t in topics if self.channel(t) is None]}"
            await self.pump()
        subs = {t: i for i, t in enumerate(topics, 1)}
        for t, i in subs.items():
            self.subscribed[i] = self.channel(t)["id"]  # type: ignore[index]
        await self.ws.send_str(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": i, "channelId": self.subscribed[i]} for i in subs.values()]}))
        return subs

    async def collect(self, want: dict[int, int], timeout: float = 15.0) -> None:
        deadline = time.monotonic() + timeout
        while any(len(self.received.get(s, [])) < n for s, n in want.items()):
            assert time.monotonic() < deadline, f"received {({s: len(v) for s, v in self.received.items()})}, want {want}"
            await self.pump()


def decoder(channel: dict[str, Any]) -> Any:
    """A decoder built from what the server advertised alone (schema name, encoding and schema), as the app does."""
    if channel["encoding"] == "json":
        assert channel["schemaEncoding"] == "jsonschema"
        props = json.loads(channel["schema"])["properties"]

        def from_json(data: bytes) -> dict[str, Any]:
            out = json.loads(data)
            assert set(out) <= set(props)
            return out

        return from_json
    assert (channel["encoding"], channel["schemaEncoding"]) == ("protobuf", "protobuf")
    pool = descriptor_pool.DescriptorPool()
    for f in FileDescriptorSet.FromString(base64.b64decode(channel["schema"])).file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"])).FromString


def _twin(endpoint: str, **foxglove: object) -> TwinService:
    cfg = from_dict({"zenoh": {"mode": "client", "connect": [endpoint]}, "viewer": {"enabled": False},
                     "foxglove": {"enabled": True, "port": 0, **foxglove}}, TwinConfig, source="<test>")
    return TwinService(cfg)


def test_the_foxglove_app_sees_the_robot_live_through_the_twin(router_endpoint, session_factory) -> None:
    twin = _twin(router_endpoint)
    twin.start()
    s, video = session_factory(), session_factory()
    sim = SyntheticSession(s, "sim1", 20.0, video_session=video)
    runner = threading.Thread(target=sim.run, name="synthetic-robot", daemon=True)
    try:
        live = twin.foxglove
        assert live is not None and live.url.startswith("ws://127.0.0.1:") and live.port > 0
        time.sleep(0.3)  # the twin's subscriptions reach the router
        runner.start()
        wait_until(lambda: live.sent > 200, timeout=10, message="the twin serving the robot's channels")

        async def view() -> tuple[FoxgloveClient, dict[str, int]]:
            async with aiohttp.ClientSession() as http, http.ws_connect(live.url, protocols=(SUBPROTOCOL,)) as ws:
                assert ws.protocol == SUBPROTOCOL
                c = FoxgloveClient(ws)
                subs = await c.subscribe(["/sim1/tf", "/sim1/camera", "/sim1/force", "/sim1/probe", "/sim1/markers"])
                await c.collect({subs["/sim1/tf"]: 40, subs["/sim1/camera"]: 5, subs["/sim1/force"]: 30,
                                 subs["/sim1/probe"]: 30, subs["/sim1/markers"]: 10})
                return c, subs

        t_connect = time.time_ns()
        client, subs = asyncio.run(view())
    finally:
        sim.stop()
        runner.join(5)
        twin.shutdown()
    assert client.server_info["name"] == SERVER_NAME
    assert client.server_info["capabilities"] == []  # read-only: no client publish, services or parameters
    assert not [st for st in client.statuses if st["level"] >= 2]
    got = {t: [(lt, decoder(client.channels[client.subscribed[i]])(data)) for lt, data in client.received[i]]
           for t, i in subs.items()}
    for msgs in got.values():  # log times are the twin's receive times: now, not the past
        assert all(t_connect - 2_000_000_000 < lt < time.time_ns() for lt, _ in msgs)
    for _, tfs in got["/sim1/tf"]:
        (tf,) = tfs.transforms
        assert (tf.parent_frame_id, tf.child_frame_id) == ("sim1/base", "sim1/tcp")
        # the simulator's circle: 5 cm around (0.30, 0), 0.2 m high, tool pointing down (π about x)
        assert math.hypot(tf.translation.x - 0.3, tf.translation.y) == pytest.approx(0.05, abs=1e-9)
        assert tf.translation.z == 0.2 and abs(tf.rotation.x) == pytest.approx(1.0)
    FrameTransforms.FromString(client.received[subs["/sim1/tf"]][0][1])  # and with Foxglove's own classes
    for _, img in got["/sim1/camera"]:
        assert (img.format, img.frame_id) == ("jpeg", "sim1/camera")
        assert Image.open(io.BytesIO(img.data)).size == (640, 480)
    for _, f in got["/sim1/force"]:
        assert f["norm"] == pytest.approx(math.sqrt(f["fx"] ** 2 + f["fy"] ** 2 + f["fz"] ** 2))
    for _, probe in got["/sim1/probe"]:
        assert probe.entities[0].frame_id == "sim1/tcp" and len(probe.entities[0].cylinders) == 1
    assert {len(m.entities) for _, m in got["/sim1/markers"]} == {3}
    # The channels say which raw key they come from.
    assert client.channel("/sim1/tf")["metadata"] == {"iorthand.source": keys.RobotKeys("sim1").key(keys.STATE_ROBOT)}


def _self_signed(tmp_path: Path) -> tuple[Path, Path]:
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "twin")])
    now = dt.datetime.now(dt.UTC)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=1))
            .add_extension(x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), False)
            .sign(key, hashes.SHA256()))
    cert_path, key_path = tmp_path / "twin.pem", tmp_path / "twin.key"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
    return cert_path, key_path


def test_tls_serves_wss_to_a_client_that_trusts_the_certificate(session_factory, tmp_path: Path) -> None:
    cert, key = _self_signed(tmp_path)
    live = FoxgloveLive(from_dict({"enabled": True, "port": 0, "tls_cert": str(cert), "tls_key": str(key)},
                                  FoxgloveLiveConfig, source="<test>"))
    s = session_factory()
    live.start(session_factory())
    try:
        assert live.url.startswith("wss://127.0.0.1:")
        pub = s.declare_publisher(keys.RobotKeys("sim1").key(keys.STATE_ROBOT))
        time.sleep(0.3)
        pose = [0.31, 0.02, 0.2, math.pi, 0.0, 0.0]
        pub.put(RobotState(tcp_pose=pose).stamp(1).encode())
        wait_until(lambda: live.sent >= 1, message="the first robot state served")
        trusted = ssl.create_default_context(cafile=str(cert))

        async def view() -> list[tuple[int, bytes]]:
            async with aiohttp.ClientSession() as http:
                with pytest.raises(aiohttp.ClientError):  # plain ws:// is not served
                    async with http.ws_connect(live.url.replace("wss://", "ws://"), protocols=(SUBPROTOCOL,)):
                        pass
                async with http.ws_connect(live.url, protocols=(SUBPROTOCOL,), ssl=trusted) as ws:
                    c = FoxgloveClient(ws)
                    (sub,) = (await c.subscribe(["/sim1/tf"])).values()
                    for seq in range(2, 40):  # until the subscription is in place
                        pub.put(RobotState(tcp_pose=pose).stamp(seq).encode())
                        await c.pump(0.05)
                        if c.received.get(sub):
                            break
                    await c.collect({sub: 1})
                    return c.received[sub]

        received = asyncio.run(view())
    finally:
        live.stop()
    tf = FrameTransforms.FromString(received[0][1]).transforms[0]
    assert [tf.translation.x, tf.translation.y, tf.translation.z] == pose[:3]


def test_configuration_refuses_clear_text_beyond_this_machine(tmp_path: Path) -> None:
    cfg = from_dict({}, FoxgloveLiveConfig)
    assert (cfg.enabled, cfg.host, cfg.port) == (False, "127.0.0.1", 8765)  # off, and loopback when on
    with pytest.raises(ConfigError, match="clear text"):
        from_dict({"enabled": True, "host": "0.0.0.0"}, FoxgloveLiveConfig)
    with pytest.raises(ConfigError, match="IP address"):
        from_dict({"host": "twin.example"}, FoxgloveLiveConfig)
    with pytest.raises(ConfigError, match="go together"):
        from_dict({"tls_cert": str(tmp_path / "a.pem")}, FoxgloveLiveConfig)
    ok = from_dict({"enabled": True, "host": "0.0.0.0", "tls_cert": "a.pem", "tls_key": "a.key"}, FoxgloveLiveConfig)
    assert ok.tls_cert == Path("a.pem")
    twin = TwinService(from_dict({"zenoh": {"mode": "client", "connect": ["tcp/127.0.0.1:1"]},
                                  "viewer": {"enabled": False}}, TwinConfig))
    assert twin.foxglove is None  # no server unless asked for


def test_a_port_in_use_is_a_clear_error(session_factory) -> None:
    first = FoxgloveLive(from_dict({"enabled": True, "port": 0}, FoxgloveLiveConfig))
    first.start(session_factory())
    try:
        second = FoxgloveLive(from_dict({"enabled": True, "port": first.port}, FoxgloveLiveConfig))
        with pytest.raises(RuntimeError, match=f"cannot listen on 127.0.0.1:{first.port}"):
            second.start(session_factory())
        second.stop()
    finally:
        first.stop()
