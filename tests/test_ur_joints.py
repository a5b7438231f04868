"""The UR emulator's arm with joints and its force/torque sensor (issue 22, item 5).

Through the REAL ur_rtde library: the emulator runs in this process (its own threads, on a loopback address of
its own: ur_rtde hard-codes the ports) and ur_rtde in a child process (its constructors hold the GIL), driven
over a JSON-lines pipe with a timeout on every call, as in tests/test_ur_emulator.py. The expected values come
from iorthand.kinematics and the phantom model, never from the emulator. The arm model itself (no ur_rtde) is
tested at the end, on a simulated clock.
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from iorthand import geometry
from iorthand import kinematics as kin
from iorthand_edge.force.contact import PhantomConfig, contact_force
from iorthand_edge.ur_emulator import HOME_POSE, HOME_Q, ControllerConfig, EmulatorConfig, UREmulator
from iorthand_edge.ur_emulator.arm import ArmModel, ForceMode, default_joint_limits
from iorthand_edge.ur_emulator.process import UR_PORTS, free_loopback_host
from tests.test_ur_emulator import WORKER, RtdeWorker, _Lines, _wait, needs_ur_rtde

DOWN = (math.pi, 0.0, 0.0)
STIFFNESSES = (2000.0, 4000.0, 8000.0)  # N/m: the must-show runs at 2, 4 and 8 N/mm
# A thigh under the home pose: a cylinder along x whose axis is at y = -0.1, z = 0.08 (its top at z = 0.15).
THIGH = {"shape": "cylinder", "axis": "x", "radius": 0.07, "axis_height": 0.08, "x_range": [0.2, 0.4],
         "y_range": [-0.2, 0.0], "damping": 20.0}
THIGH_AXIS = np.array([0.3, -0.1, 0.08])

# Helpers that run inside the ur_rtde child, prepended to test_ur_emulator's worker (they use its ``objs``).
HELPERS = r'''
import math, time
def q_during_speedl(xd, acc, duration):
    r, c = objs["r"], objs["c"]
    ok = c.speedL(xd, acc, 0.0)
    samples, t0 = [], time.perf_counter()
    while time.perf_counter() - t0 < duration:
        samples.append([r.getActualQ(), r.getActualTCPPose()])
        time.sleep(0.01)
    return {"ok": ok, "stopped": c.speedStop(10.0), "samples": samples}
def servol_track(p0, direction, speed, duration, hold, dt, lookahead):
    r, c = objs["r"], objs["c"]
    rows, t0 = [], time.perf_counter()
    while True:
        t = time.perf_counter() - t0
        if t > duration + hold:
            break
        s = speed * min(t, duration)
        target = [p0[i] + direction[i] * s for i in range(3)] + list(p0[3:])
        ok = c.servoL(target, 0.5, 0.5, dt, lookahead, 300)
        rows.append([t, target, r.getActualTCPPose(), ok])
        time.sleep(max(0.0, dt - (time.perf_counter() - t0 - t)))
    c.servoStop(10.0)
    return rows
def servoj_to(q, duration, dt, lookahead):
    r, c = objs["r"], objs["c"]
    t0, oks = time.perf_counter(), []
    while time.perf_counter() - t0 < duration:
        oks.append(c.servoJ(q, 0.5, 0.5, dt, lookahead, 300))
        time.sleep(dt)
    c.servoStop(10.0)
    return all(oks)
def force_run(task, selection, wrench, limits, settle, hold, xd, slide):
    r, c = objs["r"], objs["c"]
    ok = c.forceMode(task, selection, wrench, 2, limits)
    time.sleep(settle)
    held, t0 = [], time.perf_counter()
    while time.perf_counter() - t0 < hold:
        held.append([r.getActualTCPForce(), r.getActualTCPPose()])
        time.sleep(0.02)
    ok = c.speedL(xd, 0.5, 0.0) and ok  # the non-compliant axes follow speedL, z stays in force mode
    slid, t0 = [], time.perf_counter()
    while time.perf_counter() - t0 < slide:
        slid.append([r.getActualTCPForce(), r.getActualTCPPose()])
        time.sleep(0.02)
    return {"ok": ok, "held": held, "slid": slid, "stopped": c.forceModeStop()}
'''


class JointWorker(RtdeWorker):
    """test_ur_emulator's ur_rtde child with the helpers above."""

    def __init__(self) -> None:  # replaces the parent's: the same child, another script
        self.proc = subprocess.Popen([sys.executable, "-c", HELPERS + WORKER], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        self.lines = _Lines(self.proc)


@pytest.fixture
def make_emulator() -> Iterator[Callable[..., UREmulator]]:
    emulators: list[UREmulator] = []

    def make(**controller: Any) -> UREmulator:
        # 250 Hz instead of the e-Series' 500: the same protocol and behaviour at half the CPU on a 2-core runner.
        config = EmulatorConfig(host=free_loopback_host(UR_PORTS), control_port=None,
                                controller=ControllerConfig(frequency=250.0, unlock_delay=0.1, **controller))
        emu = UREmulator(config).start()
        emulators.append(emu)
        return emu

    yield make
    for emu in emulators:
        emu.stop()


@pytest.fixture
def worker() -> Iterator[JointWorker]:
    w = JointWorker()
    try:
        yield w
    finally:
        w.close()


def connect(w: JointWorker, emu: UREmulator) -> None:
    w.request(op="new_receive", host=emu.config.host, timeout=10)
    w.request(op="new_control", host=emu.config.host, timeout=15)


def fk(q: Any, tcp_offset: Any = None) -> np.ndarray:
    return geometry.matrix_to_pose(kin.forward(kin.UR3E, q, tcp_offset))


def pose_error(a: Any, b: Any) -> tuple[float, float]:
    """(metres, radians) between two UR poses."""
    ta, tb = geometry.pose_to_matrix(a), geometry.pose_to_matrix(b)
    return geometry.translation_distance(ta, tb), geometry.rotation_angle(ta, tb)


# --- through ur_rtde -------------------------------------------------------------------------------------------


@needs_ur_rtde
def test_actual_q_follows_speedl(make_emulator: Callable[..., UREmulator], worker: JointWorker) -> None:
    emu = make_emulator()
    connect(worker, emu)
    assert worker.call("r", "getActualQ") == pytest.approx(list(HOME_Q), abs=1e-12)
    # 42 mm/s and 0.3 rad/s about z for 0.6 s: every joint but wrist 2 turns.
    res = worker.fn("q_during_speedl", [0.03, 0.02, -0.01, 0.0, 0.0, 0.3], 1.0, 0.6)
    assert res["ok"] is True and res["stopped"] is True
    qs = np.array([s[0] for s in res["samples"]])
    assert len({tuple(q) for q in qs}) >= 10, "getActualQ must change during the speedL, not only at its end"
    assert float(np.max(np.abs(np.diff(qs, axis=0)))) < 0.05  # continuously: no jump between branches
    assert float(np.max(np.abs(qs[-1] - np.array(HOME_Q)))) > 0.05
    # At rest: the joints are exactly those of the TCP pose, the solution nearest where they started. speedStop
    # returns before the rotation has decelerated (0.3 rad/s at 10 rad/s²: 30 ms), and the receive interface's
    # state can be a period behind the controller's: read both once the arm is still (a loaded CI machine read
    # the pose 4e-5 rad before the controller's joints).
    assert _wait(lambda: not any(worker.call("r", "getActualTCPSpeed")), 2.0), "the arm did not come to rest"
    q = worker.call("r", "getActualQ")
    pose = worker.call("r", "getActualTCPPose")
    assert pose_error(fk(q), pose)[0] < 1e-9 and pose_error(fk(q), pose)[1] < 1e-7  # acos: ~3e-8 resolution
    assert q == pytest.approx(list(kin.solve_near(kin.UR3E, pose, HOME_Q)), abs=1e-9)
    assert pose_error(pose, HOME_POSE)[0] > 0.015  # the TCP did move
    at_q = worker.call("c", "getForwardKinematics")  # FK of the current joints, by the controller
    assert pose_error(at_q, pose)[0] < 1e-9 and pose_error(at_q, pose)[1] < 1e-7


@needs_ur_rtde
def test_inverse_and_forward_kinematics_round_trip(make_emulator: Callable[..., UREmulator],
                                                   worker: JointWorker) -> None:
    emu = make_emulator()
    connect(worker, emu)
    # Without qnear the controller answers the solution nearest the current joints.
    assert worker.call("c", "getInverseKinematics", list(HOME_POSE)) == pytest.approx(list(HOME_Q), abs=1e-9)
    poses = [[0.25, 0.10, 0.15, math.pi, 0.0, 0.0], [0.35, -0.20, 0.25, 2.9, 0.5, 0.1],
             [-0.20, 0.30, 0.30, 0.0, math.pi, 0.0], [0.10, -0.35, 0.05, 2.2, -2.2, 0.0]]
    for pose in poses:
        q = worker.call("c", "getInverseKinematics", pose)
        assert pose_error(fk(q), pose)[0] < 1e-4 and pose_error(fk(q), pose)[1] < 1e-4
        # qnear picks the branch: each of iorthand's solutions comes back when asked near it.
        for solution in kin.inverse(kin.UR3E, pose):
            near = worker.call("c", "getInverseKinematics", pose, list(solution + 0.01))
            assert near == pytest.approx(list(solution), abs=1e-9)
    # With a TCP offset (setTcp), IK and FK both use it; getForwardKinematics(q, offset) takes it as given.
    offset = [0.0, 0.0, 0.05, 0.0, 0.0, 0.0]
    assert worker.call("c", "setTcp", offset) is True
    assert _wait(lambda: worker.call("r", "getActualTCPPose")[2] == pytest.approx(HOME_POSE[2] - 0.05), 1.0)
    assert worker.call("c", "getTCPOffset") == pytest.approx(offset)
    for pose in poses:
        q = worker.call("c", "getInverseKinematics", pose)
        back = worker.call("c", "getForwardKinematics", q, offset)
        assert pose_error(back, pose)[0] < 1e-4 and pose_error(back, pose)[1] < 1e-4  # the 0.1 mm
        assert pose_error(fk(q, offset), pose)[0] < 1e-9
        assert pose_error(fk(q), pose)[0] == pytest.approx(0.05, abs=1e-9)  # the flange is 5 cm behind


@needs_ur_rtde
def test_servol_follows_a_moving_target(make_emulator: Callable[..., UREmulator], worker: JointWorker) -> None:
    emu = make_emulator()
    connect(worker, emu)
    speed, lookahead = 0.03, 0.05
    rows = worker.fn("servol_track", list(HOME_POSE), [0.0, 1.0, 0.0], speed, 1.0, 0.6, 0.008, lookahead,
                     timeout=15)
    assert all(row[3] is True for row in rows)
    tracking = [row for row in rows if 0.3 < row[0] < 1.0]
    assert len(tracking) > 20
    lag = [pose_error(target, actual)[0] for _, target, actual, _ in tracking]
    # A first-order lag of the lookahead time follows a ramp v·τ behind (1.5 mm); allow for the stream's period
    # and a loaded machine. Not following at all would leave it up to 30 mm behind.
    print(f"servoL: lag while tracking {1000 * float(np.median(lag)):.2f} mm median, {1000 * max(lag):.2f} mm max")
    assert max(lag) < 0.006
    final_target = rows[-1][1]
    assert _wait(lambda: pose_error(worker.call("r", "getActualTCPPose"), final_target)[0] < 1e-4, 2.0)
    assert emu.status()["q"] != pytest.approx(list(HOME_Q), abs=1e-3)


@needs_ur_rtde
def test_movej_and_servoj_reach_their_joints(make_emulator: Callable[..., UREmulator], worker: JointWorker) -> None:
    emu = make_emulator()
    connect(worker, emu)
    q1 = np.add(HOME_Q, [0.2, -0.1, 0.15, -0.1, 0.2, 0.5]).tolist()
    assert worker.call("c", "moveJ", q1, 1.0, 2.0) is True
    assert emu.status()["q"] == pytest.approx(q1, abs=1e-9)  # a synchronous moveJ returns at its target
    assert _wait(lambda: worker.call("r", "getActualQ") == pytest.approx(q1, abs=1e-9), 1.0)
    assert pose_error(worker.call("r", "getActualTCPPose"), fk(q1))[0] < 1e-9  # the TCP follows by FK
    # moveJ to a pose (moveJ_IK): the joints nearest the current ones.
    pose2 = [0.28, 0.05, 0.18, math.pi, 0.0, 0.0]
    assert worker.call("c", "moveJ_IK", pose2, 1.0, 2.0) is True
    assert _wait(lambda: pose_error(worker.call("r", "getActualTCPPose"), pose2)[0] < 1e-9, 1.0)
    assert emu.status()["q"] == pytest.approx(list(kin.solve_near(kin.UR3E, pose2, q1)), abs=1e-9)
    # servoJ streamed to other joints: the joints converge there, the TCP with them.
    q2 = np.add(HOME_Q, [-0.15, 0.1, -0.1, 0.2, -0.1, -0.3]).tolist()
    assert worker.fn("servoj_to", q2, 1.0, 0.008, 0.05, timeout=15) is True
    assert _wait(lambda: worker.call("r", "getActualQ") == pytest.approx(q2, abs=1e-4), 1.0)
    assert pose_error(worker.call("r", "getActualTCPPose"), fk(worker.call("r", "getActualQ")))[0] < 1e-9


@needs_ur_rtde
def test_unreachable_movel_is_refused_and_the_arm_does_not_move(make_emulator: Callable[..., UREmulator],
                                                                worker: JointWorker) -> None:
    emu = make_emulator()
    connect(worker, emu)
    far = [2.0, 0.0, 0.2, math.pi, 0.0, 0.0]  # 2 m away: beyond any UR3e's reach
    # The non-destructive checks answer without stopping anything.
    assert worker.call("c", "getInverseKinematicsHasSolution", far) is False
    assert worker.call("c", "getInverseKinematicsHasSolution", list(HOME_POSE)) is True
    assert worker.call("c", "isPoseWithinSafetyLimits", far) is False
    before = emu.status()
    # moveL: URScript's movel fails (no inverse kinematics): a runtime error stops the program, ur_rtde answers
    # False ("RTDE control script is not running"), the safety mode stays normal and the arm never moved.
    assert worker.call("c", "moveL", far, 0.25, 1.2) is False
    after = emu.status()
    assert after["pose"] == before["pose"] and after["q"] == before["q"]
    assert after["runtime_state"] == "STOPPED" and after["safety_mode"] == "NORMAL"
    assert any("runtime exception" in e and "no inverse kinematics solution" in e for e in after["events"])
    assert _wait(lambda: worker.call("c", "isProgramRunning") is False, 1.0)
    assert worker.call("r", "getSafetyMode") == 1
    time.sleep(0.2)
    assert emu.status()["pose"] == before["pose"]
    # Recovered by a new script; a reachable moveL is carried out.
    assert worker.call("c", "reuploadScript") is True
    assert _wait(lambda: worker.call("c", "isProgramRunning"), 2.0)
    target = [0.27, -0.05, 0.18, math.pi, 0.0, 0.0]
    assert worker.call("c", "moveL", target, 0.25, 1.2) is True
    assert emu.status()["pose"] == pytest.approx(target, abs=1e-9)


@needs_ur_rtde
def test_speedl_out_of_the_workspace_ends_in_a_protective_stop(make_emulator: Callable[..., UREmulator],
                                                               worker: JointWorker) -> None:
    emu = make_emulator()
    # The reach along +x at the home height, tool down, from iorthand's kinematics.
    lo, hi = HOME_POSE[0], 1.0
    while hi - lo > 1e-4:
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if kin.inverse(kin.UR3E, [mid, *HOME_POSE[1:]]) else (lo, mid)
    emu.set_pose([lo - 0.02, *HOME_POSE[1:]])
    connect(worker, emu)
    assert worker.call("c", "speedL", [0.05, 0.0, 0.0, 0.0, 0.0, 0.0], 1.0, 0.0) is True
    assert _wait(lambda: worker.call("r", "isProtectiveStopped"), 3.0)
    status = emu.status()
    assert status["safety_mode"] == "PROTECTIVE_STOP" and status["motion"] == "idle"
    assert status["pose"][0] < lo  # stopped before the edge of the reach...
    assert kin.inverse(kin.UR3E, status["pose"])  # ...where the arm still has joints
    assert pose_error(fk(status["q"]), status["pose"])[0] < 1e-9
    print(f"speedL out of reach: {[e for e in status['events'] if 'protective stop:' in e][-1]}")
    # ur_rtde's control connection reads its own RTDE stream, which may show the stop a few packets after the
    # receive connection's does; once it sees the program stopped, a new speedL is refused.
    assert _wait(lambda: worker.call("c", "isProgramRunning") is False, 1.0)
    assert worker.call("c", "speedL", [0.05, 0.0, 0.0, 0.0, 0.0, 0.0], 1.0, 0.0) is False


@needs_ur_rtde
def test_joint_limit_is_refused(make_emulator: Callable[..., UREmulator], worker: JointWorker) -> None:
    limits = list(default_joint_limits("ur3e"))
    upper = HOME_Q[0] + 0.3
    limits[0] = (HOME_Q[0] - 0.3, upper)  # a base joint limited to ±17° around home (a safety configuration)
    emu = make_emulator(joint_limits=tuple(limits))
    connect(worker, emu)
    beyond = np.add(HOME_Q, [0.5, 0.0, 0.0, 0.0, 0.0, 0.0]).tolist()
    assert worker.call("c", "isJointsWithinSafetyLimits", beyond) is False
    assert worker.call("c", "isJointsWithinSafetyLimits", list(HOME_Q)) is True
    # moveJ past the limit: the controller's protective stop ("position close to joint limits") ends it at the
    # limit; ur_rtde's moveJ answers False and the driver sees the protective stop.
    assert worker.call("c", "moveJ", beyond, 1.0, 2.0) is False
    assert _wait(lambda: worker.call("r", "isProtectiveStopped"), 1.0)
    assert worker.call("r", "getSafetyMode") == 3
    status = emu.status()
    assert upper - 0.02 < status["q"][0] <= upper  # it moved toward the target and stopped at the limit
    assert any("protective stop: position close to joint limits: base" in e for e in status["events"])
    time.sleep(0.2)
    assert emu.status()["q"] == status["q"]
    assert worker.call("c", "moveJ", list(HOME_Q), 1.0, 2.0) is False  # nothing moves until it is cleared


@needs_ur_rtde
def test_ft_sensor_reads_k_d_along_the_normal_of_a_curved_phantom(make_emulator: Callable[..., UREmulator],
                                                                  worker: JointWorker) -> None:
    emu = make_emulator()
    connect(worker, emu)
    assert worker.call("r", "getActualTCPForce") == [0.0] * 6  # free space
    n = np.array([0.0, math.sin(0.35), math.cos(0.35)])  # 20° off the top of the thigh
    surface = THIGH_AXIS + 0.07 * n
    for k in STIFFNESSES:
        emu.set_phantom({**THIGH, "stiffness": k})
        magnitudes = []
        for d in (0.001, 0.002, 0.004):
            pose = [*(surface - d * n), *DOWN]
            assert worker.call("c", "moveL", pose, 0.05, 0.5) is True
            # At rest, not only there: the phantom's damping (20 N·s/m) answers the speed of the move's last step,
            # and a reading within 1e-9 m of the pose while that step's 1.5e-7 m/s lingered was 2.9e-6 N off (CI).
            assert _wait(lambda p=pose: worker.call("r", "getActualTCPPose") == pytest.approx(p, abs=1e-9)
                         and not any(worker.call("r", "getActualTCPSpeed")), 1.0)
            wrench = worker.call("r", "getActualTCPForce")
            # Base frame at the TCP, as a UR reports it: k·d along the surface normal, no torque.
            assert wrench[:3] == pytest.approx(list(k * d * n), abs=1e-6)
            assert wrench[3:] == pytest.approx([0.0] * 3, abs=1e-9)
            # The raw sensor wrench is the same force in the tool frame.
            raw = worker.call("r", "getFtRawWrench")
            assert raw[:3] == pytest.approx(list(geometry.rotvec_to_matrix(DOWN).T @ (k * d * n)), abs=1e-6)
            magnitudes.append(float(np.linalg.norm(wrench[:3])))
        print(f"k = {k / 1000:g} N/mm: |F| = {[round(m, 3) for m in magnitudes]} N at 1, 2, 4 mm")
        assert magnitudes == pytest.approx([k * 0.001, k * 0.002, k * 0.004], abs=1e-6)
        assert worker.call("c", "moveL", [*(surface + 0.01 * n), *DOWN], 0.05, 0.5) is True  # off again


@needs_ur_rtde
def test_force_mode_holds_the_target_force_on_the_phantom(make_emulator: Callable[..., UREmulator],
                                                          worker: JointWorker) -> None:
    k, target = 4000.0, 5.0
    emu = make_emulator(phantom=PhantomConfig(**{**THIGH, "stiffness": k}))
    connect(worker, emu)
    assert worker.call("c", "moveL", [0.3, -0.11, 0.155, *DOWN], 0.05, 0.5) is True  # 5 mm above the thigh
    # Compliant along base z, pushing down with 5 N; x and y follow the program (speedL across the thigh).
    res = worker.fn("force_run", [0.0] * 6, [0, 0, 1, 0, 0, 0], [0.0, 0.0, -target, 0.0, 0.0, 0.0],
                    [0.1, 0.1, 0.05, 1.0, 1.0, 1.0], 1.0, 0.5, [0.0, 0.005, 0.0, 0.0, 0.0, 0.0], 3.0, timeout=20)
    assert res["ok"] is True and res["stopped"] is True
    held = np.array([f for f, _ in res["held"]])
    slid = np.array([f for f, _ in res["slid"]])
    print(f"force mode: Fz held {held[:, 2].min():.2f}..{held[:, 2].max():.2f} N, while sliding "
          f"{slid[:, 2].min():.2f}..{slid[:, 2].max():.2f} N (target {target} N)")
    assert np.all(np.abs(held[:, 2] - target) <= 1.0)  # the issue's ±1 N after settling
    assert np.all(np.abs(slid[:, 2] - target) <= 1.0)  # and while the probe slides over the curved surface
    # The probe went across the thigh (y) and down its curve (z) as far as the surface dropped.
    y0, y1 = res["slid"][0][1][1], res["slid"][-1][1][1]
    assert y1 - y0 == pytest.approx(0.005 * 3.0, abs=0.004)
    z1 = res["slid"][-1][1][2]
    surface_z1 = THIGH_AXIS[2] + math.sqrt(0.07 ** 2 - (y1 - THIGH_AXIS[1]) ** 2)
    assert z1 == pytest.approx(surface_z1 - target / k, abs=5e-4)
    assert emu.status()["force_mode"] is False


# --- the arm model alone, on a simulated clock -----------------------------------------------------------------


def test_wrist_3_turns_without_limit_on_a_ur3e_and_stops_at_360_on_a_ur5e() -> None:
    ur3e = ArmModel("ur3e")
    ur3e.speedl([0.0, 0.0, 0.0, 0.0, 0.0, 1.0], 2.0)  # turning the tool about the vertical
    for _ in range(2500):  # 10 s at 250 Hz: 10 rad
        ur3e.step(0.004)
        assert ur3e.fault is None
    assert ur3e.q[5] - HOME_Q[5] == pytest.approx(-9.75, abs=0.05)  # wound past -360°, continuously
    assert pose_error(fk(ur3e.q), ur3e.pose)[0] < 1e-9
    ur5e = ArmModel("ur5e")
    ur5e.speedl([0.0, 0.0, 0.0, 0.0, 0.0, 1.0], 2.0)
    for _ in range(2500):
        ur5e.step(0.004)
        if ur5e.fault is not None:
            break
    assert ur5e.fault is not None and "joint limits: wrist 3" in ur5e.fault
    assert ur5e.q[5] >= -2 * math.pi and ur5e.mode.value == "idle" and ur5e.twist == [0.0] * 6


def test_force_mode_is_stable_on_a_stiff_phantom_with_late_cycles() -> None:
    """8 N/mm and cycles 100 ms late (a loaded machine): the admittance still settles on the target."""
    phantom = PhantomConfig(**{**THIGH, "stiffness": 8000.0})

    def sensor(pose: Any, twist: Any) -> list[float]:
        return [*contact_force(phantom, pose, twist[:3]), 0.0, 0.0, 0.0]

    arm = ArmModel("ur3e", pose=[0.3, -0.1, 0.1525, *DOWN], wrench=sensor)  # 2.5 mm above the thigh
    arm.force_mode(ForceMode([0.0] * 6, [False, False, True, False, False, False], [0, 0, -8.0, 0, 0, 0],
                             [0.1, 0.1, 0.05, 1, 1, 1]))
    forces = []
    for dt in [0.1] * 20 + [0.004] * 50:  # the approach and the contact all in 100 ms cycles, then normal ones
        arm.step(dt)
        assert arm.fault is None
        forces.append(float(sensor(arm.pose, [0.0] * 6)[2]))
    print(f"force mode, 100 ms cycles: {[round(f, 2) for f in forces[:20]]}")
    assert forces[19] == pytest.approx(8.0, abs=0.05) and forces[-1] == pytest.approx(8.0, abs=0.01)
    assert max(forces) < 9.0  # no overshoot
    assert arm.pose[2] == pytest.approx(0.15 - 8.0 / 8000.0, abs=1e-5)


@pytest.mark.parametrize("dt", [0.002, 0.04, 0.1])
def test_joint_motion_stops_at_the_joint_limit_whatever_the_step(dt: float) -> None:
    """A movej past a joint limit ends at the limit (a protective stop), with a 500 Hz cycle as with a 100 ms one
    (the emulator's cycle on a loaded machine): a step that would cross the limit is not refused whole, which left
    the arm 0.05 rad short at 0.1 s and made test_joint_limit_is_refused fail under load."""
    limits = list(default_joint_limits("ur3e"))
    upper = HOME_Q[0] + 0.3
    limits[0] = (HOME_Q[0] - 0.3, upper)
    arm = ArmModel("ur3e", joint_limits=tuple(limits))
    arm.movej(np.add(HOME_Q, [0.5, 0.0, 0.0, 0.0, 0.0, 0.0]), 1.0, 2.0)
    for _ in range(round(3.0 / dt)):
        arm.step(dt)
        if arm.fault is not None:
            break
    assert arm.fault is not None and "position close to joint limits: base" in arm.fault
    assert arm.q[0] == pytest.approx(upper, abs=1e-9) and arm.within_limits(arm.q)
    assert arm.q[1:] == pytest.approx(np.array(HOME_Q[1:]), abs=1e-9)  # only the base joint moved
    assert pose_error(fk(arm.q), arm.pose)[0] < 1e-9  # the TCP where the joints put it
    assert arm.mode.value == "idle" and arm.twist == [0.0] * 6
