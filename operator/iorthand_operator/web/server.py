"""``iorthand web``: the operator console in a browser, bridged to Zenoh.

One aiohttp server (HTTPS, or HTTP on loopback only) serves a single page and one websocket per open page. The
server is one Zenoh client. For each robot a page watches it keeps a :class:`Feed`: a watching
:class:`~iorthand_operator.client.OperatorClient` (state, safety, force, markers and the console's events, no
liveliness token, never acquiring) and the newest camera and ultrasound frames. A page that takes control gets an
OperatorClient of its own, in its user's name, and every twist message of that page becomes one command at once:
the server never repeats, stores or invents one, so the edge's own timeout sees the page's stream (if the page
stops, the robot stops). A page that closes, or whose websocket drops, releases control.

Who may do what comes from the deployment (:mod:`iorthand_operator.web.users`): log-in by password, a session
cookie (HttpOnly, SameSite=Strict, Secure under HTTPS), and on the websocket the origin, the session and the
robot's grant. Every refusal is counted (``/api/stats``) and said on the page; nothing refused reaches Zenoh.

Video: JPEG pictures go newest first when the page's socket has room (never a queue); H.264 frames go in order
from a keyframe, and a page that falls behind skips to the next keyframe and asks the edge for one; the page
decodes them with the browser's WebCodecs. ``benchmarks/bench_web.py`` measured this against the Python client
(figures in benchmarks/README.md).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import secrets
import ssl
import struct
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from aiohttp import WSMsgType, web

from iorthand import geometry, keys, kinematics
from iorthand.config import from_dict as config_from_dict
from iorthand.config import read_yaml
from iorthand.protocol import DecodeError, Markers, Sequencer, StopCommand, VideoFeedback, VideoFrame, source_news
from iorthand.security.acl import Deployment
from iorthand.security.certs import load_certificate, subject_alt_names
from iorthand.security.hosts import host_allowed
from iorthand.transport import QOS_BY_KEY, open_session, publisher
from iorthand_operator import recovery
from iorthand_operator.client import (
    ControlRefused,
    Echo,
    Event,
    OperatorClient,
    actuator_stale_after,
)
from iorthand_operator.console.model import force_view, markers_note, picture_stale_after, stale_note, vitals_line
from iorthand_operator.link import GRADE_COLOURS
from iorthand_operator.web import messages, users
from iorthand_operator.web.config import WebConfig

log = logging.getLogger("iorthand.web")

STATIC = Path(__file__).resolve().parent / "static"
COOKIE = "iorthand_session"
WATCHER_ID = "web"  # the id of the server's watching clients (they never acquire, announce or command)
VIDEO_STREAMS = {"camera": keys.VIDEO_CAMERA, "ultrasound": keys.VIDEO_ULTRASOUND}
# A page whose socket holds more than this unsent is behind: it gets no video until it has drained (newest wins).
VIDEO_BACKLOG_BYTES = 256 * 1024
WS_MAX_BYTES = 64 * 1024  # aiohttp closes a socket whose message is larger; up to it, messages.parse refuses
MAX_SESSIONS = 10_000
PAGES_CLOSE_CODE = 4429  # a page beyond max_pages_per_login / max_pages_per_user (the close says why)
# One user's log-ins beyond this end that user's oldest, never another user's: a viewer logging in over and over
# filled the table and, at MAX_SESSIONS, evicted the physician's log-in (its page ended, and its control).
MAX_LOGINS_PER_USER = 16
SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' blob: data:; style-src 'self'; "
                               "script-src 'self'; connect-src 'self'; frame-ancestors 'none'; base-uri 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "X-Frame-Options": "DENY",
}


@dataclass
class Login:
    user: str
    expires: float  # monotonic


@dataclass
class Frame:
    """One frame of a video stream as the page gets it: JPEG or an H.264 access unit."""

    seq: int
    t: int  # capture time, ns since the epoch
    data: bytes
    failure: str = ""
    h264: bool = False
    keyframe: bool = False

    def wire(self, stream_index: int) -> bytes:
        """The binary websocket message: stream, capture time, sequence, flags (bit 0 H.264, bit 1 keyframe, bit 2
        failure notice), then the frame's data, or a failure notice's reason (UTF-8): the page says why there is
        no picture in its place."""
        flags = (1 if self.h264 else 0) | (2 if self.keyframe else 0) | (4 if self.failure else 0)
        header = struct.pack(">BQIB", stream_index, self.t, self.seq & 0xFFFFFFFF, flags)
        return header + (self.failure.encode() if self.failure else self.data)


# Frames of an H.264 stream kept for pages that are a few frames behind: a page further behind skips to the next
# keyframe (a JPEG stream needs only the newest frame, and its pages get only that).
H264_BACKLOG = 45


class Feed:
    """One robot as every page of it sees it (one per robot, shared by its pages)."""

    def __init__(self, session: zenoh.Session, robot: str, arm_model: str, loop: asyncio.AbstractEventLoop) -> None:
        self.robot = robot
        self.loop = loop
        self.watch = OperatorClient(session, robot, WATCHER_ID, announce=False, external_sender=True)
        self.arm = kinematics.ArmTracker(arm_model)
        self.frames: dict[str, deque[Frame]] = {name: deque(maxlen=H264_BACKLOG) for name in VIDEO_STREAMS}
        self.pages: set[Page] = set()
        self._video_failure = dict.fromkeys(VIDEO_STREAMS, "")  # each stream's newest failure ("": frames flow)
        # Each stream's frame period (s, 0: not known yet), from its frames' capture times and sequence numbers (a
        # frame lost on the way leaves a gap in the sequence, not a longer period): its pictures' bound for "live".
        self.frame_period = dict.fromkeys(VIDEO_STREAMS, 0.0)
        self._last_picture: dict[str, tuple[int, int]] = {}  # stream → (seq, t) of its newest picture
        self._arm_seq = -1
        self._arm_points: list[list[float]] | None = None
        self._lock = threading.Lock()
        self._subs = [session.declare_subscriber(keys.RobotKeys(robot).key(suffix), self._on_video(name))
                      for name, suffix in VIDEO_STREAMS.items()]

    def _on_video(self, name: str) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                msg = VideoFrame.decode(sample.payload.to_bytes())
            except DecodeError as exc:
                self.watch.rejects.add(str(sample.key_expr), str(exc))
                return
            frame = Frame(msg.seq, msg.t, msg.data, msg.failure, msg.encoding == "h264", msg.keyframe)
            # In the pages' event logs too, as the twin says it: when a stream stopped, why, and when it came back.
            news = source_news(f"{name} video", self._video_failure[name], msg.failure)
            if news:
                self.watch.log_event("warning" if msg.failure else "info", f"{name}_video", news)
            self._video_failure[name] = msg.failure
            if not msg.failure:
                last = self._last_picture.get(name)
                if last is not None and msg.seq > last[0] and msg.t > last[1]:
                    self.frame_period[name] = (msg.t - last[1]) / 1e9 / (msg.seq - last[0])
                self._last_picture[name] = (msg.seq, msg.t)
            frames = self.frames[name]
            if not frame.h264:
                frames.clear()  # newest wins
            frames.append(frame)
            self.loop.call_soon_threadsafe(self._notify)

        return on_sample

    def _notify(self) -> None:
        for page in self.pages:
            page.video_ready.set()

    def arm_points(self) -> list[list[float]] | None:
        """The arm's drawing points (base frame) for the newest robot state, solved once per state."""
        st = self.watch.robot_state
        if st is None:
            return None
        with self._lock:
            if st.seq != self._arm_seq:
                q = self.arm.solve(st.tcp_pose, st.q)
                self._arm_points = None if q is None else np.round(kinematics.link_points(self.arm.model, q), 4).tolist()
                self._arm_seq = st.seq
            return self._arm_points

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.watch.close()


@dataclass
class Refusals:
    """Everything the server refused, by reason (``/api/stats``, and logged once a reason per minute)."""

    counts: Counter[str] = field(default_factory=Counter)
    _logged: dict[str, float] = field(default_factory=dict)

    def add(self, kind: str, detail: str = "") -> None:
        self.counts[kind] += 1
        now = time.monotonic()
        if now - self._logged.get(kind, -math.inf) > 60.0:
            self._logged[kind] = now
            log.warning("refused (%s)%s", kind, f": {detail}" if detail else "")


class Bridge:
    """The server's state: users, log-ins, the Zenoh session, the feeds and which page controls which robot."""

    def __init__(self, config: WebConfig, deployment: Deployment, user_hashes: dict[str, str]) -> None:
        self.config = config
        # What a browser may name in Host: a DNS-rebinding page (evil.example resolving to this server) names its own
        # host, and would otherwise be this console's origin, free to guess passwords and lock accounts out.
        names = subject_alt_names(load_certificate(config.tls.certificate)) if config.tls is not None else []
        self.host_names = config.host_names(names)
        self.grants = users.grants(deployment)
        self.robots = list(deployment.robots)
        self.hashes = user_hashes
        self.logins: dict[str, Login] = {}
        self.guard = users.LoginGuard()
        self._guard_lock = threading.Lock()
        self._unknown_user_hash = users.hash_password(secrets.token_urlsafe(16))
        # Log-ins (an scrypt check each, ~50 ms) get threads of their own: a flood of them must not hold up
        # taking or releasing control, which use the loop's default pool.
        self.login_pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="web-login")
        self.refusals = Refusals()
        self.session: zenoh.Session | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self.feeds: dict[str, Feed] = {}
        self.controllers: dict[str, Page] = {}  # robot → the page of this server that holds its control
        # Pages take and release control on the loop's pool of threads: one check-and-set of controllers at a time
        # (two pages acquiring at once both found the robot free, and the loser's failure removed the winner).
        self.control_lock = threading.Lock()
        self._stops: dict[tuple[str, str], tuple[zenoh.Publisher, Sequencer]] = {}
        self._feedback: dict[tuple[str, str], tuple[zenoh.Publisher, Sequencer]] = {}
        self._keyframe_asked: dict[tuple[str, str], float] = {}

    # ------------------------------------------------------------- log-in

    def log_in(self, user: str, password: str, address: str) -> tuple[str, str]:
        """(token, "") or ("", why not). The same answer for an unknown user and a wrong password."""
        now = time.monotonic()
        with self._guard_lock:  # log-ins run on a pool of threads: one check-and-count at a time
            wait = self.guard.attempt(address, user, now)
        if wait:
            self.refusals.add("login_blocked", f"{user[:40]!r} from {address}")
            return "", f"too many failed log-ins: try again in {math.ceil(wait)} s"
        stored = self.hashes.get(user)
        # An unknown user costs one scrypt check as a known one does (against a hash made once): no user-name
        # oracle in the answer's time.
        ok = users.check_password(password, stored or self._unknown_user_hash) and stored is not None \
            and user in self.grants
        if not ok:
            self.refusals.add("login_failed", f"{user[:40]!r} from {address}")
            return "", "wrong user name or password"
        with self._guard_lock:
            self.guard.succeeded(address, user, now)
        self._expire(now, user)
        token = secrets.token_urlsafe(32)
        self.logins[token] = Login(user, now + 3600 * self.config.session_hours)
        log.info("%s logged in from %s (%s)", user, address, self.grants[user].role)
        return token, ""

    def _expire(self, now: float, user: str) -> None:
        """Room for a new log-in of ``user``: expired log-ins go, then that user's oldest beyond its share."""
        for token in [t for t, s in self.logins.items() if s.expires < now]:
            del self.logins[token]
        own = [t for t, s in self.logins.items() if s.user == user]  # oldest first (the dict keeps their order)
        for token in own[:max(0, len(own) - MAX_LOGINS_PER_USER + 1)]:
            del self.logins[token]
        while len(self.logins) >= MAX_SESSIONS:
            self.logins.pop(next(iter(self.logins)))

    def pages(self) -> list[Page]:
        """Every open page, of every robot (a snapshot: the caller may await while it goes through them)."""
        return [page for feed in list(self.feeds.values()) for page in list(feed.pages)]

    def page_refused(self, token: str, user: str) -> str:
        """Why a new page of log-in ``token`` (of ``user``) is refused, "" if it is not: one viewer's thousand pages
        held up the physician's commands past the edge's deadman timeout (red team, e1b)."""
        pages = self.pages()
        per_login, per_user = self.config.max_pages_per_login, self.config.max_pages_per_user
        if sum(1 for p in pages if p.token == token) >= per_login:
            return (f"too many pages: this log-in has {per_login} open already (the most it may): close one, "
                    "then reload this page")
        if sum(1 for p in pages if p.grant.user == user) >= per_user:
            return (f"too many pages: {user} has {per_user} open already (the most one user may, over all log-ins): "
                    "close one, then reload this page")
        return ""

    def user_of(self, request: web.Request) -> users.Grant | None:
        token = request.cookies.get(COOKIE, "")
        return self.grants.get(self.logins[token].user) if self.logged_in(token) else None

    def logged_in(self, token: str) -> bool:
        """Whether ``token`` is a log-in that has not ended (logged out, expired, or evicted for a newer one)."""
        login = self.logins.get(token)
        return login is not None and login.expires >= time.monotonic()

    def peer(self, request: web.Request) -> users.Peer:
        """The browser behind ``request`` (through a trusted reverse proxy: what the proxy says)."""
        return users.peer_of(request.remote, request.secure, request.headers, self.config.trusted_proxies)

    def origin_ok(self, request: web.Request) -> bool:
        origin = request.headers.get("Origin", "")
        own = f"{request.scheme}://{request.host}"
        return bool(origin) and (origin == own or origin in self.config.allowed_origins)

    # ------------------------------------------------------------- Zenoh

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.session = open_session(self.config.zenoh)

    def feed(self, robot: str) -> Feed:
        if robot not in self.feeds:
            assert self.session is not None and self.loop is not None
            model = self.config.arm_models.get(robot, self.config.arm_model)
            self.feeds[robot] = Feed(self.session, robot, model, self.loop)
        return self.feeds[robot]

    def stop_robot(self, robot: str, user: str, reason: str) -> None:
        """An e-stop from an operator of ``robot``, controlling it or not (a stop is everyone's)."""
        assert self.session is not None
        key = (robot, user)
        if key not in self._stops:
            suffix = keys.CMD_STOP + (f"/{user}" if self.config.bind_operator_keys else "")
            pub = publisher(self.session, keys.RobotKeys(robot).key(suffix), QOS_BY_KEY[keys.CMD_STOP])
            self._stops[key] = pub, Sequencer()
        pub, seq = self._stops[key]
        pub.put(StopCommand(operator=user, reason=reason).stamp(seq.next()).encode())

    def video_feedback(self, robot: str, grant: users.Grant, stream: str, keyframe: bool, received: int,
                       lost: int) -> None:
        """A page's report on a video stream, to the edge. With bound keys only an operator's own key is open to
        this server (a viewer's page relies on the stream's periodic keyframes); a keyframe request at most
        twice a second per robot and stream."""
        assert self.session is not None
        bind = self.config.bind_operator_keys
        if bind and not grant.may_command(robot):
            return
        now = time.monotonic()
        if keyframe and now - self._keyframe_asked.get((robot, stream), -math.inf) < 0.5:
            return
        if keyframe:
            self._keyframe_asked[(robot, stream)] = now
        name = grant.user if bind else WATCHER_ID
        key = (robot, name)
        if key not in self._feedback:
            suffix = keys.CMD_VIDEO_FEEDBACK + (f"/{name}" if bind else "")
            self._feedback[key] = (publisher(self.session, keys.RobotKeys(robot).key(suffix)), Sequencer())
        pub, seq = self._feedback[key]
        pub.put(VideoFeedback(operator=name, stream=stream, keyframe=keyframe, received=received,
                              lost=lost).stamp(seq.next()).encode())

    def close(self) -> None:
        self.login_pool.shutdown(wait=False, cancel_futures=True)
        for feed in self.feeds.values():
            feed.close()
        if self.session is not None:
            self.session.close()


class Page:
    """One open page: its websocket, its user's grant, its robot's feed and, while it holds control, its client."""

    def __init__(self, bridge: Bridge, ws: web.WebSocketResponse, grant: users.Grant, feed: Feed,
                 transport: asyncio.BaseTransport | None, token: str = "") -> None:
        self.bridge = bridge
        self.token = token  # the log-in this page was opened with: its end (log-out, expiry) closes the page
        self.ws = ws
        self.transport = transport  # the socket under the websocket: how much it holds unsent
        self.grant = grant
        self.feed = feed
        self.robot = feed.robot
        self.client: OperatorClient | None = None
        self.video_ready = asyncio.Event()
        self.video_on = True
        self.closed = False
        self._busy = False  # a control request is under way
        self._sent_video = dict.fromkeys(VIDEO_STREAMS, -1)  # seq of the last frame sent, per stream
        self._video_stats = {name: [0, 0] for name in VIDEO_STREAMS}  # frames sent, skipped since the last report
        self._feedback_at = dict.fromkeys(VIDEO_STREAMS, 0.0)
        # (command seq, its time stamp) → the page's message id: the sequence alone restarts with every grant
        self._pending: dict[tuple[int, int], int] = {}
        self._last_events: dict[str, Event | None] = {"watch": None, "client": None}
        self._notices = messages.Notices()
        self._twists = messages.TwistBudget(bridge.config.twist_hz)
        self.budgets = messages.PageBudgets()
        self._request: asyncio.Task[None] | None = None  # the request under way (held: the loop keeps tasks weakly)
        self.refused = 0
        self.heard_at = time.monotonic()  # the last message of any kind from the page

    # ------------------------------------------------------------- from the page

    async def on_text(self, data: str) -> None:
        now = time.monotonic()
        try:
            msg = messages.parse(data)
        except messages.PageError as exc:
            return await self.refuse("malformed", f"message refused: {exc}")
        if isinstance(msg, messages.Twist):
            return await self.on_twist(msg)
        if isinstance(msg, messages.Control) and msg.verb == "stop":
            return await self.on_stop(now)
        if isinstance(msg, messages.View):
            self.video_on = msg.video
            return None
        if not self.grant.may_command(self.robot):
            return await self.refuse("viewer", f"{self.grant.user} may watch {self.robot}, not command it")
        if isinstance(msg, messages.Camera) and not self.budgets.camera.allow(now):
            return await self.refuse("too_fast", f"camera steps beyond {self.budgets.CAMERA_HZ:.0f} a second are "
                                     "dropped")
        if self._busy:
            return await self.refuse("busy", "a control request is still under way")
        # Run apart from the socket's reading: the page's twists and its STOP go on while a request (a preview,
        # an acquire) waits up to seconds for its answer.
        self._busy = True
        self._request = asyncio.create_task(self._run_request(msg))

    async def _run_request(self, msg: messages.PageMessage) -> None:
        try:
            await self.on_request(msg)
        finally:
            self._busy = False

    async def on_twist(self, msg: messages.Twist) -> None:
        if not self.grant.may_command(self.robot):
            return await self.refuse("viewer", f"{self.grant.user} may watch {self.robot}, not move it")
        client = self.client
        if client is None:
            return await self.refuse("not_controlling", "take control before moving the robot")
        if not self._twists.allow(msg, time.monotonic()):
            return await self.refuse("too_fast", f"twists beyond {self._twists.rate:.0f} a second are dropped: the "
                                     f"page sends {self.bridge.config.twist_hz:.0f} (more comes from a script, or "
                                     "from a stalled link delivering its backlog at once)")
        newest = self.feed.watch.robot_state
        # The page can say it showed an older state, never a newer one than this server had.
        seen = min(msg.seen, newest.t) if newest is not None else 0
        cmd = client.send_now(msg.linear, msg.angular, msg.deadman, seen, msg.frame)
        if cmd is not None:
            self._pending[(cmd.seq, cmd.t)] = msg.id
            while len(self._pending) > 512:
                self._pending.pop(next(iter(self._pending)))

    async def on_stop(self, now: float) -> None:
        if not self.grant.may_command(self.robot):
            return await self.refuse("viewer", f"{self.grant.user} may watch {self.robot}, not stop it: ask its operator")
        if not self.budgets.stops.allow(now):  # the stop just sent holds the robot: a repeat adds only load
            return await self.refuse("stop_repeated", f"stops beyond {self.budgets.STOP_HZ:.0f} a second are not "
                                     "sent again: the robot holds the stop already sent")
        reason = f"e-stop from {self.grant.user}'s web console"
        if self.client is not None:
            self.client.emergency_stop(reason)
        else:
            self.bridge.stop_robot(self.robot, self.grant.user, reason)
        await self.send({"type": "reply", "to": "stop", "ok": True, "reason": "stop sent"})

    async def on_request(self, msg: messages.PageMessage) -> None:
        loop = asyncio.get_running_loop()
        if isinstance(msg, messages.Control) and msg.verb == "acquire":
            ok, reason = await loop.run_in_executor(None, self._acquire, msg.profile)
            return await self.send({"type": "reply", "to": "acquire", "ok": ok, "reason": reason})
        client = self.client
        if client is None:
            return await self.refuse("not_controlling", "take control first")
        if isinstance(msg, messages.Control) and msg.verb == "release":
            await loop.run_in_executor(None, self._release)
            return await self.send({"type": "reply", "to": "release", "ok": True, "reason": "control released"})
        try:
            if isinstance(msg, messages.Control) and msg.verb in ("contact_on", "contact_off"):
                reply = await loop.run_in_executor(None, client.set_contact, msg.verb == "contact_on", None)
                return await self.send({"type": "reply", "to": "contact", "ok": reply.ok, "reason": reply.reason})
            if isinstance(msg, messages.Control) and msg.verb == "poses":
                poses = await loop.run_in_executor(None, client.list_poses)
                return await self.send({"type": "poses", "poses": [p.get("name", "") for p in poses]})
            if isinstance(msg, messages.Pose):
                fn = client.preview_pose if msg.verb == "preview" else client.goto_pose
                args = (msg.name,) if msg.verb == "preview" else (msg.name, msg.token)
                reply = await loop.run_in_executor(None, fn, *args)
                detail = _json_object(reply.detail)
                return await self.send({"type": "reply", "to": msg.verb, "name": msg.name, "ok": reply.ok,
                                        "reason": reply.reason, "token": str(detail.get("token", ""))})
            if isinstance(msg, messages.Camera):
                if msg.pan or msg.tilt:
                    client.step_servo(msg.pan, msg.tilt)
                if msg.torch is not None:
                    client.set_torch(msg.torch)
                return None
        except (ControlRefused, RuntimeError) as exc:
            return await self.send({"type": "reply", "to": getattr(msg, "verb", "camera"), "ok": False,
                                    "reason": str(exc)})
        return None

    def _acquire(self, profile: str) -> tuple[bool, str]:
        """Take control of the robot for this page (a blocking query: off the event loop)."""
        controllers = self.bridge.controllers
        with self.bridge.control_lock:
            holder = controllers.get(self.robot)
            if not (holder is self and self.client is not None):
                if holder is not None and not holder.closed:
                    return False, f"{self.robot} is controlled by {holder.grant.user} from another page of this console"
                controllers[self.robot] = self  # claimed: another page's acquire now finds it taken
        if holder is self and self.client is not None:
            try:  # already ours: a profile change
                return True, self.client.switch_profile(profile).reason
            except ControlRefused as exc:
                return False, str(exc)
        assert self.bridge.session is not None
        client = OperatorClient(self.bridge.session, self.robot, self.grant.user, external_sender=True,
                                bind_keys=self.bridge.config.bind_operator_keys,
                                link_window=self.bridge.config.console.link_window,
                                release_tail=self.bridge.config.release_tail)
        client.echo_listener = self._on_echo
        try:
            reply = client.acquire(profile)
        except (ControlRefused, RuntimeError) as exc:
            client.close()
            self._unclaim()
            return False, str(exc)
        client.start()  # the lease renewal; the page's messages are the command stream
        # The page's twists start once it hears that it holds control: its silence counts from now at the earliest
        # (an acquire that took seconds must not count as silence).
        self.heard_at = max(self.heard_at, time.monotonic())
        self.client = client
        if self.closed:  # closed while acquiring: its close found no client to release
            self._release()
            return False, "page closed"
        log.info("%s controls %s from a web page", self.grant.user, self.robot)
        return True, reply.reason

    def _unclaim(self) -> None:
        """This page's entry in controllers goes, never another page's."""
        with self.bridge.control_lock:
            if self.bridge.controllers.get(self.robot) is self:
                del self.bridge.controllers[self.robot]

    def _release(self) -> None:
        client, self.client = self.client, None
        self._unclaim()
        if client is not None:
            client.close()  # releases control (the robot halts) and the user's liveliness token
            log.info("%s released %s", self.grant.user, self.robot)

    def _on_echo(self, echo: Echo, _msg: Any) -> None:
        """A command of ours came back from the edge (a Zenoh thread): tell the page, for its round trip."""
        page_id = self._pending.pop((echo.seq, echo.sent_ns), None)
        if page_id is not None and self.bridge.loop is not None:
            reply = {"type": "echo", "id": page_id, "accepted": echo.accepted, "status": echo.status}
            self.bridge.loop.call_soon_threadsafe(lambda: asyncio.ensure_future(self.send(reply)))

    async def refuse(self, kind: str, reason: str) -> None:
        """Count a refusal and say it on the page (a repeated one at most once a second: :class:`Notices`)."""
        self.refused += 1
        self.bridge.refusals.add(kind, f"{self.grant.user} on {self.robot}: {reason}")
        if self._notices.due(reason, time.monotonic()):
            await self.send({"type": "refused", "kind": kind, "reason": reason})

    # ------------------------------------------------------------- to the page

    async def send(self, obj: dict[str, Any]) -> None:
        if self.closed or self.ws.closed:
            return
        with contextlib.suppress(ConnectionError, RuntimeError):
            await self.ws.send_str(json.dumps(obj, allow_nan=False, default=_json_default))

    async def push(self) -> None:
        """State at ``state_hz``; each video stream's newest frame as soon as the socket has room."""
        period = 1.0 / self.bridge.config.state_hz
        next_state = time.monotonic()
        while not self.closed and not self.ws.closed:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.video_ready.wait(), max(0.0, next_state - time.monotonic()))
            self.video_ready.clear()
            if time.monotonic() >= next_state:
                next_state = time.monotonic() + period
                if not self.bridge.logged_in(self.token):  # its log-in ended: the page ends with it
                    await self.end(4401, "log-in ended (logged out, expired, or ended by newer log-ins of the same "
                                         "user): log in again")
                    return
                lost = self._control_lost()
                if lost:
                    await self.send({"type": "refused", "kind": "control_lost", "reason": lost})
                    await asyncio.get_running_loop().run_in_executor(None, self._release)
                await self.send(self.state())
            await self._push_video()

    def _control_lost(self) -> str:
        """Why this page no longer holds the control it took, "" while it does (or holds none, or a request for it
        is under way)."""
        if self.client is None or self._busy:
            return ""
        silent = time.monotonic() - self.heard_at
        if silent > self.bridge.config.page_silence:
            # A controlling page sends twists at twist_hz whatever the operator does: this silence is a dropped link
            # (no FIN: the socket's own heartbeat notices it only after 7.5 s) or a browser that suspended the page.
            # Its robot stopped at the edge's command timeout; another operator may now take control, as after a
            # terminal console's lease.
            reason = (f"control released: nothing from this page for {silent:.1f} s (its link dropped or the browser "
                      "suspended it): take control again")
            log.warning("%s on %s: %s", self.grant.user, self.robot, reason)
            return reason
        if not self.client.owner:
            # The lease was lost (a dead link, the edge restarted): the client said why in its events; the page
            # takes control again on purpose, with a fresh press of the deadman.
            return "control lost: take it again"
        return ""

    async def _push_video(self) -> None:
        """Each stream's frames the page has not had, while its socket has room. JPEG: the newest only. H.264: in
        order from where the page is; a page too far behind (the frames it needs are gone, or its socket is
        full) skips to the next keyframe and asks the edge for one."""
        transport = self.transport
        if not self.video_on:
            return
        for index, name in enumerate(VIDEO_STREAMS):
            for frame in list(self.feed.frames[name]):
                last = self._sent_video[name]
                if frame.seq <= last:
                    continue
                stats = self._video_stats[name]
                if frame.h264 and not frame.failure and (last < 0 or frame.seq > last + 1) and not frame.keyframe:
                    stats[1] += 1  # the frame before it never reached this page: wait for a keyframe
                    self._feedback(name, keyframe=True)
                    continue
                if not isinstance(transport, asyncio.WriteTransport) or transport.is_closing() or \
                        transport.get_write_buffer_size() > VIDEO_BACKLOG_BYTES:
                    return  # the page is behind: it gets what comes once it has drained
                self._sent_video[name] = frame.seq
                stats[0] += 1
                with contextlib.suppress(ConnectionError, RuntimeError):
                    await self.ws.send_bytes(frame.wire(index))
            if time.monotonic() - self._feedback_at[name] > 1.0:
                self._feedback(name, keyframe=False)

    def _feedback(self, stream: str, keyframe: bool) -> None:
        """Tell the edge how this page gets a stream (its H.264 bitrate follows the worst viewer)."""
        sent, skipped = self._video_stats[stream]
        if keyframe or sent or skipped:
            self.bridge.video_feedback(self.robot, self.grant, stream, keyframe, sent, skipped)
        self._video_stats[stream] = [0, 0]
        self._feedback_at[stream] = time.monotonic()

    def state(self) -> dict[str, Any]:
        """What the page shows now (the console's model, as JSON)."""
        w = self.feed.watch
        now = time.monotonic()
        st, sf = w.robot_state, w.safety
        # How old each value may be before it is shown as old: the deployment's console settings, the terminal
        # console's (the page gets each row's age from here, and the page-side bound in its hello).
        console = self.bridge.config.console
        out: dict[str, Any] = {"type": "state", "robot": self.robot, "online": bool(w.edge_alive),
                               "user": self.grant.user, "role": str(self.grant.role), "refused": self.refused}
        if st is not None:
            out["t"] = st.t
            out["age"] = round(now - w.robot_state_at, 3)
            out["tcp"] = [round(v, 5) for v in st.tcp_pose]
            out["commanded"] = [round(v, 5) for v in st.commanded]
            out["fault"] = st.fault
            out["arm"] = self.feed.arm_points()
            # "stale 2.2 s" once the newest state is older than the link's bound: the arm drawn and the speed said
            # are where the robot was then ("" while current).
            out["state_stale"] = stale_note(now - w.robot_state_at, console.state_stale_after)
        if sf is not None:
            out["safety"] = {"armed": sf.armed, "owner": sf.owner, "status": sf.status, "reason": sf.reason,
                             "profile": sf.profile, "deadman": sf.deadman, "linear_limit": sf.linear_limit,
                             "angular_limit": sf.angular_limit, "limits_hit": sf.limits_hit,
                             "contact": sf.contact_target, "task": sf.task,
                             # the edge's last word on all of these, aged once it is no longer its state
                             "stale": f"stale {w.safety_age(now):.1f} s" if w.safety_stale(now) else ""}
        fv = force_view(w.force_level, w.force_level_at, now, console.force_stale_after)
        force: dict[str, Any] = {"colour": fv.colour.replace("grey50", "grey"), "label": fv.label, "detail": fv.detail}
        if w.force is not None and st is not None and now - w.force_at <= console.force_stale_after:
            force["vector"] = [round(v, 3) for v in geometry.rotate(st.tcp_pose[3:], w.force.force)]
        out["force"] = force
        if w.vitals:  # the patient's vital signs (sensor/vital), one line as on the terminal console
            out["vitals"] = vitals_line(dict(w.vitals), now)
        if w.markers is not None:
            out.update(markers_on_page(w.markers, now - w.markers_at))
        if w.servo is not None:  # aged after three of the edge's heartbeats, as on the terminal console
            out["servo"] = {"pan": w.servo.pan, "tilt": w.servo.tilt,
                            "stale": stale_note(now - w.servo_at, actuator_stale_after(w.servo))}
        if w.torch is not None:
            out["torch"] = {"on": w.torch.on, "brightness": w.torch.brightness,
                            "stale": stale_note(now - w.torch_at, actuator_stale_after(w.torch))}
        holder = self.bridge.controllers.get(self.robot)
        # s without a new picture after which the page shows each stream's last one as not live (the page times
        # the pictures it gets: a link to it that dies stops them too)
        out["picture_stale_s"] = {name: round(picture_stale_after(self.feed.frame_period[name]), 3)
                                  for name in VIDEO_STREAMS}
        # "elsewhere": the user of another page of this console that holds control ("" if none does)
        out["control"] = {"mine": self.client is not None and self.client.owner,
                          "elsewhere": holder.grant.user if holder is not None and holder is not self else ""}
        if self.grant.may_command(self.robot) and holder is not None and holder is not self:
            # One driver: another page of this console holds control (the same user's other device or tab, or
            # another user's); "Take control" here is refused, so the page says who holds it and where.
            who = "you hold" if holder.grant.user == self.grant.user else f"{holder.grant.user} holds"
            out["hint"] = (f"{who} control of {self.robot} from another page (another device or tab): it must be "
                           "released there before this page can take it")
        elif self.grant.may_command(self.robot):
            # What stands between this page and motion, with the page's own controls named.
            step = self.client.next_step() if self.client is not None else recovery.NextStep(
                recovery.Step.ACQUIRE, "this page does not hold control")
            out["hint"] = recovery.hint(step, "Take control", "HOLD", toggle=False)
        events = self._new_events("watch", w.events)
        if self.client is not None:
            q = self.client.link_quality(state_stale_after=console.state_stale_after)
            grades = q.grades(console.link)
            out["link"] = {"rtt_p50": _finite(q.rtt_p50_ms), "rtt_p95": _finite(q.rtt_p95_ms),
                           "loss_up": _finite(q.uplink_loss), "loss_down": _finite(q.downlink_loss),
                           "no_state": q.no_state_s,  # s without robot state: the link is dead, not slow
                           "rtt_old": q.rtt_old_s,  # s since the newest echo, when the round trips are that old
                           "colour": GRADE_COLOURS[max(grades.values(), key=_grade_rank)]}
            events += self._new_events("client", self.client.events)
        if events:
            out["events"] = [{"t": e.t, "kind": e.kind, "status": str(e.status), "reason": e.reason} for e in events]
        return out

    def _new_events(self, source: str, events: deque[Event]) -> list[Event]:
        """The events of ``source`` this page has not been sent yet (oldest first)."""
        last = self._last_events[source]
        items = list(events)
        if last is not None and any(e is last for e in items):
            i = max(i for i, e in enumerate(items) if e is last)
            items = items[i + 1:]
        elif last is None:
            items = items[-20:]  # a page that just opened: the latest ones
        if items:
            self._last_events[source] = items[-1]
        return items

    async def end(self, code: int, reason: str) -> None:
        """Close the page's socket, saying why; its handler then releases control (the robot stops)."""
        await self.send({"type": "refused", "kind": "ended", "reason": reason})
        with contextlib.suppress(ConnectionError, RuntimeError):
            await self.ws.close(code=code, message=reason.encode()[:120])

    def close(self) -> None:
        self.closed = True
        self.feed.pages.discard(self)
        self._release()


def markers_on_page(markers: Markers, age: float) -> dict[str, Any]:
    """The markers the page draws, ``age`` s after they arrived, or why none (console.model.markers_note: the
    terminal console's rule; ``markers_failed``: the page shows it as a failure)."""
    note, failed = markers_note(markers.failure, age)
    if failed:
        return {"markers_note": note, "markers_failed": True}
    if note:
        return {"markers_note": note}
    return {"markers": [{"id": m.id, "pose": [round(v, 4) for v in m.pose]} for m in markers.markers]}


def _grade_rank(grade: str) -> int:
    return {"none": 0, "good": 1, "warn": 2, "bad": 3}[grade]


def _finite(v: float) -> float | None:
    return round(v, 3) if math.isfinite(v) else None


def _json_default(value: Any) -> Any:
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON")


def _json_object(text: str) -> dict[str, Any]:
    try:
        obj = json.loads(text) if text else {}
    except ValueError:
        return {}
    return obj if isinstance(obj, dict) else {}


# ----------------------------------------------------------------------------------------------- the HTTP side


def make_app(bridge: Bridge) -> web.Application:
    app = web.Application(client_max_size=16 * 1024, middlewares=[_headers, _known_host])
    app["bridge"] = bridge
    app.add_routes([
        web.get("/", _index),
        web.get("/login", _login_page),
        web.post("/api/login", _login),
        web.post("/api/logout", _logout),
        web.get("/api/me", _me),
        web.get("/api/stats", _stats),
        web.get("/ws", _websocket),
        web.static("/static", STATIC, show_index=False),
    ])
    app.on_startup.append(_on_startup)
    app.on_shutdown.append(_on_shutdown)
    return app


@web.middleware
async def _headers(request: web.Request, handler: Callable[[web.Request], Any]) -> web.StreamResponse:
    try:
        response = await handler(request)
    except web.HTTPException as exc:  # redirects, 401s, 403s and 404s carry the headers too
        response = exc
    if not response.prepared:
        response.headers.update(SECURITY_HEADERS)
        # A browser that came once over HTTPS (to us, or to the proxy in front) never tries plain HTTP here again.
        if request.app["bridge"].peer(request).https:
            response.headers["Strict-Transport-Security"] = "max-age=31536000"
        if request.path.startswith("/api/") or request.path == "/":
            response.headers["Cache-Control"] = "no-store"
    if isinstance(response, web.HTTPException):
        raise response
    return response


@web.middleware
async def _known_host(request: web.Request, handler: Callable[[web.Request], Any]) -> web.StreamResponse:
    bridge: Bridge = request.app["bridge"]
    if not host_allowed(request.host, bridge.host_names):
        bridge.refusals.add("unknown_host", f"{request.host[:80]!r} from {bridge.peer(request).address}")
        raise web.HTTPMisdirectedRequest(text=f"this console does not answer to host {request.host[:80]!r}: open it "
                                         "by its own name (server_names in its config lists more)")
    return await handler(request)


async def _on_startup(app: web.Application) -> None:
    bridge: Bridge = app["bridge"]
    loop = asyncio.get_running_loop()
    await loop.run_in_executor(None, bridge.start, loop)
    app["pages"] = set()


async def _on_shutdown(app: web.Application) -> None:
    for ws in list(app["pages"]):
        await ws.close(code=1001, message=b"server shutting down")
    await asyncio.get_running_loop().run_in_executor(None, app["bridge"].close)


async def _index(request: web.Request) -> web.StreamResponse:
    if request.app["bridge"].user_of(request) is None:
        raise web.HTTPSeeOther("/login")
    return web.FileResponse(STATIC / "index.html")


async def _login_page(_request: web.Request) -> web.StreamResponse:
    return web.FileResponse(STATIC / "login.html")


async def _login(request: web.Request) -> web.StreamResponse:
    bridge: Bridge = request.app["bridge"]
    if not bridge.origin_ok(request):
        bridge.refusals.add("cross_origin", request.headers.get("Origin", "(none)"))
        return web.json_response({"ok": False, "reason": "log-in from another site refused"}, status=403)
    try:
        body = await request.json()
        user, password = str(body["user"])[:64], str(body["password"])[:256]
    except (ValueError, KeyError, TypeError):
        return web.json_response({"ok": False, "reason": "send a user name and a password"}, status=400)
    peer = bridge.peer(request)
    token, why = await asyncio.get_running_loop().run_in_executor(
        bridge.login_pool, bridge.log_in, user, password, peer.address)
    if not token:
        return web.json_response({"ok": False, "reason": why}, status=401)
    response = web.json_response({"ok": True, "user": user})
    response.set_cookie(COOKIE, token, httponly=True, samesite="Strict", secure=peer.https, path="/",
                        max_age=int(3600 * bridge.config.session_hours))
    return response


async def _logout(request: web.Request) -> web.StreamResponse:
    """Ends the log-in: its pages are closed (a page that holds control releases it, the robot stops)."""
    bridge: Bridge = request.app["bridge"]
    if not bridge.origin_ok(request):
        bridge.refusals.add("cross_origin", request.headers.get("Origin", "(none)"))
        return web.json_response({"ok": False, "reason": "log-out from another site refused"}, status=403)
    token = request.cookies.get(COOKIE, "")
    bridge.logins.pop(token, None)
    for page in bridge.pages():  # a snapshot: a feed may open, a page close, while one page's end is awaited
        if token and page.token == token:
            await page.end(4401, "logged out")
    response = web.json_response({"ok": True})
    response.del_cookie(COOKIE, path="/")
    return response


async def _me(request: web.Request) -> web.StreamResponse:
    grant = request.app["bridge"].user_of(request)
    if grant is None:
        return web.json_response({"ok": False, "reason": "not logged in"}, status=401)
    return web.json_response({"ok": True, "user": grant.user, "role": str(grant.role), "robots": list(grant.robots)})


async def _stats(request: web.Request) -> web.StreamResponse:
    bridge: Bridge = request.app["bridge"]
    grant = bridge.user_of(request)
    if grant is None:
        return web.json_response({"ok": False, "reason": "not logged in"}, status=401)
    # Who watches and who drives: only for the robots this user may watch (an operator sees his own robots).
    pages = [{"user": p.grant.user, "robot": p.robot, "controlling": p.client is not None}
             for f in bridge.feeds.values() if grant.may_watch(f.robot) for p in f.pages]
    return web.json_response({"ok": True, "refused": dict(bridge.refusals.counts), "pages": pages,
                              "controllers": {r: p.grant.user for r, p in bridge.controllers.items()
                                              if grant.may_watch(r)}})


async def _websocket(request: web.Request) -> web.StreamResponse:
    bridge: Bridge = request.app["bridge"]
    # Refused before the upgrade, with the reason as the HTTP answer (a browser's page sees the socket fail).
    if not bridge.origin_ok(request):
        bridge.refusals.add("cross_origin", request.headers.get("Origin", "(none)"))
        raise web.HTTPForbidden(text="websocket from another origin refused")
    grant = bridge.user_of(request)
    if grant is None:
        bridge.refusals.add("not_logged_in", bridge.peer(request).address)
        raise web.HTTPUnauthorized(text="not logged in")
    robot = request.query.get("robot", "") or (grant.robots[0] if grant.robots else "")
    if not grant.may_watch(robot):
        bridge.refusals.add("robot_not_granted", f"{grant.user} asked for {robot[:40]!r}")
        raise web.HTTPForbidden(text=f"{grant.user} is not granted robot {robot[:40]!r}")
    ws = web.WebSocketResponse(max_msg_size=WS_MAX_BYTES, heartbeat=5.0)
    await ws.prepare(request)
    token = request.cookies.get(COOKIE, "")
    # Counted after the upgrade (no await between the count and the page's adding: pages opened at once are
    # counted one by one), refused on the socket with the reason, which the page shows.
    too_many = bridge.page_refused(token, grant.user)
    if too_many:
        bridge.refusals.add("too_many_pages", f"{grant.user}: {too_many}")
        with contextlib.suppress(ConnectionError, RuntimeError):
            await ws.send_str(json.dumps({"type": "refused", "kind": "too_many_pages", "reason": too_many}))
            await ws.close(code=PAGES_CLOSE_CODE, message=too_many.encode()[:120])
        return ws
    request.app["pages"].add(ws)
    feed = bridge.feed(robot)
    page = Page(bridge, ws, grant, feed, request.transport, token=token)
    feed.pages.add(page)
    await page.send({"type": "hello", "user": grant.user, "role": str(grant.role), "robot": robot,
                     "robots": list(grant.robots), "may_command": grant.may_command(robot),
                     "twist_hz": bridge.config.twist_hz,
                     # no state message from this server for this long: everything on the page is that old
                     "state_stale_s": bridge.config.console.state_stale_after,
                     # the profiles the operator chooses from, and the camera's step, as on the terminal console
                     "profiles": bridge.config.console.profiles,
                     "pan_tilt_step_deg": bridge.config.console.pan_tilt_step_deg})
    pusher = asyncio.create_task(page.push())
    try:
        async for msg in ws:
            page.heard_at = time.monotonic()
            pause = page.budgets.reading.delay(page.heard_at)
            if pause:  # a flooding page: read it no faster (the socket's buffers then hold its sender back)
                await asyncio.sleep(pause)
            if msg.type == WSMsgType.TEXT:
                await page.on_text(msg.data)
            elif msg.type == WSMsgType.BINARY:
                await page.refuse("malformed", "binary messages are not accepted")
            elif msg.type == WSMsgType.ERROR:
                bridge.refusals.add("socket_error", str(ws.exception()))
                break
    finally:
        pusher.cancel()
        request.app["pages"].discard(ws)
        # Releasing control is a blocking query: off the event loop. The robot already stops on its own: this
        # page's stream ended, and the edge's deadman timeout sees that.
        await asyncio.get_running_loop().run_in_executor(None, page.close)
    return ws


def load_bridge(config: WebConfig) -> Bridge:
    """The deployment and the users file, checked (ConfigError / ValueError naming the file)."""
    deployment = config_from_dict(read_yaml(config.deployment), Deployment, source=str(config.deployment),
                                  base_dir=config.deployment.parent)
    try:
        text = config.users_file.read_text()
    except FileNotFoundError:
        raise ValueError(f"{config.users_file}: no web users yet: add one with `iorthand web password NAME`") from None
    hashes = users.parse_users(text, str(config.users_file))
    unknown = sorted(set(hashes) - set(users.grants(deployment)))
    for name in unknown:
        log.warning("%s: user %r is neither an operator nor a viewer of %s: cannot log in", config.users_file, name,
                    config.deployment)
    return Bridge(config, deployment, hashes)


def serve(config: WebConfig, ready: Callable[[str], None] | None = None) -> None:
    """Run the console until SIGINT/SIGTERM."""
    config.check()
    bridge = load_bridge(config)
    host, port = config.host_port()
    context = None
    if config.tls is not None:
        context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        context.load_cert_chain(config.tls.certificate, config.tls.private_key)
    url = f"{'https' if context else 'http'}://{host}:{port}/"

    async def announce(_app: web.Application) -> None:
        log.info("web console ready: %s", url)
        if ready is not None:
            ready(url)

    app = make_app(bridge)
    app.on_startup.append(announce)
    web.run_app(app, host=host, port=port, ssl_context=context, print=None, access_log=None,
                handle_signals=True, shutdown_timeout=3.0)


__all__ = ["Bridge", "Feed", "Page", "load_bridge", "make_app", "serve"]
