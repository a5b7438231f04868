"""An edge and a console of different releases, through a real router: what each user sees.

The last release's code is taken from git (``git archive``, read-only) and run in its own processes, first on
PYTHONPATH, as a hospital that has updated one end and not the other runs it. A release newer than this one cannot
exist here: where one is needed, a session publishes and answers what such an edge would (said in the test)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tarfile
import time
from collections.abc import Iterator
from pathlib import Path

import msgpack
import pytest
import yaml

from iorthand import keys, protocol
from iorthand.protocol import REVISION, ControlReply, SafetyStatus
from iorthand_operator import recovery
from iorthand_operator.client import ControlRefused

from .conftest import ROOT, iorthand_cmd, stop_process

# The release before this one, whose consoles and edges are still in the field (revision 1: it said none). Move it
# on with each release.
LAST_RELEASE = "339ec9f"
PACKAGES = ("iorthand", "edge/iorthand_edge", "operator/iorthand_operator", "cloud/iorthand_cloud")

ACTUATORS = {
    "servos": {"driver": {"kind": "sim"}, "pan": {"channel": 0, "min_deg": 0, "max_deg": 180, "home_deg": 90},
               "tilt": {"channel": 1, "min_deg": 0, "max_deg": 180, "home_deg": 90}, "publish_hz": 5},
    "torch": {"driver": {"kind": "sim"}, "channel": 2, "publish_hz": 5},
}

# The last release's OperatorClient, as `iorthand operator` and the consoles use it: waits for the robot's state,
# takes control and drives for a second; prints what its user has (JSON).
OLD_OPERATOR = """
import json, sys, time
from iorthand.transport import client_config, open_session
from iorthand_operator.client import ControlRefused, OperatorClient

session = open_session(client_config(sys.argv[1]))
client = OperatorClient(session, "sim1", "old-console", realtime=False)
deadline = time.monotonic() + 15
while (client.safety is None or client.robot_state is None) and time.monotonic() < deadline:
    time.sleep(0.05)
time.sleep(1.0)  # a few servo and torch heartbeats
out = {"refused": ""}
try:
    client.acquire()
    client.start()
    client.set_twist([0.005, 0.0, 0.0], [0.0, 0.0, 0.0], True)
    time.sleep(1.0)
    client.set_twist([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], False)
    client.wait_for_echoes()
except ControlRefused as exc:
    out["refused"] = str(exc)
out["accepted"] = sum(e.accepted for e in client.echoes)
out["servo"] = client.servo is not None
out["torch"] = client.torch is not None
out["rejects"] = dict(client.rejects.counts)
out["events"] = [e.reason for e in client.events]
print(json.dumps(out))
client.close()
session.close()
"""


@pytest.fixture(scope="module")
def last_release(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The last release's packages, extracted from git (no checkout: the work tree is untouched)."""
    where = tmp_path_factory.mktemp("last-release")
    archive = where / "release.tar"
    try:
        subprocess.run(["git", "-C", str(ROOT), "archive", "-o", str(archive), LAST_RELEASE, *PACKAGES],
                       check=True, capture_output=True, timeout=60)
    except (OSError, subprocess.CalledProcessError) as exc:
        pytest.skip(f"the last release {LAST_RELEASE} is not in this checkout's history: {exc}")
    with tarfile.open(archive) as tar:
        tar.extractall(where, filter="data")
    return where


def old_release(where: Path) -> dict[str, object]:
    """How to run a process of the release in ``where``: its packages first on PYTHONPATH, and started there (the
    current directory comes first on a ``-c``/``-m`` process's path, and this one holds today's packages)."""
    pythonpath = os.pathsep.join(str(where / p) for p in (".", "edge", "operator", "cloud"))
    return {"env": {**os.environ, "PYTHONPATH": pythonpath}, "cwd": where}


def test_a_console_of_the_last_release_is_refused_control_by_todays_edge_and_told_to_update(
        edge_factory, router_endpoint: str, last_release: Path) -> None:
    """The last release's console refuses every servo and torch state of today's edge (a field it does not know):
    it showed no camera angles and no torch, said nowhere, and drove all the same (79 of 79 twists accepted). Now
    the edge refuses it control, naming both revisions, what it cannot read and what to update."""
    agent = edge_factory(**ACTUATORS)
    run = subprocess.run([sys.executable, "-c", OLD_OPERATOR, router_endpoint], **old_release(last_release),
                         capture_output=True, text=True, timeout=50)
    assert run.returncode == 0, run.stderr[-2000:]
    seen = json.loads(run.stdout.strip().splitlines()[-1])
    assert not seen["servo"] and not seen["torch"], "the last release reads today's servo state: nothing to test"
    assert seen["refused"].startswith("update this console: it speaks protocol revision 1, this edge 2"), seen
    assert "ServoState.period" in seen["refused"] and "TorchState.period" in seen["refused"]
    assert any("update this console" in e for e in seen["events"]), seen["events"]  # in its console's log
    assert seen["accepted"] == 0
    assert agent.supervisor.owner == ""


@pytest.fixture
def last_release_edge(router_endpoint: str, tmp_path: Path, last_release: Path) -> Iterator[subprocess.Popen[bytes]]:
    """The last release's edge agent (simulated robot, servos and torch) in its own process."""
    config = {"robot_id": "sim1", "zenoh": {"mode": "client", "connect": [router_endpoint]},
              "robot": {"kind": "sim", "initial_pose": [0.30, 0.0, 0.20, math.pi, 0.0, 0.0]},
              "safety": {"auto_arm": True}, **ACTUATORS}
    path = tmp_path / "edge.yaml"
    path.write_text(yaml.safe_dump(config))
    proc = subprocess.Popen(iorthand_cmd("--log-level", "warning", "edge", "--config", str(path)),
                            **old_release(last_release), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    yield proc
    stop_process(proc)


def test_todays_console_drives_an_edge_of_the_last_release_and_says_which_to_update(
        last_release_edge, operator_factory) -> None:
    """The other way round everything reads: today's console decodes the older edge's messages (their added
    fields take defaults), and that edge reads all it sends. It drives, shows the camera and the torch, and says
    once that the edge speaks an older revision."""
    client = operator_factory(operator_id="new-console", realtime=False)
    deadline = time.monotonic() + 20
    while (client.safety is None or client.servo is None or client.torch is None) and time.monotonic() < deadline:
        assert last_release_edge.poll() is None, last_release_edge.stderr.read().decode()[-2000:]
        time.sleep(0.05)
    assert client.servo is not None and client.torch is not None
    client.acquire()
    client.acquire()  # a renewal: the mismatch is said once
    client.start()
    client.set_twist([0.005, 0.0, 0.0], [0.0, 0.0, 0.0], True)
    time.sleep(0.6)
    client.set_twist([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], False)
    client.wait_for_echoes()
    assert sum(e.accepted for e in client.echoes) > 0
    said = [e.reason for e in client.events if e.status == "version"]
    assert said == [f"the edge speaks protocol revision 1, this console {REVISION}: update the edge"]
    assert client.edge_revision == 1
    assert client.rejects.total == 0


def _newer(msg: protocol.Message, **added: object) -> bytes:
    """``msg`` as a release after this one would send it: with fields this build does not know."""
    return msgpack.packb({**msgpack.unpackb(msg.encode()), **added})


def test_a_newer_edge_whose_safety_state_this_console_cannot_read_is_not_driven(
        session_factory, operator_factory) -> None:
    """A newer edge's safety status with a field this console does not know is refused whole (it may be the field
    that says why the robot stopped). The console says so once (key, field, the sender is newer), tells the
    operator to wait and update, and does not keep a grant such an edge gave: it gives it back. Here a session
    stands in for that edge (no newer release exists to run): it publishes the status and grants control."""
    edge = session_factory()
    safety_key = keys.RobotKeys("sim1").key(keys.STATE_SAFETY)
    released: list[bytes] = []

    def grant(query) -> None:
        reply = ControlReply(ok=True, reason="granted", owner="new-console", lease=3.0, key=b"k" * 32,
                             detail=json.dumps({"revision": REVISION + 1}))
        query.reply(query.key_expr, reply.stamp(1).encode())

    queryables = [edge.declare_queryable(keys.RobotKeys("sim1").key(keys.CONTROL_ACQUIRE), grant),
                  edge.declare_queryable(keys.RobotKeys("sim1").key(keys.CONTROL_RELEASE),
                                         lambda q: released.append(q.payload.to_bytes()))]
    client = operator_factory(operator_id="new-console", realtime=False, query_timeout=0.5)
    status = SafetyStatus(armed=True, status="ok").stamp(1)
    deadline = time.monotonic() + 10
    while client.rejects.counts.get(safety_key, 0) < 5 and time.monotonic() < deadline:
        edge.put(safety_key, _newer(status, why_stopped="a reason this console cannot show"))
        time.sleep(0.05)
    step = client.next_step()
    assert step.step is recovery.Step.WAIT and step.why.startswith(
        f"update this console: it speaks protocol revision {REVISION}"), step
    with pytest.raises(ControlRefused, match=rf"update this console: .*revision {REVISION}, the edge {REVISION + 1}"
                                             r".*SafetyStatus.why_stopped: unknown field"):
        client.acquire()
    assert not client.owner and released, "the grant was not given back"
    said = [e.reason for e in client.events if e.status == "version"]
    assert len([r for r in said if safety_key in r]) == 1, said  # once, not per message
    assert any("why_stopped" in r and protocol.NEWER_SENDER in r for r in said)
    assert client.rejects.counts[safety_key] >= 5
    for q in queryables:
        q.undeclare()


def test_an_edge_updated_under_a_running_console_reads_update_this_console_not_link_down(
        session_factory, operator_factory) -> None:
    """The edge is updated while a console of the release before watches it: its safety status, read until then,
    now carries a field this console does not know and is refused. Once the last one it read went stale, the
    console said "no safety status from the edge for 0.6 s: the link or the edge is down", while the link was up
    and the edge sent 20 statuses a second; what the operator must do is update the console."""
    from iorthand_operator.client import SAFETY_STALE_S

    edge = session_factory()
    safety_key = keys.RobotKeys("sim1").key(keys.STATE_SAFETY)
    client = operator_factory(operator_id="new-console", realtime=False, query_timeout=0.5)
    status = SafetyStatus(armed=True, status="ok").stamp(1)
    deadline = time.monotonic() + 10
    while client.safety is None and time.monotonic() < deadline:  # the edge before its update: read
        edge.put(safety_key, status.encode())
        time.sleep(0.05)
    assert client.safety is not None
    stale_from = time.monotonic() + SAFETY_STALE_S + 0.3
    while (time.monotonic() < stale_from or not client.safety_stale()) and time.monotonic() < deadline:
        edge.put(safety_key, _newer(status, why_stopped="a reason this console cannot show"))  # after its update
        time.sleep(0.05)
    assert client.safety_stale()
    step = client.next_step()
    assert step.step is recovery.Step.WAIT and step.why.startswith(
        f"update this console: it speaks protocol revision {REVISION}"), step


def test_a_newer_edges_servo_state_is_shown_without_what_it_added_and_said_once(
        session_factory, operator_factory) -> None:
    """A display-only message with a field this console does not know is shown without it (the camera's angles
    stay on screen), and the console says once what it left out and that the edge is newer. A session stands in
    for the newer edge."""
    edge = session_factory()
    servo_key = keys.RobotKeys("sim1").key(keys.STATE_SERVO)
    client = operator_factory(operator_id="new-console", realtime=False)
    deadline = time.monotonic() + 10
    n = 0
    while (client.servo is None or n < 10) and time.monotonic() < deadline:
        n += 1
        edge.put(servo_key, _newer(protocol.ServoState(pan=0.5, tilt=0.25, period=0.5).stamp(n), zoom=2.0))
        time.sleep(0.02)
    assert client.servo is not None and (client.servo.pan, client.servo.tilt) == (0.5, 0.25)
    said = [e.reason for e in client.events if e.status == "version"]
    assert said == [f"{servo_key}: ServoState shown without zoom: {protocol.NEWER_SENDER}"]
    assert client.rejects.total == 0
