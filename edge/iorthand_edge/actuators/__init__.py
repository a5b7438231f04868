"""Pan/tilt servos and the torch: configuration, pure decisions, drivers (sim, PCA9685, serial), units."""

from iorthand_edge.actuators.config import (
    ActuatorDriverConfig,
    PCA9685DriverConfig,
    SerialDriverConfig,
    ServoAxisConfig,
    ServosConfig,
    SimDriverConfig,
    TorchConfig,
)
from iorthand_edge.actuators.drivers import ActuatorDriver, ActuatorError, make_driver
from iorthand_edge.actuators.units import ServoUnit, TorchUnit

__all__ = [
    "ActuatorDriver",
    "ActuatorDriverConfig",
    "ActuatorError",
    "PCA9685DriverConfig",
    "SerialDriverConfig",
    "ServoAxisConfig",
    "ServoUnit",
    "ServosConfig",
    "SimDriverConfig",
    "TorchConfig",
    "TorchUnit",
    "make_driver",
]
