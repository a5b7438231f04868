"""What the console shows, computed from the client's state: pure functions, no UI, unit-tested.

The force block is the reference system's traffic light done right: it is green only for a *fresh* message
that says level 0 and not stale. No message yet → grey "NO DATA"; the edge says stale, or nothing arrived for
``stale_after`` s (a silent sensor, a dead link) → grey "STALE".
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from iorthand.protocol import FORCE_LEVEL_COLOURS, ForceLevel, ForceLevelState, SensorReading, printable
from iorthand_operator.client import MARKERS_SHOWN_S
from iorthand_operator.link import GRADE_COLOURS, LinkQuality, LinkThresholds

GREY = "grey50"
_SPARK = "▁▂▃▄▅▆▇█"


@dataclass(frozen=True)
class ForceView:
    colour: str  # green / yellow / red / grey50
    label: str  # SAFE / CAUTION / DANGER / NO DATA / STALE
    detail: str  # "fz 4.2 N (caution 6, danger 8)"


def force_view(msg: ForceLevelState | None, received_at: float, now: float, stale_after: float) -> ForceView:
    if msg is None:
        return ForceView(GREY, "NO DATA", "no force level received")
    age = now - received_at
    thresholds = f"(caution {msg.caution:g} N, danger {msg.danger:g} N)"
    if msg.stale:
        return ForceView(GREY, "STALE", f"edge reports the force sensor stale {thresholds}")
    if age > stale_after:
        return ForceView(GREY, "STALE", f"no force level for {age:.1f} s {thresholds}")
    level = ForceLevel(msg.level)
    return ForceView(
        FORCE_LEVEL_COLOURS[level].replace("grey", GREY), level.name, f"{msg.quantity} {msg.value:.1f} N {thresholds}"
    )


def vitals_line(vitals: Mapping[str, tuple[SensorReading, float]], now: float, old_after: float = 5.0) -> str:
    """The patient's vital signs for a status line, by name: "heart_rate 72 bpm · spo2 98 %"; a reading older
    than ``old_after`` s says how old it is (a silent sensor must not pass for a steady patient)."""
    parts = []
    for name in sorted(vitals):
        msg, at = vitals[name]
        age = now - at
        parts.append(f"{name} {msg.value:g} {msg.unit}".strip() + (f" ({age:.0f} s old)" if age > old_after else ""))
    return " · ".join(parts)


def stale_note(age: float, stale_after: float) -> str:
    """"stale 3.2 s" for a state ``age`` s old when that is more than ``stale_after``; "" while it is current."""
    return f"stale {age:.1f} s" if age > stale_after else ""


def markers_note(failure: str, age: float) -> tuple[str, bool]:
    """Why a console shows no markers, ``age`` s after the newest arrived ("" while it shows them), and whether that
    is a camera failure: the edge's ``failure`` first, whatever the age (an empty view then is no camera, not no
    marker in view), then markers older than MARKERS_SHOWN_S, said to be that old. Both consoles' rule and words."""
    if failure:
        return f"camera failed: {failure}", True
    if age >= MARKERS_SHOWN_S:
        return f"no marker data for {age:.1f} s", False
    return "", False


# A video picture is shown as not live once no newer one came for this many of its stream's frame periods: a stream
# that goes silent without the edge's failure notice (a dead link, a stalled relay) must not leave its last picture
# reading as live. Never sooner than MARKERS_SHOWN_S: the markers come from the same camera frames, and one dropped
# frame of a fast stream (video travels with congestion control DROP) must not blink the picture off.
PICTURE_STALE_FRAMES = 3


def picture_stale_after(period: float) -> float:
    """s without a new picture after which a stream whose frames come every ``period`` s (0: not known yet) is shown
    as not live: three of its periods, never less than MARKERS_SHOWN_S."""
    return max(PICTURE_STALE_FRAMES * period, MARKERS_SHOWN_S)


def sparkline(values: Sequence[float], width: int = 30, top: float | None = None) -> str:
    """The last ``width`` values as block characters scaled to ``top`` (default: their maximum)."""
    vals = [v for v in list(values)[-width:] if math.isfinite(v)]
    if not vals:
        return ""
    hi = top if top and top > 0 else max(max(vals), 1e-9)
    return "".join(_SPARK[min(len(_SPARK) - 1, max(0, int(v / hi * (len(_SPARK) - 1) + 0.5)))] for v in vals)


def fmt_ms(v: float) -> str:
    return "—" if math.isnan(v) else f"{v:.1f} ms"


def fmt_pct(v: float) -> str:
    return "—" if math.isnan(v) else f"{100 * v:.1f} %"


@dataclass(frozen=True)
class LinkRow:
    label: str
    text: str
    colour: str


def link_rows(q: LinkQuality, t: LinkThresholds) -> list[LinkRow]:
    g = q.grades(t)
    rtt = f"{fmt_ms(q.rtt_p50_ms)} / {fmt_ms(q.rtt_p95_ms)}"
    jit = fmt_ms(q.jitter_ms)
    if q.rtt_old_s:  # a dead link: what was measured before it died, said to be that old
        rtt, jit = f"no echo for {q.rtt_old_s:.1f} s (was {rtt})", f"{jit} (old)"
    down = fmt_pct(q.downlink_loss) + (f" (no state for {q.no_state_s:.1f} s)" if q.no_state_s else "")
    return [
        LinkRow("RTT p50/p95", rtt, GRADE_COLOURS[g["rtt"]]),
        LinkRow("jitter", jit, GRADE_COLOURS[g["jitter"]]),
        LinkRow(
            "loss up/down",
            f"{fmt_pct(q.uplink_loss)} / {down}",
            GRADE_COLOURS[max(g["uplink_loss"], g["downlink_loss"], key=_rank)],
        ),
    ]


def _rank(grade: str) -> int:
    return {"none": 0, "good": 1, "warn": 2, "bad": 3}[grade]


def next_profile(current: str, profiles: Sequence[str]) -> str:
    """The profile after ``current`` in the configured cycle (the first one if current is not listed)."""
    if current in profiles:
        return profiles[(list(profiles).index(current) + 1) % len(profiles)]
    return profiles[0]


def inert(value: Any) -> Any:
    """A view (a dataclass of what the screen shows) with every string in it ``printable``, through lists,
    tuples and nested views."""
    if isinstance(value, str):
        return printable(value)
    if isinstance(value, list | tuple):
        return type(value)(inert(v) for v in value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.replace(value, **{f.name: inert(getattr(value, f.name))
                                            for f in dataclasses.fields(value) if f.init})
    return value
