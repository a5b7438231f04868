"""Robust temporal filter for marker poses on SE(3). Pure maths, no I/O.

Per marker, a sliding window of recent T_base_marker samples (the marker lies still on the patient, so in the
base frame its samples scatter about one pose; the camera's own motion is already removed by the chain):

1. **Anchor**: the window's medoid, the sample with the smallest summed distance (rotation angle +
   translation / scale) to all the others. An isolated outlier (an IPPE mirror flip, a bad corner) can never
   be the anchor while inliers are the majority.
2. **Gates from the window's own scatter**: a sample joins the average when its rotation and translation are
   within ``inlier_spread`` times the window's median distance from the anchor (2.5: the 99.7 % quantile of
   3-D Gaussian noise), each gate clipped to [``min_inlier_*``, ``inlier_*``]. Fixed gates of 3° / 6 mm let a
   2–3° flip into the mean of samples that scatter by 0.3°; gates scaled to the scatter reject it, and widen
   again when the scatter is larger (far, small markers).
3. **Average**: mean translation and chordal mean rotation (the sum of the rotation matrices projected back
   onto SO(3) by SVD), then the gates are applied once more around that mean, a better centre than one noisy
   sample, and the inliers averaged again.

The output is always a proper rigid transform: an element-wise median of 4×4 matrices is not (its rotation part
is not orthonormal). A sample that is not a finite rigid transform is refused (ValueError), never averaged.

**The pose is the marker's at the newest frame's time** (``Markers.t``), which is how the edge's moves use it: a
move aims at the pose, and ``goto.marker_max_age`` judges it by ``t``. A plain average is the pose of the
samples' mean time, ``window``/2 frames back (4 frames, 0.27 s at 15 fps): a marker moving with the patient was
published where it had been, stamped as where it is. So, both with explicit frame times:

4. **Motion**: the inliers' translations and rotations (as rotation vectors about the mean) are fitted by a line
   in time; when its slope is significant against the inliers' own scatter (the correction exceeds
   :data:`MOTION_SIGNIFICANCE` times its standard error), the mean is carried along the line to the newest
   frame's time. A still marker's slope is noise and almost never passes (0.3 %), so it keeps the full average.
5. **Jump**: when the newest :data:`JUMP_FRAMES` samples all lie outside the gates around the output and agree
   with each other, the marker moved (the patient shifted) rather than gave outliers: the older samples are
   dropped and the window starts again from those. Up to ``JUMP_FRAMES - 1`` outliers in a row are still rejected.

Stamping the pose with an older time instead was not taken: one message stamps several markers and their raw
poses with the frame's time, and a pose the edge knows to be late is no use to aim a move at.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from iorthand.geometry import Matrix, is_rigid, make_transform, orthonormalize, rotvec_to_matrix
from iorthand.stats import median

from .config import FilterConfig


def pairwise_distances(rotations: np.ndarray, translations: np.ndarray, translation_scale: float) -> np.ndarray:
    """N×N matrix of rotation angle (rad) + translation distance / ``translation_scale``."""
    # tr(Ri^T Rj) for all pairs at once: the sum of the element-wise products of the two matrices.
    traces = np.einsum("iab,jab->ij", rotations, rotations)
    angles = np.arccos(np.clip((traces - 1.0) / 2.0, -1.0, 1.0))
    gaps = np.linalg.norm(translations[:, None, :] - translations[None, :, :], axis=-1)
    return angles + gaps / translation_scale


def _distances_to(rotation: np.ndarray, translation: np.ndarray, rotations: np.ndarray, translations: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Rotation angles (rad) and translation distances of every sample from one pose."""
    # The chordal form ‖Ri − R‖_F = 2√2·sin(θ/2) keeps precision at the sub-degree angles compared here,
    # where arccos of the trace loses it.
    chords = np.linalg.norm(rotations - rotation, axis=(1, 2)) / np.sqrt(8.0)
    return 2.0 * np.arcsin(np.clip(chords, 0.0, 1.0)), np.linalg.norm(translations - translation, axis=1)


def _gate(distances: np.ndarray, config: FilterConfig, low: float, high: float) -> float:
    return min(max(config.inlier_spread * median(distances), low), high)


def _inliers(rotation: np.ndarray, translation: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
             config: FilterConfig) -> np.ndarray:
    angles, gaps = _distances_to(rotation, translation, rotations, translations)
    rotation_gate = _gate(angles, config, config.min_inlier_rotation, config.inlier_rotation)
    translation_gate = _gate(gaps, config, config.min_inlier_translation, config.inlier_translation)
    return (angles <= rotation_gate) & (gaps <= translation_gate)


MOTION_SIGNIFICANCE = 3.76  # the 99.7 % quantile of the length of a 3-D standard normal vector (√χ²₃)
JUMP_FRAMES = 3  # consecutive samples away from the filtered pose, and together, that mean the marker moved


def _average(
    rotations: np.ndarray, translations: np.ndarray, config: FilterConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps 1–3: the robust mean (rotation, translation) and which samples it averaged."""
    distances = pairwise_distances(rotations, translations, config.translation_scale)
    medoid = int(np.argmin(distances.sum(axis=1)))
    inliers = _inliers(rotations[medoid], translations[medoid], rotations, translations, config)
    inliers[medoid] = True
    rotation = orthonormalize(rotations[inliers].sum(axis=0))
    translation = translations[inliers].mean(axis=0)
    again = _inliers(rotation, translation, rotations, translations, config)
    if np.any(again):  # the mean is inside the inliers' hull, so some stay; kept as a guard
        rotation = orthonormalize(rotations[again].sum(axis=0))
        translation = translations[again].mean(axis=0)
        inliers = again
    return rotation, translation, inliers


def _trend(values: np.ndarray, times: np.ndarray, at: float) -> np.ndarray:
    """How far the least-squares lines through ``values`` (n×6: a translation and a rotation vector) over
    ``times`` move from their mean to time ``at``: per 3-vector, that when its slope is significant against its
    residual scatter, else zero."""
    n = len(times)
    dt = times - times.mean()
    spread = float(dt @ dt)
    if n < 4 or spread <= 0.0:  # a line and its residual scatter need more points than a line has parameters
        return np.zeros(6)
    centred = values - values.mean(axis=0)
    slope = dt @ centred / spread
    scatter = ((centred - np.outer(dt, slope)) ** 2).sum(axis=0)
    lead = at - times.mean()
    shift = slope * lead
    for part in (slice(0, 3), slice(3, 6)):
        sigma = np.sqrt(float(scatter[part].sum()) / (3 * (n - 2)))  # per component
        if np.linalg.norm(shift[part]) <= MOTION_SIGNIFICANCE * sigma * abs(lead) / np.sqrt(spread):
            shift[part] = 0.0
    return shift


def _rotation_vectors(rotation: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """The rotation vectors of ``rotations`` (n×3×3) about ``rotation``, all at once. Only for the inliers: within
    the rotation gate (at most ``inlier_rotation``, far from π, where the antisymmetric part gives the axis)."""
    rel = np.einsum("ba,nbc->nac", rotation, rotations)  # rotation.T @ each
    w = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], axis=1)
    theta = np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))
    sin = np.sin(theta)
    k = np.where(sin > 1e-9, theta / (2.0 * np.where(sin > 1e-9, sin, 1.0)), 0.5)  # θ/(2 sin θ) → ½ at 0
    return w * k[:, None]


def robust_pose(samples: list[Matrix], config: FilterConfig, times: list[float] | None = None) -> Matrix:
    """The filtered pose of a window of samples (see the module docstring). With ``times`` (s, one per sample,
    oldest first), the pose at the newest time: carried along a significant motion (step 4)."""
    return _robust_pose(samples, config, times)[0]


def _robust_pose(samples: list[Matrix], config: FilterConfig, times: list[float] | None) -> tuple[Matrix, np.ndarray]:
    """robust_pose, and which samples the mean took."""
    rotations = np.stack([s[:3, :3] for s in samples])
    translations = np.stack([s[:3, 3] for s in samples])
    rotation, translation, inliers = _average(rotations, translations, config)
    if times is not None:
        # Rotations as rotation vectors about the mean: small, where a line in time is a fair model.
        values = np.hstack([translations[inliers], _rotation_vectors(rotation, rotations[inliers])])
        shift = _trend(values, np.asarray(times, dtype=float)[inliers], float(times[-1]))
        translation = translation + shift[:3]
        if shift[3:].any():
            rotation = rotation @ rotvec_to_matrix(shift[3:])
    return make_transform(rotation, translation), inliers


def _jumped(window: list[Matrix], pose: Matrix, config: FilterConfig) -> bool:
    """Step 5: whether the newest JUMP_FRAMES samples all lie outside the gates around ``pose`` (the filtered
    pose of the window) and within them around their own medoid: the marker is somewhere else now."""
    if len(window) <= JUMP_FRAMES:
        return False
    newest = np.stack(window[-JUMP_FRAMES:])
    newest_r, newest_t = newest[:, :3, :3], newest[:, :3, 3]
    angles, gaps = _distances_to(pose[:3, :3], pose[:3, 3], newest_r, newest_t)
    # The gates are never narrower than their minimums: a newest sample within both is no jump, whatever the
    # window's scatter (the common case, decided without the whole window).
    if np.any((angles <= config.min_inlier_rotation) & (gaps <= config.min_inlier_translation)):
        return False
    rotations = np.stack([s[:3, :3] for s in window])
    translations = np.stack([s[:3, 3] for s in window])
    angles, gaps = _distances_to(pose[:3, :3], pose[:3, 3], rotations, translations)
    rotation_gate = _gate(angles, config, config.min_inlier_rotation, config.inlier_rotation)
    translation_gate = _gate(gaps, config, config.min_inlier_translation, config.inlier_translation)
    away = (angles > rotation_gate) | (gaps > translation_gate)
    if not np.all(away[-JUMP_FRAMES:]):
        return False
    medoid = int(np.argmin(pairwise_distances(newest_r, newest_t, config.translation_scale).sum(axis=1)))
    angles, gaps = _distances_to(newest_r[medoid], newest_t[medoid], newest_r, newest_t)
    return bool(np.all((angles <= rotation_gate) & (gaps <= translation_gate)))


class MarkerFilter:
    """The window of one marker. Cleared when the marker has not been seen for ``reset_after`` seconds."""

    def __init__(self, config: FilterConfig) -> None:
        self.config = config
        self._window: deque[Matrix] = deque(maxlen=config.window)
        self._times: deque[float] = deque(maxlen=config.window)  # s, relative to the window's first sample
        self._origin_ns = 0
        self._last_seen_ns: int | None = None

    def update(self, t_ns: int, pose: Matrix) -> Matrix:
        sample = np.asarray(pose, dtype=float)
        if not is_rigid(sample, tol=1e-6):
            raise ValueError("marker pose is not a finite rigid transform; not filtered")
        if self._last_seen_ns is not None and t_ns - self._last_seen_ns > self.config.reset_after * 1e9:
            self._window.clear()
            self._times.clear()
        if not self._window:
            self._origin_ns = t_ns
        self._last_seen_ns = t_ns
        self._window.append(sample)
        self._times.append((t_ns - self._origin_ns) / 1e9)
        window, times = list(self._window), list(self._times)
        pose, inliers = _robust_pose(window, self.config, times)
        # A newest sample that the mean took is no sign of a jump: the whole check only when none of them was.
        if not inliers[-JUMP_FRAMES:].any() and _jumped(window, pose, self.config):
            for _ in range(len(window) - JUMP_FRAMES):
                self._window.popleft()
                self._times.popleft()
            pose = robust_pose(list(self._window), self.config, list(self._times))
        return pose

    def __len__(self) -> int:
        return len(self._window)


class MarkerFilters:
    """One :class:`MarkerFilter` per marker id; forgets markers unseen for longer than ``reset_after``."""

    def __init__(self, config: FilterConfig) -> None:
        self.config = config
        self._filters: dict[int, MarkerFilter] = {}
        self._last_seen_ns: dict[int, int] = {}

    def update(self, marker_id: int, t_ns: int, pose: Matrix) -> Matrix:
        self._forget_lost(t_ns)
        marker_filter = self._filters.get(marker_id)
        if marker_filter is None:
            marker_filter = self._filters[marker_id] = MarkerFilter(self.config)
        self._last_seen_ns[marker_id] = t_ns
        return marker_filter.update(t_ns, pose)

    def _forget_lost(self, t_ns: int) -> None:
        limit_ns = self.config.reset_after * 1e9
        for marker_id in [m for m, seen in self._last_seen_ns.items() if t_ns - seen > limit_ns]:
            del self._filters[marker_id]
            del self._last_seen_ns[marker_id]

    def tracked(self) -> list[int]:
        return sorted(self._filters)
