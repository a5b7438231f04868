"""A flood of 100 000 malformed messages at full speed on the command key: the edge agent (its own process,
so its memory is its own) stays responsive — state still published, control queries answered — nothing
reaches the robot, rejects are counted, the log is rate-limited, and memory stays within 50 MB."""

from __future__ import annotations

import random
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import psutil
import yaml
import zenoh

from iorthand import keys
from iorthand.protocol import ControlRequest, SafetyStatus, TwistCommand
from iorthand.transport import client_config, open_session, query
from tests.conftest import wait_until

N_FLOOD = 100_000


def garbage(rng: random.Random, i: int) -> bytes:
    """Every kind of bad payload, cheap to make: random bytes, truncated or wrong-typed msgpack, NaN/inf,
    huge numbers, deep nesting, huge array headers, replayed/future timestamps with a bad field."""
    valid = TwistCommand(operator="mallory", linear=[0.01, 0, 0], deadman=True).stamp(i).encode()
    kind = i % 9
    if kind == 0:
        return rng.randbytes(rng.randint(0, 256))
    if kind == 1:
        return valid[: rng.randint(0, len(valid) - 1)]
    if kind == 2:
        return msgpack.packb({"v": 1, "seq": i, "t": time.time_ns(), "operator": "m", "linear": [float("nan"), 0, 0],
                              "angular": [0, 0, 0], "deadman": True})
    if kind == 3:
        return msgpack.packb({"v": 1, "seq": 2**64 - 1, "t": -1, "operator": 5, "linear": "fast", "angular": None, "deadman": 1})
    if kind == 4:
        return b"\x91" * 2000 + b"\xc0"  # 2000 nested arrays
    if kind == 5:
        return b"\xdd\xff\xff\xff\xff" + b"\x00" * 16  # an array that claims 4 G elements
    if kind == 6:
        return msgpack.packb({"v": 1, "seq": i, "t": 2**63, "operator": "m", "linear": [1e308, 0, 0], "angular": [0, 0, 0], "deadman": True})
    if kind == 7:
        return msgpack.packb([0] * 5000)
    return msgpack.packb({"v": 99, "x": "y" * 1000})


def test_flood_of_malformed_commands(router_endpoint: str, tmp_path: Path) -> None:
    cfg = tmp_path / "edge.yaml"
    cfg.write_text(yaml.safe_dump({
        "robot_id": "sim1",
        "zenoh": {"mode": "client", "connect": [router_endpoint], "connect_retry_s": 10.0},
        "robot": {"kind": "sim", "initial_pose": [0.30, 0.0, 0.20, 3.14159, 0.0, 0.0]},
        "safety": {"auto_arm": True},
    }))
    proc = subprocess.Popen([sys.executable, "-m", "iorthand.cli", "--log-level", "warning", "edge", "--config", str(cfg)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    log_lines: list[str] = []
    assert proc.stdout is not None
    threading.Thread(target=lambda: log_lines.extend(ln.decode(errors="replace") for ln in proc.stdout), daemon=True).start()
    session = open_session(client_config(router_endpoint))
    k = keys.RobotKeys("sim1")
    states: list[float] = []
    safety: list[SafetyStatus] = []
    session.declare_subscriber(k.key(keys.STATE_ROBOT), lambda s: states.append(time.monotonic()))
    session.declare_subscriber(k.key(keys.STATE_SAFETY), lambda s: safety.append(SafetyStatus.decode(s.payload.to_bytes())))
    try:
        wait_until(lambda: len(states) > 50, 30.0, message="the edge publishing state")
        agent = psutil.Process(proc.pid)
        time.sleep(1.0)  # let start-up allocations settle
        rss0 = agent.memory_info().rss
        rng = random.Random(10)
        payloads = [garbage(rng, i) for i in range(200)]
        pub = session.declare_publisher(k.key(keys.CMD_TWIST), congestion_control=zenoh.CongestionControl.BLOCK)
        n_before = len(states)
        t0 = time.monotonic()
        for i in range(N_FLOOD):
            pub.put(payloads[i % 200])
        t1 = time.monotonic()
        # State must have kept coming during the flood.
        during = [t for t in states[n_before:] if t0 <= t <= t1]
        rate = len(during) / (t1 - t0)
        time.sleep(1.0)
        rss1 = agent.memory_info().rss
        # Still responsive: a control query is answered (the acquire is refused for nothing, just answered).
        req = ControlRequest(operator="probe").stamp(1).encode()
        assert query(session, k.key(keys.CONTROL_RELEASE), req, timeout=5.0)
        wait_until(lambda: safety and safety[-1].malformed > 0, 5.0, message="rejects counted")
        last = safety[-1]
        print(f"\nflood: {N_FLOOD} msgs in {t1 - t0:.2f} s ({N_FLOOD / (t1 - t0):.0f}/s); state during flood "
              f"{rate:.0f} Hz; rss {rss0 / 2**20:.1f} → {rss1 / 2**20:.1f} MB (Δ {(rss1 - rss0) / 2**20:+.1f} MB); "
              f"malformed counted {last.malformed}, applied {last.applied}")
        assert last.applied == 0 and last.received == 0  # nothing decoded reached the supervisor
        assert rss1 - rss0 < 50 * 2**20
        assert len(during) > 0, "no state published during the flood"
        rejected_lines = [ln for ln in log_lines if "rejected malformed command" in ln]
        assert 1 <= len(rejected_lines) <= 2 + (time.monotonic() - t0) / 5.0, rejected_lines[:5]
        assert proc.poll() is None
    finally:
        session.close()
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
