"""The web console against the Python operator client, in one run (issue 21).

One router, one edge (configs/edge-sim.yaml: the simulated robot, camera video at ``--fps`` from the perception
camera, ultrasound video), the web server (``iorthand web``) and Debian's Chromium driven by Playwright. Phases
alternate over ``--rounds`` on the same robot:

- ``page``: a desktop page logged in as an operator holds control and the deadman (Space) with a key held
  (motion along y): its own 60 Hz timer sends the twists; the page times each command from its ``send`` to the
  server's forward of the edge's echo (page → server → router → edge → router → server → page);
- ``python``: an :class:`OperatorClient` (thread sender, 60 Hz) drives the same way; the client times send → echo.

The difference of the two p50s is what the browser, the websocket and the server add (target ≤ 1 ms on
loopback): measured with a page that asked for no video and no 3D view (``page_extra_p50_ms``: in headless
Chromium the 3D view renders in software on the same two cores, which a phone's GPU does not), and with both
(``page_with_video_and_3d_extra_p50_ms``). During the page phases the page also records each video frame's glass-to-page delay: the frame's
capture time (the edge's media process stamps it) to its arrival in the page, both on this host's clock, and the
bytes received. Then the web server's CPU is measured with 0, 1, 2 and 4 pages open (viewers, video flowing):
the slope is its CPU per connected page.

Writes benchmarks/results/web.json.

    .venv/bin/python benchmarks/bench_web.py [--seconds 15] [--rounds 2] [--fps 30]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil
import yaml
from teleop_stack import CONFIGS, RESULTS, close_operator, edge_config, operator, start_edge, start_router

from iorthand.transport import free_port
from iorthand_operator.bench import report
from iorthand_operator.bench.procs import Group, iorthand_argv
from iorthand_operator.web import users

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
        "--no-first-run", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
USERS = {"physician": "bench-physician-pw", "student": "bench-student-pw"}
TARGET_EXTRA_P50_MS = 1.0


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q / 100 * len(s)))] if s else float("nan")


def summary(values: list[float]) -> dict[str, float]:
    return {"count": len(values), "p50": round(pct(values, 50), 3), "p90": round(pct(values, 90), 3),
            "p99": round(pct(values, 99), 3), "max": round(max(values), 3) if values else float("nan")}


def open_page(browser: Any, url: str, user: str) -> Any:
    ctx = browser.new_context(viewport={"width": 1280, "height": 800}, bypass_csp=True)
    page = ctx.new_page()
    page.goto(url + "/login")
    page.fill("#user", user)
    page.fill("#password", USERS[user])
    page.click("#login-button")
    page.wait_for_url(url + "/")
    page.wait_for_function("window.iorthand && window.iorthand.socket === 'open'")
    return page


def page_phase(browser: Any, url: str, seconds: float, lite: bool) -> dict[str, Any]:
    page = open_page(browser, url, "physician")
    if lite:  # no video pushed, no 3D view drawn: what the bridge itself costs
        page.click("summary")
        page.uncheck("#want-video")
        page.uncheck("#want-3d")
    page.click("#control")
    page.wait_for_function("document.getElementById('control').textContent === 'Release control'", timeout=15_000)
    page.evaluate("window.iorthand.echoes.length = 0")
    page.keyboard.down("Space")
    time.sleep(0.3)  # the press after the grant's release
    page.evaluate("""() => { const s = window.iorthand; s.echoes.length = 0; s.video.camera.length = 0;
                             s.video.ultrasound.length = 0; s.videoBytes = 0; s.t0 = performance.now(); }""")
    direction = "KeyW"
    end = time.monotonic() + seconds
    while time.monotonic() < end:  # back and forth along y, a key held for 2 s each way
        page.keyboard.down(direction)
        time.sleep(min(2.0, max(0.0, end - time.monotonic())))
        page.keyboard.up(direction)
        direction = "KeyS" if direction == "KeyW" else "KeyW"
    got = page.evaluate("""() => { const s = window.iorthand; return {echoes: s.echoes, video: s.video,
                           bytes: s.videoBytes, seconds: (performance.now() - s.t0) / 1000}; }""")
    page.keyboard.up("Space")
    page.click("#control")
    page.wait_for_function("document.getElementById('control').textContent !== 'Release control'", timeout=10_000)
    page.context.close()
    return got


def python_phase(endpoint: str, robot: str, seconds: float) -> list[float]:
    op = operator(endpoint, robot, "physician")
    try:
        op.set_twist([0.0, 0.0, 0.0], [0.0] * 3, deadman=False)
        time.sleep(0.3)
        start = op.echo_count
        speed, end = 0.005, time.monotonic() + seconds
        while time.monotonic() < end:
            op.set_twist([0.0, speed, 0.0], [0.0] * 3, deadman=True)
            time.sleep(min(2.0, max(0.0, end - time.monotonic())))
            speed = -speed
        return [e.rtt_ms for e in op.echoes_since(start) if e.accepted]
    finally:
        close_operator(op)


def cpu_per_page(browser: Any, url: str, web_pid: int, seconds: float) -> dict[str, Any]:
    proc = psutil.Process(web_pid)
    pages: list[Any] = []
    rows = []
    for n in (0, 1, 2, 4):
        while len(pages) < n:
            pages.append(open_page(browser, url, "student"))
        time.sleep(2.0)
        t0, c0 = time.monotonic(), sum(proc.cpu_times()[:2])
        time.sleep(seconds)
        share = 100 * (sum(proc.cpu_times()[:2]) - c0) / (time.monotonic() - t0)
        rows.append({"pages": n, "cpu_percent_of_a_core": round(share, 2)})
    for p in pages:
        p.context.close()
    n = [r["pages"] for r in rows]
    c = [r["cpu_percent_of_a_core"] for r in rows]
    slope = statistics.linear_regression(n, c).slope
    return {"rows": rows, "per_page_percent_of_a_core": round(slope, 2)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=15.0, help="s per phase")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--fps", type=int, default=30, help="camera video frames per second")
    p.add_argument("--out", default=str(RESULTS / "web.json"))
    args = p.parse_args(argv)
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        print("bench_web: pip install playwright (no browser download: Debian's chromium is used)", file=sys.stderr)
        return 2
    if not Path(CHROMIUM).exists():
        print("bench_web: apt-get install -y chromium", file=sys.stderr)
        return 2
    work = Path(tempfile.mkdtemp(prefix="iorthand-bench-web-"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    robot = "sim1"
    cpu0 = report.cpu_times()
    result: dict[str, Any] = {"page_ms": [], "page_lite_ms": [], "python_ms": [],
                              "video_ms": {"camera": [], "ultrasound": []}, "video_bytes": 0, "video_seconds": 0.0}
    with Group(work) as g:
        start_router(g, endpoint)
        cfg = edge_config(CONFIGS / "edge-sim.yaml", work / "edge.yaml", endpoint, {"robot_id": robot})
        data = yaml.safe_load(cfg.read_text())
        data["video"]["camera"]["fps"] = args.fps
        data["perception"]["camera"]["fps"] = float(args.fps)
        cfg.write_text(yaml.safe_dump(data))
        start_edge(g, cfg)
        (work / "deployment.yaml").write_text(yaml.safe_dump(
            {"robots": [robot], "operators": {"physician": [robot]}, "viewers": ["student"]}))
        (work / "web-users.txt").write_text(users.format_users({u: users.hash_password(pw) for u, pw in USERS.items()}))
        port = free_port()
        (work / "web.yaml").write_text(yaml.safe_dump({"deployment": "deployment.yaml", "users_file": "web-users.txt",
                                                       "listen": f"127.0.0.1:{port}",
                                                       "zenoh": {"mode": "client", "connect": [endpoint]}}))
        web = g.start("web", iorthand_argv("web", "--config", str(work / "web.yaml")), ready="web console ready",
                      timeout=60.0)
        url = f"http://127.0.0.1:{port}"
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS)
            for r in range(args.rounds):
                print(f"  round {r + 1}/{args.rounds}: page without video and 3D ({args.seconds:g} s) ...", flush=True)
                got = page_phase(browser, url, args.seconds, lite=True)
                result["page_lite_ms"] += [e[1] for e in got["echoes"] if e[2]]
                print(f"  round {r + 1}/{args.rounds}: page ({args.seconds:g} s) ...", flush=True)
                got = page_phase(browser, url, args.seconds, lite=False)
                result["page_ms"] += [e[1] for e in got["echoes"] if e[2]]
                for name in ("camera", "ultrasound"):
                    result["video_ms"][name] += got["video"][name]
                result["video_bytes"] += got["bytes"]
                result["video_seconds"] += got["seconds"]
                print(f"  round {r + 1}/{args.rounds}: python client ({args.seconds:g} s) ...", flush=True)
                result["python_ms"] += python_phase(endpoint, robot, args.seconds)
            print("  web server CPU with 0, 1, 2, 4 pages ...", flush=True)
            cpu = cpu_per_page(browser, url, web.proc.pid, args.seconds / 2)
            browser.close()
    page_s, py_s = summary(result["page_ms"]), summary(result["python_ms"])
    lite_s = summary(result["page_lite_ms"])
    extra = round(lite_s["p50"] - py_s["p50"], 3)
    secs = result["video_seconds"] or 1.0
    video = {name: {**summary(v), "fps_received": round(len(v) / secs, 1)} for name, v in result["video_ms"].items()}
    out = {
        "benchmark": "web",
        "what": "command round trip from a browser page (page -> web server -> router -> edge and back) against the "
                "Python OperatorClient in alternating phases of one run; video glass-to-page delay; the server's CPU "
                "per connected page",
        "machine": report.machine(),
        "config": {"seconds": args.seconds, "rounds": args.rounds, "camera_fps": args.fps, "workdir": str(work),
                   "video_transport": "JPEG over the websocket, newest frame wins"},
        "host_cpu": report.cpu_share_since(cpu0),
        "page_round_trip_ms": page_s,
        "page_without_video_and_3d_round_trip_ms": lite_s,
        "python_round_trip_ms": py_s,
        "page_extra_p50_ms": extra,
        "page_with_video_and_3d_extra_p50_ms": round(page_s["p50"] - py_s["p50"], 3),
        "target": {"limit_ms": TARGET_EXTRA_P50_MS, "pass": extra <= TARGET_EXTRA_P50_MS},
        "video_glass_to_page_ms": video,
        "video_bandwidth_mbit_s": round(8 * result["video_bytes"] / secs / 1e6, 2),
        "server_cpu": cpu,
    }
    report.write_json(Path(args.out), out)
    print(json.dumps({k: out[k] for k in ("page_round_trip_ms", "page_without_video_and_3d_round_trip_ms",
                                          "python_round_trip_ms", "page_extra_p50_ms",
                                          "video_glass_to_page_ms", "video_bandwidth_mbit_s", "server_cpu")}, indent=1))
    print(f"page extra p50 {extra} ms (limit {TARGET_EXTRA_P50_MS}): {'PASS' if extra <= TARGET_EXTRA_P50_MS else 'MISS'}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
