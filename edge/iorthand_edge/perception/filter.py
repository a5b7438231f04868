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
"""

from __future__ import annotations

from collections import deque

import numpy as np

from iorthand.geometry import Matrix, is_rigid, make_transform, orthonormalize
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


def robust_pose(samples: list[Matrix], config: FilterConfig) -> Matrix:
    """The filtered pose of a window of samples (see the module docstring)."""
    rotations = np.stack([s[:3, :3] for s in samples])
    translations = np.stack([s[:3, 3] for s in samples])
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
    return make_transform(rotation, translation)


class MarkerFilter:
    """The window of one marker. Cleared when the marker has not been seen for ``reset_after`` seconds."""

    def __init__(self, config: FilterConfig) -> None:
        self.config = config
        self._window: deque[Matrix] = deque(maxlen=config.window)
        self._last_seen_ns: int | None = None

    def update(self, t_ns: int, pose: Matrix) -> Matrix:
        sample = np.asarray(pose, dtype=float)
        if not is_rigid(sample, tol=1e-6):
            raise ValueError("marker pose is not a finite rigid transform; not filtered")
        if self._last_seen_ns is not None and t_ns - self._last_seen_ns > self.config.reset_after * 1e9:
            self._window.clear()
        self._last_seen_ns = t_ns
        self._window.append(sample)
        return robust_pose(list(self._window), self.config)

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
