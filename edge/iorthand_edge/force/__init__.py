"""Force sensing: sensors behind one interface, warning levels (pure), and the worker that publishes them."""

from iorthand_edge.force.config import ForceConfig, ForceSensorConfig, NetFTSensorConfig, SimForceSensorConfig
from iorthand_edge.force.contact import PhantomConfig, contact_wrench
from iorthand_edge.force.levels import LevelConfig, LevelState, LevelTracker, next_level, quantity_value
from iorthand_edge.force.sensors import ForceSensor, SensorError, WrenchSample, make_force_sensor

__all__ = [
    "ForceConfig",
    "ForceSensor",
    "ForceSensorConfig",
    "LevelConfig",
    "LevelState",
    "LevelTracker",
    "NetFTSensorConfig",
    "PhantomConfig",
    "SensorError",
    "SimForceSensorConfig",
    "WrenchSample",
    "contact_wrench",
    "make_force_sensor",
    "next_level",
    "quantity_value",
]
