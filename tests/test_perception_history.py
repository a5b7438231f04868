"""Robot-pose and servo-angle histories: interpolation at a frame's capture time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from iorthand.geometry import compose, pose_to_matrix, rot_z, rotation_angle, translation, translation_distance
from iorthand_edge.perception.history import PoseHistory, ServoHistory

MS = 1_000_000


def test_pose_interpolated_between_samples_not_the_latest() -> None:
    history = PoseHistory(span_s=1.0, max_extrapolation_s=0.02)
    history.add(0, translation(0.0, 0.0, 0.0))
    history.add(8 * MS, compose(translation(0.008, 0.0, 0.0), rot_z(0.08)))
    history.add(16 * MS, compose(translation(0.016, 0.0, 0.0), rot_z(0.16)))
    pose = history.at(4 * MS)
    assert pose is not None
    assert translation_distance(pose, translation(0.004, 0.0, 0.0)) < 1e-12
    assert rotation_angle(pose, rot_z(0.04)) < 1e-9


def test_ur_pose_is_a_rotation_vector() -> None:
    """[x,y,z,rx,ry,rz] through pose_to_matrix: the rotation part is about the rotvec's axis, not Euler angles."""
    history = PoseHistory()
    history.add(0, pose_to_matrix([0.1, 0.2, 0.3, 0.0, math.pi, 0.0]))
    history.add(10 * MS, pose_to_matrix([0.1, 0.2, 0.3, 0.0, math.pi, 0.0]))
    pose = history.at(5 * MS)
    assert pose is not None
    np.testing.assert_allclose(pose[:3, :3], np.diag([-1.0, 1.0, -1.0]), atol=1e-9)


def test_outside_the_history_is_none_and_short_extrapolation_holds() -> None:
    history = PoseHistory(span_s=1.0, max_extrapolation_s=0.02)
    assert history.at(0) is None
    history.add(100 * MS, translation(0.1, 0.0, 0.0))
    history.add(108 * MS, translation(0.2, 0.0, 0.0))
    assert history.at(50 * MS) is None  # older than anything kept
    held = history.at(120 * MS)
    assert held is not None and translation_distance(held, translation(0.2, 0.0, 0.0)) < 1e-12
    assert history.at(200 * MS) is None  # the robot state stopped: no pose rather than a stale one


def test_old_samples_are_dropped_and_out_of_order_ones_inserted() -> None:
    history = PoseHistory(span_s=0.1)
    for i in range(100):
        history.add(i * 8 * MS, translation(i * 0.001, 0.0, 0.0))
    assert len(history) <= 15
    history.add(780 * MS, translation(0.5, 0.0, 0.0))  # late arrival between two kept samples
    pose = history.at(780 * MS)
    assert pose is not None and translation_distance(pose, translation(0.5, 0.0, 0.0)) < 1e-12


def test_rejects_a_non_rigid_pose() -> None:
    with pytest.raises(ValueError, match="rigid"):
        PoseHistory().add(0, np.diag([2.0, 1.0, 1.0, 1.0]))


def test_servo_angles_interpolate_and_hold() -> None:
    servos = ServoHistory()
    servos.add(0, 0.0, 0.2)
    servos.add(100 * MS, 0.4, -0.2)
    assert servos.at(25 * MS) == pytest.approx((0.1, 0.1))
    # Published on change and as a heartbeat (2 Hz by default): the last value holds for a few heartbeats.
    assert servos.at(1_000 * MS) == pytest.approx((0.4, -0.2))


def test_servo_angles_from_long_ago_are_unknown() -> None:
    """The red team's case: the servo unit stopped publishing 600 s ago; a frame now has no known camera angle
    (None, as the robot pose's history says after its own limit), not the angles of 10 minutes ago."""
    servos = ServoHistory(2.0)  # as the media process built it without a heartbeat rate
    servos.add(0, 0.30, -0.10)
    assert servos.at(600_000 * MS) is None
    assert servos.at(1_400 * MS) == pytest.approx((0.30, -0.10))  # within three heartbeats at 2 Hz
    assert servos.at(1_600 * MS) is None
    from iorthand_edge.perception.history import servo_max_age

    slow = ServoHistory(2.0, servo_max_age(0.5))  # a heartbeat every 2 s: 6 s
    slow.add(0, 0.30, -0.10)
    assert slow.at(5_900 * MS) == pytest.approx((0.30, -0.10)) and slow.at(6_100 * MS) is None
