"""The table of channels: it covers every key and message, and keys, decoders, QoS and the ACL come from it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import zenoh

from iorthand import channels, keys, protocol, transport
from iorthand.channels import Channel, Kind, OperatorKey, Qos, Role
from iorthand.security import acl

ROWS = {name: c for name, c in vars(channels).items() if isinstance(c, Channel)}
# Messages of the cloud services, under iorthand/_twin and iorthand/_recorder: not channels of a robot.
SERVICE_MESSAGES = {protocol.Annotation, protocol.RecorderRequest, protocol.RecorderStatus, protocol.TwinSnapshot}


def test_every_row_is_in_the_table_and_named_in_keys() -> None:
    assert set(ROWS.values()) == set(channels.TABLE)
    for name, row in ROWS.items():
        assert getattr(keys, name) == row.suffix, name


def test_every_message_class_has_its_row() -> None:
    classes = {c for c in vars(protocol).values() if isinstance(c, type) and issubclass(c, protocol.Message)}
    named = {protocol.message_class(n) for c in channels.TABLE for n in (c.message, c.reply) if n}
    assert classes - {protocol.Message} - SERVICE_MESSAGES == named
    for cls in named:  # a class that names its key names the row it belongs to
        assert not cls.KEY or channels.TABLE[[c.suffix for c in channels.TABLE].index(cls.KEY)].message == cls.__name__


def test_decoders_and_qos_are_the_tables() -> None:
    puts = [c for c in channels.TABLE if c.kind is Kind.PUT]
    assert {c.suffix: getattr(protocol, c.message) for c in puts} == protocol.MESSAGES_BY_KEY
    assert {c.suffix: transport.QOS_PROFILES[c.qos] for c in puts if c.qos} == transport.QOS_BY_KEY
    assert set(transport.QOS_PROFILES) == set(Qos)
    k = keys.RobotKeys("r1")
    assert protocol.message_type_for(k.key(keys.VIDEO_ULTRASOUND)) is protocol.VideoFrame
    assert protocol.message_type_for(k.key(keys.CONTROL_ACQUIRE)) is None  # queries are not recorded streams
    # An operator's own key (bind_operator_keys) carries its channel's message; no other key gains a type.
    assert protocol.message_type_for(k.key(f"{keys.CMD_TWIST}/alice")) is protocol.TwistCommand
    assert protocol.message_type_for(k.key(f"{keys.CMD_STOP}/bob")) is protocol.StopCommand
    for suffix in (f"{keys.STATE_ROBOT}/alice", f"{keys.CMD_TWIST}/alice/x", f"{keys.CMD_TWIST}/no one"):
        assert protocol.message_type_for(f"{keys.ROOT}/r1/{suffix}") is None, suffix


def _dep(bind: bool) -> acl.Deployment:
    d = acl.Deployment(robots=["r1"], operators={"alice": ["r1"], "bob": ["r1"]}, viewers=["x"], bind_operator_keys=bind,
                       certs_dir=Path("/etc/iorthand/certs"))
    d.check()
    return d


def _allows(cfg: dict, subject: str, message: str, key: str) -> bool:
    """Whether ``subject`` may send ``message`` on ``key`` (ingress), as the router matches it."""
    ac = cfg["access_control"]
    rules = {r["id"]: r for r in ac["rules"]}
    granted = [ke for p in ac["policies"] if subject in p["subjects"] for rid in p["rules"]
               if message in rules[rid]["messages"] and "ingress" in rules[rid]["flows"] for ke in rules[rid]["key_exprs"]]
    return any(zenoh.KeyExpr(ke).includes(zenoh.KeyExpr(key)) for ke in granted)


@pytest.mark.parametrize("bind", [True, False])
def test_the_acl_grants_exactly_what_the_table_says(bind: bool) -> None:
    cfg = acl.router_config(_dep(bind))
    k, replayed = keys.RobotKeys("r1"), keys.RobotKeys(keys.replay_id("r1"))
    for c in channels.TABLE:
        plain = k.key(c.suffix)
        if c.kind is Kind.PUT:
            assert _allows(cfg, "edge-r1", "put", plain) == (Role.EDGE in c.writers), c
            assert _allows(cfg, "replay", "put", replayed.key(c.suffix)) == (Role.REPLAY in c.writers), c
            assert not _allows(cfg, "replay", "put", plain), c
            own = plain + "/alice" if bind and c.operator_key is OperatorKey.BOUND else plain
            assert _allows(cfg, "operator-alice", "put", own) == (Role.OPERATOR in c.writers), c
            if bind and Role.OPERATOR in c.writers:
                assert not _allows(cfg, "operator-alice", "put", plain + "/bob"), c  # nobody's in another's name
                assert _allows(cfg, "operator-alice", "put", plain) == c.shared, c  # the stop is everyone's
        elif c.kind is Kind.QUERY:
            assert _allows(cfg, "edge-r1", "declare_queryable", plain + "/**") == (Role.EDGE in c.writers), c
            own = plain + "/alice" if bind else plain
            assert _allows(cfg, "operator-alice", "query", own) == (Role.OPERATOR in c.callers), c
            assert _allows(cfg, "operator-alice", "query", plain + "/bob") == (not bind), c
            assert _allows(cfg, "operator-alice", "query", plain) == (not bind or c.shared), c
            assert not _allows(cfg, "viewer-x", "query", plain), c
            # The twin asks the edge for previews (plan/**), and nothing else: never control/** (acquiring).
            assert _allows(cfg, "twin", "query", plain) == (Role.TWIN in c.callers), c
            assert not _allows(cfg, "recorder", "query", plain), c
        else:
            own = plain + "/alice" if c.operator_key is OperatorKey.ALWAYS else plain
            assert _allows(cfg, "edge-r1", "liveliness_token", own) == (Role.EDGE in c.writers), c
            assert _allows(cfg, "operator-alice", "liveliness_token", own) == (Role.OPERATOR in c.writers), c
            assert not _allows(cfg, "operator-alice", "liveliness_token", plain + "/bob"), c


def test_a_new_row_reaches_decoders_qos_and_acl() -> None:
    audio = Channel("audio/mic", Kind.PUT, "VideoFrame", Qos.VIDEO, frozenset({Role.EDGE, Role.REPLAY}))
    table = (*channels.TABLE, audio)
    channels.check(table)
    assert protocol.messages_by_key(table)["audio/mic"] is protocol.VideoFrame
    assert transport.qos_by_key(table)["audio/mic"] is transport.VIDEO
    cfg = acl.router_config(_dep(True))
    assert not _allows(cfg, "edge-r1", "put", "iorthand/r1/audio/mic")  # not routed while it is no row
    cfg = {"access_control": acl.acl_rules(_dep(True), table)}
    assert _allows(cfg, "edge-r1", "put", "iorthand/r1/audio/mic")
    assert _allows(cfg, "replay", "put", "iorthand/r1-replay/audio/mic")
    assert not _allows(cfg, "operator-alice", "put", "iorthand/r1/audio/mic/alice")


@pytest.mark.parametrize(("row", "why"), [
    (dataclasses.replace(channels.STATE_FORCE, suffix="state/robot"), "two rows"),
    (dataclasses.replace(channels.STATE_FORCE, suffix="state/*"), "without wildcards"),
    (dataclasses.replace(channels.STATE_FORCE, suffix="state/echo", writers=frozenset({Role.EDGE})), "family at once"),
    (dataclasses.replace(channels.STATE_FORCE, suffix="video/cmd", kind=Kind.QUERY, callers=frozenset({Role.OPERATOR}),
                         reply="ControlReply", qos=None), "mixes"),
    (dataclasses.replace(channels.STATE_FORCE, suffix="state/x", qos=None), "a put has a message and a QoS"),
    (dataclasses.replace(channels.CMD_STOP, suffix="order/stop"), "one family"),
    (dataclasses.replace(channels.STATE_FORCE, suffix="state/x", shared=True), "shared plain key"),
    (dataclasses.replace(channels.STATE_FORCE, suffix="state/x", operator_key=OperatorKey.BOUND), "bound to them"),
])
def test_check_refuses_a_table_the_acl_would_get_wrong(row: Channel, why: str) -> None:
    with pytest.raises(ValueError, match=why):
        channels.check((*channels.TABLE, row))
