"""The viewer's gateway: what browsers reach of the rerun relay, and nothing that writes.

The relay (``rerun --serve-web``) takes writes on the same gRPC port its viewers read from: ``WriteMessages``
over HTTP/2 (how the twin streams to it) and ``WriteTable``. Anyone who reached that port, including every user
an authenticating reverse proxy lets through to watch, could draw a robot, a force or an image into what every
viewer sees. So the relay listens on loopback ports of its own, and this gateway, a process of its own, serves
the public ports:

- the web viewer's port: GET and HEAD of the relay's web server (the page and its wasm), nothing else;
- the data port: the browser's gRPC-Web calls that read (:data:`READ_METHODS`, and their CORS preflights),
  streamed through as they come. Any other method, path or protocol is refused (403 with the reason; HTTP/2,
  how a native gRPC client writes, is not spoken here at all).

Both refuse (421) a request that names a host the viewer is not (``--hosts``): a DNS-rebinding page would
otherwise be the viewer's own origin and read the patient's images from a browser that reaches the viewer.

Run by :class:`iorthand_cloud.twin.server.ViewerServer`: ``python -m iorthand_cloud.twin.gateway --web
HOST:PORT=UPSTREAM_PORT --data HOST:PORT=UPSTREAM_PORT --hosts NAME,...``, the upstream ports on 127.0.0.1.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import sys
from collections.abc import Callable, Iterable

from aiohttp import ClientSession, ClientTimeout, web

from iorthand.security.hosts import host_allowed, normalise

log = logging.getLogger("iorthand.twin.gateway")

_PROXY_SERVICE = "/rerun.sdk_comms.v1alpha1.MessageProxyService"
READ_METHODS = frozenset({f"{_PROXY_SERVICE}/ReadMessages", f"{_PROXY_SERVICE}/ReadTables"})
READ_ONLY = "the twin's viewer is read-only: only the viewer's reads pass here (writes go to the twin alone)"
# Headers that belong to one hop (RFC 9110 §7.6.1), and those aiohttp sets itself for the next.
_HOP = frozenset({"connection", "keep-alive", "proxy-connection", "te", "trailer", "transfer-encoding", "upgrade",
                  "host", "content-length"})
MAX_REQUEST_BYTES = 64 * 1024  # a read request is a few bytes; nothing larger is taken in
_CHUNK = 1 << 16


def _forwarded(headers: Iterable[tuple[str, str]]) -> list[tuple[str, str]]:
    return [(k, v) for k, v in headers if k.lower() not in _HOP]


def data_allowed(method: str, path: str) -> bool:
    """Whether a request to the data port is a viewer's read (or the browser's preflight for one)."""
    return method in ("POST", "OPTIONS") and path in READ_METHODS


def web_allowed(method: str, path: str) -> bool:
    """Whether a request to the web port only fetches the viewer (its page and assets)."""
    return method in ("GET", "HEAD")


def make_app(upstream_port: int, allowed: Callable[[str, str], bool], hosts: frozenset[str] | None = None
             ) -> web.Application:
    """A proxy to ``127.0.0.1:upstream_port`` of what ``allowed(method, path)`` lets through, for requests that name
    one of ``hosts`` (None: any; see :mod:`iorthand.security.hosts`)."""
    app = web.Application(client_max_size=MAX_REQUEST_BYTES)

    async def start_client(app: web.Application) -> None:
        # No timeout on a response: a viewer's read is a stream for as long as the page stays open.
        app["client"] = ClientSession(timeout=ClientTimeout(total=None, sock_connect=5.0), auto_decompress=False)

    async def stop_client(app: web.Application) -> None:
        await app["client"].close()

    async def forward(request: web.Request) -> web.StreamResponse:
        if hosts is not None and not host_allowed(request.host, hosts):
            log.warning("refused a request for host %r from %s", request.host[:80], request.remote)
            raise web.HTTPMisdirectedRequest(text=f"the twin's viewer does not answer to host {request.host[:80]!r}: "
                                             "open it by its own name (viewer.public_host)")
        if not allowed(request.method, request.path):
            log.warning("refused %s %s from %s", request.method, request.path[:120], request.remote)
            raise web.HTTPForbidden(text=f"{READ_ONLY}; {request.method} {request.path[:120]} is not one")
        body = await request.read()
        client: ClientSession = request.app["client"]
        url = f"http://127.0.0.1:{upstream_port}{request.path_qs}"
        async with client.request(request.method, url, headers=_forwarded(request.headers.items()), data=body,
                                  allow_redirects=False) as upstream:
            response = web.StreamResponse(status=upstream.status, reason=upstream.reason)
            for k, v in _forwarded(upstream.headers.items()):
                response.headers.add(k, v)
            await response.prepare(request)
            with contextlib.suppress(ConnectionError):  # the browser went: the upstream stream ends with it
                async for chunk in upstream.content.iter_chunked(_CHUNK):
                    await response.write(chunk)
                await response.write_eof()
        return response

    app.on_startup.append(start_client)
    app.on_cleanup.append(stop_client)
    app.router.add_route("*", "/{tail:.*}", forward)
    return app


def _site(spec: str) -> tuple[str, int, int]:
    """HOST:PORT=UPSTREAM_PORT → (host, port, upstream port)."""
    listen, sep, upstream = spec.rpartition("=")
    host, colon, port = listen.rpartition(":")
    if not sep or not colon or not port.isdigit() or not upstream.isdigit():
        raise ValueError(f"{spec!r}: expected HOST:PORT=UPSTREAM_PORT")
    return host.strip("[]"), int(port), int(upstream)


async def serve(sites: list[tuple[str, int, web.Application]], stop: asyncio.Event) -> None:
    runners: list[web.AppRunner] = []
    try:
        for host, port, app in sites:
            runner = web.AppRunner(app, access_log=None)
            await runner.setup()
            runners.append(runner)
            await web.TCPSite(runner, host, port).start()
        print("gateway ready", flush=True)
        await stop.wait()
    finally:
        for runner in runners:
            await runner.cleanup()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m iorthand_cloud.twin.gateway", description=__doc__.split("\n")[0])
    parser.add_argument("--web", required=True, help="HOST:PORT=UPSTREAM_PORT of the viewer's page and assets")
    parser.add_argument("--data", required=True, help="HOST:PORT=UPSTREAM_PORT of the viewer's data (gRPC-Web)")
    parser.add_argument("--hosts", default="", help="comma-separated names requests may name (default: any)")
    args = parser.parse_args(argv)
    hosts = normalise(args.hosts.split(",")) if args.hosts else None
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        (web_host, web_port, web_up), (data_host, data_port, data_up) = _site(args.web), _site(args.data)
    except ValueError as exc:
        parser.error(str(exc))

    async def run() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        await serve([(web_host, web_port, make_app(web_up, web_allowed, hosts)),
                     (data_host, data_port, make_app(data_up, data_allowed, hosts))], stop)

    try:
        asyncio.run(run())
    except OSError as exc:
        print(f"gateway: cannot listen: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
