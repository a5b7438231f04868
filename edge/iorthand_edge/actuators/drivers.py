"""Actuator drivers: set a servo angle or a PWM level on a channel. Hardware libraries are imported only when
their driver is opened, so the simulated setup needs none of them; a missing library or device fails with an
:class:`ActuatorError` that says what to install or check."""

from __future__ import annotations

import contextlib
import importlib
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any, Protocol

from iorthand_edge.actuators.config import (
    ActuatorDriverConfig,
    PCA9685DriverConfig,
    SerialDriverConfig,
    SimDriverConfig,
)


class ActuatorError(RuntimeError):
    """An actuator cannot be driven (no library, no device, link broken); the message says why."""


class ActuatorDriver(ABC):
    @abstractmethod
    def open(self) -> None:
        """Reach the hardware; raise ActuatorError with the reason if it cannot."""

    @abstractmethod
    def set_angle(self, channel: int, degrees: float) -> None:
        """Move a servo; raise ActuatorError if the command cannot be delivered."""

    @abstractmethod
    def set_level(self, channel: int, value: float) -> None:
        """Set a PWM output (a torch) to ``value`` in [0, 1]; raise ActuatorError if it cannot."""

    @abstractmethod
    def close(self) -> None:
        """Release the hardware. Never raises."""


class SimDriver(ActuatorDriver):
    def __init__(self, config: SimDriverConfig | None = None) -> None:
        self.angles: dict[int, float] = {}
        self.levels: dict[int, float] = {}
        self.writes = 0
        self.is_open = False

    def open(self) -> None:
        self.is_open = True

    def _check(self) -> None:
        if not self.is_open:
            raise ActuatorError("simulated actuator driver is closed")

    def set_angle(self, channel: int, degrees: float) -> None:
        self._check()
        self.angles[channel] = degrees
        self.writes += 1

    def set_level(self, channel: int, value: float) -> None:
        self._check()
        self.levels[channel] = value
        self.writes += 1

    def close(self) -> None:
        self.is_open = False


def _import(module: str, package: str) -> Any:
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise ActuatorError(
            f"this driver needs the Python package {package} ({exc}); install it with: pip install 'iorthand-edge[pi]'"
        ) from None


class PCA9685Driver(ActuatorDriver):
    def __init__(self, config: PCA9685DriverConfig) -> None:
        self.config = config
        self._kit: Any = None

    def open(self) -> None:
        servokit = _import("adafruit_servokit", "adafruit-circuitpython-servokit")
        c = self.config
        try:
            self._kit = servokit.ServoKit(channels=c.channels, address=c.address, frequency=c.frequency)
        except (OSError, ValueError, RuntimeError) as exc:
            # Blinka raises all three for a missing bus, a disabled I²C interface or nothing at the address.
            raise ActuatorError(
                f"no PCA9685 reachable at I²C address 0x{c.address:02x}: {exc}. Is I²C enabled "
                "(raspi-config → Interface Options → I2C) and the board wired and powered?"
            ) from None
        for ch in range(c.channels):
            self._kit.servo[ch].set_pulse_width_range(c.min_pulse_us, c.max_pulse_us)

    def _require(self) -> Any:
        if self._kit is None:
            raise ActuatorError("PCA9685 driver used before open()")
        return self._kit

    def set_angle(self, channel: int, degrees: float) -> None:
        kit = self._require()
        try:
            kit.servo[channel].angle = degrees
        except (OSError, ValueError, IndexError) as exc:
            raise ActuatorError(f"PCA9685 channel {channel}: cannot set {degrees:.1f}°: {exc}") from None

    def set_level(self, channel: int, value: float) -> None:
        kit = self._require()
        try:
            # ServoKit has no public PWM call; its PCA9685 object is the one handle to the shared chip.
            kit._pca.channels[channel].duty_cycle = round(value * 0xFFFF)
        except (OSError, ValueError, IndexError) as exc:
            raise ActuatorError(f"PCA9685 channel {channel}: cannot set level {value:.2f}: {exc}") from None

    def close(self) -> None:
        kit, self._kit = self._kit, None
        if kit is not None:
            with contextlib.suppress(Exception):  # closing must never raise; the process is going away anyway
                kit._pca.deinit()


class SerialPort(Protocol):
    """What the serial driver needs of a port (pyserial's Serial has it)."""

    def write(self, data: bytes) -> int | None: ...
    def readline(self) -> bytes: ...
    def close(self) -> None: ...


def format_serial_command(template: str, channel: int, value: float, degrees: float = 0.0) -> bytes:
    """The bytes of one command line (pure; ``value`` in [0, 1] for levels)."""
    v = min(1.0, max(0.0, value))
    text = template.format(channel=channel, degrees=degrees, value=v, percent=round(100 * v), pwm=round(255 * v))
    return text.encode("ascii")


def _open_pyserial(config: SerialDriverConfig) -> SerialPort:
    serial = _import("serial", "pyserial")
    try:
        return serial.serial_for_url(config.port, baudrate=config.baudrate, timeout=config.timeout,
                                     write_timeout=config.timeout)
    except (OSError, ValueError) as exc:  # SerialException is an OSError
        raise ActuatorError(f"cannot open serial port {config.port}: {exc}. Is the microcontroller plugged in?") from None


class SerialDriver(ActuatorDriver):
    def __init__(self, config: SerialDriverConfig, opener: Callable[[SerialDriverConfig], SerialPort] | None = None) -> None:
        self.config = config
        self._opener = opener or _open_pyserial
        self._port: SerialPort | None = None
        self._lock = threading.Lock()  # servos and torch may share one port

    def open(self) -> None:
        self._port = self._opener(self.config)

    def _send(self, line: bytes) -> None:
        with self._lock:
            port = self._port
            if port is None:
                raise ActuatorError(f"serial port {self.config.port} is not open")
            try:
                port.write(line)
                if self.config.ack:
                    reply = port.readline().decode("ascii", errors="replace").strip()
                    if reply != self.config.ack:
                        raise ActuatorError(
                            f"serial port {self.config.port}: expected {self.config.ack!r} after {line!r}, got "
                            f"{reply!r}" + (" (no reply within the timeout)" if not reply else "")
                        )
            except (OSError, ValueError, TypeError, AttributeError) as exc:
                # pyserial raises SerialException (OSError) on a dead port, PortNotOpenError on a closed one.
                raise ActuatorError(f"serial port {self.config.port}: {exc}") from None

    def set_angle(self, channel: int, degrees: float) -> None:
        self._send(format_serial_command(self.config.servo_format, channel, 0.0, degrees))

    def set_level(self, channel: int, value: float) -> None:
        self._send(format_serial_command(self.config.level_format, channel, value))

    def close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            with contextlib.suppress(Exception):  # closing must never raise
                port.close()


def make_driver(config: ActuatorDriverConfig) -> ActuatorDriver:
    if isinstance(config, SimDriverConfig):
        return SimDriver(config)
    if isinstance(config, PCA9685DriverConfig):
        return PCA9685Driver(config)
    if isinstance(config, SerialDriverConfig):
        return SerialDriver(config)
    raise ValueError(f"no actuator driver for {type(config).__name__}")
