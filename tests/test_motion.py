"""Named poses, straight-line Cartesian planning at the speed limit, workspace and reach checks."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from iorthand import geometry, motion

START = [0.30, 0.0, 0.20, math.pi, 0.0, 0.0]
LIMITS = motion.Limits(linear_speed=0.03, angular_speed=0.2, acceleration=0.25)


def test_trapezoid_duration_and_progress():
    assert motion.trapezoid_duration(0.1, 0.03, 0.25) == pytest.approx(0.1 / 0.03 + 0.03 / 0.25)
    assert motion.trapezoid_duration(0.0001, 0.03, 0.25) == pytest.approx(2 * math.sqrt(0.0001 / 0.25))
    d = motion.trapezoid_duration(0.1, 0.03, 0.25)
    s = [motion.trapezoid_progress(t, d, 0.1, 0.03, 0.25) for t in np.linspace(0, d, 50)]
    assert s[0] == 0.0 and s[-1] == 1.0 and all(b >= a for a, b in itertools.pairwise(s))
    assert motion.trapezoid_progress(d / 2, d, 0.1, 0.03, 0.25) == pytest.approx(0.5, abs=1e-6)


def test_plan_is_a_straight_line_timed_at_the_speed_limit():
    goal = [0.35, 0.05, 0.25, math.pi, 0.0, 0.0]
    plan = motion.check_plan(motion.plan_line("home", START, goal, LIMITS), LIMITS)
    assert plan.ok and plan.reason == "ok"
    length = math.dist(START[:3], goal[:3])
    assert plan.length == pytest.approx(length)
    assert plan.duration == pytest.approx(length / 0.03 + 0.03 / 0.25)
    # every sample on the segment; speeds never above the limit
    d = np.asarray(goal[:3]) - np.asarray(START[:3])
    for p in plan.poses[:, :3]:
        off = p - np.asarray(START[:3])
        assert np.linalg.norm(off - np.dot(off, d) / np.dot(d, d) * d) < 1e-9
    speeds = np.linalg.norm(np.diff(plan.poses[:, :3], axis=0), axis=1) / np.diff(plan.times)
    assert speeds.max() <= 0.03 * 1.01
    assert plan.joints is not None and len(plan.joints) == len(plan.poses)


def test_rotation_only_is_timed_by_the_angular_limit():
    goal = [*START[:3], 0.0, math.pi, 0.0]  # half a turn about z, tool still down
    plan = motion.plan_line("turn", START, goal, LIMITS)
    assert plan.length == pytest.approx(0.0, abs=1e-9)
    assert plan.duration >= math.pi / 0.2


def test_workspace_refusal_names_the_axis_and_where():
    goal = [0.30, 0.0, 0.50, math.pi, 0.0, 0.0]
    plan = motion.check_plan(motion.plan_line("up", START, goal, LIMITS), LIMITS)
    assert not plan.ok and not plan.inside_workspace
    assert "z=" in plan.reason and "0.450" in plan.reason and "along the path" in plan.reason


def test_reach_refusal():
    lim = motion.Limits(0.03, 0.2, workspace_min=(-1, -1, -1), workspace_max=(1, 1, 1))
    plan = motion.check_plan(motion.plan_line("far", START, [0.6, 0.0, 0.3, math.pi, 0, 0], lim), lim)
    assert plan.inside_workspace and not plan.reachable and "reach" in plan.reason


def test_named_poses():
    poses = {"home": [0.3, 0.1, 0.3, math.pi, 0, 0]}
    assert motion.resolve_pose("home", START, poses) == pytest.approx(poses["home"])
    up = motion.resolve_pose("retract", START, poses, retract_distance=0.05)
    assert up[:3] == pytest.approx([0.30, 0.0, 0.25]) and up[3:] == pytest.approx(START[3:])
    marker = geometry.make_transform(None, [0.35, 0.05, 0.05])
    above = motion.resolve_pose("above_marker:7", START, poses, {7: marker}, marker_standoff=0.1)
    t = geometry.pose_to_matrix(above)
    assert t[:3, 3] == pytest.approx([0.35, 0.05, 0.15]) and t[:3, 2] == pytest.approx([0, 0, -1], abs=1e-9)
    with pytest.raises(motion.PoseError, match="not in view"):
        motion.resolve_pose("above_marker:8", START, poses, {7: marker})
    with pytest.raises(motion.PoseError, match="unknown pose"):
        motion.resolve_pose("elsewhere", START, poses)
    refused = motion.plan_to("elsewhere", START, LIMITS, poses)
    assert not refused.ok and "unknown pose" in refused.reason


def test_summary_fits_a_control_reply():
    import json

    goal = [0.40, -0.25, 0.40, math.pi, 0.0, 0.0]
    plan = motion.check_plan(motion.plan_line("corner", START, goal, LIMITS), LIMITS)
    text = json.dumps(plan.summary(token="x" * 24, ttl=10.0))
    assert len(text) < 4096
