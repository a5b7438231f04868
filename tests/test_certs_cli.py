"""``iorthand certs``: issuing and passwords refuse to replace what a deployed service uses; ``show`` counts days."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import pytest

from iorthand.cli import main
from iorthand.security import certs


@pytest.fixture()
def ca(tmp_path: Path) -> Path:
    certs.init_ca(tmp_path)
    return tmp_path


def test_issue_refuses_to_replace_a_key_without_force(ca: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["certs", "issue", "edge-sim1", "--dir", str(ca)]) == 0
    key = (ca / "edge-sim1.key").read_bytes()
    # Twin is new, edge-sim1 exists: nothing at all is issued, and the message names the files and the way out.
    assert main(["certs", "issue", "twin", "edge-sim1", "--dir", str(ca)]) == 1
    err = capsys.readouterr().err
    assert "edge-sim1.pem" in err and "edge-sim1.key" in err and "--force" in err
    assert (ca / "edge-sim1.key").read_bytes() == key and not (ca / "twin.pem").exists()
    assert main(["certs", "issue", "edge-sim1", "--dir", str(ca), "--force"]) == 0
    assert (ca / "edge-sim1.key").read_bytes() != key


def test_password_refuses_to_replace_a_password_without_force(ca: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["certs", "password", "edge-sim1", "--dir", str(ca)]) == 0
    assert main(["certs", "password", "twin", "--dir", str(ca)]) == 0
    before = ((ca / "edge-sim1.password").read_text(), (ca / "users.txt").read_text())
    assert main(["certs", "password", "edge-sim1", "--dir", str(ca)]) == 1
    err = capsys.readouterr().err
    assert "edge-sim1.password" in err and "users.txt" in err and "--force" in err
    assert ((ca / "edge-sim1.password").read_text(), (ca / "users.txt").read_text()) == before
    # Only the dictionary has the name (its password file was deleted): still refused.
    (ca / "edge-sim1.password").unlink()
    assert main(["certs", "password", "edge-sim1", "--dir", str(ca)]) == 1
    assert main(["certs", "password", "edge-sim1", "--dir", str(ca), "--force"]) == 0
    new = (ca / "edge-sim1.password").read_text().strip()
    lines = (ca / "users.txt").read_text().splitlines()
    assert f"edge-sim1:{new}" in lines and len(lines) == 2 and new != before[0].strip()


def test_show_counts_whole_days_toward_zero(ca: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Expired a day (and a few seconds) ago: -1 day left, not -2.
    now = dt.datetime.now(dt.UTC)
    old = certs.issue(ca, "operator-old", days=365, not_before=now - dt.timedelta(days=366, seconds=5))
    assert main(["certs", "show", str(old.certificate), "--json"]) == 1
    info = json.loads(capsys.readouterr().out)
    assert info["expired"] and info["days_left"] == -1, info
    fresh = certs.issue(ca, "operator-new", days=30)
    main(["certs", "show", str(fresh.certificate), "--json"])
    assert json.loads(capsys.readouterr().out)["days_left"] == 29  # 30 days less the moment since it was issued
