"""Contact mode (issue 22): the operator steers along the surface, the edge holds the force along the probe.

Pure: the admittance replaces the twist's axial part, its sign and bounds, entering and leaving. Closed loop: the
simulated robot on the phantom at the must-show's stiffnesses (2, 4 and 8 N/mm), through a real router: with
the deadman held and a tangential twist, the force stays within ±1 N of the target ≥ 95 % of the time once in
contact and never reaches red."""

from __future__ import annotations

import time

import pytest

from iorthand import keys
from iorthand.protocol import ForceSample, Status
from iorthand_edge.supervisor import Supervisor
from tests.conftest import wait_until
from tests.test_supervisor import POSE, armed

TARGET = 4.0


def contact_supervisor() -> tuple[Supervisor, object]:
    sv, c = armed()
    sv.force_required = True
    sv.update_force(0, False, c.mono)
    sv.contact_ceiling = 6.0
    return sv, c


def test_contact_mode_replaces_the_axial_motion_by_the_admittance() -> None:
    sv, c = contact_supervisor()
    cfg = sv.config.contact
    cfg.integral_gain = 0.0  # the proportional part alone here (the integral: the next test)
    ok, why = sv.set_contact(c.request(sv, "op1", keys.CONTROL_CONTACT), True, TARGET)
    assert ok and sv.contact_target == TARGET, why
    # The tool points down (POSE): the probe's axis is -z of the base. No force yet: it approaches, at most
    # max_speed, whatever the operator asks along the axis (here: pulling up); x stays the operator's.
    sv.update_contact_force(0.0, c.mono)
    c.mono += 0.02
    d = sv.on_command(c.cmd(vx=0.004, vz=0.008), c.wall, c.mono, POSE)
    assert d.accepted and d.status == Status.CONTACT
    assert d.twist[0] == pytest.approx(0.004) and d.twist[2] == pytest.approx(-min(cfg.max_speed, cfg.gain * TARGET))
    # Pressing too hard: it backs off, proportionally.
    sv.update_contact_force(TARGET + 2.0, c.mono)
    c.mono += 0.02
    d = sv.on_command(c.cmd(vx=0.0), c.wall, c.mono, POSE)
    assert d.twist[2] == pytest.approx(cfg.gain * 2.0)
    # Within the deadband: nothing along the axis.
    sv.update_contact_force(TARGET + 0.05, c.mono)
    c.mono += 0.02
    assert sv.on_command(c.cmd(vx=0.0), c.wall, c.mono, POSE).twist[2] == 0.0
    # A force reading older than max_force_age: hold (no axial motion), said so.
    c.mono += cfg.max_force_age + 0.02
    d = sv.on_command(c.cmd(vx=0.0), c.wall, c.mono, POSE)
    assert d.twist[2] == 0.0 and "no fresh force reading" in d.reason


def test_the_admittance_integrates_a_standing_error_without_winding_up() -> None:
    sv, c = contact_supervisor()
    cfg = sv.config.contact
    assert sv.set_contact(c.request(sv, "op1", keys.CONTROL_CONTACT), True, TARGET)[0]
    # Free space: the error is the whole target, the output at its bound: nothing accumulates.
    for _ in range(100):
        c.mono += sv.period
        sv.update_contact_force(0.0, c.mono)
        assert sv.on_command(c.cmd(vx=0.0), c.wall, c.mono, POSE).twist[2] == pytest.approx(-cfg.max_speed)
    # In contact, 0.5 N short of the target (a surface falling away under a sweep): the speed toward it grows
    # with the error's integral, beyond the proportional part.
    speeds = []
    for _ in range(50):
        c.mono += sv.period
        sv.update_contact_force(TARGET - 0.5, c.mono)
        speeds.append(-sv.on_command(c.cmd(vx=0.0), c.wall, c.mono, POSE).twist[2])
    assert speeds[0] == pytest.approx(cfg.gain * 0.5 + cfg.integral_gain * 0.5 * sv.period, rel=1e-6)
    assert speeds[-1] == pytest.approx(cfg.gain * 0.5 + cfg.integral_gain * 0.5 * 50 * sv.period, rel=1e-6)
    # Leaving and entering again starts from nothing.
    assert sv.set_contact(c.request(sv, "op1", keys.CONTROL_CONTACT), False)[0]
    assert sv.set_contact(c.request(sv, "op1", keys.CONTROL_CONTACT), True, TARGET)[0]
    c.mono += sv.period
    sv.update_contact_force(TARGET - 0.5, c.mono)
    assert -sv.on_command(c.cmd(vx=0.0), c.wall, c.mono, POSE).twist[2] == pytest.approx(cfg.gain * 0.5, rel=1e-6)


def test_contact_mode_is_entered_and_left_on_purpose() -> None:
    sv, c = contact_supervisor()
    ok, why = sv.set_contact(c.request(sv, "op1", keys.CONTROL_CONTACT), True, 6.5)
    assert not ok and "below the caution level" in why
    sv.update_force(0, True, c.mono)  # a stale sensor: no contact mode
    ok, why = sv.set_contact(c.request(sv, "op1", keys.CONTROL_CONTACT), True, TARGET)
    assert not ok and "stale" in why
    sv.update_force(0, False, c.mono)
    assert sv.set_contact(c.request(sv, "op1", keys.CONTROL_CONTACT), True, None)[0]
    assert sv.contact_target == sv.config.contact.target
    # Another session cannot switch it: the request is the owner's alone.
    other = sv.set_contact(c.request(sv, "mallory", keys.CONTROL_CONTACT), False)
    assert not other[0] and sv.contact_target is not None
    sv.stop("stop from nurse")  # a halt that waits for a fresh press ends contact mode too
    assert sv.contact_target is None
    assert any("contact mode off: stop from nurse" in r for _, r in sv.interventions)
    assert sv.set_contact(c.request(sv, "op1", keys.CONTROL_CONTACT), True, TARGET)[0]
    assert sv.set_contact(c.request(sv, "op1", keys.CONTROL_CONTACT), False)[0] and sv.contact_target is None


def test_a_sensor_gone_silent_in_contact_stops_the_probe_ends_contact_mode_and_waits_for_a_fresh_press() -> None:
    """The probe on a patient, the sensor silent: sliding on would press blind. The stop is latched (the deadman
    held through it moves nothing, even once the sensor is back) and contact mode ends."""
    sv, c = contact_supervisor()
    assert sv.set_contact(c.request(sv, "op1", keys.CONTROL_CONTACT), True, TARGET)[0]
    sv.update_contact_force(TARGET, c.mono)
    c.mono += 0.02
    assert sv.on_command(c.cmd(vx=0.004), c.wall, c.mono, POSE).twist[0] == pytest.approx(0.004)
    sv.update_force(0, True, c.mono)
    assert sv.contact_target is None
    assert any("contact mode off: force sensor stale" in r for _, r in sv.interventions)
    for _ in range(10):  # the operator keeps steering, the deadman held
        c.mono += 0.016
        d = sv.on_command(c.cmd(vx=0.004), c.wall, c.mono, POSE)
        assert not d.accepted and d.status == Status.FORCE_STALE and not any(d.twist)
        assert "press it again" in d.reason
        assert not any(sv.step(c.mono, POSE).twist)
    sv.update_force(0, False, c.mono)  # samples again
    c.mono += 0.016
    assert not any(sv.on_command(c.cmd(vx=0.004), c.wall, c.mono, POSE).twist)
    c.mono += 0.016
    sv.on_command(c.cmd(vx=0.0, deadman=False), c.wall, c.mono, POSE)
    c.mono += 0.016
    d = sv.on_command(c.cmd(vx=0.004), c.wall, c.mono, POSE)
    assert d.accepted and d.twist[0] == pytest.approx(0.004) and sv.contact_target is None


def test_red_in_contact_mode_stops_the_steering_and_a_sweep_and_only_backs_off() -> None:
    """Red while the admittance holds a force below yellow: it is not keeping up (a surface rising under the
    sweep). Steering on would press harder sideways: only the back-off moves the probe until the level drops."""
    sv, c = contact_supervisor()
    assert sv.set_contact(c.request(sv, "op1", keys.CONTROL_CONTACT), True, TARGET)[0]
    sv.update_force(2, False, c.mono)
    sv.update_contact_force(8.5, c.mono)
    c.mono += 0.02
    d = sv.on_command(c.cmd(vx=0.004, wz=0.05), c.wall, c.mono, POSE)
    assert d.accepted and d.status == Status.FORCE_DANGER and "steering stopped" in d.reason
    assert d.twist[0] == 0.0 and d.twist[5] == 0.0 and d.twist[2] > 0.0  # the tool points down: +z backs off
    c.mono += 0.02
    d = sv.on_command(c.cmd(vx=0.0), c.wall, c.mono, POSE, [0.005, 0.0, 0.0, 0.0, 0.0, 0.0])  # a sweep's lane
    assert d.twist[0] == 0.0 and "steering stopped" in d.cancel_goto
    assert sv.step(c.mono, POSE).status.halts  # the control loop ends the move too
    sv.update_force(1, False, c.mono)  # back under red: steering is the operator's again (held throughout)
    sv.update_contact_force(7.0, c.mono)
    c.mono += 0.02
    d = sv.on_command(c.cmd(vx=0.004), c.wall, c.mono, POSE)
    assert d.accepted and d.twist[0] == pytest.approx(0.004)


def _pressing(sample: ForceSample) -> float:
    return -sample.force[2]  # the tool points down: the surface pushes back along the tool's -z


@pytest.mark.slow
@pytest.mark.serial  # the edge's force loop must hold ±1 N 95 % of the time
@pytest.mark.parametrize("stiffness_n_per_mm", [2.0, 4.0, 8.0])
def test_a_tangential_sweep_in_contact_mode_holds_the_force(edge_factory, operator_factory, stiffness_n_per_mm) -> None:
    edge_factory(phantom={"surface_z": 0.195, "stiffness": 1000 * stiffness_n_per_mm, "damping": 20.0},
                 force={"sensor": {"kind": "sim", "noise": 0.05, "seed": 3}}, safety={"profile": "local"})
    op = operator_factory()
    op.wait_for_state()
    forces: list[tuple[float, float]] = []
    op.session.declare_subscriber(keys.RobotKeys("sim1").key(keys.STATE_FORCE),
                                  lambda s: forces.append((time.monotonic(), _pressing(ForceSample.decode(s.payload.to_bytes())))))
    op.start()
    op.acquire()
    wait_until(lambda: op.safety is not None and not op.safety.force_stale, 5.0, message="a fresh force sensor")
    assert op.set_contact(True, TARGET).ok
    # Hold the deadman, steer along x: the edge brings the probe down to the surface and holds 4 N.
    op.set_twist([0.004, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=True)
    wait_until(lambda: forces and forces[-1][1] > TARGET - 1.0, 10.0, message="contact at the target force")
    t0 = time.monotonic()
    for vx in (-0.004, 0.004, -0.004):  # back and forth along the surface
        op.set_twist([vx, 0.002, 0.0], [0.0, 0.0, 0.0], deadman=True)
        time.sleep(2.0)
    op.set_twist([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], deadman=False)
    held = [f for t, f in forces if t >= t0 + 0.5]
    within = sum(abs(f - TARGET) <= 1.0 for f in held) / len(held)
    assert within >= 0.95, f"{100 * within:.1f} % of {len(held)} samples within ±1 N of {TARGET} N"
    assert op.peak_force_level < 2, "reached red"
    assert op.safety.contact_target == TARGET
