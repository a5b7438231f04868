"""iorthand: safe robot teleoperation over Zenoh — the core (protocol, geometry, configuration, transport)."""

__version__ = "0.1.0"
