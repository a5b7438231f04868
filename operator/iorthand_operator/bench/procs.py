"""Child processes of a benchmark run: started with a log file, optionally inside a network namespace, and
always stopped — by ``try/finally`` in the caller, by ``atexit``, on SIGTERM/SIGINT, and by the kernel
(PR_SET_PDEATHSIG) if the benchmark itself is killed. Every wait has a time bound."""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import psutil

from iorthand.process import die_with_parent

log = logging.getLogger("iorthand.bench")

_cleanups: list[Callable[[], None]] = []
_cleanup_lock = threading.Lock()
_handlers_installed = False
# Scheduling priority of every child (os.nice increment; negative needs root). 0 by default: a shared machine
# is measured as it is. ``--nice -5`` isolates the benchmark from other users' work, and the JSON says so.
NICE = 0


class Unavailable(RuntimeError):
    """What a benchmark needs is not on this machine; the message says what is missing and what to do. The
    command line prints it without a traceback."""


def set_nice(value: int) -> None:
    global NICE
    NICE = value


def _die_with_parent() -> None:
    if NICE:
        with contextlib.suppress(OSError):
            os.nice(NICE)
    die_with_parent(signal.SIGKILL)


def run_cleanups() -> None:
    """Run every registered clean-up once, newest first (processes before the namespaces they live in)."""
    with _cleanup_lock:
        items = list(reversed(_cleanups))
        _cleanups.clear()
    for fn in items:
        try:
            fn()
        except Exception as exc:  # a clean-up failure must not stop the others
            log.warning("clean-up %s failed: %s", getattr(fn, "__name__", fn), exc)


def on_cleanup(fn: Callable[[], None]) -> Callable[[], None]:
    """Register ``fn`` to run at exit or on SIGTERM/SIGINT; returns a function that unregisters it."""
    global _handlers_installed
    with _cleanup_lock:
        _cleanups.append(fn)
        if not _handlers_installed and threading.current_thread() is threading.main_thread():
            atexit.register(run_cleanups)
            for sig in (signal.SIGTERM, signal.SIGHUP):
                signal.signal(sig, _on_signal)
            _handlers_installed = True

    def remove() -> None:
        with _cleanup_lock:
            if fn in _cleanups:
                _cleanups.remove(fn)

    return remove


def _on_signal(signum: int, _frame: object) -> None:
    # Raise in the main thread: the callers' finally blocks stop what they started, atexit does the rest.
    raise SystemExit(128 + signum)


def python_argv(module: str, *args: str) -> list[str]:
    return [sys.executable, "-m", module, *args]


def iorthand_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "iorthand.cli", *args]


class Child:
    """One child process: its own session (so a stop reaches its children too), output to ``log_path``."""

    def __init__(self, name: str, argv: list[str], log_path: Path, netns: str | None = None) -> None:
        self.name = name
        self.argv = (["ip", "netns", "exec", netns, *argv]) if netns else argv
        self.log_path = log_path
        self.netns = netns
        self.proc: subprocess.Popen[bytes] | None = None
        self._unregister: Callable[[], None] | None = None

    def start(self) -> Child:
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with self.log_path.open("wb") as logf:
            env = dict(os.environ, PYTHONUNBUFFERED="1")
            self.proc = subprocess.Popen(
                self.argv, stdout=logf, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                preexec_fn=_die_with_parent, start_new_session=True,
            )
        self._unregister = on_cleanup(self.stop)
        return self

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def output(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def wait_for(self, text: str, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if text in self.output():
                return
            if self.proc is not None and self.proc.poll() is not None:
                raise RuntimeError(f"{self.name} exited with {self.proc.returncode}: {self.output()[-2000:]}")
            time.sleep(0.05)
        raise RuntimeError(f"{self.name} did not print {text!r} within {timeout:.0f} s; log {self.log_path}")

    def wait(self, timeout: float) -> int:
        assert self.proc is not None
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.stop()
            raise RuntimeError(f"{self.name} did not finish within {timeout:.0f} s; log {self.log_path}") from None

    def signal(self, sig: int) -> None:
        """Send ``sig`` to the process itself (under ``ip netns exec`` that is the exec'd program)."""
        if self.proc is not None and self.proc.poll() is None:
            os.kill(self.proc.pid, sig)

    def stop(self, timeout: float = 5.0) -> None:
        if self._unregister:
            self._unregister()
            self._unregister = None
        if self.proc is None or self.proc.poll() is not None:
            return
        try:
            os.killpg(self.proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            return
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(2.0)


class Group:
    """The children of one benchmark case; ``with Group(...) as g:`` stops them all on the way out."""

    def __init__(self, workdir: Path) -> None:
        self.workdir = workdir
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.children: list[Child] = []

    def start(self, name: str, argv: list[str], netns: str | None = None, ready: str | None = None,
              timeout: float = 30.0) -> Child:
        child = Child(name, argv, self.workdir / f"{name}.log", netns).start()
        self.children.append(child)
        if ready:
            child.wait_for(ready, timeout)
        return child

    def stop(self) -> None:
        for child in reversed(self.children):
            child.stop()
        self.children.clear()

    def __enter__(self) -> Group:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class CpuMeter:
    """CPU use of a process (and its children) over a window, in % of one core."""

    def __init__(self, pid: int) -> None:
        self._proc = psutil.Process(pid)
        self._t0 = time.monotonic()
        self._c0 = self._cpu()

    def _cpu(self) -> float:
        total = 0.0
        for p in [self._proc, *self._proc.children(recursive=True)]:
            try:
                t = p.cpu_times()
                total += t.user + t.system
            except psutil.Error:
                pass
        return total

    def reset(self) -> None:
        self._t0, self._c0 = time.monotonic(), self._cpu()

    def percent(self) -> float:
        dt = time.monotonic() - self._t0
        return 100.0 * (self._cpu() - self._c0) / dt if dt > 0 else float("nan")
