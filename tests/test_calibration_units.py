"""Calibration files in other units than iorthand writes are refused with a message naming what is wrong: a
hand-eye in millimetres and degrees (read as metres and radians: the camera tens of metres from the TCP),
intrinsics whose principal point lies outside the image. Every calibration file in the repository still loads."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from iorthand.config import load
from iorthand_edge.perception.calibration import (
    CalibrationError,
    HandEyeCalibration,
    IntrinsicsCalibration,
    load_handeye,
    load_intrinsics,
    save_calibration,
)

ROOT = Path(__file__).resolve().parents[1]
HANDEYE = ROOT / "configs" / "calibration" / "handeye.yaml"
INTRINSICS = ROOT / "configs" / "calibration" / "intrinsics-640x480.yaml"


def _write(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data, allow_unicode=True), encoding="utf-8")
    return path


def _handeye(**changes: object) -> dict:
    data = yaml.safe_load(HANDEYE.read_text())
    data.update(changes)
    return data


def _intrinsics(**changes: object) -> dict:
    data = yaml.safe_load(INTRINSICS.read_text())
    data.update(changes)
    return data


def test_every_calibration_file_in_the_repository_loads() -> None:
    files = [p for d in ("configs", "deploy", "tests") if (ROOT / d).exists()
             for p in sorted((ROOT / d).rglob("*.y*ml"))]
    found = {"intrinsics": 0, "handeye": 0}
    for path in files:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
        if not isinstance(data, dict):
            continue
        if "camera_matrix" in data:
            load_intrinsics(path)
            found["intrinsics"] += 1
        elif "tcp_camera" in data:
            load_handeye(path)
            found["handeye"] += 1
    assert found["intrinsics"] >= 1 and found["handeye"] >= 1, found


def test_the_red_teams_handeye_in_mm_and_degrees_is_refused(tmp_path: Path) -> None:
    path = _write(tmp_path / "he.yaml", {"tcp_camera": [0.0, 45.0, 30.0, 0.0, 0.0, 3.0], "image_width": 640,
                                         "image_height": 480, "pan": 5.0, "tilt": -3.0, "units": "mm and degrees"})
    with pytest.raises(CalibrationError, match=r"he\.yaml.*units.*'mm and degrees'"):
        load_handeye(path, (640, 480))


@pytest.mark.parametrize(("changes", "problem"), [
    ({"tcp_camera": [0.0, 45.0, 30.0, 0.0, 0.0, 0.2]}, r"tcp_camera: the camera would be 54.1 m from the TCP.*metres"),
    ({"tcp_camera": [0.0, 0.6, 0.0, 0.0, 0.0, 0.2]}, r"tcp_camera: .*0.6 m from the TCP"),
    ({"tcp_camera": [0.0, 0.05, 0.06, 0.0, 0.0, 11.5]}, r"tcp_camera: the rotation vector's angle is 11.5.*degrees"),
    ({"tilt_camera": [0.0, 15.0, 35.0, 0.0, 0.0, 0.0]}, r"tilt_camera: .*metres"),
    ({"pan": 3.5}, r"pan: 3.5 is beyond ±π.*radians"),
    ({"tilt": -5.7}, r"tilt: -5.7 is beyond ±π"),
    ({"units": "mm and degrees"}, r"units: the file says 'mm and degrees'"),
])
def test_a_handeye_in_other_units_is_refused_saying_what_is_wrong(tmp_path: Path, changes: dict, problem: str) -> None:
    path = _write(tmp_path / "he.yaml", _handeye(**changes))
    with pytest.raises(CalibrationError, match=problem):
        load_handeye(path, (640, 480))


@pytest.mark.parametrize(("matrix", "where"), [
    ([[600, 0, 1280], [0, 600, 960], [0, 0, 1]], r"\(1280, 960\)"),
    ([[600, 0, 320], [0, 600, 480], [0, 0, 1]], r"\(320, 480\)"),
    ([[600, 0, -1], [0, 600, 240], [0, 0, 1]], r"\(-1, 240\)"),
    ([[600, 0, 0], [0, 600, 0], [0, 0, 1]], r"\(0, 0\)"),
])
def test_intrinsics_with_the_principal_point_outside_the_image_are_refused(
    tmp_path: Path, matrix: list, where: str
) -> None:
    path = _write(tmp_path / "k.yaml", _intrinsics(camera_matrix=matrix))
    with pytest.raises(CalibrationError, match=rf"principal point {where} px lies outside the 640×480 image"):
        load_intrinsics(path, (640, 480))


def test_intrinsics_in_other_units_are_refused(tmp_path: Path) -> None:
    path = _write(tmp_path / "k.yaml", _intrinsics(units="mm"))
    with pytest.raises(CalibrationError, match=r"units: the file says 'mm'"):
        load_intrinsics(path, (640, 480))


def test_what_iorthand_writes_it_reads_back(tmp_path: Path) -> None:
    """The writer's units are the ones the reader requires (save_calibration of the dataclasses' defaults)."""
    he = load(HANDEYE, HandEyeCalibration)
    k = load(INTRINSICS, IntrinsicsCalibration)
    assert he.units == "m and rad; poses are [x, y, z, rx, ry, rz] with a rotation vector"
    assert k.units == "camera_matrix and rms in px; target sizes in m"
    save_calibration(tmp_path / "he.yaml", HandEyeCalibration(
        tcp_camera=he.tcp_camera, image_width=640, image_height=480, pan=he.pan, tilt=he.tilt))
    save_calibration(tmp_path / "k.yaml", IntrinsicsCalibration(
        image_width=640, image_height=480, camera_matrix=k.camera_matrix))
    assert load_handeye(tmp_path / "he.yaml", (640, 480)).tcp_camera == he.tcp_camera
    assert load_intrinsics(tmp_path / "k.yaml", (640, 480)).camera_matrix == k.camera_matrix
