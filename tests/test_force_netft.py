"""The ATI Net F/T RDT client against a real UDP responder on 127.0.0.1 (speaking the RDT protocol)."""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from iorthand.protocol import ForceLevel
from iorthand_edge.force.config import ForceConfig, NetFTSensorConfig
from iorthand_edge.force.levels import LevelConfig, LevelTracker
from iorthand_edge.force.monitor import ForceMonitor, stale_message
from iorthand_edge.force.sensors import (
    FROZEN_AFTER_S,
    FROZEN_MIN_RECORDS,
    RDT_SET_BIAS,
    RDT_START_REALTIME,
    RDT_STOP,
    ForceSensor,
    FreezeDetector,
    NetFTSensor,
    WrenchSample,
    decode_rdt_record,
    decode_rdt_request,
    encode_rdt_record,
    encode_rdt_request,
    seq_newer,
)


class NetFTResponder:
    """A minimal Net F/T box: streams 36-byte records to whoever sent START, applies BIAS, stops on STOP. Its
    counts carry a few counts of noise, as a live gauge's do; ``frozen`` makes it repeat its last reading with
    advancing sequence numbers (a stuck acquisition)."""

    def __init__(self, wrench_counts: tuple[int, ...] = (1_500_000, -250_000, -7_000_000, 10_000, 0, -20_000)) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.005)
        self.port = self.sock.getsockname()[1]
        self.counts = np.array(wrench_counts, dtype=np.int64)
        self.bias = np.zeros(6, dtype=np.int64)
        self.client: tuple[str, int] | None = None
        self.commands: list[int] = []
        self.extra: list[bytes] = []  # packets to send before the next record (garbage injection)
        self.spike: tuple[int, ...] | None = None  # counts of one record to send before the next normal one
        self.status = 0
        self.seq = 0
        self.frozen = False
        self._rng = np.random.default_rng(7)
        self._reading = self.counts.copy()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="netft-responder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, addr = self.sock.recvfrom(64)
                command, _ = decode_rdt_request(data)
                self.commands.append(command)
                if command == RDT_START_REALTIME:
                    self.client = addr
                elif command == RDT_STOP:
                    self.client = None
                elif command == RDT_SET_BIAS:
                    self.bias = self.counts.copy()
            except (TimeoutError, ValueError):
                pass
            if self.client is not None:
                for packet in self.extra:
                    self.sock.sendto(packet, self.client)
                self.extra = []
                if self.spike is not None:
                    self.seq += 1
                    self.sock.sendto(encode_rdt_record(self.seq, self.seq, 0, self.spike), self.client)
                    self.spike = None
                self.seq += 1
                if not self.frozen:
                    self._reading = self.counts - self.bias + self._rng.integers(-2, 3, 6)
                record = encode_rdt_record(self.seq, self.seq, self.status, tuple(int(c) for c in self._reading))
                self.sock.sendto(record, self.client)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.sock.close()


@pytest.fixture
def responder() -> Iterator[NetFTResponder]:
    r = NetFTResponder()
    yield r
    r.close()


def read_until(sensor: NetFTSensor, predicate, timeout: float = 3.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        sample = sensor.read(0.02)
        if sample is not None and predicate(sample):
            return sample
    raise AssertionError("no matching sample")


def test_wire_format_round_trip() -> None:
    assert encode_rdt_request(RDT_START_REALTIME) == bytes([0x12, 0x34, 0x00, 0x02, 0, 0, 0, 0])
    record = decode_rdt_record(encode_rdt_record(7, 9, 0, (1, -2, 3, -4, 5, -6)))
    assert (record.rdt_sequence, record.ft_sequence, record.status, record.counts) == (7, 9, 0, (1, -2, 3, -4, 5, -6))
    with pytest.raises(ValueError, match="36 bytes"):
        decode_rdt_record(b"\x00" * 35)
    with pytest.raises(ValueError, match="header"):
        decode_rdt_request(struct.pack(">HHI", 0xBEEF, 2, 0))


def test_sequence_comparison_survives_wrap_around() -> None:
    assert seq_newer(2, 1) and not seq_newer(1, 2) and not seq_newer(5, 5)
    assert seq_newer(3, 2**32 - 2)  # wrapped


def test_streams_and_scales_counts(responder: NetFTResponder) -> None:
    sensor = NetFTSensor(NetFTSensorConfig(host="127.0.0.1", port=responder.port, counts_per_force=1e6, counts_per_torque=1e6))
    sensor.start()
    try:
        sample = read_until(sensor, lambda s: True)
        assert sample.wrench == pytest.approx([1.5, -0.25, -7.0, 0.01, 0.0, -0.02], abs=1e-5)
        assert abs(sample.t_ns - time.time_ns()) < 5e9
        assert responder.commands[0] == RDT_START_REALTIME
    finally:
        sensor.close()
    time.sleep(0.05)
    assert responder.commands[-1] == RDT_STOP


def test_a_spike_between_two_ticks_reaches_the_level_logic(responder: NetFTResponder) -> None:
    """One record of 20 N among records of 7 N, all arriving between two reads: the read returns the newest
    (7 N) and the whole batch, and the level logic sees the peak."""
    sensor = NetFTSensor(NetFTSensorConfig(host="127.0.0.1", port=responder.port, counts_per_force=1e6, counts_per_torque=1e6))
    sensor.start()
    try:
        read_until(sensor, lambda s: True)
        responder.spike = (0, 0, -20_000_000, 0, 0, 0)
        time.sleep(0.05)  # several records (the spike among them) wait in the socket, as between two ticks
        sample = sensor.read(0.02)
        assert sample is not None and sample.batch is not None and len(sample.batch) >= 3
        assert sample.wrench[2] == pytest.approx(-7.0)  # the newest
        assert np.array_equal(sample.batch[-1], sample.wrench)
        assert min(sample.batch[:, 2]) == pytest.approx(-20.0)
        assert LevelTracker(LevelConfig()).add(sample.batch, 0.0) == ForceLevel.DANGER
        assert LevelTracker(LevelConfig()).add(sample.wrench, 0.0) == ForceLevel.CAUTION  # the newest alone hides it
    finally:
        sensor.close()


def test_bias_on_request(responder: NetFTResponder) -> None:
    sensor = NetFTSensor(NetFTSensorConfig(host="127.0.0.1", port=responder.port))
    sensor.start()
    try:
        read_until(sensor, lambda s: abs(s.wrench[2]) > 1.0)
        sensor.zero()
        sample = read_until(sensor, lambda s: abs(s.wrench[2]) < 1e-4)
        assert np.allclose(sample.wrench, 0.0, atol=1e-4)
        assert RDT_SET_BIAS in responder.commands
    finally:
        sensor.close()


def test_garbage_packets_are_counted_and_never_crash(responder: NetFTResponder) -> None:
    sensor = NetFTSensor(NetFTSensorConfig(host="127.0.0.1", port=responder.port))
    sensor.start()
    try:
        read_until(sensor, lambda s: True)
        responder.extra = [b"", b"hello", b"\xff" * 35, b"\x00" * 37, bytes(range(200))]
        deadline = time.monotonic() + 3.0
        while sensor.errors < 4 and time.monotonic() < deadline:  # the empty datagram may be merged away
            sensor.read(0.02)
        assert sensor.errors >= 4 and "garbage packet" in sensor.last_error
        assert read_until(sensor, lambda s: True).wrench[2] == pytest.approx(-7.0)  # still streaming
        responder.status = 0x80000001  # the box reports an error: its values are not used
        errors = sensor.errors
        deadline = time.monotonic() + 3.0
        while sensor.errors == errors and time.monotonic() < deadline:
            assert sensor.read(0.02) is None or responder.status == 0
        assert "status 0x80000001" in sensor.last_error
    finally:
        sensor.close()


def test_no_device_gives_no_samples_and_a_reason() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # then closed: nothing listens there
    sensor = NetFTSensor(NetFTSensorConfig(host="127.0.0.1", port=port))
    sensor.start()
    try:
        for _ in range(5):
            assert sensor.read(0.01) is None
        assert sensor.errors >= 1 and "refused" in sensor.last_error.lower()
    finally:
        sensor.close()


def test_a_freeze_needs_both_a_quarter_second_and_enough_identical_records() -> None:
    detector = FreezeDetector()
    reading = (1, 2, 3, 4, 5, 6)
    # A burst of identical records arriving together (a datagram storm) is not a quarter second of them.
    assert not any(detector.add(reading, 10.0) for _ in range(10 * FROZEN_MIN_RECORDS))
    # Nor are a few identical records spread over a long time (a sensor sending slowly, with a chance repeat).
    detector = FreezeDetector()
    assert not any(detector.add(reading, 10.0 + i) for i in range(FROZEN_MIN_RECORDS - 1))
    # 1 kHz of one reading: frozen once the run has lasted FROZEN_AFTER_S; back as soon as the values change.
    detector = FreezeDetector()
    frozen_at = next(i for i in range(1000) if detector.add(reading, i / 1000))
    assert frozen_at == round(FROZEN_AFTER_S * 1000)
    assert not detector.add((1, 2, 3, 4, 5, 7), 1.0) and not detector.frozen


def test_a_live_sensors_noise_is_never_taken_for_a_freeze() -> None:
    rng = np.random.default_rng(3)
    detector = FreezeDetector()
    base = np.array([1_500_000, -250_000, -7_000_000, 10_000, 0, -20_000])
    assert not any(
        detector.add(tuple(int(c) for c in base + rng.integers(-2, 3, 6)), i / 7000) for i in range(70_000)
    )  # 10 s at 7 kHz


def test_a_frozen_sensor_goes_stale_as_a_silent_one_and_says_why(responder: NetFTResponder) -> None:
    """The box keeps sending one reading with advancing sequence numbers: no sample once it is frozen, so the levels
    go stale (the supervisor stops); the error says frozen, once; samples come back when the values move."""
    sensor = NetFTSensor(NetFTSensorConfig(host="127.0.0.1", port=responder.port))
    sensor.start()
    changes = []
    monitor = ForceMonitor(ForceConfig(), sensor, changes.append)
    try:
        monitor.tick(read_until(sensor, lambda s: True), time.monotonic())
        assert not monitor.state.stale
        errors = sensor.errors
        responder.frozen = True
        frozen_since = time.monotonic()
        deadline = frozen_since + 5.0
        while not monitor.state.stale and time.monotonic() < deadline:
            monitor.tick(sensor.read(0.005), time.monotonic())
        assert monitor.state.stale and changes[-1].stale, "a frozen sensor never went stale"
        assert time.monotonic() - frozen_since >= FROZEN_AFTER_S  # the quarter second of identical records
        assert sensor.errors == errors + 1 and sensor.last_error.startswith("frozen: the same reading")
        received = sensor.received
        for _ in range(20):  # still frozen: records arrive, none is a sample
            assert sensor.read(0.01) is None
        assert sensor.received > received and sensor.errors == errors + 1  # the error is counted once a spell
        responder.frozen = False
        read_until(sensor, lambda s: True)  # noise again: samples again
    finally:
        sensor.close()


def test_the_stale_line_says_why_when_the_sensor_does(responder: NetFTResponder, caplog: pytest.LogCaptureFixture) -> None:
    """A frozen box goes stale: the log line says "frozen", not only how long there was no sample."""
    sensor = NetFTSensor(NetFTSensorConfig(host="127.0.0.1", port=responder.port))
    sensor.start()
    monitor = ForceMonitor(ForceConfig(), sensor, [].append)
    try:
        monitor.tick(read_until(sensor, lambda s: True), time.monotonic())
        responder.frozen = True
        deadline = time.monotonic() + 5.0
        with caplog.at_level("ERROR", logger="iorthand.edge.force"):
            while not monitor.state.stale and time.monotonic() < deadline:
                monitor.tick(sensor.read(0.005), time.monotonic())
        assert monitor.state.stale
        (line,) = [r.getMessage() for r in caplog.records if "stale" in r.getMessage()]
        assert "no sample for" in line and "(frozen: the same reading" in line, line
    finally:
        sensor.close()


class _Scripted(ForceSensor):
    """Stands in for a sensor's software side (no device): gives the samples and errors a test sets."""

    def __init__(self) -> None:
        self.sample: WrenchSample | None = None

    def start(self) -> None: ...

    def read(self, timeout: float) -> WrenchSample | None:
        sample, self.sample = self.sample, None
        return sample

    def zero(self) -> None: ...

    def close(self) -> None: ...


def test_the_stale_line_blames_no_error_from_before_the_last_sample(caplog: pytest.LogCaptureFixture) -> None:
    """``last_error`` keeps the sensor's last complaint forever: one from before the last sample did not stop it."""
    sensor = _Scripted()
    monitor = ForceMonitor(ForceConfig(), sensor, [].append)
    sensor.errors, sensor.last_error = 1, "garbage packet: 35 bytes"
    sensor.sample = WrenchSample(np.zeros(6), time.time_ns())
    monitor.tick(sensor.read(0.0), 10.0)
    with caplog.at_level("ERROR", logger="iorthand.edge.force"):
        monitor.tick(None, 11.0)  # silent: stale, no error since the sample
    (line,) = [r.getMessage() for r in caplog.records]
    assert line.startswith("force sensor stale: no sample for 1000 ms —") and "garbage" not in line, line
    assert stale_message(0.25, "sensor reports status 0x00000001") == (
        "force sensor stale: no sample for 250 ms (sensor reports status 0x00000001) — stopping, contact motion refused")
