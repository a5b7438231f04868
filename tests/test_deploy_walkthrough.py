"""What a hospital-IT walkthrough of docs/DEPLOY.md ran into: commands that ended in a traceback, and steps the
guide left out."""

from __future__ import annotations

import argparse
import re
import subprocess
from pathlib import Path

import pytest

from tests.conftest import ROOT, iorthand_cmd

DEPLOY_DOC = ROOT / "docs" / "DEPLOY.md"


class _Silent:
    """An operator client connected to a router where no edge answers (what ``connect`` returns there)."""

    def __init__(self) -> None:
        self.session = self
        self.closed = 0

    def wait_for_state(self, timeout: float = 5.0) -> None:
        raise TimeoutError(f"no state from robot 'ur5e-lyon' within {timeout} s")

    def start(self) -> None:
        raise AssertionError("nothing may start without the robot's state")

    def close(self) -> None:
        self.closed += 1


def test_operator_move_without_an_edge_says_what_to_check(monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    from iorthand_operator import cli

    client = _Silent()
    monkeypatch.setattr(cli, "connect", lambda config: client)
    args = argparse.Namespace(config=None, robot="ur5e-lyon", operator_id="dr-martin",
                              connect=["tls/router.example.org:7447"], vx=0.005, vy=0.0, vz=0.0, seconds=1.0,
                              patience=1.0)
    code = cli._move(args)  # the old code let the TimeoutError out: a traceback
    err = capsys.readouterr().err
    assert code != 0 and code != 3, code  # 3 is "control refused"
    assert err.count("\n") == 1 and "no state from robot 'ur5e-lyon'" in err, err
    assert "edge agent" in err and "tls/router.example.org:7447" in err and "operator-dr-martin" in err
    assert client.closed == 2  # the client and its session


def _web_password(users: Path, stdin: str, *extra: str) -> subprocess.CompletedProcess[str]:
    # A new session: no controlling terminal, as under ssh with a pipe or in a provisioning script.
    return subprocess.run(iorthand_cmd("web", "password", "dr-martin", "--users-file", str(users), *extra),
                          input=stdin, capture_output=True, text=True, timeout=60, start_new_session=True)


def test_web_password_reads_a_piped_password(tmp_path: Path) -> None:
    users = tmp_path / "web-users.txt"
    r = _web_password(users, "correct horse battery\n")
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    from iorthand_operator.web import users as web_users

    hashes = web_users.parse_users(users.read_text(), str(users))
    assert web_users.check_password("correct horse battery", hashes["dr-martin"])
    r = _web_password(tmp_path / "other.txt", "")
    assert r.returncode == 2 and "Traceback" not in r.stderr and "--password-file" in r.stderr, r.stderr
    assert not (tmp_path / "other.txt").exists()


def _section(number: str) -> str:
    text = DEPLOY_DOC.read_text()
    start = text.index(f"\n## {number}.")
    end = text.find("\n## ", start + 1)
    return text[start:end if end > 0 else None]


def test_the_guide_writes_etc_iorthand_as_root_and_checks_as_the_service_user() -> None:
    # /etc/iorthand is root:iorthand 0750: writing it needs root, and a check as root proves nothing about what
    # the service user can read.
    block = re.search(r"```bash\n(.*?)```", _section("2"), re.S).group(1)
    for line in block.splitlines():
        if "--out /etc/iorthand" in line or "> /etc/iorthand" in line:
            assert line.lstrip().startswith("sudo "), line
        if re.search(r"\biorthand check\b", line):
            assert "sudo -u iorthand " in line, line


def test_the_web_console_section_installs_what_the_router_needs() -> None:
    text = _section("5")
    assert "deploy/configs/web.yaml" in text and (ROOT / "deploy" / "configs" / "web.yaml").exists()
    # web: true in the VM's deployment.yaml (the router's configuration is generated from it), the web identity and
    # the updated users.txt copied there, the router regenerated and restarted.
    assert "/etc/iorthand/deployment.yaml" in text and "web: true" in text
    for name in ("web.pem", "web.key", "web.password", "users.txt"):
        assert name in text, name
    assert "certs router-config --deployment /etc/iorthand/deployment.yaml" in text
    assert "restart iorthand-router" in text
    # Who reads the web users file, and with which ownership.
    assert re.search(r"chgrp iorthand /etc/iorthand/web-users\.txt", text) and "0640 /etc/iorthand/web-users.txt" in text
