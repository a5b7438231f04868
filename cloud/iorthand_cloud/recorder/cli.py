"""Subcommands: ``recorder`` (the service, and start/stop/status of a running one), ``annotate``, ``replay``,
``report``, ``export``. Registered through the ``iorthand.commands`` entry point."""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import logging
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path

from iorthand import keys
from iorthand.config import ConfigError, cli_number, from_dict, load
from iorthand.security.certs import CertError, common_name, load_certificate
from iorthand.security.identity import operator_from_common_name
from iorthand.transport import ZenohConfig, client_config, open_session
from iorthand_cloud.recorder.config import RecorderConfig, ReportConfig
from iorthand_cloud.recorder.manifest import ManifestError
from iorthand_cloud.recorder.reader import SegmentError

log = logging.getLogger("iorthand.recorder")
DEFAULT_CONNECT = "tcp/127.0.0.1:7447"


def load_config(args: argparse.Namespace) -> RecorderConfig:
    cfg = load(args.config, RecorderConfig) if getattr(args, "config", None) else from_dict({}, RecorderConfig)
    if getattr(args, "connect", None):
        cfg.zenoh = ZenohConfig(mode="client", connect=list(args.connect), connect_retry_s=cfg.zenoh.connect_retry_s)
    elif cfg.zenoh.mode == "peer" and not cfg.zenoh.connect and not cfg.zenoh.listen:
        cfg.zenoh = client_config(DEFAULT_CONNECT)
    if getattr(args, "output", None):
        cfg.output_dir = Path(args.output)
    return cfg


def _session(args: argparse.Namespace):
    return open_session(load_config(args).zenoh)


def _print_status(st) -> None:
    print(json.dumps({f.name: getattr(st, f.name) for f in dataclasses.fields(st)}, indent=1))


def _cmd_recorder(args: argparse.Namespace) -> int:
    from iorthand_cloud.recorder import client
    from iorthand_cloud.recorder.service import RecorderService

    if args.action == "serve":
        cfg = load_config(args)
        if args.start_now:
            cfg.start_on_launch = True
        svc = RecorderService(cfg)
        if args.session:
            svc.launch_session = args.session
        svc.run_forever()
        return 1 if svc.status.error else 0
    session = _session(args)
    try:
        if args.action == "start":
            st = client.start(session, session_id=args.session or "", operator=args.operator or "",
                              robots=args.robot or [], note=args.note or "")
        elif args.action == "stop":
            st = client.stop(session)
        else:
            st = client.status(session)
        _print_status(st)
        return 0 if st.ok else 1
    finally:
        session.close()


def _certificate_operator(cfg: ZenohConfig) -> str:
    """The operator an ``operator-<name>`` client certificate names, "" for any other (or none)."""
    if cfg.tls is None or not cfg.tls.certificate:
        return ""
    try:
        name = common_name(load_certificate(Path(cfg.tls.certificate)))
    except CertError:
        return ""  # the session's own start-up says what is wrong with it
    return operator_from_common_name(name) or ""


def _cmd_annotate(args: argparse.Namespace) -> int:
    from iorthand_cloud.recorder import client

    cfg = load_config(args)
    # Behind the deployment's router an operator annotates only as itself: by default, as its certificate says.
    author = args.author or _certificate_operator(cfg.zenoh)
    session = open_session(cfg.zenoh)
    try:
        st = client.annotate(session, args.text, author=author, tags=args.tag or [], score=args.score)
    except client.RecorderUnavailable as exc:
        print(f"annotation not stored: {exc}; behind a router with bind_operator_keys, only operator-{author or 'NAME'}'s "
              "certificate may annotate as that author (--author)")
        return 1
    finally:
        session.close()
    print(("annotation stored in " + st.session) if st.ok else f"annotation refused: {st.reason}")
    return 0 if st.ok else 1


def _reading(command: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """A command that reads a session's segments: a segment or manifest it cannot read safely, or a session it
    cannot repair first (a disk still full), is said in one line (exit 1)."""

    @functools.wraps(command)
    def run(args: argparse.Namespace) -> int:
        try:
            return command(args)
        except (SegmentError, ManifestError, OSError) as exc:
            print(f"iorthand {args.command}: {exc}", file=sys.stderr)
            return 1

    return run


@_reading
def _cmd_replay(args: argparse.Namespace) -> int:
    from iorthand_cloud.recorder.manifest import Manifest
    from iorthand_cloud.recorder.replay import NothingToReplay, Replayer

    Manifest.read(Path(args.session))  # a wrong folder is said at once, not after connecting
    session = _session(args)
    try:
        try:
            rp = Replayer(session, args.session, speed=args.speed, loop=args.loop, key_filter=args.keys,
                          include_malformed=args.include_malformed, start=args.start, end=args.end,
                          rename=_renames(args.rename or []))
        except ValueError as exc:
            print(f"replay: {exc}", file=sys.stderr)
            return 2
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: rp.stop_event.set())
        refused: list[SegmentError] = []
        nothing: list[NothingToReplay] = []

        def run() -> None:
            try:
                rp.run()
            except SegmentError as exc:  # a later segment: what went before was replayed
                refused.append(exc)
            except NothingToReplay as exc:
                nothing.append(exc)

        t = threading.Thread(target=run, name="replay", daemon=True)
        t.start()
        while t.is_alive():
            t.join(0.2)
        if refused:
            raise refused[0]
        if nothing:
            print(f"replay: {nothing[0]}", file=sys.stderr)
            return 1
        robots = sorted({keys.split_key(k)[0] for k in rp.stats.per_key})
        print(f"replayed {rp.stats.published} messages as {', '.join(robots) or 'no robot'} ({rp.stats.loops} "
              f"pass(es)), at most {rp.stats.max_late_ms:.1f} ms late; {rp.stats.commands_withheld} operator "
              "commands withheld (a replay never drives a robot)"
              + (f"; {rp.stats.gaps_shortened:.1f} s of silence in the recording not waited for"
                 if rp.stats.gaps_shortened else ""))
    finally:
        session.close()
    return 0


def _renames(pairs: list[str]) -> dict[str, str]:
    """``--as OLD=NEW`` options → {OLD: NEW}."""
    out: dict[str, str] = {}
    for pair in pairs:
        old, sep, new = pair.partition("=")
        if not sep or not old or not new:
            raise ValueError(f"--as {pair!r}: expected RECORDED=NEW robot ids, e.g. --as sim1=lyon-replay")
        out[old] = new
    return out


def _report_config(args: argparse.Namespace) -> ReportConfig:
    cfg = load(args.config, RecorderConfig).report if args.config else ReportConfig()
    if args.contact_threshold is not None:
        cfg.contact_threshold = args.contact_threshold
    return cfg


@_reading
def _cmd_report(args: argparse.Namespace) -> int:
    from iorthand_cloud.recorder.report import build_report

    data = build_report(args.session, _report_config(args), Path(args.out) if args.out else None)
    for robot, r in data["robots"].items():
        ix = r["index"]
        print(f"{robot}: t_t {ix['t_t']:.2f} s, τ {ix['tau']:.2f} s, ψ {ix['psi']:.4f}, ω_R {ix['omega_R']}, "
              f"ω_Y {ix['omega_Y']}, φ {ix['phi']:.2f} %")
    print(f"report: {data['path']}")
    return 0


@_reading
def _cmd_export(args: argparse.Namespace) -> int:
    if args.start is not None and args.end is not None and args.end <= args.start:
        raise ConfigError("command line", "--end", f"{args.end:g} s is not after --start {args.start:g} s")
    if args.format == "rrd":
        from iorthand_cloud.recorder.export import export_rrd

        path, n = export_rrd(args.session, args.out, args.start, args.end, args.video_fps)
        print(f"exported {n} entries to {path}")
        return 0
    # The ROS 2 and LeRobot writers need packages of their own (rosbags; lerobot with torch): a missing one, or a
    # session they cannot export as asked, is said in one line.
    from iorthand_cloud.recorder.export_ros2 import ExportError

    try:
        if args.format == "ros2":
            from iorthand_cloud.recorder.export_ros2 import export_ros2

            bag = export_ros2(args.session, args.out, args.start, args.end, storage=args.storage)
            if bag.skipped:
                print("left out: " + ", ".join(f"{n} {why}" for why, n in sorted(bag.skipped.items())),
                      file=sys.stderr)
            print(f"exported {bag.messages} messages on {len(bag.counts)} topics to {bag.path}")
        else:
            from iorthand_cloud.recorder.export_lerobot import export_lerobot

            ds = export_lerobot(args.session, args.out, args.start, args.end, fps=args.fps, robot=args.robot,
                                task=args.task, vcodec=args.vcodec, image_scale=args.image_scale)
            for warning in ds.warnings:
                print(f"warning: {warning}", file=sys.stderr)
            print(f"exported {ds.frames} frames in {len(ds.episodes)} episode(s) at {ds.fps} fps to {ds.path}")
    except ModuleNotFoundError as exc:
        from iorthand_cloud.recorder import export_lerobot, export_ros2

        hint = (export_ros2 if args.format == "ros2" else export_lerobot).INSTALL
        print(f"iorthand export: --format {args.format} needs the Python package {exc.name!r}, which is not "
              f"installed: {hint}", file=sys.stderr)
        return 1
    except ExportError as exc:
        print(f"iorthand export: {exc}", file=sys.stderr)
        return 1
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    def connection(p: argparse.ArgumentParser) -> None:
        p.add_argument("--config", help="recorder YAML (configs/recorder.yaml)")
        p.add_argument("--connect", action="append", help=f"router endpoint (default {DEFAULT_CONNECT})")

    p = sub.add_parser("recorder", help="the MCAP recorder service, or start/stop/status of a running one")
    p.add_argument("action", nargs="?", default="serve", choices=["serve", "start", "stop", "status"])
    connection(p)
    p.add_argument("--output", help="sessions folder (overrides output_dir)")
    p.add_argument("--start-now", action="store_true", help="serve: start recording at once")
    p.add_argument("--session", help="session id (start, or serve --start-now)")
    p.add_argument("--operator", help="start: the operator's id, for the manifest")
    p.add_argument("--robot", action="append", help="start: robot ids, for the manifest")
    p.add_argument("--note", help="start: free text for the manifest")
    p.set_defaults(func=_cmd_recorder)

    p = sub.add_parser("annotate", help="add a comment, tags or a score to the recording in progress")
    p.add_argument("text")
    connection(p)
    p.add_argument("--author", default="", help="who annotates (default: the operator the client certificate names); "
                   "behind a router with bind_operator_keys only that operator's certificate may annotate as it")
    p.add_argument("--tag", action="append")
    p.add_argument("--score", type=float)
    p.set_defaults(func=_cmd_annotate)

    p = sub.add_parser("replay", help="republish a recorded session into Zenoh with its original timing")
    p.add_argument("session", help="session folder")
    connection(p)
    p.add_argument("--speed", type=cli_number(float, lo=0.01, hi=100.0), default=1.0, help="2 = twice as fast")
    p.add_argument("--loop", action="store_true")
    p.add_argument("--keys", action="append", help="key expression to replay (repeatable; default: all)")
    p.add_argument("--include-malformed", action="store_true")
    p.add_argument("--start", type=float, help="s from the session's first message")
    p.add_argument("--end", type=float)
    p.add_argument("--as", dest="rename", action="append", metavar="RECORDED=NEW",
                   help="the id to replay a recorded robot as (repeatable; it must end in -replay; "
                        "default: the recorded id + -replay)")
    p.set_defaults(func=_cmd_replay)

    p = sub.add_parser("report", help="session report: performance index, latencies, plots (Markdown + JSON)")
    p.add_argument("session")
    p.add_argument("--config", help="recorder YAML whose `report:` section to use")
    p.add_argument("--contact-threshold", type=cli_number(float, lo=0.0), help="N")
    p.add_argument("--out", help="folder (default SESSION/report)")
    p.set_defaults(func=_cmd_report)

    p = sub.add_parser("export", help="export a session (or a time range): a rerun .rrd (default), a ROS 2 bag or "
                                      "a LeRobot dataset")
    p.add_argument("session")
    # The choices below are export_ros2.STORAGES and export_lerobot's VCODECS, IMAGE_SCALES and DEFAULT_FPS (a test
    # checks it): not imported, because every iorthand command builds this parser and they would add ~0.1 s.
    p.add_argument("--format", choices=["rrd", "ros2", "lerobot"], default="rrd",
                   help="rrd: rerun recording; ros2: ROS 2 bag (rosbags); lerobot: LeRobotDataset v3 (parquet + mp4)")
    p.add_argument("--out", help="path (default SESSION/<id>.rrd, SESSION/<id>-ros2, SESSION/<id>-lerobot); a bag "
                                 "or dataset folder must not exist yet")
    p.add_argument("--start", type=float, help="s from the session's first message")
    p.add_argument("--end", type=float)
    p.add_argument("--video-fps", type=cli_number(float, lo=0.1), default=5.0, help="rrd: JPEG images per second kept (H.264 video is never thinned: every frame from a keyframe on)")
    p.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap",
                   help="ros2: the bag's storage (sqlite3 for ROS 2 Humble without the MCAP plugin)")
    p.add_argument("--fps", type=cli_number(int, lo=1, hi=120), default=30,
                   help="lerobot: frames per second of the dataset (state and images held at each frame time)")
    p.add_argument("--robot", help="lerobot: the robot to export (needed when the session has several)")
    p.add_argument("--task", help="lerobot: the task of every episode (default: from the annotations or the note)")
    p.add_argument("--vcodec", choices=["mjpeg", "h264", "libsvtav1"], default="mjpeg",
                   help="lerobot: video codec (mjpeg: the recorded JPEGs as they are, fast, every frame a keyframe; "
                        "h264 and libsvtav1, LeRobot's own default: re-encoded, smaller files, many times slower)")
    p.add_argument("--image-scale", type=float, choices=[1.0, 0.5, 0.25], default=1.0,
                   help="lerobot: picture size relative to the recorded frames (smaller: less to encode and store)")
    p.set_defaults(func=_cmd_export)


if __name__ == "__main__":  # pragma: no cover
    sys.exit("use `iorthand recorder`")
