"""A sender whose Zenoh send thread stalls loses no command (iorthand.transport.TX_QUEUE_SIZE).

In the 2-hour soak an operator's send thread stalled 40–55 ms while its own loop kept producing twists on time;
Zenoh's default queue (2 batches, one per express command) dropped the next ones, and neither the edge nor the
recorder ever saw them. Here a publisher process streams twists at 60 Hz on its ``cmd/twist`` key, with the
QoS and session settings every iorthand client uses, while its send thread (Zenoh's ``tx-*``, pinned to CPU 0)
is starved for 100 ms in every 400 ms by a real-time busy loop on that CPU; the Python loop runs on CPU 1.
Nothing is faked: a real router and real sessions, only the stall is made on purpose.

The stall needs root (SCHED_FIFO) and CPUs 0 and 1; without them that test is skipped.
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import threading

import pytest

from iorthand import keys
from iorthand.transport import TX_QUEUE_SIZE, TX_QUEUE_SIZE_KEY, ZenohConfig, open_session, zenoh_entries
from tests.conftest import ROOT

RATE_HZ = 60
COUNT = 180  # 3 s: seven stalls of 100 ms
STALL_S = 0.1
KEY = keys.RobotKeys("stall1").key(keys.CMD_TWIST)

# The publisher: opens a session like every iorthand client, pins its send threads to CPU 0 and itself to CPU 1,
# starts the staller and streams COUNT numbered twists. ``default`` sets Zenoh's own queue size (2 batches) back:
# the control run, which must lose commands, or the stall did not happen.
PUBLISHER = """
import glob, os, struct, subprocess, sys, time
from iorthand.transport import TX_QUEUE_SIZE_KEY, ZenohConfig, open_session, publisher
endpoint, key, queues, stall = sys.argv[1:5]
count, rate = int(sys.argv[5]), float(sys.argv[6])
extra = {f"{TX_QUEUE_SIZE_KEY}/real_time": 2} if queues == "default" else {}
session = open_session(ZenohConfig(mode="client", connect=[endpoint], shared_memory=False, extra=extra))
pub = publisher(session, key)
pub.put(b"warm-up")
time.sleep(0.3)  # the send threads exist once something was sent
tx = [int(p.split("/")[4]) for p in glob.glob("/proc/self/task/*/comm") if open(p).read().startswith("tx-")]
assert tx, "no Zenoh send thread (tx-*) found"
for tid in tx:
    os.sched_setaffinity(tid, {0})
os.sched_setaffinity(0, {1})
staller = subprocess.Popen([sys.executable, "-c", stall])
try:
    t0 = time.monotonic()
    for i in range(count):
        pub.put(struct.pack("<q", i) + bytes(140))
        time.sleep(max(0.0, t0 + (i + 1) / rate - time.monotonic()))
finally:
    staller.kill()
    staller.wait()
time.sleep(0.5)  # what was sent has arrived before this process ends
session.close()
"""

# The staller: real time on CPU 0, busy for STALL_S, then asleep 0.3 s, until killed.
STALLER = f"""
import os, time
os.sched_setaffinity(0, {{0}})
os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
while True:
    t = time.monotonic()
    while time.monotonic() - t < {STALL_S}:
        pass
    time.sleep(0.3)
"""

needs_stall = pytest.mark.skipif(
    os.geteuid() != 0 or not {0, 1} <= os.sched_getaffinity(0),
    reason="the stall needs root (SCHED_FIFO) and CPUs 0 and 1",
)


def test_every_session_gets_the_deeper_send_queues() -> None:
    entries = zenoh_entries(ZenohConfig(mode="client", connect=["tcp/127.0.0.1:7447"]))
    assert {k: entries[f"{TX_QUEUE_SIZE_KEY}/{k}"] for k in TX_QUEUE_SIZE} == TX_QUEUE_SIZE


def _received_while_stalled(router_endpoint: str, queues: str) -> set[int]:
    session = open_session(ZenohConfig(mode="client", connect=[router_endpoint], shared_memory=False))
    got: set[int] = set()
    lock = threading.Lock()

    def on_sample(sample) -> None:
        data = sample.payload.to_bytes()
        if len(data) > 8:
            with lock:
                got.add(struct.unpack("<q", data[:8])[0])

    sub = session.declare_subscriber(KEY, on_sample)
    try:
        proc = subprocess.run(
            [sys.executable, "-c", PUBLISHER, router_endpoint, KEY, queues, STALLER, str(COUNT), str(RATE_HZ)],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert proc.returncode == 0, proc.stderr[-2000:]
        with lock:
            return set(got)
    finally:
        sub.undeclare()
        session.close()


@needs_stall
@pytest.mark.serial  # it takes CPU 0 from every other process for 100 ms in every 400 ms
def test_a_stalled_send_thread_loses_no_twist(router_endpoint: str) -> None:
    # The control run: Zenoh's default queue loses twists under the same stalls, so the stall really happened.
    default = _received_while_stalled(router_endpoint, "default")
    assert len(default) < COUNT - 10, f"the stall did not starve the send thread ({len(default)} of {COUNT} arrived)"
    ours = _received_while_stalled(router_endpoint, "ours")
    assert sorted(set(range(COUNT)) - ours) == [], f"{COUNT - len(ours)} of {COUNT} twists lost"
