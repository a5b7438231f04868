"""Analysis of benchmark outputs (no processes): blackout trials, ping records, report targets."""

from __future__ import annotations

import math

from iorthand_operator.bench import report
from iorthand_operator.bench.linkemu import LinkProfile
from iorthand_operator.bench.transports import analyse_ping, merge_ping_rounds
from iorthand_operator.bench.wan import PROFILES, blackout_trials, netem_args, summarize_trials, video_figures

MS = 1_000_000


def _states(stop_at_ms: float, last_recv_ms: float, b1_ms: float, end_ms: float) -> list[list[object]]:
    """States every 8 ms: moving until ``stop_at_ms``, stopped until b1 + 40 ms, then moving again."""
    out = []
    t = 0.0
    while t <= end_ms:
        moving = t < stop_at_ms or t > b1_ms + 40
        recv = min(t, last_recv_ms) if t < b1_ms else t
        out.append([int(t * MS), 1, int(recv * MS), moving, int(t * MS)])
        t += 8
    return out


def test_blackout_trial_within_limit() -> None:
    states = _states(stop_at_ms=1150 + 152, last_recv_ms=1150, b1_ms=2500, end_ms=4000)
    records = [[1, int(1000 * MS), 0, 0, int(2510 * MS), True, "ok"],  # sent before the blackout: ignored
               [2, int(2550 * MS), 0, 0, int(2600 * MS), True, "ok"]]
    (trial,) = blackout_trials(states, records, [(1160 * MS, 2495 * MS, 2500 * MS)])
    assert trial["ok"] and trial["stayed_stopped"]
    assert 150 <= trial["stop_after_last_command_ms"] <= 158
    assert trial["operator_echo_after_ms"] == 105  # from the restore request (2495 ms)
    assert trial["motion_resumed_after_ms"] is not None
    summary = summarize_trials([trial])
    assert summary["passed"] == 1 and summary["limit_ms"] == 158


def test_motion_while_the_restore_command_returns_is_not_motion_during_the_blackout() -> None:
    states = _states(stop_at_ms=1150 + 152, last_recv_ms=1150, b1_ms=2480, end_ms=3000)  # moving from 2520 ms
    (trial,) = blackout_trials(states, [], [(1160 * MS, 2490 * MS, 2530 * MS)])
    assert trial["ok"] and trial["stayed_stopped"]


def test_blackout_trial_too_slow_fails() -> None:
    states = _states(stop_at_ms=1150 + 250, last_recv_ms=1150, b1_ms=2500, end_ms=3000)
    (trial,) = blackout_trials(states, [], [(1160 * MS, 2495 * MS, 2500 * MS)])
    assert not trial["ok"] and trial["stop_after_last_command_ms"] > 158


def test_blackout_trial_robot_not_moving_is_not_a_pass() -> None:
    states = [[int(t * MS), 1, 0, False, 0] for t in range(0, 3000, 8)]
    (trial,) = blackout_trials(states, [], [(1000 * MS, 1995 * MS, 2000 * MS)])
    assert not trial["ok"]


def test_netem_arguments_of_known_links() -> None:
    # 4G: the relay's uniform 40 ± 15 ms, its 1 % stalls as 1 % packet loss, paced at the profile's rate.
    assert netem_args(PROFILES["4g"].link, PROFILES["4g"].rate) == [
        "netem", "limit", "10000", "delay", "40ms", "15ms", "loss", "random", "1%", "rate", "20mbit"]
    # No jitter, no loss, no rate: still paced (at a rate that limits nothing), so packets keep their order.
    assert netem_args(LinkProfile(0.5)) == ["netem", "limit", "10000", "delay", "0.5ms", "rate", "10gbit"]
    assert netem_args(LinkProfile(150.0, 80.0, 0.025, 300.0), "2mbit")[5:] == [
        "80ms", "loss", "random", "2.5%", "rate", "2mbit"]


def test_analyse_ping_records() -> None:
    data = {"status": "ok", "sent": [1, 2, 3, 4],
            "records": [[1, 0, 1 * MS, 1 * MS, 2 * MS], [3, 10 * MS, 11 * MS, 11 * MS, 13 * MS], [2, 5 * MS, 6 * MS, 6 * MS, 7 * MS]]}
    r = analyse_ping(data)
    assert r["sequence"]["lost"] == 1 and r["sequence"]["reordered"] == 1
    assert r["rtt_ms"]["max"] == 3.0 and r["rtt_ms"]["min"] == 2.0


def test_interleaved_rounds_merge_without_false_duplicates() -> None:
    """Every round numbers its pings from the same start: merged, they stay distinct, and a ping lost in one
    round is one lost ping, not hidden by the other round's ping of the same number."""
    round1 = {"status": "ok", "sent": [7, 8], "records": [[7, 0, 1 * MS, 1 * MS, 2 * MS], [8, 5 * MS, 6 * MS, 6 * MS, 7 * MS]]}
    round2 = {"status": "ok", "sent": [7, 8], "records": [[8, 100 * MS, 101 * MS, 101 * MS, 104 * MS]]}
    merged = merge_ping_rounds([round1, round2])
    r = analyse_ping(merged)
    assert r["sequence"]["sent"] == 4 and r["sequence"]["lost"] == 1
    assert r["sequence"]["duplicates"] == 0 and r["sequence"]["reordered"] == 0
    assert sorted(r["samples_ms"]) == [2.0, 2.0, 4.0]
    assert merge_ping_rounds([round1, {"status": "no echo during warm-up", "sent": [], "records": []}])["status"] != "ok"


def test_targets_and_ratios() -> None:
    def case(t: str, size: int, p50: float, p99: float) -> dict[str, object]:
        return {"transport": t, "size": size, "rtt_ms": {"p50": p50, "p99": p99}}

    cases = {"zenoh-router/small": case("zenoh-router", 64, 0.4, 1.0), "mqtt/small": case("mqtt", 64, 0.8, 4.0)}
    ratios = report.transport_ratios(cases)
    assert ratios == {"zenoh-router/small": {"p50": 0.5, "p99": 0.25}}
    checks = report.targets({"transports": {"cases": cases, "ratios": ratios}})
    assert checks[0]["ok"]
    assert "p50 ms" in report.table(report.LATENCY_HEADERS[:3], [["x", 1, 0.5]])


def test_idle_penalty_reports_both_costs_and_their_ratio() -> None:
    p = report.idle_penalty(samples=5, gap_s=0.002)
    assert p["decode_hot_us"] > 0 and p["decode_after_idle_us"] > 0 and p["idle_gap_ms"] == 2.0
    assert abs(p["factor"] - p["decode_after_idle_us"] / p["decode_hot_us"]) <= 0.05 * p["factor"] + 0.1


def test_cpu_share_from_known_cpu_times() -> None:
    """10 s of two CPUs: 4 s busy (user, system, softirq), 15 s idle or waiting, 1 s stolen by the hypervisor."""
    before = {"user": 100.0, "system": 50.0, "idle": 500.0, "iowait": 5.0, "softirq": 1.0, "steal": 2.0}
    after = {"user": 102.5, "system": 51.0, "idle": 514.0, "iowait": 6.0, "softirq": 1.5, "steal": 3.0}
    assert report.cpu_share(report.cpu_spent(before, after)) == {"cpu_seconds": 20.0, "busy_percent": 20.0, "steal_percent": 5.0}
    nothing = report.cpu_share(report.cpu_spent(after, after))
    assert nothing["cpu_seconds"] == 0.0 and math.isnan(nothing["steal_percent"])
    now = report.cpu_times()
    assert "steal" in now and "guest" not in now  # guest time is already in user: not counted twice
    rows = report.latency_rows({"c": {"rtt_ms": dict.fromkeys(("count", "p50", "p90", "p99", "p99.9", "max", "jitter"), 1.0),
                                      "host_cpu": {"steal_percent": 5.0}}})
    assert rows[0][report.LATENCY_HEADERS.index("stolen %")] == 5.0


def test_a_result_names_the_commit_of_the_code_that_produced_it() -> None:
    import subprocess

    from tests.conftest import ROOT

    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    if head.returncode:
        assert report.source_tree() == ""  # not a checkout: nothing to name
        return
    dirty = subprocess.run(["git", "-C", str(ROOT), "diff", "--quiet", "HEAD", "--"]).returncode
    assert report.source_tree() == head.stdout.strip() + ("+changes" if dirty else "")


def test_video_figures_count_what_a_viewer_got_after_the_warm_up() -> None:
    """Frames as the video probe writes them (seq, capture ns, arrival ns, bytes, keyframe, decoded): 30 fps for
    12 s on a 40 ms link, 60 ms from capture to arrival, except 4 frames that a stall held 240 ms more, one frame
    missing by sequence and one that did not decode. The first 2 s are the warm-up."""
    period = 1e9 / 30
    frames = []
    for i in range(360):
        if i == 200:
            continue  # lost on the way
        arrival = int(1e9 + i * period)
        late = 300e6 if i in (100, 101, 102, 103) else 60e6
        frames.append([i + 1, int(arrival - late), arrival, 6000, i % 30 == 0, i != 150])
    v = video_figures(frames, link_delay_ms=40.0, codec="h264")
    kept = [f for f in frames if f[2] >= frames[0][2] + 2e9]
    assert v["frames"] == len(kept) == 299
    assert v["decoded"] == 298
    assert v["lost_by_sequence"] == 1
    assert 29.0 < v["fps_delivered"] < 30.5
    assert v["delay_ms"]["p50"] == 60.0
    assert v["share_over_target"] == round(4 / 298, 4)  # 260 ms over the link's 40: over the 200 ms target
    assert v["delay_over_link_p99_ms"] > 200.0  # 4 of 298 is more than 1 %: the p99 is a stalled frame
    span_s = (kept[-1][2] - (frames[0][2] + 2e9)) / 1e9
    assert v["bitrate_kbit_s"] == round(8 * 6000 * 299 / span_s / 1e3, 1)  # ≈ 1.44 Mbit/s
