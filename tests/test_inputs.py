"""Input devices: axis shaping, gamepad mapping (pure), keyboard hold/deadman semantics, keymap loading."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from iorthand.config import ConfigError, from_dict, load
from iorthand_operator.inputs import AxisMap, GamepadConfig, KeyboardInput, KeymapConfig, load_keymap, map_gamepad
from iorthand_operator.inputs.mapping import shape_axis

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def test_shape_axis_deadband_expo_scale_invert() -> None:
    m = AxisMap(axis=0, scale=0.01, deadband=0.2, expo=0.0)
    assert shape_axis(0.19, m) == 0.0
    assert shape_axis(-0.2, m) == 0.0
    assert shape_axis(0.21, m) == pytest.approx(0.01 * 0.01 / 0.8)  # continuous at the deadband edge
    assert shape_axis(1.0, m) == pytest.approx(0.01)
    assert shape_axis(-1.0, m) == pytest.approx(-0.01)
    assert shape_axis(5.0, m) == pytest.approx(0.01)  # clamped
    assert shape_axis(float("nan"), m) == 0.0
    inv = AxisMap(axis=0, scale=1.0, deadband=0.0, invert=True)
    assert shape_axis(0.5, inv) == pytest.approx(-0.5)
    cubic = AxisMap(axis=0, scale=1.0, deadband=0.0, expo=1.0)
    assert shape_axis(0.5, cubic) == pytest.approx(0.125)  # fine control near the centre
    assert shape_axis(1.0, cubic) == pytest.approx(1.0)  # full speed at the end


def _pad(**kw: object) -> GamepadConfig:
    data = {
        "enable_button": 4, "turbo_button": 5, "turbo_factor": 2.0,
        "axes": {name: {"axis": i, "scale": 0.01, "deadband": 0.1} for i, name in enumerate(
            ("linear_x", "linear_y", "linear_z", "angular_x", "angular_y", "angular_z"))},
        "buttons": {"estop": 1},
    }
    data.update(kw)
    return from_dict(data, GamepadConfig, source="<test>")


def test_map_gamepad_needs_enable_and_maps_all_six_axes() -> None:
    cfg = _pad()
    axes = {i: 1.0 for i in range(6)}
    twist, deadman = map_gamepad(axes, set(), cfg)
    assert not deadman and not np.any(twist)
    twist, deadman = map_gamepad(axes, {4}, cfg)
    assert deadman and np.allclose(twist, 0.01)
    twist, _ = map_gamepad(axes, {4, 5}, cfg)
    assert np.allclose(twist, 0.02)  # turbo
    twist, _ = map_gamepad({0: 0.05, 1: -1.0}, {4}, cfg)
    assert twist[0] == 0.0 and twist[1] == pytest.approx(-0.01)  # axis 0 inside the deadband


def test_gamepad_config_rejects_unknown_names() -> None:
    with pytest.raises(ConfigError, match="linear_w"):
        _pad(axes={"linear_w": {"axis": 0}})
    with pytest.raises(ConfigError, match="fly"):
        _pad(buttons={"fly": 2})
    with pytest.raises(ConfigError, match="enable"):
        _pad(buttons={"estop": 4})
    for name in ("gamepad-xbox.yaml", "gamepad-generic.yaml"):
        load(CONFIGS / name, GamepadConfig)


def test_keyboard_hold_is_inferred_from_repeats() -> None:
    kb = KeyboardInput(KeymapConfig(initial_hold=0.6, repeat_hold=0.15, deadman_mode="toggle"))
    kb.key("space", 0.0)
    kb.key("w", 0.0)
    s = kb.poll(0.5)  # within the repeat delay: still held
    assert s.deadman and s.twist[0] == pytest.approx(0.005)
    assert not np.any(kb.poll(0.61).twist)  # no repeat came: released
    for t in np.arange(1.0, 2.0, 0.04):  # press, then repeats at 25 Hz
        kb.key("w", float(t))
    assert kb.poll(2.0).twist[0] > 0
    assert not np.any(kb.poll(1.96 + 0.16).twist)  # released: stops within repeat_hold
    assert kb.poll(2.2).deadman  # the toggle stays on...
    assert not kb.poll(1.96 + 5.01).deadman  # ...until it expires after the last key activity


def test_keyboard_toggle_and_actions() -> None:
    """A terminal reports presses only: a second press soon after the first is a held key's repeat or a second tap
    meant to turn the deadman off, and nothing tells which. It turns it off, never leaves it on (found by a
    red-team run: a tap 0.4 s after the first was taken for a repeat, and the deadman stayed on)."""
    kb = KeyboardInput()
    kb.key("space", 0.0)
    assert kb.poll(0.1).deadman
    kb.key("space", 0.4)  # a second tap soon after
    assert not kb.poll(0.45).deadman
    kb.key("space", 0.43)  # and the repeats of a key held down keep it off, never flicker it back on
    kb.key("space", 0.46)
    assert not kb.poll(0.5).deadman
    kb.key("space", 1.5)  # a press after a pause turns it on
    assert kb.poll(1.6).deadman
    kb.key("space", 1.7)  # held: its repeats turn it off
    assert not kb.poll(1.8).deadman
    kb.key("space", 3.0)
    kb.key("space", 4.0)
    assert not kb.poll(4.1).deadman
    kb.key("t", 2.0)
    kb.key("t", 2.03)  # repeat: one torch toggle, not two
    kb.key("x", 2.0)
    kb.key("x", 2.03)  # every stop counts
    assert kb.poll(2.1).actions == ["torch", "estop", "estop"]
    assert not kb.key("z", 3.0)  # unbound keys are left to the UI


def test_keyboard_motion_mode_deadman_is_the_held_key() -> None:
    kb = KeyboardInput(load_keymap("hold", CONFIGS))
    assert not kb.poll(0.0).deadman
    kb.key("r", 1.0)
    s = kb.poll(1.1)
    assert s.deadman and s.twist[2] > 0
    assert not kb.poll(1.7).deadman


def test_unknown_keymaps_fail_with_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"unknown key map 'nope'.*hold"):
        load_keymap("nope", CONFIGS)
    bad = tmp_path / "km.yaml"
    bad.write_text("keys: {w: +linear_w}\n")
    with pytest.raises(ConfigError, match=r"keys\.w.*linear_w"):
        load_keymap(str(bad))
    bad.write_text("keys: {notakey: estop, space: deadman}\n")
    with pytest.raises(ConfigError, match="notakey"):
        load_keymap(str(bad))
    assert load_keymap(str(CONFIGS / "keymap-default.yaml")).keys == KeymapConfig().keys
    bad.write_text("keys: {space: deadman, w: +linear_x, x: +linear_y, escape: -linear_y}\n")
    with pytest.raises(ConfigError, match="no key is bound to 'estop'"):  # it loaded: a console with no stop key
        load_keymap(str(bad))


def test_gamepad_through_sdl_injected_events() -> None:
    """The real pygame/SDL event path, headless, with an injected event stream (no device on this machine)."""
    from iorthand_operator.inputs.gamepad import GamepadInput

    pad = GamepadInput(_pad())
    try:
        s = pad.poll(0.0)
        pg = pad._pg
        if s.connected:  # a real pad is plugged in: leave it alone
            pytest.skip("a real joystick is attached")
        assert "no gamepad" in s.status
        pg.event.post(pg.event.Event(pg.JOYDEVICEADDED, device_index=0, guid="test"))
        pg.event.post(pg.event.Event(pg.JOYAXISMOTION, instance_id=0, joy=0, axis=0, value=0.05))  # deadband
        pg.event.post(pg.event.Event(pg.JOYAXISMOTION, instance_id=0, joy=0, axis=2, value=-1.0))
        pg.event.post(pg.event.Event(pg.JOYAXISMOTION, instance_id=0, joy=0, axis=5, value=0.55))
        s = pad.poll(0.1)
        assert s.connected and not s.deadman and not np.any(s.twist)  # no enable button: nothing
        pg.event.post(pg.event.Event(pg.JOYBUTTONDOWN, instance_id=0, joy=0, button=4))
        pg.event.post(pg.event.Event(pg.JOYBUTTONDOWN, instance_id=0, joy=0, button=1))
        s = pad.poll(0.2)
        assert s.deadman and s.actions == ["estop"]
        assert s.twist[0] == 0.0 and s.twist[2] == pytest.approx(-0.01) and s.twist[5] == pytest.approx(0.005)
        pg.event.post(pg.event.Event(pg.JOYHATMOTION, instance_id=0, joy=0, hat=0, value=(1, 0)))
        assert pad.poll(0.3).actions == ["pan_right"]
        pg.event.post(pg.event.Event(pg.JOYBUTTONUP, instance_id=0, joy=0, button=4))
        s = pad.poll(0.4)
        assert not s.deadman and not np.any(s.twist)
        pg.event.post(pg.event.Event(pg.JOYBUTTONDOWN, instance_id=0, joy=0, button=4))
        assert pad.poll(0.5).deadman
        pg.event.post(pg.event.Event(pg.JOYDEVICEREMOVED, instance_id=0))
        s = pad.poll(0.6)
        assert not s.connected and not s.deadman and not np.any(s.twist) and "UNPLUGGED" in s.status
        # Plugged back in: the enable button held before the unplug is not trusted.
        pg.event.post(pg.event.Event(pg.JOYDEVICEADDED, device_index=0, guid="test"))
        s = pad.poll(0.7)
        assert s.connected and not s.deadman
    finally:
        pad.close()


@pytest.mark.parametrize(("change", "message"), [
    ({"axes": {"linear_x": {"axis": 0}, "angular_z": {"axis": 0}}}, "axes.angular_z: axis 0 already drives linear_x"),
    ({"turbo_button": 4}, "turbo_button: button 4 is the enable \\(deadman\\) button"),
    ({"buttons": {"estop": 5}}, "buttons.estop: button 5 is the turbo button"),
    ({"buttons": {"estop": 1, "torch": 1}}, "buttons.torch: button 1 is already 'estop'"),
])
def test_a_gamepad_mapping_with_one_control_for_two_things_is_refused(change, message) -> None:
    """Found by a review of the operator side: a mapping that put two twist components on one stick axis, or the
    turbo on the enable button (every motion at turbo speed), loaded without a word."""
    with pytest.raises(ConfigError, match=message):
        _pad(**change)


def test_a_deadman_key_in_motion_mode_is_named_at_load(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Found by a review of the operator side: ``deadman_mode: motion`` with the default keys kept space bound to
    deadman, and pressing it silently did nothing. A warning at load names the key and why (not a refusal)."""
    path = tmp_path / "keymap-mine.yaml"
    path.write_text("name: mine\ndeadman_mode: motion\n")  # the default keys: space → deadman
    with caplog.at_level(logging.WARNING, logger="iorthand.operator"):
        km = load_keymap(str(path))
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "key 'space' is bound to 'deadman', which does nothing with deadman_mode: motion" \
        in warned[0] and str(path) in warned[0], warned
    kb = KeyboardInput(km)
    assert kb.warnings() == km.warnings() and "'space'" in kb.warnings()[0]
    kb.key("space", 10.0)
    assert not kb.poll(10.1).deadman  # what the warning says: it does nothing
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="iorthand.operator"):
        load_keymap("hold", CONFIGS)  # motion mode with no deadman key
        load_keymap(str(CONFIGS / "keymap-default.yaml"))  # toggle mode: space is its deadman
    assert not caplog.records and KeyboardInput(KeymapConfig()).warnings() == []
