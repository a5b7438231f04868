"""Command → applied latency through one router with the simulated edge (the foundation's benchmark).

A thin wrapper around ``iorthand bench command-latency``: starts a router, ``iorthand edge`` with a simulated
robot and an OperatorClient on 127.0.0.1, streams 60 Hz twists for ``--duration`` seconds and writes
benchmarks/results/command_latency.json (+ command_latency.png). Extra arguments are passed on, e.g.
``--video`` (30 fps video through the same router) or ``--transport zenoh-chain3``.

    .venv/bin/python benchmarks/bench_command_latency.py --duration 20
"""

from __future__ import annotations

import sys
from pathlib import Path

from iorthand.cli import main

if __name__ == "__main__":
    out = Path(__file__).resolve().parent / "results"
    sys.exit(main(["bench", "command-latency", "--out", str(out), *sys.argv[1:]]))
