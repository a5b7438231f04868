"""``iorthand web password``: the users file keeps its owner, group and mode, is replaced whole or not at all, and a
new one comes with what to do about its permissions. Found by a review."""

from __future__ import annotations

import argparse
import os
import stat
from pathlib import Path

import pytest

from iorthand_operator.web import cli, users
from tests.conftest import small_disk


def _set(path: Path, name: str, tmp_path: Path) -> int:
    secret = tmp_path / "pw"
    secret.write_text(f"password of {name}\n")
    return cli._password(argparse.Namespace(users_file=str(path), name=name, generate=False, password_file=str(secret)))


def test_a_new_users_file_is_0600_and_says_how_to_give_it_to_the_service(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """DEPLOY §5 says to chgrp/chmod it after: the command did not (the console then cannot read it)."""
    path = tmp_path / "etc" / "web-users.txt"
    assert _set(path, "alice", tmp_path) == 0
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    out = capsys.readouterr().out
    assert f"{path} is new: 0600" in out and f"chgrp iorthand {path} && sudo chmod 0640 {path}" in out
    assert _set(path, "bob", tmp_path) == 0  # an existing file: nothing to say
    assert "chgrp" not in capsys.readouterr().out
    assert sorted(users.parse_users(path.read_text())) == ["alice", "bob"]
    assert [p.name for p in path.parent.iterdir()] == ["web-users.txt"]  # no temporary file left


def test_an_existing_users_file_keeps_its_owner_group_and_mode(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "web-users.txt"
    assert _set(path, "alice", tmp_path) == 0
    # Root gives it another group, as `chgrp iorthand` does (another user keeps its own).
    group = (path.stat().st_gid + 1) % 3 if os.getuid() == 0 else path.stat().st_gid
    os.chown(path, -1, group)
    for mode in (0o640, 0o604):
        os.chmod(path, mode)
        capsys.readouterr()
        assert _set(path, "bob", tmp_path) == 0
        st = path.stat()
        assert (stat.S_IMODE(st.st_mode), st.st_gid) == (mode, group)
        warned = "readable by every user (mode 0604, kept)" in capsys.readouterr().out
        assert warned == (mode == 0o604)


@pytest.fixture
def full_tmpfs(tmp_path: Path):
    """A small tmpfs filled up: a disk that is really full (root only)."""
    with small_disk(tmp_path, "64k") as mnt:
        yield mnt


def test_a_full_disk_leaves_the_users_file_as_it_was(
    full_tmpfs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Before, the file was truncated and then written in place: on a full disk every user's password was lost
    (and a traceback printed)."""
    path = full_tmpfs / "web-users.txt"
    path.write_text(users.format_users({f"user{i:02d}": users.hash_password("pw", b"\0" * 16) for i in range(42)}))
    assert 3900 < path.stat().st_size < 4096  # one more user needs another page of the tmpfs
    before = path.read_bytes()
    with (full_tmpfs / "filler").open("wb", buffering=0) as filler, pytest.raises(OSError):
        while True:
            filler.write(b"\0" * 512)
    assert _set(path, "newcomer", tmp_path) == 2
    assert path.read_bytes() == before
    err = capsys.readouterr().err
    assert f"cannot write {path}: No space left on device; nothing written, the file is as it was" in err
    assert sorted(p.name for p in full_tmpfs.iterdir()) == ["filler", "web-users.txt"]
