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
