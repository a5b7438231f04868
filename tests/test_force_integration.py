"""The force chain end to end through a real router: simulated robot pressing into the phantom, the
simulated sensor, levels on state/force_level, the supervisor's reaction on state/safety, staleness, zeroing."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest

from iorthand import keys
from iorthand.protocol import (
    ControlReply,
    ControlRequest,
    ForceLevelState,
    ForceSample,
    RobotState,
    SafetyStatus,
    Status,
)
from iorthand.security import auth
from iorthand.transport import query
from tests.conftest import wait_until

SURFACE = 0.199
STIFFNESS = 4000.0
FORCE_CONFIG = {
    "phantom": {"surface_z": SURFACE, "stiffness": STIFFNESS, "damping": 20.0},
    "force": {"sensor": {"kind": "sim", "noise": 0.02, "seed": 1}},
}


class Watcher:
    """Collects force levels, samples and safety statuses published by the edge."""

    def __init__(self, session, robot: str = "sim1") -> None:
        k = keys.RobotKeys(robot)
        self.lock = threading.Lock()
        self.levels: list[ForceLevelState] = []
        self.samples = 0
        self.safety: list[SafetyStatus] = []
        self._subs = [
            session.declare_subscriber(k.key(keys.STATE_FORCE_LEVEL), self._on_level),
            session.declare_subscriber(k.key(keys.STATE_FORCE), self._on_force),
            session.declare_subscriber(k.key(keys.STATE_SAFETY), self._on_safety),
        ]

    def _on_level(self, sample) -> None:
        with self.lock:
            self.levels.append(ForceLevelState.decode(sample.payload.to_bytes()))

    def _on_force(self, sample) -> None:
        ForceSample.decode(sample.payload.to_bytes())
        self.samples += 1

    def _on_safety(self, sample) -> None:
        with self.lock:
            self.safety.append(SafetyStatus.decode(sample.payload.to_bytes()))

    def transitions(self) -> list[tuple[int, bool]]:
        with self.lock:
            out: list[tuple[int, bool]] = []
            for m in self.levels:
                if not out or out[-1] != (m.level, m.stale):
                    out.append((m.level, m.stale))
            return out

    def statuses(self) -> list[tuple[str, str]]:
        with self.lock:
            return [(s.status, s.reason) for s in self.safety]


def depth(agent) -> float:
    return max(0.0, SURFACE - float(agent.reading.tcp_pose[2]))


def test_press_levels_reaction_retreat_and_stale(edge_factory, operator_factory, session_factory, caplog) -> None:
    caplog.set_level(logging.INFO)
    agent = edge_factory(**FORCE_CONFIG)
    watcher = Watcher(session_factory())
    op = operator_factory()
    op.wait_for_state()
    op.acquire()
    op.start()
    wait_until(lambda: (0, False) in watcher.transitions(), message="fresh SAFE level")
    assert watcher.samples > 0

    # Press down (remote profile: 8 mm/s) and keep pressing well past the red threshold.
    op.set_twist([0, 0, -0.05], [0, 0, 0], deadman=True)
    wait_until(lambda: agent.force.state.level == 2, timeout=5.0, message="danger level")
    red_depth = depth(agent)
    max_depth = red_depth
    t_end = time.monotonic() + 1.0
    while time.monotonic() < t_end:
        max_depth = max(max_depth, depth(agent))
        time.sleep(0.005)
    margin = agent.config.safety.force.overshoot_margin
    assert max_depth - red_depth <= margin, f"{1000 * (max_depth - red_depth):.2f} mm past red"
    assert max_depth <= 8.0 / STIFFNESS + margin  # never deeper than the static red depth + the margin
    levels_seen = [lv for lv, stale in watcher.transitions() if not stale]
    assert levels_seen[:3] == [0, 1, 2]
    wait_until(lambda: any(s == Status.FORCE_DANGER and r for s, r in watcher.statuses()), message="force_danger on state/safety")
    assert any("safety intervention [force_danger]" in r.getMessage() for r in caplog.records)

    # Retreat is allowed.
    z = float(agent.reading.tcp_pose[2])
    op.set_twist([0, 0, 0.005], [0, 0, 0], deadman=True)
    wait_until(lambda: float(agent.reading.tcp_pose[2]) > z + 0.002, message="retreat")
    wait_until(lambda: agent.force.state.level == 0, message="level back to SAFE")

    # Stop the sensor: stale, the robot stops (latched: a release and a press to move again), contact motion is
    # refused, retreat allowed.
    op.set_twist([0, 0, -0.005], [0, 0, 0], deadman=True)
    time.sleep(0.2)
    agent.force.sensor.silent = True
    wait_until(lambda: agent.force.state.stale, message="stale")
    detected = agent.force.stale_since - agent.force.state.last_sample
    print(f"stale detected {1000 * detected:.1f} ms after the last sample")
    wait_until(lambda: any(s == Status.FORCE_STALE for s, _ in watcher.statuses()), message="force_stale on state/safety")
    wait_until(lambda: (watcher.transitions() or [(0, False)])[-1][1], message="stale on state/force_level")
    time.sleep(0.1)
    z = float(agent.reading.tcp_pose[2])
    time.sleep(0.5)
    assert float(agent.reading.tcp_pose[2]) >= z - 0.0005
    op.set_twist([0, 0, 0.005], [0, 0, 0], deadman=True)  # held through the stop: moves nothing
    time.sleep(0.3)
    assert float(agent.reading.tcp_pose[2]) == pytest.approx(z, abs=0.0005)
    op.set_twist([0, 0, 0], [0, 0, 0], deadman=False)
    time.sleep(0.1)
    op.set_twist([0, 0, 0.005], [0, 0, 0], deadman=True)
    wait_until(lambda: float(agent.reading.tcp_pose[2]) > z + 0.001, message="retreat while stale")
    assert any("force sensor stale" in r.getMessage() for r in caplog.records)
    op.set_twist([0, 0, 0], [0, 0, 0], deadman=False)


def _zero(session, operator: str, key: bytes = b"", seq: int = 1) -> ControlReply:
    """A force-zero request, signed with ``key`` (the owner's grant) when given."""
    req = ControlRequest(operator=operator).stamp(seq)
    if key:
        auth.sign(key, auth.context("sim1", keys.CONTROL_FORCE_ZERO), req)
    return ControlReply.decode(query(session, keys.RobotKeys("sim1").key(keys.CONTROL_FORCE_ZERO), req.encode())[0])


def test_a_sensor_read_from_the_robot_state_gives_one_sample_per_state(edge_factory, session_factory) -> None:
    """The simulated sensor's force is computed from the robot's state, so the control loop samples it with each
    state it reads, before the supervisor's cycle, and no thread of its own polls that state at another rate (at
    100 Hz against 125 states a second, which repeated some states' force and skipped others'): each state/force
    sample carries the time of one state/robot, and no state's twice."""
    edge_factory(**FORCE_CONFIG)
    assert "edge-force" not in [t.name for t in threading.enumerate()]
    k = keys.RobotKeys("sim1")
    robot_t: list[int] = []
    force_t: list[int] = []
    s = session_factory()
    subs = [
        s.declare_subscriber(k.key(keys.STATE_ROBOT), lambda x: robot_t.append(RobotState.decode(x.payload.to_bytes()).t)),
        s.declare_subscriber(k.key(keys.STATE_FORCE), lambda x: force_t.append(ForceSample.decode(x.payload.to_bytes()).t)),
    ]
    wait_until(lambda: len(robot_t) > 150, 5.0, message="robot states")
    for sub in subs:
        sub.undeclare()
    time.sleep(0.05)
    states = set(robot_t)
    window = [t for t in force_t if robot_t[0] <= t <= robot_t[-1]]
    assert len(window) > 100
    assert all(t in states for t in window), [t for t in window if t not in states][:3]
    assert len(set(window)) == len(window)  # no state's force twice
    # Every state between the first and the last force sample has its force (none skipped).
    assert len(window) == len([t for t in robot_t if window[0] <= t <= window[-1]])


def test_zeroing_on_request_only_by_the_owner_and_out_of_contact(edge_factory, operator_factory) -> None:
    agent = edge_factory(**FORCE_CONFIG)
    op = operator_factory()
    op.wait_for_state()
    wait_until(lambda: not agent.force.state.stale, message="fresh sensor")
    assert not _zero(op.session, "op1").ok  # not the owner
    key = op.acquire().key
    biased = np.array(agent.force.last_wrench)
    assert abs(biased[2]) > 0.3  # the configured bias shows before zeroing
    reply = _zero(op.session, "op1")  # the owner's name without its grant's signature
    assert not reply.ok and "not signed" in reply.reason
    assert abs(agent.force.last_wrench[2]) > 0.3
    reply = _zero(op.session, "op1", key, seq=1)
    assert reply.ok, reply.reason
    wait_until(lambda: abs(agent.force.last_wrench[2]) < 0.15, message="zeroed reading")
    agent.robot.teleport([0.30, 0.0, SURFACE - 0.0018, np.pi, 0.0, 0.0])  # 7.2 N into the phantom
    wait_until(lambda: agent.force.state.level == 1, message="caution")
    reply = _zero(op.session, "op1", key, seq=2)
    assert not reply.ok and "contact" in reply.reason


@pytest.mark.parametrize("bad", [{"force": {"levels": {"caution": 9.0}}}, {"force": {"sensor": {"kind": "ati"}}}])
def test_bad_force_config_fails_with_the_key(bad: dict) -> None:
    from iorthand.config import ConfigError
    from tests.conftest import edge_config

    with pytest.raises(ConfigError, match="force"):
        edge_config("tcp/127.0.0.1:1", **bad)


def test_example_edge_sim_config_loads_with_every_component() -> None:
    from iorthand_edge.config import load_edge_config
    from tests.conftest import ROOT

    c = load_edge_config(ROOT / "configs" / "edge-sim.yaml")
    assert c.phantom and c.force and c.servos and c.torch and c.video and c.video.camera and c.video.ultrasound
