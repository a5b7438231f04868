"""ArUco detection, sub-pixel corners from the marker's outer edges, and per-marker pose (IPPE_SQUARE) with a
probabilistic choice between IPPE's two mirror solutions.

Why the corners are re-measured: OpenCV's corners (even with ``CORNER_REFINE_SUBPIX``) sit ~0.2 px inside the
black square on a blurred image: cornerSubPix looks at a few pixels around a rounded corner tip and the
ArUco detector shrinks its window on small markers. A quad that is too small by 0.2 px a side puts a 30 mm
marker 0.3–0.7 % too far (1–2 mm at 0.3 m), and ±0.1–0.2 px of corner noise becomes degrees of out-of-plane
rotation. :func:`refine_corners` instead measures the black square's four outer edges along their whole
length (the edge between the black border and the white paper is straight and uninterrupted), fits a
straight line to each in undistorted coordinates and intersects them: ~0.02 px, unbiased by a symmetric blur.
What moves every black/white edge alike (a camera's tone curve, sharpening) is measured on the marker's own
border and undone (:func:`_border_shift`), so no response curve has to be calibrated.

The maths (:func:`refine_corners`, :func:`ippe_weights`, :func:`choose_ippe_solution`,
:func:`marker_object_points`) is free of I/O. The code is written for both OpenCV 4.x (ids of shape (N, 1))
and 5.x (ids of shape (N,)).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from iorthand.geometry import Matrix, make_transform
from iorthand.stats import median

from .config import CORNER_REFINEMENTS, DetectorConfig


@dataclass
class Detection:
    id: int
    corners: NDArray[np.float64]  # 4×2 px: top-left, top-right, bottom-right, bottom-left of the marker
    # 1-σ error of one corner coordinate (px), from the scatter of the edge points; None: not edge-refined.
    corner_sigma: float | None = None


@dataclass
class MarkerPoseEstimate:
    t_camera_marker: Matrix
    reprojection_error: float  # RMS per coordinate, px, of the chosen IPPE solution
    pixel_size: float  # mean side length, px
    ambiguous: bool  # the corners alone could not tell the two mirror solutions apart (odds under 100:1)
    mirror_weight: float = 0.0  # posterior probability of the other IPPE solution, given corners and prior


def make_aruco_detector(config: DetectorConfig) -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = CORNER_REFINEMENTS[config.corner_refinement]
    params.cornerRefinementWinSize = config.corner_refinement_window
    params.adaptiveThreshWinSizeMin = config.adaptive_window_min
    params.adaptiveThreshWinSizeMax = config.adaptive_window_max
    params.adaptiveThreshWinSizeStep = config.adaptive_window_step
    params.minMarkerPerimeterRate = config.min_marker_perimeter_rate
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, config.dictionary))
    return cv2.aruco.ArucoDetector(dictionary, params)


def detect_markers(detector: cv2.aruco.ArucoDetector, gray: np.ndarray) -> list[Detection]:
    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None or len(ids) == 0:
        return []
    # reshape(-1) accepts (N,) from OpenCV 5 as well as (N, 1) from 4.x; corners likewise (1, 4, 2) or (4, 2).
    return [
        Detection(int(i), np.asarray(c, dtype=np.float64).reshape(4, 2))
        for i, c in zip(np.asarray(ids).reshape(-1), corners, strict=True)
    ]


# ---------------------------------------------------------------------------------------------------------
# Corners from the outer edges


@dataclass
class EdgeFit:
    corners: NDArray[np.float64]  # 4×2 px, same order as the detector's
    corner_sigma: float  # px, 1-σ per coordinate, estimated from the edge points' scatter about their lines
    points: int  # edge points that made the four lines
    edge_shift: float = 0.0  # px the lines were moved outwards by the border measurement (0: not measured)


_PROFILE_STEP = 0.25  # px between samples across an edge: fine enough that the trapezoid sum is exact to ~1e-3 px
_MIN_POINTS_PER_SIDE = 4
_MIN_CONTRAST = 8.0  # grey levels between the paper and the black border below which a profile is noise
# Edge points are ~1 px apart but a blurred image correlates neighbours: count them as a third as many
# independent ones when turning their scatter into a corner's uncertainty (then the RMS of corner error / σ is
# ~1.1 on the benchmark's scenes; 1.3 when counted as half).
_CORRELATED_POINTS = 3.0
_MAD_TO_SIGMA = 1.4826  # median absolute deviation → σ of a normal distribution
_SIGMA_FLOOR = 0.005  # px: no corner is trusted beyond this (interpolation and model errors)
_PROFILES_PER_SIDE = 64  # beyond ~1 a pixel they are correlated: 64 covers a side of 80 px, more buys little
_PLATEAU_SIGMAS = 4.0  # half a profile's length in blur σ: both plateaus reached, tails cut at 4σ
_PASSES = 2  # the second pass centres the profiles on the first's lines: one pass leaves a −0.005 px shrink
_UNDISTORT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-10)
# The next and the previous of a quad's four corners or sides, as indices (np.roll costs ~30 µs a call).
_NEXT = np.array([1, 2, 3, 0])
_PREVIOUS = np.array([3, 0, 1, 2])


def refine_corners(
    gray: NDArray[np.uint8],
    corners: NDArray[np.float64],
    camera_matrix: NDArray[np.float64],
    dist_coeffs: NDArray[np.float64],
    cells: int,
    config: DetectorConfig,
    bits: NDArray[np.bool_] | None = None,
) -> EdgeFit | None:
    """The four corners as the intersections of lines fitted to the black square's outer edges.

    Each side is probed by profiles across it, about one per pixel along the side, leaving out its ends
    (where the blurred corner tip bends the edge). On a profile the edge is placed where the area between the
    profile and its dark plateau equals the area of an ideal step between the dark and light plateaus: a
    symmetric blur moves light across the edge without changing that area, so the estimate is unbiased by
    blur, and it integrates the noise. The edge points are undistorted (a straight edge is straight only
    there), a line is fitted to each side by total least squares with a 3-MAD outlier cut, and adjacent lines
    are intersected. Two passes: the second centres the profiles on the first pass's lines. The four sides
    are processed together as arrays: per-side Python loops cost ~1 ms a marker, most of the refinement.

    With the marker's ``bits`` (cells × cells, True = black, as printed) and ``config.border_calibration``,
    the lines are then moved by the edge shift measured on the marker itself (:func:`_border_shift`): what
    a tone curve, sharpening or a lopsided blur does to every black/white edge.

    Returns None when an edge cannot be measured (too small, too little contrast, occluded) or when the
    result moved a corner further than ``config.edge_max_shift`` from the detector's (a wrong fit).
    """
    start = np.asarray(corners, dtype=np.float64).reshape(4, 2)
    sides = np.linalg.norm(start[_NEXT] - start, axis=1)
    # A profile must stay inside the one-cell black border on the inside and inside the paper's white margin
    # (assumed at least a cell too) on the outside.
    widest = min(config.edge_band, 0.6 * float(sides.min()) / cells)
    if widest < 1.0:
        return None
    half_width = widest
    x0, y0 = np.floor(start.min(axis=0) - widest - 3).astype(int)
    x1, y1 = np.ceil(start.max(axis=0) + widest + 4).astype(int)
    height, width = gray.shape[:2]
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return None
    roi = gray[y0:y1, x0:x1].astype(np.float32)
    origin = np.array([x0, y0], dtype=np.float64)
    fx = float(camera_matrix[0, 0])

    current = start
    for attempt in range(_PASSES):
        # The first pass only centres the profiles and measures the blur for the last: a third of the profiles.
        most = _PROFILES_PER_SIDE if attempt == _PASSES - 1 else _PROFILES_PER_SIDE // 3
        measured = _edge_points(roi, current - origin, _offsets(half_width), most)
        if measured is None:
            return None
        points, valid, blur = measured
        # The next pass (and the border) with profiles just long enough to reach both plateaus of edges this
        # blurred: longer ones add noise (the plateaus' noise is integrated too), shorter ones cut the
        # edge's tails and bias it (3 px at a blur σ of 1.3 px: −0.02 px).
        half_width = float(np.clip(_PLATEAU_SIGMAS * blur, 1.0, widest))
        undistorted = cv2.undistortPointsIter(
            (points + origin).reshape(-1, 1, 2), camera_matrix, dist_coeffs, None, None, _UNDISTORT
        ).reshape(points.shape)
        fitted = _fit_lines(undistorted, valid)
        if fitted is None:
            return None
        lines, residual_rms, used = fitted
        normalised = _intersections(lines)
        if normalised is None:
            return None
        current = _distort(normalised, camera_matrix, dist_coeffs)
    shift = 0.0
    if bits is not None and config.border_calibration:
        measured_shift = _border_shift(roi, origin, normalised, bits, camera_matrix, dist_coeffs, half_width)
        if measured_shift is not None:
            shift = measured_shift
            # Each line moves outwards (away from the quad's centre) by the shift, in normalised units.
            centre = normalised.mean(axis=0)
            side_of_centre = np.sign(lines[:, 0] * centre[0] + lines[:, 1] * centre[1] + lines[:, 2])
            focal = 0.5 * float(camera_matrix[0, 0] + camera_matrix[1, 1])
            lines = lines + np.column_stack([np.zeros((4, 2)), side_of_centre * shift / focal])
            normalised = _intersections(lines)
            if normalised is None:
                return None
            current = _distort(normalised, camera_matrix, dist_coeffs)
    if float(np.max(np.linalg.norm(current - start, axis=1))) > config.edge_max_shift:
        return None
    # σ of a line's offset where it meets its neighbours (its ends, half a side from its centroid) is about
    # twice that of its centroid: 1/n + (L/2)²/(n·L²/12) = 4/n for points spread evenly along the side.
    line_sigma = residual_rms * fx * np.sqrt(4.0 * _CORRELATED_POINTS / used)
    sigma = max(_SIGMA_FLOOR, float(np.sqrt(np.mean(np.square(line_sigma)))))
    return EdgeFit(current, sigma, int(used.sum()), shift)


def _intersections(lines: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """Corner i where side i−1 meets side i, in the lines' (normalised) coordinates; None if two are parallel."""
    h = _cross(lines[_PREVIOUS], lines)
    if (np.abs(h[:, 2]) < 1e-12).any():
        return None
    return h[:, :2] / h[:, 2:3]


def _distort(normalised: NDArray[np.float64], camera_matrix: NDArray[np.float64], dist_coeffs: NDArray[np.float64]
             ) -> NDArray[np.float64]:
    """Undistorted normalised image coordinates → pixels."""
    points = np.column_stack([normalised, np.ones(len(normalised))])
    projected, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), camera_matrix, dist_coeffs)
    return projected.reshape(-1, 2)


def _homography(source: NDArray[np.float64], target: NDArray[np.float64]) -> NDArray[np.float64]:
    """The 3×3 homography taking four source points to four target points (in float64: OpenCV's
    getPerspectiveTransform takes float32 points)."""
    (x, y), (u, v) = source.T, target.T
    system = np.zeros((8, 8))
    system[0::2, 0], system[0::2, 1], system[0::2, 2] = x, y, 1.0  # u = (h0·x + h1·y + h2) / (h6·x + h7·y + 1)
    system[1::2, 3], system[1::2, 4], system[1::2, 5] = x, y, 1.0  # v likewise with h3, h4, h5
    system[0::2, 6], system[0::2, 7] = -u * x, -u * y
    system[1::2, 6], system[1::2, 7] = -v * x, -v * y
    return np.append(np.linalg.solve(system, target.reshape(-1)), 1.0).reshape(3, 3)


_UNIT_SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])  # marker coordinates, x right, y down
_MIN_BORDER_PROFILES = 8
_MAX_BORDER_SHIFT = 0.6  # px: beyond this the border measurement is not measuring what it assumes
_INWARDS = np.array([[0.0, 1.0], [0.0, -1.0], [1.0, 0.0], [-1.0, 0.0]])  # into the marker from its top, bottom, left, right


def _border_shift(
    roi: NDArray[np.float32],
    origin: NDArray[np.float64],
    corners: NDArray[np.float64],
    bits: NDArray[np.bool_],
    camera_matrix: NDArray[np.float64],
    dist_coeffs: NDArray[np.float64],
    half_width: float,
) -> float | None:
    """How far (px) the measured outer edges sit inside the true ones, measured on the marker itself.

    The black border is exactly one cell wide. Wherever a white data cell touches it, the border's inner
    edge is a black/white edge like the outer one, facing the other way: whatever moves edges towards their
    dark side (a gamma-encoded image: ~0.2 px; sharpening, a lopsided blur) moves the outer edge inwards and
    the inner edge outwards by the same amount δ. Predicted from the measured quad, the inner edge then
    appears 2δ(1 − 1/cells) further out than measured, which gives δ without knowing the camera's tone curve.
    ``corners`` are the outer corners in undistorted normalised coordinates. None when too few white cells
    touch the border or the marker is too small to probe them.
    """
    cells = bits.shape[0]
    cell = 1.0 / cells
    to_image = _homography(_UNIT_SQUARE, corners)
    corners_px = _distort(corners, camera_matrix, dist_coeffs)
    side_px = float(np.mean(np.linalg.norm(corners_px[_NEXT] - corners_px, axis=1)))
    cell_px = side_px / cells
    # As wide as the outer profiles, so that the plateaus of both edges are cut alike, and inside the border
    # and the white cell.
    half_width = min(half_width, 0.6 * cell_px)
    if half_width < 1.0:
        return None
    probes = _border_probes(bits.tobytes(), cells, max(3, round(0.4 * cell_px)))
    if probes is None:
        return None
    # The probes and the points a little way into their cells, mapped onto the image together.
    h = probes @ to_image.T
    base, towards_cell = np.split(_distort(h[:, :2] / h[:, 2:3], camera_matrix, dist_coeffs), 2)
    directions = towards_cell - base
    directions /= np.linalg.norm(directions, axis=1)[:, None]  # dark (the border) at negative offsets
    edge, good, _ = _profile_edges(roi, base - origin, directions, _offsets(half_width), groups=1)
    if np.count_nonzero(good) < _MIN_BORDER_PROFILES:
        return None
    shift = -median(edge[good]) / (2.0 * (1.0 - cell))
    return shift if abs(shift) <= _MAX_BORDER_SHIFT else None


@lru_cache(maxsize=256)
def _border_probes(bits: bytes, cells: int, samples: int) -> NDArray[np.float64] | None:
    """Where :func:`_border_shift` probes a marker's border, in marker coordinates (homogeneous rows): points on
    the border's inner edge at the middle of each white cell touching it (``samples`` of them across its middle
    two fifths, clear of its neighbours along the edge, which may be black), then as many a tenth of a cell into
    those cells. A marker's pattern and its size in cells fix them: computed once per marker (and image size).
    None when no white cell touches the border."""
    pattern = np.frombuffer(bits, dtype=np.bool_).reshape(cells, cells)
    cell = 1.0 / cells
    spread = np.linspace(-0.2, 0.2, samples)
    ks = np.arange(1, cells - 1)
    across = (ks[:, None] + 0.5 + spread) * cell  # k × spread
    near, far = np.full_like(across, cell), np.full_like(across, 1.0 - cell)  # the top or left edge, the other
    # Per k and side (top, bottom, left, right: _INWARDS's order), the points and whether the cell there is white.
    xs = np.stack([across, across, near, far], axis=1)
    ys = np.stack([near, far, across, across], axis=1)
    white = ~np.stack([pattern[1, ks], pattern[cells - 2, ks], pattern[ks, 1], pattern[ks, cells - 2]], axis=1)
    if not white.any():
        return None
    on_edge = np.stack([xs[white], ys[white]], axis=-1).reshape(-1, 2)
    ahead = on_edge + 0.1 * cell * np.repeat(_INWARDS[np.nonzero(white)[1]], samples, axis=0)
    points = np.concatenate([on_edge, ahead])
    probes = np.column_stack([points, np.ones(len(points))])
    probes.flags.writeable = False  # shared by every call with the same marker
    return probes


def _offsets(half_width: float) -> NDArray[np.float64]:
    return np.arange(-half_width, half_width + 1e-9, _PROFILE_STEP)


def _edge_points(
    roi: NDArray[np.float32], quad: NDArray[np.float64], offsets: NDArray[np.float64], most: int
) -> tuple[NDArray[np.float64], NDArray[np.bool_], float] | None:
    """Sub-pixel edge points (4 sides × n × 2, ROI px) of the quad's sides, which of them are valid, and
    the edges' blur (px, the median σ of their gradient profiles)."""
    following = quad[_NEXT]
    sides = following - quad
    lengths = np.sqrt((sides * sides).sum(axis=1))
    along = sides / lengths[:, None]
    normals = np.column_stack([along[:, 1], -along[:, 0]])
    middles = (quad + following) / 2.0
    outwards = np.einsum("ij,ij->i", normals, middles - quad.sum(axis=0) / 4) > 0
    normals[~outwards] *= -1.0  # dark (the border) at negative offsets, light (the paper) at positive
    margins = np.maximum(2.5, 0.1 * lengths)  # the blurred corner tip and the neighbouring edge stay out
    count = min(most, round(float((lengths - 2.0 * margins).min())))  # about one a pixel
    if count < _MIN_POINTS_PER_SIDE:
        return None
    fractions = _spaced(count)
    t = margins[:, None] + fractions[None, :] * (lengths - 2.0 * margins)[:, None]  # 4 × n
    base = quad[:, None, :] + t[:, :, None] * along[:, None, :]  # 4 × n × 2
    directions = np.repeat(normals, count, axis=0)
    edge, good, spread = _profile_edges(roi, base.reshape(-1, 2), directions, offsets, groups=4)
    valid = good.reshape(4, count)
    if (valid.sum(axis=1) < _MIN_POINTS_PER_SIDE).any():
        return None
    points = base + np.where(valid, edge.reshape(4, count), 0.0)[:, :, None] * normals[:, None, :]
    return points, valid, median(spread[good])


def _profile_edges(
    roi: NDArray[np.float32],
    base: NDArray[np.float64],
    directions: NDArray[np.float64],
    offsets: NDArray[np.float64],
    groups: int,
) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64]]:
    """Edge offsets (px along ``directions``, dark at negative offsets) of profiles through ``base`` points,
    which are clean: enough contrast (against the median of their group: the profiles come in ``groups``
    equal consecutive groups, one per edge) and an edge far enough inside the profile to have a plateau
    beyond it; and each profile's blur, the σ of its gradient about the edge."""
    xs = (base[:, 0, None] + offsets * directions[:, 0, None]).astype(np.float32)
    ys = (base[:, 1, None] + offsets * directions[:, 1, None]).astype(np.float32)
    profiles = cv2.remap(roi, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    plateau = max(2, offsets.size // 6)
    dark = profiles[:, :plateau].sum(axis=1) / plateau
    light = profiles[:, -plateau:].sum(axis=1) / plateau
    contrast = light - dark
    by_group = np.sort(contrast.reshape(groups, -1), axis=1)
    n = by_group.shape[1]
    typical = ((by_group[:, (n - 1) // 2] + by_group[:, n // 2]) / 2.0).repeat(n)  # each group's median
    good = contrast > np.maximum(_MIN_CONTRAST, 0.3 * typical)
    step = offsets[1] - offsets[0]
    above = profiles - dark[:, None]
    area = step * (above.sum(axis=1) - 0.5 * (above[:, 0] + above[:, -1]))  # trapezoid rule
    divisor = np.where(good, contrast, 1.0)
    edge = offsets[-1] - area / divisor
    good &= np.abs(edge) < offsets[-1] - 0.75  # an edge near the profile's end has no plateau beyond it
    gradient = profiles[:, 1:] - profiles[:, :-1]  # × step⁻¹, and Σ gradient ≈ contrast: the steps cancel below
    middles = (offsets[:-1] + offsets[1:]) / 2.0
    moment = (gradient * (middles[None, :] - edge[:, None]) ** 2).sum(axis=1) / divisor
    return edge, good, np.sqrt(np.maximum(moment, 0.0))


def _fit_lines(
    points: NDArray[np.float64], valid: NDArray[np.bool_]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]] | None:
    """Total-least-squares lines (4 × (a, b, c), a·x + b·y + c = 0, a² + b² = 1) through each side's valid
    points, refitted once without the points beyond 3 robust σ; their RMS residuals and the points used."""
    keep = valid.copy()
    for _ in range(2):
        used = keep.sum(axis=1).astype(float)
        if (used < _MIN_POINTS_PER_SIDE).any():
            return None
        weights = keep / used[:, None]
        centroid = np.einsum("ij,ijk->ik", weights, points)
        centred = points - centroid[:, None, :]
        sxx = np.einsum("ij,ij->i", weights, centred[..., 0] ** 2)
        syy = np.einsum("ij,ij->i", weights, centred[..., 1] ** 2)
        sxy = np.einsum("ij,ij->i", weights, centred[..., 0] * centred[..., 1])
        direction = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # the major axis of the 2×2 scatter
        normal = np.column_stack([-np.sin(direction), np.cos(direction)])
        residuals = np.einsum("ijk,ik->ij", centred, normal)
        spread = _MAD_TO_SIGMA * _row_medians(np.abs(residuals), keep)
        keep = valid & (np.abs(residuals) <= np.maximum(3.0 * spread, 1e-9)[:, None])
    used = keep.sum(axis=1).astype(float)
    if (used < _MIN_POINTS_PER_SIDE).any():
        return None
    rms = np.sqrt(np.where(keep, residuals**2, 0.0).sum(axis=1) / used)
    lines = np.column_stack([normal, -np.einsum("ij,ij->i", normal, centroid)])
    return lines, rms, used


def _cross(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise cross products of N×3 arrays (np.cross costs ~50 µs a call in its generality)."""
    return np.column_stack([
        a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2], a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    ])


@lru_cache(maxsize=128)
def _spaced(count: int) -> NDArray[np.float64]:
    """``count`` fractions evenly spaced from 0 to 1 (read-only: shared by every call)."""
    fractions = np.linspace(0.0, 1.0, count)
    fractions.flags.writeable = False
    return fractions


def _row_medians(values: NDArray[np.float64], mask: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Median of each row's masked-in values (every row has some); np.nanmedian costs ~10× more here."""
    ordered = np.sort(np.where(mask, values, np.inf), axis=1)
    count = mask.sum(axis=1)
    rows = np.arange(len(ordered))
    low = ordered[rows, (count - 1) // 2]
    high = ordered[rows, count // 2]
    return (low + high) / 2.0


def marker_bits(dictionary: cv2.aruco.Dictionary, marker_id: int) -> NDArray[np.bool_]:
    """The printed pattern of a marker, border included: cells × cells, True = black, row 0 at its top."""
    cells = int(dictionary.markerSize) + 2
    return np.asarray(dictionary.generateImageMarker(marker_id, cells)) < 128


def refine_detections(
    gray: NDArray[np.uint8],
    detections: list[Detection],
    camera_matrix: NDArray[np.float64],
    dist_coeffs: NDArray[np.float64],
    bits_of: Callable[[int], NDArray[np.bool_]],
    config: DetectorConfig,
) -> list[Detection]:
    """Each detection with edge-refined corners where the edges could be measured, else as detected.
    ``bits_of(id)`` is the marker's printed pattern (:func:`marker_bits`)."""
    out = []
    for detection in detections:
        bits = bits_of(detection.id)
        fit = refine_corners(gray, detection.corners, camera_matrix, dist_coeffs, bits.shape[0], config, bits)
        out.append(detection if fit is None else replace(detection, corners=fit.corners, corner_sigma=fit.corner_sigma))
    return out


# ---------------------------------------------------------------------------------------------------------
# Pose


def marker_object_points(size: float) -> NDArray[np.float64]:
    """The marker's corners in its own frame (x right, y up, z out of the printed face), detector order."""
    h = size / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def ippe_weights(
    rotations: list[Matrix],
    squared_residuals: list[float],
    corner_sigma: float,
    expected_normal: ArrayLike,
    normal_sigma: float,
) -> tuple[NDArray[np.float64], float]:
    """Posterior probabilities of IPPE's solutions, and the log-odds the corners alone give the best one.

    Likelihood: Gaussian corner noise of σ ``corner_sigma`` px, so each solution scores −SSR / 2σ² (SSR: sum
    of squared reprojection residuals). Prior: the marker's +z (column 2 of the rotation, camera frame) is
    Gaussian about ``expected_normal`` with σ ``normal_sigma`` rad. With clean corners the likelihood decides;
    when the corners cannot tell the mirror poses apart (small, far or frontal markers) the prior does.
    """
    normal = np.asarray(expected_normal, dtype=float)
    normal = normal / np.linalg.norm(normal)
    ssr = np.asarray(squared_residuals, dtype=float)
    data = -ssr / (2.0 * corner_sigma**2)
    angles = np.array([math.acos(float(np.clip(r[:, 2] @ normal, -1.0, 1.0))) for r in rotations])
    score = data - angles**2 / (2.0 * normal_sigma**2)
    weights = np.exp(score - score.max())
    weights /= weights.sum()
    ordered = np.sort(data)[::-1]
    evidence = float(ordered[0] - ordered[1]) if len(ordered) > 1 else math.inf
    return weights, evidence


_DECISIVE_LOG_ODDS = math.log(100.0)


def choose_ippe_solution(
    rotations: list[Matrix],
    squared_residuals: list[float],
    corner_sigma: float,
    expected_normal: ArrayLike,
    normal_sigma: float,
) -> tuple[int, bool, float]:
    """Index of the most probable IPPE solution (see :func:`ippe_weights`), whether the corners alone were
    ambiguous (odds under 100:1), and the probability left to the other solution.

    "Closest to the previous output" is deliberately not used: it locks onto a wrong solution once it has
    been chosen.
    """
    if len(rotations) < 2:
        return 0, False, 0.0
    weights, evidence = ippe_weights(rotations, squared_residuals, corner_sigma, expected_normal, normal_sigma)
    best = int(np.argmax(weights))
    return best, evidence < _DECISIVE_LOG_ODDS, float(1.0 - weights[best])


def estimate_marker_pose(
    corners: NDArray[np.float64],
    size: float,
    camera_matrix: NDArray[np.float64],
    dist_coeffs: NDArray[np.float64],
    expected_normal_camera: NDArray[np.float64] | None,
    *,
    corner_sigma: float,
    normal_sigma: float,
) -> MarkerPoseEstimate | None:
    """T_camera_marker from the four corners; None when PnP finds no solution.

    Both IPPE solutions are polished by Levenberg–Marquardt on the reprojection error before they are
    compared: IPPE minimises an approximation of it, and on a marker seen within ~10° of face-on the exact
    minimum is ~2× closer to the truth (0.34° against 0.70° at p95 on the benchmark's scenes). There the two
    solutions converge to the same pose, which is then the only one; further from face-on they stay two
    distinct minima and :func:`choose_ippe_solution` decides. ``expected_normal_camera`` None means "facing
    the camera" (the normal points from the marker towards it).
    """
    object_points = marker_object_points(size)
    image_points = np.asarray(corners, dtype=np.float64).reshape(4, 1, 2)
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(
        object_points, image_points, camera_matrix, dist_coeffs, flags=cv2.SOLVEPNP_IPPE_SQUARE
    )
    if n == 0:
        return None
    rotations: list[Matrix] = []
    translations: list[NDArray[np.float64]] = []
    squared: list[float] = []
    for rvec, tvec in zip(rvecs, tvecs, strict=True):
        rvec, tvec = cv2.solvePnPRefineLM(object_points, image_points, camera_matrix, dist_coeffs, rvec.copy(), tvec.copy())
        rotation = cv2.Rodrigues(rvec)[0]
        if rotations and _angle(rotation, rotations[0]) < _SAME_SOLUTION:
            continue  # both started in the basin of one minimum
        projected, _ = cv2.projectPoints(object_points, rvec, tvec, camera_matrix, dist_coeffs)
        squared.append(float(np.sum(np.square(projected.reshape(4, 2) - image_points.reshape(4, 2)))))
        rotations.append(rotation)
        translations.append(np.asarray(tvec, dtype=float).reshape(3))
    if expected_normal_camera is None:
        towards_camera = -translations[0]
        expected_normal_camera = towards_camera / np.linalg.norm(towards_camera)
    chosen, ambiguous, other_weight = choose_ippe_solution(
        rotations, squared, corner_sigma, expected_normal_camera, normal_sigma
    )
    quad = image_points.reshape(4, 2)
    sides = np.linalg.norm(quad - quad[_NEXT], axis=1)
    rms = math.sqrt(squared[chosen] / 8.0)
    return MarkerPoseEstimate(
        make_transform(rotations[chosen], translations[chosen]), rms, float(sides.mean()), ambiguous, other_weight
    )


_SAME_SOLUTION = 1e-4  # rad: LM's convergence tolerance is far below; mirror minima are degrees apart


def _angle(r_a: Matrix, r_b: Matrix) -> float:
    # The chord form: arccos of the trace loses precision for the small angles compared here.
    chord = float(np.linalg.norm(np.asarray(r_a) - np.asarray(r_b))) / math.sqrt(8.0)
    return 2.0 * math.asin(min(1.0, chord))
