"""``iorthand demo``: the whole system on this machine, from one command.

Starts, as separate processes on 127.0.0.1 with free ports: a Zenoh router, the recorder, the digital twin, a
simulated edge agent (configs/edge-sim.yaml: robot, force sensor on a phantom, servos, torch, camera with ArUco
markers, video) and a scripted operator (configs/demo-script.yaml). It records the session, writes its report,
prints a summary and exits 0; a part that did not work (a service that died, no deadman stop seen, a recording
that is not complete, ...) is said in the summary, in place of its figure, and the demo exits 1. ``--view``
also starts the browser console (``iorthand web``, with generated log-ins), keeps everything running and prints
the twin's and the console's addresses.

Ctrl-C (or SIGTERM) stops everything; each child also dies with the demo (PR_SET_PDEATHSIG), so no process is
left behind even if the demo is killed. The core imports no role: the demo drives them by their commands.
"""

from __future__ import annotations

import argparse
import errno
import fcntl
import json
import math
import secrets
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Collection
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import IO, Any

import yaml

from iorthand.config import cli_number
from iorthand.keys import KeyExprError, check_edge_robot_id
from iorthand.process import die_with_parent
from iorthand.transport import free_port

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


@dataclass
class Child:
    name: str
    argv: list[str]
    log_path: Path
    proc: subprocess.Popen[bytes] | None = None
    log: IO[bytes] | None = field(default=None, repr=False)

    def start(self) -> None:
        self.log = self.log_path.open("wb")
        self.proc = subprocess.Popen(
            self.argv, stdout=self.log, stderr=subprocess.STDOUT, preexec_fn=die_with_parent, start_new_session=True,
        )

    def stop(self, timeout: float = 5.0) -> int | None:
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(2.0)
        if self.log:
            self.log.close()
        return self.proc.returncode


def iorthand_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "iorthand.cli", *args]


# The commands the demo runs, by the role package that adds each (its entry point in iorthand.commands).
NEEDED_COMMANDS = {"edge": "edge", "recorder": "cloud", "twin": "cloud", "operator": "operator"}


def missing_commands(available: Collection[str], view: bool) -> list[str]:
    """What the demo needs of ``available`` (the iorthand.commands entry points installed) and lacks: each as
    "the 'X' command (the Y package)". A role installed alone (a cloud VM's, an edge computer's) has only its own."""
    needed = {**NEEDED_COMMANDS, **({"web": "operator"} if view else {})}
    return [f"the {name!r} command (the {package} package)" for name, package in needed.items()
            if name not in available]


def robot_id_arg(text: str) -> str:
    """An argparse ``type`` for --robot: an id an edge may take, checked before anything starts."""
    try:
        return check_edge_robot_id(text)
    except KeyExprError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def demo_edge_config(robot: str, endpoint: str) -> dict:
    """configs/edge-sim.yaml with the demo's robot id and router."""
    config = yaml.safe_load((CONFIGS / "edge-sim.yaml").read_text())
    config["robot_id"] = robot
    config["zenoh"]["connect"] = [endpoint]
    return config


def step_failure(what: str, code: int, stdout: str, stderr: str) -> str:
    """Why a step failed, in one line: the reason a JSON answer gives (``recorder start`` answers with the
    recorder's status), else the end of what the command said."""
    try:
        answer = json.loads(stdout)
    except ValueError:
        answer = None
    reason = answer.get("reason") or answer.get("error") if isinstance(answer, dict) else ""
    return f"{what} failed (exit {code}): {reason or (stderr or stdout).strip()[-500:]}"


def run_step(argv: list[str], what: str, timeout: float = 60.0, stdin: str | None = None) -> str:
    """Run one command to completion; its output, or RuntimeError with what it said."""
    try:
        done = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, preexec_fn=die_with_parent,
                              input=stdin, stdin=None if stdin is not None else subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        raise RuntimeError(f"{what} did not finish within {timeout:g} s") from None
    if done.returncode != 0:
        raise RuntimeError(step_failure(what, done.returncode, done.stdout, done.stderr))
    return done.stdout


def wait_for_line(child: Child, text: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if child.proc is not None and child.proc.poll() is not None:
            raise RuntimeError(f"{child.name} exited with {child.proc.returncode}; see {child.log_path}")
        if text in child.log_path.read_text(errors="replace"):
            return
        time.sleep(0.05)
    raise RuntimeError(f"{child.name} did not report {text!r} within {timeout} s; see {child.log_path}")


def web_console(workdir: Path, robot: str, endpoint: str) -> tuple[Child, list[tuple[str, str]]]:
    """The browser console for ``--view``: a deployment with one operator and one viewer of the demo's robot,
    on loopback. Their passwords are made here and given to ``iorthand web password`` on its stdin: what it
    prints besides (a new users file's chgrp/chmod step) is no password."""
    (workdir / "deployment.yaml").write_text(yaml.safe_dump(
        {"robots": [robot], "operators": {"physician": [robot]}, "viewers": ["student"]}))
    logins = []
    for user in ("physician", "student"):
        password = secrets.token_urlsafe(12)  # (as `web password --generate`)
        run_step(iorthand_argv("web", "password", user, "--users-file", str(workdir / "web-users.txt")),
                 f"the web password of {user}", stdin=password + "\n")
        logins.append((user, password))
    (workdir / "web.yaml").write_text(yaml.safe_dump({
        "deployment": "deployment.yaml", "users_file": "web-users.txt", "listen": f"127.0.0.1:{free_port()}",
        "zenoh": {"mode": "client", "connect": [endpoint]}}))
    return Child("web", iorthand_argv("web", "--config", str(workdir / "web.yaml")), workdir / "web.log"), logins


@dataclass
class RunFacts:
    """What the demo saw of its own run, beside the script's result and the report."""

    workdir: Path
    report_path: Path
    twin_url: str = ""
    twin_rrd_bytes: int = 0  # the twin's saved recording (0: none)
    # By service: one that died during the run, or did not stop cleanly.
    process_problems: dict[str, str] = field(default_factory=dict)


def _ms(values: list[float] | None) -> float | None:
    return values[0] if values else None


def summary_lines(result: dict[str, Any], report: dict[str, Any], facts: RunFacts) -> tuple[list[str], list[str]]:
    """The summary, and what did not work (empty: everything did). Each line is a figure from the script's
    result or the report, or says that the part behind it did not run: never a figure for something missing."""
    failures = list(facts.process_problems.values())
    robot = result["robot"]
    rtt = result.get("command_to_echo_ms") or {}
    levels = {0: "green", 1: "yellow", 2: "red"}
    if result.get("ended_by_stop"):
        failures.append(f"the script ended early: {result['ended_by_stop']}")
    if not result.get("commands_sent"):
        failures.append("the scripted operator sent no command")

    if rtt.get("count"):
        latency = f"p50 {rtt['p50']:.2f} ms, p99 {rtt['p99']:.2f} ms (through the router, echo)"
    else:
        latency = "NOT MEASURED: the edge echoed no command"
        failures.append("the edge echoed none of the commands")

    stop_sent, stop_received = _ms(result.get("deadman_stops_ms")), _ms(result.get("deadman_stops_after_receipt_ms"))
    if stop_sent is None or stop_received is None:
        deadman = "NOT SEEN: the edge did not stop the arm within the dead link"
        failures.append("the deadman stop on the dead link was not seen")
    else:
        deadman = (f"{stop_sent:.0f} ms after the last command was sent, {stop_received:.0f} ms after the edge "
                   "received it")

    figures = report.get("robots", {}).get(robot)
    index = (figures or {}).get("index")
    if not index or not isinstance(index.get("phi"), (int, float)) or math.isnan(index["phi"]):
        phi = f"NOT COMPUTED: the report has no index for {robot}"
        failures.append(f"the report has no session index for {robot}")
    else:
        phi = (f"{index['phi']:.1f} % (contact {index['tau']:.1f} s of {index['t_t']:.1f} s, "
               f"warnings red {index['omega_R']}, yellow {index['omega_Y']})")

    rec = report.get("recording")
    status = report.get("status", "")
    if not rec:
        recording = "NOT IN THE REPORT"
        failures.append("the report says nothing of the recording")
    else:
        # Which streams lost messages (the report says): a video frame dropped by its latest-frame QoS is not a
        # lost command.
        lost_on = rec.get("missing_where", "")
        lost = f" ({lost_on})" if lost_on else ""
        recording = (f"{rec['messages']} messages, {rec['missing']} missing by sequence{lost}, "
                     f"{rec['malformed']} malformed")
        if rec.get("dropped"):
            recording += f", {rec['dropped']} dropped by the recorder"
        if status != "complete":
            error = f": {rec['error']}" if rec.get("error") else ""
            recording += f"; status {status or 'unknown'}{error}"
            failures.append(f"the recording is {status or 'of unknown status'}, not complete")
        recorded = (figures or {}).get("commands", 0)
        if recorded < result.get("commands_sent", 0):
            recording += f"; it holds {recorded} of the {result['commands_sent']} commands sent"
            failures.append(f"the recording holds {recorded} of the {result['commands_sent']} commands sent")
        if not rec.get("messages"):
            failures.append("nothing was recorded")

    rrd = facts.workdir / "twin.rrd"
    if "twin" in facts.process_problems:
        twin = f"FAILED: {facts.process_problems['twin']}"
    elif not facts.twin_rrd_bytes:
        twin = f"FAILED: it saved nothing; see {facts.workdir / 'twin.log'}"
        failures.append(f"the twin saved nothing to {rrd}")
    else:
        viewer = Path(sys.executable).parent / "rerun"  # (the venv's, wherever the demo is run from)
        twin = f"{rrd}  (view it: {viewer} {rrd})" + (f"; live: {facts.twin_url}" if facts.twin_url else "")

    lines = [
        "",
        "iorthand demo — summary",
        f"  robot {robot} (simulated), operator {result['operator']}, profile {result['profile']}",
        f"  commands sent/accepted/refused  {result['commands_sent']} / {result['commands_accepted']} / "
        f"{result['commands_refused']}",
        f"  command→applied latency   {latency}",
        f"  deadman stop (dead link)  {deadman}",
        f"  force                     peak level {result['peak_force_level']} "
        f"({levels.get(result['peak_force_level'], '?')})",
        f"  session index φ           {phi}",
        f"  recording                 {recording}",
        f"  refusals                  {'; '.join(r[:70] for r in result['refusals'][:3]) or 'none'}",
        f"  report                    {facts.report_path}",
        f"  twin (rerun)              {twin}",
        f"  logs, configs, recording  {facts.workdir}",
    ]
    if failures:
        lines += ["", "iorthand demo: NOT everything worked:", *(f"  - {f}" for f in failures)]
    return lines, failures


def process_problems(children: Collection[Child], codes: dict[str, int | None] | None = None) -> dict[str, str]:
    """The demo's services that died during the run (each should run until the demo stops it) or, given the
    ``codes`` they ended with when stopped, did not stop cleanly (a kill after the grace time is one)."""
    problems = {}
    for child in children:
        if child.proc is None:
            continue
        if codes is None:
            if child.proc.poll() is not None:
                problems[child.name] = (f"{child.name} stopped during the run (exit {child.proc.returncode}); "
                                        f"see {child.log_path}")
        elif codes.get(child.name) not in (0, None):
            problems[child.name] = (f"{child.name} ended with exit {codes[child.name]} when stopped; "
                                    f"see {child.log_path}")
    return problems


def os_error_reason(exc: OSError, workdir: Path | str) -> str:
    """An OSError in the demo's words: a full or read-only disk is the folder's, and --workdir is the way out."""
    where = f" ({exc.filename})" if exc.filename else ""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES):
        return f"{exc.strerror}{where}: cannot write the demo's folder {workdir} (--workdir DIR puts it elsewhere)"
    return str(exc)


def ignore_signals() -> None:
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)


def run_demo(args: argparse.Namespace) -> int:
    missing = missing_commands({ep.name for ep in entry_points(group="iorthand.commands")}, args.view)
    if missing:
        print(f"iorthand demo: this install lacks {', '.join(missing)}: the demo runs every role on this machine "
              "(make install, or pip install -e . -e 'edge[ur]' -e cloud -e operator)", file=sys.stderr)
        return 2
    try:
        workdir = Path(args.workdir or tempfile.mkdtemp(prefix="iorthand-demo-"))
        workdir.mkdir(parents=True, exist_ok=True)
        lock = (workdir / ".demo.lock").open("a")
    except OSError as exc:
        where = args.workdir or "in TMPDIR or /tmp"
        print(f"iorthand demo failed: {os_error_reason(exc, where)}", file=sys.stderr)
        return 1
    with lock:
        try:
            # Two demos in one folder would write over each other's configs, logs and recordings. Released as the
            # demo ends, however it ends (the kernel drops the lock of a killed process).
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            print(f"iorthand demo failed: another demo is running in {workdir}; wait for it, or give another "
                  "--workdir", file=sys.stderr)
            return 1
        return _run_demo(args, workdir)


def _run_demo(args: argparse.Namespace, workdir: Path) -> int:
    children: dict[str, Child] = {}

    def on_signal(signum: int, _frame: object) -> None:
        # One is enough: a second Ctrl-C (or the SIGINT that `timeout` forwards) must not cut short the message or
        # the clean-up; each child dies with the demo anyway.
        ignore_signals()
        raise KeyboardInterrupt

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    code = 1
    try:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        edge_cfg = workdir / "edge.yaml"
        edge_cfg.write_text(yaml.safe_dump(demo_edge_config(args.robot, endpoint), sort_keys=False))
        rec_cfg = workdir / "recorder.yaml"
        recordings = workdir / "recordings"
        rec_cfg.write_text(yaml.safe_dump({"zenoh": {"mode": "client", "connect": [endpoint]},
                                           "output_dir": str(recordings)}))
        session = f"demo-{time.strftime('%Y%m%d-%H%M%S')}"
        twin_cfg = CONFIGS / "twin.yaml"
        if args.view:  # the Foxglove app can connect live too
            twin = yaml.safe_load(twin_cfg.read_text())
            twin["foxglove"] = {**twin.get("foxglove", {}), "enabled": True, "port": free_port()}
            twin_cfg = workdir / "twin.yaml"
            twin_cfg.write_text(yaml.safe_dump(twin, sort_keys=False))
        twin_argv = ["twin", "--config", str(twin_cfg), "--connect", endpoint, "--save", str(workdir / "twin.rrd"),
                     "--log-dir", str(workdir)]
        twin_argv += ["--web-port", str(free_port()), "--grpc-port", str(free_port())] if args.view else ["--no-serve"]
        children.update({
            "router": Child("router", iorthand_argv("router", "--listen", endpoint), workdir / "router.log"),
            "recorder": Child("recorder", iorthand_argv("recorder", "--config", str(rec_cfg)),
                              workdir / "recorder.log"),
            "twin": Child("twin", iorthand_argv(*twin_argv), workdir / "twin.log"),
            "edge": Child("edge", iorthand_argv("edge", "--config", str(edge_cfg)), workdir / "edge.log"),
        })
        ready = {"router": "router ready", "recorder": "recorder ready", "twin": "twin ready", "edge": "edge agent",
                 "web": "web console ready"}
        logins: list[tuple[str, str]] = []
        if args.view:
            children["web"], logins = web_console(workdir, args.robot, endpoint)
        print(f"iorthand demo: router on {endpoint}; logs in {workdir}", flush=True)
        for name, child in children.items():
            child.start()
            wait_for_line(child, ready[name], 30.0)
        twin_url = next((line.split(": ", 1)[1] for line in (workdir / "twin.log").read_text().splitlines()
                         if line.startswith("twin viewer: ")), "")
        run_step(iorthand_argv("recorder", "start", "--connect", endpoint, "--session", session, "--robot", args.robot,
                               "--operator", "demo-operator", "--note", "iorthand demo"), "starting the recording")
        out = run_step(iorthand_argv("operator", "script", str(CONFIGS / "demo-script.yaml"), "--robot", args.robot,
                                     "--operator-id", "demo-operator", "--connect", endpoint),
                       "the scripted operator", timeout=args.timeout)
        (workdir / "summary.json").write_text(out)
        run_step(iorthand_argv("recorder", "stop", "--connect", endpoint), "stopping the recording")
        run_step(iorthand_argv("report", str(recordings / session)), "the session report", timeout=120.0)
        report_dir = recordings / session / "report"
        problems = process_problems(children.values())
        if not args.view:
            # Stopped before the summary: the twin writes the end of its .rrd as it stops, and each service's exit
            # says whether it ended well.
            codes = {name: child.stop() for name, child in reversed(children.items()) if child.proc is not None
                     and child.proc.poll() is None}
            problems.update(process_problems(children.values(), codes))
        rrd = workdir / "twin.rrd"
        facts = RunFacts(workdir, report_dir / "report.md", twin_url, rrd.stat().st_size if rrd.exists() else 0,
                         problems)
        lines, failures = summary_lines(json.loads(out), json.loads((report_dir / "report.json").read_text()), facts)
        print("\n".join(lines), flush=True)
        code = 1 if failures else 0
        if args.view and not failures:
            web_url = next((line.split("web console ready: ", 1)[1] for line in
                            (workdir / "web.log").read_text().splitlines() if "web console ready: " in line), "")
            foxglove = next((line.split("twin foxglove: ", 1)[1] for line in
                             (workdir / "twin.log").read_text().splitlines() if "twin foxglove: " in line), "")
            print(f"\nthe twin is live at {twin_url}", flush=True)
            if foxglove:
                print(f"the Foxglove app connects live at {foxglove} (Open connection → Foxglove WebSocket)",
                      flush=True)
            print(f"the operator console (phone or desktop browser) is at {web_url}", flush=True)
            for user, password in logins:
                print(f"  log in as {user:<10} password {password}", flush=True)
            print("Ctrl-C stops everything", flush=True)
            while all(c.proc is not None and c.proc.poll() is None for c in children.values()):
                time.sleep(0.5)
            print("iorthand demo: " + "; ".join(process_problems(children.values()).values()), file=sys.stderr)
            code = 1
    except KeyboardInterrupt:
        print(f"\niorthand demo: interrupted, stopping every process; logs in {workdir}", flush=True)
        code = 130 if code else 0
    except (RuntimeError, OSError, ValueError) as exc:
        why = os_error_reason(exc, workdir) if isinstance(exc, OSError) else exc
        print(f"iorthand demo failed: {why}; logs in {workdir}", file=sys.stderr)
    finally:
        ignore_signals()  # (as after a Ctrl-C)
        for child in reversed(children.values()):
            child.stop()
    return code


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="the whole system on this machine: router, recorder, twin, simulated edge, "
                                    "scripted operator; prints a summary and the session report")
    p.add_argument("--robot", default="sim1", type=robot_id_arg, help="the simulated robot's id")
    p.add_argument("--workdir", help="where logs, configs and the recording go (default: a new temporary folder)")
    p.add_argument("--timeout", type=cli_number(float, lo=10.0, hi=3600.0), default=120.0,
                   help="s the scripted operator may take")
    p.add_argument("--view", action="store_true", help="serve the twin and the operator console in a browser and keep "
                                                          "running until Ctrl-C")
    p.set_defaults(func=run_demo)
