"""Bridges between Zenoh and other middleware: ``iorthand bridge mqtt`` (robot streams out to an MQTT broker as
JSON, sensor readings such as vital signs in). :mod:`.mapping` holds the rules (pure), :mod:`.mqtt` the adapter."""
