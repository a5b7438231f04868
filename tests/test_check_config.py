"""``iorthand check --config``: validates a configuration and its certificate paths without starting anything."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import yaml

from iorthand.check import check_file
from iorthand.security.lab import Lab, make_lab
from tests.conftest import iorthand_cmd


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Lab:
    return make_lab(tmp_path_factory.mktemp("pki"), 7447, robots=["sim1"], operators={"alice": ["sim1"]})


def _edge_yaml(lab: Lab, path: Path, cert: str = "edge-sim1") -> Path:
    path.write_text(yaml.safe_dump({
        "robot_id": "sim1",
        "zenoh": {"connect": [lab.endpoint], "username": "edge-sim1", "password_file": str(lab.directory / "edge-sim1.password"),
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
    rep = check_file(_edge_yaml(lab, tmp_path / "edge2.yaml", cert="twin"), router_config=lab.router_config)
    assert rep.ok  # twin has a subject
    (lab.directory / "users.txt").exists()
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
