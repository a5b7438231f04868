"""Robust temporal filter for marker poses. Pure maths, no I/O.

Per marker, a sliding window of recent T_base_marker samples. The output is built around the window's
medoid — the sample with the smallest summed distance (rotation angle + translation / scale) to all the
others — so an isolated outlier (a mirror flip of IPPE, a bad corner) can never be chosen while inliers are
the majority. The samples close to the medoid are then averaged (mean translation, chordal mean rotation
projected back onto SO(3)) to reduce noise. The output is always a proper rigid transform: an element-wise
median of 4×4 matrices is not (its rotation part is not orthonormal).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from iorthand.geometry import Matrix, make_transform, orthonormalize

from .config import FilterConfig


def pairwise_distances(rotations: np.ndarray, translations: np.ndarray, translation_scale: float) -> np.ndarray:
    """N×N matrix of rotation angle (rad) + translation distance / ``translation_scale``."""
    # tr(Ri^T Rj) for all pairs at once: the sum of the element-wise products of the two matrices.
    traces = np.einsum("iab,jab->ij", rotations, rotations)
    angles = np.arccos(np.clip((traces - 1.0) / 2.0, -1.0, 1.0))
    gaps = np.linalg.norm(translations[:, None, :] - translations[None, :, :], axis=-1)
    return angles + gaps / translation_scale


def robust_pose(samples: list[Matrix], config: FilterConfig) -> Matrix:
    """The filtered pose of a window of samples (see the module docstring)."""
    rotations = np.stack([s[:3, :3] for s in samples])
    translations = np.stack([s[:3, 3] for s in samples])
    distances = pairwise_distances(rotations, translations, config.translation_scale)
    medoid = int(np.argmin(distances.sum(axis=1)))
    traces = np.einsum("ab,iab->i", rotations[medoid], rotations)
    angles = np.arccos(np.clip((traces - 1.0) / 2.0, -1.0, 1.0))
    gaps = np.linalg.norm(translations - translations[medoid], axis=1)
    inliers = (angles <= config.inlier_rotation) & (gaps <= config.inlier_translation)
    inliers[medoid] = True
    rotation = orthonormalize(rotations[inliers].sum(axis=0))
    return make_transform(rotation, translations[inliers].mean(axis=0))


class MarkerFilter:
    """The window of one marker. Cleared when the marker has not been seen for ``reset_after`` seconds."""

    def __init__(self, config: FilterConfig) -> None:
        self.config = config
        self._window: deque[Matrix] = deque(maxlen=config.window)
        self._last_seen_ns: int | None = None

    def update(self, t_ns: int, pose: Matrix) -> Matrix:
        if self._last_seen_ns is not None and t_ns - self._last_seen_ns > self.config.reset_after * 1e9:
            self._window.clear()
        self._last_seen_ns = t_ns
        self._window.append(np.asarray(pose, dtype=float))
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
