"""Threads named where the kernel shows them (``top -H``, ``ps -L``, /proc): which thread of a process takes the
CPU is then visible without a Python profiler."""

from __future__ import annotations

import subprocess
import threading
from pathlib import Path

import psutil
import pytest

from iorthand.process import NATIVE_NAME_BYTES, native_thread_name
from iorthand.transport import Worker, free_port
from tests.conftest import iorthand_cmd, stop_process, wait_until


def kernel_thread_names(pid: int | str = "self") -> list[str]:
    return [(task / "comm").read_text().strip() for task in Path(f"/proc/{pid}/task").iterdir()]


@pytest.mark.parametrize(("name", "native"), [
    ("edge-control", "edge-control"),
    ("edge-control-plane", "control-plane"),  # the leading words go first: what tells threads apart stays
    ("edge-video-camera-send", "camera-send"),
    ("edge-video-ultrasound-send", "ultrasound-send"),
    ("edge-video-ultrasound-capture", "ultrasound-capt"),  # two words left: cut, not dropped to "capture"
    ("perception", "perception"),
    ("a-very-long-single-word-at-the-end-xxxxxxxxxxxxxxxxxx", "end-xxxxxxxxxxx"),
    ("ééééééééééé", "ééééééé"),  # 15 bytes of UTF-8 at most, never half a character
])
def test_a_name_is_shortened_to_what_the_kernel_keeps(name: str, native: str) -> None:
    assert native_thread_name(name) == native
    assert len(native_thread_name(name).encode()) <= NATIVE_NAME_BYTES


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="no /proc: the kernel's thread names are Linux's")
def test_a_worker_is_named_in_the_kernel() -> None:
    stop, started = threading.Event(), threading.Event()

    def work(stop: threading.Event) -> None:
        started.set()
        stop.wait(5.0)

    worker = Worker("edge-video-ultrasound-send", work, stop)
    worker.start()
    try:
        assert started.wait(5.0)
        assert (Path(f"/proc/self/task/{worker.native_id}/comm").read_text().strip() == "ultrasound-send")
    finally:
        stop.set()
        worker.join(5.0)


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="no /proc: the kernel's thread names are Linux's")
def test_a_service_shows_as_its_command_in_ps() -> None:
    """What an engineer sees in ps and top on a host that runs several services: not "python" three times.
    (The edge agent's name is checked with its media process's, in test_media_process.py.)"""
    router = subprocess.Popen(iorthand_cmd("router", "--listen", f"tcp/127.0.0.1:{free_port()}"),
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        process = psutil.Process(router.pid)
        wait_until(lambda: process.name() == "iorthand-router", timeout=20.0, message="the router's process name")
    finally:
        stop_process(router)
    assert native_thread_name("iorthand-recorder") == "iorthand-record"  # the kernel's 15 bytes
