"""Force warning levels (pure): thresholds, hysteresis, staleness, and the level codes on the wire."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from iorthand.config import ConfigError, from_dict
from iorthand.protocol import FORCE_LEVEL_COLOURS, ForceLevel, ForceLevelState, SafetyStatus
from iorthand_edge.force import levels
from iorthand_edge.force.levels import LevelConfig, LevelTracker, next_level, quantity_value

CFG = LevelConfig()  # 6 N, 8 N, 0.5 N, 100 ms


def test_level_codes_are_defined_once_in_the_protocol() -> None:
    # The reference system shipped these inverted between robot and app: 0 must be safe, 2 danger.
    assert levels.ForceLevel is ForceLevel
    assert (int(ForceLevel.SAFE), int(ForceLevel.CAUTION), int(ForceLevel.DANGER)) == (0, 1, 2)
    assert FORCE_LEVEL_COLOURS[ForceLevel.SAFE] == "green" and FORCE_LEVEL_COLOURS[ForceLevel.DANGER] == "red"
    wire = ForceLevelState.decode(ForceLevelState(level=ForceLevel.DANGER, stale=False).stamp(1).encode())
    assert ForceLevel(wire.level) is ForceLevel.DANGER
    assert SafetyStatus.decode(SafetyStatus(force_level=0).stamp(1).encode()).force_level == ForceLevel.SAFE


def test_defaults_are_six_and_eight_newtons_on_abs_fz() -> None:
    assert (CFG.caution, CFG.danger, CFG.hysteresis, CFG.stale_after, CFG.quantity) == (6.0, 8.0, 0.5, 0.1, "fz")


@pytest.mark.parametrize(
    ("value", "expected"), [(0.0, 0), (5.99, 0), (6.0, 1), (7.99, 1), (8.0, 2), (50.0, 2)]
)
def test_rising_levels_change_at_the_thresholds(value: float, expected: int) -> None:
    assert next_level(ForceLevel.SAFE, value, CFG) == expected


def test_falling_levels_wait_for_the_hysteresis() -> None:
    assert next_level(ForceLevel.DANGER, 7.6, CFG) == ForceLevel.DANGER
    assert next_level(ForceLevel.DANGER, 7.49, CFG) == ForceLevel.CAUTION
    assert next_level(ForceLevel.CAUTION, 5.6, CFG) == ForceLevel.CAUTION
    assert next_level(ForceLevel.CAUTION, 5.49, CFG) == ForceLevel.SAFE
    assert next_level(ForceLevel.DANGER, 1.0, CFG) == ForceLevel.SAFE  # a sudden release drops all the way


def test_garbage_values_never_look_safe() -> None:
    assert next_level(ForceLevel.SAFE, math.nan, CFG) == ForceLevel.DANGER


@settings(max_examples=200, deadline=None)
@given(
    threshold=st.sampled_from([6.0, 8.0]),
    amplitude=st.floats(0.0, 0.49),
    phases=st.lists(st.floats(-1.0, 1.0), min_size=2, max_size=60),
)
def test_oscillation_smaller_than_the_hysteresis_does_not_flicker(threshold: float, amplitude: float, phases: list[float]) -> None:
    # Once the level has been reached, any force within ±amplitude (< hysteresis) of the threshold keeps it.
    tracker = LevelTracker(CFG)
    tracker.add([0, 0, threshold], 0.0)
    reached = tracker.level
    assert reached == (1 if threshold == 6.0 else 2)
    for i, p in enumerate(phases):
        tracker.add([0, 0, -(threshold + amplitude * p)], 0.01 * (i + 1))  # sign of Fz does not matter
        assert tracker.level == reached


def test_quantities() -> None:
    w = [3.0, 4.0, -2.0, 0.0, 0.0, 0.0]
    assert quantity_value(w, "fz") == 2.0
    assert quantity_value(w, "norm") == pytest.approx(math.sqrt(29.0))
    assert math.isnan(quantity_value([0, 0, math.nan, 0, 0, 0], "fz"))  # one sample too: NaN is never a value
    assert next_level(ForceLevel.SAFE, quantity_value([0, 0, math.nan, 0, 0, 0], "fz"), CFG) == ForceLevel.DANGER
    norm_cfg = LevelConfig(quantity="norm")
    assert next_level(ForceLevel.SAFE, quantity_value(w, "norm"), norm_cfg) == ForceLevel.SAFE
    assert next_level(ForceLevel.SAFE, quantity_value([6, 0, 0, 0, 0, 0], "norm"), norm_cfg) == ForceLevel.CAUTION


def test_a_peak_inside_a_batch_sets_the_level() -> None:
    """A fast sensor delivers many samples per tick: a spike among them counts even if the newest is calm."""
    calm, spike = [0, 0, -3.0, 0, 0, 0], [0, 0, -9.0, 0, 0, 0]
    batch = [calm, calm, spike, calm, calm]
    assert quantity_value(batch, "fz") == 9.0
    tracker = LevelTracker(CFG)
    assert tracker.add(batch, 1.0) == ForceLevel.DANGER and tracker.value == 9.0
    assert tracker.add([calm, calm], 1.01) == ForceLevel.SAFE  # the next calm batch: the level falls again
    assert math.isnan(quantity_value([calm, [0, 0, math.nan, 0, 0, 0]], "norm"))  # one bad sample is not hidden
    assert tracker.add([calm, [0, 0, math.nan, 0, 0, 0]], 1.02) == ForceLevel.DANGER


def test_stale_before_the_first_sample_and_after_silence() -> None:
    tracker = LevelTracker(CFG)
    assert tracker.state(0.0).stale
    tracker.add([0, 0, 1.0], 10.0)
    assert not tracker.state(10.1).stale  # just under stale_after (10.1 - 10.0 < 0.1): still fresh; the exact bound is
    # test_force_and_goto_rules.py's
    assert tracker.state(10.1001).stale


@pytest.mark.parametrize(
    ("data", "key"),
    [
        ({"caution": 8.0, "danger": 6.0}, "caution"),
        ({"hysteresis": 3.0}, "hysteresis"),
        ({"quantity": "fx"}, "quantity"),
        ({"stale_after": 0.0}, "stale_after"),
    ],
)
def test_bad_level_config_names_the_problem(data: dict, key: str) -> None:
    with pytest.raises(ConfigError, match=key):
        from_dict(data, LevelConfig)
