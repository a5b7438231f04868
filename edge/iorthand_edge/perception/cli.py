"""``iorthand calibrate ...``: camera intrinsics, eye-in-hand hand-eye, and a synthetic dataset to try them on.

    iorthand calibrate render DIR [--config perception.yaml] [--views 15]
    iorthand calibrate intrinsics (--images DIR | --device N) --out intrinsics.yaml
    iorthand calibrate handeye DIR --intrinsics intrinsics.yaml [--config perception.yaml] --out handeye.yaml

Each command prints its figures and returns 0, or prints why it refused and returns 2.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import yaml

from iorthand.config import ConfigError, cli_number, from_dict, load, to_dict
from iorthand.geometry import matrix_to_pose

from .calibration import (
    HANDEYE_METHODS,
    MIN_INTRINSICS_VIEWS,
    RECOMMENDED_HANDEYE_POSES,
    CalibrationError,
    TargetFinder,
    TargetSpec,
    calibrate_handeye,
    calibrate_intrinsics,
    handeye_calibration,
    load_intrinsics,
    poses_file_entry,
    read_poses_file,
    save_calibration,
    target_pose,
)
from .camera import CameraError, DeviceCamera
from .chain import CameraChain
from .config import DeviceCameraConfig, PerceptionConfig, SyntheticCameraConfig
from .synthetic import render_board_views

_IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}
_FAILED = 2


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``calibrate`` and its sub-commands. Each parser sets ``func(args) -> int`` (the exit code)."""
    calibrate = subparsers.add_parser("calibrate", help="camera intrinsics and hand-eye calibration")
    commands = calibrate.add_subparsers(dest="calibrate_command", required=True)

    render = commands.add_parser("render", help="render a synthetic ChArUco dataset with a known camera")
    render.add_argument("out", type=Path, help="folder to write images, poses.yaml and truth.yaml into")
    render.add_argument("--config", type=Path, help="perception YAML: synthetic camera and mount geometry")
    render.add_argument("--views", type=cli_number(int, lo=1), default=15)
    render.add_argument("--pan", type=float, default=0.0, help="servo pan during the dataset, rad")
    render.add_argument("--tilt", type=float, default=0.0, help="servo tilt during the dataset, rad")
    render.add_argument("--robot-noise", type=float, nargs=2, default=(0.0002, 0.0005), metavar=("M", "RAD"))
    render.add_argument("--seed", type=int, default=0)
    _target_arguments(render)
    render.set_defaults(func=_render)

    intrinsics = commands.add_parser("intrinsics", help="camera matrix and distortion from target images")
    source = intrinsics.add_mutually_exclusive_group(required=True)
    source.add_argument("--images", type=Path, help="folder of images of the target")
    source.add_argument("--device", type=int, help="capture live from this camera index")
    intrinsics.add_argument("--size", type=int, nargs=2, default=(640, 480), metavar=("W", "H"), help="live only")
    intrinsics.add_argument("--views", type=cli_number(int, lo=1), default=20, help="views to capture live")
    intrinsics.add_argument("--timeout", type=float, default=120.0, help="s to wait for live views")
    intrinsics.add_argument("--out", type=Path, required=True)
    _target_arguments(intrinsics)
    intrinsics.set_defaults(func=_intrinsics)

    handeye = commands.add_parser("handeye", help="eye-in-hand T_tcp_camera from robot poses and target images")
    handeye.add_argument("dataset", type=Path, help="folder with poses.yaml (pan, tilt, views: image + tcp_pose)")
    handeye.add_argument("--intrinsics", type=Path, required=True)
    handeye.add_argument("--config", type=Path, help="perception YAML whose mount geometry derives T_tilt_camera")
    handeye.add_argument("--method", choices=sorted(HANDEYE_METHODS), default="tsai")
    handeye.add_argument("--out", type=Path, required=True)
    _target_arguments(handeye)
    handeye.set_defaults(func=_handeye)


def _target_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = TargetSpec()
    parser.add_argument("--target", choices=("charuco", "chessboard"), default=defaults.kind)
    parser.add_argument(
        "--squares", type=int, nargs=2, default=(defaults.squares_x, defaults.squares_y), metavar=("X", "Y")
    )
    parser.add_argument("--square", type=float, default=defaults.square, help="square side, m")
    parser.add_argument("--marker", type=float, default=defaults.marker, help="ChArUco marker side, m")
    parser.add_argument("--dictionary", default=defaults.dictionary)


def _target(args: argparse.Namespace) -> TargetSpec:
    # Through the loader, so that the options get the checks the same settings get in a YAML file.
    return from_dict({"kind": args.target, "squares_x": args.squares[0], "squares_y": args.squares[1],
                      "square": args.square, "marker": args.marker, "dictionary": args.dictionary},
                     TargetSpec, source="command line")


def _refuse(reason: str) -> int:
    print(f"calibration refused: {reason}", file=sys.stderr)
    return _FAILED


def _perception_config(path: Path | None) -> PerceptionConfig:
    return PerceptionConfig() if path is None else load(path, PerceptionConfig)


def _read_grey(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise CalibrationError(f"{path}: not an image OpenCV can read")
    return image


# ---------------------------------------------------------------------------------------------------------


def _render(args: argparse.Namespace) -> int:
    try:
        config = _perception_config(args.config)
    except ConfigError as exc:
        return _refuse(str(exc))
    camera = config.camera
    if not isinstance(camera, SyntheticCameraConfig):
        return _refuse(f"{args.config}: render needs a synthetic camera (camera.kind: synthetic)")
    target = _target(args)
    if target.kind != "charuco":
        return _refuse("render draws ChArUco boards only")
    tcp_camera = CameraChain(config.geometry).tcp_camera(args.pan, args.tilt)
    rng = np.random.default_rng(args.seed)
    views, t_base_board = render_board_views(
        target.charuco_board(), camera, tcp_camera, args.views, rng, tuple(args.robot_noise)
    )
    args.out.mkdir(parents=True, exist_ok=True)
    entries = []
    for i, view in enumerate(views):
        name = f"view_{i:03d}.png"
        cv2.imwrite(str(args.out / name), view.image)
        entries.append(poses_file_entry(name, view.t_base_tcp))
    poses = {"pan": args.pan, "tilt": args.tilt, "units": "m, rad; tcp_pose is [x,y,z,rx,ry,rz]", "views": entries}
    (args.out / "poses.yaml").write_text(yaml.safe_dump(poses, sort_keys=False), encoding="utf-8")
    truth = {
        "camera": to_dict(camera),
        "tcp_camera": matrix_to_pose(tcp_camera).tolist(),
        "base_board": matrix_to_pose(t_base_board).tolist(),
        "target": to_dict(target),
    }
    (args.out / "truth.yaml").write_text(yaml.safe_dump(truth, sort_keys=False), encoding="utf-8")
    print(f"wrote {len(views)} views of a {target.describe()} to {args.out} (fx {camera.fx:g} px)")
    return 0


def _intrinsics(args: argparse.Namespace) -> int:
    target = _target(args)
    finder = TargetFinder(target)
    try:
        if args.images is not None:
            views, image_size, total = _views_from_folder(args.images, finder)
        else:
            views, image_size, total = _views_live(args, finder)
        result = calibrate_intrinsics(views, image_size, target, total)
    except (CalibrationError, CameraError) as exc:
        return _refuse(str(exc))
    calibration = result.calibration
    save_calibration(args.out, calibration)
    k = calibration.matrix()
    print(
        f"{calibration.views} views, {image_size[0]}×{image_size[1]}: RMS reprojection error {calibration.rms_px:.3f} px"
    )
    print(
        f"fx {k[0, 0]:.2f}  fy {k[1, 1]:.2f}  cx {k[0, 2]:.2f}  cy {k[1, 2]:.2f} px; worst view {max(result.view_errors):.3f} px"
    )
    print(f"saved to {args.out}")
    return 0


def _views_from_folder(folder: Path, finder: TargetFinder) -> tuple[list, tuple[int, int], int]:
    if not folder.is_dir():
        raise CalibrationError(f"{folder}: no such folder")
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in _IMAGE_SUFFIXES)
    if not paths:
        raise CalibrationError(f"{folder}: no images ({', '.join(sorted(_IMAGE_SUFFIXES))})")
    views, sizes = [], set()
    for path in paths:
        grey = _read_grey(path)
        sizes.add((grey.shape[1], grey.shape[0]))
        found = finder.find(grey)
        if found is not None:
            views.append(found)
    if len(sizes) > 1:
        raise CalibrationError(f"{folder}: images of different sizes {sorted(sizes)}; a calibration is for one size")
    return views, sizes.pop(), len(paths)


def _views_live(args: argparse.Namespace, finder: TargetFinder) -> tuple[list, tuple[int, int], int]:
    """Keep a view whenever the target is found and has moved since the last kept view."""
    width, height = args.size
    views: list = []
    last_centre: np.ndarray | None = None
    grabbed = 0
    with DeviceCamera(DeviceCameraConfig(index=args.device, width=width, height=height)) as camera:
        deadline = time.monotonic() + args.timeout
        print(f"move the target in front of the camera; {args.views} views wanted", file=sys.stderr)
        while len(views) < args.views and time.monotonic() < deadline:
            frame = camera.read()
            grabbed += 1
            grey = cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY) if frame.image.ndim == 3 else frame.image
            found = finder.find(grey)
            if found is None:
                continue
            centre = found[1].mean(axis=0)
            if last_centre is None or np.linalg.norm(centre - last_centre) > 0.1 * width:
                views.append(found)
                last_centre = centre
                print(f"view {len(views)}/{args.views}", file=sys.stderr)
    if len(views) < MIN_INTRINSICS_VIEWS:
        raise CalibrationError(f"only {len(views)} distinct views in {args.timeout:g} s ({grabbed} frames)")
    return views, (width, height), grabbed


def _handeye(args: argparse.Namespace) -> int:
    target = _target(args)
    finder = TargetFinder(target)
    try:
        config = _perception_config(args.config)
        poses, pan, tilt = read_poses_file(args.dataset / "poses.yaml")
        first = _read_grey(poses[0][0]) if poses else None
        image_size = None if first is None else (first.shape[1], first.shape[0])
        intrinsics = load_intrinsics(args.intrinsics, image_size)
        robot, observed, skipped = [], [], []
        for path, t_base_tcp in poses:
            found = finder.find(_read_grey(path))
            if found is None:
                skipped.append(path.name)
                continue
            robot.append(t_base_tcp)
            observed.append(target_pose(*found, intrinsics.matrix(), intrinsics.distortion()))
        result = calibrate_handeye(robot, observed, args.method)
    except (CalibrationError, ConfigError) as exc:
        return _refuse(str(exc))
    t_tilt_camera = CameraChain(config.geometry).tilt_camera_from_tcp_camera(result.t_tcp_camera, pan, tilt)
    save_calibration(args.out, handeye_calibration(result, pan, tilt, t_tilt_camera, intrinsics.image_size, len(robot)))
    pose = matrix_to_pose(result.t_tcp_camera)
    print(
        f"{len(robot)} poses ({len(skipped)} images without the target{': ' + ', '.join(skipped) if skipped else ''})"
    )
    if len(robot) < RECOMMENDED_HANDEYE_POSES:
        print(f"warning: fewer than {RECOMMENDED_HANDEYE_POSES} poses; expect a less accurate result", file=sys.stderr)
    print(f"T_tcp_camera [x y z rx ry rz] = {np.array2string(pose, precision=5)} ({result.method})")
    print(
        f"target spread in the base frame: {result.residual_translation * 1000:.2f} mm, "
        f"{math.degrees(result.residual_rotation):.3f}° RMS; saved to {args.out}"
    )
    return 0
