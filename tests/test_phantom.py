"""The simulated phantom's shapes (edge/iorthand_edge/force/contact.py), pure: depth and normal from the surface,
continuity, the force k·d along the normal, and the flat shape exactly as before curved shapes existed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from iorthand.config import ConfigError, from_dict
from iorthand.geometry import rotvec_to_matrix
from iorthand_edge.force.contact import PhantomConfig, contact_force, contact_wrench

DOWN = [math.pi, 0.0, 0.0]  # tool pointing down
STIFFNESSES = (2000.0, 4000.0, 8000.0)  # the must-show runs: 2, 4 and 8 N/mm


def _flat_wrench_before(surface_z: float, box: tuple[list[float], list[float]], k: float, c: float,
                        pose: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """contact_wrench as it was with only a flat phantom (the reference the default must still match)."""
    inside = box[0][0] <= pose[0] <= box[0][1] and box[1][0] <= pose[1] <= box[1][1]
    depth = max(0.0, surface_z - pose[2]) if inside else 0.0
    if depth <= 0.0:
        return np.zeros(6)
    normal = max(0.0, k * depth - c * speed[2])
    return np.concatenate([rotvec_to_matrix(pose[3:]).T @ np.array([0.0, 0.0, normal]), np.zeros(3)])


def test_flat_default_unchanged() -> None:
    ph = PhantomConfig()
    assert ph.shape == "flat"
    rng = np.random.default_rng(7)
    for _ in range(500):
        pose = np.concatenate([rng.uniform([0.15, -0.15, 0.13], [0.45, 0.15, 0.17]), rng.normal(0, 1.5, 3)])
        speed = rng.normal(0, 0.02, 6)
        before = _flat_wrench_before(ph.surface_z, (ph.x_range, ph.y_range), ph.stiffness, ph.damping, pose, speed)
        assert contact_wrench(ph, pose, speed) == pytest.approx(before, abs=1e-12)
        assert list(ph.normal(pose)) == [0.0, 0.0, 1.0]
    assert ph.depth([0.3, 0.0, 0.148, *DOWN]) == pytest.approx(0.002)
    assert ph.depth([0.5, 0.0, 0.10, *DOWN]) == 0.0  # outside the box


@pytest.mark.parametrize("axis", ["x", "y"])
def test_cylinder_depth_and_normal(axis: str) -> None:
    ph = PhantomConfig(shape="cylinder", axis=axis, radius=0.07, axis_height=0.08, x_range=[0.2, 0.4],
                       y_range=[-0.1, 0.1])
    centre = np.array([0.3, 0.0, 0.08])
    along = np.array([1.0, 0.0, 0.0]) if axis == "x" else np.array([0.0, 1.0, 0.0])
    across = np.array([0.0, 1.0, 0.0]) if axis == "x" else np.array([1.0, 0.0, 0.0])
    for angle in (-1.2, -0.5, 0.0, 0.3, 1.0):  # from the top, in the plane across the axis
        n = math.sin(angle) * across + math.cos(angle) * np.array([0.0, 0.0, 1.0])
        for shift in (-0.08, 0.0, 0.05):  # anywhere along the axis within the footprint
            surface = centre + shift * along + 0.07 * n
            for d in (0.0005, 0.002, 0.006):
                p = [*(surface - d * n), *DOWN]
                assert ph.depth(p) == pytest.approx(d, abs=1e-12)
                assert ph.normal(p) == pytest.approx(n, abs=1e-12)
            assert ph.depth([*(surface + 0.001 * n), *DOWN]) == 0.0  # just outside
    # Beyond the ends of the footprint along the axis: nothing to press on.
    assert ph.depth([*(centre + 0.11 * along + [0, 0, 0.069]), *DOWN]) == 0.0
    # Below the axis the cylinder continues as vertical walls (a thigh on a bed): horizontal normal.
    wall = [*(centre + 0.065 * across - [0, 0, 0.03]), *DOWN]
    assert ph.depth(wall) == pytest.approx(0.005) and ph.normal(wall) == pytest.approx(across)


def _ellipsoid_surface(ph: PhantomConfig, theta: float, phi: float) -> np.ndarray:
    a, b, c = ph.semi_axes
    return np.array([0.3 + a * math.sin(theta) * math.cos(phi), b * math.sin(theta) * math.sin(phi),
                     ph.base_z + c * math.cos(theta)])


def _nearest_on_dome(ph: PhantomConfig, p: np.ndarray) -> float:
    """Distance from ``p`` to the dome by brute force: a coarse sampling, then a fine one around its best."""
    best, (t0, f0), span = math.inf, (math.pi / 4, 0.0), (math.pi / 2, math.pi)
    for _ in range(4):
        theta, phi = np.meshgrid(np.linspace(t0 - span[0], t0 + span[0], 201),
                                 np.linspace(f0 - span[1], f0 + span[1], 201))
        theta = np.clip(theta, 0.0, math.pi / 2)
        a, b, c = ph.semi_axes
        pts = np.stack([0.3 + a * np.sin(theta) * np.cos(phi), b * np.sin(theta) * np.sin(phi),
                        ph.base_z + c * np.cos(theta)], -1)
        dist = np.linalg.norm(pts - p, axis=-1)
        i = np.unravel_index(np.argmin(dist), dist.shape)
        best, t0, f0 = float(dist[i]), float(theta[i]), float(phi[i])
        span = (span[0] / 50, span[1] / 50)
    return best


def test_ellipsoid_depth_is_the_distance_to_the_surface() -> None:
    ph = PhantomConfig(shape="ellipsoid", semi_axes=[0.10, 0.08, 0.06], base_z=0.09)
    a, b, c = ph.semi_axes
    rng = np.random.default_rng(3)
    for _ in range(12):
        s = _ellipsoid_surface(ph, rng.uniform(0.1, 1.4), rng.uniform(-math.pi, math.pi))
        n = ph.normal(s)
        # The normal at a surface point is the gradient of x²/a² + y²/b² + z²/c² there.
        grad = (s - [0.3, 0.0, ph.base_z]) / np.array([a * a, b * b, c * c])
        assert n == pytest.approx(grad / np.linalg.norm(grad), abs=1e-9)
        for d in (0.001, 0.003, 0.006):
            p = s - d * n
            assert ph.depth(p) == pytest.approx(d, abs=1e-9)  # the surface point is the nearest one...
            assert ph.normal(p) == pytest.approx(n, abs=1e-9)  # ...and its normal is the contact's
            assert ph.depth(p) == pytest.approx(_nearest_on_dome(ph, p), abs=1e-7)  # by brute force
        assert ph.depth(s + 0.002 * n) == 0.0
    top = [0.3, 0.0, ph.base_z + c - 0.004, *DOWN]
    assert ph.depth(top) == pytest.approx(0.004) and ph.normal(top) == pytest.approx([0, 0, 1])


@pytest.mark.parametrize("shape", ["flat", "cylinder", "ellipsoid"])
def test_depth_and_normal_are_continuous(shape: str) -> None:
    """A probe swept through each phantom (its top at z = 0.15 by default) at the depths a probe reaches, across
    its top and over its sides: no jumps in depth or normal."""
    ph = PhantomConfig(shape=shape, axis="x")
    step = 1e-4
    for z in (0.149, 0.145, 0.14, 0.135):
        ys = np.arange(-0.095, 0.095, step)
        depths = np.array([ph.depth([0.31, y, z, *DOWN]) for y in ys])
        normals = np.array([ph.normal([0.31, y, z, *DOWN]) for y in ys])
        assert np.all(np.abs(np.diff(depths)) <= step * (1 + 1e-9))  # 1-Lipschitz, as a distance is
        turn = np.arccos(np.clip(np.sum(normals[1:] * normals[:-1], axis=1), -1, 1))
        # The normal turns no faster than the tightest curvature allows (here: ~1/(2 cm) worst case).
        assert np.max(turn) < step / 0.02, (shape, z, float(np.max(turn)))
        assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)


@pytest.mark.parametrize("stiffness", STIFFNESSES)
@pytest.mark.parametrize("shape", ["cylinder", "ellipsoid"])
def test_force_is_k_d_along_the_normal(shape: str, stiffness: float) -> None:
    ph = PhantomConfig(shape=shape, stiffness=stiffness, damping=20.0)
    for d in (0.0005, 0.001, 0.002, 0.004):
        if shape == "cylinder":
            n = np.array([0.0, math.sin(0.4), math.cos(0.4)])
            p = np.array([0.3, 0.0, 0.08]) + (0.07 - d) * n
        else:
            s = _ellipsoid_surface(ph, 0.6, 2.0)
            n = ph.normal(s)
            p = s - d * n
        pose = [*p, 2.9, 0.4, -0.3]  # a tilted tool
        assert contact_force(ph, pose, np.zeros(3)) == pytest.approx(stiffness * d * n, abs=1e-9)
        # The sensor sees it in the tool frame, without torque (the contact is at the TCP).
        wrench = contact_wrench(ph, pose, np.zeros(6))
        assert wrench[:3] == pytest.approx(rotvec_to_matrix(pose[3:]).T @ (stiffness * d * n), abs=1e-9)
        assert list(wrench[3:]) == [0.0, 0.0, 0.0]
        # Damping along the normal only: pressing in (against n) adds, sliding along the surface does not.
        pressing = contact_force(ph, pose, -0.01 * n)
        assert pressing == pytest.approx((stiffness * d + ph.damping * 0.01) * n, abs=1e-9)
        tangent = np.cross(n, [1.0, 0.0, 0.0])
        assert contact_force(ph, pose, 0.05 * tangent) == pytest.approx(stiffness * d * n, abs=1e-9)
        # Never pulling: leaving fast enough gives no force at all.
        assert list(contact_force(ph, pose, 10.0 * n)) == [0.0, 0.0, 0.0]
    assert ph.depth_for_force(8.0) == pytest.approx(8.0 / stiffness)


def test_config_from_yaml_keys() -> None:
    ph = from_dict({"shape": "cylinder", "axis": "y", "radius": 0.06, "axis_height": 0.1, "stiffness": 8000.0},
                   PhantomConfig, source="<test>")
    assert ph.shape == "cylinder" and ph.axis == "y" and ph.stiffness == 8000.0
    with pytest.raises(ConfigError, match="shape: expected one of"):
        from_dict({"shape": "sphere"}, PhantomConfig, source="<test>")
    with pytest.raises(ConfigError, match=r"semi_axes\[1\]"):
        from_dict({"shape": "ellipsoid", "semi_axes": [0.1, -0.1, 0.05]}, PhantomConfig, source="<test>")
