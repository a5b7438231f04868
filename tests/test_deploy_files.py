"""What an installer runs, checked by the tools that run it. The systemd units in deploy/systemd, read by systemd
itself: ``systemd-analyze verify`` names every key it does not know or that sits in the wrong section (such a
line is ignored at boot, silently for the user); the executables live in /opt/iorthand on a deployed host, so
that they are missing here is the one thing it may say. The shell scripts, read by shellcheck. Each test skips
where its tool is not installed (``make test`` installs both as root). And the example router configuration,
which must be what the generator writes for the example deployment."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from iorthand.check import check_file
from iorthand.config import load
from iorthand.security import acl
from iorthand_edge.config import load_edge_config

ROOT = Path(__file__).resolve().parents[1]
UNITS = sorted((ROOT / "deploy" / "systemd").glob("*.service"))
SCRIPTS = [ROOT / "deploy" / "pi-setup.sh", ROOT / "scripts" / "install-test-deps.sh", ROOT / ".ci" / "run"]


def test_every_service_is_checked() -> None:
    assert {u.name for u in UNITS} >= {"iorthand-edge.service", "iorthand-router.service"}


@pytest.mark.parametrize("unit", UNITS, ids=lambda u: u.name)
def test_systemd_takes_every_line_of_the_unit(unit: Path, tmp_path: Path) -> None:
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not installed")
    copy = tmp_path / unit.name  # verify loads the unit's whole directory: give it this one alone
    shutil.copy(unit, copy)
    r = subprocess.run([analyze, "verify", "--man=no", str(copy)], capture_output=True, text=True, timeout=60,
                       env={**os.environ, "SYSTEMD_LOG_LEVEL": "warning"})
    said = [line for line in (r.stdout + r.stderr).splitlines() if line.strip()]
    assert [line for line in said if "is not executable" not in line] == [], said


def test_the_shell_scripts_pass_shellcheck() -> None:
    shellcheck = shutil.which("shellcheck")
    if shellcheck is None:
        pytest.skip("shellcheck is not installed")
    r = subprocess.run([shellcheck, "--shell=bash", *map(str, SCRIPTS)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr


def test_the_example_router_configuration_is_what_the_generator_writes() -> None:
    # A reviewer reads this file to see what a deployment gets: it must not lag behind the generator.
    generated = acl.to_json5(acl.router_config(load(ROOT / "deploy" / "deployment.example.yaml", acl.Deployment)))
    assert (ROOT / "deploy" / "router" / "router.example.json5").read_text() == generated, (
        "regenerate: iorthand certs router-config --deployment deploy/deployment.example.yaml "
        "--out deploy/router/router.example.json5")


def test_the_pi_can_arm_its_robot() -> None:
    # The deployed edge is armed only by local confirmation, through a socket in the unit's runtime directory
    # (the one place under /run its user may write with ProtectSystem=strict).
    edge = load_edge_config(ROOT / "deploy" / "configs" / "edge.yaml")
    assert not edge.safety.auto_arm and edge.warnings() == []
    unit = (ROOT / "deploy" / "systemd" / "iorthand-edge.service").read_text().splitlines()
    assert edge.local_socket is not None and f"RuntimeDirectory={edge.local_socket.parent.name}" in unit
    assert edge.local_socket.parent.parent == Path("/run")


@pytest.mark.parametrize("name", ["edge", "operator", "twin", "recorder", "replay", "web"])
def test_each_deploy_config_loads_as_its_role_and_misses_only_the_installed_files(name: str) -> None:
    # The configurations an installer copies to /etc/iorthand (or ~/.config/iorthand): their role is told from
    # the file, every key loads, and all that is wrong here is that no certificate has been installed.
    path = ROOT / "deploy" / "configs" / f"{name}.yaml"
    rep = check_file(path)
    assert rep.role == {"replay": "recorder"}.get(name, name)
    errors = [f for f in rep.findings if f.level == "error"]
    assert errors and all("does not exist" in f.message for f in errors), errors
    assert [f for f in rep.findings if f.level == "warning"] == []


@pytest.mark.parametrize("name", ["twin", "recorder", "replay"])
def test_the_cloud_services_dial_the_router_on_the_loopback_with_their_own_identity(name: str) -> None:
    zenoh = yaml.safe_load((ROOT / "deploy" / "configs" / f"{name}.yaml").read_text())["zenoh"]
    assert zenoh["connect"] == ["tls/127.0.0.1:7447"] and zenoh["username"] == name
    assert zenoh["tls"]["certificate"] == f"/etc/iorthand/certs/{name}.pem"
