"""iorthand operator tools: teleoperation client, console and benchmarks."""
