"""The recorder's CPU with its Foxglove channels against without them → JSON
(default benchmarks/results/recorder_foxglove.json).

One interleaved run: a router (``iorthand router``), two recorders (``iorthand recorder --start-now``) that
record the same traffic at the same time, one with ``foxglove.enabled: false`` (today's recorder) and one with
the default (the Foxglove channels too), and a full-rate synthetic robot (``python -m
iorthand_cloud.recorder.simulate``: state 125 Hz, force 100 Hz, markers 30 Hz, commands 60 Hz + echoes, safety
20 Hz, force level 10 Hz, camera JPEG 640×480 at 30 fps). Both recorders see the same messages under the same
load from the rest of this shared machine, so their ratio holds where absolute figures drift; ``--rounds``
repeats it with fresh processes, alternating which recorder starts first. Each recorder's CPU (user + system,
psutil) is taken over the simulator's run only. Target (issue 23): with ≤ 1.5× without.

Also, in this process: the writer thread's cost per message of each kind, decode → raw write vs decode → raw
write + conversion + Foxglove write (the recorder's own methods and streams, into MCAP files in a temporary
folder), so the ratio can be traced to the messages that cost it. The simulator's camera repeats 8 synthetic
JPEGs of ~60 kB; a real camera's frames are larger and all different, which costs the uncompressed copy little
more (a memory copy and a CRC) but would have cost zstd ~1.5 ms per 150 kB frame. The Zenoh callbacks are unchanged (they only queue); that
the receive path kept up shows as 0 dropped and 0 missing by sequence in both recorders.

Usage: ``python benchmarks/bench_recorder_foxglove.py [--duration 60] [--rounds 3] [--micro 2000]``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from importlib.metadata import version
from pathlib import Path
from typing import Any

import psutil
import yaml
from mcap.reader import make_reader
from mcap.writer import CompressionType

from iorthand import keys
from iorthand.protocol import (
    AppliedCommand,
    ForceLevelState,
    ForceSample,
    MarkerPose,
    Markers,
    RobotState,
    SafetyStatus,
    Status,
    TwistCommand,
    VideoFrame,
    message_type_for,
)
from iorthand.transport import free_port
from iorthand_cloud.foxglove_channels import FoxgloveConverter
from iorthand_cloud.recorder import manifest as mf
from iorthand_cloud.recorder.config import RecorderConfig
from iorthand_cloud.recorder.reader import segment_files
from iorthand_cloud.recorder.segments import Stream
from iorthand_cloud.recorder.service import FOXGLOVE, RecorderService
from iorthand_cloud.recorder.simulate import make_jpegs

ROOT = Path(__file__).resolve().parent.parent
TARGET = 1.5


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "iorthand.cli", *args]


def _wait_line(proc: subprocess.Popen[bytes], text: str, timeout: float = 30.0) -> None:
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout
    for line in proc.stdout:
        if text.encode() in line:
            return
        if time.monotonic() > deadline:
            break
    raise RuntimeError(f"{proc.args} did not print {text!r}")


def _stop(proc: subprocess.Popen[bytes] | None) -> None:
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)


def _cpu(p: psutil.Process) -> tuple[float, float]:
    t = p.cpu_times()
    return t.user, t.system


def _foxglove_messages(folder: Path) -> tuple[int, float]:
    count, size = 0, 0
    for path in sorted((folder / FOXGLOVE).glob("*.mcap")):
        size += path.stat().st_size
        with path.open("rb") as f:
            summary = make_reader(f).get_summary()
            if summary is not None and summary.statistics is not None:
                count += summary.statistics.message_count
    return count, size / 1e6


def one_round(workdir: Path, index: int, duration: float) -> dict[str, Any]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs: list[subprocess.Popen[bytes]] = []
    variants = ("without", "with") if index % 2 == 0 else ("with", "without")
    try:
        router = subprocess.Popen(_cli("router", "--listen", endpoint), stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT)
        procs.append(router)
        _wait_line(router, "router ready")
        recorders: dict[str, subprocess.Popen[bytes]] = {}
        for name in variants:
            cfg = workdir / f"recorder-{name}.yaml"
            cfg.write_text(yaml.safe_dump({
                "zenoh": {"mode": "client", "connect": [endpoint]}, "output_dir": str(workdir / name),
                "flush_interval": 0.5, "fsync": True, "foxglove": {"enabled": name == "with"},
            }))
            log = (workdir / f"recorder-{name}.log").open("ab")
            p = subprocess.Popen(_cli("recorder", "--config", str(cfg), "--start-now", "--session", f"round-{index}"),
                                 stdout=subprocess.PIPE, stderr=log)
            procs.append(p)
            _wait_line(p, "recorder ready")
            recorders[name] = p
        ps = {name: psutil.Process(p.pid) for name, p in recorders.items()}
        sim = subprocess.Popen(
            [sys.executable, "-m", "iorthand_cloud.recorder.simulate", "--connect", endpoint,
             "--duration", str(duration), "--out", str(workdir / f"sim-{index}.json")],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        procs.append(sim)
        _wait_line(sim, "synthetic session ready")
        time.sleep(0.5)  # the simulator waits 0.5 s for subscriptions before publishing
        cpu0 = {name: _cpu(p) for name, p in ps.items()}
        t0 = time.monotonic()
        load0 = os.getloadavg()[0]
        sim.wait(duration + 60)
        time.sleep(1.0)  # the writers drain what arrived last
        elapsed = time.monotonic() - t0
        cpu1 = {name: _cpu(p) for name, p in ps.items()}
        user = {name: cpu1[name][0] - cpu0[name][0] for name in ps}
        system = {name: cpu1[name][1] - cpu0[name][1] for name in ps}
        cpu = {name: user[name] + system[name] for name in ps}
        for p in recorders.values():
            _stop(p)  # SIGTERM: closes the session cleanly (footers, manifest complete)
    finally:
        for p in reversed(procs):
            _stop(p)
    out: dict[str, Any] = {"started_first": variants[0], "elapsed_s": round(elapsed, 2),
                           "load_avg_1m": [round(load0, 2), round(os.getloadavg()[0], 2)]}
    for name in ("without", "with"):
        folder = workdir / name / f"round-{index}"
        m = mf.Manifest.read(folder)
        t = mf.totals(m.keys)
        raw_mb = sum(p.stat().st_size for p in segment_files(folder)) / 1e6
        fox_n, fox_mb = _foxglove_messages(folder)
        out[name] = {
            "cpu_s": round(cpu[name], 3), "cpu_percent": round(100 * cpu[name] / elapsed, 2),
            "user_s": round(user[name], 3), "system_s": round(system[name], 3),
            "recorded": t["messages"], "missing_by_sequence": t["missing"], "dropped": m.dropped,
            "status": m.status, "raw_MB": round(raw_mb, 1), "foxglove_messages": fox_n, "foxglove_MB": round(fox_mb, 1),
        }
    out["cpu_ratio_with_over_without"] = round(cpu["with"] / cpu["without"], 3) if cpu["without"] else None
    return out


# ---------------------------------------------------------------------------------------------------------
# The writer thread's cost per message (in this process)


def _samples() -> dict[str, tuple[str, bytes]]:
    k = keys.RobotKeys("sim1").key
    eye = [1.0, 0, 0, 0.3, 0, 1.0, 0, 0.0, 0, 0, 1.0, 0.0, 0, 0, 0, 1.0]
    jpeg = make_jpegs(1)[0]
    return {
        "state/robot": (k(keys.STATE_ROBOT), RobotState(tcp_pose=[0.3, 0.0, 0.2, 3.14, 0.0, 0.0]).stamp(1).encode()),
        "state/force": (k(keys.STATE_FORCE), ForceSample(force=[0.01, -0.02, -7.0]).stamp(1).encode()),
        "state/force_level": (k(keys.STATE_FORCE_LEVEL), ForceLevelState(level=1, stale=False).stamp(1).encode()),
        "state/safety": (k(keys.STATE_SAFETY), SafetyStatus(status=Status.OK).stamp(1).encode()),
        "state/applied (accepted)": (k(keys.STATE_APPLIED), AppliedCommand(accepted=True).stamp(1).encode()),
        "state/applied (refused)": (k(keys.STATE_APPLIED), AppliedCommand(
            accepted=False, status=Status.NO_DEADMAN, reason="deadman released").stamp(1).encode()),
        "markers (3)": (k(keys.MARKERS), Markers(markers=[MarkerPose(id=i, pose=eye, raw=eye) for i in range(3)])
                        .stamp(1).encode()),
        "cmd/twist (no Foxglove channel)": (k(keys.CMD_TWIST), TwistCommand(deadman=True).stamp(1).encode()),
        f"video/camera (JPEG {len(jpeg) // 1000} kB)": (k(keys.VIDEO_CAMERA),
                                                       VideoFrame(width=640, height=480, data=jpeg).stamp(1).encode()),
    }


def micro(n: int, folder: Path) -> dict[str, Any]:
    """µs per message in the writer thread, with the recorder's own methods and streams as it sets them up by
    default: decode + raw write, against decode + raw write + conversion + Foxglove write. Safety statuses are
    converted with their status changing every time (the costly case: a log line each)."""
    svc = RecorderService(RecorderConfig(output_dir=folder))  # not started: only its writer-side methods are used
    out: dict[str, Any] = {}
    for name, (key, payload) in _samples().items():
        cls = message_type_for(key)
        assert cls is not None
        row: dict[str, float] = {}
        for variant in ("raw", "raw+foxglove"):
            sub = folder / f"{len(out)}-{variant}"
            sub.mkdir()
            raw = Stream(name="raw", folder=sub, compression=CompressionType.NONE if "video" in key
                         else CompressionType.ZSTD, max_bytes=1 << 40, max_seconds=1e9, chunk_size=1 << 20)
            fox = Stream(name=FOXGLOVE, folder=sub, compression=CompressionType.NONE, max_bytes=1 << 40,
                         max_seconds=1e9, chunk_size=1 << 20)
            conv = FoxgloveConverter()
            statuses = ["ok", "command_timeout"]
            t0 = time.perf_counter()
            for i in range(n):
                msg = cls.decode(payload)
                raw.write(svc._spec(key, False), 1, msg.t, msg.seq, payload)
                if variant == "raw+foxglove":
                    if isinstance(msg, SafetyStatus):
                        msg.status = statuses[i % 2]
                    svc._write_foxglove(conv, fox, key, msg, 1, msg.seq)
            raw.close(fsync=False)
            fox.close(fsync=False)
            row[f"{variant}_us"] = round((time.perf_counter() - t0) / n * 1e6, 2)
        row["foxglove_extra_us"] = round(row["raw+foxglove_us"] - row["raw_us"], 2)
        out[name] = row
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=60.0, help="s of full-rate traffic per round")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--micro", type=int, default=2000, help="messages per kind in the per-message part (0: skip)")
    p.add_argument("--keep", action="store_true", help="keep the sessions and logs")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "recorder_foxglove.json"))
    args = p.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-recorder-foxglove-"))
    results: dict[str, Any] = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "load_avg_at_start": os.getloadavg(),
                    "mcap": version("mcap"), "foxglove-schemas-protobuf": version("foxglove-schemas-protobuf"),
                    "protobuf": version("protobuf")},
        "config": {"duration_s": args.duration, "rounds": args.rounds, "target_ratio": TARGET,
                   "traffic": "simulate.py full rate: state 125 Hz, force 100 Hz, markers 30 Hz (3 markers), "
                              "commands 60 Hz + echoes, safety 20 Hz, force level 10 Hz, camera JPEG 640x480 30 fps"},
    }
    try:
        if args.micro:
            mdir = tmp / "micro"
            mdir.mkdir()
            results["per_message_writer_thread"] = micro(args.micro, mdir)
            print(json.dumps(results["per_message_writer_thread"], indent=1), flush=True)
        rounds = []
        for i in range(args.rounds):
            workdir = tmp / f"round-{i}"
            workdir.mkdir()
            rounds.append(one_round(workdir, i, args.duration))
            print(json.dumps(rounds[-1], indent=1), flush=True)
        results["rounds"] = rounds
        ratios = [r["cpu_ratio_with_over_without"] for r in rounds if r["cpu_ratio_with_over_without"]]
        total = sum(r["with"]["cpu_s"] for r in rounds) / max(1e-9, sum(r["without"]["cpu_s"] for r in rounds))
        results["summary"] = {
            "cpu_ratio_median": round(statistics.median(ratios), 3) if ratios else None,
            "cpu_ratio_total": round(total, 3),
            "cpu_percent_without_mean": round(statistics.mean(r["without"]["cpu_percent"] for r in rounds), 2),
            "cpu_percent_with_mean": round(statistics.mean(r["with"]["cpu_percent"] for r in rounds), 2),
            "dropped": sum(r[v]["dropped"] for r in rounds for v in ("with", "without")),
            "missing_by_sequence": sum(r[v]["missing_by_sequence"] for r in rounds for v in ("with", "without")),
            "same_messages_recorded": all(r["with"]["recorded"] == r["without"]["recorded"] for r in rounds),
            "disk_MB_per_s_raw": round(statistics.mean(r["with"]["raw_MB"] / r["elapsed_s"] for r in rounds), 2),
            "disk_MB_per_s_foxglove": round(statistics.mean(r["with"]["foxglove_MB"] / r["elapsed_s"] for r in rounds), 2),
            "target_met": bool(ratios) and total <= TARGET,
        }
        print(json.dumps(results["summary"], indent=1), flush=True)
    finally:
        if args.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1))
    print(f"results: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
