"""Headless operator: ``iorthand operator script FILE.yaml`` plays timed twists and actions, prints JSON.

A script file::

    name: square
    profile: local            # optional: speed profile asked for on acquire
    steps:
      - {twist: [0.01, 0, 0, 0, 0, 0], duration: 1.0}   # m/s, rad/s, deadman held
      - {twist: [0, 0, 0, 0.1, 0, 0], duration: 1.0, frame: tool}  # rock the probe about its tip
      - {wait: 0.5}                                     # deadman released (zero twists, then quiet)
      - {action: torch, torch_on: true}          # ("on" would be a YAML 1.1 boolean key)
      - {action: servo, pan_deg: 10, tilt_deg: -5}
      - {action: profile, profile: remote}
      - {action: silence, duration: 0.5}                # sender muted with the deadman held: a dead link
      - {action: contact, contact_on: true, contact_force: 4.0}  # the edge holds 4 N along the probe
      - {action: stop, reason: end of scan}

Steps run on the same client and fixed-rate sender as the console; the summary reports per step what was
sent, echoed, accepted or refused (with the distinct refusal reasons) and how far the tool moved. A motion step
(a twist with the deadman held) lasts until the robot has moved for its duration: a lost lease, a dead link or
a halt on the way is recovered from by the script itself (its intent is clear), within ``patience`` s.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from iorthand import stats
from iorthand.config import setting
from iorthand.protocol import RobotState, Status
from iorthand_operator.client import ControlRefused, OperatorClient
from iorthand_operator.scripted import drive_for

STEP_ACTIONS = ("stop", "torch", "servo", "profile", "silence", "contact")
# The fields each kind of step takes besides the one that names its kind. A field given to a kind it does not apply
# to is refused: it would be ignored, and the script would not do what it says (``{wait: 1, duration: 5}`` waited
# 1 s; ``{action: stop, torch_on: true}`` stopped and left the torch as it was).
STEP_FIELDS = {
    "twist": ("duration", "frame", "deadman"),
    "wait": (),
    "stop": ("reason", "duration"),
    "torch": ("torch_on", "brightness", "duration"),
    "servo": ("pan_deg", "tilt_deg", "duration"),
    "profile": ("profile", "duration"),
    "silence": ("duration",),
    "contact": ("contact_on", "contact_force", "duration"),
}


@dataclass
class ScriptStep:
    """One step. Every field is None until given, so that one given to a kind of step it does not apply to is seen
    even at its default value; run_step applies the defaults the comments name."""

    twist: list[float] | None = setting(None, length=6, lo=-10.0, hi=10.0)
    frame: str | None = setting(None, choices=("base", "tool"), help="of the twist: base (default), or the probe's")
    duration: float | None = setting(None, lo=0.0, hi=3600.0, help="s; after an action, s before the next step")
    deadman: bool | None = None  # of a twist: held (default) or released
    wait: float | None = setting(None, lo=0.0, hi=3600.0)
    action: str | None = setting(None, choices=STEP_ACTIONS)
    reason: str | None = None  # of a stop; default "script stop"
    torch_on: bool | None = None  # default on
    brightness: float | None = setting(None, lo=0.0, hi=1.0, help="default 1")
    pan_deg: float | None = setting(None, lo=-180.0, hi=180.0)
    tilt_deg: float | None = setting(None, lo=-180.0, hi=180.0)
    profile: str | None = None
    contact_on: bool | None = None  # action contact: on (holding contact_force; default) or off
    contact_force: float | None = setting(None, lo=0.5, hi=50.0, help="N; default: the edge's contact.target")

    def check(self) -> None:
        given = [k for k in ("twist", "wait", "action") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(f"a step needs exactly one of twist, wait, action (got {given or 'none'})")
        kind, takes = self.kind, STEP_FIELDS[self.kind]
        for f in fields(self):
            if f.name not in (given[0], *takes) and getattr(self, f.name) is not None:
                also = f"it takes {', '.join(takes)}" if takes else "its 'wait' is its duration"
                raise ValueError(f"a {kind} step does not take {f.name!r} ({also})")
        if kind == "twist" and self.deadman is False and any(self.twist or ()):
            raise ValueError("a twist step with the deadman released sends a zero twist: give zeros, or a wait step")
        if kind in ("twist", "silence") and not self.seconds > 0:
            raise ValueError(f"a {kind} step needs a duration > 0 s")
        if kind == "profile" and not self.profile:
            raise ValueError("a profile step needs 'profile'")
        if kind == "servo" and self.pan_deg is None and self.tilt_deg is None:
            raise ValueError("a servo step needs pan_deg, tilt_deg or both")
        if kind == "contact" and self.contact_on is False and self.contact_force is not None:
            raise ValueError("a contact step that turns contact off does not take 'contact_force'")

    @property
    def kind(self) -> str:
        return "twist" if self.twist is not None else "wait" if self.wait is not None else str(self.action)

    @property
    def seconds(self) -> float:
        return 0.0 if self.duration is None else self.duration


@dataclass
class Script:
    name: str = "script"
    profile: str = ""
    settle: float = setting(0.5, lo=0.0, hi=30.0, help="s to wait for echoes and rest after the last step")
    patience: float = setting(30.0, lo=0.0, hi=3600.0,
                              help="s a motion step may take beyond its duration to recover from halts")
    steps: list[ScriptStep] = field(default_factory=list)

    def check(self) -> None:
        if not self.steps:
            raise ValueError("steps: a script needs at least one step")


def _pos(client: OperatorClient) -> np.ndarray | None:
    s = client.robot_state
    return None if s is None else np.array(s.tcp_pose[:3])


def _mm(p: np.ndarray | None) -> list[float] | None:
    return None if p is None else (1000 * p).round(2).tolist()


def run_step(client: OperatorClient, step: ScriptStep, patience: float = 30.0,
             since: float | None = None) -> dict[str, Any]:
    """One step. ``since`` (monotonic): a stop from somebody else after it ends a motion (the script's start)."""
    start, sent0, echo0, ev0 = _pos(client), client.sent_count, client.echo_count, client.event_count
    t0 = time.monotonic()
    zero = np.zeros(3)
    silence: dict[str, float | None] = {}
    recoveries: list[str] = []
    if step.twist is not None:
        tw = np.asarray(step.twist, float)
        deadman = step.deadman is not False
        client.set_twist(tw[:3], tw[3:], deadman=deadman, frame=step.frame or "base")
        if deadman and np.any(tw):  # a motion: it goes on through halts until done (drive_for)
            _, recoveries = drive_for(client, step.seconds, patience, since)
        else:
            time.sleep(step.seconds)
    elif step.wait is not None:
        client.set_twist(zero, zero, deadman=False)
        time.sleep(step.wait)
    elif step.action == "stop":
        client.emergency_stop(step.reason if step.reason is not None else "script stop")
        time.sleep(step.seconds)
    elif step.action == "torch":
        client.set_torch(step.torch_on is not False, 1.0 if step.brightness is None else step.brightness)
        time.sleep(step.seconds)
    elif step.action == "servo":
        client.send_servo(
            None if step.pan_deg is None else np.radians(step.pan_deg),
            None if step.tilt_deg is None else np.radians(step.tilt_deg),
        )
        time.sleep(step.seconds)
    elif step.action == "profile":
        profile = step.profile or ""
        try:
            client.switch_profile(profile)
        except ControlRefused as exc:
            client.log_event("refused", "profile", f"profile {profile!r} refused: {exc}")
        time.sleep(step.seconds)
    elif step.action == "contact":
        try:
            client.set_contact(step.contact_on is not False, step.contact_force)
        except ControlRefused as exc:
            client.log_event("refused", "contact", f"contact mode: {exc}")
        time.sleep(step.seconds)
    elif step.action == "silence":
        after_sent, after_receipt = _silence(client, step.seconds) or (None, None)
        silence = {"deadman_stop_ms": after_sent, "deadman_stop_after_receipt_ms": after_receipt}
    end = _pos(client)
    echoes = client.echoes_since(echo0)
    return {
        "kind": step.kind,
        "seconds": round(time.monotonic() - t0, 3),
        "start_mm": _mm(start),
        "end_mm": _mm(end),
        "moved_mm": None if start is None or end is None else round(1000 * float(np.linalg.norm(end - start)), 2),
        "sent": client.sent_count - sent0,
        "echoed": len(echoes),
        "accepted": sum(e.accepted for e in echoes),
        "refused": sum(not e.accepted for e in echoes),
        "events": [f"{e.kind} {e.status}: {e.reason}" for e in client.events_since(ev0)],
        **({"recoveries": recoveries} if recoveries else {}),
        **silence,
    }


def _silence(client: OperatorClient, duration: float) -> tuple[float, float] | None:
    """Mute the sender with the deadman held (a dead link) for ``duration``. Returns the ms to the edge's first
    state with a zero commanded twist from the last command sent, and from when the edge received it (the
    edge's bound, timeout + one control period, runs from there; the first also holds the command's transit).
    Edge time stamps, one host clock in the demo and tests. None if the robot was not stopped within the
    silence."""
    client.muted = True
    time.sleep(2.0 / client.rate_hz)  # a send may still be under way
    last_sent = client.last_sent_ns
    deadline = time.monotonic() + duration
    stop: RobotState | None = None
    while time.monotonic() < deadline:
        state = client.robot_state
        if stop is None and state is not None and state.t > last_sent and not np.any(state.commanded):
            stop = state
        time.sleep(0.002)
    client.muted = False
    if stop is None:
        return None
    return round((stop.t - last_sent) / 1e6, 1), round((stop.t - stop.cmd_recv_t) / 1e6, 1)


def run_script(client: OperatorClient, script: Script) -> dict[str, Any]:
    """Play ``script`` on a started client that holds control; return the JSON-able summary."""
    client.wait_for_echoes()  # the grant's release, sent as the client started, is not the script's
    start, sent0, echo0 = _pos(client), client.sent_count, client.echo_count
    # A stop that somebody else sends while the script runs ends it: the script was the intent for what came
    # before, not for what comes after (its later motions pressed the deadman afresh and moved again).
    since = time.monotonic()
    steps: list[dict[str, Any]] = []
    ended = ""
    for step in script.steps:
        steps.append(run_step(client, step, script.patience, since))
        if client.stopped_by_other_at > since:
            ended = f"{client.stopped_by_other}: the script ended there; run it again to go on"
            client.set_twist(np.zeros(3), np.zeros(3), deadman=False)
            client.log_event("stop", Status.STOPPED, ended)
            break
    client.set_twist(np.zeros(3), np.zeros(3), deadman=False)
    time.sleep(script.settle)
    end = _pos(client)
    echoes = client.echoes_since(echo0)
    q = client.link_quality()
    safety = client.safety
    refusals = sorted({f"{e.status}: {e.reason}" for e in client.events if e.kind == "refused"})
    return {
        "script": script.name,
        "ended_by_stop": ended,
        "robot": client.keys.robot,
        "operator": client.operator_id,
        "profile": safety.profile if safety else "",
        "steps": steps,
        "commands_sent": client.sent_count - sent0,
        "commands_echoed": len(echoes),
        "commands_accepted": sum(e.accepted for e in echoes),
        "commands_refused": sum(not e.accepted for e in echoes),
        "refusals": refusals,
        "net_displacement_mm": None if start is None or end is None else round(1000 * float(np.linalg.norm(end - start)), 2),
        "start_mm": _mm(start),
        "end_mm": _mm(end),
        "command_to_echo_ms": {k: round(v, 3) for k, v in stats.summary([e.rtt_ms for e in echoes]).items()},
        "link": {
            "rtt_p50_ms": round(q.rtt_p50_ms, 3), "rtt_p95_ms": round(q.rtt_p95_ms, 3),
            "jitter_ms": round(q.jitter_ms, 3), "uplink_loss": q.uplink_loss, "downlink_loss": q.downlink_loss,
        },
        "peak_force_level": client.peak_force_level,
        "deadman_stops_ms": [s["deadman_stop_ms"] for s in steps if s.get("deadman_stop_ms") is not None],
        "deadman_stops_after_receipt_ms": [s["deadman_stop_after_receipt_ms"] for s in steps
                                           if s.get("deadman_stop_after_receipt_ms") is not None],
        "final_status": {"status": safety.status, "reason": safety.reason, "owner": safety.owner} if safety else {},
        "edge_counters": {
            "received": safety.received, "applied": safety.applied, "rejected": safety.rejected,
            "malformed": safety.malformed, "superseded": safety.superseded, "stops": safety.stops,
        } if safety else {},
    }
