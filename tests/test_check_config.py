"""``iorthand check --config``: validates a configuration and its certificate paths without starting anything."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest
import yaml

from iorthand.check import check_file
from iorthand.security import acl, certs
from iorthand.security.lab import Lab, make_lab
from tests.conftest import ROOT, iorthand_cmd


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Lab:
    return make_lab(tmp_path_factory.mktemp("pki"), 7447, robots=["sim1"], operators={"alice": ["sim1"]})


def _edge_yaml(lab: Lab, path: Path, cert: str = "edge-sim1", robot_id: str = "sim1", username: str = "edge-sim1",
               password_file: Path | None = None) -> Path:
    path.write_text(yaml.safe_dump({
        "robot_id": robot_id,
        "zenoh": {"connect": [lab.endpoint], "username": username,
                  "password_file": str(password_file or lab.directory / f"{username}.password"),
                  "tls": {"root_ca": str(lab.directory / "ca.pem"), "certificate": str(lab.directory / f"{cert}.pem"),
                          "private_key": str(lab.directory / f"{cert}.key")}},
        "robot": {"kind": "sim"},
    }))
    return path


def test_good_edge_config(lab: Lab, tmp_path: Path) -> None:
    rep = check_file(_edge_yaml(lab, tmp_path / "edge.yaml"), router_config=lab.router_config)
    assert rep.role == "edge" and rep.ok, rep.text(Path("edge.yaml"))


def test_missing_certificate_and_unknown_subject(lab: Lab, tmp_path: Path) -> None:
    rep = check_file(_edge_yaml(lab, tmp_path / "edge.yaml", cert="edge-nope"))
    assert not rep.ok and any("does not exist" in f.message for f in rep.findings)
    # twin has a subject in the router's ACL, but it is not this edge's identity: that alone is an error.
    rep = check_file(_edge_yaml(lab, tmp_path / "edge2.yaml", cert="twin"), router_config=lab.router_config)
    assert not rep.ok and not any("has no subject" in f.message for f in rep.findings)
    assert any("'twin' is not this edge's identity 'edge-sim1'" in f.message for f in rep.findings), rep.text(Path("e"))
    from iorthand.security import certs

    certs.issue(lab.directory, "operator-mallory")
    rep = check_file(_edge_yaml(lab, tmp_path / "edge3.yaml", cert="operator-mallory"), router_config=lab.router_config)
    assert any("silently ignored" in f.message for f in rep.findings)


def test_router_and_deployment_configs(lab: Lab, tmp_path: Path) -> None:
    assert check_file(lab.router_config).ok
    dep = tmp_path / "deployment.yaml"
    dep.write_text(yaml.safe_dump({"certs_dir": str(lab.directory), "robots": ["sim1"], "operators": {"alice": ["sim1"]},
                                   "listen": ["tls/0.0.0.0:7447"]}))
    rep = check_file(dep)
    assert rep.role == "deployment" and rep.ok


def test_cli_exit_codes(lab: Lab, tmp_path: Path) -> None:
    good = _edge_yaml(lab, tmp_path / "edge.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("robot_id: [unclosed")
    missing = _edge_yaml(lab, tmp_path / "missing.yaml", cert="edge-nope")
    out = {name: subprocess.run(iorthand_cmd("check", "--config", str(p)), capture_output=True, text=True, timeout=60)
           for name, p in (("good", good), ("bad", bad), ("missing", missing))}
    assert out["good"].returncode == 0, out["good"].stdout + out["good"].stderr
    assert out["bad"].returncode == 2 and "not valid YAML" in out["bad"].stdout
    assert out["missing"].returncode == 1 and "edge-nope.pem" in out["missing"].stdout


def test_an_edge_nothing_can_arm_is_a_warning(tmp_path: Path) -> None:
    # auto_arm is false by default: without the local socket no one could ever confirm arming.
    base = {"robot_id": "sim1", "zenoh": {"connect": ["tcp/127.0.0.1:7447"]}, "robot": {"kind": "sim"}}
    path = tmp_path / "edge.yaml"
    path.write_text(yaml.safe_dump(base))
    rep = check_file(path)
    assert rep.ok  # a warning, not an error: the agent runs, and says so in its log
    assert [(f.level, f.subject) for f in rep.findings if "arming" in f.message] == [("warning", "local_socket")]
    path.write_text(yaml.safe_dump({**base, "local_socket": str(tmp_path / "edge.sock")}))
    assert not [f for f in check_file(path).findings if "arming" in f.message]
    path.write_text(yaml.safe_dump({**base, "safety": {"auto_arm": True}}))
    assert not [f for f in check_file(path).findings if "arming" in f.message]


def test_bind_operator_keys_off_behind_security_is_a_warning(lab: Lab, tmp_path: Path) -> None:
    # The generated router binds operators' command keys by default: an edge or an operator that does not use
    # them on a secured link cannot work with it, and a deployment without them trusts the name in a command.
    edge = _edge_yaml(lab, tmp_path / "edge.yaml")
    operator = tmp_path / "operator.yaml"
    operator.write_text(yaml.safe_dump({
        "operator_id": "alice", "robot": "sim1",
        "zenoh": {"connect": [lab.endpoint], "tls": {"root_ca": str(lab.directory / "ca.pem"),
                  "certificate": str(lab.directory / "operator-alice.pem"),
                  "private_key": str(lab.directory / "operator-alice.key")}},
    }))

    def unbound(path: Path, data: dict, **overrides: object) -> list[str]:
        path.write_text(yaml.safe_dump({**data, **overrides}))
        return [f.level for f in check_file(path).findings if f.subject == "bind_operator_keys"]

    for path in (edge, operator):
        data = yaml.safe_load(path.read_text())
        assert unbound(path, data) == ["warning"], path.name  # the edge's and the operator's default: an open router
        assert unbound(path, data, bind_operator_keys=True) == []
        assert unbound(path, data, zenoh={"connect": ["tcp/127.0.0.1:7447"]}) == []  # no security: nothing to bind to
    dep = tmp_path / "deployment.yaml"
    base = {"certs_dir": str(lab.directory), "robots": ["sim1"], "operators": {"alice": ["sim1"]}}
    dep.write_text(yaml.safe_dump(base))
    assert [f.subject for f in check_file(dep).findings if f.level == "warning"] == []  # bound by default
    dep.write_text(yaml.safe_dump({**base, "bind_operator_keys": False}))
    assert [f.subject for f in check_file(dep).findings if f.level == "warning"] == ["bind_operator_keys"]


def _router(lab: Lab, path: Path, listen: str = "tls/0.0.0.0:7447", **changes: object) -> Path:
    """The lab's generated router configuration, listening on ``listen``, with parts changed (a dotted key set to
    None is removed)."""
    cfg = acl.router_config(lab.deployment)
    cfg["listen"] = {"endpoints": [listen]}
    for dotted, value in changes.items():
        *parents, last = dotted.split(".")
        node = cfg
        for part in parents:
            node = node[part]
        if value is None:
            node.pop(last, None)
        else:
            node[last] = value
    path.write_text(json.dumps(cfg))
    return path


def _errors(path: Path) -> dict[str, str]:
    rep = check_file(path)
    return {f.subject: f.message for f in rep.findings if f.level == "error"}


def test_a_router_reachable_from_the_network_must_encrypt_authenticate_and_filter(lab: Lab, tmp_path: Path) -> None:
    # What the walkthrough ran: tcp/0.0.0.0 in clear, no ACL, default allow, no user/password, no mTLS. The
    # router's systemd unit runs check before starting it: every one of these must stop it.
    assert check_file(_router(lab, tmp_path / "good.json5")).ok  # the generated configuration, on every address
    assert _errors(_router(lab, tmp_path / "clear.json5", listen="tcp/0.0.0.0:7447")).keys() == {"listen.endpoints"}
    assert "tls/HOST:PORT" in _errors(tmp_path / "clear.json5")["listen.endpoints"]
    assert _errors(_router(lab, tmp_path / "noacl.json5", **{"access_control.enabled": False})).keys() == {"access_control"}
    assert _errors(_router(lab, tmp_path / "allow.json5", **{"access_control.default_permission": "allow"})).keys() == {
        "access_control.default_permission"}
    # Neither client certificates nor passwords: nobody is authenticated.
    open_router = _router(lab, tmp_path / "noauth.json5", **{"transport.link.tls.enable_mtls": False, "transport.auth": None,
                                                             "access_control.enabled": False})
    errors = _errors(open_router)
    assert errors.keys() == {"transport.link.tls.enable_mtls", "transport.auth.usrpwd", "access_control"}
    assert "no one is authenticated" in errors["access_control"] and "every authenticated" not in errors["access_control"]
    # mTLS without passwords still authenticates every client: a finding, not an error.
    rep = check_file(_router(lab, tmp_path / "nopw.json5", **{"transport.auth": None}))
    assert rep.ok and [f.subject for f in rep.findings if f.level == "warning"] == ["transport.auth.usrpwd"]
    # Zenoh's default listener (no listen section) is tcp/[::]:7447: in clear, on every address.
    cfg = json.loads((tmp_path / "good.json5").read_text())
    del cfg["listen"]
    (tmp_path / "default.json5").write_text(json.dumps(cfg))
    assert "listen.endpoints" in _errors(tmp_path / "default.json5")
    r = subprocess.run(iorthand_cmd("check", "--config", str(open_router)), capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "PROBLEMS FOUND" in r.stdout, r.stdout + r.stderr


def test_a_loopback_router_may_stay_open_for_development(lab: Lab, tmp_path: Path) -> None:
    # make demo, the tests and the local-dev files: a router on 127.0.0.1 in clear, without ACL, is fine.
    for path in (ROOT / "configs" / "router.json5", ROOT / "deploy" / "router" / "router.local-dev.json5"):
        rep = check_file(path)
        assert rep.ok, rep.text(path)
    rep = check_file(_router(lab, tmp_path / "local.json5", listen="tcp/127.0.0.1:7447",
                             **{"access_control.enabled": False, "transport.auth": None}))
    assert rep.ok and {f.subject for f in rep.findings} == {"access_control"}, rep.text(Path("local.json5"))


def test_a_router_that_forwards_the_edges_status_as_published_is_warned_about(lab: Lab, tmp_path: Path) -> None:
    """Without the egress rules, one hung subscriber holds up the edge's status for everyone (forwarding_rules)."""
    def warned(path: Path) -> str:
        return " ".join(f.message for f in check_file(path).findings if f.subject == "qos.network")

    local = {"access_control.enabled": False, "transport.auth": None}
    assert warned(_router(lab, tmp_path / "generated.json5", listen="tcp/127.0.0.1:7447", **local)) == ""
    said = warned(_router(lab, tmp_path / "old.json5", listen="tcp/127.0.0.1:7447", qos=None, **local))
    assert "iorthand/*/state/safety, iorthand/*/state/force_level forwarded as published" in said, said
    # A rule of its own that drops every key's puts covers them; one that blocks does not.
    for mode, expected in (("drop", ""), ("block", "iorthand/*/state/safety")):
        rules = {"network": [{"messages": ["put"], "flows": ["egress"], "overwrite": {"congestion_control": mode}}]}
        said = warned(_router(lab, tmp_path / f"{mode}.json5", listen="tcp/127.0.0.1:7447", qos=rules, **local))
        assert expected in said if expected else said == "", (mode, said)


def test_the_identity_must_be_the_roles_own(lab: Lab, tmp_path: Path) -> None:
    def errors(path: Path, **kw: object) -> list[str]:
        return [f"{f.subject}: {f.message}" for f in check_file(path, **kw).findings if f.level == "error"]

    certs.issue(lab.directory, "edge-sim2")
    # edge-sim1's certificate on robot sim2: the router gives sim2's keys to edge-sim2 only.
    said = errors(_edge_yaml(lab, tmp_path / "e1.yaml", robot_id="sim2"))
    assert len(said) == 2 and "'edge-sim1' is not this edge's identity 'edge-sim2'" in said[0], said
    assert "username: 'edge-sim1' is not 'edge-sim2'" in said[1], said
    # An operator's certificate on an edge.
    assert any("'operator-alice' is not this edge's identity" in e for e in errors(
        _edge_yaml(lab, tmp_path / "e2.yaml", cert="operator-alice", username="operator-alice")))
    # The right certificate, another role's user name (and password).
    said = errors(_edge_yaml(lab, tmp_path / "e3.yaml", username="twin"))
    assert said == [said[0]] and "'twin' is not 'edge-sim1'" in said[0] and "silently ignored" in said[0], said
    # An operator whose certificate is another operator's.
    operator = tmp_path / "operator.yaml"
    operator.write_text(yaml.safe_dump({
        "operator_id": "bob", "robot": "sim1", "bind_operator_keys": True,
        "zenoh": {"connect": [lab.endpoint], "username": "operator-alice",
                  "password_file": str(lab.directory / "operator-alice.password"),
                  "tls": {"root_ca": str(lab.directory / "ca.pem"), "certificate": str(lab.directory / "operator-alice.pem"),
                          "private_key": str(lab.directory / "operator-alice.key")}},
    }))
    said = errors(operator)
    assert any("'operator-alice' is not this operator's identity 'operator-bob'" in e for e in said), said
    data = yaml.safe_load(operator.read_text())
    # (bind_operator_keys as the lab's router: not bound)
    operator.write_text(yaml.safe_dump({**data, "operator_id": "alice", "bind_operator_keys": False}))
    assert errors(operator, router_config=lab.router_config) == []


def test_the_password_must_be_the_routers(lab: Lab, tmp_path: Path) -> None:
    wrong = tmp_path / "edge-sim1.password"
    wrong.write_text("not-the-password\n")
    os.chmod(wrong, 0o600)
    path = _edge_yaml(lab, tmp_path / "edge.yaml", password_file=wrong)
    assert check_file(path).ok  # without the router's dictionary nothing says it is wrong
    rep = check_file(path, router_config=lab.router_config)
    assert [f.subject for f in rep.findings if f.level == "error"] == [str(wrong)], rep.text(path)
    # A user the dictionary does not have (issued after the router's users.txt was installed).
    certs.issue(lab.directory, "edge-sim9")
    (tmp_path / "edge-sim9.password").write_text("whatever")
    os.chmod(tmp_path / "edge-sim9.password", 0o600)
    rep = check_file(_edge_yaml(lab, tmp_path / "e9.yaml", cert="edge-sim9", robot_id="sim9", username="edge-sim9",
                                password_file=tmp_path / "edge-sim9.password"), router_config=lab.router_config)
    assert any("'edge-sim9' is not in the router's dictionary" in f.message for f in rep.findings), rep.text(path)


def _web_yaml(lab: Lab, path: Path, deployment: dict, **overrides: object) -> Path:
    certs.issue(lab.directory, "web")
    (lab.directory / "web.password").write_text("pw-web")
    os.chmod(lab.directory / "web.password", 0o600)
    (path.parent / "deployment.yaml").write_text(yaml.safe_dump(deployment))
    (path.parent / "web-users.txt").write_text("")
    path.write_text(yaml.safe_dump({
        "deployment": "deployment.yaml", "users_file": "web-users.txt", "listen": "127.0.0.1:8443",
        "bind_operator_keys": True,
        "zenoh": {"connect": [lab.endpoint], "username": "web", "password_file": str(lab.directory / "web.password"),
                  "tls": {"root_ca": str(lab.directory / "ca.pem"), "certificate": str(lab.directory / "web.pem"),
                          "private_key": str(lab.directory / "web.key")}},
        **overrides,
    }))
    return path


def test_a_secured_web_console_needs_web_true_and_bound_keys(lab: Lab, tmp_path: Path) -> None:
    dep = {"certs_dir": str(lab.directory), "robots": ["sim1"], "operators": {"alice": ["sim1"]}}
    rep = check_file(_web_yaml(lab, tmp_path / "web.yaml", dep))
    assert rep.role == "web"
    assert [(f.level, Path(f.subject).name) for f in rep.findings] == [("error", "deployment.yaml")], rep.text(Path("w"))
    assert "web: true" in rep.findings[0].message and "regenerate" in rep.findings[0].message
    assert check_file(_web_yaml(lab, tmp_path / "web.yaml", {**dep, "web": True})).ok
    # bind_operator_keys off behind the router's bound keys: "no answer from robot on control/acquire" (it was
    # a warning, and the other way round one too).
    for bind in (False, True):
        rep = check_file(_web_yaml(lab, tmp_path / "web.yaml", {**dep, "web": True, "bind_operator_keys": not bind},
                                   bind_operator_keys=bind))
        said = [f.message for f in rep.findings if f.subject == "bind_operator_keys"]
        assert not rep.ok and len(said) == 1 and said[0].startswith(f"{str(bind).lower()} here but "
                                                                      f"{str(not bind).lower()} in "), said
    # The development console (plain TCP on loopback, a deployment without web: true) stays fine.
    rep = check_file(ROOT / "configs" / "web.yaml")
    assert not [f for f in rep.findings if f.subject == "bind_operator_keys" or "web: true" in f.message]


@pytest.mark.parametrize("role", ["edge", "operator"])
def test_bind_operator_keys_must_be_the_deployments(lab: Lab, tmp_path: Path, role: str) -> None:
    """Found by a review: an edge's or operator's bind_operator_keys was never compared with the deployment's
    (commands refused by the router's ACL or not heard by the edge; or a weaker binding than deployed), only
    warned about when off on a secured link."""
    if role == "edge":
        path = _edge_yaml(lab, tmp_path / "edge.yaml")
    else:
        path = tmp_path / "operator.yaml"
        path.write_text(yaml.safe_dump({
            "operator_id": "alice", "robot": "sim1",
            "zenoh": {"connect": [lab.endpoint], "username": "operator-alice",
                      "password_file": str(lab.directory / "operator-alice.password"),
                      "tls": {"root_ca": str(lab.directory / "ca.pem"),
                              "certificate": str(lab.directory / "operator-alice.pem"),
                              "private_key": str(lab.directory / "operator-alice.key")}},
        }))
    data = yaml.safe_load(path.read_text())
    dep = tmp_path / "deployment.yaml"
    bound_router = tmp_path / "router-bound.json5"
    base = {"certs_dir": str(lab.directory), "robots": ["sim1"], "operators": {"alice": ["sim1"]}}
    bound_router.write_text(acl.to_json5(acl.router_config(acl.Deployment(**base, bind_operator_keys=True))))
    for ours in (False, True):
        path.write_text(yaml.safe_dump({**data, "bind_operator_keys": ours}))
        for deployed in (False, True):
            dep.write_text(yaml.safe_dump({**base, "bind_operator_keys": deployed}))
            rep = check_file(path, deployment=dep)
            said = [f for f in rep.findings if f.subject == "bind_operator_keys"]
            if ours == deployed:
                assert said == [], rep.text(path)
                continue
            assert not rep.ok and [f.level for f in said] == ["error"], rep.text(path)
            assert said[0].message.startswith(f"{str(ours).lower()} here but {str(deployed).lower()} in {dep}: ")
        # The router's ACL says it too (the lab's router does not bind, this one does).
        for router, deployed in ((lab.router_config, False), (bound_router, True)):
            said = [f for f in check_file(path, router_config=router).findings if f.subject == "bind_operator_keys"]
            assert [f.level for f in said if f.level == "error"] == ([] if ours == deployed else ["error"])
            if ours != deployed:
                assert f"here but {str(deployed).lower()} in {router} (its operators' command rules)" in said[0].message
    rep = check_file(path, deployment=tmp_path / "nope.yaml")
    assert any(f.subject == str(tmp_path / "nope.yaml") and f.level == "error" for f in rep.findings)


def test_the_routers_binding_is_read_back_from_its_acl() -> None:
    base = {"robots": ["r1"], "operators": {"alice": ["r1"]}, "web": True}
    for bind in (False, True):
        assert acl.bound_operator_keys(acl.router_config(acl.Deployment(**base, bind_operator_keys=bind))) is bind
    assert acl.bound_operator_keys(acl.router_config(acl.Deployment(robots=["r1"]))) is None  # no operator
    assert acl.bound_operator_keys({"mode": "router"}) is None


def test_a_recorder_folder_it_cannot_write_is_an_error(tmp_path: Path) -> None:
    """Found by a review: `iorthand check` said OK for a recorder whose output_dir could never be made (every
    recording refused once the service ran) and whose calibration file was missing (left out of every
    recording without a word at check time)."""
    (tmp_path / "afile").write_text("")
    path = tmp_path / "recorder.yaml"
    path.write_text(yaml.safe_dump({
        "zenoh": {"mode": "client", "connect": ["tcp/127.0.0.1:7447"]},
        "output_dir": str(tmp_path / "afile" / "recordings"),
        "calibration_files": [str(tmp_path / "hand-eye.yaml")],
    }))
    rep = check_file(path)
    said = {(f.level, f.subject): f.message for f in rep.findings}
    assert not rep.ok and "is not a folder: no recording can be made" in said[("error", "output_dir")]
    assert "recordings are made without it" in said[("warning", str(tmp_path / "hand-eye.yaml"))]
    path.write_text(yaml.safe_dump({"zenoh": {"mode": "client", "connect": ["tcp/127.0.0.1:7447"]},
                                    "output_dir": str(tmp_path / "new" / "recordings")}))
    assert check_file(path).ok  # a folder the recorder creates


def test_a_recorder_folder_the_service_user_cannot_write_is_an_error(tmp_path_factory: pytest.TempPathFactory) -> None:
    """As the service user (DEPLOY: `sudo -u iorthand iorthand check`), here nobody: root may write anywhere."""
    import shutil
    import tempfile

    if os.geteuid() != 0 or shutil.which("setpriv") is None:
        pytest.skip("running as another user needs root and setpriv")
    folder = Path(tempfile.mkdtemp(prefix="check-recorder-"))  # (pytest's own folders are closed to others)
    try:
        folder.chmod(0o755)
        (folder / "recordings").mkdir(mode=0o755)
        configs = {}
        (folder / "replay.password").write_text("pw")
        replay = {"username": "replay", "password_file": str(folder / "replay.password")}
        for name, extra in (("recorder", {}), ("replay", replay)):
            configs[name] = folder / f"{name}.yaml"
            configs[name].write_text(yaml.safe_dump({
                "zenoh": {"mode": "client", "connect": ["tcp/127.0.0.1:7447"], **extra},
                "output_dir": str(folder / "recordings"),
            }))
            configs[name].chmod(0o644)
        out = {name: subprocess.run(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups",
                                     *iorthand_cmd("check", "--config", str(p), "--role", "recorder")],
                                    capture_output=True, text=True, timeout=60).stdout for name, p in configs.items()}
        assert "is not writable by this user (uid 65534): every recording would be refused" in out["recorder"]
        assert "replay.yaml: recorder configuration" in out["replay"] and "output_dir" not in out["replay"], out
        # (a replay only reads the recordings)
    finally:
        shutil.rmtree(folder)
