"""What a router's shared-memory pool costs the processes it forwards to (iorthand.transport.SHM_POOL_SIZE).

A router forwarding large messages that arrived over a link (a remote site's video) hands them to the processes
on its host through a pool of shared memory. Each receiver maps the pool, and its RSS counts every page of it it
has read. In the 2-hour soak the router, the recorder and the twin stepped up together by 11, 20 and 20 MB; the
same step happens here, on purpose: a burst of 60 KB frames from a session without shared memory (a site
elsewhere), through a real router in its own process, to a receiver in this process with the settings every
iorthand client uses. With Zenoh's default pool (the control run) the receiver's shared resident memory grows by
about the whole 16 MiB, or the burst did not exercise the pool; with ours, by at most our pool plus Zenoh's
own bookkeeping segment.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest

from iorthand import keys
from iorthand.transport import SHM_POOL_SIZE, client_config, free_port, open_session, router_settings
from tests.conftest import RouterProcess, wait_until

FRAMES = 300
FRAME_BYTES = 60_000
KEY = keys.RobotKeys("shm1").key(keys.VIDEO_CAMERA)
BOOKKEEPING = 2 * 1024 * 1024  # Zenoh's per-process metadata segment (1.25 MiB), mapped once


def shared_resident_bytes() -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith("RssShmem:"))


def burst_growth(tmp_path: Path, pool: str) -> int:
    """How much this process's shared resident memory grew while receiving the burst through the router."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = router_settings([endpoint])
    if pool == "default":
        del settings["transport"]["shared_memory"]
    config = tmp_path / f"router-{pool}.json5"
    config.write_text(json.dumps(settings))
    router = RouterProcess(endpoint, config)
    router.start()
    receiver = open_session(client_config(endpoint))
    site = open_session(client_config(endpoint, shared_memory=False))
    received = 0
    lock = threading.Lock()

    def on_frame(sample) -> None:
        nonlocal received
        sample.payload.to_bytes()  # as every iorthand receiver does: the frame is copied out, its buffer freed
        with lock:
            received += 1

    try:
        sub = receiver.declare_subscriber(KEY, on_frame)
        pub = site.declare_publisher(KEY)
        time.sleep(0.5)  # the subscription has reached the router
        before = shared_resident_bytes()
        for _ in range(FRAMES):
            pub.put(bytes(FRAME_BYTES))
            time.sleep(0.003)
        wait_until(lambda: received >= FRAMES * 0.95, timeout=10.0, message=f"the burst's frames ({received})")
        growth = shared_resident_bytes() - before
        sub.undeclare()
    finally:
        site.close()
        receiver.close()
        router.stop()
    return growth


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads RssShmem from /proc")
def test_a_burst_forwarded_by_the_router_maps_only_the_small_pool_into_a_receiver(tmp_path: Path) -> None:
    control = burst_growth(tmp_path, "default")
    assert control >= 12 * 1024 * 1024, f"the default pool grew the receiver by only {control / 2**20:.1f} MiB"
    ours = burst_growth(tmp_path, "ours")
    assert ours <= SHM_POOL_SIZE + BOOKKEEPING, (
        f"the receiver's shared resident memory grew {ours / 2**20:.1f} MiB (pool {SHM_POOL_SIZE / 2**20:.0f} MiB)")
