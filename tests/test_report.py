"""Session report maths (pure): the performance index against the reference's published rows, contact time,
warning edges, hysteresis."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import pytest
from mcap.writer import CompressionType, Writer

from iorthand.protocol import ForceSample, TwistCommand
from iorthand_cloud.recorder import manifest as mf
from iorthand_cloud.recorder import metrics
from iorthand_cloud.recorder.config import ReportConfig
from iorthand_cloud.recorder.report import build_report
from iorthand_cloud.recorder.simulate import expected_events


@pytest.mark.parametrize(
    ("t_t", "tau", "red", "yellow", "phi"),
    [(180.67, 55.88, 6, 15, 57.02), (130.46, 51.22, 0, 4, 88.66)],
)
def test_performance_index_matches_the_published_rows(t_t, tau, red, yellow, phi) -> None:
    ix = metrics.PerformanceIndex(t_t, tau, red, yellow)
    assert ix.phi == pytest.approx(phi, abs=0.01)
    assert ix.omega == 4 * red + yellow
    assert 0 < ix.psi < 1  # ψ is a fraction: in percent neither row comes out


def test_performance_index_edges() -> None:
    assert math.isnan(metrics.PerformanceIndex(0.0, 0.0, 0, 0).phi)
    assert metrics.PerformanceIndex(10.0, 10.0, 1, 0).phi == -math.inf
    assert metrics.PerformanceIndex(10.0, 5.0, 0, 0, alpha=100.0).phi == pytest.approx(50.0)


def test_contact_time_counts_samples_above_threshold_and_caps_gaps() -> None:
    samples = [(i * 0.01, 5.0 if 100 <= i < 300 else 0.0) for i in range(500)]
    assert metrics.contact_time(samples, 1.0, 0.1) == pytest.approx(2.0)
    gap = [(0.0, 5.0), (0.01, 5.0), (3.0, 5.0)]  # a silent sensor for 3 s is not 3 s of contact
    assert metrics.contact_time(gap, 1.0, 0.1) == pytest.approx(0.01 + 0.1 + 0.01)
    assert metrics.contact_time([], 1.0, 0.1) == 0.0


def test_warning_edges_count_rising_edges_only() -> None:
    levels = [0, 1, 1, 2, 1, 2, 0, 2, 2, 1, 0, 1]
    samples = [(float(i), lv, False) for i, lv in enumerate(levels)]
    red, yellow, edges = metrics.warning_edges(samples)
    # 0→1 (t=1), 1→2 (3), 1→2 (5), 0→2 (7), 0→1 (11); 2→1 at 4 and 9 are falling edges.
    assert (red, yellow) == (3, 2)
    assert [t for t, _ in edges] == [1.0, 3.0, 5.0, 7.0, 11.0]


def test_stale_levels_are_skipped() -> None:
    red, yellow, _ = metrics.warning_edges([(0, 2, False), (1, 0, True), (2, 2, False)])
    assert (red, yellow) == (1, 0)  # the stale sample is no evidence the level fell


def test_levels_from_force_with_hysteresis() -> None:
    values = [0.0, 6.5, 5.8, 6.2, 5.4, 8.5, 7.8, 7.4, 0.0]
    levels = [lv for _, lv in metrics.levels_from_force(enumerate(values), 6.0, 8.0, 0.5)]
    assert levels == [0, 1, 1, 1, 0, 2, 2, 1, 0]


def test_rising_edges_and_teleoperation_time() -> None:
    states = [(0.0, "ok"), (1.0, "command_timeout"), (1.1, "command_timeout"), (2.0, "ok"), (3.0, "deadman_released")]
    assert metrics.rising_edges(states, {"command_timeout", "deadman_released"}) == [1.0, 3.0]
    assert metrics.teleoperation_time([(1.0, False), (2.0, True), (5.0, True), (6.0, False)]) == 3.0


def test_simulation_script_expectations() -> None:
    ev = expected_events(10.0)
    assert ev == {"contact_time": 6.0, "omega_R": 2, "omega_Y": 1, "deadman_stops": 1}
    assert expected_events(20.0)["omega_R"] == 4


def _write_session(folder: Path, seconds: float, commands: Callable[[int], Iterable[tuple[str, int, TwistCommand]]]
                   ) -> Path:
    """A session written straight to MCAP as the recorder would: 3 N of force (contact, below caution) at 100 Hz
    for ``seconds``, and the twist commands ``commands(t0)`` gives: (key, receive time, stamped command)."""
    folder.mkdir()
    t0 = time.time_ns()
    messages = []
    with (folder / "telemetry-0001.mcap").open("wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start("iorthand", "crafted")
        force = w.register_channel("iorthand/sim1/state/force", "msgpack", 0)
        for i in range(int(seconds * 100)):
            t = t0 + i * 10_000_000
            messages.append((t + 1_000_000, force, ForceSample(force=[0, 0, 3.0]).stamp(i + 1, t).encode(), t, i + 1))
        channels: dict[str, int] = {}
        for key, log_time, c in commands(t0):
            if key not in channels:
                channels[key] = w.register_channel(key, "msgpack", 0)
            messages.append((log_time, channels[key], c.encode(), c.t, c.seq))
        for log_time, channel, data, publish_time, seq in sorted(messages):
            w.add_message(channel, log_time, data, publish_time, seq)
        w.finish()
    mf.Manifest(session_id=folder.name, status=mf.COMPLETE, start_t=t0, stop_t=t0 + int(seconds * 1e9)).write(folder)
    return folder


def _crafted_session(folder: Path, held_until_s: float, operator_ahead_s: float, commands: bool = True,
                     seconds: float = 20.0) -> Path:
    """Force for the whole session; twist commands at 50 Hz, the deadman held for the first ``held_until_s``,
    stamped by an operator clock ``operator_ahead_s`` ahead of the edge's."""
    def twists(t0: int) -> Iterator[tuple[str, int, TwistCommand]]:
        for i in range(int(seconds * 50) if commands else 0):
            t = t0 + i * 20_000_000
            c = TwistCommand(operator="op1", deadman=t - t0 < held_until_s * 1e9)
            yield "iorthand/sim1/cmd/twist", t + 2_000_000, c.stamp(i + 1, t + int(operator_ahead_s * 1e9))
    return _write_session(folder, seconds, twists)


def test_contact_counts_only_within_the_teleoperation_window(tmp_path: Path) -> None:
    """Found by a red-team run: contact for 20 s, the deadman held for the first 10: τ counted all 20 s against
    t_t = 10 s, ψ 2.004 and φ 460 %."""
    data = build_report(_crafted_session(tmp_path / "a", 10.0, 0.0), ReportConfig(plots=False))
    r = data["robots"]["sim1"]
    assert r["index"]["t_t"] == pytest.approx(9.98, abs=0.03)
    assert r["index"]["tau"] == pytest.approx(r["index"]["t_t"], abs=0.03) and r["index"]["psi"] <= 1.0
    assert r["figures_within"] == "teleoperation"


def test_an_operator_clock_ahead_of_the_edges_keeps_the_commands(tmp_path: Path) -> None:
    """Found by a red-team run: an operator laptop 30 s ahead of the edge had every command discarded as
    implausible (one clock offset per robot, taken across the edge's series and the operator's)."""
    data = build_report(_crafted_session(tmp_path / "b", 20.0, 30.0), ReportConfig(plots=False))
    r = data["robots"]["sim1"]
    assert r["implausible_time"] == 0 and r["commands"] == 1000
    assert r["index"]["t_t"] == pytest.approx(19.98, abs=0.03)
    assert r["index"]["tau"] == pytest.approx(19.98, abs=0.05)  # the window put on the edge's clock


def test_the_report_says_where_t_t_comes_from(tmp_path: Path) -> None:
    """Found by a red-team run: without commands, t_t silently became the session's span."""
    data = build_report(_crafted_session(tmp_path / "c", 0.0, 0.0, commands=False), ReportConfig(plots=False))
    r = data["robots"]["sim1"]
    assert r["index"]["t_t"] == pytest.approx(20.0) and r["figures_within"] == "session"
    assert r["t_t_source"] == "session span: no commands were recorded"
    report = (tmp_path / "c" / "report" / "report.md").read_text()
    assert "t_t from the session span: no commands were recorded" in report


def _two_operators_session(folder: Path, ahead_s: dict[str, float], seconds: float = 20.0) -> Path:
    """Force for the whole session; op1 commands (deadman held) at 50 Hz in the first half, op2 in the second,
    each on its own key and stamped by its own clock, ``ahead_s`` ahead of the edge's."""
    def twists(t0: int) -> Iterator[tuple[str, int, TwistCommand]]:
        half = int(seconds * 25)
        for n, (op, ahead) in enumerate(ahead_s.items()):
            for i in range(half):
                t = t0 + (n * half + i) * 20_000_000
                c = TwistCommand(operator=op, deadman=True).stamp(i + 1, t + int(ahead * 1e9))
                yield f"iorthand/sim1/cmd/twist/{op}", t + 2_000_000, c
    return _write_session(folder, seconds, twists)


@pytest.mark.parametrize("ahead", [{"op1": 0.0, "op2": 60.0}, {"op1": 45.0, "op2": -3.0}, {"op1": 0.0, "op2": 5.0}])
def test_each_operator_has_its_own_clock_offset(tmp_path: Path, ahead: dict[str, float]) -> None:
    """Found by a review: one clock offset for all of a robot's commands: with two operators whose clocks
    differ by more than 10 s, one operator's commands were all discarded as implausible (500 of 1000) and
    t_t was half the session; with 2-9 s apart the window would have been stretched or shrunk instead."""
    data = build_report(_two_operators_session(tmp_path / "s", ahead), ReportConfig(plots=False))
    r = data["robots"]["sim1"]
    assert r["implausible_time"] == 0 and r["commands"] == 1000
    assert r["index"]["t_t"] == pytest.approx(19.98, abs=0.03)  # op1's first to op2's last, on one clock
    assert r["index"]["tau"] == pytest.approx(19.98, abs=0.05)  # the window put on the edge's clock
