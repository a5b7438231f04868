"""iorthand.logs: a process's log lines never block it, and none is lost without a word.

Each case runs a small Python process whose stderr is a pipe this test fills first and reads later, as a terminal
paused with Ctrl-S or a stalled log collector would leave it."""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import select
import subprocess
import sys
import time

from iorthand import logs

CHILD = """
import logging, sys
from iorthand import logs
logs.setup("info")
log = logging.getLogger("child")
for i in range({count}):
    log.info("line %d", i)
print("logged", flush=True)  # stdout: the test reads it while stderr is still full
sys.stdin.readline()  # the test reads stderr again meanwhile
log.info("the end")
sys.stdin.readline()
"""


def full_pipe() -> tuple[int, int]:
    read_end, write_end = os.pipe()
    fcntl.fcntl(write_end, fcntl.F_SETPIPE_SZ, 4096)
    os.set_blocking(write_end, False)
    with contextlib.suppress(BlockingIOError):
        while True:
            os.write(write_end, b"x" * 64 + b"\n")
    os.set_blocking(write_end, True)
    return read_end, write_end


def test_lines_logged_while_stderr_is_full_do_not_block_and_what_did_not_fit_is_counted() -> None:
    count = logs.MAX_PENDING * 2
    read_end, write_end = full_pipe()
    child = subprocess.Popen([sys.executable, "-c", CHILD.format(count=count)], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, stderr=write_end)
    os.close(write_end)
    try:
        assert child.stdout is not None and child.stdin is not None
        # Before: the child blocked in its first log call and never got here.
        assert select.select([child.stdout], [], [], 30.0)[0], "the child blocked while logging"
        assert child.stdout.readline() == b"logged\n"
        said = b""
        os.set_blocking(read_end, False)

        def read_until(text: bytes) -> None:
            nonlocal said
            deadline = time.monotonic() + 30.0
            while text not in said:
                assert time.monotonic() < deadline, said[-500:]
                try:
                    said += os.read(read_end, 1 << 16)
                except BlockingIOError:
                    time.sleep(0.02)

        read_until(b"log line(s) lost")  # the writer is draining: the queue has room again
        child.stdin.write(b"go\n")
        child.stdin.flush()
        read_until(b"INFO child: the end\n")
        text = said.decode()
        written = len(re.findall(r"INFO child: line \d+", text))
        lost = int(re.search(r"WARNING iorthand.logs: (\d+) log line\(s\) lost", text).group(1))  # type: ignore[union-attr]
        assert written >= logs.MAX_PENDING
        assert written + lost == count
    finally:
        with contextlib.suppress(OSError):
            child.kill()
        child.wait(10.0)
        os.close(read_end)


def test_lines_logged_just_before_a_process_ends_are_written() -> None:
    done = subprocess.run([sys.executable, "-c", "import logging; from iorthand import logs; logs.setup('info');"
                           "logging.getLogger('child').warning('the last word')"],
                          capture_output=True, timeout=30.0, check=True)
    assert b"WARNING child: the last word" in done.stderr


def test_a_process_whose_stderr_is_full_still_ends_with_its_exit_code() -> None:
    """``systemctl stop`` of an edge whose log pipe is full: before, the process hung in its next log line; the
    writer thread alone, blocked in ``write`` while it held the handler's lock, also hung logging's own shutdown."""
    read_end, write_end = full_pipe()
    try:
        child = subprocess.Popen([sys.executable, "-c", "import logging, sys; from iorthand import logs;"
                                  "logs.setup('info'); logging.getLogger('child').info('last words'); sys.exit(3)"],
                                 stderr=write_end)
        os.close(write_end)
        try:
            assert child.wait(30.0) == 3
        finally:
            with contextlib.suppress(OSError):
                child.kill()
            child.wait(10.0)
    finally:
        os.close(read_end)


def test_a_stderr_that_is_no_file_gets_the_lines_directly() -> None:
    """A harness that replaced sys.stderr by an object without a file descriptor (a capture) before the command ran
    in its process: the lines go to that object, as logging.basicConfig would send them (setup raised before)."""
    done = subprocess.run([sys.executable, "-c", "import io, logging, sys; from iorthand import logs;"
                           "capture = sys.stderr = io.StringIO(); logs.setup('info');"
                           "logging.getLogger('child').info('captured'); sys.stderr = sys.__stderr__;"
                           "print(capture.getvalue(), end='')"], capture_output=True, timeout=30.0, check=True)
    assert done.stdout.endswith(b"INFO child: captured\n")
