"""Force/torque sensors behind one interface: a 6-axis wrench (N, N·m) with its capture time.

- :class:`SimForceSensor`: the simulated robot pressing on the phantom (:mod:`.contact`), plus bias and noise.
- :class:`NetFTSensor`: ATI Net F/T (and Axia) over the Raw Data Transfer protocol (UDP).

Decoding the RDT wire format is pure (:func:`encode_rdt_request`, :func:`decode_rdt_record`); the sensor
class is the thin socket adapter around it.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from iorthand.geometry import rotvec_to_matrix
from iorthand_edge.force.config import (
    ForceSensorConfig,
    NetFTSensorConfig,
    RobotForceSensorConfig,
    SimForceSensorConfig,
)
from iorthand_edge.force.contact import PhantomConfig, contact_wrench
from iorthand_edge.robots.base import RobotReading

Wrench = NDArray[np.float64]


class SensorError(RuntimeError):
    """The sensor cannot be used (no device, bad data); the message says why."""


@dataclass(frozen=True)
class WrenchSample:
    wrench: Wrench  # [Fx, Fy, Fz, Tx, Ty, Tz], N and N·m, sensor frame, bias removed
    t_ns: int  # capture time on the agent's wall clock (ns since the epoch)
    # Every sample since the previous read, oldest first, the newest (``wrench``) last: n×6. A fast sensor
    # (Net F/T: up to 7 kHz) delivers tens per 10 ms tick, and a spike among them must reach the level logic
    # even when the newest one is calm. None: ``wrench`` is the only sample.
    batch: Wrench | None = None


class ForceSensor(ABC):
    """A force/torque sensor. One thread calls everything but :meth:`zero`: the force worker's, or for a sensor
    paced by the robot, the control loop's."""

    errors: int = 0  # samples rejected as invalid (garbage, bad status)
    last_error: str = ""
    # Its samples come from the robot's state (the simulator's contact, the arm's own wrist sensor): the control
    # loop reads it once per robot state, right after the robot, instead of a thread of its own polling that state
    # at another rate (which repeated or skipped states, and cost a wake-up per sample).
    paced_by_robot: bool = False

    @abstractmethod
    def start(self) -> None:
        """Open the device and start streaming; raise SensorError with the reason if it cannot."""

    @abstractmethod
    def read(self, timeout: float) -> WrenchSample | None:
        """The newest sample since the last call (with the others in ``batch``), waiting at most ``timeout``
        s; None if there is none."""

    @abstractmethod
    def zero(self) -> None:
        """Take the current reading as zero (bias). Only meaningful with the tool in free space."""

    @abstractmethod
    def close(self) -> None:
        """Stop streaming and release the device. Never raises."""


# ---------------------------------------------------------------------------------------------------------
# Simulated


NOISE_BLOCK = 256  # samples of the simulated sensor's noise drawn at once (2 s at 125 Hz)
_NOISE_SCALE = np.array([1.0, 1.0, 1.0, 0.1, 0.1, 0.1])  # torque noise in N·m for force noise in N


class SimForceSensor(ForceSensor):
    """Reads the simulated robot's latest state (``reading``) and the phantom; adds bias and noise.

    ``silent`` makes it stop answering, as an unplugged sensor would (tests, demos).
    """

    paced_by_robot = True

    def __init__(
        self,
        config: SimForceSensorConfig,
        phantom: PhantomConfig | None,
        reading: Callable[[], RobotReading | None],
    ) -> None:
        self.config = config
        self.phantom = phantom
        self._reading = reading
        self._rng = np.random.default_rng(config.seed)
        self._offset = [0.0] * 6
        self._bias = [float(v) for v in config.bias]
        self._noise: Iterator[list[float]] = iter(())
        self._lock = threading.Lock()
        self.silent = False

    def start(self) -> None:
        pass

    def _next_noise(self) -> list[float]:
        """The next sample's white noise. Drawn NOISE_BLOCK samples at a time: one numpy call per block instead of
        one (and the arithmetic on its array) per control cycle."""
        noise = next(self._noise, None)
        if noise is None:
            block = self._rng.normal(0.0, self.config.noise, (NOISE_BLOCK, 6)) * _NOISE_SCALE
            self._noise = iter(block.tolist())
            noise = next(self._noise)
        return noise

    def _raw(self, r: RobotReading) -> list[float]:
        """The wrench the sensor measures in robot state ``r``: contact with the phantom, bias and noise."""
        noise = self._next_noise()
        if self.phantom is None:
            return [b + n for b, n in zip(self._bias, noise, strict=True)]
        contact = contact_wrench(self.phantom, r.tcp_pose, r.tcp_speed).tolist()
        return [c + b + n for c, b, n in zip(contact, self._bias, noise, strict=True)]

    def read(self, timeout: float) -> WrenchSample | None:
        r = None if self.silent else self._reading()
        if r is None:
            return None
        raw = self._raw(r)
        with self._lock:  # stamped with the robot state it was computed from
            return WrenchSample(np.array([v - o for v, o in zip(raw, self._offset, strict=True)]), r.timestamp_ns)

    def zero(self) -> None:
        r = self._reading()
        if r is None:
            raise SensorError("simulated force sensor: no robot state yet, nothing to zero")
        raws = [self._raw(r) for _ in range(16)]
        with self._lock:
            self._offset = np.mean(raws, axis=0).tolist()

    def close(self) -> None:
        pass


# ---------------------------------------------------------------------------------------------------------
# ATI Net F/T, Raw Data Transfer (RDT) over UDP. Request: 8 bytes big-endian (header 0x1234, command,
# sample count; 0 = stream forever). Record: 36 bytes big-endian (rdt_sequence, ft_sequence, status,
# Fx, Fy, Fz, Tx, Ty, Tz as signed counts; divide by counts-per-force/torque from the calibration).

RDT_HEADER = 0x1234
RDT_STOP = 0x0000
RDT_START_REALTIME = 0x0002
RDT_SET_BIAS = 0x0042
_REQUEST = struct.Struct(">HHI")
_RECORD = struct.Struct(">III6i")
RDT_RECORD_SIZE = _RECORD.size  # 36


@dataclass(frozen=True)
class RdtRecord:
    rdt_sequence: int
    ft_sequence: int
    status: int
    counts: tuple[int, int, int, int, int, int]


def encode_rdt_request(command: int, count: int = 0) -> bytes:
    return _REQUEST.pack(RDT_HEADER, command, count)


def decode_rdt_request(data: bytes) -> tuple[int, int]:
    """(command, count) of a request; raises ValueError if it is not one (used by test responders)."""
    if len(data) != _REQUEST.size:
        raise ValueError(f"an RDT request has {_REQUEST.size} bytes, got {len(data)}")
    header, command, count = _REQUEST.unpack(data)
    if header != RDT_HEADER:
        raise ValueError(f"RDT request header 0x{header:04x} is not 0x{RDT_HEADER:04x}")
    return command, count


def encode_rdt_record(rdt_sequence: int, ft_sequence: int, status: int, counts: tuple[int, ...]) -> bytes:
    return _RECORD.pack(rdt_sequence, ft_sequence, status, *counts)


def decode_rdt_record(data: bytes) -> RdtRecord:
    """One RDT record; raises ValueError naming what is wrong with a packet that is not one."""
    if len(data) != RDT_RECORD_SIZE:
        raise ValueError(f"RDT record must be {RDT_RECORD_SIZE} bytes, got {len(data)}")
    rdt_seq, ft_seq, status, *counts = _RECORD.unpack(data)
    return RdtRecord(rdt_seq, ft_seq, status, tuple(counts))  # type: ignore[arg-type]


def rdt_wrench(record: RdtRecord, counts_per_force: float, counts_per_torque: float) -> Wrench:
    c = np.asarray(record.counts, dtype=float)
    return np.concatenate([c[:3] / counts_per_force, c[3:] / counts_per_torque])


def seq_newer(a: int, b: int) -> bool:
    """Whether 32-bit sequence ``a`` comes after ``b`` (wrap-around aware): UDP may reorder datagrams."""
    return 0 < (a - b) % 2**32 < 2**31


# A live strain-gauge sensor's counts always carry noise in their last digits (several counts on each of six
# gauges): two identical consecutive records are already unlikely, a quarter second of them means the box keeps
# sending one stuck reading (a hung acquisition, a frozen DSP) with advancing sequence numbers. 0.25 s is 25 records
# at RDT's slowest useful rate (100 Hz) and 250–7000 at the usual 1–7 kHz: far from a chance repeat, and short
# enough that the supervisor (stale after ``levels.stale_after`` without a sample) stops within ~0.35 s of a
# freeze. Both bounds must hold, so a burst of records arriving together cannot pass for a quarter second.
FROZEN_AFTER_S = 0.25
FROZEN_MIN_RECORDS = 25


class FreezeDetector:
    """Whether a stream of readings is stuck: the same values for :data:`FROZEN_AFTER_S` and at least
    :data:`FROZEN_MIN_RECORDS` consecutive records. Pure: the caller gives each reading's arrival time."""

    def __init__(self, after_s: float = FROZEN_AFTER_S, min_records: int = FROZEN_MIN_RECORDS) -> None:
        self.after_s = after_s
        self.min_records = min_records
        self._values: tuple[int, ...] | None = None
        self._since = 0.0  # arrival time of the first record of the current run of identical values
        self._run = 0  # records in that run
        self.frozen = False

    def add(self, values: tuple[int, ...], now: float) -> bool:
        """Note one record's values; True while the stream is frozen (this record is not a measurement)."""
        if values != self._values:
            self._values, self._since, self._run = values, now, 1
            self.frozen = False
            return False
        self._run += 1
        self.frozen = self._run >= self.min_records and now - self._since >= self.after_s
        return self.frozen

    def describe(self, now: float) -> str:
        return (
            f"frozen: the same reading in {self._run} consecutive records over {now - self._since:.2f} s "
            "with advancing sequence numbers (a live sensor always shows noise): no sample until it changes"
        )


class NetFTSensor(ForceSensor):
    """A frozen box (the same counts with advancing sequence numbers: :class:`FreezeDetector`) gives no samples,
    as a silent one: the levels go stale and the supervisor stops; ``last_error`` says it is frozen."""

    RESTART_AFTER = 1.0  # s of silence before the streaming request is sent again (the box may have rebooted)

    def __init__(self, config: NetFTSensorConfig) -> None:
        self.config = config
        self._freeze = FreezeDetector()
        self._sock: socket.socket | None = None
        self._last_rdt: int | None = None
        self._last_packet = 0.0
        self._last_start = 0.0
        self.errors = 0
        self.last_error = ""
        self.received = 0

    def start(self) -> None:
        address = (self.config.host, self.config.port)
        try:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            # connect(): the kernel then drops datagrams from any other address (spoofed or stray).
            sock.connect(address)
            sock.send(encode_rdt_request(RDT_START_REALTIME))
        except OSError as exc:
            raise SensorError(f"Net F/T at {address[0]}:{address[1]}: cannot start streaming ({exc})") from None
        self._sock = sock
        self._last_start = self._last_packet = time.monotonic()
        if self.config.bias_on_start:
            self.zero()

    def _send(self, command: int) -> None:
        if self._sock is None:
            raise SensorError("Net F/T: not started")
        try:
            self._sock.send(encode_rdt_request(command))
        except OSError as exc:
            raise SensorError(f"Net F/T at {self.config.host}:{self.config.port}: {exc}") from None

    def _error(self, problem: str) -> None:
        self.errors += 1
        self.last_error = problem

    def read(self, timeout: float) -> WrenchSample | None:
        sock = self._sock
        if sock is None:
            raise SensorError("Net F/T: read before start")
        now = time.monotonic()
        if now - self._last_packet > self.RESTART_AFTER and now - self._last_start > self.RESTART_AFTER:
            self._last_start = now
            try:
                sock.send(encode_rdt_request(RDT_START_REALTIME))
            except OSError as exc:
                self._error(f"cannot re-send the streaming request: {exc}")
        wrenches: list[Wrench] = []
        t_ns = 0
        sock.settimeout(max(timeout, 1e-4))
        while True:
            try:
                data = sock.recv(2048)
            except (TimeoutError, BlockingIOError):
                break
            except OSError as exc:  # e.g. ICMP port unreachable: nobody listens at that address
                self._error(f"receive failed: {exc}")
                break
            sock.settimeout(0.0)  # got one: drain the rest without waiting
            try:
                record = decode_rdt_record(data)
            except ValueError as exc:
                self._error(f"garbage packet: {exc}")
                continue
            if record.status != 0:
                # The box flags saturation, broken gauges, etc.: the values cannot be trusted.
                self._error(f"sensor reports status 0x{record.status:08x}")
                continue
            if self._last_rdt is not None and not seq_newer(record.rdt_sequence, self._last_rdt):
                continue  # a late, reordered datagram: older than what we have
            self._last_rdt = record.rdt_sequence
            self.received += 1
            arrived = time.monotonic()
            was_frozen = self._freeze.frozen
            if self._freeze.add(record.counts, arrived):
                if not was_frozen:  # once per spell: the monitor logs each new error
                    self._error(self._freeze.describe(arrived))
                continue  # not a sample; nor a sign of life: the streaming request is re-sent as after silence
            self._last_packet = arrived
            wrenches.append(rdt_wrench(record, self.config.counts_per_force, self.config.counts_per_torque))
            t_ns = time.time_ns()
        if not wrenches:
            return None
        return WrenchSample(wrenches[-1], t_ns, np.array(wrenches) if len(wrenches) > 1 else None)

    def zero(self) -> None:
        self._send(RDT_SET_BIAS)

    def close(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.send(encode_rdt_request(RDT_STOP))
            self._sock.close()
            self._sock = None


class RobotForceSensor(ForceSensor):
    """The arm's built-in wrist sensor: a UR e-Series reports it over RTDE (``getActualTCPForce``) in the base
    frame at the TCP; this turns it into the tool frame, as a wrist sensor reads. One sample per new robot state;
    none from a state that is old or from a robot that is not connected (the levels then go stale)."""

    paced_by_robot = True

    def __init__(self, config: RobotForceSensorConfig, reading: Callable[[], RobotReading | None]) -> None:
        self.config = config
        self._reading = reading
        self._offset = np.zeros(6)
        self._last_ns = 0
        self._lock = threading.Lock()

    def start(self) -> None:
        pass

    def _tool_frame(self, r: RobotReading) -> Wrench:
        rot = rotvec_to_matrix(np.asarray(r.tcp_pose, dtype=float)[3:]).T
        w = np.asarray(r.tcp_force, dtype=float)
        return np.concatenate([rot @ w[:3], rot @ w[3:]])

    def read(self, timeout: float) -> WrenchSample | None:
        r = self._reading()
        if r is None or not r.connected or r.monotonic_ns == self._last_ns:
            return None
        # Aged on the monotonic clock: on the wall clock a step forward would drop every sample, one back keep old ones.
        if time.monotonic_ns() - r.monotonic_ns > self.config.max_age * 1e9:
            return None
        self._last_ns = r.monotonic_ns
        with self._lock:
            return WrenchSample(self._tool_frame(r) - self._offset, r.timestamp_ns)

    def zero(self) -> None:
        r = self._reading()
        if r is None or not r.connected:
            raise SensorError("robot force sensor: no state from the robot, nothing to zero")
        with self._lock:
            self._offset = self._tool_frame(r)

    def close(self) -> None:
        pass


def make_force_sensor(
    config: ForceSensorConfig, phantom: PhantomConfig | None, reading: Callable[[], RobotReading | None]
) -> ForceSensor:
    if isinstance(config, SimForceSensorConfig):
        return SimForceSensor(config, phantom, reading)
    if isinstance(config, NetFTSensorConfig):
        return NetFTSensor(config)
    if isinstance(config, RobotForceSensorConfig):
        return RobotForceSensor(config, reading)
    raise ValueError(f"no force sensor driver for {type(config).__name__}")
