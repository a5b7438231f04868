"""``iorthand demo`` as a new user meets it: a summary whose every line is true (a part that did not run says so
and the demo exits non-zero), the log-ins ``--view`` prints, Ctrl-C, a full disk, mistakes on its command line, an
install that lacks a role. The end-to-end tests run the real demo (router, recorder, twin, simulated edge, scripted
operator: about 30 s each); the summary's decisions are also checked on their own, with the script's result and the
report as the demo's run writes them."""

from __future__ import annotations

import contextlib
import copy
import fcntl
import json
import os
import signal
import subprocess
import time
import urllib.request
from pathlib import Path
from typing import Any

import psutil
import pytest

from iorthand import demo
from tests.conftest import ROOT, iorthand_cmd, small_disk, wait_until

# A demo's run, as it writes them (summary.json: the scripted operator's result; report.json: the session report),
# cut to what the summary reads.
RESULT: dict[str, Any] = {
    "script": "demo", "ended_by_stop": "", "robot": "sim1", "operator": "demo-operator", "profile": "local",
    "commands_sent": 911, "commands_echoed": 911, "commands_accepted": 911, "commands_refused": 0, "refusals": [],
    "command_to_echo_ms": {"count": 911, "mean": 2.5, "p50": 1.704, "p90": 4.6, "p99": 12.784, "max": 23.2},
    "peak_force_level": 2, "deadman_stops_ms": [150.7], "deadman_stops_after_receipt_ms": [150.2],
}
REPORT: dict[str, Any] = {
    "session": "demo-20261129-112021", "status": "complete",
    "recording": {"messages": 8251, "malformed": 0, "gaps": 0, "missing": 0, "dropped": 0, "repaired": False,
                  "error": "", "missing_where": ""},
    "robots": {"sim1": {"index": {"t_t": 15.07, "tau": 5.24, "omega_R": 3, "omega_Y": 3, "phi": 74.24},
                        "commands": 911, "applied": 911}},
}


def _facts(tmp_path: Path, **kw: Any) -> demo.RunFacts:
    return demo.RunFacts(tmp_path, tmp_path / "report.md", **{"twin_rrd_bytes": 11_000_000, **kw})


def test_a_whole_run_is_summarised_with_its_figures(tmp_path: Path) -> None:
    lines, failures = demo.summary_lines(RESULT, REPORT, _facts(tmp_path))
    text = "\n".join(lines)
    assert failures == []
    assert "commands sent/accepted/refused  911 / 911 / 0" in text
    assert "p50 1.70 ms, p99 12.78 ms" in text
    assert "151 ms after the last command was sent, 150 ms after the edge received it" in text
    assert "74.2 % (contact 5.2 s of 15.1 s, warnings red 3, yellow 3)" in text
    assert "8251 messages, 0 missing by sequence, 0 malformed" in text
    assert f"twin (rerun)              {tmp_path / 'twin.rrd'}" in text
    assert "NOT" not in text


@pytest.mark.parametrize(("change", "line", "failure"), [
    # The edge did not stop the arm within the dead link: the script measured nothing (the old summary: "nan ms").
    (lambda r, p, f: (r.update(deadman_stops_ms=[], deadman_stops_after_receipt_ms=[])),
     "deadman stop (dead link)  NOT SEEN", "the deadman stop on the dead link was not seen"),
    (lambda r, p, f: p["robots"].clear(), "session index φ           NOT COMPUTED", "no session index for sim1"),
    (lambda r, p, f: p.pop("recording"), "recording                 NOT IN THE REPORT",
     "says nothing of the recording"),
    (lambda r, p, f: (p.update(status="failed"), p["recording"].update(error="No space left on device")),
     "status failed: No space left on device", "the recording is failed, not complete"),
    (lambda r, p, f: p["robots"]["sim1"].update(commands=700), "it holds 700 of the 911 commands sent",
     "the recording holds 700 of the 911 commands sent"),
    (lambda r, p, f: p["recording"].update(dropped=12), "12 dropped by the recorder", None),
    (lambda r, p, f: r.update(command_to_echo_ms={"count": 0}), "NOT MEASURED: the edge echoed no command",
     "echoed none of the commands"),
    (lambda r, p, f: r.update(ended_by_stop="stop by ops: e-stop"), "", "the script ended early: stop by ops"),
    (lambda r, p, f: f.process_problems.update(twin="twin stopped during the run (exit -9); see twin.log"),
     "twin (rerun)              FAILED: twin stopped during the run (exit -9)", "twin stopped during the run"),
    (lambda r, p, f: setattr(f, "twin_rrd_bytes", 0), "twin (rerun)              FAILED: it saved nothing",
     "the twin saved nothing"),
], ids=["no deadman stop", "no index", "no recording", "recording failed", "commands not recorded",
        "dropped", "no echo", "ended by a stop", "twin died", "no twin file"])
def test_a_part_that_did_not_work_is_said_and_fails_the_demo(tmp_path: Path, change, line: str,
                                                             failure: str | None) -> None:
    result, report, facts = copy.deepcopy(RESULT), copy.deepcopy(REPORT), _facts(tmp_path)
    change(result, report, facts)
    lines, failures = demo.summary_lines(result, report, facts)
    text = "\n".join(lines)
    assert line in text
    assert "nan" not in text
    if failure is None:
        assert failures == []
    else:
        assert any(failure in f for f in failures), failures
        assert "NOT everything worked" in text and failure in text


def test_a_refused_step_says_its_reason() -> None:
    answer = json.dumps({"ok": False, "reason": "cannot record into /x/rec: Not a directory", "messages": 0})
    assert demo.step_failure("starting the recording", 1, answer, "") == \
        "starting the recording failed (exit 1): cannot record into /x/rec: Not a directory"
    assert demo.step_failure("the report", 2, "", "Traceback...\nValueError: bad").endswith("ValueError: bad")


def test_an_install_without_a_role_is_named() -> None:
    everything = {"edge", "recorder", "twin", "operator", "web", "bench", "calibrate"}
    assert demo.missing_commands(everything, view=True) == []
    assert demo.missing_commands({"recorder", "twin", "bridge"}, view=False) == [
        "the 'edge' command (the edge package)", "the 'operator' command (the operator package)"]
    assert demo.missing_commands(everything - {"web"}, view=True) == ["the 'web' command (the operator package)"]


# A cloud VM's install: the cloud package and the core, no edge nor operator package. Simulated by hiding the edge's
# and the operator's entry points from importlib.metadata in the demo's process (installing a second venv takes
# minutes).
CLOUD_ONLY = """
import importlib.metadata as md
_eps = md.entry_points
md.entry_points = lambda **kw: md.EntryPoints(
    e for e in _eps(**kw) if not e.value.startswith(("iorthand_edge", "iorthand_operator")))
"""


def _run(args: list[str], cwd: Path, timeout: float = 60, **kw: Any) -> subprocess.CompletedProcess[str]:
    return subprocess.run(iorthand_cmd(*args), capture_output=True, text=True, timeout=timeout, cwd=cwd,
                          stdin=subprocess.DEVNULL, **kw)


def test_a_cloud_only_install_is_told_what_the_demo_needs(tmp_path: Path) -> None:
    (tmp_path / "sitecustomize.py").write_text(CLOUD_ONLY)
    r = _run(["demo", "--workdir", str(tmp_path / "w")], tmp_path, env={**os.environ, "PYTHONPATH": str(tmp_path)})
    assert r.returncode == 2, r.stdout + r.stderr
    assert "lacks the 'edge' command (the edge package), the 'operator' command (the operator package)" in r.stderr
    assert not (tmp_path / "w").exists()  # nothing started, nothing written


@pytest.mark.parametrize(("args", "said"), [
    (["--timeout", "-5"], "--timeout: '-5' is not within 10..3600"),
    (["--robot", "a/b"], "robot id 'a/b' is invalid"),
    (["--robot", "sim1-replay"], "reserved for replayed recordings"),
    (["--veiw"], "iorthand demo: unrecognized option --veiw (did you mean --view?)"),
])
def test_mistakes_on_the_demo_command_line_start_nothing(tmp_path: Path, args: list[str], said: str) -> None:
    r = _run(["demo", "--workdir", str(tmp_path / "w"), *args], tmp_path, timeout=30)
    assert r.returncode == 2, r.stdout + r.stderr
    assert said in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "w").exists()


def test_a_full_disk_is_one_line_that_names_the_folder(tmp_path: Path) -> None:
    with small_disk(tmp_path, "64k") as mnt:
        with contextlib.suppress(OSError):
            (mnt / "fill").write_bytes(b"\0" * 100_000)  # fills it, then ENOSPC
        r = _run(["demo", "--workdir", str(mnt / "w")], tmp_path)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    assert "No space left on device" in r.stderr and f"{mnt / 'w'}" in r.stderr and "--workdir" in r.stderr


def test_a_second_demo_in_the_same_folder_is_refused(tmp_path: Path) -> None:
    """The folder's lock held as a running demo holds it: the old demo started a second stack that wrote over the
    first one's configs and logs."""
    workdir = tmp_path / "w"
    workdir.mkdir()
    with (workdir / ".demo.lock").open("a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        r = _run(["demo", "--workdir", str(workdir)], tmp_path, timeout=30)
    assert r.returncode == 1, r.stdout + r.stderr
    assert f"another demo is running in {workdir}" in r.stderr
    assert sorted(p.name for p in workdir.iterdir()) == [".demo.lock"]  # nothing written, nothing started


# --- the real demo, end to end (about 30 s each) -----------------------------------------------------------------

def _start(tmp_path: Path, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(iorthand_cmd("demo", "--workdir", str(tmp_path / "w"), *args), cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def _descendants(pid: int) -> set[psutil.Process]:
    try:
        return set(psutil.Process(pid).children(recursive=True))
    except psutil.NoSuchProcess:
        return set()


def _none_left(procs: set[psutil.Process]) -> list[str]:
    left = []
    for p in procs:
        try:
            if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                left.append(" ".join(p.cmdline()[:5]))
                p.kill()
        except psutil.NoSuchProcess:
            pass
    return left


@pytest.mark.slow
def test_a_twin_that_dies_during_the_run_fails_the_demo(tmp_path: Path) -> None:
    """The twin killed while the operator drives: the old summary printed its .rrd as if whole, and exited 0."""
    proc = _start(tmp_path)
    seen: set[psutil.Process] = set()
    try:
        edge_log = tmp_path / "w" / "edge.log"
        wait_until(lambda: edge_log.exists() and "edge agent" in edge_log.read_text(errors="replace"), timeout=90,
                   message="the demo's edge")
        seen = _descendants(proc.pid)
        twin = next(p for p in seen if "twin" in p.cmdline())
        twin.kill()
        out, _ = proc.communicate(timeout=180)
    finally:
        proc.kill()
    assert proc.returncode == 1, out
    assert "twin (rerun)              FAILED: twin stopped during the run (exit -9)" in out
    assert "NOT everything worked" in out
    assert "commands sent/accepted/refused" in out  # the rest of the summary is still there
    assert _none_left(seen) == []


def _log_in(url: str, user: str, password: str) -> int:
    req = urllib.request.Request(f"{url.rstrip('/')}/api/login", method="POST",
                                 data=json.dumps({"user": user, "password": password}).encode(),
                                 headers={"Content-Type": "application/json", "Origin": url.rstrip("/")})
    try:
        with urllib.request.urlopen(req, timeout=10) as answer:
            return answer.status
    except urllib.error.HTTPError as exc:
        return exc.code


@pytest.mark.slow
def test_view_prints_log_ins_that_work_and_ctrl_c_stops_everything(tmp_path: Path) -> None:
    """The printed log-ins open the printed console (the old demo printed the users file's chgrp step as the
    operator's password), and two quick Ctrl-Cs still end in the message that says where the logs are, with every
    process the demo started gone."""
    proc = _start(tmp_path, "--view")
    lines: list[str] = []
    seen: set[psutil.Process] = set()
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + 150
        while time.monotonic() < deadline and not any("Ctrl-C stops everything" in line for line in lines):
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
        out = "".join(lines)
        assert "Ctrl-C stops everything" in out, out
        seen = _descendants(proc.pid)
        url = next(line.split(" is at ", 1)[1].strip() for line in lines if "operator console" in line)
        logins = [(line.split()[3], line.split(" password ", 1)[1].strip()) for line in lines
                  if line.strip().startswith("log in as")]
        assert [user for user, _ in logins] == ["physician", "student"]
        for user, password in logins:
            assert _log_in(url, user, password) == 200, (user, password)
        assert _log_in(url, "physician", "not-the-password") == 401
        proc.send_signal(signal.SIGINT)
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0, rest
    assert f"iorthand demo: interrupted, stopping every process; logs in {tmp_path / 'w'}" in rest
    assert _none_left(seen) == []
