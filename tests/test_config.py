"""Configuration errors name the file, the key and what was expected."""

from __future__ import annotations

from pathlib import Path

import pytest

from iorthand.config import ConfigError, load
from iorthand_edge.config import EdgeConfig, load_edge_config
from iorthand_edge.robots.config import SimRobotConfig, URRobotConfig

GOOD = """
robot_id: lab1
zenoh: {mode: client, connect: ["tcp/127.0.0.1:7447"]}
robot: {kind: sim}
safety: {auto_arm: true, profile: local}
"""


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "edge.yaml"
    p.write_text(text)
    return p


def test_good_config_loads_with_defaults(tmp_path: Path) -> None:
    cfg = load_edge_config(write(tmp_path, GOOD))
    assert cfg.robot_id == "lab1"
    assert isinstance(cfg.robot, SimRobotConfig)
    assert cfg.safety.command_timeout == 0.15
    assert cfg.safety.profiles["remote"].linear == 0.008
    assert cfg.safety.profiles["local"].linear == 0.030


@pytest.mark.parametrize(
    ("text", "key", "expected"),
    [
        (GOOD.replace("lab1", "Lab 1"), "", "robot id"),
        (GOOD.replace("lab1", "lab1-replay"), "", "reserved for replayed recordings"),
        (GOOD.replace("auto_arm: true", "auto_arm: yes please"), "safety.auto_arm", "true or false"),
        (GOOD + "safety_rate_hz: -3\n", "safety_rate_hz", "at least"),
        (GOOD.replace("kind: sim", "kind: kuka"), "robot.kind", "one of"),
        (GOOD.replace("profile: local", "profile: turbo"), "safety", "profile 'turbo'"),
        (GOOD + "colour: red\n", "colour", "unknown key"),
        (GOOD.replace("robot_id: lab1\n", ""), "robot_id", "missing"),
        (GOOD.replace('connect: ["tcp/127.0.0.1:7447"]', "connect: []"), "zenoh", "router endpoint"),
        (GOOD.replace("kind: sim", "kind: ur") , "", "auto_arm is allowed only"),
        (GOOD.replace("profile: local}", "profile: local, command_timeout: .nan}"), "safety.command_timeout", "finite"),
        (GOOD + "perception: {camera: {kind: synthetic, fps: 15}}\nvideo: {camera: {source: perception, fps: 30}}\n",
         "", "video.camera.fps 30 must be perception.camera.fps 15"),
        # A box written in millimetres: its + faces would never be met.
        (GOOD.replace("profile: local}", "profile: local, workspace: {min: [100, -300, 20], max: [450, 300, 450]}}"),
         "safety.workspace", "100 m is beyond any arm's reach (2 m); the box is in metres (millimetres?)"),
        (GOOD.replace("profile: local}", "profile: local, contact: {target: 7}}") + "force: {sensor: {kind: sim}}\n",
         "", "safety.contact.target 7 N must lie below force.levels.caution (6 N)"),
        (GOOD.replace("profile: local}", "profile: local, force: {contact_axis: [0, 0, 1.0e-12]}}"),
         "safety.force", "must be a direction"),
        (GOOD + "goto: {poses: {sweep: [0.3, 0, 0.25, 3.14, 0, 0]}}\n", "goto", "the name of a primitive"),
        (GOOD + "goto: {poses: {'above_marker:3': [0.3, 0, 0.25, 3.14, 0, 0]}}\n", "goto", "':' is reserved"),
    ],
)
def test_errors_name_file_key_and_expectation(tmp_path: Path, text: str, key: str, expected: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_edge_config(path)
    assert err.value.source == str(path)
    assert err.value.key == key
    assert expected in str(err.value)


def test_a_named_pose_or_a_start_outside_the_workspace_is_said(tmp_path: Path) -> None:
    """They load (the box may be narrowed on purpose), but every move there is refused: `iorthand check` and the
    agent's start say so."""
    cfg = load_edge_config(write(tmp_path, GOOD.replace("robot: {kind: sim}", "robot: {kind: sim, initial_pose: "
                                                        "[0.9, 0.0, 0.2, 3.14, 0, 0]}")
                                 + "goto: {poses: {home: [0.30, 0.0, 0.60, 3.14, 0, 0]}}\n"))
    said = dict(cfg.warnings())
    assert said["goto.poses.home"].startswith("[0.3, 0.0, 0.6] lies outside safety.workspace")
    assert "robot.initial_pose" in said
    assert not dict(load_edge_config(write(tmp_path, GOOD)).warnings()).keys() & {"goto.poses.home", "robot.initial_pose"}


def test_a_key_written_twice_is_refused_with_both_lines(tmp_path: Path) -> None:
    """YAML keeps the last of two equal keys and says nothing: a script step `{duration: 1, duration: 100}` ran for
    100 s (found by a red-team run). Every configuration file goes through this loader."""
    twice = GOOD.replace("safety: {auto_arm: true, profile: local}",
                         "safety:\n  auto_arm: true\n  command_timeout: 0.15\n  command_timeout: 1.5")
    with pytest.raises(ConfigError, match=r"line 8, column 3: the key 'command_timeout' appears twice \(first at line 7\)"):
        load_edge_config(write(tmp_path, twice))


def test_unreadable_and_corrupt_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load(tmp_path / "nope.yaml", EdgeConfig)
    with pytest.raises(ConfigError, match=r"not valid YAML .*line 2"):
        load(write(tmp_path, "robot_id: a\n  zenoh: [\n"), EdgeConfig)


def test_ur_variant_has_its_own_dataclass(tmp_path: Path) -> None:
    cfg = load_edge_config(write(tmp_path, GOOD.replace("kind: sim", "kind: ur, host: 10.0.0.5").replace("auto_arm: true", "auto_arm: false")))
    assert isinstance(cfg.robot, URRobotConfig) and cfg.robot.host == "10.0.0.5"
