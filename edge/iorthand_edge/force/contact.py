"""The simulated phantom: a springy surface in the robot's workspace, flat or curved. Pure maths, no I/O.

Three shapes (``shape``), all in the base frame, the tool tip being the TCP:

* ``flat`` (the default): the plane ``z = surface_z`` over the box ``x_range`` × ``y_range``.
* ``cylinder``: a thigh lying on a bed, a horizontal cylinder of ``radius`` whose axis runs along ``axis`` (x or
  y) at height ``axis_height``, through the middle of the footprint ``x_range`` × ``y_range`` and over the
  footprint's whole extent along the axis (the ends are cut flat).
* ``ellipsoid``: an abdomen, the upper half of an ellipsoid of ``semi_axes`` (x, y, z) centred over the middle of
  the footprint, its flat base at ``base_z``.

Only the upper halves of the curved shapes can be touched from above; below the axis (the base) they continue
as vertical walls, so that depth and normal are defined wherever the tool goes. Both are continuous for any
depth a probe reaches (less than the surface's radius of curvature); far deeper, on the shape's medial axis,
the nearest surface point jumps, as it does for any solid.

Pressing ``d`` metres into the surface at speed ``v`` gives a force ``k·d − c·(v·n)`` (never pulling: a surface
cannot hold the probe) along the outward surface normal ``n`` at the contact point, the point of the surface
nearest the tool tip; ``d`` is the distance to it (exact for every shape). The force sensor measures the reaction
in its own frame (the tool frame), which is what a real wrist sensor reports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iorthand.config import setting
from iorthand.geometry import rotate

SHAPES = ("flat", "cylinder", "ellipsoid")
_UP = (0.0, 0.0, 1.0)


@dataclass
class PhantomConfig:
    shape: str = setting("flat", choices=SHAPES, help="flat (a plane), cylinder (a thigh), ellipsoid (an abdomen)")
    surface_z: float = setting(0.15, lo=-2.0, hi=2.0, help="m: flat: height of the surface, base frame")
    x_range: list[float] = setting(default_factory=lambda: [0.20, 0.40], length=2,
                                   help="m: extent along x (flat); the footprint the curved shapes are centred in")
    y_range: list[float] = setting(default_factory=lambda: [-0.10, 0.10], length=2, help="m: extent along y (idem)")
    axis: str = setting("x", choices=("x", "y"), help="cylinder: the direction of its axis")
    radius: float = setting(0.07, lo=0.005, hi=1.0, help="m: cylinder radius")
    axis_height: float = setting(0.08, lo=-2.0, hi=2.0, help="m: cylinder: height of its axis (top: + radius)")
    semi_axes: list[float] = setting(default_factory=lambda: [0.10, 0.08, 0.06], length=3, lo=0.005, hi=1.0,
                                     help="m: ellipsoid semi-axes along x, y, z")
    base_z: float = setting(0.09, lo=-2.0, hi=2.0, help="m: ellipsoid: height of its base (top: + semi_axes[2])")
    stiffness: float = setting(2000.0, lo=1.0, hi=1e6, help="N/m (soft tissue phantom: ~1–8 kN/m)")
    damping: float = setting(20.0, lo=0.0, hi=1e4, help="N·s/m, acts only while pressing in")

    def check(self) -> None:
        for name, r in (("x_range", self.x_range), ("y_range", self.y_range)):
            if r[0] >= r[1]:
                raise ValueError(f"{name} {r} must be [min, max] with min < max")

    def _surface(self, point: ArrayLike) -> tuple[float, tuple[float, float, float]]:
        """Depth below the surface (m, ≥ 0) and the outward unit normal there (base frame)."""
        x, y, z = float(point[0]), float(point[1]), float(point[2])
        (x0, x1), (y0, y1) = self.x_range, self.y_range
        if self.shape == "flat":
            inside = x0 <= x <= x1 and y0 <= y <= y1
            return (max(0.0, self.surface_z - z) if inside else 0.0), _UP
        if self.shape == "cylinder":
            along, lo, hi = (x, x0, x1) if self.axis == "x" else (y, y0, y1)
            across = y - (y0 + y1) / 2 if self.axis == "x" else x - (x0 + x1) / 2
            up = max(0.0, z - self.axis_height)  # below the axis: vertical walls (see the module's docstring)
            rho = math.hypot(across, up)
            if rho < 1e-12:
                normal = _UP  # on the axis itself every direction is as near: take the top's
            else:
                normal = (0.0, across / rho, up / rho) if self.axis == "x" else (across / rho, 0.0, up / rho)
            return (max(0.0, self.radius - rho) if lo <= along <= hi else 0.0), normal
        centred = (x - (x0 + x1) / 2, y - (y0 + y1) / 2, max(0.0, z - self.base_z))
        foot, inside = _ellipsoid_foot(self.semi_axes, centred)
        grad = [f / (s * s) for f, s in zip(foot, self.semi_axes, strict=True)]  # outward normal at the foot
        g = math.sqrt(grad[0] ** 2 + grad[1] ** 2 + grad[2] ** 2)
        depth = math.dist(foot, centred) if inside else 0.0
        return depth, (grad[0] / g, grad[1] / g, grad[2] / g)

    def depth(self, tcp_pose: ArrayLike) -> float:
        """How far (m) the tool tip is inside the surface; 0 when outside it."""
        return self._surface(tcp_pose)[0]

    def normal(self, tcp_pose: ArrayLike) -> NDArray[np.float64]:
        """The outward unit normal (base frame) of the surface at the contact point nearest the tool tip: the
        direction of the force the phantom exerts. Defined everywhere (also out of contact), continuous."""
        return np.array(self._surface(tcp_pose)[1])

    def depth_for_force(self, force: float) -> float:
        """Static penetration (m) at which the spring alone gives ``force`` N."""
        return force / self.stiffness


def _ellipsoid_foot(semi_axes: list[float], p: tuple[float, float, float]) -> tuple[list[float], bool]:
    """The point of the ellipsoid ``Σ x_i²/s_i² = 1`` (centred at the origin) nearest ``p``, and whether ``p`` is
    inside. The foot is ``x_i = s_i² p_i / (s_i² + t)`` for the one root ``t > −min s_i²`` of
    ``g(t) = Σ (s_i p_i / (s_i² + t))² − 1`` (Lagrange; Eberly, "Distance from a point to an ellipse, an
    ellipsoid, or a hyperellipsoid"): ``g`` decreases monotonically on that interval."""
    s = semi_axes
    a = [abs(v) for v in p]  # solve in the first octant; the foot has p's signs
    sign = [1.0 if v >= 0 else -1.0 for v in p]
    inside = sum((a[i] / s[i]) ** 2 for i in range(3)) < 1.0
    s_min2 = min(s) ** 2

    flat = [i for i in range(3) if s[i] * s[i] - s_min2 < 1e-15 and a[i] < 1e-15]
    if inside and len(flat) == sum(1 for v in s if v * v - s_min2 < 1e-15):
        # p lies in the plane of the shortest axis: the root may not exist on (−s_min², 0]; then the foot leaves
        # that plane along the shortest axis (Eberly's degenerate case).
        rest = [i for i in range(3) if i not in flat]
        x = [0.0, 0.0, 0.0]
        for i in rest:
            x[i] = s[i] * s[i] * a[i] / (s[i] * s[i] - s_min2)
        r = sum((x[i] / s[i]) ** 2 for i in rest)
        if r < 1.0:
            x[flat[0]] = s[flat[0]] * math.sqrt(1.0 - r)
            return [x[i] * sign[i] for i in range(3)], inside
    # Newton from t = 0 (the root is near 0 for a tool a few mm from the surface), kept inside a bracket that
    # bisection narrows whenever a step would leave it: a handful of iterations instead of ~60 bisections.
    lo, hi = (-s_min2, 0.0) if inside else (0.0, max(s) * math.sqrt(a[0] ** 2 + a[1] ** 2 + a[2] ** 2) + 1.0)
    t = 0.0
    for _ in range(100):
        terms = [(s[i] * a[i]) ** 2 / (s[i] * s[i] + t) ** 2 for i in range(3)]
        value = sum(terms) - 1.0
        if value > 0.0:
            lo = t
        else:
            hi = t
        slope = -2.0 * sum(terms[i] / (s[i] * s[i] + t) for i in range(3))
        step = t - value / slope if slope < 0.0 else (lo + hi) / 2
        if not lo < step < hi:
            step = (lo + hi) / 2
        if step == t or abs(value) < 1e-15:
            break
        t = step
    return [s[i] * s[i] * a[i] / (s[i] * s[i] + t) * sign[i] for i in range(3)], inside


def _force(phantom: PhantomConfig, point: ArrayLike, tcp_speed: ArrayLike) -> tuple[float, float, float] | None:
    """The force (N, base frame) on a tool tip at ``point`` moving at ``tcp_speed``; None out of contact. Plain
    floats: the simulated sensor calls this in every control cycle, where numpy's per-call cost on 3-vectors was
    most of its cost."""
    depth, (nx, ny, nz) = phantom._surface(point)
    if depth <= 0.0:
        return None
    v_normal = float(tcp_speed[0]) * nx + float(tcp_speed[1]) * ny + float(tcp_speed[2]) * nz  # < 0: pressing in
    magnitude = max(0.0, phantom.stiffness * depth - phantom.damping * v_normal)
    return magnitude * nx, magnitude * ny, magnitude * nz


def contact_force(phantom: PhantomConfig, tcp_pose: ArrayLike, tcp_speed: ArrayLike) -> NDArray[np.float64]:
    """The force ``[Fx, Fy, Fz]`` (N) the phantom exerts on the tool, in the base frame."""
    force = _force(phantom, tcp_pose, tcp_speed)
    return np.zeros(3) if force is None else np.array(force)


def contact_wrench(phantom: PhantomConfig, tcp_pose: ArrayLike, tcp_speed: ArrayLike) -> NDArray[np.float64]:
    """The wrench ``[Fx, Fy, Fz, Tx, Ty, Tz]`` the phantom exerts on the tool, in the tool (sensor) frame."""
    force = _force(phantom, tcp_pose, tcp_speed)
    if force is None or not any(force):
        return np.zeros(6)
    # The sensor's frame is the tool's: the inverse of the tool's rotation. The contact is at the TCP, so it exerts
    # no torque about it.
    return np.array([*rotate((-float(tcp_pose[3]), -float(tcp_pose[4]), -float(tcp_pose[5])), force), 0.0, 0.0, 0.0])
