"""``iorthand router``: a Zenoh router run from the Python package (no zenohd binary needed)."""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import threading
from pathlib import Path

import zenoh

from iorthand.config import ConfigError, cli_number
from iorthand.security.diagnose import clear_beyond_loopback
from iorthand.transport import (
    DATAGRAM_MAX_LINKS,
    MAX_LINKS_KEY,
    announced_lease,
    check_endpoint,
    load_router_config,
    router_settings,
    with_datagram_links,
)

log = logging.getLogger("iorthand.router")


def run_router(config: zenoh.Config, describe: str) -> None:
    # A router keeps Zenoh's default threads: separate receive and transmit runtimes. All of it on one runtime
    # saved a thread wake-up per forwarded message (small commands p50 1.03-1.09 -> 0.81-0.87 ms), but then the
    # router closed any session a 300 KB frame went to ("Unable to push non droppable network message"): Zenoh
    # waits for a free batch synchronously, on the thread the transmit task needs to free it.
    if os.environ.get("ZENOH_RUNTIME"):
        log.warning("ZENOH_RUNTIME=%s: a router whose receive and transmit share a runtime closes the sessions "
                    "large payloads go to (see benchmarks/README.md)", os.environ["ZENOH_RUNTIME"])
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    # Zenoh's own warnings (links lost, transports closed) belong in a router's log; RUST_LOG overrides.
    zenoh.init_log_from_env_or("warn")
    session = zenoh.open(config)
    log.info("router %s listening on %s", session.zid(), describe)
    print(f"router ready: {describe}", flush=True)
    stop.wait()
    session.close()
    log.info("router stopped")


def _cmd(args: argparse.Namespace) -> int:
    for endpoint in [*(args.listen or []), *(args.connect or [])]:
        try:
            check_endpoint(endpoint)
        except ValueError as exc:
            raise ConfigError("command line", "--listen/--connect", str(exc)) from None
    if args.config:
        config = load_router_config(Path(args.config))
        if args.listen:
            config.insert_json5("listen/endpoints", json.dumps(args.listen))
        if args.connect:
            config.insert_json5("connect/endpoints", json.dumps(args.connect))
        lease_ms = args.lease_ms
        if not lease_ms and args.connect:
            lease_ms = announced_lease(json.loads(config.get_json("transport/link/tx/lease")), dials=True)
        if lease_ms:
            config.insert_json5("transport/link/tx/lease", str(lease_ms))
        if args.no_shared_memory:
            config.insert_json5("transport/shared_memory/enabled", "false")
        if args.datagrams:
            listen, connect = (_endpoints(config, "listen"), _endpoints(config, "connect"))
            try:
                listen, connect = with_datagram_links(listen, connect)
            except ValueError as exc:
                raise ConfigError(args.config, "--datagrams", str(exc)) from None
            config.insert_json5("listen/endpoints", json.dumps(listen))
            config.insert_json5("connect/endpoints", json.dumps(connect))
            config.insert_json5(MAX_LINKS_KEY, str(DATAGRAM_MAX_LINKS))
    else:
        try:
            settings = router_settings(args.listen or ["tcp/127.0.0.1:7447"], args.connect, lease_ms=args.lease_ms,
                                       shared_memory=not args.no_shared_memory, datagrams=args.datagrams)
        except ValueError as exc:
            raise ConfigError("command line", "--datagrams", str(exc)) from None
        config = zenoh.Config.from_json5(json.dumps(settings))
    listen = _endpoints(config, "listen")
    clear = clear_beyond_loopback(listen)
    if clear:
        # Not refused: a closed lab or a test's network namespace may want it. But said, at every start: anyone who
        # reaches that port may command the robots (`iorthand check` refuses such a router configuration).
        log.warning("listening in clear on %s, reachable from the network: nobody is authenticated and anyone who "
                    "reaches it may command the robots. Outside a closed lab, run the TLS configuration that "
                    "`iorthand certs router-config` generates (docs/DEPLOY.md §2)", ", ".join(clear))
    run_router(config, ", ".join(listen))
    return 0


def _endpoints(config: zenoh.Config, which: str) -> list[str]:
    endpoints = json.loads(config.get_json(f"{which}/endpoints"))
    if isinstance(endpoints, dict):  # per-role form {router: [...], peer: [...]}
        endpoints = endpoints.get("router", [])
    return list(endpoints)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("router", help="run a Zenoh router")
    p.add_argument("--config", help="router JSON5 configuration (e.g. configs/router.json5)")
    p.add_argument("--listen", action="append", help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)")
    p.add_argument("--connect", action="append", help="another router to connect to (a chain of sites)")
    p.add_argument("--lease-ms", type=cli_number(int, lo=500, hi=60_000), help="the lease this router announces (default 2000 ms, 1000 ms more with --connect: see announced_lease)")
    p.add_argument("--no-shared-memory", action="store_true",
                   help="never hand payloads over through shared memory (a router modelling its own host)")
    p.add_argument("--datagrams", action="store_true",
                   help="UDP links beside the TCP ones (listen on UDP at each TCP address, dial UDP beside each TCP "
                        "--connect): the video goes as datagrams, everything else stays on TCP; not with tls/ "
                        "(use quic/HOST:PORT?mixed_rel=1)")
    p.set_defaults(func=_cmd)
