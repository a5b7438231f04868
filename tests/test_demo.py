"""The README's front door: ``iorthand demo`` runs the whole system (router, edge, twin, recorder, a scripted operator,
the session report) and exits 0 with its summary.

Not serial: the demo must work on a new user's busy laptop. Beside a one-core CPU hog (stress-ng --cpu 1) it passed
3 times of 3, which is more load than a neighbouring test puts on the machine."""

from __future__ import annotations

import subprocess

import pytest

from tests.conftest import iorthand_cmd


@pytest.mark.slow
def test_demo_exits_zero(tmp_path) -> None:
    result = subprocess.run(iorthand_cmd("demo", "--workdir", str(tmp_path)), capture_output=True, text=True, timeout=180)
    assert result.returncode == 0, result.stderr + result.stdout
    assert "summary" in result.stdout and "deadman stop" in result.stdout
