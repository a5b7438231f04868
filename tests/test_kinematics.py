"""UR3e/UR5e kinematics: forward kinematics against known values, analytic IK round trips, reach."""

from __future__ import annotations

import math

import numpy as np
import pytest

from iorthand import geometry, kinematics


def test_zero_posture_matches_the_dh_table():
    # All joints at 0: the arm lies along -x; flange at x = a2 + a3, y = -(d4 + d6), z = d1 - d5.
    for m in (kinematics.UR3E, kinematics.UR5E):
        t = kinematics.forward(m, np.zeros(6))
        assert t[:3, 3] == pytest.approx([m.a[1] + m.a[2], -(m.d[3] + m.d[5]), m.d[0] - m.d[4]], abs=1e-9)


def test_home_posture_of_ur3e():
    t = kinematics.forward(kinematics.UR3E, kinematics.HOME_Q)
    # Home: tool pointing down (z axis of the flange along -z of the base).
    assert t[:3, 2] == pytest.approx([0.0, 0.0, -1.0], abs=1e-6)
    # Upper arm up, forearm along -x, wrist 2 offset d5 further along -x, flange d6 below wrist 3.
    d1, a2, a3, d4, d5, d6 = 0.15185, -0.24355, -0.2132, 0.13105, 0.08535, 0.0921
    assert t[:3, 3] == pytest.approx([a3 - d5, -d4, d1 - a2 - d6], abs=1e-6)


@pytest.mark.parametrize("name", ["ur3e", "ur5e"])
def test_inverse_recovers_random_postures(name):
    m = kinematics.model(name)
    rng = np.random.default_rng(7)
    for _ in range(200):
        q = rng.uniform(-math.pi, math.pi, 6)
        t = kinematics.forward(m, q)
        sols = kinematics.inverse(m, t)
        assert sols, q
        for s in sols:  # every returned solution is exact
            assert geometry.translation_distance(kinematics.forward(m, s), t) < 1e-6
        best = kinematics.nearest(sols, q)
        assert best is not None and np.max(np.abs(best - q)) < 1e-6


def test_tcp_offset_is_applied_on_the_flange():
    m = kinematics.UR3E
    offset = [0.0, 0.0, 0.15, 0.0, 0.0, 0.0]
    q = kinematics.solve_near(m, [0.30, 0.0, 0.20, math.pi, 0.0, 0.0], tcp_offset=offset)
    assert q is not None
    tcp = kinematics.forward(m, q, offset)
    assert tcp[:3, 3] == pytest.approx([0.30, 0.0, 0.20], abs=1e-6)
    flange = kinematics.forward(m, q)
    assert flange[2, 3] == pytest.approx(0.35, abs=1e-6)  # 15 cm above the tip: the tool points down


def test_out_of_reach_and_inside_the_shoulder_cylinder_have_no_solution():
    m = kinematics.UR3E
    assert kinematics.inverse(m, [0.6, 0.3, 0.5, math.pi, 0.0, 0.0]) == []
    assert kinematics.inverse(m, [0.0, 0.0, 0.30, math.pi, 0.0, 0.0]) == []  # on the base axis
    assert 0.5 < m.reach < 0.75  # an upper bound of the flange distance from the shoulder


def test_default_solution_is_elbow_up_tool_down():
    q = kinematics.solve_near(kinematics.UR3E, [0.30, 0.0, 0.20, math.pi, 0.0, 0.0])
    assert q is not None
    assert q[1] == pytest.approx(-math.pi / 2, abs=0.3) and q[2] > 0  # shoulder up, elbow bent like home
    pts = kinematics.link_points(kinematics.UR3E, q)
    assert pts.shape == (9, 3) and pts[-1] == pytest.approx([0.30, 0.0, 0.20], abs=1e-6)


@pytest.mark.parametrize("name", ["ur3e", "ur5e"])
def test_the_jacobian_is_the_derivative_of_the_forward_kinematics(name):
    """Central differences of the TCP pose, per joint, against each column: the linear rows are the TCP's velocity,
    the angular rows the rotation's (R(q+h)·R(q-h)ᵀ as a rotation vector over 2h)."""
    m = kinematics.model(name)
    rng = np.random.default_rng(7)
    h = 1e-6
    for i in range(20):
        q = rng.uniform(-math.pi, math.pi, 6)
        offset = [0.01, -0.02, 0.15, 0.1, 0.0, 0.2] if i % 2 else None
        jac, tcp = kinematics.jacobian(m, q, offset)
        assert np.allclose(tcp, kinematics.forward(m, q, offset), atol=1e-12)
        for j in range(6):
            dq = np.zeros(6)
            dq[j] = h
            ahead, behind = kinematics.forward(m, q + dq, offset), kinematics.forward(m, q - dq, offset)
            linear = (ahead[:3, 3] - behind[:3, 3]) / (2 * h)
            angular = geometry.matrix_to_rotvec(ahead[:3, :3] @ behind[:3, :3].T) / (2 * h)
            assert np.allclose(jac[:3, j], linear, atol=1e-6), (i, j)
            assert np.allclose(jac[3:, j], angular, atol=1e-6), (i, j)
