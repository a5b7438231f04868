"""Servo and torch configuration. Angles are in degrees here (what a technician reads on a servo's data
sheet); the code and the wire use radians."""

from __future__ import annotations

import string
from dataclasses import dataclass, field
from typing import ClassVar

from iorthand.config import setting


@dataclass
class ActuatorDriverConfig:
    VARIANTS: ClassVar[dict[str, type[ActuatorDriverConfig]]] = {}
    KIND: ClassVar[str] = ""


@dataclass
class SimDriverConfig(ActuatorDriverConfig):
    """No hardware: the driver remembers what it was told (demo, tests)."""

    KIND: ClassVar[str] = "sim"


@dataclass
class PCA9685DriverConfig(ActuatorDriverConfig):
    """A PCA9685 PWM board on I²C, through adafruit-circuitpython-servokit (``pip install iorthand-edge[pi]``)."""

    KIND: ClassVar[str] = "pca9685"
    address: int = setting(0x40, lo=0x03, hi=0x77, help="I²C address of the board")
    channels: int = setting(16, choices=(8, 16))
    frequency: int = setting(50, lo=24, hi=1526, help="PWM frequency, Hz (50 for hobby servos)")
    min_pulse_us: int = setting(500, lo=100, hi=3000)
    max_pulse_us: int = setting(2500, lo=100, hi=3000)


PCA9685_RANGE_DEG = 180.0  # ServoKit's actuation range: the angles its servos take

SERIAL_FIELDS = {"channel": 0, "degrees": 90.0, "value": 0.5, "percent": 50, "pwm": 128}


@dataclass
class SerialDriverConfig(ActuatorDriverConfig):
    """A microcontroller on a serial port (pyserial). Commands are text lines built from templates with the
    fields ``{channel}``, ``{degrees}`` (servo angle), ``{value}`` (0–1), ``{percent}`` (0–100), ``{pwm}``
    (0–255)."""

    KIND: ClassVar[str] = "serial"
    port: str = setting("/dev/ttyACM0", help="device path or pyserial URL (e.g. loop://, rfc2217://host:port)")
    baudrate: int = setting(115200, lo=300, hi=4_000_000)
    timeout: float = setting(0.2, lo=0.001, hi=5.0, help="s to wait for an acknowledgement or a write")
    servo_format: str = "S{channel}:{degrees:.1f}\n"
    level_format: str = "L{channel}:{percent}\n"
    ack: str = setting("", help="reply line expected after each command (e.g. OK); empty: none expected")

    def check(self) -> None:
        for name in ("servo_format", "level_format"):
            template = getattr(self, name)
            try:
                names = {f for _, f, _, _ in string.Formatter().parse(template) if f}
                unknown = names - set(SERIAL_FIELDS)
                if unknown:
                    raise ValueError(f"unknown fields {sorted(unknown)}")
                template.format(**SERIAL_FIELDS)
            except (ValueError, KeyError, IndexError) as exc:
                raise ValueError(f"{name} {template!r} is not a valid template ({exc}); fields: {sorted(SERIAL_FIELDS)}") from None


ActuatorDriverConfig.VARIANTS = {c.KIND: c for c in (SimDriverConfig, PCA9685DriverConfig, SerialDriverConfig)}


@dataclass
class ServoAxisConfig:
    channel: int = setting(0, lo=0, hi=255)
    min_deg: float = setting(0.0, lo=-360.0, hi=360.0)
    max_deg: float = setting(180.0, lo=-360.0, hi=360.0)
    home_deg: float = setting(90.0, lo=-360.0, hi=360.0)

    def check(self) -> None:
        if not self.min_deg < self.max_deg:
            raise ValueError(f"min_deg {self.min_deg} must be below max_deg {self.max_deg}")
        if not self.min_deg <= self.home_deg <= self.max_deg:
            raise ValueError(f"home_deg {self.home_deg} is outside [{self.min_deg}, {self.max_deg}]")


@dataclass
class ServosConfig:
    driver: ActuatorDriverConfig = field(default_factory=SimDriverConfig)
    pan: ServoAxisConfig = field(default_factory=lambda: ServoAxisConfig(channel=0))
    tilt: ServoAxisConfig = field(default_factory=lambda: ServoAxisConfig(channel=1))
    max_rate_deg_s: float = setting(90.0, lo=1.0, hi=2000.0, help="angular speed limit of each servo")
    rate_hz: float = setting(50.0, lo=5.0, hi=500.0, help="update rate of the rate-limited motion")
    publish_hz: float = setting(2.0, lo=0.1, hi=50.0, help="state/servo heartbeat (also sent on change)")
    history_s: float = setting(2.0, lo=0.1, hi=60.0, help="s of angles kept for servo_angles_at()")

    def check(self) -> None:
        if self.pan.channel == self.tilt.channel:
            raise ValueError(f"pan and tilt share channel {self.pan.channel}")
        if isinstance(self.driver, PCA9685DriverConfig):
            for name, axis in (("pan", self.pan), ("tilt", self.tilt)):
                if axis.channel >= self.driver.channels:
                    raise ValueError(f"{name}.channel {axis.channel}: the PCA9685 board has channels 0.."
                                     f"{self.driver.channels - 1}")
                if axis.min_deg < 0.0 or axis.max_deg > PCA9685_RANGE_DEG:
                    # ServoKit refuses any other angle: every move of that axis would fail at run time.
                    raise ValueError(f"{name}: [{axis.min_deg:g}, {axis.max_deg:g}]° is outside what a PCA9685 "
                                     f"servo takes, 0..{PCA9685_RANGE_DEG:g}° (centre {PCA9685_RANGE_DEG / 2:g})")


@dataclass
class TorchConfig:
    driver: ActuatorDriverConfig = field(default_factory=SimDriverConfig)
    channel: int = setting(2, lo=0, hi=255)
    max_brightness: float = setting(1.0, lo=0.0, hi=1.0, help="cap (heat, glare on the patient)")
    publish_hz: float = setting(2.0, lo=0.1, hi=50.0, help="state/torch heartbeat (also sent on change)")
