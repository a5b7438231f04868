"""Headless scripts: ``iorthand operator script FILE.yaml`` and run_script."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from iorthand.config import ConfigError, from_dict, load
from iorthand_operator.script import Script, run_script
from tests.conftest import ROOT, iorthand_cmd

SCRIPT = """
name: test
steps:
  - {twist: [0.006, 0, 0, 0, 0, 0], duration: 0.6}
  - {wait: 0.3}
  - {action: torch, torch_on: true}
  - {action: profile, profile: warp}
  - {action: stop, reason: end of test, duration: 0.2}
"""


def test_script_validation() -> None:
    with pytest.raises(ConfigError, match="exactly one of"):
        from_dict({"steps": [{"twist": [0] * 6, "wait": 1.0, "duration": 1}]}, Script)
    with pytest.raises(ConfigError, match="duration"):
        from_dict({"steps": [{"twist": [0] * 6}]}, Script)
    with pytest.raises(ConfigError, match="6 values"):
        from_dict({"steps": [{"twist": [0, 0], "duration": 1}]}, Script)
    with pytest.raises(ConfigError, match="action"):
        from_dict({"steps": [{"action": "dance"}]}, Script)


@pytest.mark.parametrize(("step", "index", "kind", "field"), [
    ({"wait": 1.0, "duration": 5.0}, 1, "wait", "duration"),
    ({"wait": 1.0, "frame": "tool"}, 1, "wait", "frame"),
    ({"action": "stop", "torch_on": True}, 1, "stop", "torch_on"),  # at its old default value: still no torch
    ({"action": "torch", "reason": "why"}, 1, "torch", "reason"),
    ({"twist": [0.01, 0, 0, 0, 0, 0], "duration": 1.0, "profile": "remote"}, 1, "twist", "profile"),
    ({"action": "servo", "pan_deg": 10, "deadman": False}, 1, "servo", "deadman"),
    ({"action": "silence", "duration": 0.5, "frame": "base"}, 1, "silence", "frame"),
])
def test_a_step_refuses_what_does_not_apply_to_its_kind(step, index, kind, field, tmp_path: Path) -> None:
    """Found by a review of the operator side: a field for another kind of step was taken and ignored
    (``{wait: 1, duration: 5}`` waited 1 s, ``{action: stop, torch_on: true}`` left the torch as it was)."""
    path = tmp_path / "s.yaml"
    path.write_text(json.dumps({"steps": [{"wait": 0.1}, step]}))  # (JSON is YAML)
    with pytest.raises(ConfigError) as err:
        load(path, Script)
    assert err.value.key == f"steps[{index}]", err.value
    assert f"a {kind} step does not take {field!r}" in str(err.value), err.value


def test_steps_that_would_do_nothing_are_refused() -> None:
    with pytest.raises(ConfigError, match=r"steps\[0\]: a silence step needs a duration > 0 s"):
        from_dict({"steps": [{"action": "silence"}]}, Script)
    with pytest.raises(ConfigError, match="a servo step needs pan_deg, tilt_deg or both"):
        from_dict({"steps": [{"action": "servo", "duration": 1.0}]}, Script)
    with pytest.raises(ConfigError, match="turns contact off does not take 'contact_force'"):
        from_dict({"steps": [{"action": "contact", "contact_on": False, "contact_force": 4.0}]}, Script)
    with pytest.raises(ConfigError, match="deadman released sends a zero twist"):
        from_dict({"steps": [{"twist": [0.01, 0, 0, 0, 0, 0], "duration": 1.0, "deadman": False}]}, Script)
    from_dict({"steps": [{"twist": [0] * 6, "duration": 1.0, "deadman": False}]}, Script)  # released on purpose


def test_the_demo_script_loads() -> None:
    assert len(load(ROOT / "configs" / "demo-script.yaml", Script).steps) > 10


def test_run_script_moves_and_reports(edge_factory, operator_factory, tmp_path: Path) -> None:
    edge_factory()
    client = operator_factory()
    (tmp_path / "s.yaml").write_text(SCRIPT)
    script = load(tmp_path / "s.yaml", Script)
    client.wait_for_state()
    client.acquire()
    client.start()
    summary = run_script(client, script)
    move = summary["steps"][0]
    assert move["kind"] == "twist" and move["moved_mm"] > 2.0 and move["accepted"] > 0
    assert summary["steps"][3]["events"] and "warp" in summary["steps"][3]["events"][0]  # refused profile
    assert summary["final_status"]["status"] == "stopped"
    assert summary["commands_echoed"] > 0 and summary["link"]["rtt_p50_ms"] > 0
    json.dumps(summary)


def test_script_command_line(edge_factory, router_endpoint: str, tmp_path: Path) -> None:
    edge_factory()
    path = tmp_path / "s.yaml"
    path.write_text("steps:\n  - {twist: [0, 0.006, 0, 0, 0, 0], duration: 0.5}\n  - {wait: 0.2}\n")
    out = subprocess.run(
        iorthand_cmd("--log-level", "warning", "operator", "script", str(path), "--robot", "sim1",
                     "--operator-id", "scripter", "--connect", router_endpoint),
        capture_output=True, text=True, timeout=60,
    )
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    assert summary["operator"] == "scripter" and summary["steps"][0]["moved_mm"] > 1.5


def test_a_silent_link_in_a_script_reports_the_stop_from_the_send_and_from_the_edge(edge_factory, operator_factory,
                                                                                    tmp_path: Path) -> None:
    """The demo's dead-link line: the stop timed from the last command sent (with its transit) and from when the
    edge received it, where the edge's bound (timeout + one control period) runs from."""
    edge = edge_factory()
    client = operator_factory()
    (tmp_path / "s.yaml").write_text("steps:\n  - {twist: [0.005, 0, 0, 0, 0, 0], duration: 0.5}\n"
                                     "  - {action: silence, duration: 0.6}\n")
    script = load(tmp_path / "s.yaml", Script)
    client.wait_for_state()
    client.acquire()
    client.start()
    summary = run_script(client, script)
    [after_sent], [after_receipt] = summary["deadman_stops_ms"], summary["deadman_stops_after_receipt_ms"]
    timeout_ms = 1000 * edge.config.safety.command_timeout
    assert timeout_ms - 1.0 <= after_receipt <= timeout_ms + 1000 * edge.period, summary["steps"][1]
    assert after_sent >= after_receipt  # the command left before it arrived
