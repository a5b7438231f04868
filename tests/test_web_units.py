"""The web console's pure parts: who may log in and do what, and what a page may send."""

from __future__ import annotations

import json
import re
import struct

import pytest

from iorthand.protocol import MarkerPose, Markers
from iorthand.security.acl import Deployment
from iorthand.security.hosts import host_allowed
from iorthand_operator.client import MARKERS_SHOWN_S
from iorthand_operator.console.model import picture_stale_after
from iorthand_operator.web import messages, users
from iorthand_operator.web.config import WebConfig
from iorthand_operator.web.server import Frame, markers_on_page


def test_grants_follow_the_deployment_as_the_routers_acl_does() -> None:
    dep = Deployment(robots=["r1", "r2"], operators={"alice": ["r1"]}, viewers=["sam"])
    g = users.grants(dep)
    assert g["alice"].may_command("r1") and not g["alice"].may_command("r2") and not g["alice"].may_watch("r2")
    assert g["sam"].may_watch("r1") and g["sam"].may_watch("r2")
    assert not g["sam"].may_command("r1")  # a viewer moves nothing
    assert "mallory" not in g


def test_passwords_are_stored_as_scrypt_hashes_and_checked_in_constant_time() -> None:
    stored = users.hash_password("correct horse")
    assert stored.startswith("scrypt$") and "correct horse" not in stored
    assert users.check_password("correct horse", stored)
    assert not users.check_password("correct hors", stored)
    assert not users.check_password("x", "scrypt$bad")  # a damaged entry matches nothing
    assert users.hash_password("pw", b"\0" * 16) == users.hash_password("pw", b"\0" * 16)
    with pytest.raises(ValueError):
        users.hash_password("")


def test_the_users_file_round_trips_and_names_a_bad_line() -> None:
    text = users.format_users({"alice": users.hash_password("a-long-pw")})
    assert list(users.parse_users(text)) == ["alice"]
    with pytest.raises(ValueError, match="line 2"):
        users.parse_users("# comment\nalice:plaintext\n")
    with pytest.raises(ValueError):
        users.parse_users("Bad Name:scrypt$1$1$1$AA==$AA==\n")


def test_log_ins_from_an_address_are_refused_after_repeated_failures() -> None:
    guard = users.LoginGuard(max_failures=3, window=60.0)
    for i in range(3):
        assert guard.blocked("1.2.3.4", 100.0 + i) == 0
        guard.failed("1.2.3.4", 100.0 + i)
    assert guard.blocked("1.2.3.4", 103.0) == pytest.approx(57.0)
    assert guard.blocked("5.6.7.8", 103.0) == 0  # another address is not punished
    assert guard.blocked("1.2.3.4", 161.0) == 0  # the window passed


def test_a_valid_log_in_clears_no_other_failures_and_guessing_one_account_is_limited_from_anywhere() -> None:
    """Found by a red-team run: one viewer's valid log-in cleared its address's failed guesses at another account
    (24 of 24 guesses checked), the limit was per address only, and 24 attempts sent at once got 9 checks."""
    guard = users.LoginGuard(max_failures=3, window=60.0, max_user_failures=5)
    assert guard.attempt("1.2.3.4", "physician", 100.0) == 0
    assert guard.attempt("1.2.3.4", "student", 100.5) == 0
    guard.succeeded("1.2.3.4", "student", 100.5)  # the student's own attempt is taken back, nothing else
    assert guard.attempt("1.2.3.4", "physician", 101.0) == 0
    assert guard.attempt("1.2.3.4", "physician", 102.0) == 0
    assert guard.attempt("1.2.3.4", "student", 103.0) == pytest.approx(57.0)  # 3 failures: the address waits
    # Attempts are counted when let through, before their password is checked: at once, only the limit passes.
    assert sum(guard.attempt("9.9.9.9", "nurse", 200.0) == 0 for _ in range(24)) == 3
    # One account guessed at from many addresses: once it has 5 failures, only an address with no failure of its
    # own gets a try, 5 such tries a window at most: refused from the 11th on, whichever address asks.
    passed = [guard.attempt(f"10.0.0.{i}", "physician", 300.0 + i) == 0 for i in range(30)]
    assert passed == [True] * 10 + [False] * 20
    assert guard.attempt("10.0.0.99", "student", 310.0) == 0  # other accounts are not locked by it


def test_behind_a_trusted_proxy_the_browser_is_who_the_proxy_says_and_nobody_else_is_believed() -> None:
    """Behind the reverse proxy DEPLOY.md describes, every request comes from the proxy's address: one user's five
    wrong passwords locked every user out for a minute, and the session cookie lost its Secure flag."""
    trusted = ["127.0.0.1", "::1"]
    proxied = {"X-Forwarded-For": "6.6.6.6, 203.0.113.9", "X-Forwarded-Proto": "https"}
    # The address the proxy appended (the last one); the ones before it are the client's own claims.
    assert users.peer_of("127.0.0.1", False, proxied, trusted) == users.Peer("203.0.113.9", True)
    assert users.peer_of("::1", False, {"X-Forwarded-For": "2001:db8::7"}, trusted) == users.Peer("2001:db8::7", False)
    # Forwarding headers from anyone else are ignored: nobody can pick the address their failures count against.
    assert users.peer_of("198.51.100.4", False, proxied, trusted) == users.Peer("198.51.100.4", False)
    assert users.peer_of("127.0.0.1", True, proxied, []) == users.Peer("127.0.0.1", True)
    # Garbage for an address keeps the proxy's own (the shared, stricter limit); no header: the connection's.
    assert users.peer_of("127.0.0.1", False, {"X-Forwarded-For": "<script>"}, trusted).address == "127.0.0.1"
    assert users.peer_of("127.0.0.1", False, {}, trusted) == users.Peer("127.0.0.1", False)
    with pytest.raises(ValueError, match=re.escape("trusted_proxies: 'proxy.local' is not an IP address")):
        WebConfig(trusted_proxies=["proxy.local"]).check()


def test_one_users_log_ins_end_only_that_users_oldest_never_anothers(monkeypatch) -> None:
    """Found by a red-team run: a viewer logging in over and over filled the table of log-ins, and at its size the
    oldest log-in was evicted whoever it was: the driving physician's page ended, and its control."""
    from iorthand_operator.web import server

    monkeypatch.setattr(server, "MAX_SESSIONS", 12)
    monkeypatch.setattr(server, "MAX_LOGINS_PER_USER", 4)
    dep = Deployment(robots=["r1"], operators={"alice": ["r1"]}, viewers=["sam"])
    bridge = server.Bridge(WebConfig(), dep, {"alice": users.hash_password("alice-pw"),
                                              "sam": users.hash_password("sam-pw")})
    try:
        alice, _ = bridge.log_in("alice", "alice-pw", "10.0.0.1")
        sams = [bridge.log_in("sam", "sam-pw", "10.0.0.2")[0] for _ in range(20)]
        assert all(sams) and bridge.logged_in(alice)
        assert [bridge.logged_in(t) for t in sams] == [False] * 16 + [True] * 4  # his newest four
    finally:
        bridge.login_pool.shutdown()


def test_deeply_nested_json_is_refused_by_name() -> None:
    with pytest.raises(messages.PageError, match="nested too deeply"):
        messages.parse("[" * 1023 + "]" * 1023)


def test_rate_budgets_pass_a_burst_then_their_rate_and_pace_without_refusing() -> None:
    b = messages.RateBudget(rate=5.0, burst=1.0)
    assert [b.allow(10.0), b.allow(10.05), b.allow(10.25), b.allow(10.3)] == [True, False, True, False]
    pace = messages.RateBudget(rate=100.0, burst=2.0)
    waits = [pace.delay(0.0) for _ in range(5)]
    assert waits[:2] == [0.0, 0.0] and waits[2:] == pytest.approx([0.01, 0.02, 0.03])


def test_a_refusal_is_said_once_a_second_and_few_are_remembered() -> None:
    notices = messages.Notices(remember=3)
    assert [notices.due("a", 0.0), notices.due("a", 0.5), notices.due("a", 1.0)] == [True, False, True]
    assert [notices.due(t, 1.1) for t in ("b", "c", "d")] == [True, True, False]  # 3 remembered, all recent
    assert notices.due("d", 2.2) and len(notices._said) <= 3  # the old ones forgotten, not piled up


def twist(**changes: object) -> str:
    data = {"type": "twist", "id": 7, "linear": [0.001, 0, 0], "angular": [0, 0, 0.05], "deadman": True, "seen": 5}
    data.update(changes)
    return json.dumps(data)


def test_a_twist_message_parses_to_si_velocities() -> None:
    m = messages.parse(twist())
    assert m == messages.Twist(7, (0.001, 0.0, 0.0), (0.0, 0.0, 0.05), True, 5)


@pytest.mark.parametrize(("data", "problem"), [
    ("{", "not JSON"),
    ("[1, 2]", "expected a JSON object"),
    (json.dumps({"type": "fly"}), "unknown message type 'fly'"),
    (twist(linear=[0, 0]), "linear: expected 3 numbers"),
    (twist(linear=[2.0, 0, 0]), "linear: expected a finite number within ±1"),
    (twist(angular=[0, "x", 0]), "angular: expected a finite number"),
    (twist(deadman=1), "deadman: expected true or false"),
    (twist(id=-1), "id: expected a whole number"),
    (twist(id=True), "id: expected a whole number"),
    (twist(extra=1), "extra: unknown field of a twist message"),
    (json.dumps({"type": "preview", "name": ""}), "name: must not be empty"),
    (json.dumps({"type": "goto", "name": "home", "token": "t" * 200}), "token: expected text of at most 128"),
    (json.dumps({"type": "camera", "pan": 3.0}), "pan: expected a finite number within ±1.5708"),
    (json.dumps({"type": "camera", "torch": "on"}), "torch: expected true, false or nothing"),
    ("x" * (messages.MAX_MESSAGE_BYTES + 1), "exceeds 2048"),
])
def test_bad_page_messages_are_refused_by_name(data: str, problem: str) -> None:
    with pytest.raises(messages.PageError, match=re.escape(problem)):
        messages.parse(data)


def test_nan_and_infinity_never_pass() -> None:
    for bad in ("NaN", "Infinity", "-Infinity"):
        with pytest.raises(messages.PageError, match="finite"):
            messages.parse(twist().replace("[0.001, 0, 0]", f"[{bad}, 0, 0]"))


def _held(i: int, deadman: bool = True) -> messages.Twist:
    return messages.Twist(i, (0.001, 0.0, 0.0) if deadman else (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), deadman, 0)


def test_a_page_at_its_rate_is_never_held_back_even_with_late_ticks() -> None:
    budget = messages.TwistBudget(60.0)
    t, passed = 100.0, 0
    for i in range(6000):  # 100 s; every tenth tick 50 ms late, the next ones close behind (a busy browser)
        t += 0.05 if i % 10 == 0 else 1 / 60 - 0.0037
        passed += budget.allow(_held(i), t)
    assert passed == 6000


def test_a_flooding_page_gets_twice_its_rate_through_and_still_lets_go() -> None:
    budget = messages.TwistBudget(60.0)
    sent = [budget.allow(_held(i), 10.0 + i * 1e-4) for i in range(10_000)]  # 10 000 a second, for 1 s
    # A quarter second's worth at once, then 120 a second.
    assert 30 + 120 - 2 <= sum(sent) <= 30 + 120 + 1, sum(sent)
    assert not sent[-1]
    # Over budget, the first release after a held twist still goes (letting go must reach the robot) ...
    assert budget.allow(_held(10_001, deadman=False), 11.0)
    # ... but not a stream of releases: once released, the budget holds for them too.
    assert not any(budget.allow(_held(10_002 + i, deadman=False), 11.0) for i in range(100))
    assert budget.allow(_held(20_000), 12.0)  # a second later the page has its budget back


def test_a_request_may_name_only_the_hosts_the_console_answers_to() -> None:
    """Against DNS rebinding (test_web_console has it with a browser): the Host header names one of the console's
    names, any port (a relay or a NAT may change it)."""
    local = WebConfig(listen="127.0.0.1:8443").host_names()
    assert {"127.0.0.1", "localhost", "::1"} <= local
    for host in ("127.0.0.1:8443", "LOCALHOST:9000", "[::1]:8443", "localhost"):
        assert host_allowed(host, local), host
    for host in ("evil.example:8443", "127.0.0.1.evil.example", "", "[::1", "localhost.evil"):
        assert not host_allowed(host, local), host
    served = WebConfig(listen="0.0.0.0:8443", server_names=["Robot-1.hospital.org"],
                       allowed_origins=["https://console.hospital.org:4443"])
    names = served.host_names(["*.ward.hospital.org", "10.0.0.7"])
    assert "localhost" not in names  # not on loopback: a browser on this host opens it by a name it has
    for host in ("robot-1.hospital.org:8443", "console.hospital.org", "scanner.ward.hospital.org", "10.0.0.7:8443",
                 "robot-1.hospital.org."):
        assert host_allowed(host, names), host
    for host in ("a.b.ward.hospital.org", "ward.hospital.org", "localhost:8443", "10.0.0.8"):
        assert not host_allowed(host, names), host


def test_a_console_reachable_from_the_network_needs_tls() -> None:
    WebConfig(listen="127.0.0.1:8443").check()
    WebConfig(listen="[::1]:8443").check()
    with pytest.raises(ValueError, match="needs tls"):
        WebConfig(listen="0.0.0.0:8443").check()
    with pytest.raises(ValueError, match="HOST:PORT"):
        WebConfig(listen="8443").check()
    with pytest.raises(ValueError, match="is not an origin"):
        WebConfig(allowed_origins=["https://proxy.example/"]).check()


def test_by_default_no_address_is_a_trusted_proxy_not_even_loopback() -> None:
    """Found by a red-team run (e7): loopback was a trusted proxy by default, so on a console listening on loopback
    and reached through an ssh tunnel (or by any local process) a client naming a new X-Forwarded-For each time had
    20 password guesses a minute instead of 5. A proxy is now trusted only when listed."""
    forged = {"X-Forwarded-For": "10.9.0.1", "X-Forwarded-Proto": "https"}
    default = WebConfig().trusted_proxies
    assert users.peer_of("127.0.0.1", False, forged, default) == users.Peer("127.0.0.1", False)
    assert users.peer_of("::1", False, forged, default) == users.Peer("::1", False)
    assert users.peer_of("127.0.0.1", False, forged, ["127.0.0.1"]) == users.Peer("10.9.0.1", True)  # listed


def test_an_account_under_attack_stays_open_to_its_user_from_a_clean_address() -> None:
    """Found by a red-team run (e7): the account's lock (20 failures a minute, from anywhere) was checked before
    the password, so anyone could lock the physician out with 20 wrong passwords a minute. Through the server's own
    log-in: the attacker's addresses stay refused, the physician from a clean address logs in."""
    from iorthand_operator.web import server

    dep = Deployment(robots=["r1"], operators={"alice": ["r1"]}, viewers=["sam"])
    bridge = server.Bridge(WebConfig(), dep, {"alice": users.hash_password("alice-pw"),
                                              "sam": users.hash_password("sam-pw")})
    try:
        # 20 wrong passwords from 4 addresses, 5 each: the account's limit, each address's limit.
        for a in range(4):
            for i in range(5):
                token, why = bridge.log_in("alice", f"guess-{a}-{i}", f"203.0.113.{a}")
                assert not token and why == "wrong user name or password", why
        # The attacker's further guesses are refused unchecked, the right password included.
        for a in range(4):
            token, why = bridge.log_in("alice", "alice-pw", f"203.0.113.{a}")
            assert not token and why.startswith("too many failed log-ins"), why
        # The physician, from an address that has not failed: in.
        token, why = bridge.log_in("alice", "alice-pw", "192.0.2.10")
        assert token and not why and bridge.logins[token].user == "alice"
        # An address that failed once at another account waits while this one is under attack.
        assert not bridge.log_in("sam", "wrong", "192.0.2.11")[0]
        token, why = bridge.log_in("alice", "alice-pw", "192.0.2.11")
        assert not token and why.startswith("too many failed log-ins"), why
    finally:
        bridge.login_pool.shutdown()
    # Clean addresses' tries at a locked account are limited too: guessing it stays bounded.
    guard = users.LoginGuard(max_failures=5, window=60.0, max_user_failures=20)
    for i in range(20):
        assert guard.attempt(f"203.0.113.{i}", "alice", 100.0) == 0
    clean = [guard.attempt(f"198.51.100.{i}", "alice", 101.0) == 0 for i in range(30)]
    assert clean == [True] * 20 + [False] * 10
    assert guard.attempt("192.0.2.1", "alice", 161.0) == 0  # the window passed


def test_a_camera_failure_is_a_note_on_the_page_never_an_empty_view_of_markers() -> None:
    """The edge's Markers with ``failure`` set (no markers, and why) is said as the terminal console says it, fresh
    or old; markers that arrive are drawn until MARKERS_SHOWN_S, then said to be that old."""
    failed = Markers(failure="camera /dev/video0: no frame for 2.0 s")
    for age in (0.0, MARKERS_SHOWN_S + 5.0):
        assert markers_on_page(failed, age) == {"markers_note": "camera failed: camera /dev/video0: no frame for 2.0 s",
                                                "markers_failed": True}
    seen = Markers(markers=[MarkerPose(id=3)])
    assert [m["id"] for m in markers_on_page(seen, 0.0)["markers"]] == [3]
    assert markers_on_page(seen, MARKERS_SHOWN_S + 0.5) == {"markers_note": f"no marker data for {MARKERS_SHOWN_S + 0.5:.1f} s"}


def test_a_video_failure_notice_goes_to_the_page_with_its_reason() -> None:
    """A frame's wire form: the 14-byte header, then its data; a failure notice's flag (bit 2) and its reason in
    place of data, which the page shows where the picture was."""
    notice = Frame(seq=7, t=123, data=b"", failure="USB camera unplugged")
    wire = notice.wire(0)
    stream, t, seq, flags = struct.unpack(">BQIB", wire[:14])
    assert (stream, t, seq, flags) == (0, 123, 7, 4)
    assert wire[14:].decode() == "USB camera unplugged"
    picture = Frame(seq=8, t=124, data=b"\xff\xd8jpeg", h264=True, keyframe=True).wire(1)
    assert struct.unpack(">BQIB", picture[:14]) == (1, 124, 8, 3) and picture[14:] == b"\xff\xd8jpeg"


def test_a_pictures_bound_for_live_is_three_of_its_streams_frame_periods_and_at_least_a_second() -> None:
    assert picture_stale_after(0.0) == MARKERS_SHOWN_S  # no period known yet
    assert picture_stale_after(0.1) == MARKERS_SHOWN_S  # 10 fps: one lost frame must not blink the picture off
    assert picture_stale_after(1.0) == pytest.approx(3.0)  # 1 fps: three periods


def test_the_console_measures_each_video_streams_frame_period_from_its_frames(router_endpoint) -> None:
    """The page's bound for a live picture follows the stream's rate (a frame lost on the way is a gap in the
    sequence, not a longer period): measured on the console's feed from real frames through a real router."""
    import asyncio
    import time

    from iorthand import keys
    from iorthand.protocol import VideoFrame
    from iorthand.transport import client_config, open_session
    from iorthand_operator.web.server import Feed

    session = open_session(client_config(router_endpoint))
    loop = asyncio.new_event_loop()
    feed = Feed(session, "r1", "ur3e", loop)
    pub = session.declare_publisher(keys.RobotKeys("r1").key(keys.VIDEO_ULTRASOUND))
    try:
        time.sleep(0.3)  # the subscription reaches the router
        t0 = time.time_ns()
        for seq in (1, 2, 4):  # 2 fps; frame 3 lost on the way
            pub.put(VideoFrame(source="ultrasound", width=4, height=4, data=b"jpeg").stamp(seq, t0 + seq * 500_000_000)
                    .encode())
        deadline = time.monotonic() + 5.0
        while feed.frame_period["ultrasound"] == 0.0 or len(feed._last_picture) == 0 or \
                feed._last_picture["ultrasound"][0] != 4:
            assert time.monotonic() < deadline, "the frames did not arrive"
            time.sleep(0.01)
        assert feed.frame_period["ultrasound"] == pytest.approx(0.5)
        assert picture_stale_after(feed.frame_period["ultrasound"]) == pytest.approx(1.5)
        assert feed.frame_period["camera"] == 0.0
    finally:
        pub.undeclare()
        feed.close()
        session.close()
        loop.close()
