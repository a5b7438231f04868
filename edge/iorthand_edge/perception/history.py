"""Recent robot poses and servo angles, interpolated at a camera frame's capture time.

A frame is exposed at one instant; the robot state arrives at another rate (125 Hz) and the arm keeps
moving, so the pose to chain with is the one at the frame's timestamp, not the latest one received.
Both histories are thread-safe: the media process adds what ``state/robot`` and ``state/servo`` say, the
perception worker reads.
"""

from __future__ import annotations

import bisect
import threading
from collections.abc import Callable, Sequence
from typing import Generic, TypeVar

import numpy as np

from iorthand.geometry import Matrix, interpolate_pose, is_rigid, pose_to_matrix

S = TypeVar("S")


class _TimedHistory(Generic[S]):
    """Samples ordered by time, kept for ``span_s``; :meth:`at` interpolates between the two around ``t``."""

    def __init__(
        self, interpolate: Callable[[S, S, float], S], span_s: float, max_extrapolation_s: float | None
    ) -> None:
        self._interpolate = interpolate
        self._span_ns = int(span_s * 1e9)
        self._max_extrapolation_ns = None if max_extrapolation_s is None else int(max_extrapolation_s * 1e9)
        self._times: list[int] = []
        self._samples: list[S] = []
        self._lock = threading.Lock()

    def _add(self, t_ns: int, sample: S) -> None:
        with self._lock:
            if self._times and t_ns <= self._times[-1]:
                # Out-of-order or repeated samples (a re-sent state) would break the bisection: insert in place.
                i = bisect.bisect_left(self._times, t_ns)
                if i < len(self._times) and self._times[i] == t_ns:
                    self._samples[i] = sample
                    return
                self._times.insert(i, t_ns)
                self._samples.insert(i, sample)
            else:
                self._times.append(t_ns)
                self._samples.append(sample)
            cutoff = self._times[-1] - self._span_ns
            drop = bisect.bisect_left(self._times, cutoff)
            # Keep one sample older than the span so a frame near the cutoff can still be bracketed.
            if drop > 1:
                del self._times[: drop - 1]
                del self._samples[: drop - 1]

    def at(self, t_ns: int) -> S | None:
        """The sample interpolated at ``t_ns``; None if ``t_ns`` is outside what the history can answer for."""
        with self._lock:
            if not self._times:
                return None
            if t_ns >= self._times[-1]:
                # A frame slightly newer than the last state (states arrive late): hold the newest sample.
                limit = self._max_extrapolation_ns
                return self._samples[-1] if limit is None or t_ns - self._times[-1] <= limit else None
            i = bisect.bisect_right(self._times, t_ns)
            if i == 0:
                return None
            t0, t1 = self._times[i - 1], self._times[i]
            s0, s1 = self._samples[i - 1], self._samples[i]
        return self._interpolate(s0, s1, (t_ns - t0) / (t1 - t0))

    def __len__(self) -> int:
        with self._lock:
            return len(self._times)


class PoseHistory(_TimedHistory[Matrix]):
    """T_base_tcp over time; interpolation is linear in translation and geodesic in rotation."""

    def __init__(self, span_s: float = 2.0, max_extrapolation_s: float = 0.05) -> None:
        super().__init__(interpolate_pose, span_s, max_extrapolation_s)

    def add(self, t_ns: int, t_base_tcp: np.ndarray) -> None:
        pose = np.array(t_base_tcp, dtype=float)
        if not is_rigid(pose, tol=1e-5):
            raise ValueError("T_base_tcp must be a rigid 4×4 transform (convert UR poses with pose_to_matrix)")
        self._add(t_ns, pose)

    def add_pose(self, t_ns: int, tcp_pose: Sequence[float]) -> None:
        """Add a UR pose ``[x, y, z, rx, ry, rz]`` (m, rotation vector). Rigid by construction, so not checked:
        the check was 80 % of the cost of adding a robot state, 125 of which arrive every second."""
        self._add(t_ns, pose_to_matrix(tcp_pose))


def _lerp_angles(a: tuple[float, float], b: tuple[float, float], s: float) -> tuple[float, float]:
    return (a[0] + (b[0] - a[0]) * s, a[1] + (b[1] - a[1]) * s)


# The servo unit publishes state/servo on every change and, while still, as a heartbeat every 1/publish_hz s
# (servos.publish_hz, 2 Hz by default). The newest angles hold for a frame until this many heartbeats went
# missing: then the servo unit (or its link) is gone and the camera's angle is unknown: a frozen state never
# passes for a live one.
SERVO_STALE_HEARTBEATS = 3.0
DEFAULT_SERVO_PUBLISH_HZ = 2.0  # servos.publish_hz's default: when the heartbeat rate is not known


def servo_max_age(publish_hz: float | None = None) -> float:
    """s the newest servo state holds for a later frame: :data:`SERVO_STALE_HEARTBEATS` heartbeat periods at
    ``publish_hz`` (the servo config's; :data:`DEFAULT_SERVO_PUBLISH_HZ` when unknown)."""
    hz = DEFAULT_SERVO_PUBLISH_HZ if publish_hz is None else publish_hz
    if not hz > 0:
        raise ValueError(f"servo publish_hz must be positive, got {hz!r}")
    return SERVO_STALE_HEARTBEATS / hz


class ServoHistory(_TimedHistory[tuple[float, float]]):
    """(pan, tilt) in rad over time, linearly interpolated.

    Servo states are published on change and as a heartbeat, so the newest angles hold for a later time, but only
    for ``max_extrapolation_s`` (default :func:`servo_max_age` at the default heartbeat rate): after that the
    angles are unknown (None), and the markers seen in such a frame are not published.
    """

    def __init__(self, span_s: float = 2.0, max_extrapolation_s: float | None = None) -> None:
        if max_extrapolation_s is None:
            max_extrapolation_s = servo_max_age()
        super().__init__(_lerp_angles, span_s, max_extrapolation_s)

    def add(self, t_ns: int, pan: float, tilt: float) -> None:
        self._add(t_ns, (float(pan), float(tilt)))
