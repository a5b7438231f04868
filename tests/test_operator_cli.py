"""``iorthand operator`` argument mistakes: refused in one line before anything connects."""

from __future__ import annotations

import subprocess
from pathlib import Path

from tests.conftest import iorthand_cmd


def test_a_move_with_every_velocity_zero_is_refused(tmp_path: Path) -> None:
    """Found by a review of the operator side: ``operator move`` with no velocity (all default to 0) took control,
    held it for --seconds and moved nothing. Refused now like the CLI's other argument errors (exit 2), before it
    connects: the endpoint here has no router, and a move that got as far as connecting would wait for one."""
    r = subprocess.run(iorthand_cmd("operator", "--connect", "tcp/127.0.0.1:9", "move", "--seconds", "1"),
                       capture_output=True, text=True, timeout=20, cwd=tmp_path, stdin=subprocess.DEVNULL)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert "--vx/--vy/--vz: all zero: the move would move nothing" in r.stderr, r.stderr
