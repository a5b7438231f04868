"""Geometry against known values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from iorthand import geometry as g


def test_rotvec_known_values() -> None:
    r = g.rotvec_to_matrix([0, 0, math.pi / 2])
    assert np.allclose(r @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(g.rotvec_to_matrix([0, 0, 0]), np.eye(3))
    # UR's "tool pointing down" pose: a half turn about x.
    assert np.allclose(g.rotvec_to_matrix([math.pi, 0, 0]) @ [0, 0, 1], [0, 0, -1])


@pytest.mark.parametrize("rv", [[0.1, -0.2, 0.3], [0, 0, 1e-9], [math.pi - 1e-6, 0, 0], [0, 2.0, 2.0], [-1.2, 0.4, 0.9]])
def test_rotvec_round_trip(rv: list[float]) -> None:
    r = g.rotvec_to_matrix(rv)
    back = g.rotvec_to_matrix(g.matrix_to_rotvec(r))
    assert np.allclose(back, r, atol=1e-9)
    assert g.is_rigid(g.make_transform(r))


def _rigid_by_numpy(t: np.ndarray, tol: float) -> bool:
    """The definition, in numpy's terms: what is_rigid computes in plain floats."""
    r = t[:3, :3]
    return bool(np.all(np.isfinite(t)) and np.allclose(r.T @ r, np.eye(3), atol=tol)
                and abs(np.linalg.det(r) - 1.0) < tol and np.allclose(t[3], [0, 0, 0, 1], atol=tol))


def test_is_rigid_refuses_what_is_not_a_rigid_transform_and_agrees_with_its_definition() -> None:
    t = g.make_transform(g.rotvec_to_matrix([0.3, -0.2, 1.1]), [0.4, -0.1, 0.2])
    assert g.is_rigid(t)
    mirrored = t.copy()
    mirrored[:3, 0] *= -1.0  # orthonormal, but det −1: a reflection
    sheared = t.copy()
    sheared[0, 1] += 1e-4
    projective = t.copy()
    projective[3, 0] = 1e-4
    broken = t.copy()
    broken[1, 2] = math.nan
    for bad in (mirrored, sheared, projective, broken, np.eye(3)):
        assert not g.is_rigid(bad)
    assert g.is_rigid(sheared, tol=1e-3)  # within a looser tolerance
    # Near the tolerance, the same answer as numpy's definition, either way.
    rng = np.random.default_rng(7)
    answers = set()
    for _ in range(2000):
        noisy = g.make_transform(g.rotvec_to_matrix(rng.normal(0, 1, 3)), rng.normal(0, 1, 3))
        noisy += rng.normal(0, 10 ** rng.uniform(-8, -5), (4, 4)) * (rng.random((4, 4)) < 0.3)
        answer = g.is_rigid(noisy, tol=1e-6)
        assert answer == _rigid_by_numpy(noisy, 1e-6)
        answers.add(answer)
    assert answers == {True, False}  # both sides of the tolerance were tried


@pytest.mark.parametrize("rv", [[0.0, 0.0, 0.0], [0, 0, 1e-13], [0, 0, 1e-7], [math.pi, 0, 0], [0.1, -0.2, 0.3],
                                [-1.2, 0.4, 0.9], [0, 2.0, 2.0]])
def test_rotate_matches_the_matrix(rv: list[float]) -> None:
    """The float-only rotation the supervisor uses agrees with Rodrigues' matrix."""
    for v in ([1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.3, -0.7, 0.2]):
        assert np.allclose(g.rotate(rv, v), g.rotvec_to_matrix(rv) @ v, atol=1e-12)


def test_pose_matrix_round_trip_and_composition() -> None:
    pose = np.array([0.3, -0.1, 0.25, 3.0, 0.1, -0.2])
    t = g.pose_to_matrix(pose)
    assert np.allclose(g.pose_to_matrix(g.matrix_to_pose(t)), t)
    assert np.allclose(g.compose(t, g.invert(t)), np.eye(4))
    a = g.compose(g.translation(1, 0, 0), g.rot_z(math.pi / 2))
    assert np.allclose(a @ [1, 0, 0, 1], [1, 1, 0, 1])  # rotate first, then translate
    assert math.isclose(g.rotation_angle(g.rot_x(0.3), g.rot_x(0.5)), 0.2)


def test_bad_pose_shape_is_named() -> None:
    with pytest.raises(ValueError, match="6 numbers"):
        g.pose_to_matrix([1, 2, 3])


def test_interpolation_stays_rigid() -> None:
    a = g.pose_to_matrix([0, 0, 0, 0, 0, 0])
    b = g.pose_to_matrix([1, 0, 0, 0, 0, math.pi / 2])
    mid = g.interpolate_pose(a, b, 0.5)
    assert g.is_rigid(mid)
    assert np.allclose(mid[:3, 3], [0.5, 0, 0])
    assert math.isclose(g.rotation_angle(a, mid), math.pi / 4, abs_tol=1e-9)


def test_orthonormalize() -> None:
    noisy = g.rot_y(0.4)[:3, :3] + 0.01
    r = g.orthonormalize(noisy)
    assert np.allclose(r.T @ r, np.eye(3)) and math.isclose(np.linalg.det(r), 1.0)
