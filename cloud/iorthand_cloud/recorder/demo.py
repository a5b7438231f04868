"""Recording the ``iorthand demo``: a recorder process, a session started by query, the report at the end.

For ``iorthand/demo.py`` (the core must not import roles, so it imports this under ``try``)::

    rec = DemoRecorder(endpoint, workdir, robot=args.robot, operator="demo-operator")
    rec.start()                 # after the router is ready, before the edge and the operator
    ...                         # the scripted operator runs
    report = rec.finish()       # stop the recording, write the report; returns the report.md path
    rec.close()                 # in the demo's `finally`: stops the recorder process (idempotent)
"""

from __future__ import annotations

import contextlib
import ctypes
import signal
import subprocess
import sys
import time
from pathlib import Path

import yaml

from iorthand.transport import client_config, open_session
from iorthand_cloud.recorder import client


def _die_with_parent() -> None:
    with contextlib.suppress(OSError):  # not Linux: close() still stops the recorder
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class DemoRecorder:
    def __init__(self, endpoint: str, workdir: Path, robot: str = "demo", operator: str = "demo-operator") -> None:
        self.endpoint = endpoint
        self.workdir = Path(workdir)
        self.robot = robot
        self.operator = operator
        self.sessions = self.workdir / "recordings"
        self.session_id = f"demo-{time.strftime('%Y%m%d-%H%M%S')}"
        self.proc: subprocess.Popen[bytes] | None = None
        self._log = None
        self._zs = None

    @property
    def session_dir(self) -> Path:
        return self.sessions / self.session_id

    def start(self, timeout: float = 20.0) -> None:
        cfg = self.workdir / "recorder.yaml"
        cfg.write_text(yaml.safe_dump({"zenoh": {"mode": "client", "connect": [self.endpoint]},
                                       "output_dir": str(self.sessions)}))
        self._log = (self.workdir / "recorder.log").open("wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "iorthand.cli", "recorder", "--config", str(cfg)],
            stdout=subprocess.PIPE, stderr=self._log, preexec_fn=_die_with_parent, start_new_session=True,
        )
        assert self.proc.stdout is not None
        deadline = time.monotonic() + timeout
        for line in self.proc.stdout:
            if b"recorder ready" in line:
                break
            if time.monotonic() > deadline:
                raise RuntimeError(f"the recorder did not start; see {self.workdir / 'recorder.log'}")
        else:
            raise RuntimeError(f"the recorder exited ({self.proc.poll()}); see {self.workdir / 'recorder.log'}")
        self._zs = open_session(client_config(self.endpoint))
        st = client.start(self._zs, session_id=self.session_id, operator=self.operator, robots=[self.robot],
                          note="iorthand demo")
        if not st.ok:
            raise RuntimeError(f"the recorder refused to start: {st.reason}")

    def finish(self) -> Path:
        """Stop the recording and write its report; returns the path of report.md."""
        from iorthand_cloud.recorder.report import build_report

        assert self._zs is not None, "start() first"
        st = client.stop(self._zs)
        if not st.ok:
            raise RuntimeError(f"the recorder could not stop cleanly: {st.reason}")
        return Path(build_report(self.session_dir)["path"])

    def close(self) -> None:
        if self._zs is not None:
            self._zs.close()
            self._zs = None
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(2)
        if self._log is not None:
            self._log.close()
            self._log = None
