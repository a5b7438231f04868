"""``iorthand report SESSION``: the session report (Markdown + JSON + PNG plots) in ``SESSION/report/``.

Reads the session's messages (validated by their protocol classes; malformed ones are counted, not used),
extracts per-robot series, and hands them to :mod:`metrics` for the figures. Times are the messages' source
times (``t``): they measure what happened at the robot, not when the recorder heard of it. A message whose source
time strays from its receipt by more than :data:`TIME_OUTLIER_S` beyond the robot's usual clock offset is counted,
not used (one forged command stamped 2^62 ns made a 3 s session last 89 years). Keys whose robot id is invalid are
counted too (``foreign_keys``): their ids would become headings and file names.

Every text from the wire (operator, robots' refusal reasons, annotations, keys) is written into the Markdown as
text (:func:`md_text`): no markup, HTML or control character of theirs reaches the report.
"""

from __future__ import annotations

import json
import math
import re
import statistics
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from iorthand import keys, stats
from iorthand.protocol import (
    Annotation,
    AppliedCommand,
    DecodeError,
    ForceLevelState,
    ForceSample,
    RobotState,
    SafetyStatus,
    Status,
    TwistCommand,
    printable,
)
from iorthand_cloud.recorder import metrics
from iorthand_cloud.recorder.config import ReportConfig
from iorthand_cloud.recorder.manifest import Manifest, totals
from iorthand_cloud.recorder.reader import iter_records, session_dir
from iorthand_cloud.recorder.repair import repair_if_crashed

DEADMAN_STATES = {Status.COMMAND_TIMEOUT, Status.NO_DEADMAN}
TIME_OUTLIER_S = 10.0  # s a source time may stray from its receipt beyond the robot's median clock offset


@dataclass
class RobotSeries:
    force: list[tuple[float, float]] = field(default_factory=list)  # (t s, value N)
    levels: list[tuple[float, int, bool]] = field(default_factory=list)
    commands: list[tuple[float, bool]] = field(default_factory=list)  # (t, deadman)
    latency_ms: list[float] = field(default_factory=list)  # operator send → edge receive (two clocks)
    # Edge receive − the edge's stamp of the state the operator saw (TwistCommand.view_t): both on the edge's clock,
    # the whole loop (state out, the operator's screen, command back), whatever the clocks' skew.
    view_age_ms: list[float] = field(default_factory=list)
    view_t: dict[tuple[str, int], int] = field(default_factory=dict)  # (operator, seq) → view_t: see settle
    echo_recv: dict[tuple[str, int], int] = field(default_factory=dict)  # (operator, command seq) → edge receive
    refusals: Counter[str] = field(default_factory=Counter)
    applied: int = 0
    safety: list[tuple[float, str]] = field(default_factory=list)
    pose: list[tuple[float, list[float]]] = field(default_factory=list)
    malformed: int = 0
    implausible_time: int = 0  # messages whose source time strays from their receipt (TIME_OUTLIER_S)
    # (series, entry, source − receive time in ns, whose clock) until the clocks' offsets are known: see settle
    timed: list[tuple[list[Any], tuple[Any, ...], int, str]] = field(default_factory=list)
    usual_offset: dict[int, int] = field(default_factory=dict)  # id(series) → its clock's source − receive, ns

    def clock_shift(self, series: list[Any], to: list[Any]) -> float:
        """Seconds to subtract from a time of ``series`` to put it on the clock of ``to`` (through the
        recorder's receive times, which both share)."""
        return (self.usual_offset.get(id(series), 0) - self.usual_offset.get(id(to), 0)) / 1e9

    def add(self, series: list[Any], entry: tuple[Any, ...], t_ns: int, recv_ns: int, clock: str = "") -> None:
        """``entry`` (its time first, in s) into ``series`` at :meth:`settle`; ``clock`` names whose clock stamped
        it where a series mixes clocks (each operator's commands: one laptop may be a minute off another's)."""
        self.timed.append((series, entry, t_ns - recv_ns, clock))

    def settle(self) -> None:
        """Each message into its series, unless its source time strays from the robot's usual offset; each
        command's picture age from its echo (a command and its echo arrive at the recorder in either order)."""
        for key, view_t in self.view_t.items():
            recv_t = self.echo_recv.get(key, 0)
            if recv_t >= view_t:
                self.view_age_ms.append((recv_t - view_t) / 1e6)
        self.view_t, self.echo_recv = {}, {}
        # One usual offset per clock of each series: commands carry their operator's clock, the rest the edge's,
        # and any two may be far apart (an operator's laptop without NTP) without any message being implausible.
        offsets: dict[tuple[int, str], list[int]] = {}
        for series, _, offset, clock in self.timed:
            offsets.setdefault((id(series), clock), []).append(offset)
        usual = {k: statistics.median_low(v) for k, v in offsets.items()}
        # A series with several clocks is put on the one that stamped most of it (the others shifted onto it).
        for (sid, clock), _values in sorted(offsets.items(), key=lambda e: (len(e[1]), e[0][1]), reverse=True):
            self.usual_offset.setdefault(sid, usual[(sid, clock)])
        for series, entry, offset, clock in self.timed:
            own = usual[(id(series), clock)]
            if abs(offset - own) > TIME_OUTLIER_S * 1e9:
                self.implausible_time += 1
                continue
            shift = (own - self.usual_offset[id(series)]) / 1e9
            series.append((entry[0] - shift, *entry[1:]) if shift else entry)
        self.timed = []
        for series in (self.force, self.levels, self.commands, self.safety, self.pose):
            series.sort(key=lambda x: x[0])  # merge order is by receive time; the maths wants source-time order


def _load(folder: Path, cfg: ReportConfig) -> tuple[dict[str, RobotSeries], list[dict[str, Any]], int]:
    """The robots' series, the annotations, and how many messages were on keys with an invalid robot id."""
    robots: dict[str, RobotSeries] = {}
    annotations: list[dict[str, Any]] = []
    foreign = 0
    ann_key = keys.service_key(keys.RECORDER, keys.RECORDER_ANNOTATIONS)
    for rec in iter_records(folder):
        if rec.key == ann_key:
            try:
                a = Annotation.decode(rec.data)
                annotations.append({"t": a.t / 1e9, "author": a.author, "text": a.text, "tags": a.tags,
                                    "score": a.score})
            except DecodeError:
                pass
            continue
        try:
            robot, suffix = keys.split_key(rec.key)
        except keys.KeyExprError:
            continue
        raw_suffix, suffix = suffix, keys.channel_suffix(suffix)  # an operator's own command key is its channel's
        if not keys.is_robot_id(robot):
            foreign += 1
            continue
        s = robots.setdefault(robot, RobotSeries())
        if rec.malformed:
            s.malformed += 1
            continue
        try:
            if suffix == keys.STATE_FORCE:
                m = ForceSample.decode(rec.data)
                s.add(s.force, (m.t / 1e9, metrics.force_value(m.force, cfg.force_quantity)), m.t, rec.log_time)
            elif suffix == keys.STATE_FORCE_LEVEL:
                lv = ForceLevelState.decode(rec.data)
                s.add(s.levels, (lv.t / 1e9, lv.level, lv.stale), lv.t, rec.log_time)
            elif suffix == keys.CMD_TWIST:
                c = TwistCommand.decode(rec.data)
                # Each operator's clock apart: the key (bound to its certificate, bind_operator_keys) and the name.
                s.add(s.commands, (c.t / 1e9, c.deadman), c.t, rec.log_time, f"{raw_suffix} {c.operator}")
                if c.view_t:
                    s.view_t[(c.operator, c.seq)] = c.view_t
            elif suffix == keys.STATE_APPLIED:
                ap = AppliedCommand.decode(rec.data)
                s.applied += 1
                if ap.recv_t and ap.cmd_t:
                    s.latency_ms.append((ap.recv_t - ap.cmd_t) / 1e6)
                if ap.recv_t:
                    s.echo_recv[(ap.operator, ap.cmd_seq)] = ap.recv_t
                if not ap.accepted:
                    s.refusals[ap.status] += 1
            elif suffix == keys.STATE_SAFETY:
                sf = SafetyStatus.decode(rec.data)
                s.add(s.safety, (sf.t / 1e9, sf.status), sf.t, rec.log_time)
            elif suffix == keys.STATE_ROBOT:
                rs = RobotState.decode(rec.data)
                s.add(s.pose, (rs.t / 1e9, rs.tcp_pose), rs.t, rec.log_time)
        except DecodeError:
            s.malformed += 1
    for s in robots.values():
        s.settle()
    return robots, annotations, foreign


def robot_figures(s: RobotSeries, cfg: ReportConfig, session_span: float) -> dict[str, Any]:
    levels = s.levels or [(t, lv, False) for t, lv in
                          metrics.levels_from_force(s.force, cfg.caution, cfg.danger, cfg.hysteresis)]
    red, yellow, edges = metrics.warning_edges(levels)
    tau = metrics.contact_time(s.force, cfg.contact_threshold, cfg.max_sample_gap)
    if cfg.teleop_time == "commands" and s.commands:
        # τ and the warnings within teleoperation only (ψ = τ/t_t), the window put on each series' clock.
        window = metrics.teleoperation_window(s.commands) or (math.inf, -math.inf)  # (none: nothing inside)
        t_t = max(0.0, window[1] - window[0])
        shift = s.clock_shift(s.commands, s.force)
        tau = metrics.contact_time(metrics.within(s.force, (window[0] - shift, window[1] - shift)),
                                   cfg.contact_threshold, cfg.max_sample_gap)
        shift = s.clock_shift(s.commands, s.levels) if s.levels else shift
        edges = metrics.within(edges, (window[0] - shift, window[1] - shift))
        red, yellow = sum(lv == 2 for _, lv in edges), sum(lv == 1 for _, lv in edges)
        t_t_source, within = "commands: first to last with the deadman held", "teleoperation"
    elif cfg.teleop_time == "commands":
        t_t, t_t_source, within = session_span, "session span: no commands were recorded", "session"
    else:
        t_t, t_t_source, within = session_span, "session span (teleop_time = session)", "session"
    # (The last force sample holds for one sample period, which may reach past the end of t_t.)
    index = metrics.PerformanceIndex(t_t, min(tau, t_t), red, yellow, cfg.alpha, cfg.beta)
    stops = metrics.rising_edges(s.safety, DEADMAN_STATES)
    return {
        "index": index.as_dict(),
        "levels_source": keys.STATE_FORCE_LEVEL if s.levels else f"{keys.STATE_FORCE} thresholds",
        "t_t_source": t_t_source,
        "figures_within": within,  # τ and the warnings: "teleoperation" (the t_t window) or the whole "session"
        "warning_edges": [{"t": t, "level": lv} for t, lv in edges],
        "command_latency_ms": _summary(s.latency_ms),
        "view_age_ms": _summary(s.view_age_ms),
        "commands": len(s.commands),
        "applied": s.applied,
        "refusals": dict(s.refusals),
        "refusals_total": sum(s.refusals.values()),
        "deadman_stops": len(stops),
        "force_samples": len(s.force),
        "malformed": s.malformed,
        "implausible_time": s.implausible_time,
    }


def _summary(values: list[float]) -> dict[str, Any]:
    return {k: v if k == "count" else _num(v) for k, v in stats.summary(values).items()}


def _num(v: float) -> float | None:
    return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else round(float(v), 4)


def _plots(robot: str, s: RobotSeries, cfg: ReportConfig, out: Path, t0: float) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files: list[str] = []
    if s.force:
        fig, ax = plt.subplots(figsize=(10, 3.5))
        ax.plot([t - t0 for t, _ in s.force], [v for _, v in s.force], lw=0.8, label=f"force ({cfg.force_quantity})")
        for y, colour, name in ((cfg.contact_threshold, "grey", "contact"), (cfg.caution, "gold", "caution"),
                                (cfg.danger, "red", "danger")):
            ax.axhline(y, color=colour, ls="--", lw=0.8, label=name)
        ax.set_xlabel("time since session start (s)")
        ax.set_ylabel("N")
        ax.set_title(f"{robot}: contact force")
        ax.legend(loc="upper right", fontsize=8)
        fig.tight_layout()
        name = f"force_{robot}.png"
        fig.savefig(out / name, dpi=100)
        plt.close(fig)
        files.append(name)
    if s.pose:
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
        xs = [1000 * p[0] for _, p in s.pose]
        ys = [1000 * p[1] for _, p in s.pose]
        ax1.plot(xs, ys, lw=0.8)
        ax1.set_aspect("equal", adjustable="datalim")
        ax1.set_xlabel("x (mm, base)")
        ax1.set_ylabel("y (mm, base)")
        ax1.set_title(f"{robot}: tool path")
        ts = [t - t0 for t, _ in s.pose]
        for i, axis in enumerate("xyz"):
            ax2.plot(ts, [1000 * p[i] for _, p in s.pose], lw=0.8, label=axis)
        ax2.set_xlabel("time since session start (s)")
        ax2.set_ylabel("mm")
        ax2.legend(fontsize=8)
        fig.tight_layout()
        name = f"trajectory_{robot}.png"
        fig.savefig(out / name, dpi=100)
        plt.close(fig)
        files.append(name)
    return files


def build_report(session: str | Path, cfg: ReportConfig | None = None, out_dir: Path | None = None) -> dict[str, Any]:
    """Compute the report of a session, write ``report.md``, ``report.json`` and the plots; return the data."""
    cfg = cfg or ReportConfig()
    folder = session_dir(session)
    repaired = repair_if_crashed(folder)  # a session whose recorder died is repaired by its first reader
    manifest = Manifest.read(folder)
    out = out_dir or folder / "report"
    out.mkdir(parents=True, exist_ok=True)
    robots, annotations, foreign = _load(folder, cfg)
    start = manifest.start_t / 1e9
    stop = (manifest.stop_t or manifest.start_t) / 1e9
    data: dict[str, Any] = {
        "session": manifest.session_id, "status": manifest.status, "operator": manifest.operator,
        "start": manifest.start_iso, "stop": manifest.stop_iso, "duration_s": round(stop - start, 3),
        "recording": {**totals(manifest.keys), "dropped": manifest.dropped, "repaired": manifest.repaired,
                      "error": manifest.error, "repair": repaired, "foreign_keys": foreign,
                      "missing_by_key": {k: st.missing for k, st in sorted(manifest.keys.items()) if st.missing}},
        "config": {k: getattr(cfg, k) for k in cfg.__dataclass_fields__},
        "robots": {}, "annotations": annotations, "plots": [],
    }
    data["recording"]["missing_where"] = missing_where(data["recording"]["missing_by_key"])
    for robot, s in sorted(robots.items()):
        data["robots"][robot] = robot_figures(s, cfg, stop - start)
        if cfg.plots:
            data["plots"] += _plots(robot, s, cfg, out, start)
    (out / "report.json").write_text(json.dumps(_clean(data), indent=1, default=str, allow_nan=False))
    (out / "report.md").write_text(render_markdown(data))
    data["path"] = str(out / "report.md")
    return data


def _clean(v: Any) -> Any:
    """JSON has no NaN or infinity: those become null."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    return v


def _fmt(v: Any, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "n/a"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def missing_where(missing_by_key: dict[str, int], most: int = 3) -> str:
    """``"video/ultrasound 1, state/force 2"``: the keys (robot suffix) that lost messages, most first."""
    by_key = sorted(missing_by_key.items(), key=lambda kv: -kv[1])
    shown = ", ".join(f"{k.split('/', 2)[-1]} {n}" for k, n in by_key[:most])
    return shown + (f" and {len(by_key) - most} more keys" if len(by_key) > most else "")


# Markdown's inline markup, and the table's cell separator: escaped with a backslash in text from the wire.
_MARKUP = re.compile(r"([\\`*_\[\]|#!~])")


def md_text(value: Any, limit: int = 500) -> str:
    """``value`` as inert Markdown text on one line: control characters (newlines, terminal escapes) written
    out as escapes, HTML's ``& < >`` as entities, Markdown's markup escaped; at most ``limit`` characters."""
    text = str(value)
    if len(text) > limit:
        text = text[:limit] + "…"
    text = printable(text).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
    return _MARKUP.sub(r"\\\1", text)


def render_markdown(data: dict[str, Any]) -> str:
    rec = data["recording"]
    foreign = rec.get("foreign_keys", 0)
    lines = [
        f"# Session {md_text(data['session'])}",
        "",
        f"- status: **{md_text(data['status'])}**{' (repaired after a crash)' if rec['repaired'] else ''}"
        f"{' — ' + md_text(rec['error']) if rec['error'] else ''}",
        f"- operator: {md_text(data['operator']) if data['operator'] else 'n/a'}; {md_text(data['start'])} → "
        f"{md_text(data['stop'])} ({data['duration_s']:.1f} s)",
        f"- recorded: {rec['messages']} messages, {rec['bytes'] / 1e6:.1f} MB, {rec['malformed']} malformed, "
        f"{rec['missing']} missing by sequence ({rec['gaps']} gaps"
        f"{'; on ' + md_text(rec['missing_where']) if rec['missing_where'] else ''}), "
        f"{rec['dropped']} dropped by the recorder"
        f"{f', {foreign} on keys whose robot id is invalid (not used)' if foreign else ''}",
        "",
    ]
    for robot, r in data["robots"].items():
        ix = r["index"]
        lat, view = r["command_latency_ms"], r["view_age_ms"]
        lines += [
            f"## Robot {md_text(robot)}",
            "",
            "| figure | value |",
            "|---|---|",
            f"| teleoperation time t_t | {_fmt(ix['t_t'])} s |",
            f"| body-contact time τ (force > {data['config']['contact_threshold']} N) | {_fmt(ix['tau'])} s |",
            f"| contact ratio ψ = τ/t_t | {_fmt(ix['psi'], 4)} |",
            f"| danger warnings ω_R (rising edges into level 2) | {ix['omega_R']} |",
            f"| caution warnings ω_Y (rising edges into level 1) | {ix['omega_Y']} |",
            f"| Ω = 4·ω_R + ω_Y | {ix['Omega']} |",
            f"| **performance index φ = α·ψ − β·Ω/(1−ψ)** (α = {ix['alpha']}, β = {ix['beta']}) | "
            f"**{_fmt(ix['phi'])} %** |",
            f"| command latency (operator → edge; two clocks) p50 / p90 / p99 | {_fmt(lat['p50'])} / "
            f"{_fmt(lat['p90'])} / {_fmt(lat['p99'])} ms ({lat['count']} commands) |",
            f"| age of the operator's picture when the edge got the command (the edge's clock) p50 / p90 / p99 | "
            f"{_fmt(view['p50'])} / {_fmt(view['p90'])} / {_fmt(view['p99'])} ms ({view['count']} commands) |",
            f"| deadman stops | {r['deadman_stops']} |",
            f"| refusals | {r['refusals_total']} {md_text(r['refusals']) if r['refusals'] else ''} |",
            f"| malformed messages | {r['malformed']} |",
            f"| messages with a source time {TIME_OUTLIER_S:g} s off the robot's clock (not used) | "
            f"{r.get('implausible_time', 0)} |",
            "",
            f"t_t from the {md_text(r['t_t_source'])}; τ and the warnings counted within the "
            f"{'teleoperation window' if r['figures_within'] == 'teleoperation' else 'whole session'}. "
            f"Warning levels from {md_text(r['levels_source'])}.",
            "",
        ]
        for plot in data["plots"]:
            if plot.endswith(f"_{robot}.png"):
                lines.append(f"![{plot}]({plot})")
        lines.append("")
    if data["annotations"]:
        lines += ["## Annotations", "", "| time | author | text | tags | score |", "|---|---|---|---|---|"]
        for a in data["annotations"]:
            lines.append(f"| {a['t']:.3f} | {md_text(a['author'])} | {md_text(a['text'])} | "
                         f"{md_text(', '.join(a['tags']))} | {_fmt(a['score'])} |")
    return "\n".join(lines) + "\n"
