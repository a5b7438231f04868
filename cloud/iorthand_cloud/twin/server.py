"""Where the twin's rerun data goes: the web viewer an operator opens in a browser, and/or an .rrd file.

Choice (issue 6 §4, FACTS.md): ``rr.serve_grpc`` / ``rr.serve_web_viewer`` always bind 0.0.0.0 and have no
option to change it, so they cannot honour ``viewer.bind: 127.0.0.1`` (the default: expose the viewer only
through a reverse proxy or an SSH tunnel). The twin therefore runs rerun's own relay as a child process,

    rerun --serve-web --bind 127.0.0.1 --port <relay port> --web-viewer-port <relay port> --server-memory-limit <limit>

and streams to it with ``connect_grpc``. Browsers reach it only through the viewer's gateway (gateway.py, a child
process too), on ``bind``'s ``web_port`` and ``grpc_port``: the page, its assets and the viewer's reads pass, and
nothing that writes (the relay's gRPC port takes writes from anyone who reaches it). One code path for every bind
address, and a side benefit: the
relay's buffering and the HTTP serving use another process's CPU and memory, never the twin's (the memory
limit drops the oldest data; static data — the robot model — is kept). The relay dies with the twin
(PR_SET_PDEATHSIG) and is terminated on shutdown. The viewer's assets are inside the wheel: no network.
The relay reads its web viewer (a 43 MB wasm) into memory at the first page load and keeps it: the twin loads
it once at start (:func:`_load_viewer_assets`), so the twin's memory is what it will stay from the start
instead of jumping by ~45 MB when the first browser opens the viewer hours later (measured: +44.5 MB at the
first viewer, +0.4 MB at the second and third).

``viewer.save`` adds a file sink with the same data (``set_sinks``), with or without serving. Without the rrd
footer by default (``viewer.save_footer``): rerun keeps the footer's index of every chunk in memory until the
file closes, which grew the twin by ~10 MB a minute (+200 MB by the 500 MB cap) in the soak benchmark.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
import urllib.parse
import urllib.request
from pathlib import Path
from typing import Any

import rerun as rr

from iorthand.process import die_with_parent, terminate
from iorthand.security.hosts import WILDCARDS, own_names
from iorthand.transport import free_port

from .config import ViewerConfig

log = logging.getLogger("iorthand.twin.server")


def rerun_executable() -> str:
    """The ``rerun`` binary of the installed rerun-sdk (same version as the SDK).

    Not the ``bin/rerun`` entry point: that is a Python wrapper which runs the binary as *its* child, so
    terminating the wrapper would leave the relay running (seen in testing)."""
    try:
        import rerun_cli

        binary = Path(rerun_cli.__file__).parent / "rerun"
        if binary.exists():
            return str(binary)
    except ImportError:
        pass
    found = shutil.which("rerun")
    if found is None:
        raise RuntimeError("the rerun CLI (from rerun-sdk) is not installed: pip install rerun-sdk==0.41.0")
    return found


def viewer_url(host: str, grpc_port: int, web_port: int) -> str:
    """The URL to open in a browser: the web viewer, told where its data (the gRPC proxy) is."""
    data = f"rerun+http://{host}:{grpc_port}/proxy"
    return f"http://{host}:{web_port}/?url={urllib.parse.quote(data, safe='')}"


def viewer_hosts(c: ViewerConfig) -> frozenset[str]:
    """The names the viewer's gateway answers to: its bind address, ``public_host``, and the loopback names on a
    loopback bind. Empty (any name) on a wildcard bind without a ``public_host``: there the machine's own addresses,
    which browsers may use, are not known here."""
    if c.bind in WILDCARDS and not c.public_host:
        return frozenset()
    return own_names(c.bind, [c.public_host])


def _load_viewer_assets(host: str, web_port: int, timeout: float = 10.0) -> None:
    """Ask the relay's web server for the viewer's page and the wasm it names, as a browser would (see the
    module's docstring). Not being able to costs only memory later: a warning, never a failed start."""
    base = f"http://{host}:{web_port}/"
    try:
        with urllib.request.urlopen(base, timeout=timeout) as r:
            page = r.read().decode("utf-8", "replace")
        for name in sorted(set(re.findall(r'["\'](?:\./)?([\w.-]+\.wasm)["\']', page))):
            with urllib.request.urlopen(base + name, timeout=timeout) as r:
                while r.read(1 << 20):
                    pass
    except OSError as exc:
        log.warning("could not load the web viewer's assets from %s at start (%s): the relay will load them at "
                    "the first page load instead", base, exc)


def _wait_port(host: str, port: int, timeout: float, proc: subprocess.Popen[bytes], what: str) -> None:
    target = "127.0.0.1" if host in WILDCARDS else host
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"{what} exited with code {proc.returncode} (port {port} in use?)")
        try:
            with socket.create_connection((target, port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise RuntimeError(f"{what} did not listen on {host}:{port} within {timeout:g} s")


class ViewerServer:
    """Starts the relay (when serving) and points a recording stream at the relay and/or a file."""

    def __init__(self, config: ViewerConfig, save: Path | None = None, log_dir: Path | None = None) -> None:
        self.config = config
        self.save = save if save is not None else config.save
        self.log_dir = log_dir
        self.proc: subprocess.Popen[bytes] | None = None  # the rerun relay
        self.gateway: subprocess.Popen[bytes] | None = None  # what browsers reach of it (gateway.py)
        self.url = ""
        self.grpc_url = ""
        self._rec: rr.RecordingStream | None = None
        self._stopped = threading.Event()
        self._live_sinks: list[object] = []
        self._blueprint: object | None = None
        self._watch: threading.Thread | None = None
        self.save_stopped = False

    def start(self, rec: rr.RecordingStream, default_blueprint: object | None = None) -> None:
        self._rec = rec
        c = self.config
        sinks: list[object] = []
        if c.serve:
            host = c.public_host or ("127.0.0.1" if c.bind in WILDCARDS else c.bind)
            # The relay on loopback ports of its own, which only this host reaches; the viewer's ports are the
            # read-only gateway's (see gateway.py: the relay's gRPC port takes writes from anyone who reaches it).
            relay_grpc, relay_web = free_port(), free_port()
            argv = [
                rerun_executable(), "--serve-web", "--bind", "127.0.0.1", "--port", str(relay_grpc),
                "--web-viewer-port", str(relay_web), "--server-memory-limit", c.memory_limit,
                "--newest-first",  # a browser that opens the viewer gets now first, then what came before
            ]
            env = {**os.environ, "RERUN_ANALYTICS": "0"}
            self.proc = subprocess.Popen(argv, stdout=self._log("rerun-relay.log"), stderr=subprocess.STDOUT,
                                         stdin=subprocess.DEVNULL, preexec_fn=die_with_parent, env=env)
            _wait_port("127.0.0.1", relay_grpc, c.relay_start_timeout, self.proc, "the rerun relay")
            _wait_port("127.0.0.1", relay_web, c.relay_start_timeout, self.proc, "the rerun relay")
            _load_viewer_assets("127.0.0.1", relay_web)
            hosts = viewer_hosts(c)
            self.gateway = subprocess.Popen(
                [sys.executable, "-m", "iorthand_cloud.twin.gateway", "--web", f"{c.bind}:{c.web_port}={relay_web}",
                 "--data", f"{c.bind}:{c.grpc_port}={relay_grpc}", *(["--hosts", ",".join(sorted(hosts))] if hosts else [])],
                stdout=self._log("viewer-gateway.log"), stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                preexec_fn=die_with_parent)
            _wait_port(c.bind, c.grpc_port, c.relay_start_timeout, self.gateway, "the viewer's gateway")
            _wait_port(c.bind, c.web_port, c.relay_start_timeout, self.gateway, "the viewer's gateway")
            self.grpc_url = f"rerun+http://127.0.0.1:{relay_grpc}/proxy"
            self.url = viewer_url(host, c.grpc_port, c.web_port)
            sinks.append(rr.GrpcSink(self.grpc_url))
            log.info("rerun web viewer on %s:%d (data %s:%d, read-only); open %s", c.bind, c.web_port, c.bind,
                     c.grpc_port, self.url)
        if self.save is not None:
            Path(self.save).parent.mkdir(parents=True, exist_ok=True)
            # No footer by default: the FileSink keeps a manifest entry per chunk in memory until it closes (rerun
            # 0.41 docs; measured: the twin's RSS grew ~7 MB/min while saving and jumped when the footer was written).
            sinks.append(rr.FileSink(str(self.save), write_footer=c.save_footer))
            log.info("saving the twin's rerun data to %s (at most %g MB%s)", self.save, c.save_max_mb,
                     "" if c.save_footer else "; no footer: `rerun rrd optimize FILE -o OUT` adds one")
            self._live_sinks = [s for s in sinks if not isinstance(s, rr.FileSink)]
            self._blueprint = default_blueprint
            self._watch = threading.Thread(target=self._bound_save, name="twin-save-bound", daemon=True)
            self._watch.start()
        if sinks:
            rec.set_sinks(*sinks, default_blueprint=default_blueprint)  # type: ignore[arg-type]

    def _bound_save(self) -> None:
        """Stop the .rrd file at ``save_max_mb``: a twin runs for a clinic day, its file would grow without end
        (the recorder's MCAP files hold whole sessions; ``iorthand export`` makes an .rrd of any part of one)."""
        limit = self.config.save_max_mb * 1e6
        while not self._stopped.wait(5.0):
            try:
                size = Path(self.save).stat().st_size  # type: ignore[arg-type]
            except OSError:
                continue
            if size >= limit and self._rec is not None:
                if self._live_sinks:
                    self._rec.set_sinks(*self._live_sinks, default_blueprint=self._blueprint)  # type: ignore[arg-type]
                else:
                    self._rec.disconnect()
                self.save_stopped = True
                log.warning("%s reached %.0f MB: the twin stops saving it (the viewer stays live; the recorder's "
                            "files hold the whole session)", self.save, size / 1e6)
                return

    def stop(self) -> None:
        self._stopped.set()
        if self._rec is not None:
            # Flush and drop the sinks before the relay goes: a stream left pointing at a dead relay reports
            # "connection severed" errors when the process exits.
            with contextlib.suppress(Exception):
                self._rec.flush(timeout_sec=2.0)
                self._rec.disconnect()
            self._rec = None
        for proc in (self.gateway, self.proc):
            if proc is not None:
                terminate(proc)
        self.proc = self.gateway = None

    def _log(self, name: str) -> Any:
        """A child's output: a file in ``log_dir``, or nowhere."""
        if self.log_dir is None:
            return subprocess.DEVNULL
        self.log_dir.mkdir(parents=True, exist_ok=True)
        return (self.log_dir / name).open("wb")


__all__ = ["ViewerServer", "rerun_executable", "viewer_hosts", "viewer_url"]
