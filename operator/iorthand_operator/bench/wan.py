"""WAN emulation: operator, cloud and edge as three hosts on this machine, with profiles on their links.

As root, the tool creates three network namespaces (operator, cloud, edge) joined by two veth pairs with
addresses 10.201.1.0/24 (operator↔cloud) and 10.201.2.0/24 (cloud↔edge), only inside those namespaces:

    operator ns: OperatorClient probe ──► 10.201.1.1:17447 [relay, op-link profile] ─┐
    cloud ns:    cloud router 127.0.0.1:7447 ◄──────────────────────────────────────────┘◄─┐
    edge ns:     edge agent + state monitor ─► edge-site router ─► 10.201.2.1:17448 [relay, edge-link profile]

Delay and jitter come from one of two emulators (``--emulator``; ``auto`` takes netem where it can):

- ``netem``, where the kernel has it: a netem qdisc on each veth end delays, jitters, drops and paces the packets
  of that direction, and the clients dial the cloud router's veth addresses directly (no relays). A profile's
  stalls become packet loss, so TCP's own retransmissions make them, as on a real radio link.
- ``relay``: the project's TCP relay (``linkemu``, order preserving) in the cloud namespace, at the addresses
  above; bandwidth is limited with ``tc tbf`` on the veth. This machine's kernel has no netem, so it runs here.

Either way a blackout is an nftables drop rule in the edge namespace (nothing passes, both directions). The
edge-site router lets a monitor in the edge namespace watch the robot during a blackout (the deadman stop is
measured at the edge).

Without root (or without ``ip netns``) everything runs on 127.0.0.1 through relays, and the relay itself holds
all traffic during a blackout; the run says so. Everything created is removed on exit, failure or signal.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import shutil
import signal
import subprocess
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from iorthand.transport import free_port
from iorthand_operator.bench import stats
from iorthand_operator.bench.linkemu import LinkProfile
from iorthand_operator.bench.procs import Group, Unavailable, on_cleanup, python_argv
from iorthand_operator.bench.transports import ROLES, analyse_probe, ep, start_edge, start_router

log = logging.getLogger("iorthand.bench.wan")

COMMAND_TIMEOUT_S = 0.150  # the edge's default safety.command_timeout
CONTROL_PERIOD_S = 0.008  # the simulated robot's 125 Hz control period


@dataclass(frozen=True)
class WanProfile:
    name: str
    link: LinkProfile  # each direction of the affected link
    rate: str = ""  # tc tbf rate of the affected link ("" = unlimited)
    blackout: bool = False
    note: str = ""


PROFILES: dict[str, WanProfile] = {
    "lan": WanProfile("lan", LinkProfile(0.5, 0.2), note="wired LAN, 0.5 ± 0.2 ms one-way"),
    "5g": WanProfile("5g", LinkProfile(15.0, 5.0), "100mbit", note="15 ± 5 ms one-way, 100 Mbit/s"),
    "4g": WanProfile("4g", LinkProfile(40.0, 15.0, 0.01, 200.0), "20mbit",
                     note="40 ± 15 ms one-way, 1 % of chunks stall 200 ms (loss + retransmission), 20 Mbit/s"),
    "poor": WanProfile("poor", LinkProfile(150.0, 80.0, 0.02, 300.0), "2mbit",
                       note="150 ± 80 ms one-way, 2 % stall 300 ms, 2 Mbit/s"),
    # A field site's 4G uplink: what the edge's video must fit in (issue 24).
    "4g-5mbit": WanProfile("4g-5mbit", LinkProfile(40.0, 15.0, 0.01, 200.0), "5mbit",
                           note="4g's delay and stalls, the edge's link shaped to 5 Mbit/s"),
    "blackout": WanProfile("blackout", LinkProfile(0.5, 0.2), blackout=True,
                           note="LAN link with repeated blackouts: nothing passes for N s"),
}


EMULATORS = ("auto", "netem", "relay")
# What the edge streams during a profile (``--video``): nothing, or 640×480 at 30 fps of the camera's test pattern
# (with sensor noise) in one of its codecs. The probe in the operator's namespace watches it across the link.
# ``h264-datagrams``: the same H.264 stream, with the edge-site router's link to the cloud doubled by a UDP link
# (``iorthand router --datagrams``) through a datagram relay of the same profile: the video crosses the WAN as
# datagrams, everything else stays on TCP. The operator's side stays TCP (a client session has one link).
VIDEOS = ("none", "jpeg", "h264", "h264-datagrams")
DATAGRAMS_SUFFIX = "-datagrams"
VIDEO_CAMERA = {"source": "pattern", "width": 640, "height": 480, "fps": 30.0}
# netem sends a packet no earlier than the one queued before it only while it paces a rate; without one, jitter
# would reorder packets, which no wired or radio link does to a TCP stream. This rate limits nothing here.
NETEM_UNLIMITED_RATE = "10gbit"
NETEM_LIMIT_PACKETS = 10000  # netem's queue (default 1000) must hold a poor link's delay × bandwidth


def netem_args(link: LinkProfile, rate: str = "") -> list[str]:
    """The ``tc qdisc … root`` arguments of a netem qdisc for one direction of ``link``: the relay's uniform delay
    ± jitter, its stall probability as packet loss (the stall is then TCP's retransmission), at ``rate``."""
    args = ["netem", "limit", str(NETEM_LIMIT_PACKETS), "delay", f"{link.delay_ms:g}ms"]
    if link.jitter_ms:
        args.append(f"{link.jitter_ms:g}ms")
    if link.stall_prob:
        args += ["loss", "random", f"{link.stall_prob * 100:g}%"]
    return [*args, "rate", rate or NETEM_UNLIMITED_RATE]


def _run(argv: list[str], stdin: str | None = None, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(argv, input=stdin, text=True, capture_output=True, check=check, timeout=20)


class Namespaces:
    """Three namespaces and two veth links; removed by :meth:`destroy` (registered for exit and signals)."""

    def __init__(self, tag: str | None = None) -> None:
        tag = tag or str(os.getpid() % 100000)
        self.tag = tag
        self.op, self.cloud, self.edge = f"ioh{tag}-op", f"ioh{tag}-cloud", f"ioh{tag}-edge"
        # veth names: ≤ 15 characters; o = operator link, e = edge link; suffix = which end
        self.veth = {"op": f"i{tag}oo", "cloud_op": f"i{tag}oc", "cloud_edge": f"i{tag}ec", "edge": f"i{tag}ee"}
        self.created: list[str] = []
        self._unregister = None

    @staticmethod
    def available() -> tuple[bool, str]:
        if os.geteuid() != 0:
            return False, "not root: network namespaces need root"
        if shutil.which("ip") is None:
            return False, "the ip command (iproute2) is missing"
        probe = f"ioh-probe-{os.getpid()}"
        r = _run(["ip", "netns", "add", probe], check=False)
        if r.returncode != 0:
            return False, f"ip netns add failed: {r.stderr.strip()}"
        _run(["ip", "netns", "del", probe], check=False)
        if shutil.which("nft") is None:
            return False, "nftables is not installed (apt-get install -y nftables): blackouts need it"
        return True, "namespaces, veth, tbf and nftables"

    @staticmethod
    def netem_available() -> tuple[bool, str]:
        """Whether this kernel takes a netem qdisc (tried on the loopback of a throwaway namespace), and tc's
        words when it does not. Call only where :meth:`available` holds."""
        probe = f"ioh-netem-{os.getpid()}"
        _run(["ip", "netns", "add", probe])
        try:
            r = _run(["tc", "-n", probe, "qdisc", "add", "dev", "lo", "root", *netem_args(LinkProfile(1.0))],
                     check=False)
        finally:
            _run(["ip", "netns", "del", probe], check=False)
        if r.returncode == 0:
            return True, "netem qdiscs on the veth links"
        return False, f"this kernel has no netem qdisc (tc: {(r.stderr or r.stdout).strip()})"

    def create(self) -> Namespaces:
        self._unregister = on_cleanup(self.destroy)
        for ns in (self.op, self.cloud, self.edge):
            _run(["ip", "netns", "add", ns])
            self.created.append(ns)
            _run(["ip", "-n", ns, "link", "set", "lo", "up"])
        v = self.veth
        for a, ns_a, addr_a, b, ns_b, addr_b in (
            (v["op"], self.op, "10.201.1.2/24", v["cloud_op"], self.cloud, "10.201.1.1/24"),
            (v["edge"], self.edge, "10.201.2.2/24", v["cloud_edge"], self.cloud, "10.201.2.1/24"),
        ):
            _run(["ip", "link", "add", a, "netns", ns_a, "type", "veth", "peer", "name", b, "netns", ns_b])
            _run(["ip", "-n", ns_a, "addr", "add", addr_a, "dev", a])
            _run(["ip", "-n", ns_b, "addr", "add", addr_b, "dev", b])
            _run(["ip", "-n", ns_a, "link", "set", a, "up"])
            _run(["ip", "-n", ns_b, "link", "set", b, "up"])
        _run(["ip", "netns", "exec", self.edge, "nft", "-f", "-"], stdin=(
            "table inet iohbench {\n"
            " chain in { type filter hook input priority 0; policy accept; }\n"
            " chain out { type filter hook output priority 0; policy accept; }\n"
            "}\n"
        ))
        return self

    def blackout(self, on: bool) -> None:
        """Drop everything on the edge's link (both directions), or stop dropping."""
        dev = self.veth["edge"]
        rules = (f"add rule inet iohbench in iifname {dev} drop\nadd rule inet iohbench out oifname {dev} drop\n"
                 if on else "flush chain inet iohbench in\nflush chain inet iohbench out\n")
        _run(["ip", "netns", "exec", self.edge, "nft", "-f", "-"], stdin=rules)

    def shape(self, rate: str) -> None:
        """Limit the edge link to ``rate`` in both directions with tbf (or remove the limit)."""
        for ns, dev in ((self.edge, self.veth["edge"]), (self.cloud, self.veth["cloud_edge"])):
            _run(["tc", "-n", ns, "qdisc", "del", "dev", dev, "root"], check=False)
            if rate:
                _run(["tc", "-n", ns, "qdisc", "add", "dev", dev, "root", "tbf", "rate", rate, "burst", "64kb",
                      "latency", "100ms"])

    def emulate(self, op_link: LinkProfile, edge_link: LinkProfile, edge_rate: str) -> None:
        """netem on both ends of both links (each end shapes what it sends): ``op_link`` on the operator's link,
        ``edge_link`` at ``edge_rate`` on the edge's. Replaces what an earlier profile set."""
        v = self.veth
        for ns, dev, link, rate in ((self.op, v["op"], op_link, ""), (self.cloud, v["cloud_op"], op_link, ""),
                                    (self.edge, v["edge"], edge_link, edge_rate),
                                    (self.cloud, v["cloud_edge"], edge_link, edge_rate)):
            _run(["tc", "-n", ns, "qdisc", "replace", "dev", dev, "root", *netem_args(link, rate)])

    def destroy(self) -> None:
        if self._unregister:
            self._unregister()
            self._unregister = None
        for ns in reversed(self.created):
            _run(["ip", "netns", "del", ns], check=False)  # deleting a namespace deletes its veth ends
        self.created.clear()


def _relay_argv(listen: str, connect: str, prof: LinkProfile, seed: int, max_s: float, udp: bool = False) -> list[str]:
    return python_argv("iorthand_operator.bench.linkemu", "--listen", listen, "--connect", connect,
                       "--delay-ms", str(prof.delay_ms), "--jitter-ms", str(prof.jitter_ms),
                       "--stall-prob", str(prof.stall_prob), "--stall-ms", str(prof.stall_ms), "--seed", str(seed),
                       "--max-seconds", str(max_s), *(["--udp"] if udp else []))


@dataclass
class Plan:
    duration: float
    trials: int = 0
    blackout_s: float = 1.5
    settle_s: float = 1.5
    recover_s: float = 3.0
    long_blackouts: tuple[float, ...] = ()  # extra blackouts longer than the Zenoh lease (session is lost)
    long_recover_s: float = 10.0


def run_profile(workdir: Path, profile: WanProfile, plan: Plan, netns: Namespaces | None, links: str = "edge",
                robot: str = "wan", netem: bool = False, video: str = "none") -> dict[str, Any]:
    """One profile: ``netem`` (needs ``netns``) shapes the veth links in the kernel, else relays carry them.
    ``video``: what the edge streams meanwhile (:data:`VIDEOS`), watched by a probe on the operator's side."""
    if netem and netns is None:
        raise ValueError("netem emulation needs the network namespaces")
    if video not in VIDEOS:
        raise ValueError(f"unknown video {video!r} (known: {', '.join(VIDEOS)})")
    name = f"wan-{profile.name}" + (f"-{video}" if video != "none" else "")
    datagrams = video.endswith(DATAGRAMS_SUFFIX)
    codec = video.removesuffix(DATAGRAMS_SUFFIX)
    schedule = [plan.blackout_s] * plan.trials + list(plan.long_blackouts) if profile.blackout else []
    total = plan.duration if not profile.blackout else sum(
        plan.settle_s + b + (plan.recover_s if b < 2.0 else plan.long_recover_s) for b in schedule) + 1.0
    max_s = total + 300.0
    lan = PROFILES["lan"].link
    op_link = profile.link if links == "both" else lan
    out, mon_out = workdir / f"{name}-probe.json", workdir / f"{name}-monitor.json"
    blackouts: list[tuple[int, int, int]] = []  # (cut, restore requested, restore done), ns
    with Group(workdir / name) as g:
        edge_relays: list[Any] = []  # what a blackout on loopback signals
        if netns is None:
            ns_op = ns_cloud = ns_edge = None
            cloud_port, edge_port = free_port(), free_port()
            op_dial, edge_dial = f"127.0.0.1:{free_port()}", f"127.0.0.1:{free_port()}"
        else:
            ns_op, ns_cloud, ns_edge = netns.op, netns.cloud, netns.edge
            cloud_port = edge_port = 7447  # each namespace has its own loopback
            # netem: the operator and the edge-site router dial the cloud router across the shaped veths;
            # relay: they dial the relays in the cloud namespace.
            op_dial, edge_dial = (f"10.201.1.1:{cloud_port}", f"10.201.2.1:{cloud_port}") if netem else (
                "10.201.1.1:17447", "10.201.2.1:17448")
        if netem and netns is not None:  # (netem without namespaces was refused above)
            netns.emulate(op_link, profile.link, profile.rate)
            start_router(g, "router-cloud", cloud_port, netns=ns_cloud, host="0.0.0.0", datagrams=datagrams)
        else:
            if netns is not None:
                netns.shape(profile.rate)
            start_router(g, "router-cloud", cloud_port, netns=ns_cloud, datagrams=datagrams)
            g.start("relay-op", _relay_argv(op_dial, f"127.0.0.1:{cloud_port}", op_link, 11, max_s), netns=ns_cloud,
                    ready="linkemu ready")
            edge_relays.append(g.start("relay-edge", _relay_argv(edge_dial, f"127.0.0.1:{cloud_port}", profile.link, 12,
                                                              max_s), netns=ns_cloud, ready="linkemu ready"))
            if datagrams:  # the same address and port, over UDP: what the edge-site router's UDP link dials
                edge_relays.append(g.start("relay-edge-udp", _relay_argv(
                    edge_dial, f"127.0.0.1:{cloud_port}", profile.link, 13, max_s, udp=True), netns=ns_cloud,
                    ready="linkemu ready"))
        start_router(g, "router-edge", edge_port, [f"tcp/{edge_dial}"], netns=ns_edge, datagrams=datagrams)
        start_edge(g, robot, [ep(edge_port)], netns=ns_edge,
                   video=None if video == "none" else {"camera": {**VIDEO_CAMERA, "codec": codec}})
        video_out = workdir / f"{name}-video.json"
        if video != "none":
            g.start("video", python_argv(ROLES, "video-probe", "--connect", f"tcp/{op_dial}", "--robot", robot,
                                         "--duration", str(total), "--out", str(video_out), "--max-seconds", str(max_s)),
                    netns=ns_op, ready="video-probe ready", timeout=120.0)
        g.start("monitor", python_argv(ROLES, "state-monitor", "--connect", ep(edge_port), "--robot", robot,
                                       "--duration", str(total + 60), "--out", str(mon_out), "--max-seconds", str(max_s)),
                netns=ns_edge, ready="monitor ready")
        probe = g.start("operator", python_argv(ROLES, "operator-probe", "--connect", f"tcp/{op_dial}", "--robots", robot,
                                                "--duration", str(total), "--out", str(out), "--max-seconds", str(max_s)),
                        netns=ns_op, ready="probe ready", timeout=120.0)
        if profile.blackout:
            for length in schedule:
                time.sleep(plan.settle_s)
                _blackout(netns, edge_relays, True)
                b0 = time.time_ns()
                time.sleep(length)
                b_end_req = time.time_ns()
                _blackout(netns, edge_relays, False)
                blackouts.append((b0, b_end_req, max(b_end_req, time.time_ns())))
                # A blackout longer than the 2 s lease ends the Zenoh sessions: give them time to come back.
                time.sleep(plan.recover_s if length < 2.0 else plan.long_recover_s)
        probe.wait(total + 120.0)
        g.children[[c.name for c in g.children].index("monitor")].signal(signal.SIGTERM)
        deadline = time.monotonic() + 20
        while not mon_out.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
    if not out.exists():
        raise RuntimeError(f"{name}: the operator probe wrote nothing; see {workdir / name}/operator.log")
    probe_data = json.loads(out.read_text())
    rd = probe_data["robots"][robot]
    result = analyse_probe(rd)
    states = json.loads(mon_out.read_text())["states"] if mon_out.exists() else []
    result.update(profile=profile.name, note=profile.note, link=asdict(profile.link), rate=profile.rate,
                  links=links, emulator="netem" if netem else "relay", events=probe_data.get("events", []))
    result["deadman_stops_while_driving"] = _spurious_stops(states, blackouts)
    if video != "none":
        deadline = time.monotonic() + 20
        while not video_out.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        frames = json.loads(video_out.read_text())["frames"] if video_out.exists() else []
        result["video"] = video_figures(frames, profile.link.delay_ms, codec)
        result["video"]["link"] = "TCP and UDP datagrams" if datagrams else "TCP"
    if profile.blackout:
        result["trials"] = blackout_trials(states, rd["records"], blackouts)
        result["blackout_s"] = plan.blackout_s
        result["blackout_times_ns"] = blackouts
    return result


# Issue 24: a frame's delay over the link's own one-way delay, at p99, on a 4G uplink.
FRAME_DELAY_OVER_LINK_TARGET_MS = 200.0


def video_figures(frames: list[list[Any]], link_delay_ms: float, codec: str, warmup_s: float = 2.0) -> dict[str, Any]:
    """What a viewer got (frames as the video probe writes them: seq, capture ns, arrival ns, bytes, keyframe,
    decoded), after ``warmup_s`` (the encoder's first keyframe, the bitrate finding the link): frames per second
    delivered and decodable, delay from capture to arrival, and over the link's own one-way delay, bitrate. And the
    share of frames over FRAME_DELAY_OVER_LINK_TARGET_MS: the p99 meets it only while that share stays under 1 %,
    and with the 4G profiles' 200 ms stalls, every frame that a stall holds back is over it."""
    if not frames:
        return {"codec": codec, "frames": 0, "fps_delivered": 0.0}
    t0 = frames[0][2] + warmup_s * 1e9
    kept = [f for f in frames if f[2] >= t0]
    span = max(1e-9, (kept[-1][2] - t0) / 1e9) if kept else 1e-9
    decoded = [f for f in kept if f[5]]
    delays = [(f[2] - f[1]) / 1e6 for f in decoded]
    summary = stats.latency_summary(delays)
    return {
        "codec": codec, "frames": len(kept), "decoded": len(decoded),
        "fps_delivered": round(len(decoded) / span, 2),
        "delay_ms": summary,
        "delay_over_link_p99_ms": round(summary["p99"] - link_delay_ms, 2) if delays else None,
        "share_over_target": round(sum(d - link_delay_ms > FRAME_DELAY_OVER_LINK_TARGET_MS for d in delays)
                                   / len(delays), 4) if delays else None,
        "bitrate_kbit_s": round(8 * sum(f[3] for f in kept) / span / 1e3, 1),
        "keyframes": sum(1 for f in kept if f[4]),
        "lost_by_sequence": sum(b[0] - a[0] - 1 for a, b in itertools.pairwise(kept) if b[0] > a[0] + 1),
    }


def _blackout(netns: Namespaces | None, relays: list[Any], on: bool) -> None:
    if netns is not None:
        netns.blackout(on)
    else:
        for relay in relays:
            relay.signal(signal.SIGUSR1 if on else signal.SIGUSR2)


def _spurious_stops(states: list[list[Any]], blackouts: list[tuple[int, int, int]]) -> int:
    """Moving → stopped transitions at the edge outside blackouts: deadman timeouts the operator felt."""
    states = sorted(states, key=lambda s: s[0])
    last_moving = max((s[0] for s in states if s[3]), default=0)
    n = 0
    for prev, cur in itertools.pairwise(states):
        # The operator's final release is not a stop it suffered: count only stops the robot came back from.
        if prev[3] and not cur[3] and cur[0] < last_moving and not any(b[0] <= cur[0] <= b[2] + 1e9 for b in blackouts):
            n += 1
    return n


def blackout_trials(states: list[list[Any]], records: list[list[Any]], blackouts: list[tuple[int, int, int]],
                    limit_s: float = COMMAND_TIMEOUT_S + CONTROL_PERIOD_S) -> list[dict[str, Any]]:
    """Per blackout (cut, restore requested, restore done; ns): the edge's stop time after the last command it received (state t − cmd_recv_t of the
    first state with a zero commanded twist), whether it stayed stopped, and when motion and the operator's
    echoes came back after the link did. States are (t, cmd_seq, cmd_recv_t, moving, arrival)."""
    states = sorted(states, key=lambda s: s[0])
    trials = []
    for i, (b0, b_req, b1) in enumerate(blackouts):
        before = [s for s in states if s[0] < b0]
        moving_before = bool(before) and bool(before[-1][3])
        stop = next((s for s in states if s[0] >= b0 and not s[3]), None)
        trial: dict[str, Any] = {"trial": i + 1, "moving_before": moving_before, "blackout_ms": (b1 - b0) / 1e6}
        if stop is None or not moving_before:
            trial.update(ok=False, reason="robot was not moving before the blackout" if not moving_before else "no stop seen")
            trials.append(trial)
            continue
        stop_ms = (stop[0] - stop[2]) / 1e6
        # Until the restore was *requested*: the link is back while the nft command is still returning.
        moved_during = any(s[3] for s in states if stop[0] < s[0] < b_req)
        # Recovery is timed from the restore request (the rule is gone at some instant before b1): an upper bound.
        resume = next((s for s in states if s[0] > b_req and s[3]), None)
        # The first command *sent after* the link returned that the edge applied: older commands held in TCP
        # buffers arrive late and are refused as stale, so they say nothing about recovery.
        echo = next((r for r in records if r[1] > b_req and r[5]), None)
        trial.update(
            stop_after_last_command_ms=stop_ms,
            stop_after_blackout_start_ms=(stop[0] - b0) / 1e6,
            stayed_stopped=not moved_during,
            motion_resumed_after_ms=(resume[0] - b_req) / 1e6 if resume else None,
            operator_echo_after_ms=(echo[4] - b_req) / 1e6 if echo else None,
            ok=stop_ms <= limit_s * 1000 and not moved_during,
        )
        trials.append(trial)
    return trials


def summarize_trials(trials: list[dict[str, Any]], long_from_ms: float = 2000.0) -> dict[str, Any]:
    """Stop times over every trial; recovery figures only over the short blackouts (a blackout past the lease
    is a different event — the sessions are re-opened — and is reported per trial)."""
    short = [t for t in trials if t["blackout_ms"] < long_from_ms]
    stops = [t["stop_after_last_command_ms"] for t in trials if "stop_after_last_command_ms" in t]
    rec = [t["operator_echo_after_ms"] for t in short if t.get("operator_echo_after_ms") is not None]
    resumed = [t["motion_resumed_after_ms"] for t in short if t.get("motion_resumed_after_ms") is not None]
    return {
        "trials": len(trials), "passed": sum(bool(t.get("ok")) for t in trials),
        "limit_ms": (COMMAND_TIMEOUT_S + CONTROL_PERIOD_S) * 1000,
        "stop_ms": stats.latency_summary(stops), "stop_ms_values": [round(s, 2) for s in stops],
        "operator_recovery_ms": stats.latency_summary(rec), "motion_resumed_ms": stats.latency_summary(resumed),
        "long_blackouts": [t for t in trials if t["blackout_ms"] >= long_from_ms],
    }


def choose_emulator(emulator: str, force_loopback: bool) -> tuple[bool, bool, str]:
    """(namespaces, netem, why) for ``--emulator`` (one of :data:`EMULATORS`). ``auto`` takes what the machine
    has and says what it fell back from; ``netem`` where the machine cannot do it is an error naming why."""
    if emulator not in EMULATORS:
        raise ValueError(f"unknown link emulator {emulator!r} (known: {', '.join(EMULATORS)})")
    ok, why = (False, "loopback requested") if force_loopback else Namespaces.available()
    if not ok:
        if emulator == "netem":
            raise Unavailable(f"--emulator netem needs network namespaces: {why}")
        print(f"iorthand bench wan: no namespaces ({why}); falling back to relays on 127.0.0.1 — blackouts hold "
              "traffic in the relay instead of dropping it, and tbf rate limits are not applied", flush=True)
        return False, False, why
    if emulator == "relay":
        return True, False, f"{why}; relays requested"
    netem, netem_why = Namespaces.netem_available()
    if not netem and emulator == "netem":
        raise Unavailable(f"--emulator netem: {netem_why}; use --emulator relay (or auto)")
    if not netem:
        print(f"iorthand bench wan: {netem_why}; delay and jitter come from the project's TCP relay", flush=True)
        return True, False, f"{why}; relays: {netem_why}"
    return True, True, f"{why}; {netem_why}"


def run_wan(workdir: Path, profiles: list[str], duration: float, trials: int, blackout_s: float, links: str = "edge",
            force_loopback: bool = False, long_blackouts: tuple[float, ...] = (), emulator: str = "auto",
            videos: tuple[str, ...] = ("none",)) -> dict[str, Any]:
    unknown = [name for name in profiles if name not in PROFILES]
    if unknown:
        raise ValueError(f"unknown WAN profile {unknown[0]!r} (known: {', '.join(PROFILES)})")
    ok, netem, why = choose_emulator(emulator, force_loopback)
    netns = Namespaces().create() if ok else None
    results: dict[str, Any] = {"isolation": "namespaces" if ok else "loopback", "emulator": "netem" if netem else "relay",
                               "why": why, "links": links, "profiles": {}}
    try:
        for name in profiles:
            for video in videos:
                plan = Plan(duration=duration, trials=trials, blackout_s=blackout_s, long_blackouts=tuple(long_blackouts))
                r = run_profile(workdir, PROFILES[name], plan, netns, links, netem=netem, video=video)
                if "trials" in r:
                    r["blackout_summary"] = summarize_trials(r["trials"])
                results["profiles"][name if video == "none" else f"{name}+{video}"] = r
        for name in profiles:  # the command path with video against the same profile without, in this run
            base = results["profiles"].get(name)
            for video in videos:
                r = results["profiles"].get(f"{name}+{video}")
                if base is not None and r is not None and base["rtt_ms"].get("p99"):
                    r["command_p99_ratio_to_no_video"] = round(r["rtt_ms"]["p99"] / base["rtt_ms"]["p99"], 3)
    finally:
        if netns is not None:
            netns.destroy()
    return results
