"""The twin's memory while it saves its .rrd (the soak: twin RSS +200 MB over the first 21 minutes).

rerun's ``FileSink`` keeps a manifest entry (~2–4 KB) per chunk in memory until it closes, for the footer it
writes at the end; the twin logs ~2000 chunks a minute (~+10 MB/min). The twin therefore saves without a footer by default
(``viewer.save_footer``): the file is still read by rerun, and its memory stays flat.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from iorthand_cloud.twin.server import rerun_executable

# Runs in a fresh interpreter: the test process's own allocations would hide a few MB.
PROBE = textwrap.dedent("""
    import sys, time, uuid
    from pathlib import Path
    import numpy as np, psutil, rerun as rr
    from iorthand_cloud.twin.config import ViewerConfig
    from iorthand_cloud.twin.server import ViewerServer

    path, n, footer = Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
    cfg = ViewerConfig(serve=False) if footer == "default" else ViewerConfig(serve=False, save_footer=footer == "1")
    # One row per chunk: the chunk count of minutes of a twin in a second.
    rec = rr.RecordingStream("t", recording_id=uuid.uuid4(), batcher_config=rr.ChunkBatcherConfig(flush_num_rows=1))
    server = ViewerServer(cfg, save=path)
    server.start(rec)

    def log(k, offset):
        for i in range(offset, offset + k):
            rec.set_time("time", sequence=i)
            rec.log(f"robots/r{i % 8}", rr.Points3D(np.random.rand(2, 3)), rr.TextLog("x"))
        rec.flush()

    def rss():
        time.sleep(0.3)  # let the file writer drain its queue
        return psutil.Process().memory_info().rss

    log(n, 0)  # warm up (allocator, batcher, encoder, the writer's buffers)
    before = rss()
    log(n, n)
    after = rss()
    server.stop()
    print((after - before) / 1e6)
""")


def _growth_mb(tmp_path: Path, footer: str, n: int = 20000) -> tuple[float, Path]:
    path = tmp_path / f"twin-{footer}.rrd"
    out = subprocess.run([sys.executable, "-c", PROBE, str(path), str(n), footer], capture_output=True, text=True,
                         timeout=120, check=True)
    return float(out.stdout.strip().splitlines()[-1]), path


def _rrd(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([rerun_executable(), "rrd", *args], capture_output=True, text=True, timeout=60)


@pytest.mark.slow
def test_saving_keeps_the_twin_memory_flat(tmp_path):
    """20000 chunks (10 minutes of a twin) after 20000 more: measured -5..+5 MB; with the footer +34..+39 MB."""
    grown, path = _growth_mb(tmp_path, "default")
    assert grown < 15.0, f"the twin's memory grew {grown:.1f} MB over 20000 saved chunks"
    # The file without a footer holds everything, and rerun reads it.
    stats = _rrd("stats", str(path))
    assert stats.returncode == 0, stats.stderr
    line = stats.stdout.split("num_chunks = ", 1)[1].split("\n", 1)[0]
    assert int("".join(ch for ch in line if ch.isdigit())) >= 2 * 20000  # printed with thin spaces: "40 001"


@pytest.mark.parametrize("footer", ["0", "1"])
def test_footer_is_opt_in_and_optimize_adds_it(tmp_path, footer):
    _, path = _growth_mb(tmp_path, footer, n=100)
    verify = _rrd("verify", str(path))
    if footer == "1":
        assert verify.returncode == 0, verify.stdout + verify.stderr
        return
    assert verify.returncode != 0 and "footer" in (verify.stdout + verify.stderr).lower()
    # What the docs tell an operator who needs random access: `rerun rrd optimize` writes the indexed copy.
    indexed = tmp_path / "indexed.rrd"
    assert _rrd("optimize", str(path), "-o", str(indexed)).returncode == 0
    verify = _rrd("verify", str(indexed))
    assert verify.returncode == 0, verify.stdout + verify.stderr
