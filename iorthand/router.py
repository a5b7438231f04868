"""``iorthand router``: a Zenoh router run from the Python package (no zenohd binary needed)."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import threading
from pathlib import Path

import zenoh

from iorthand.transport import load_router_config, router_settings

log = logging.getLogger("iorthand.router")


def run_router(config: zenoh.Config, describe: str) -> None:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    session = zenoh.open(config)
    log.info("router %s listening on %s", session.zid(), describe)
    print(f"router ready: {describe}", flush=True)
    stop.wait()
    session.close()
    log.info("router stopped")


def _cmd(args: argparse.Namespace) -> int:
    if args.config:
        config = load_router_config(Path(args.config))
        if args.listen:
            config.insert_json5("listen/endpoints", json.dumps(args.listen))
        if args.connect:
            config.insert_json5("connect/endpoints", json.dumps(args.connect))
    else:
        settings = router_settings(args.listen or ["tcp/127.0.0.1:7447"], args.connect)
        config = zenoh.Config.from_json5(json.dumps(settings))
    endpoints = json.loads(config.get_json("listen/endpoints"))
    if isinstance(endpoints, dict):  # per-role form {router: [...], peer: [...]}
        endpoints = endpoints.get("router", [])
    run_router(config, ", ".join(endpoints))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("router", help="run a Zenoh router")
    p.add_argument("--config", help="router JSON5 configuration (e.g. configs/router.json5)")
    p.add_argument("--listen", action="append", help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)")
    p.add_argument("--connect", action="append", help="another router to connect to (a chain of sites)")
    p.set_defaults(func=_cmd)
