"""The console, headless (textual's run_test pilot), against a real router and a simulated edge."""

from __future__ import annotations

import asyncio
import math
import re
import threading
import time

import numpy as np
import pytest
from textual import events
from textual.widgets import OptionList, RichLog

from iorthand import keys
from iorthand.protocol import ForceLevelState, SafetyStatus, StopCommand, TwistCommand
from iorthand.transport import publisher
from iorthand_operator.console.app import OperatorConsole
from iorthand_operator.console.controller import ConsoleController, ConsoleView
from iorthand_operator.console.model import printable
from iorthand_operator.console.settings import ConsoleSettings
from iorthand_operator.inputs import KeyboardInput, KeymapConfig
from tests.conftest import ROOT, wait_until


async def _wait(pred, timeout: float = 5.0, message: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        await asyncio.sleep(0.02)
    raise AssertionError(f"timed out after {timeout} s waiting for {message}")


async def _key(app: OperatorConsole, name: str, after: float = 0.05) -> None:
    """A key event as the terminal delivers it (pilot.press waits for the screen to settle, ~1-2 s here:
    too slow to model key repeats at 15-30 Hz)."""
    app.post_message(events.Key(name, name if len(name) == 1 else None))
    await asyncio.sleep(after)


def _text(app: OperatorConsole, wid: str) -> str:
    """What a panel shows, as plain text (rendered into the headless screen)."""
    widget = app.query_one(f"#{wid}")
    return "\n".join(strip.text for strip in widget.render_lines(widget.region.reset_offset))


def _console(operator_factory, robot: str = "sim1", operator: str = "op1", **settings: object):
    client = operator_factory(robot, operator)
    device = KeyboardInput(KeymapConfig(initial_hold=0.4, repeat_hold=0.15))
    ctrl = ConsoleController(client, device, ConsoleSettings(**settings), router="test router")
    return client, ctrl, OperatorConsole(ctrl)


def test_hold_deadman_and_move_key_moves_release_stops(edge_factory, operator_factory) -> None:
    edge = edge_factory()
    client, ctrl, app = _console(operator_factory)
    client.wait_for_state()
    client.acquire()
    client.start()
    ctrl.start()

    async def run() -> dict[str, float]:
        async with app.run_test(size=(160, 50)) as pilot:
            x0 = client.robot_state.tcp_pose[0]
            await _key(app, "space")  # deadman on (toggle)
            for _ in range(30):  # "hold" w: a press, then repeats at ~20 Hz
                await _key(app, "w", 0.05)
            last_key = time.monotonic()
            assert client.robot_state.tcp_pose[0] > x0 + 0.002, "the tool did not move +x"
            assert app.view_model.deadman
            # The edge's view of the deadman, from its 20 Hz status: on a loaded machine a stalled sender can
            # leave a gap over command_timeout (CI saw 178 ms), which the edge rightly shows as released until
            # the next command.
            await _wait(lambda: app.view_model.edge_deadman, 2.0, "the edge seeing the deadman held")
            # Key released: no more repeats → zero twist within repeat_hold, the robot stops.
            await _wait(lambda: not np.any(client.robot_state.commanded), 3.0, "motion to stop")
            stop_s = time.monotonic() - last_key
            await _wait(lambda: "ms" in app.view_model.link[0].text, 3.0, "RTT figures")
            await pilot.pause(0.2)
            link = _text(app, "link")
            assert "RTT p50/p95" in link and " ms" in link
            assert "judged, 0 superseded" in link  # the edge's own count of the commands it saw
            # Deadman off: the sender sends its zero tail, then goes quiet.
            await _key(app, "space")
            await _wait(lambda: not client.safety.deadman, 2.0, "edge deadman off")
            sent = client.sent_count
            await asyncio.sleep(client.release_tail + 0.3)
            quiet_sent = client.sent_count - sent
            moved = client.robot_state.tcp_pose[0] - x0
            await pilot.press("q")
            return {"stop_s": stop_s, "quiet_sent": quiet_sent, "moved": moved}

    result = asyncio.run(run())
    ctrl.stop()
    assert result["moved"] > 0.002
    # repeat_hold (0.15 s) + transport; generous for a loaded 2-core machine.
    assert result["stop_s"] < 1.5, result
    assert result["quiet_sent"] <= 60 * (client.release_tail + 0.1)
    assert edge.supervisor.counters.applied > 0


def test_force_block_colours_and_stale(session_factory, operator_factory) -> None:
    """The force block from state/force_level messages published here (the sensor is another issue)."""
    robot = "forcebot"  # no edge: only our messages reach this robot's keys
    _client, ctrl, app = _console(operator_factory, robot=robot, force_stale_after=0.4)
    pub = publisher(session_factory(), keys.RobotKeys(robot).key(keys.STATE_FORCE_LEVEL))
    current: dict[str, ForceLevelState | None] = {"msg": None}
    stop = threading.Event()

    def publish() -> None:
        seq = 0
        while not stop.wait(0.05):
            msg = current["msg"]
            if msg is not None:
                seq += 1
                pub.put(msg.stamp(seq).encode())

    t = threading.Thread(target=publish, daemon=True)
    t.start()

    async def run() -> list[tuple[str, str]]:
        seen = []
        async with app.run_test(size=(160, 50)) as pilot:
            await pilot.pause(0.3)
            seen.append((app.view_model.force.label, app.view_model.force.colour))  # nothing yet
            for level, value in ((0, 2.0), (1, 6.5), (2, 8.5)):
                current["msg"] = ForceLevelState(level=level, stale=False, value=value)
                want = ("SAFE", "CAUTION", "DANGER")[level]
                await _wait(lambda w=want: app.view_model.force.label == w, 3.0, want)
                await pilot.pause(0.15)
                assert want in _text(app, "force")
                seen.append((app.view_model.force.label, app.view_model.force.colour))
            current["msg"] = ForceLevelState(level=0, stale=True, value=0.0)  # the edge says: stale
            await _wait(lambda: app.view_model.force.label == "STALE", 3.0, "edge-reported stale")
            seen.append((app.view_model.force.label, app.view_model.force.colour))
            current["msg"] = ForceLevelState(level=0, stale=False, value=1.0)
            await _wait(lambda: app.view_model.force.label == "SAFE", 3.0, "safe again")
            current["msg"] = None  # the sensor (or link) goes silent
            await _wait(lambda: app.view_model.force.label == "STALE", 3.0, "silent sensor → stale")
            await pilot.pause(0.15)
            assert "STALE" in _text(app, "force")
            seen.append((app.view_model.force.label, app.view_model.force.colour))
            await pilot.press("ctrl+c")
        return seen

    try:
        seen = asyncio.run(run())
    finally:
        stop.set()
        t.join(1)
        ctrl.stop()
    assert seen == [
        ("NO DATA", "grey50"), ("SAFE", "green"), ("CAUTION", "yellow"), ("DANGER", "red"),
        ("STALE", "grey50"), ("STALE", "grey50"),
    ]


ESCAPES = "\x1b[2J\x1b]0;OWNED\x07\n robot OFFLINE \u202e\x9b"


def test_printable_shows_every_control_character_as_its_escape() -> None:
    assert printable("lease of 'op1' renewed for 3 s — ok, 5 °/s") == "lease of 'op1' renewed for 3 s — ok, 5 °/s"
    assert printable(ESCAPES) == "\\x1b[2J\\x1b]0;OWNED\\x07\\n robot OFFLINE \\u202e\\x9b"


def test_text_from_the_wire_cannot_steer_the_terminal(session_factory, operator_factory) -> None:
    """Found by a red-team run of the operator side: escape sequences in a safety reason, an owner's name or a
    force quantity reached the terminal raw: they cleared the screen (the force panel went blank), set the
    window title, and a newline drew a fake "robot OFFLINE" line."""
    robot = "escbot"  # no edge: only our messages reach this robot's keys
    _client, ctrl, app = _console(operator_factory, robot=robot)
    s, k = session_factory(), keys.RobotKeys(robot)
    safety, force = publisher(s, k.key(keys.STATE_SAFETY)), publisher(s, k.key(keys.STATE_FORCE_LEVEL))

    async def run() -> tuple[str, str, ConsoleView]:
        async with app.run_test(size=(160, 50)) as pilot:
            for seq in range(1, 40):
                safety.put(SafetyStatus(owner="op1\x1b[2J", status="stopped", reason=ESCAPES, task=ESCAPES,
                                        limits_hit=[ESCAPES[:16]]).stamp(seq).encode())
                force.put(ForceLevelState(level=2, stale=False, value=9.0, quantity=ESCAPES[:16]).stamp(seq).encode())
                await pilot.pause(0.05)
                if app.view_model.edge_reason and app.view_model.force.label == "DANGER":
                    break
            await pilot.pause(0.2)
            status, forces, v = _text(app, "status"), _text(app, "force"), app.view_model
            await pilot.press("ctrl+c")
        return status, forces, v

    try:
        status, forces, v = asyncio.run(run())
    finally:
        ctrl.stop()
    texts = [v.owner, v.edge_reason, v.task, *v.limits_hit, v.force.detail, *v.events]
    assert all(t.isprintable() for t in texts), [t for t in texts if not t.isprintable()]
    assert v.edge_reason == printable(ESCAPES) and "\\x1b[2J" in v.owner
    assert "\\x1b[2J" in status and "\x1b" not in status + forces and "DANGER" in forces


def test_a_camera_that_cannot_open_is_shown_with_its_reason(edge_factory, operator_factory) -> None:
    """No device at the configured path (this machine has no camera): the edge keeps retrying, and the
    console says why there are no markers instead of "none in view"."""
    intrinsics = ROOT / "configs" / "calibration" / "intrinsics-640x480.yaml"
    edge_factory(perception={"camera": {"kind": "device", "path": "/nonexistent/video9"},
                             "intrinsics_file": str(intrinsics), "retry_interval": 0.3})
    client, ctrl, app = _console(operator_factory)
    client.wait_for_state()
    ctrl.start()

    async def run() -> str:
        async with app.run_test(size=(160, 50)) as pilot:
            await _wait(lambda: app.view_model.markers_note.startswith("camera failed"), 5.0, "the camera's failure")
            await pilot.pause(0.2)
            shown = " ".join(_text(app, "pose").replace("│", " ").split())  # the panel wraps long lines
            await pilot.press("q")
            return shown

    try:
        shown = asyncio.run(run())
    finally:
        ctrl.stop()
    assert "camera failed: cannot open camera /nonexistent/video9" in shown
    news = [e for e in client.events if e.status == "perception"]
    assert len(news) == 1 and news[0].kind == "warning", news  # repeated attempts are not repeated news
    assert "/nonexistent/video9" in news[0].reason and "the edge retries" in news[0].reason


def test_refused_control_shows_the_reason(edge_factory, operator_factory, session_factory) -> None:
    from iorthand_operator.client import ControlRefused

    edge = edge_factory(safety={"auto_arm": True, "allowed_operators": ["someone_else"]})
    client, ctrl, app = _console(operator_factory)
    client.wait_for_state()
    with pytest.raises(ControlRefused):
        client.acquire()
    client.start()
    ctrl.start()
    pub = publisher(session_factory(), keys.RobotKeys("sim1").key(keys.CMD_TWIST))

    async def run() -> str:
        async with app.run_test(size=(160, 50)) as pilot:
            rejects = edge.rejects.total  # the refused acquire
            await _key(app, "space")
            await _key(app, "w")
            # Without a grant (no key to sign with) the client sends no command at all: nothing reaches the edge.
            await asyncio.sleep(0.3)
            assert client.sent_count == 0 and edge.supervisor.counters.received == 0 and edge.rejects.total == rejects
            # A command in op1's name from elsewhere: the edge refuses it and answers in op1's name; the console
            # shows that refusal too.
            cmd = TwistCommand(operator="op1", linear=[0.005, 0.0, 0.0], deadman=True, state_age=0.02).stamp(1)
            pub.put(cmd.encode())
            await _wait(lambda: any(e.kind == "refused" for e in client.events), 3.0, "a refusal")
            await pilot.pause(0.3)
            log = app.query_one("#events")
            text = "\n".join(line.text for line in log.lines)
            await pilot.press("q")
            return text

    text = asyncio.run(run())
    ctrl.stop()
    assert "allow-list" in text  # the acquire refusal, with the edge's reason
    # The command refusals: the edge's gate refuses an operator off the allow-list before the supervisor.
    assert "refused operator_not_allowed" in text


def test_gamepad_unplugged_mid_session_stops_motion(edge_factory, operator_factory) -> None:
    """SDL event path with injected events: enable + axis moves the tool; unplugging stops it and says so."""
    from iorthand.config import from_dict
    from iorthand_operator.inputs.gamepad import GamepadInput
    from iorthand_operator.inputs.mapping import GamepadConfig

    edge_factory()
    client = operator_factory()
    pad = GamepadInput(from_dict({"enable_button": 4, "axes": {"linear_y": {"axis": 0, "scale": 0.006}}}, GamepadConfig))
    ctrl = ConsoleController(client, pad, ConsoleSettings())
    client.wait_for_state()
    client.acquire()
    client.start()
    pg = pad._pg
    # Polled from this thread only (SDL's queue); the input thread is not started.
    pad.poll(time.monotonic())
    if pad.connected:
        pytest.skip("a real joystick is attached")
    y0 = client.robot_state.tcp_pose[1]
    pg.event.post(pg.event.Event(pg.JOYDEVICEADDED, device_index=0, guid="test"))
    pg.event.post(pg.event.Event(pg.JOYAXISMOTION, instance_id=0, joy=0, axis=0, value=1.0))
    pg.event.post(pg.event.Event(pg.JOYBUTTONDOWN, instance_id=0, joy=0, button=4))
    t_end = time.monotonic() + 0.8
    while time.monotonic() < t_end:
        ctrl.poll_once(time.monotonic())
        time.sleep(0.02)
    assert client.robot_state.tcp_pose[1] > y0 + 0.002
    pg.event.post(pg.event.Event(pg.JOYDEVICEREMOVED, instance_id=0))
    ctrl.poll_once(time.monotonic())
    v = ctrl.view()
    assert not v.input_connected and "UNPLUGGED" in v.input_status
    assert any(e.kind == "input" and e.status == "input_lost" for e in client.events)
    wait_until(lambda: not np.any(client.robot_state.commanded), 2.0, message="motion to stop")
    wait_until(lambda: client.safety is not None and not client.safety.deadman, 2.0, message="deadman off")
    ctrl.stop()


def test_the_console_never_starts_latched_and_names_the_key_after_every_halt(edge_factory, operator_factory) -> None:
    """A previous operator vanished (its session killed: the edge latched owner_lost). A console that starts
    shows no latch once it holds control, and after each halt it says which key moves the robot again; one
    press of that key does (an e-stop needed SPACE twice before, without the screen saying so)."""
    edge = edge_factory()
    ghost = operator_factory("sim1", "op1")
    ghost.wait_for_state()
    ghost.acquire()
    with edge.lock:  # its session is gone as a killed console's is
        edge.supervisor.owner_lost("op1", "owner 'op1' disappeared (liveliness lost)")
    client, ctrl, app = _console(operator_factory)
    client.wait_for_state()
    client.start()  # as the console does: the sender first, then control
    client.acquire()
    ctrl.start()

    async def run() -> None:
        async with app.run_test(size=(160, 50)) as pilot:
            # Holding control, the robot waits for a press: no latch on the screen, the key named.
            await _wait(lambda: app.view_model.we_own and app.view_model.edge_status == "deadman_released", 5.0,
                        "control held, no latch")
            assert app.view_model.edge_status not in ("owner_lost", "stopped")
            await _wait(lambda: app.view_model.hint.startswith("press SPACE to move"), 3.0, "the deadman key named")
            x0 = client.robot_state.tcp_pose[0]

            async def drive(what: str) -> None:
                await _key(app, "space")  # one press
                for _ in range(20):
                    await _key(app, "w", 0.05)
                await _wait(lambda: client.robot_state.tcp_pose[0] > x0 + 0.001, 3.0, f"motion after {what}")

            await drive("the start")
            await _key(app, "x")  # e-stop
            await _wait(lambda: edge.supervisor.counters.stops >= 1 and not np.any(client.robot_state.commanded),
                        3.0, "the robot stopped")
            await _wait(lambda: app.view_model.hint.startswith("press SPACE to move"), 5.0, "the hint")
            await pilot.pause(0.3)
            assert not app.view_model.deadman  # the toggle was forgotten: nothing moves by itself
            assert not np.any(client.robot_state.commanded)
            x0 = client.robot_state.tcp_pose[0]
            await drive("the e-stop")  # a single SPACE
            # A stop from someone else while this operator drives: the edge latches, the console forgets its
            # toggle and names the key; one press moves again.
            other = client.session.declare_publisher(keys.RobotKeys("sim1").key(keys.CMD_STOP))
            other.put(StopCommand(operator="nurse", reason="patient moved").stamp(1).encode())
            await _wait(lambda: "patient moved" in " ".join(app.view_model.events), 3.0, "the stop logged")
            await _wait(lambda: not app.view_model.deadman and app.view_model.hint.startswith("press SPACE to move"),
                        5.0, "the hint after someone else's stop")
            x0 = client.robot_state.tcp_pose[0]
            await drive("someone else's stop")
            other.undeclare()
            # The footer names the keys, the one that quits among them.
            shown = {k.key: k.description for k in app.screen.query("FooterKey")}
            assert shown.get("q") == "quit" and "ctrl+c" not in shown, shown
            assert shown.get("x") == "e-stop" and shown.get("space") == "deadman", shown

    asyncio.run(run())
    ctrl.stop()


def test_a_safety_status_that_stopped_coming_is_shown_as_old(session_factory, operator_factory) -> None:
    """Found by a review of the operator side: armed, owner and status showed the last safety status however old,
    so with the link dead the screen went on saying "armed / op1 / ok" as if current. Older than the client's bound
    (SAFETY_STALE_S, the one its hint uses), each row says how old it is."""
    from iorthand_operator.client import SAFETY_STALE_S

    robot = "stalebot"  # no edge: only our messages reach this robot's keys
    _client, ctrl, app = _console(operator_factory, robot=robot)
    pub = publisher(session_factory(), keys.RobotKeys(robot).key(keys.STATE_SAFETY))

    async def run() -> tuple[str, str, str]:
        async with app.run_test(size=(160, 50)) as pilot:
            for seq in range(1, 60):  # the edge's 20 Hz status, until the console has it
                pub.put(SafetyStatus(armed=True, owner="op1", status="ok", profile="local").stamp(seq).encode())
                await pilot.pause(0.05)
                if app.view_model.armed:
                    break
            await pilot.pause(0.2)
            fresh = _text(app, "status")
            # The link dies: no more status.
            await _wait(lambda: app.view_model.hint.startswith("no safety status"), SAFETY_STALE_S + 2.0,
                        "the status older than the client's bound")
            await pilot.pause(0.2)
            old, profile = _text(app, "status"), _text(app, "profile")
            await pilot.press("ctrl+c")
        return fresh, old, profile

    try:
        fresh, old, profile = asyncio.run(run())
    finally:
        ctrl.stop()
    assert "yes" in fresh and "stale" not in fresh
    # Connected while the robot's status arrives; not once it has stopped (its liveliness heard once said so).
    assert "test router  connected" in fresh and "test router  no data" in old, (fresh, old)
    for row in (r"armed\s+yes \(stale \d", r"owner\s+op1 \(stale \d", r"status\s+ok \(stale \d", r"edge off \(stale \d"):
        assert re.search(row, old), (row, old)
    assert "local (stale" in profile


def test_a_dead_link_reads_dead_in_the_link_figures(operator_factory) -> None:
    """Found by a review of the operator side: with no robot state for 1.4 s the link panel read downlink 0 % and
    RTT 20 ms, all green (gaps were counted only between states that arrived). The client's real link window is
    fed at explicit times (no edge: a healthy second, then silence) and the controller's view taken at them."""
    from iorthand_operator.link import BAD

    client = operator_factory("deadlinkbot", "op1")
    settings = ConsoleSettings()
    ctrl = ConsoleController(client, KeyboardInput(KeymapConfig()), settings)

    def ns(t: float) -> int:
        return int(t * 1e9)

    t0 = 1000.0
    for i in range(125):  # states at 125 Hz, each command echoed after 20 ms
        t = t0 + i * 0.008
        client.link.state(i, ns(t))
        client.link.sent((i, ns(t)), ns(t))
        client.link.echoed((i, ns(t)), ns(t), ns(t + 0.020))
    last = t0 + 124 * 0.008
    live = ctrl.view(last + 0.1).link
    assert [r.colour for r in live] == ["green"] * 3 and live[2].text == "0.0 % / 0.0 %", live
    rtt, jit, loss = ctrl.view(last + 1.4).link
    assert loss.text == "0.0 % / 100.0 % (no state for 1.4 s)" and loss.colour == "red", loss
    assert rtt.text.startswith("no echo for 1.4 s") and rtt.colour == "red", rtt
    assert jit.text.endswith("(old)") and jit.colour == "grey50", jit
    assert client.link_quality(ns(last + 1.4), settings.state_stale_after).overall(settings.link) == BAD
    # The bound is the console's "no fresh state" setting, the one its robot row uses.
    ctrl.settings = ConsoleSettings(state_stale_after=2.0)
    assert ctrl.view(last + 1.4).link[2].text == "0.0 % / 0.0 %"


def test_camera_and_torch_rows_say_how_old_they_are(session_factory, operator_factory) -> None:
    """Found by a review of the operator side: the camera (servo) and torch rows showed the last state however old,
    with the edge gone a "torch on" from minutes ago looked current. Older than the bound the edge's heartbeat
    implies (ACTUATOR_STALE_S), each row is greyed and says how old it is."""
    from iorthand.protocol import ServoState, TorchState
    from iorthand_operator.client import ACTUATOR_STALE_S

    robot = "servobot"  # no edge: only our messages reach this robot's keys
    client = operator_factory(robot, "op1")
    ctrl = ConsoleController(client, KeyboardInput(KeymapConfig()), ConsoleSettings())
    k = keys.RobotKeys(robot)
    servo_pub = publisher(session_factory(), k.key(keys.STATE_SERVO))
    torch_pub = publisher(session_factory(), k.key(keys.STATE_TORCH))

    def arrived() -> bool:
        servo_pub.put(ServoState(pan=0.1745, tilt=-0.0873).stamp(1).encode())
        torch_pub.put(TorchState(on=True, brightness=0.8).stamp(1).encode())
        return client.servo is not None and client.torch is not None

    wait_until(arrived, 5.0, message="servo and torch state at the client")
    now = time.monotonic()
    app = OperatorConsole(ctrl)  # not run: its input panel is rendered from the view below

    def rows(v: ConsoleView) -> dict[str, tuple[str, str]]:
        """The input panel's rows: label → (text, style)."""
        labels, values = app._input(v).columns[0]._cells, app._input(v).columns[1]._cells
        return {str(k): (str(c), str(getattr(c, "style", ""))) for k, c in zip(labels, values, strict=True)}

    fresh = rows(ctrl.view(now))
    assert fresh["camera"] == ("pan +10° tilt -5°", "") and fresh["torch"] == ("on 80 %", ""), fresh
    old = rows(ctrl.view(now + ACTUATOR_STALE_S + 1.0))
    assert re.fullmatch(r"pan \+10° tilt -5° \(stale 2\.\d s\)", old["camera"][0]), old
    assert re.fullmatch(r"on 80 % \(stale 2\.\d s\)", old["torch"][0]), old
    assert old["camera"][1] == old["torch"][1] == "grey50", old


def test_camera_and_torch_rows_age_by_the_heartbeat_period_the_edge_says(session_factory, operator_factory) -> None:
    """Found by a review of the operator side: the rows aged by three heartbeats at the default 2 Hz (1.5 s) whatever
    the edge's servos/torch publish_hz: an edge at 0.2 Hz showed "stale" between every heartbeat, one at 50 Hz was
    shown current 1.5 s after it died. The states now say their period; a row is old after three of them (never
    sooner than a robot state: STATE_STALE_S), and after 1.5 s for a state that does not say (an older edge)."""
    import msgpack

    from iorthand.protocol import ServoState, TorchState
    from iorthand_operator.client import ACTUATOR_STALE_S, actuator_stale_after
    from iorthand_operator.link import STATE_STALE_S

    robot = "heartbot"  # no edge: only our messages reach this robot's keys
    client = operator_factory(robot, "op1")
    ctrl = ConsoleController(client, KeyboardInput(KeymapConfig()), ConsoleSettings())
    k = keys.RobotKeys(robot)
    servo_pub = publisher(session_factory(), k.key(keys.STATE_SERVO))
    torch_pub = publisher(session_factory(), k.key(keys.STATE_TORCH))

    def arrived(servo: bytes, torch: bytes) -> bool:
        servo_pub.put(servo)
        torch_pub.put(torch)
        return client.servo is not None and client.torch is not None

    slow_servo = ServoState(pan=0.1745, period=5.0).stamp(1).encode()  # servos.publish_hz 0.2
    fast_torch = TorchState(on=True, brightness=0.8, period=0.02).stamp(1).encode()  # torch.publish_hz 50
    wait_until(lambda: arrived(slow_servo, fast_torch), 5.0, message="servo and torch state at the client")
    time.sleep(0.2)  # the last puts of the wait arrive: the ages below count from the newest
    servo_at, torch_at = client.servo_at, client.torch_at
    assert ctrl.view(servo_at + 10.0).camera_stale == ""  # two heartbeats of 5 s missed: not yet old
    assert ctrl.view(servo_at + 15.5).camera_stale.startswith("stale 15."), "three heartbeats missed: old"
    assert ctrl.view(torch_at + 1.0).torch_stale.startswith("stale 1."), "a 50 Hz torch silent for 1 s is old"
    assert actuator_stale_after(TorchState(period=0.02)) == STATE_STALE_S  # 60 ms would flicker on a link's jitter

    # An older edge: its states have no period, and age as before, by three heartbeats at 2 Hz.
    def older(msg: ServoState | TorchState) -> bytes:
        data = msgpack.unpackb(msg.stamp(2).encode())
        del data["period"]
        return msgpack.packb(data)

    client.servo = client.torch = None
    wait_until(lambda: arrived(older(ServoState(pan=0.1745)), older(TorchState(on=True))), 5.0,
               message="an older edge's servo and torch state at the client")
    time.sleep(0.2)
    assert client.servo is not None and client.torch is not None and client.servo.period == client.torch.period == 0
    view = ctrl.view(client.servo_at + ACTUATOR_STALE_S - 0.3)
    assert view.camera_stale == "", view.camera_stale
    assert ctrl.view(client.servo_at + ACTUATOR_STALE_S + 0.3).camera_stale.startswith("stale 1.")
    assert ctrl.view(client.torch_at + ACTUATOR_STALE_S + 0.3).torch_stale.startswith("stale 1.")


def test_both_consoles_take_markers_out_of_view_at_the_same_age(session_factory, operator_factory) -> None:
    """Found by a review of the operator side: the web console stopped drawing markers 1 s after they arrived, the
    terminal console said "no marker data" only after 2 s (a literal of its own). Both follow MARKERS_SHOWN_S."""
    from iorthand.protocol import MarkerPose, Markers
    from iorthand_operator.client import MARKERS_SHOWN_S
    from iorthand_operator.web.server import markers_on_page

    robot = "markerbot"  # no edge: only our messages reach this robot's keys
    client = operator_factory(robot, "op1")
    ctrl = ConsoleController(client, KeyboardInput(KeymapConfig()), ConsoleSettings())
    pub = publisher(session_factory(), keys.RobotKeys(robot).key(keys.MARKERS))
    seen = Markers(markers=[MarkerPose(id=7, pose=np.eye(4).ravel().tolist())])

    def arrived() -> bool:
        pub.put(seen.stamp(1).encode())
        return client.markers is not None

    wait_until(arrived, 5.0, message="markers at the client")
    time.sleep(0.2)  # the last puts of the wait arrive: the ages below count from the newest
    shown, gone = MARKERS_SHOWN_S - 0.1, MARKERS_SHOWN_S + 0.1
    assert ctrl.view(client.markers_at + shown).markers == [7]
    late = ctrl.view(client.markers_at + gone)
    assert late.markers == [] and late.markers_note == f"no marker data for {gone:.1f} s", late.markers_note
    assert [m["id"] for m in markers_on_page(client.markers, shown)["markers"]] == [7]
    assert markers_on_page(client.markers, gone) == {"markers_note": f"no marker data for {gone:.1f} s"}


def test_the_deadman_row_shows_what_the_command_stream_sends(edge_factory, operator_factory) -> None:
    """Found by a review of the operator side: "deadman sent ON" came from the input device, while without a grant
    the stream sent nothing and under a new grant it sent the deadman released until a fresh press."""
    edge_factory()
    client = operator_factory()
    device = KeyboardInput(KeymapConfig())
    ctrl = ConsoleController(client, device, ConsoleSettings())
    client.wait_for_state()
    client.start()

    def poll(seconds: float) -> ConsoleView:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            ctrl.poll_once(time.monotonic())
            time.sleep(0.02)
        return ctrl.view()

    device.key("space", time.monotonic())  # the deadman toggled on before control is held
    v = poll(0.3)
    assert device.poll(time.monotonic()).deadman and client.sent_count == 0
    assert not v.deadman, "nothing is sent without a grant"
    client.acquire()
    v = poll(0.5)
    assert client.sent_count > 0 and client.echoes and client.echoes[-1].status == "deadman_released"
    assert not v.deadman and not any(v.command), "the new grant's stream sends the deadman released"
    assert v.hint.startswith("press SPACE"), v.hint
    device.key("space", time.monotonic())  # off
    poll(0.1)
    device.key("space", time.monotonic() + 1.0)  # and on again after a pause: a fresh press
    wait_until(lambda: poll(0.05).deadman, 3.0, message="the fresh press sent")
    wait_until(lambda: client.safety.deadman, 3.0, message="the edge seeing the deadman held")
    ctrl.stop()


def test_a_key_read_during_a_stall_is_stamped_when_it_was_read(operator_factory) -> None:
    """Found by a review of the operator side: keys were stamped when the UI handled them, so a move key pressed
    and let go while the UI stalled counted as held for initial_hold after the stall, and moved the robot then."""
    client = operator_factory("stallbot", "op1")  # no edge: the device's sample is what is checked
    device = KeyboardInput(KeymapConfig(deadman_mode="motion", initial_hold=0.4))
    app = OperatorConsole(ConsoleController(client, device, ConsoleSettings()))
    pressed: dict[str, float] = {}

    def press_during_the_stall() -> None:
        time.sleep(0.1)
        pressed["at"] = time.monotonic()
        app.post_message(events.Key("w", "w"))  # read now (textual stamps it so), handled after the stall

    async def run() -> tuple[bool, float]:
        async with app.run_test(size=(160, 50)) as pilot:
            await pilot.pause(0.2)
            threading.Thread(target=press_during_the_stall, daemon=True).start()
            time.sleep(1.0)  # the UI stalls (a slow render, a swapped-out terminal): nothing handled meanwhile
            await _wait(lambda: "at" in pressed and bool(device._last_event), 3.0, "the key handled")
            held = device.poll(time.monotonic()).deadman
            stamped = device._last_event["w"]
            await pilot.press("ctrl+c")
        return held, stamped

    held, stamped = asyncio.run(run())
    assert abs(stamped - pressed["at"]) < 0.1, (stamped, pressed["at"])
    assert not held, "a key pressed 0.9 s ago, initial_hold 0.4 s: no longer held"


def test_a_keymap_warning_is_in_the_console_log(operator_factory) -> None:
    """The load-time warning goes to stderr, behind the console's screen: the console's log says it too."""
    client = operator_factory("keymapbot", "op1")  # no edge: only the log is checked
    ctrl = ConsoleController(client, KeyboardInput(KeymapConfig(name="mine", deadman_mode="motion")), ConsoleSettings())
    ctrl.start()
    try:
        events = ctrl.view().events
    finally:
        ctrl.stop()
    assert any("warning" in e and "key 'space' is bound to 'deadman'" in e for e in events), events


def test_the_force_light_and_the_edges_status_are_on_a_small_terminal(session_factory, operator_factory) -> None:
    """Found by a red-team run of the console: on an 80×24 terminal the event log took the focus and scrolled the
    screen to itself, and the force panel's light and the robot's first rows went off the top; on 40×12 the three
    columns cut every label to a letter and the light was off screen too. A docked banner says the force level and
    the edge's status on any terminal; the panels take two columns at 80, one at 40, and leave the log room."""
    robot = "tinybot"  # no edge: only our messages reach this robot's keys
    s, k = session_factory(), keys.RobotKeys(robot)
    safety, force = publisher(s, k.key(keys.STATE_SAFETY)), publisher(s, k.key(keys.STATE_FORCE_LEVEL))
    reason = "stop from 'nurse': patient moved"

    async def run(app: OperatorConsole, size: tuple[int, int]) -> dict[str, object]:
        async with app.run_test(size=size) as pilot:
            for seq in range(1, 60):
                safety.put(SafetyStatus(status="stopped", reason=reason).stamp(seq).encode())
                force.put(ForceLevelState(level=2, stale=False, value=9.0).stamp(seq).encode())
                await pilot.pause(0.05)
                if app.view_model.edge_reason and app.view_model.force.label == "DANGER":
                    break
            await pilot.pause(0.2)
            screen = app.screen.region

            def shown(wid: str) -> bool:  # the widget's first line is on the screen
                region = app.query_one(f"#{wid}").region
                return region.height > 0 and screen.contains(region.x, region.y)

            seen = {"banner": _text(app, "banner"), "banner_row": app.query_one("#banner").region.y,
                    **{wid: shown(wid) for wid in ("status", "force", "events")},
                    "force_text": _text(app, "force"), "events_text": _text(app, "events")}
            await pilot.press("ctrl+c")
        return seen

    for size in ((80, 24), (40, 12)):
        _client, ctrl, app = _console(operator_factory, robot=robot)
        try:
            seen = asyncio.run(run(app, size))
        finally:
            ctrl.stop()
        assert seen["banner_row"] == 0 and seen["banner"].startswith(" DANGER  stopped stop from"), (size, seen)
        assert seen["status"], (size, seen)
        if size == (80, 24):
            assert seen["force"] and "DANGER" in seen["force_text"], seen
            assert seen["events"] and reason in seen["events_text"], seen


def test_every_event_reaches_the_log_however_alike_and_a_burst_says_what_it_left_out(operator_factory) -> None:
    """Found by a red-team run of the console: the log found its new lines by the text of the last one shown, so
    a stop between two alike refusals in the same second ("refused, stop, refused") never reached it. And after a
    burst of 10 000 events it showed the latest 50 without a word about the rest."""
    client, ctrl, app = _console(operator_factory, robot="logbot")

    async def run() -> tuple[list[str], list[str]]:
        async with app.run_test(size=(160, 50)) as pilot:
            log = app.query_one("#events", RichLog)
            client.log_event("refused", "no_deadman", "deadman released")
            await _wait(lambda: len(log.lines) == 1, message="the first refusal in the log")
            client.log_event("stop", "stopped", "e-stop sent: operator e-stop")
            client.log_event("refused", "no_deadman", "deadman released")
            await _wait(lambda: len(app.view_model.events) == 3, message="the view after the second refusal")
            await pilot.pause(0.3)  # (the lines written: a stop left out would not come later)
            alike = [line.text for line in log.lines]
            for i in range(10_000):  # at once: no refresh comes between them
                client.log_event("refused", "no_deadman", f"deadman released ({i})")
            await _wait(lambda: log.lines[-1].text.endswith("(9999)"), message="the burst's last event in the log")
            burst = [line.text for line in log.lines]
            await pilot.press("ctrl+c")
        return alike, burst

    try:
        alike, burst = asyncio.run(run())
    finally:
        ctrl.stop()
    assert [line.split(" ", 1)[1] for line in alike] == [
        "refused no_deadman: deadman released", "stop    stopped: e-stop sent: operator e-stop",
        "refused no_deadman: deadman released"], alike
    assert len(burst) <= len(alike) + 51  # bounded: the latest 50 and one line about the rest
    assert burst[len(alike)] == "… 9950 more events came at once: the latest 50 follow", burst[len(alike):][:3]
    assert burst[-1].endswith("deadman released (9999)")


def test_pose_names_with_brackets_are_shown_as_written(edge_factory, operator_factory) -> None:
    """Found by a red-team run of the console: the pose list read each pose's name (a key of the edge's goto.poses)
    as textual markup: a name with a closing tag ("lift [/] back") raised MarkupError and closed the console (the
    robot then stops: its command stream ends). Names and replies are shown as text, brackets and all."""
    name = "lift [/] back"
    edge_factory(goto={"poses": {name: [0.30, 0.0, 0.25, math.pi, 0.0, 0.0]}})
    client, ctrl, app = _console(operator_factory)
    client.wait_for_state()

    async def run() -> tuple[list[str], bool]:
        async with app.run_test(size=(160, 50)) as pilot:
            app.ui_action("poses")

            def listed() -> bool:
                found = app.screen.query("#pose-list") if len(app.screen_stack) > 1 else None
                return bool(found) and found.first(OptionList).option_count > 0

            await _wait(listed, 10.0, "the pose list")
            await pilot.pause(0.2)
            options = app.screen.query_one("#pose-list", OptionList)
            shown = [str(options.get_option_at_index(i).prompt) for i in range(options.option_count)]
            running = app.is_running
            await pilot.press("escape")
            await pilot.press("ctrl+c")
        return shown, running

    try:
        shown, running = asyncio.run(run())
    finally:
        ctrl.stop()
    assert running and name in shown, shown
