"""``iorthand replay`` on a window that holds nothing to replay: refused at once, never looped over."""

from __future__ import annotations

import subprocess
import threading
import time
from pathlib import Path

import pytest
from mcap.writer import CompressionType, Writer

from iorthand.protocol import ForceSample, TwistCommand
from iorthand_cloud.recorder import manifest as mf
from iorthand_cloud.recorder.replay import NothingToReplay, Replayer
from tests.conftest import iorthand_cmd


def _session(folder: Path, commands: int = 50, forces: int = 50) -> Path:
    """One second of twist commands (never replayed) and force samples, as the recorder writes them."""
    folder.mkdir()
    t0 = time.time_ns()
    with (folder / "telemetry-0001.mcap").open("wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start("iorthand", "crafted")
        twist = w.register_channel("iorthand/sim1/cmd/twist", "msgpack", 0)
        force = w.register_channel("iorthand/sim1/state/force", "msgpack", 0)
        for seq in range(1, max(commands, forces) + 1):
            t = t0 + seq * 20_000_000
            if seq <= commands:
                w.add_message(twist, t, TwistCommand(operator="op1", deadman=True).stamp(seq, t).encode(), t, seq)
            if seq <= forces:
                w.add_message(force, t + 1, ForceSample(force=[0.0, 0.0, 2.0]).stamp(seq, t).encode(), t, seq)
        w.finish()
    mf.Manifest(session_id=folder.name, status=mf.COMPLETE, start_t=t0, stop_t=t0 + 10**9).write(folder)
    return folder


def test_an_end_not_after_the_start_is_refused_up_front(session_factory, tmp_path: Path) -> None:
    """Found by a red-team run: --start 5 --end 2 ended in a traceback from mcap, with exit status 0."""
    with pytest.raises(ValueError, match=r"--end 2 s is not after --start 5 s"):
        Replayer(session_factory(), _session(tmp_path / "s"), start=5.0, end=2.0)


def test_a_looped_window_with_nothing_to_replay_stops_and_says_so(session_factory, tmp_path: Path) -> None:
    """Found by a red-team run: `--loop` over a session of operator commands only went round 4319 times in 5 s,
    counting the withheld commands again at each pass."""
    rp = Replayer(session_factory(), _session(tmp_path / "s", forces=0), loop=True, speed=100.0)
    errors: list[Exception] = []

    def run() -> None:
        try:
            rp.run()
        except NothingToReplay as exc:
            errors.append(exc)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(3.0)
    rp.stop_event.set()  # (the old replay would spin until told to stop)
    t.join(3.0)
    assert not t.is_alive() and len(errors) == 1, rp.stats
    assert "nothing to replay in this window" in str(errors[0])
    assert rp.stats.commands_withheld == 50 and rp.stats.loops == 0 and rp.stats.published == 0


def test_a_looped_replay_counts_withheld_commands_once(session_factory, tmp_path: Path) -> None:
    rp = Replayer(session_factory(), _session(tmp_path / "s"), loop=True, speed=100.0)
    rp.on_publish = lambda _r: rp.stop_event.set() if rp.stats.loops >= 2 else None
    rp.run()
    assert rp.stats.loops >= 2 and rp.stats.commands_withheld == 50 and rp.stats.skipped == 50


def test_the_command_line_says_there_is_nothing_to_replay(router_endpoint: str, tmp_path: Path) -> None:
    folder = _session(tmp_path / "s")
    run = subprocess.run(iorthand_cmd("replay", str(folder), "--connect", router_endpoint, "--loop", "--start",
                                      "1000"), capture_output=True, text=True, timeout=60)
    assert run.returncode == 1 and "nothing to replay in this window" in run.stderr, (run.stdout, run.stderr)
    run = subprocess.run(iorthand_cmd("replay", str(folder), "--connect", router_endpoint, "--start", "5",
                                      "--end", "2"), capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and "--end 2 s is not after --start 5 s" in run.stderr, (run.stdout, run.stderr)
