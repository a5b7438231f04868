"""Calibration on rendered ChArUco views with a known camera and mount; refusals of degenerate sets."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import pytest

from iorthand.geometry import compose, rot_x, rot_z, rotation_angle, translation, translation_distance
from iorthand_edge.perception.calibration import (
    CalibrationError,
    TargetFinder,
    TargetSpec,
    calibrate_handeye,
    calibrate_intrinsics,
    load_handeye,
    load_intrinsics,
    target_pose,
)
from iorthand_edge.perception.cli import register
from iorthand_edge.perception.config import SyntheticCameraConfig
from iorthand_edge.perception.synthetic import render_board_views

TCP_CAMERA = compose(translation(0.01, 0.06, 0.05), rot_z(0.3), rot_x(-0.2))
CAMERA = SyntheticCameraConfig(fx=610.0, fy=608.0, cx=322.0, cy=236.0, noise_sigma=2.0, blur_sigma=0.6)


@pytest.fixture(scope="module")
def dataset() -> tuple[list, list]:
    """15 noisy views (image noise, and 0.2 mm / 0.03° on the reported robot poses)."""
    rng = np.random.default_rng(7)
    views, _ = render_board_views(
        TargetSpec().charuco_board(), CAMERA, TCP_CAMERA, 15, rng, (0.0002, math.radians(0.03))
    )
    finder = TargetFinder(TargetSpec())
    return views, [finder.find(v.image) for v in views]


def test_intrinsics_recover_focal_length_within_one_percent(dataset: tuple[list, list]) -> None:
    _, found = dataset
    result = calibrate_intrinsics([f for f in found if f is not None], (640, 480), TargetSpec())
    k = result.calibration.matrix()
    assert abs(k[0, 0] - CAMERA.fx) / CAMERA.fx < 0.01
    assert abs(k[1, 1] - CAMERA.fy) / CAMERA.fy < 0.01
    assert result.calibration.rms_px < 0.5
    assert result.calibration.views == 15


def test_handeye_within_2_mm_and_half_a_degree(dataset: tuple[list, list]) -> None:
    views, found = dataset
    intrinsics = calibrate_intrinsics([f for f in found if f is not None], (640, 480), TargetSpec()).calibration
    observations = [target_pose(*f, intrinsics.matrix(), intrinsics.distortion()) for f in found]
    result = calibrate_handeye([v.t_base_tcp for v in views], observations, "tsai")
    assert translation_distance(result.t_tcp_camera, TCP_CAMERA) < 0.002
    assert math.degrees(rotation_angle(result.t_tcp_camera, TCP_CAMERA)) < 0.5


def test_numpy_fallback_agrees_with_opencv(dataset: tuple[list, list], monkeypatch: pytest.MonkeyPatch) -> None:
    """OpenCV 5.0 has no calibrateHandEye: the Park–Martin fallback must give the same answer."""
    import cv2

    views, found = dataset
    k = np.array([[CAMERA.fx, 0, CAMERA.cx], [0, CAMERA.fy, CAMERA.cy], [0, 0, 1.0]])
    observations = [target_pose(*f, k, np.zeros(5)) for f in found]
    monkeypatch.delattr(cv2, "calibrateHandEye")
    result = calibrate_handeye([v.t_base_tcp for v in views], observations)
    assert "Park-Martin" in result.method
    assert translation_distance(result.t_tcp_camera, TCP_CAMERA) < 0.002
    assert math.degrees(rotation_angle(result.t_tcp_camera, TCP_CAMERA)) < 0.5


def test_refuses_too_few_views(dataset: tuple[list, list]) -> None:
    _, found = dataset
    with pytest.raises(CalibrationError, match="at least 10 views"):
        calibrate_intrinsics([f for f in found if f is not None][:6], (640, 480), TargetSpec())


def test_refuses_views_all_from_the_same_angle(dataset: tuple[list, list]) -> None:
    _, found = dataset
    with pytest.raises(CalibrationError, match="degenerate views"):
        calibrate_intrinsics([found[0]] * 12, (640, 480), TargetSpec())


def test_refuses_handeye_without_rotation(dataset: tuple[list, list]) -> None:
    views, _ = dataset
    poses = [compose(translation(0.01 * i, 0.0, 0.0), views[0].t_base_tcp) for i in range(8)]
    with pytest.raises(CalibrationError, match="degenerate poses"):
        calibrate_handeye(poses, [np.eye(4)] * 8)


def test_cli_render_intrinsics_handeye_round_trip(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(required=True))

    def run(*argv: str) -> int:
        args = parser.parse_args(["calibrate", *argv])
        return args.func(args)

    data = tmp_path / "dataset"
    assert run("render", str(data), "--views", "12", "--pan", "0.3", "--tilt", "-0.2") == 0
    assert run("intrinsics", "--images", str(data), "--out", str(tmp_path / "intrinsics.yaml")) == 0
    intrinsics = load_intrinsics(tmp_path / "intrinsics.yaml", (640, 480))
    assert intrinsics.views == 12 and intrinsics.method and intrinsics.date and intrinsics.rms_px < 0.5
    assert abs(intrinsics.matrix()[0, 0] - 600.0) < 6.0
    assert (
        run("handeye", str(data), "--intrinsics", str(tmp_path / "intrinsics.yaml"), "--out", str(tmp_path / "he.yaml"))
        == 0
    )
    handeye = load_handeye(tmp_path / "he.yaml", (640, 480))
    assert handeye.poses == 12 and handeye.pan == pytest.approx(0.3)
    # Too few images: refused with the reason, exit code 2.
    for extra in sorted(data.glob("view_*.png"))[5:]:
        extra.unlink()
    assert run("intrinsics", "--images", str(data), "--out", str(tmp_path / "bad.yaml")) == 2
    assert "at least 10 views" in capsys.readouterr().err
    assert not (tmp_path / "bad.yaml").exists()
