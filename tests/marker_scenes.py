"""An independent renderer of ArUco marker scenes with exact ground truth, for accuracy tests and benchmarks.

Deliberately shares no code with ``iorthand_edge.perception.synthetic`` (the camera the pipeline is developed
against) so that a bias of one cannot hide in the other. It differs from it in how it forms the image:

- **Ray casting, not texture warping.** Each pixel is split into ``supersample``² sub-pixels; each sub-pixel's
  ray is intersected with the marker plane and the printed pattern (black border, data cells, white paper) is
  looked up exactly at that point, so a pixel's value is its true area coverage (a box filter over the pixel),
  with no texture interpolation. Pixel centres are at integer coordinates (OpenCV's convention).
- **Lens distortion** (OpenCV's k1 k2 p1 p2 k3 model, written out here) is inverted by Newton's method on the
  pixel-corner grid; sub-pixels interpolate that grid (the distortion is smooth, so the error is far below
  1e-4 px).
- **Light and sensor in linear units**: paper and ink reflectances, a skin-coloured textured background, an
  illumination gradient with vignetting; then an optical blur, photon (shot) and read noise, an optional tone
  curve, 8-bit quantisation and JPEG compression.

:func:`make_track` draws a scene: a marker fixed in the robot base frame, a camera that drifts slowly around
it at 0.20–0.35 m with 0–50° between its line of sight and the marker's normal, and one frame per camera pose.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

Matrix = NDArray[np.float64]

ROOT = Path(__file__).resolve().parents[1]
INTRINSICS_FILE = ROOT / "configs" / "calibration" / "intrinsics-640x480.yaml"

PAPER = 0.85  # reflectance of the white paper around and inside the marker
INK = 0.05  # reflectance of the printed black


# ---------------------------------------------------------------------------------------------------------
# Small rigid-transform helpers (own code: this module must not lean on the code it checks).


def rotation(axis: NDArray[np.float64], angle: float) -> Matrix:
    """Rodrigues' formula."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def rigid(r: Matrix, t: NDArray[np.float64]) -> Matrix:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = r, t
    return out


def inverse(t: Matrix) -> Matrix:
    r = t[:3, :3]
    return rigid(r.T, -r.T @ t[:3, 3])


def angle_between(r_a: Matrix, r_b: Matrix) -> float:
    """rad between two rotations; the arccos form is inaccurate below ~1e-4 rad, so the chord is used."""
    chord = np.linalg.norm(r_a[:3, :3] - r_b[:3, :3]) / math.sqrt(8.0)
    return 2.0 * math.asin(min(1.0, chord))


def looking_at(eye: NDArray[np.float64], target: NDArray[np.float64], roll: float) -> Matrix:
    """T_world_camera of an OpenCV camera (x right, y down, z forward) at ``eye`` aimed at ``target``."""
    z = target - eye
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.95 else np.array([1.0, 0.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return rigid(np.column_stack([x, y, z]) @ rotation(np.array([0.0, 0.0, 1.0]), roll), eye)


# ---------------------------------------------------------------------------------------------------------
# The lens


@dataclass
class Lens:
    """Pinhole camera with OpenCV's radial/tangential distortion (k1, k2, p1, p2, k3)."""

    k: NDArray[np.float64]
    dist: NDArray[np.float64]
    size: tuple[int, int]  # (width, height), px

    @classmethod
    def from_file(cls, path: Path = INTRINSICS_FILE) -> Lens:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
        return cls(np.array(data["camera_matrix"], float), np.array(data["dist_coeffs"], float).reshape(-1)[:5],
                   (int(data["image_width"]), int(data["image_height"])))

    def distort(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
        """Normalised ideal coordinates → normalised distorted coordinates."""
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return xd, yd

    def project(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """N×3 camera-frame points → N×2 pixels."""
        x, y = points[:, 0] / points[:, 2], points[:, 1] / points[:, 2]
        xd, yd = self.distort(x, y)
        k = self.k
        return np.column_stack([k[0, 0] * xd + k[0, 1] * yd + k[0, 2], k[1, 1] * yd + k[1, 2]])

    def rays(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
        """Pixels → normalised ideal coordinates (x, y) of their rays (x, y, 1), by Newton's method."""
        k = self.k
        yd = (v - k[1, 2]) / k[1, 1]
        xd = (u - k[0, 2] - k[0, 1] * yd) / k[0, 0]
        x, y = xd.copy(), yd.copy()
        step = 1e-7
        for _ in range(20):
            fx, fy = self.distort(x, y)
            ex, ey = fx - xd, fy - yd
            # Jacobian by central differences: the model is smooth and this keeps the code short.
            ax, ay = self.distort(x + step, y)
            bx, by = self.distort(x - step, y)
            cx_, cy_ = self.distort(x, y + step)
            dx_, dy_ = self.distort(x, y - step)
            j11, j21 = (ax - bx) / (2 * step), (ay - by) / (2 * step)
            j12, j22 = (cx_ - dx_) / (2 * step), (cy_ - dy_) / (2 * step)
            det = j11 * j22 - j12 * j21
            x -= (j22 * ex - j12 * ey) / det
            y -= (-j21 * ex + j11 * ey) / det
            if max(float(np.max(np.abs(ex), initial=0.0)), float(np.max(np.abs(ey), initial=0.0))) < 1e-13:
                break
        return x, y


# ---------------------------------------------------------------------------------------------------------
# The printed marker


@dataclass
class PrintedMarker:
    """A marker of side ``size`` (the black square, m) on white paper that extends ``margin`` m beyond it."""

    marker_id: int
    size: float
    margin: float
    bits: NDArray[np.bool_]  # (cells × cells), True = black, border included; row 0 is the marker's top

    @classmethod
    def make(cls, dictionary: cv2.aruco.Dictionary, marker_id: int, size: float, margin_cells: float) -> PrintedMarker:
        cells = dictionary.markerSize + 2
        image = dictionary.generateImageMarker(marker_id, cells)  # one pixel per cell
        return cls(marker_id, size, margin_cells * size / cells, image < 128)

    @property
    def cell(self) -> float:
        return self.size / self.bits.shape[0]

    def reflectance(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        """Reflectance at marker-frame points (x right, y up, m); NaN off the paper."""
        half = self.size / 2.0
        n = self.bits.shape[0]
        col = np.floor((x + half) / self.cell).astype(np.int64)
        row = np.floor((half - y) / self.cell).astype(np.int64)
        inside = (col >= 0) & (col < n) & (row >= 0) & (row < n)
        black = np.zeros(x.shape, dtype=bool)
        black[inside] = self.bits[row[inside], col[inside]]
        out = np.where(black, INK, PAPER)
        paper = (np.abs(x) <= half + self.margin) & (np.abs(y) <= half + self.margin)
        return np.where(paper, out, np.nan)


# ---------------------------------------------------------------------------------------------------------
# Image formation


@dataclass
class Nuisance:
    """What degrades one frame. Values are drawn per track by :func:`make_track`."""

    light: float = 0.8  # irradiance at the image centre, as a fraction of the sensor's full scale on PAPER
    gradient: tuple[float, float] = (0.0, 0.0)  # relative change of irradiance per 640 px in u and v
    vignetting: float = 0.15  # relative loss at the image corner
    blur_sigma: float = 0.6  # px, Gaussian point-spread function
    full_well: float = 4000.0  # electrons at full scale: shot noise σ = sqrt(electrons)
    read_noise: float = 3.0  # electrons
    gamma: float = 1.0  # output = linear^(1/gamma); 1 = a linear sensor output
    jpeg_quality: int = 85  # 0 = no compression


def _background(size: tuple[int, int], rng: np.random.Generator) -> NDArray[np.float64]:
    """A skin-like reflectance field: mid-grey with smooth blotches, varying slowly (no edges to confuse)."""
    width, height = size
    coarse = rng.normal(0.0, 1.0, (height // 32 + 2, width // 32 + 2))
    field_ = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    field_ = cv2.GaussianBlur(field_, (0, 0), 12.0)
    field_ /= max(float(np.std(field_)), 1e-9)
    return np.clip(0.45 + 0.05 * field_, 0.2, 0.7)


def render_frame(
    lens: Lens,
    markers: list[tuple[PrintedMarker, Matrix]],
    nuisance: Nuisance,
    rng: np.random.Generator,
    background: NDArray[np.float64] | None = None,
    supersample: int = 8,
) -> NDArray[np.uint8]:
    """An 8-bit grey image of the printed markers at their T_camera_marker poses."""
    width, height = lens.size
    reflect = _background(lens.size, rng) if background is None else background.copy()
    for marker, t_camera_marker in markers:
        _paint_marker(reflect, lens, marker, t_camera_marker, supersample)
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    du, dv = (u - (width - 1) / 2) / 640.0, (v - (height - 1) / 2) / 640.0
    r2 = (du * du + dv * dv) / (0.25 * (width * width + height * height) / 640.0**2)
    light = nuisance.light * (1.0 + nuisance.gradient[0] * du + nuisance.gradient[1] * dv) * (1.0 - nuisance.vignetting * r2)
    linear = reflect / PAPER * light  # fraction of full scale
    if nuisance.blur_sigma > 0:
        linear = cv2.GaussianBlur(linear, (0, 0), nuisance.blur_sigma)
    electrons = np.clip(linear, 0.0, None) * nuisance.full_well
    electrons = rng.poisson(electrons).astype(float) + rng.normal(0.0, nuisance.read_noise, electrons.shape)
    signal = np.clip(electrons / nuisance.full_well, 0.0, 1.0) ** (1.0 / nuisance.gamma)
    image = np.clip(np.rint(signal * 255.0), 0, 255).astype(np.uint8)
    if nuisance.jpeg_quality > 0:
        ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, nuisance.jpeg_quality])
        assert ok
        image = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
    return image


def _paint_marker(
    reflect: NDArray[np.float64], lens: Lens, marker: PrintedMarker, t_camera_marker: Matrix, s: int
) -> None:
    """Overwrite ``reflect`` with the area-averaged reflectance of the marker's paper where it covers pixels."""
    height, width = reflect.shape
    half = marker.size / 2.0 + marker.margin
    outline = np.array([[-half, half, 0.0], [half, half, 0.0], [half, -half, 0.0], [-half, -half, 0.0]])
    camera_points = (t_camera_marker[:3, :3] @ outline.T).T + t_camera_marker[:3, 3]
    if np.any(camera_points[:, 2] <= 0.01):
        return
    # Sample the outline densely: with distortion its image is slightly curved.
    steps = np.linspace(0.0, 1.0, 9)[:, None]
    dense = np.concatenate([a + (b - a) * steps for a, b in zip(camera_points, np.roll(camera_points, -1, axis=0), strict=True)])
    pixels = lens.project(dense)
    u0, v0 = (int(max(0, math.floor(c) - 2)) for c in pixels.min(axis=0))
    u1, v1 = (int(min(lim, math.ceil(c) + 3)) for c, lim in zip(pixels.max(axis=0), (width, height), strict=True))
    if u1 <= u0 or v1 <= v0:
        return
    # Rays through the pixel corners (u - 0.5, v - 0.5) of the region, exact; sub-pixels interpolate them.
    cu, cv_ = np.meshgrid(np.arange(u0, u1 + 1) - 0.5, np.arange(v0, v1 + 1) - 0.5)
    rx, ry = lens.rays(cu.ravel(), cv_.ravel())
    rx, ry = rx.reshape(cu.shape), ry.reshape(cu.shape)
    f = (np.arange(s) + 0.5) / s  # sub-pixel positions inside a pixel
    a = f[None, :, None, None]  # along v
    b = f[None, None, None, :]  # along u
    def corners(grid: NDArray[np.float64]) -> NDArray[np.float64]:
        g00, g01 = grid[:-1, :-1][:, None, :, None], grid[:-1, 1:][:, None, :, None]
        g10, g11 = grid[1:, :-1][:, None, :, None], grid[1:, 1:][:, None, :, None]
        return (1 - a) * ((1 - b) * g00 + b * g01) + a * ((1 - b) * g10 + b * g11)
    sx, sy = corners(rx), corners(ry)  # shape (rows, s, cols, s)
    # Ray (sx, sy, 1)·λ meets the plane n·(p − t) = 0.
    r, t = t_camera_marker[:3, :3], t_camera_marker[:3, 3]
    n = r[:, 2]
    denom = n[0] * sx + n[1] * sy + n[2]
    lam = float(n @ t) / denom
    px, py, pz = lam * sx - t[0], lam * sy - t[1], lam - t[2]
    mx = r[0, 0] * px + r[1, 0] * py + r[2, 0] * pz
    my = r[0, 1] * px + r[1, 1] * py + r[2, 1] * pz
    value = marker.reflectance(mx, my)
    value = np.where(lam > 0, value, np.nan)
    region = reflect[v0:v1, u0:u1]
    under = np.broadcast_to(region[:, None, :, None], value.shape)
    covered = np.where(np.isnan(value), under, value)
    region[:] = covered.mean(axis=(1, 3))


# ---------------------------------------------------------------------------------------------------------
# Scenes: a marker fixed in the base frame, a camera drifting around it


@dataclass
class Frame:
    image: NDArray[np.uint8]
    t_base_camera: Matrix  # ground truth
    t_camera_marker: Matrix  # ground truth


@dataclass
class Track:
    """Frames of one marker seen by a slowly moving camera."""

    marker: PrintedMarker
    t_base_marker: Matrix
    frames: list[Frame] = field(default_factory=list)
    distance: float = 0.0  # m, camera to marker centre at the start
    tilt: float = 0.0  # rad between the line of sight and the marker normal at the start
    normal_offset: float = 0.0  # rad between the marker's normal and the expected one (the base z axis)
    nuisance: Nuisance = field(default_factory=Nuisance)


def draw_nuisance(rng: np.random.Generator) -> Nuisance:
    return Nuisance(
        light=float(rng.uniform(0.45, 0.95)),
        gradient=(float(rng.uniform(-0.4, 0.4)), float(rng.uniform(-0.4, 0.4))),
        vignetting=float(rng.uniform(0.05, 0.3)),
        blur_sigma=float(rng.uniform(0.45, 0.9)),
        full_well=float(rng.uniform(2500.0, 8000.0)),
        read_noise=float(rng.uniform(2.0, 6.0)),
        jpeg_quality=int(rng.integers(75, 96)),
    )


def make_track(
    rng: np.random.Generator,
    lens: Lens,
    dictionary: cv2.aruco.Dictionary,
    *,
    distance: tuple[float, float] = (0.20, 0.35),
    tilt: tuple[float, float] = (0.0, math.radians(50.0)),
    normal_offset: float = math.radians(10.0),
    size: float = 0.03,
    frames: int = 24,
    fps: float = 15.0,
    speed: float = 0.008,
    turn_rate: float = math.radians(2.0),
    marker_id: int | None = None,
    nuisance: Nuisance | None = None,
    supersample: int = 8,
) -> Track:
    """A track of ``frames`` frames at ``fps``: the camera moves at ``speed`` m/s and turns at ``turn_rate``
    rad/s. The marker's normal is off the base z axis (the configured expected normal) by up to
    ``normal_offset`` (a curved body); the marker stays inside the image with a margin."""
    marker = PrintedMarker.make(
        dictionary, int(rng.integers(0, 50)) if marker_id is None else marker_id, size, float(rng.uniform(0.75, 1.5))
    )
    offset = float(rng.uniform(0.0, normal_offset))
    normal_axis = np.array([math.cos(a := rng.uniform(0, 2 * math.pi)), math.sin(a), 0.0])
    r_base_marker = rotation(normal_axis, offset) @ rotation(np.array([0.0, 0.0, 1.0]), float(rng.uniform(-math.pi, math.pi)))
    centre = np.array([0.35, -0.05, 0.12]) + rng.uniform(-0.03, 0.03, 3)
    t_base_marker = rigid(r_base_marker, centre)
    normal = r_base_marker[:, 2]
    chosen_distance = float(rng.uniform(*distance))
    chosen_tilt = float(rng.uniform(*tilt))
    # The camera on a cone of half-angle ``tilt`` around the marker's normal, at a random azimuth.
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    azimuth = float(rng.uniform(0, 2 * math.pi))
    sight = math.cos(chosen_tilt) * normal + math.sin(chosen_tilt) * (math.cos(azimuth) * e1 + math.sin(azimuth) * e2)
    eye = centre + chosen_distance * sight
    # Aim off the marker so that it lands anywhere in the central part of the image.
    aim = centre + rng.uniform(-0.25, 0.25, 3) * chosen_distance * np.array([0.6, 0.45, 0.0])
    roll = float(rng.uniform(-math.pi, math.pi))
    velocity = rng.normal(0.0, 1.0, 3)
    velocity *= speed / np.linalg.norm(velocity)
    spin = rng.normal(0.0, 1.0, 3)  # the axis the camera turns about
    start = looking_at(eye, aim, roll)
    background = _background(lens.size, rng)
    degrade = draw_nuisance(rng) if nuisance is None else nuisance
    track = Track(marker, t_base_marker, distance=chosen_distance, tilt=chosen_tilt, normal_offset=offset,
                  nuisance=degrade)
    for i in range(frames):
        dt = i / fps
        # Turning about its own centre at a constant rate, moving at a constant velocity: what a slow
        # teleoperated approach does over a second or two.
        t_base_camera = rigid(rotation(spin, turn_rate * dt) @ start[:3, :3], start[:3, 3] + velocity * dt)
        t_camera_marker = inverse(t_base_camera) @ t_base_marker
        image = render_frame(lens, [(marker, t_camera_marker)], degrade, rng, background, supersample)
        track.frames.append(Frame(image, t_base_camera, t_camera_marker))
    return track


def marker_corners(lens: Lens, marker: PrintedMarker, t_camera_marker: Matrix) -> NDArray[np.float64]:
    """Ground-truth pixel corners of the black square: top-left, top-right, bottom-right, bottom-left."""
    h = marker.size / 2.0
    square = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    return lens.project((t_camera_marker[:3, :3] @ square.T).T + t_camera_marker[:3, 3])


# ---------------------------------------------------------------------------------------------------------
# Running a pipeline on tracks and scoring it against the ground truth

FRAME_NS = 66_666_667  # 15 fps: the media process's rate on the Pi
T0_NS = 1_800_000_000_000_000_000


def pipeline_settings(size: float = 0.03) -> dict[str, object]:
    """Perception settings for these scenes: the calibrated 640×480 camera (a device that is never opened:
    frames are handed to ``process``), markers of ``size`` expected to face up (base +z), and a mount whose
    chain is the identity at servo angles (0, 0), so that the robot pose handed in is T_base_camera."""
    return {
        "camera": {"kind": "device", "width": 640, "height": 480},
        "intrinsics_file": str(INTRINSICS_FILE),
        "markers": {"default_size": size, "expected_normal": [0.0, 0.0, 1.0]},
    }


@dataclass
class FrameScore:
    distance: float  # m, true camera-to-marker distance
    detected: bool
    raw_mm: float = math.nan  # position error of the single-frame pose
    raw_deg: float = math.nan
    raw_range: float = math.nan  # signed range error, % of the distance (+: too far)
    filtered_mm: float = math.nan
    filtered_deg: float = math.nan
    filtered_range: float = math.nan
    cpu_ms: float = 0.0  # process CPU for the frame (all threads)
    wall_ms: float = 0.0
    stages_ms: dict[str, float] = field(default_factory=dict)  # the pipeline's own per-stage wall times


def score_pose(estimate_base: Matrix, frame: Frame, t_base_marker: Matrix) -> tuple[float, float, float]:
    """(position error mm, rotation error deg, signed range error %) of a T_base_marker estimate."""
    in_camera = inverse(frame.t_base_camera) @ estimate_base
    true_range = float(np.linalg.norm(frame.t_camera_marker[:3, 3]))
    return (
        float(np.linalg.norm(estimate_base[:3, 3] - t_base_marker[:3, 3])) * 1000.0,
        math.degrees(angle_between(estimate_base, t_base_marker)),
        (float(np.linalg.norm(in_camera[:3, 3])) / true_range - 1.0) * 100.0,
    )


def run_track(pipeline: Any, track: Track, robot: _Robot) -> list[FrameScore]:
    """Feed a track's frames to ``pipeline.process`` with the robot where the track's camera is, and score
    what it publishes for the track's marker."""
    from iorthand_edge.perception.camera import Frame as CameraFrame

    scores = []
    for i, frame in enumerate(track.frames):
        robot.move(frame.t_base_camera)
        cpu, wall = time.process_time(), time.perf_counter()
        message = pipeline.process(CameraFrame(frame.image, T0_NS + i * FRAME_NS, i))
        score = FrameScore(float(np.linalg.norm(frame.t_camera_marker[:3, 3])), False,
                           cpu_ms=(time.process_time() - cpu) * 1e3, wall_ms=(time.perf_counter() - wall) * 1e3,
                           stages_ms=dict(vars(pipeline.stats.stages)))
        for marker in message.markers:
            if marker.id != track.marker.marker_id:
                continue
            score.detected = True
            score.raw_mm, score.raw_deg, score.raw_range = score_pose(
                np.asarray(marker.raw, float).reshape(4, 4), frame, track.t_base_marker)
            score.filtered_mm, score.filtered_deg, score.filtered_range = score_pose(
                np.asarray(marker.pose, float).reshape(4, 4), frame, track.t_base_marker)
        scores.append(score)
    return scores


class _Robot:
    """The robot pose the pipeline asks for: where the track's camera is for the frame being processed."""

    def __init__(self) -> None:
        self.pose = np.eye(4)

    def move(self, pose: Matrix) -> None:
        self.pose = pose

    def pose_at(self, _t_ns: int) -> Matrix:
        return self.pose


def evaluate_tracks(tracks: list[Track], settings: dict[str, object] | None = None) -> list[list[FrameScore]]:
    """A fresh pipeline per track (as when a marker comes into view), scored frame by frame."""
    from iorthand.config import from_dict
    from iorthand_edge.perception.config import PerceptionConfig
    from iorthand_edge.perception.pipeline import PerceptionPipeline

    config = from_dict(settings or pipeline_settings(), PerceptionConfig)
    results = []
    for track in tracks:
        robot = _Robot()
        pipeline = PerceptionPipeline(config, robot.pose_at, lambda _t: (0.0, 0.0), lambda _m: None)
        results.append(run_track(pipeline, track, robot))
    return results


def _percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else math.nan


def summarize(results: list[list[FrameScore]], warmup: int) -> dict[str, object]:
    """Error statistics of tracks scored by :func:`run_track`. "filtered" counts a track's frames from the
    ``warmup``-th on (the filter's window full); the range bias's 95 % interval is over track means."""
    frames = [s for track in results for s in track]
    out: dict[str, object] = {
        "tracks": len(results),
        "frames": len(frames),
        "distance_m": [round(min(s.distance for s in frames), 4), round(max(s.distance for s in frames), 4)],
        "detection_rate": sum(s.detected for s in frames) / max(1, len(frames)),
    }
    for kind, chosen in (("single_frame", [s for t in results for s in t]),
                         ("filtered", [s for t in results for s in t[warmup:]])):
        seen = [s for s in chosen if s.detected]
        mm = [getattr(s, f"{'raw' if kind == 'single_frame' else 'filtered'}_mm") for s in seen]
        deg = [getattr(s, f"{'raw' if kind == 'single_frame' else 'filtered'}_deg") for s in seen]
        prefix = "raw" if kind == "single_frame" else "filtered"
        track_bias = [float(np.mean(v)) for t in results
                      if (v := [getattr(s, f"{prefix}_range") for s in (t if kind == "single_frame" else t[warmup:])
                                if s.detected])]
        half = 1.96 * float(np.std(track_bias, ddof=1)) / math.sqrt(len(track_bias)) if len(track_bias) > 1 else math.nan
        bias = float(np.mean([getattr(s, f"{prefix}_range") for s in seen])) if seen else math.nan
        out[kind] = {
            "frames": len(seen),
            "position_mm": {"median": _percentile(mm, 50), "p99": _percentile(mm, 99), "max": max(mm, default=math.nan)},
            "range_bias_percent": {"mean": bias, "ci95": [bias - half, bias + half],
                                   "median": _percentile([getattr(s, f"{prefix}_range") for s in seen], 50)},
            "rotation_deg": {"p95": _percentile(deg, 95), "p99": _percentile(deg, 99), "max": max(deg, default=math.nan),
                             "over_1deg_fraction": sum(d > 1.0 for d in deg) / max(1, len(deg))},
        }
    cpu = [s.cpu_ms for s in frames]
    out["cpu_ms_per_frame"] = {"mean": float(np.mean(cpu)), "median": _percentile(cpu, 50), "p95": _percentile(cpu, 95)}
    wall = [s.wall_ms for s in frames]
    out["wall_ms_per_frame"] = {"median": _percentile(wall, 50), "p95": _percentile(wall, 95)}
    out["stage_ms_mean"] = {name: float(np.mean([s.stages_ms.get(name, 0.0) for s in frames]))
                            for name in frames[0].stages_ms} if frames else {}
    return out
