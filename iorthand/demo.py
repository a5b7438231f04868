"""``iorthand demo``: the whole system on this machine, from one command.

Starts, as separate processes on 127.0.0.1 with free ports: a Zenoh router, the recorder, the digital twin, a
simulated edge agent (configs/edge-sim.yaml: robot, force sensor on a phantom, servos, torch, camera with ArUco
markers, video) and a scripted operator (configs/demo-script.yaml). It records the session, writes its report,
prints a summary and exits 0. ``--view`` also starts the browser console (``iorthand web``, with generated
log-ins), keeps everything running and prints the twin's and the console's addresses.

Ctrl-C (or SIGTERM) stops everything; each child also dies with the demo (PR_SET_PDEATHSIG), so no process is
left behind even if the demo is killed. The core imports no role: the demo drives them by their commands.
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import yaml

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


def demo_edge_config(robot: str, endpoint: str) -> dict:
    """configs/edge-sim.yaml with the demo's robot id and router."""
    config = yaml.safe_load((CONFIGS / "edge-sim.yaml").read_text())
    config["robot_id"] = robot
    config["zenoh"]["connect"] = [endpoint]
    return config


def run_step(argv: list[str], what: str, timeout: float = 60.0) -> str:
    """Run one command to completion; its output, or RuntimeError with what it said."""
    done = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, preexec_fn=die_with_parent)
    if done.returncode != 0:
        raise RuntimeError(f"{what} failed (exit {done.returncode}): {(done.stderr or done.stdout).strip()[-500:]}")
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
    their passwords generated (``iorthand web password --generate``), on loopback."""
    (workdir / "deployment.yaml").write_text(yaml.safe_dump(
        {"robots": [robot], "operators": {"physician": [robot]}, "viewers": ["student"]}))
    logins = []
    for user in ("physician", "student"):
        out = run_step(iorthand_argv("web", "password", user, "--users-file", str(workdir / "web-users.txt"),
                                     "--generate"), f"the web password of {user}")
        logins.append((user, out.strip().rsplit(": ", 1)[-1]))
    (workdir / "web.yaml").write_text(yaml.safe_dump({
        "deployment": "deployment.yaml", "users_file": "web-users.txt", "listen": f"127.0.0.1:{free_port()}",
        "zenoh": {"mode": "client", "connect": [endpoint]}}))
    return Child("web", iorthand_argv("web", "--config", str(workdir / "web.yaml")), workdir / "web.log"), logins


def print_summary(result: dict, report: dict, workdir: Path, report_path: Path, twin_url: str) -> None:
    rtt = result["command_to_echo_ms"]
    stops = result.get("deadman_stops_ms") or [float("nan")]
    received = result.get("deadman_stops_after_receipt_ms") or [float("nan")]
    index = report.get("robots", {}).get(result["robot"], {}).get("index", {})
    gaps = report.get("recording", {})
    # Which streams lost messages (the report says): a video frame dropped by its latest-frame QoS is not a lost command.
    lost_on = gaps.get("missing_where", "")
    levels = {0: "green", 1: "yellow", 2: "red"}
    lines = [
        "",
        "iorthand demo — summary",
        f"  robot {result['robot']} (simulated), operator {result['operator']}, profile {result['profile']}",
        f"  commands sent/accepted/refused  {result['commands_sent']} / {result['commands_accepted']} / {result['commands_refused']}",
        f"  command→applied latency   p50 {rtt['p50']:.2f} ms, p99 {rtt['p99']:.2f} ms (through the router, echo)",
        f"  deadman stop (dead link)  {stops[0]:.0f} ms after the last command was sent, {received[0]:.0f} ms after "
        "the edge received it",
        f"  force                     peak level {result['peak_force_level']} ({levels.get(result['peak_force_level'], '?')})",
        f"  session index φ           {index.get('phi', float('nan')):.1f} % (contact {index.get('tau', 0):.1f} s of "
        f"{index.get('t_t', 0):.1f} s, warnings red {index.get('omega_R', 0)}, yellow {index.get('omega_Y', 0)})",
        f"  recording                 {gaps.get('messages', 0)} messages, {gaps.get('missing', 0)} missing by sequence"
        f"{f' ({lost_on})' if lost_on else ''}, {gaps.get('malformed', 0)} malformed",
        f"  refusals                  {'; '.join(r[:70] for r in result['refusals'][:3]) or 'none'}",
        f"  report                    {report_path}",
        f"  twin (rerun)              {workdir / 'twin.rrd'}  (view it: .venv/bin/rerun {workdir / 'twin.rrd'})" + (f"; live: {twin_url}" if twin_url else ""),
        f"  logs, configs, recording  {workdir}",
    ]
    print("\n".join(lines), flush=True)


def run_demo(args: argparse.Namespace) -> int:
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="iorthand-demo-"))
    workdir.mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    edge_cfg = workdir / "edge.yaml"
    edge_cfg.write_text(yaml.safe_dump(demo_edge_config(args.robot, endpoint), sort_keys=False))
    rec_cfg = workdir / "recorder.yaml"
    recordings = workdir / "recordings"
    rec_cfg.write_text(yaml.safe_dump({"zenoh": {"mode": "client", "connect": [endpoint]}, "output_dir": str(recordings)}))
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
    children = {
        "router": Child("router", iorthand_argv("router", "--listen", endpoint), workdir / "router.log"),
        "recorder": Child("recorder", iorthand_argv("recorder", "--config", str(rec_cfg)), workdir / "recorder.log"),
        "twin": Child("twin", iorthand_argv(*twin_argv), workdir / "twin.log"),
        "edge": Child("edge", iorthand_argv("edge", "--config", str(edge_cfg)), workdir / "edge.log"),
    }
    ready = {"router": "router ready", "recorder": "recorder ready", "twin": "twin ready", "edge": "edge agent",
             "web": "web console ready"}
    logins: list[tuple[str, str]] = []
    if args.view:
        children["web"], logins = web_console(workdir, args.robot, endpoint)

    def on_signal(signum: int, _frame: object) -> None:
        raise KeyboardInterrupt

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    print(f"iorthand demo: router on {endpoint}; logs in {workdir}", flush=True)
    code = 1
    try:
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
        print_summary(json.loads(out), json.loads((report_dir / "report.json").read_text()), workdir,
                      report_dir / "report.md", twin_url)
        code = 0
        if args.view:
            web_url = next((line.split("web console ready: ", 1)[1] for line in
                            (workdir / "web.log").read_text().splitlines() if "web console ready: " in line), "")
            foxglove = next((line.split("twin foxglove: ", 1)[1] for line in
                             (workdir / "twin.log").read_text().splitlines() if "twin foxglove: " in line), "")
            print(f"\nthe twin is live at {twin_url}", flush=True)
            if foxglove:
                print(f"the Foxglove app connects live at {foxglove} (Open connection → Foxglove WebSocket)", flush=True)
            print(f"the operator console (phone or desktop browser) is at {web_url}", flush=True)
            for user, password in logins:
                print(f"  log in as {user:<10} password {password}", flush=True)
            print("Ctrl-C stops everything", flush=True)
            while all(c.proc is not None and c.proc.poll() is None for c in children.values()):
                time.sleep(0.5)
    except KeyboardInterrupt:
        print("\niorthand demo: interrupted, stopping every process", flush=True)
        code = 130 if code else 0
    except (RuntimeError, subprocess.TimeoutExpired, OSError, ValueError) as exc:
        print(f"iorthand demo failed: {exc}", file=sys.stderr)
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not interrupt the clean-up
        for child in reversed(children.values()):
            child.stop()
    return code


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="the whole system on this machine: router, recorder, twin, simulated edge, "
                                    "scripted operator; prints a summary and the session report")
    p.add_argument("--robot", default="sim1")
    p.add_argument("--workdir", help="where logs, configs and the recording go (default: a new temporary folder)")
    p.add_argument("--timeout", type=float, default=120.0, help="s the scripted operator may take")
    p.add_argument("--view", action="store_true", help="serve the twin and the operator console in a browser and keep "
                                                          "running until Ctrl-C")
    p.set_defaults(func=run_demo)
