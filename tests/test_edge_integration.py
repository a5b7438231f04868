"""The edge agent with its components wired together, through a real router: perception publishing marker
poses chained through the servos, previewed goto through the twin, local arming."""

from __future__ import annotations

import json
import math
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from iorthand import geometry, keys
from iorthand.protocol import Markers
from tests.conftest import ROOT, iorthand_cmd, wait_until

HOME = math.pi / 2  # the servos' home angle: the perception chain's zero in these configs


def perception_section() -> dict:
    section = yaml.safe_load((ROOT / "configs" / "scene-phantom.yaml").read_text())
    section["geometry"].update(pan_zero=HOME, tilt_zero=HOME)
    return section


class MarkerLog:
    def __init__(self, session, robot: str = "sim1") -> None:
        self.messages: list[Markers] = []
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(keys.RobotKeys(robot).key(keys.MARKERS), self._add)

    def _add(self, sample) -> None:
        with self._lock:
            self.messages.append(Markers.decode(sample.payload.to_bytes()))

    def since(self, t_ns: int) -> list[Markers]:
        with self._lock:
            return [m for m in self.messages if m.t >= t_ns]


def pose_errors(msg: Markers, scene: dict) -> dict[int, tuple[float, float]]:
    """Per marker id: (position error mm, rotation error deg) of the filtered pose against the scene."""
    truth = {m["id"]: geometry.pose_to_matrix(m["pose"]) for m in scene["markers"]}
    out = {}
    for m in msg.markers:
        est = geometry.unflatten(m.pose)
        out[m.id] = (1000 * geometry.translation_distance(est, truth[m.id]), math.degrees(geometry.rotation_angle(est, truth[m.id])))
    return out


def test_markers_are_published_in_the_base_frame_and_servos_do_not_move_them(
    edge_factory, operator_factory, session_factory, twin_factory
) -> None:
    section = perception_section()
    edge = edge_factory(
        robot={"kind": "sim", "initial_pose": [0.40, 0.11, 0.36, math.pi, 0.0, 0.0]},  # camera above the phantom
        servos={}, perception=section,
    )
    log = MarkerLog(session_factory())
    twin_factory()  # previews go through the twin
    wait_until(lambda: len(log.messages) >= 15 and len(log.messages[-1].markers) == 3, timeout=15.0, message="3 markers")
    errors = pose_errors(log.messages[-1], section["scene"])
    print(f"\nmarkers at the servos' home: {errors}")
    assert all(mm <= 3.0 and deg <= 1.0 for mm, deg in errors.values()), errors

    # Turn the camera (owner only): the markers must stay where they are in the base frame.
    op = operator_factory()
    op.wait_for_state()
    op.acquire()
    op.send_servo(pan=HOME + 0.12, tilt=HOME - 0.10)
    wait_until(lambda: abs(edge.servos.servo_angles_at(time.time_ns())[0] - (HOME + 0.12)) < 1e-3, timeout=5.0, message="servos turned")
    turned = time.time_ns()
    wait_until(lambda: len(log.since(turned)) >= 15, timeout=15.0, message="frames after turning")
    msg = log.since(turned)[-1]
    errors = pose_errors(msg, section["scene"])
    print(f"markers with the servos turned: {errors}")
    assert errors and all(mm <= 3.0 and deg <= 1.0 for mm, deg in errors.values()), errors
    assert edge.markers.keys() == {m.id for m in msg.markers}

    # Markers in view can be moved above; once the camera stalls, their poses age out and no move may aim
    # at where the patient was (goto.marker_max_age, 0.5 s by default).
    assert {"above_marker:3", "above_marker:7", "above_marker:11"} <= {p["name"] for p in op.list_poses()}
    assert edge.media is not None
    edge.media.stop()  # the camera (in the media process) stalls: no frames, no news
    time.sleep(edge.config.goto.marker_max_age + 0.1)
    assert not [p["name"] for p in op.list_poses() if p["name"].startswith("above_marker:")]
    stale = op.preview_pose("above_marker:3")
    assert not stale.ok and "marker 3 is not in view" in stale.reason, stale.reason


def test_previewed_goto_through_the_twin(edge_factory, twin_factory, operator_factory) -> None:
    # A 1 s command timeout: this test is about the preview, its token and the pose reached; router, edge, twin and
    # operator share its process, and a pause of that process on a loaded machine must not cancel the move
    # (stopping at the 150 ms timeout is tested in test_teleop_loop and test_primitives_live).
    edge = edge_factory(
        safety={"profile": "local", "command_timeout": 1.0},
        goto={"poses": {"home": [0.30, 0.02, 0.24, math.pi, 0.0, 0.0], "outside": [0.60, 0.0, 0.25, math.pi, 0.0, 0.0]}},
    )
    twin_factory()
    op = operator_factory()
    op.wait_for_state()
    op.acquire()
    op.start()
    names = {p["name"] for p in op.list_poses()}
    assert {"home", "outside", "retract"} <= names

    outside = op.preview_pose("outside")
    assert not outside.ok and "workspace" in outside.reason

    preview = op.preview_pose("home")
    assert preview.ok, preview.reason
    detail = json.loads(preview.detail)
    assert detail["token"] and detail["duration"] > 0 and detail["inside_workspace"] and detail["reachable"]

    refused = op.goto_pose("home", "not-a-token")
    assert not refused.ok and "token" in refused.reason
    # The wrong token consumed nothing: the real one still works, once.
    started = op.goto_pose("home", detail["token"])
    assert started.ok, started.reason
    op.set_twist([0, 0, 0], [0, 0, 0], deadman=True)  # hold-to-run: the edge supplies the velocity
    wait_until(lambda: not edge.goto.active, timeout=detail["duration"] + 10.0, message="move finished")
    op.set_twist([0, 0, 0], [0, 0, 0], deadman=False)
    assert edge.goto.status == "done", edge.goto.reason
    reached = np.array(op.robot_state.tcp_pose[:3])
    error_mm = 1000 * float(np.linalg.norm(reached - [0.30, 0.02, 0.24]))
    print(f"\ngoto home through the twin: {detail['duration']:.2f} s planned, ended {error_mm:.3f} mm from the pose")
    assert error_mm <= 1.0
    again = op.goto_pose("home", detail["token"])
    assert not again.ok and "already used" in again.reason


def test_arming_needs_the_local_socket(router_endpoint, edge_factory, operator_factory, tmp_path: Path) -> None:
    sock = tmp_path / "edge.sock"
    edge = edge_factory(safety={"auto_arm": False}, local_socket=str(sock))
    op = operator_factory()
    op.wait_for_state()
    reply = op.request_arm()
    assert not reply.ok and "confirmation" in reply.reason
    wait_until(lambda: op.safety is not None and op.safety.arm_requested, message="arm request visible")
    assert not edge.supervisor.armed
    cfg = tmp_path / "edge.yaml"
    cfg.write_text(yaml.safe_dump({"robot_id": "sim1", "zenoh": {"connect": [router_endpoint]}, "local_socket": str(sock)}))
    out = subprocess.run(iorthand_cmd("arm", "--config", str(cfg)), capture_output=True, text=True, timeout=30)
    assert out.returncode == 0 and "armed" in out.stdout, out.stderr
    assert edge.supervisor.armed
    wait_until(lambda: op.safety.armed, message="armed state published")
    assert oct(sock.stat().st_mode & 0o777) == "0o600"


@pytest.mark.parametrize("command", ["status", "bogus"])
def test_local_commands_answer_in_one_line(edge_factory, command: str) -> None:
    edge = edge_factory()
    answer = edge.local_command(command)
    assert "\n" not in answer
    assert (json.loads(answer)["armed"] is True) if command == "status" else answer.startswith("error: unknown")
