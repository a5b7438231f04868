"""Background load through the same routers as the commands: camera video (30 fps 640×480 JPEG, edge →
operator, video QoS on its own session) and the edge's other state streams (force 100 Hz, markers 30 Hz; the
edge agent itself already publishes state/robot at 125 Hz, safety at 20 Hz and the command echo).

:func:`run_load` measures commands with and without that load, and once more with the commands' priority
lowered to Zenoh's default, to show what ``REAL_TIME`` + express buys.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from iorthand_operator.bench.procs import Group, python_argv
from iorthand_operator.bench.transports import ROLES, Sites, run_command_path, run_ping

LOAD_ROBOT = "bench"


def video_load(fps: float = 30.0, quality: int = 85, robot: str = LOAD_ROBOT) -> Callable[[Group, Sites], None]:
    """A load function for :func:`run_ping`/:func:`run_command_path`: video + state streams."""

    def start(group: Group, sites: Sites) -> None:
        group.start("video-pub", python_argv(ROLES, "video-pub", *sites.edge_args, "--robot", robot, "--fps", str(fps),
                                             "--quality", str(quality)), ready="video ready")
        group.start("video-sub", python_argv(ROLES, "video-sub", *sites.operator_args, "--robot", robot,
                                             "--out", str(group.workdir / "video-sub.json")), ready="video-sub ready")
        group.start("state-pub", python_argv(ROLES, "state-pub", *sites.edge_args, "--robot", robot), ready="state ready")

    return start


def frame_size(group_dir: Path) -> int:
    """The synthetic JPEG size the video publisher reported (0 if unknown)."""
    try:
        text = (group_dir / "video-pub.log").read_text()
    except OSError:
        return 0
    for line in text.splitlines():
        if line.startswith("video ready"):
            return int(line.split()[2])
    return 0


def video_received(group_dir: Path) -> dict[str, Any]:
    import json

    try:
        return json.loads((group_dir / "video-sub.json").read_text())
    except (OSError, ValueError):
        return {}


def run_load(workdir: Path, duration: float, transport: str = "zenoh-router", fps: float = 30.0) -> dict[str, Any]:
    cases: dict[str, Any] = {}
    cases["command_path_idle"] = run_command_path(workdir, transport, duration, name="load-command-idle")
    cases["command_path_video"] = run_command_path(workdir, transport, duration, load=video_load(fps),
                                                   name="load-command-video")
    vdir = workdir / "load-command-video"
    cases["command_path_video"]["video"] = {"frame_bytes": frame_size(vdir), **video_received(vdir)}
    cases["ping_realtime_video"] = run_ping(workdir, transport, 64, 60.0, duration, qos="command", load=video_load(fps))
    cases["ping_default_priority_video"] = run_ping(workdir, transport, 64, 60.0, duration, qos="default",
                                                    load=video_load(fps))
    return {"transport": transport, "fps": fps, "cases": cases}
