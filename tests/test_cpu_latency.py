"""The PM QoS request that keeps CPUs out of slow idle states: on the real /dev/cpu_dma_latency (root), whose
value read back is the strictest request in force."""

from __future__ import annotations

import os
import struct
import time
from pathlib import Path

import pytest

from iorthand.cpu_latency import CPU_DMA_LATENCY, CpuLatencyHold, CpuLatencyWhileNeeded
from tests.conftest import wait_until


def current_limit_us() -> int:
    """The limit in force: the strictest request of every process (2,000,000,000 when there is none)."""
    return int(struct.unpack("=i", CPU_DMA_LATENCY.read_bytes()[:4])[0])

needs_device = pytest.mark.skipif(
    os.geteuid() != 0 or not CPU_DMA_LATENCY.exists(), reason="PM QoS needs root and /dev/cpu_dma_latency"
)


@needs_device
def test_the_request_is_in_force_while_held_and_gone_after() -> None:
    before = current_limit_us()
    request = min(before - 1, 123)  # stricter than anything in force, so the read-back is ours
    with CpuLatencyHold(request) as hold:
        assert hold.held and hold.state == f"held at {request} µs"
        assert current_limit_us() == request
    assert hold.state == "released" and not hold.held
    assert current_limit_us() == before


def test_a_device_that_cannot_be_opened_is_reported_not_raised(tmp_path: Path) -> None:
    hold = CpuLatencyHold(0, path=tmp_path / "missing")
    assert not hold.held
    assert hold.state.startswith("not held:") and "missing" in hold.state
    hold.close()  # nothing to release, no error


@pytest.mark.parametrize("bad", [-1, 1.5, True, "0"])
def test_a_latency_that_is_not_whole_microseconds_is_refused(bad: object) -> None:
    with pytest.raises(ValueError, match="whole number of microseconds"):
        CpuLatencyHold(bad)  # type: ignore[arg-type]


@needs_device
def test_a_request_while_needed_is_in_force_only_then() -> None:
    before = current_limit_us()
    request = min(before - 1, 99)
    wanted = CpuLatencyWhileNeeded(request)
    assert not wanted.held and current_limit_us() == before  # nothing until needed
    wanted.need(True)
    wanted.need(True)  # once is enough: still one request
    assert wanted.held and current_limit_us() == request
    wanted.need(False)
    assert not wanted.held and current_limit_us() == before
    wanted.need(True)
    wanted.close()
    assert current_limit_us() == before


def test_a_refused_request_while_needed_is_reported_once_and_not_retried(tmp_path: Path) -> None:
    wanted = CpuLatencyWhileNeeded(0, path=tmp_path / "missing")
    wanted.need(True)
    assert not wanted.held and wanted.state.startswith("not held:") and "missing" in wanted.state
    (tmp_path / "missing").write_bytes(b"")  # even if it could be opened now: not tried again
    wanted.need(False)
    wanted.need(True)
    assert not wanted.held


@needs_device
def test_an_edge_configured_for_it_holds_the_request_while_an_operator_holds_control(edge_factory,
                                                                                     operator_factory) -> None:
    before = current_limit_us()
    request = min(before - 1, 77)
    edge = edge_factory(cpu_latency_us=request)
    op = operator_factory()
    op.wait_for_state(timeout=10.0)
    time.sleep(0.1)  # a dozen control cycles: nobody holds control, the host keeps its own idle states
    assert current_limit_us() == before
    op.acquire()
    wait_until(lambda: current_limit_us() == request, timeout=2.0, message="the request while op1 holds control")
    op.release()
    wait_until(lambda: current_limit_us() == before, timeout=2.0, message="the request gone after the release")
    op.acquire()
    wait_until(lambda: current_limit_us() == request, timeout=2.0, message="the request with control again")
    edge.shutdown()
    assert current_limit_us() == before


def test_an_edge_refuses_a_negative_cpu_latency() -> None:
    from tests.conftest import edge_config

    with pytest.raises(ValueError, match="cpu_latency_us"):
        edge_config("tcp/127.0.0.1:1", "sim1", cpu_latency_us=-5)
