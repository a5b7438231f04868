"""The security rules as a deployment engineer or an attacker states them, one test each: pure code, no router.

Each pins a rule of :mod:`iorthand.security` that a mutation of its code (a comparison flipped, a check skipped, a
key expression widened) left standing under the other fast tests. The router enforces the ACL: the tests on its
structure read the generated rules the way Zenoh matches them (``zenoh.KeyExpr.includes``); the live-router tests
of the same rules are in test_tls_integration.py.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import zenoh

from iorthand import channels, keys
from iorthand.channels import Role
from iorthand.config import ConfigError, from_dict
from iorthand.protocol import StopCommand, TwistCommand
from iorthand.security import acl, auth, hosts, identity

KEY = bytes(range(32))
# Every kind of message Zenoh's ACL names: spelled out here, not read from acl, so that a kind dropped there shows.
MESSAGES = ["put", "delete", "declare_subscriber", "query", "declare_queryable", "reply", "liveliness_token",
            "declare_liveliness_subscriber", "liveliness_query"]
WATCHING = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]
USERS = Path("/etc/iorthand/users.txt")


def _dep(**kw: object) -> acl.Deployment:
    base: dict[str, object] = dict(certs_dir=Path("/etc/iorthand/certs"), users_file=USERS, robots=["r1", "r2"],
                                   operators={"alice": ["r1"], "bob": ["r1", "r2"]}, viewers=["eve"])
    base.update(kw)
    dep = acl.Deployment(**base)  # type: ignore[arg-type]
    dep.check()
    return dep


def _may(cfg: dict, subject: str, message: str, key: str, flow: str = "ingress") -> bool:
    """Whether the router lets ``subject`` send (ingress) or receive (egress) ``message`` on ``key``: the rules of
    its policies, matched as Zenoh matches key expressions."""
    ac = cfg["access_control"]
    rules = {r["id"]: r for r in ac["rules"]}
    granted = [ke for p in ac["policies"] if subject in p["subjects"] for rid in p["rules"]
               if message in rules[rid]["messages"] and flow in rules[rid]["flows"] for ke in rules[rid]["key_exprs"]]
    return any(zenoh.KeyExpr(ke).includes(zenoh.KeyExpr(key)) for ke in granted)


def _subjects(cfg: dict) -> dict[str, dict]:
    return {s["id"]: s for s in cfg["access_control"]["subjects"]}


def _signed_twist(key: bytes = KEY, robot: str = "r1", suffix: str = keys.CMD_TWIST) -> TwistCommand:
    """A command as the edge receives it: sealed by the owner's client, decoded from the bytes that travelled."""
    cmd = TwistCommand(operator="alice", linear=[0.005, 0.0, 0.0], deadman=True, state_age=0.02).stamp(7, 1_700_000_000_000_000_000)
    return TwistCommand.decode(auth.seal(key, auth.context(robot, suffix), cmd))


def test_a_command_signed_for_one_robot_does_not_verify_for_another() -> None:
    cmd = _signed_twist(robot="r1")
    assert auth.verify(KEY, auth.context("r1", keys.CMD_TWIST), cmd)
    assert not auth.verify(KEY, auth.context("r2", keys.CMD_TWIST), cmd)
    assert not auth.verify(KEY, auth.context("r1", keys.CMD_SERVO), cmd)  # nor as another kind of message


def test_an_edges_answer_does_not_verify_as_a_request_and_back() -> None:
    ctx, reply_ctx = auth.context("r1", keys.CONTROL_ACQUIRE), auth.reply_context("r1", keys.CONTROL_ACQUIRE)
    request = _signed_twist(suffix=keys.CONTROL_ACQUIRE)
    assert auth.verify(KEY, ctx, request) and not auth.verify(KEY, reply_ctx, request)
    answer = TwistCommand.decode(auth.seal(KEY, reply_ctx, TwistCommand(operator="alice").stamp(8)))
    assert auth.verify(KEY, reply_ctx, answer) and not auth.verify(KEY, ctx, answer)


def test_a_signature_under_an_earlier_grant_does_not_verify_under_the_next() -> None:
    earlier, current = auth.new_key(), auth.new_key()
    assert len(earlier) == len(current) == auth.KEY_BYTES and earlier != current
    assert not auth.verify(current, auth.context("r1", keys.CMD_TWIST), _signed_twist(key=earlier))


def test_no_key_verifies_nothing_not_even_a_mac_anyone_can_compute() -> None:
    """A session without a grant holds the empty key: BLAKE2s with an empty key is a plain hash that anyone can
    compute over a forged command, so the empty key must verify nothing."""
    forged = _signed_twist(key=b"")
    assert not auth.verify(b"", auth.context("r1", keys.CMD_TWIST), forged)


def test_any_byte_changed_in_a_signed_command_fails_verification() -> None:
    ctx = auth.context("r1", keys.CMD_TWIST)
    wire = _signed_twist()._wire  # type: ignore[attr-defined]
    checked = 0
    for i in range(len(wire)):
        tampered = bytearray(wire)
        tampered[i] ^= 0x01
        try:
            msg = TwistCommand.decode(bytes(tampered))
        except ValueError:
            continue  # the decoder refuses it before any signature is checked
        checked += 1
        assert not auth.verify(KEY, ctx, msg), f"byte {i} changed and the command still verifies"
    assert checked > len(wire) // 2


def test_a_command_changed_in_transit_does_not_verify_even_when_it_decodes_to_the_same_values() -> None:
    """The MAC covers the bytes that travelled, not a re-encoding: a middleman's rewrite (here the sequence number
    in a wider integer format) is not the owner's message."""
    ctx = auth.context("r1", keys.CMD_TWIST)
    wire = _signed_twist()._wire  # type: ignore[attr-defined]
    canonical_seq = b"\xa3seq\x07"
    assert canonical_seq in wire
    rewritten = TwistCommand.decode(wire.replace(canonical_seq, b"\xa3seq\xcf" + (7).to_bytes(8, "big")))
    assert rewritten.seq == 7 and rewritten.encode() == wire  # the same values, the same canonical encoding
    assert not auth.verify(KEY, ctx, rewritten)


def test_a_command_signed_in_this_process_verifies_before_it_travels() -> None:
    ctx = auth.context("r1", keys.CMD_TWIST)
    cmd = auth.sign(KEY, ctx, TwistCommand(operator="alice", deadman=True).stamp(3))
    assert len(cmd.mac) == auth.MAC_BYTES and auth.verify(KEY, ctx, cmd)
    assert TwistCommand.decode(cmd.encode()).mac == cmd.mac


def test_an_unsigned_command_does_not_verify() -> None:
    cmd = TwistCommand(operator="alice", deadman=True).stamp(1)
    assert not auth.verify(KEY, auth.context("r1", keys.CMD_TWIST), TwistCommand.decode(cmd.encode()))


def test_a_message_that_cannot_carry_a_signature_is_refused_rather_than_sent_unsigned() -> None:
    with pytest.raises(TypeError, match="cannot be signed"):
        auth.seal(KEY, auth.context("r1", keys.CMD_STOP), StopCommand(operator="alice").stamp(1))


# --- the router's ACL (structure; the live-router tests of the same roles: test_tls_integration.py) ---------------


def test_a_certificate_named_web_or_bridge_is_granted_nothing_unless_the_deployment_enables_it() -> None:
    assert not acl.Deployment().web and not acl.Deployment().bridge  # both off unless asked for
    cfg = acl.router_config(_dep())
    assert not {acl.WEB, acl.BRIDGE} & _subjects(cfg).keys()
    assert not _may(cfg, "web", "put", "iorthand/r1/cmd/twist/alice")
    assert not _may(cfg, "bridge", "put", "iorthand/r1/sensor/vital")


def test_the_web_console_sends_for_each_operator_only_what_that_operators_certificate_may() -> None:
    cfg = acl.router_config(_dep(web=True))
    assert "web" in _subjects(cfg)  # the name `iorthand web`'s certificate carries
    assert _may(cfg, "web", "put", "iorthand/r1/cmd/twist/alice") and _may(cfg, "web", "put", "iorthand/r1/cmd/stop")
    assert _may(cfg, "web", "query", "iorthand/r1/control/acquire/alice")
    assert _may(cfg, "web", "liveliness_token", "iorthand/r1/alive/operator/alice")
    assert not _may(cfg, "web", "put", "iorthand/r2/cmd/twist/alice")  # alice is granted r1 only
    assert not _may(cfg, "web", "put", "iorthand/r1/cmd/twist/mallory")  # nobody the deployment does not name
    assert not _may(cfg, "web", "query", "iorthand/r1/control/acquire/mallory")
    assert not _may(cfg, "web", "put", "iorthand/r1/state/robot") and not _may(cfg, "web", "liveliness_token",
                                                                              "iorthand/r1/alive/edge")
    for robot in ("r1", "r2"):  # it shows every robot to its viewers
        assert _may(cfg, "web", "declare_subscriber", f"iorthand/{robot}/state/robot")
        assert _may(cfg, "web", "put", f"iorthand/{robot}/state/robot", flow="egress")
    assert _may(cfg, "web", "query", "iorthand/_recorder/status")


def test_the_bridge_publishes_only_sensor_readings_of_the_deployments_robots() -> None:
    cfg = acl.router_config(_dep(bridge=True))
    assert _may(cfg, "bridge", "put", "iorthand/r1/sensor/vital") and _may(cfg, "bridge", "put", "iorthand/r2/sensor/vital")
    assert not _may(cfg, "bridge", "put", "iorthand/r9/sensor/vital")
    for key in ("iorthand/r1/state/robot", "iorthand/r1/cmd/stop", "iorthand/r1/markers"):
        assert not _may(cfg, "bridge", "put", key), key
    assert not _may(cfg, "bridge", "query", "iorthand/r1/control/acquire")
    assert not _may(cfg, "bridge", "liveliness_token", "iorthand/r1/alive/edge")
    assert _may(cfg, "bridge", "declare_subscriber", "iorthand/r1/state/robot")  # it mirrors their state out
    assert not _may(cfg, "bridge", "declare_subscriber", "iorthand/r9/state/robot")


def test_everyone_granted_to_watch_receives_every_kind_of_message_there_and_may_subscribe_and_watch_tokens() -> None:
    """A kind missing from a receive rule is dropped by the router without a word: an operator that receives no
    reply never gets its grant, an edge that may not watch liveliness never sees its owner go."""
    cfg = acl.router_config(_dep(web=True, bridge=True))
    watched = {"edge-r1": "iorthand/r1/control/acquire/alice", "operator-alice": "iorthand/r1/alive/edge",
               "viewer-eve": "iorthand/r2/state/robot", "twin": "iorthand/r1/plan/preview",
               "recorder": "iorthand/r1/cmd/twist/bob", "web": "iorthand/r2/alive/operator/bob",
               "bridge": "iorthand/r1/sensor/vital", "replay": "iorthand/r1-replay/state/robot"}
    for subject, key in watched.items():
        for message in MESSAGES:
            assert _may(cfg, subject, message, key, flow="egress"), (subject, message, key)
        if subject != "replay":  # it only publishes
            for message in WATCHING:
                assert _may(cfg, subject, message, key), (subject, message, key)
    assert not _may(cfg, "replay", "put", "iorthand/r1/state/robot", flow="egress")


def test_every_subject_is_its_certificates_common_name_and_with_a_users_file_also_its_username() -> None:
    for users_file in (USERS, None):
        cfg = acl.router_config(_dep(users_file=users_file, web=True, bridge=True))
        policies = {p["id"]: p for p in cfg["access_control"]["policies"]}
        for sid, subject in _subjects(cfg).items():
            # Without a users file the router knows no usernames: a subject that named one would match nobody.
            assert subject == ({"id": sid, "cert_common_names": [sid], "usernames": [sid]} if users_file
                               else {"id": sid, "cert_common_names": [sid]}), subject
            assert policies[f"policy-{sid}"]["subjects"] == [sid]


def test_the_router_requires_a_password_from_the_deployments_users_file_only_when_it_has_one() -> None:
    assert acl.router_config(_dep())["transport"]["auth"] == {"usrpwd": {"dictionary_file": str(USERS)}}
    assert "auth" not in acl.router_config(_dep(users_file=None))["transport"]


def test_the_router_serves_tls_from_the_deployments_ca_and_drops_a_link_whose_certificate_expires() -> None:
    tls = acl.router_config(_dep(certs_dir=Path("/srv/pki")))["transport"]["link"]["tls"]
    assert tls == {"root_ca_certificate": "/srv/pki/ca.pem", "listen_certificate": "/srv/pki/router.pem",
                   "listen_private_key": "/srv/pki/router.key", "enable_mtls": True, "close_link_on_expiration": True}


def test_the_router_is_not_discoverable_and_listens_and_dials_only_where_the_deployment_says() -> None:
    cfg = acl.router_config(_dep(listen=["tls/10.0.0.5:7447", "quic/10.0.0.5:7447"],
                                 connect=["tls/cloud.example.org:7447"]))
    assert cfg["mode"] == "router"
    assert cfg["scouting"] == {"multicast": {"enabled": False}, "gossip": {"enabled": False}}
    assert cfg["listen"] == {"endpoints": ["tls/10.0.0.5:7447", "quic/10.0.0.5:7447"]}  # QUIC is encrypted too
    assert cfg["connect"] == {"endpoints": ["tls/cloud.example.org:7447"]}


def test_the_twin_and_the_recorder_serve_only_their_own_space_and_a_viewer_serves_nothing() -> None:
    cfg = acl.router_config(_dep())
    for service, other in (("twin", "recorder"), ("recorder", "twin")):
        for message in ("put", "delete", "declare_queryable", "reply", "liveliness_token"):
            assert _may(cfg, service, message, f"iorthand/_{service}/status"), (service, message)
            assert not _may(cfg, service, message, f"iorthand/_{other}/status"), (service, message)
    for message in ("put", "declare_queryable", "reply", "liveliness_token"):
        assert not [r for r in cfg["access_control"]["rules"] if r["id"].startswith("viewer-eve")
                    and message in r["messages"] and "ingress" in r["flows"]], message


def test_a_deployment_without_services_or_with_an_operator_granted_no_robot_gives_a_configuration_zenoh_accepts() -> None:
    """Zenoh refuses a rule with no key expression ("Given collection was empty"): no rule may be made empty."""
    for bind in (True, False):
        zenoh.Config.from_json5(acl.to_json5(acl.router_config(_dep(services=[], bind_operator_keys=bind, web=True))))
        zenoh.Config.from_json5(acl.to_json5(acl.router_config(_dep(operators={"alice": [], "bob": ["r1"]},
                                                                    bind_operator_keys=bind, web=True))))


def test_a_cloud_router_set_up_before_its_first_robot_or_with_an_operator_granted_none_gets_a_configuration_zenoh_accepts(
) -> None:
    """Found by mutation testing: a deployment that passed its check gave a configuration Zenoh refused with only
    "Given collection was empty" (the router did not start, without saying why): with no robot yet, the twin's
    preview rule and the set-point caps had no key; an operator granted no robot with no services, its subscribe
    and receive rules. A rule that would allow nothing is left out, as is a cap with nothing to cap."""
    for dep in (acl.Deployment(robots=[], services=["twin"]), acl.Deployment(robots=[], services=[]),
                acl.Deployment(robots=["r1"], operators={"alice": []}, services=[])):
        dep.check()
        config = acl.router_config(dep)
        zenoh.Config.from_json5(acl.to_json5(config))
        assert all(rule["key_exprs"] for rule in config["access_control"]["rules"])


def test_the_routers_lease_stays_between_half_a_second_and_a_minute() -> None:
    """The lease is how soon the router drops a silent session and its liveliness token: how soon the edge sees
    its owner gone."""
    assert from_dict({"lease_ms": 500}, acl.Deployment).lease_ms == 500
    assert from_dict({"lease_ms": 60_000}, acl.Deployment).lease_ms == 60_000
    for lease in (499, 60_001):
        with pytest.raises(ConfigError, match="lease_ms"):
            from_dict({"lease_ms": lease}, acl.Deployment)


def test_iorthand_check_reads_the_routers_bind_setting_back_from_its_rules() -> None:
    assert acl.bound_operator_keys(acl.router_config(_dep())) is True
    assert acl.bound_operator_keys(acl.router_config(_dep(bind_operator_keys=False))) is False
    assert acl.bound_operator_keys(acl.router_config(_dep(operators={}))) is None  # nobody to tell by
    assert acl.bound_operator_keys({"mode": "router"}) is None  # not made by the generator


def test_a_user_name_or_password_cannot_add_a_line_to_the_routers_password_file() -> None:
    assert acl.users_line("operator-alice", "s3cret") == "operator-alice:s3cret\n"
    for user, password in (("operator-alice:x", "pw"), ("operator-alice\nweb", "pw"), ("operator-alice", "pw\nweb:pw")):
        with pytest.raises(ValueError, match="may not contain"):
            acl.users_line(user, password)


def test_a_name_that_could_widen_a_key_expression_is_refused_by_the_deployment_and_the_generator() -> None:
    """An operator named ``**`` would be granted ``cmd/*/**`` (everyone's commands) and annotate as anyone. The
    deployment's check refuses it; so does the generator, for a deployment made without the check."""
    for name in ("**", "*", "a/b", "$*"):
        with pytest.raises(ValueError, match="operator id"):
            _dep(operators={name: ["r1"]})
    with pytest.raises(ValueError, match="operator id"):  # granted a robot, no services: its token's key checks it
        acl.router_config(acl.Deployment(robots=["r1"], operators={"**": ["r1"]}, services=[]))
    with pytest.raises(ValueError, match="operator id"):  # granted no robot: its annotation key checks it
        acl.router_config(acl.Deployment(robots=["r1"], operators={"**": []}))


def test_a_deployment_names_only_known_services_and_a_bridge_needs_robots() -> None:
    with pytest.raises(ValueError, match="is not one of"):
        _dep(services=["twin", "shell"])
    with pytest.raises(ValueError, match="bridge: true needs robots"):
        _dep(robots=[], operators={}, bridge=True)


def test_the_acl_refuses_a_table_whose_family_rows_disagree_on_who_may_write() -> None:
    """The ACL grants a family whole (state/**): a row that only the edge should write, in a family the replay also
    writes, would be granted to the replay too."""
    odd = dataclasses.replace(channels.STATE_ROBOT, suffix="state/secret", writers=frozenset({Role.EDGE}))
    with pytest.raises(ValueError, match="the ACL grants a family at once"):
        acl.acl_rules(_dep(), (*channels.TABLE, odd))


# --- the edge's own identity checks (iorthand.security.identity) ---------------------------------------------


def test_only_an_operator_certificate_names_an_operator() -> None:
    assert identity.operator_from_common_name("operator-alice") == "alice"
    # "viewer-alice"[len("operator-"):] would be "ice": a viewer's certificate must not become an operator.
    for cn in ("viewer-mallory", "edge-r1-operator-alice", "operator-", "operator-**", "operator-a/b"):
        assert identity.operator_from_common_name(cn) is None, cn


def test_an_operator_id_is_read_only_from_right_under_the_key_it_was_sent_on() -> None:
    assert identity.operator_in_key("iorthand/r1/cmd/twist/alice", keys.CMD_TWIST) == "alice"
    # cmd/torch has as many characters as cmd/twist: the id is not read by position alone.
    assert identity.operator_in_key("iorthand/r1/cmd/torch/alice", keys.CMD_TWIST) is None
    assert identity.operator_in_key("iorthand/r1/cmd/twistxalice", keys.CMD_TWIST) is None
    assert identity.operator_in_key("iorthand/r1/cmd/twist/alice/extra", keys.CMD_TWIST) is None
    assert identity.operator_in_key("iorthand/r1/cmd/twist", keys.CMD_TWIST) is None


def test_with_bound_keys_a_stop_on_the_plain_key_is_obeyed_but_a_twist_is_not() -> None:
    """A stop is everyone's (the shared plain key cmd/stop); every other command must come on the key the router
    ties to its sender's certificate, and the refusal says so."""
    gate = identity.CommandGate(bind_keys=True)
    assert gate.check_command("iorthand/r1/cmd/stop", keys.CMD_STOP, "alice")[0]
    ok, why = gate.check_command("iorthand/r1/cmd/twist", keys.CMD_TWIST, "alice")
    assert not ok and "identity-scoped key" in why
    ok, why = gate.check_command("iorthand/r1/cmd/stop/not an id", keys.CMD_STOP, "alice")
    assert not ok and "identity-scoped key" in why


def test_an_operator_outside_the_allow_list_or_in_anothers_name_cannot_acquire_even_with_a_token() -> None:
    gate = identity.CommandGate(allowed=["alice"], bind_keys=True)
    gate.operator_alive("alice")
    gate.operator_alive("carol")
    ok, why = gate.check_acquire("iorthand/r1/control/acquire/carol", keys.CONTROL_ACQUIRE, "carol")
    assert not ok and "allow-list" in why
    ok, why = gate.check_acquire("iorthand/r1/control/acquire/alice", keys.CONTROL_ACQUIRE, "bob")
    assert not ok and "not in this robot's allow-list" in why
    gate.allowed.append("bob")
    ok, why = gate.check_acquire("iorthand/r1/control/acquire/alice", keys.CONTROL_ACQUIRE, "bob")
    assert not ok and "authenticated 'alice'" in why


# --- Host headers against DNS rebinding (iorthand.security.hosts; the console's full check: test_web_units.py) -----


def test_a_server_listening_on_every_address_answers_to_no_wildcard_as_a_host_name() -> None:
    """0.0.0.0 and :: name no host: a request naming them is not one of the server's names."""
    for listen, header in (("0.0.0.0", "0.0.0.0:8443"), ("::", "[::]:8443")):
        names = hosts.own_names(listen, ["robot-1.hospital.org"])
        assert names == {"robot-1.hospital.org"}, listen
        assert not hosts.host_allowed(header, names), header


def test_a_server_on_ipv6_loopback_answers_to_the_loopback_names_and_to_no_other() -> None:
    assert hosts.is_loopback("[::1]") and hosts.is_loopback("localhost") and not hosts.is_loopback("10.0.0.7")
    names = hosts.own_names("[::1]")
    assert names == {"localhost", "127.0.0.1", "::1"}
    assert hosts.host_allowed("[::1]:8443", names) and hosts.host_allowed("localhost:8443", names)
    assert hosts.own_names("10.0.0.7") == {"10.0.0.7"}  # the address it listens on, and no loopback name


def test_a_certificate_wildcard_covers_exactly_one_non_empty_label() -> None:
    names = hosts.normalise(["*.ward.hospital.org", "[::1]"])
    assert hosts.host_allowed("scanner.ward.hospital.org", names) and hosts.host_allowed("[::1]:8443", names)
    for header in (".ward.hospital.org", "ward.hospital.org", "a.b.ward.hospital.org"):
        assert not hosts.host_allowed(header, names), header
