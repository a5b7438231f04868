"""Certificates, the ACL generator, the diagnosis of failures and the edge's identity gate — no network."""

from __future__ import annotations

import datetime as dt
import json
import os
import stat
from pathlib import Path

import pytest
import zenoh

from iorthand.security import acl, certs, diagnose, identity
from iorthand.transport import (
    ACCEPT_PENDING,
    ACCEPT_PENDING_KEY,
    DIALING_LEASE_EXTRA_MS,
    ROUTER_LEASE_MS,
    SHM_POOL_SIZE,
    SHM_POOL_SIZE_KEY,
    TX_QUEUE_SIZE,
    TlsConfig,
    ZenohConfig,
    forwarding_rules,
    load_router_config,
    rate_limits,
    router_settings,
    zenoh_config,
    zenoh_entries,
)
from tests.conftest import ROOT


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("pki")
    certs.init_ca(d)
    certs.issue(d, "router", hosts=["router.example.org", "10.0.0.5"])
    certs.issue(d, "edge-sim1")
    certs.issue(d, "operator-alice")
    return d


def test_ca_and_role_certificates(pki: Path) -> None:
    assert stat.S_IMODE(os.stat(pki).st_mode) == 0o700
    assert stat.S_IMODE(os.stat(pki / "ca.key").st_mode) == 0o600
    assert stat.S_IMODE(os.stat(pki / "edge-sim1.key").st_mode) == 0o600
    info = certs.describe(pki / "router.pem")
    assert info["common_name"] == "router" and not info["ca"] and 360 <= info["days_left"] <= 365
    assert {"router.example.org", "10.0.0.5"} <= set(info["subject_alt_names"])
    assert certs.describe(pki / "ca.pem")["ca"]
    assert diagnose.check_certificate_files(pki / "ca.pem", pki / "operator-alice.pem", pki / "operator-alice.key") == []


def test_refuses_bad_names_and_overwriting_the_ca(pki: Path) -> None:
    with pytest.raises(certs.CertError):
        certs.issue(pki, "admin")
    with pytest.raises(certs.CertError):
        certs.init_ca(pki)


def test_precheck_finds_each_problem(pki: Path, tmp_path: Path) -> None:
    other = tmp_path / "other"
    certs.init_ca(other)
    certs.issue(other, "operator-alice")
    old = certs.issue(pki, "operator-old", days=1, not_before=dt.datetime.now(dt.UTC) - dt.timedelta(days=5))

    def problems(ca: Path, cert: Path | None, key: Path | None) -> str:
        return " | ".join(str(f) for f in diagnose.check_certificate_files(ca, cert, key) if f.level == "error")

    assert "not signed by the CA" in problems(pki / "ca.pem", other / "operator-alice.pem", other / "operator-alice.key")
    assert "expired" in problems(pki / "ca.pem", old.certificate, old.private_key)
    assert "does not belong" in problems(pki / "ca.pem", pki / "operator-alice.pem", pki / "edge-sim1.key")
    assert "does not exist" in problems(pki / "ca.pem", pki / "nobody.pem", pki / "nobody.key")
    (tmp_path / "junk.pem").write_text("junk")
    assert "not a PEM certificate" in problems(tmp_path / "junk.pem", None, None)


def test_zenoh_entries_are_keys_zenoh_accepts(pki: Path, tmp_path: Path) -> None:
    pw = tmp_path / "pw"
    pw.write_text("secret\n")
    for mode in ("client", "peer", "router"):
        cfg = ZenohConfig(mode=mode, connect=["tls/127.0.0.1:7447"], listen=["tls/127.0.0.1:7448"] if mode != "client" else [],
                          tls=TlsConfig(root_ca=pki / "ca.pem", certificate=pki / "router.pem", private_key=pki / "router.key"),
                          username="edge-sim1", password_file=pw)
        entries = zenoh_entries(cfg)
        zenoh_config(cfg)  # insert_json5 raises on any key unknown to zenoh 1.10.2
        assert entries["transport/auth/usrpwd/password"] == "secret"
        assert entries["transport/link/tls/enable_mtls"] is True
        assert entries["transport/link/tls/verify_name_on_connect"] is True
        assert ("transport/link/tls/connect_certificate" in entries) == (mode != "router")
        assert ("transport/link/tls/listen_certificate" in entries) == (mode != "client")


def test_config_refuses_tls_endpoint_without_tls_and_user_without_password() -> None:
    from iorthand.config import ConfigError, from_dict

    with pytest.raises(ConfigError, match="needs a tls section"):
        from_dict({"connect": ["tls/1.2.3.4:7447"]}, ZenohConfig)
    with pytest.raises(ConfigError, match="password_file"):
        from_dict({"connect": ["tcp/1.2.3.4:7447"], "username": "u"}, ZenohConfig)
    # A session on UDP alone would send its commands as datagrams, lost without a word, and in clear.
    with pytest.raises(ConfigError, match=r"UDP carries nothing reliably.*quic/HOST:PORT\?mixed_rel=1"):
        from_dict({"connect": ["udp/1.2.3.4:7447"]}, ZenohConfig)


def _dep(**kw: object) -> acl.Deployment:
    base = dict(listen=["tls/0.0.0.0:7447"], certs_dir=Path("/etc/iorthand/certs"), users_file=Path("/etc/iorthand/users.txt"),
                robots=["r1", "r2"], operators={"alice": ["r1"], "bob": ["r1", "r2"]}, viewers=["eve"])
    base.update(kw)
    d = acl.Deployment(**base)  # type: ignore[arg-type]
    d.check()
    return d


def _allowed(cfg: dict, subject: str, message: str, flow: str) -> list[str]:
    ac = cfg["access_control"]
    rules = {r["id"]: r for r in ac["rules"]}
    out = []
    for p in ac["policies"]:
        if subject in p["subjects"]:
            for rid in p["rules"]:
                r = rules[rid]
                if message in r["messages"] and flow in r["flows"]:
                    out += r["key_exprs"]
    return out


def test_acl_policy_by_role() -> None:
    cfg = acl.router_config(_dep())
    assert cfg["access_control"]["default_permission"] == "deny"
    assert cfg["transport"]["link"]["tls"]["enable_mtls"] is True
    # Operators' command and control keys are bound to their certificates by default; a stop is everyone's.
    assert _allowed(cfg, "operator-alice", "put", "ingress") == ["iorthand/r1/cmd/*/alice", "iorthand/r1/cmd/stop"]
    assert sorted(_allowed(cfg, "operator-bob", "put", "ingress")) == [
        "iorthand/r1/cmd/*/bob", "iorthand/r1/cmd/stop", "iorthand/r2/cmd/*/bob", "iorthand/r2/cmd/stop"]
    # ... and so is its authorship of a recording's annotations (the recorder stores the author the key names).
    assert _allowed(cfg, "operator-alice", "query", "ingress") == [
        "iorthand/r1/control/*/alice", "iorthand/r1/plan/*/alice", "iorthand/r1/plan/preview", "iorthand/_twin/**",
        "iorthand/_recorder/start", "iorthand/_recorder/stop", "iorthand/_recorder/status",
        "iorthand/_recorder/annotate/alice"]
    unbound = acl.router_config(_dep(bind_operator_keys=False))
    assert _allowed(unbound, "operator-alice", "put", "ingress") == ["iorthand/r1/cmd/**"]
    assert sorted(_allowed(unbound, "operator-bob", "put", "ingress")) == ["iorthand/r1/cmd/**", "iorthand/r2/cmd/**"]
    assert _allowed(unbound, "operator-alice", "query", "ingress")[0] == "iorthand/r1/control/**"
    assert _allowed(unbound, "operator-alice", "query", "ingress")[-2:] == ["iorthand/_twin/**", "iorthand/_recorder/**"]
    assert _allowed(cfg, "operator-alice", "liveliness_token", "ingress") == ["iorthand/r1/alive/operator/alice"]
    edge_puts = _allowed(cfg, "edge-r1", "put", "ingress")
    assert all(k.startswith("iorthand/r1/") and "/cmd" not in k for k in edge_puts)
    assert _allowed(cfg, "edge-r1", "declare_queryable", "ingress") == ["iorthand/r1/control/**", "iorthand/r1/plan/**"]
    for viewer in ("viewer-eve", "twin", "recorder"):
        assert not [k for k in _allowed(cfg, viewer, "put", "ingress") if not k.startswith("iorthand/_")]
        assert not [k for k in _allowed(cfg, viewer, "query", "ingress") if "/control" in k]
    # The twin has the edge plan the operators' previews: plan/** of every robot, and no other robot key.
    assert [k for k in _allowed(cfg, "twin", "query", "ingress") if not k.startswith("iorthand/_")] == [
        "iorthand/r1/plan/**", "iorthand/r2/plan/**"]
    # A viewer only reads the services: no starting, stopping or annotating a recording, no previews.
    assert _allowed(cfg, "viewer-eve", "query", "ingress") == ["iorthand/_twin/*/snapshot", "iorthand/_recorder/status"]
    assert _allowed(acl.router_config(_dep(services=["twin"])), "viewer-eve", "query", "ingress") == [
        "iorthand/_twin/*/snapshot"]
    # The replay identity publishes only under the ids reserved for replays, which no edge may take.
    replay_puts = _allowed(cfg, "replay", "put", "ingress")
    assert replay_puts and all(k.startswith("iorthand/$*-replay/") for k in replay_puts), replay_puts
    assert not [k for k in _allowed(cfg, "replay", "declare_queryable", "ingress") + _allowed(cfg, "replay", "query", "ingress")]
    assert "replay" not in {s["id"] for s in acl.router_config(_dep(replay=False))["access_control"]["subjects"]}
    subj = {s["id"]: s for s in cfg["access_control"]["subjects"]}
    assert subj["operator-alice"] == {"id": "operator-alice", "cert_common_names": ["operator-alice"], "usernames": ["operator-alice"]}


@pytest.mark.parametrize("bind", [True, False])
def test_generated_config_is_accepted_by_zenoh(tmp_path: Path, bind: bool) -> None:
    p = tmp_path / "router.json5"
    p.write_text(acl.to_json5(acl.router_config(_dep(bind_operator_keys=bind))))
    zc = zenoh.Config.from_file(str(p))
    assert json.loads(zc.get_json("access_control/enabled")) is True


def test_every_router_configuration_has_the_queue_sizes_the_small_shared_memory_pool_and_the_forwarding() -> None:
    """The generated (TLS) configuration, the shipped plain one and ``iorthand router``'s built-in one all
    ride out CPU stalls without dropping commands (see TX_QUEUE_SIZE), forward through a small pool
    (SHM_POOL_SIZE) and let no subscriber hold up the edge's status (forwarding_rules)."""
    configs = {
        "generated": zenoh.Config.from_json5(acl.to_json5(acl.router_config(_dep()))),
        "configs/router.json5": load_router_config(ROOT / "configs" / "router.json5"),
        "built-in": zenoh.Config.from_json5(json.dumps(router_settings(["tcp/127.0.0.1:7447"]))),
    }
    robots = {"generated": _dep().robots}
    for name, zc in configs.items():
        sizes = json.loads(zc.get_json("transport/link/tx/queue/size"))
        assert {k: sizes[k] for k in TX_QUEUE_SIZE} == TX_QUEUE_SIZE, name
        assert json.loads(zc.get_json("transport/link/tx/lease")) == ROUTER_LEASE_MS, name
        assert json.loads(zc.get_json(SHM_POOL_SIZE_KEY)) == SHM_POOL_SIZE, name
        assert json.loads(zc.get_json(ACCEPT_PENDING_KEY)) == ACCEPT_PENDING, name
        # The per-session caps on set-points (rate_limits), as Zenoh reads them back; not in the built-in router
        # (see rate_limits).
        caps = [{k: item[k] for k in ("flows", "messages", "rules")} for item in json.loads(zc.get_json("downsampling"))]
        assert caps == ([] if name == "built-in" else rate_limits(robots.get(name, ("*",)))), name
        # The edge's status dropped for a subscriber that stops reading, not held up for all (forwarding_rules).
        rules = [{k: item[k] for k in ("id", "messages", "flows", "key_exprs")} | {"overwrite": {
            "congestion_control": item["overwrite"]["congestion_control"]}} for item in json.loads(zc.get_json("qos/network"))]
        assert rules == forwarding_rules(), name
    # A router that dials another carries every operator's messages on that link: no cap there.
    assert "downsampling" not in acl.router_config(_dep(connect=["tls/cloud.example.org:7447"]))


def test_a_router_that_dials_another_announces_the_longer_lease() -> None:
    """Equal leases on a router-to-router link race after an outage (see DIALING_LEASE_EXTRA_MS)."""
    assert DIALING_LEASE_EXTRA_MS > 0
    site = zenoh.Config.from_json5(json.dumps(router_settings(["tcp/127.0.0.1:7448"], ["tcp/127.0.0.1:7447"])))
    assert json.loads(site.get_json("transport/link/tx/lease")) == ROUTER_LEASE_MS + DIALING_LEASE_EXTRA_MS
    generated = acl.router_config(_dep(connect=["tls/cloud.example.org:7447"], lease_ms=2500))
    assert generated["transport"]["link"]["tx"]["lease"] == 2500 + DIALING_LEASE_EXTRA_MS
    assert acl.router_config(_dep(lease_ms=2500))["transport"]["link"]["tx"]["lease"] == 2500
    assert router_settings(["tcp/127.0.0.1:7448"], ["tcp/127.0.0.1:7447"], lease_ms=5000)["transport"]["link"]["tx"]["lease"] == 5000


def test_a_router_modelling_its_own_host_shares_no_memory() -> None:
    on = zenoh.Config.from_json5(json.dumps(router_settings(["tcp/127.0.0.1:7447"])))
    off = zenoh.Config.from_json5(json.dumps(router_settings(["tcp/127.0.0.1:7447"], shared_memory=False)))
    assert json.loads(on.get_json("transport/shared_memory/enabled")) is True
    assert json.loads(off.get_json("transport/shared_memory/enabled")) is False


def test_a_deployment_without_bound_keys_is_a_warning() -> None:
    assert acl.Deployment().bind_operator_keys and _dep().warnings() == []
    assert [subject for subject, _ in _dep(bind_operator_keys=False).warnings()] == ["bind_operator_keys"]


def test_deployment_validation() -> None:
    with pytest.raises(ValueError, match="not in robots"):
        _dep(operators={"alice": ["r9"]})
    with pytest.raises(ValueError, match="not encrypted"):
        _dep(listen=["tcp/0.0.0.0:7447"])
    with pytest.raises(ValueError, match="reserved for replayed recordings"):
        _dep(robots=["r1", "r1-replay"])


@pytest.mark.parametrize(
    ("log", "cause"),
    [
        ("Unable to connect to tls/1.2.3.4:7447! Can not create a new TLS link: [1.2.3.4:7447: Connection refused (os error 111)", "nothing listens"),
        ("Unable to connect to tls/h:1! received fatal alert: DecryptError at /x/y.rs:226.", "not signed by the router's CA"),
        ("Unable to connect to tls/h:1! received fatal alert: CertificateRequired", "requires a client certificate"),
        ("Unable to connect to tls/h:1! received fatal alert: CertificateExpired", "expired"),
        ("Unable to connect to tls/h:1! invalid peer certificate: BadSignature", "router's certificate is not signed"),
        ("Unable to connect to tls/h:1! invalid peer certificate: NotValidForName", "does not name the host"),
        ("Received a close message (reason GENERIC) in response to an OpenSyn on: ...", "wrong username or password"),
        ("Unable to connect to tcp/h:1! Read error on TCP link: early eof", "expects TLS"),
    ],
)
def test_explain_maps_zenoh_log_to_a_cause(log: str, cause: str) -> None:
    text = diagnose.explain("\x1b[33m WARN\x1b[0m " + log)
    assert text is not None and cause in text
    assert "/x/y.rs" not in text  # source paths of zenoh are noise to a user


def test_identity_gate() -> None:
    assert identity.operator_from_common_name("operator-alice") == "alice"
    assert identity.operator_from_common_name("edge-r1") is None
    gate = identity.CommandGate(allowed=["alice", "bob"], bind_keys=True)
    k = "iorthand/r1/control/acquire/alice"
    assert not gate.check_acquire(k, "control/acquire", "alice")[0]  # no liveliness token yet
    gate.operator_alive("alice")
    assert gate.check_acquire(k, "control/acquire", "alice") == (True, "")
    ok, why = gate.check_command("iorthand/r1/cmd/twist/alice", "cmd/twist", "bob")
    assert not ok and "authenticated 'alice'" in why
    assert not gate.check_command("iorthand/r1/cmd/twist", "cmd/twist", "alice")[0]
    assert not gate.check_command("iorthand/r1/cmd/twist/carol", "cmd/twist", "carol")[0]  # not in the allow-list
    gate.operator_gone("alice")
    assert not gate.check_acquire(k, "control/acquire", "alice")[0]
    assert identity.CommandGate().check_command("iorthand/r1/cmd/twist", "cmd/twist", "anyone") == (True, "")


def test_a_secret_every_user_can_read_is_an_error(pki: Path, tmp_path: Path) -> None:
    # The documented modes are root:iorthand 0640 (a service) or 0600 (a laptop); 0644 gives the key to every user.
    key = tmp_path / "edge-sim1.key"
    key.write_bytes((pki / "edge-sim1.key").read_bytes())
    pw = tmp_path / "edge-sim1.password"
    pw.write_text("secret\n")
    cfg = ZenohConfig(connect=["tls/127.0.0.1:7447"], username="edge-sim1", password_file=pw,
                      tls=TlsConfig(root_ca=pki / "ca.pem", certificate=pki / "edge-sim1.pem", private_key=key))
    for mode in (0o600, 0o640):
        os.chmod(key, mode)
        os.chmod(pw, mode)
        assert diagnose.precheck(cfg) == []
    os.chmod(key, 0o644)
    os.chmod(pw, 0o602)
    found = {f.subject: f for f in diagnose.precheck(cfg)}
    assert found.keys() == {str(key), str(pw)}
    assert found[str(key)].level == "error" and "read" in found[str(key)].message
    assert found[str(pw)].level == "error" and "write" in found[str(pw)].message
    assert all("chmod 640 (group iorthand" in f.message and "or 600" in f.message for f in found.values())
    # It must be fixed, but it does not explain a failed connection: the diagnosis does not give it as the cause.
    assert diagnose.diagnose(cfg, run_probe=False).cause == "not probed"


def test_tls_settings_with_a_plain_endpoint_to_another_host_is_an_error(pki: Path) -> None:
    tls = TlsConfig(root_ca=pki / "ca.pem", certificate=pki / "edge-sim1.pem", private_key=pki / "edge-sim1.key")

    def found(endpoint: str) -> list[tuple[str, str]]:
        return [(f.level, f.subject) for f in diagnose.precheck(ZenohConfig(connect=[endpoint], tls=tls))]

    assert found("tcp/router.example.org:7447") == [("error", "zenoh.connect")]
    assert found("tcp/10.0.0.5:7447") == [("error", "zenoh.connect")]
    assert found("tcp/127.0.0.1:7447") == [("warning", "zenoh.connect")]  # stays on this machine
    assert found("tcp/[::1]:7447") == [("warning", "zenoh.connect")]
    assert found("tls/router.example.org:7447") == []
    assert [diagnose.endpoint_is_local(ep) for ep in ("tcp/localhost:7447", "tcp/0.0.0.0:7447", "tcp/[::]:7447",
                                                       "unixsock-stream//run/z.sock")] == [True, False, False, True]
