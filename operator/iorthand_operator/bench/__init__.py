"""Benchmarks of the command path, transports, load, WAN profiles and scale (issue 9)."""
