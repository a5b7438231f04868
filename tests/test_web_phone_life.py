"""The web console through a phone's day (``iorthand web`` in Debian's Chromium driven by Playwright, a real router,
edge and web server): the screen locked or the app sent to the background while HOLD is held, the network lost for
two seconds, a reload, the same physician on two devices, the back button; and the deployment's console settings
(the terminal console's ``console:`` section) reaching the page.

What a phone does that headless Chromium cannot, the test does as the browser would, and says so where it does:
CDP's ``Page.setWebLifecycleState`` (frozen) leaves a visible headless page running (measured: its timers went on
at 100 a second and no ``freeze`` event came), so a frozen page is the page's clock stopped (Playwright's clock: no
timer runs, nothing is sent) and, as Chrome does when it freezes a page, its ``freeze`` event.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from typing import Any

import pytest
import zenoh

from iorthand import keys
from iorthand.protocol import ServoCommand, ServoState
from tests.test_web_console import (
    ARGS,
    CHROMIUM,
    ROBOT,
    TWIST_HOOK,
    Fingers,
    Stack,
    _require_browser,
    drive,
    open_console,
)

# serial: the pages draw in software and stream at 60 Hz; a page letting go must stop the robot within the edge's
# deadman timeout, and a controlling page must not fall silent for the server's page_silence by the machine's load.
pytestmark = [pytest.mark.slow, pytest.mark.serial]

# The deployment's console section, each value not the default: the order of the profiles (remote first by
# default) and the camera's step (5° by default).
CONSOLE = {"profiles": ["local", "remote"], "pan_tilt_step_deg": 2.0}


@pytest.fixture(scope="module")
def stack(tmp_path_factory) -> Any:
    s = Stack(tmp_path_factory.mktemp("web-phone"), web={"console": CONSOLE})
    yield s
    s.close()


@pytest.fixture(scope="module")
def browser(stack) -> Any:
    sync_playwright = _require_browser()
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS)
        yield b
        b.close()


def _twists(page, since: int) -> list[dict]:
    return page.evaluate(f"window.__twists.slice({since})")


def _events(page) -> str:
    return page.inner_text("#events")


def _held(page) -> bool:
    return "held" in (page.get_attribute("#deadman", "class") or "").split()


def _fresh_press_moves(stack, page, fingers: Fingers) -> None:
    """The fingers lifted, HOLD pressed anew and the stick pushed again (a release centres the sticks): the robot
    moves again."""
    fingers.lift(1)
    fingers.lift(0)
    time.sleep(0.1)
    w = stack.watch
    again = time.time_ns()
    drive(page, fingers, 1.0, 0.0)
    w.wait(lambda: len(w.moving_echoes(again)) > 10, 5.0, "a fresh press moving the robot again")


def test_the_deployments_console_settings_reach_the_page(stack, browser) -> None:
    """Found: the web console used the default console settings, whatever the deployment's console: section said
    (the terminal console reads it). Now the web config's console: section is read by the same dataclass: here its
    profiles (in its order) are the page's choices, and its camera step is what a pan button sends."""
    page = open_console(browser, stack.url)
    servo: list[ServoState] = []
    commands: list[ServoCommand] = []
    lock = threading.Lock()

    def on(sample: zenoh.Sample, into: list, cls: Any) -> None:
        with lock:
            into.append(cls.decode(sample.payload.to_bytes()))

    k = keys.RobotKeys(ROBOT)
    subs = [stack.session.declare_subscriber(k.key(keys.STATE_SERVO), lambda s: on(s, servo, ServoState)),
            stack.session.declare_subscriber(k.key(keys.CMD_SERVO), lambda s: on(s, commands, ServoCommand))]
    try:
        assert page.evaluate("[...document.getElementById('profile').options].map((o) => o.value)") == \
            CONSOLE["profiles"]
        stack.watch.wait(lambda: servo, 10.0, "the servos' state")
        with lock:
            target = servo[-1].pan_target
        direction = -1 if target > 0 else 1  # away from the end of its range (the client clamps to ±90°)
        page.click("details summary")
        page.click(f"[data-pan='{direction}']")
        stack.watch.wait(lambda: commands, 10.0, "the page's servo command")
        with lock:
            sent = commands[0]
        step = math.radians(CONSOLE["pan_tilt_step_deg"])
        assert sent.pan == pytest.approx(target + direction * step, abs=1e-6), (sent, target)
        assert sent.tilt is None
    finally:
        for sub in subs:
            sub.undeclare()
        page.context.close()


@pytest.mark.parametrize("how", ["freeze event", "no event"])
def test_a_page_frozen_while_hold_is_held_stops_and_needs_a_fresh_press(stack, browser, how) -> None:
    """Found: a page frozen while HOLD was held (the screen locked, the app sent to the background) came back still
    holding it: with the finger still down it sent held twists again at once, and only the edge's resume rule (a
    gap over 0.5 s) kept the robot still. Now the browser's freeze event releases the hold; and a page whose
    timer did not run for longer than a state stays current (the hello's state_stale_s: a freeze with no event,
    the device asleep) releases it on its first tick back. Nothing moves until HOLD is pressed anew."""
    page = None
    try:
        page = open_console(browser, stack.url, clock=True)
        page.evaluate(TWIST_HOOK)
        fingers = Fingers(page)
        w = stack.watch
        since = time.time_ns()
        drive(page, fingers, 0.0, 1.0)
        w.wait(lambda: len(w.moving_echoes(since)) > 20, 5.0, "the robot moving")
        if how == "freeze event":
            page.evaluate("document.dispatchEvent(new Event('freeze'))")  # what Chrome fires as it freezes a page
        page.clock.pause_at((page.evaluate("Date.now()") + 300) / 1000)  # (s; ahead of a slow call)  # frozen: no timer runs, the page sends nothing
        elapsed, stopped_by, _ = w.stop_after(since)
        assert elapsed <= 0.3, f"stopped {1000 * elapsed:.0f} ms after the last command ({stopped_by})"
        time.sleep(1.0)
        back = page.evaluate("window.__twists.length")
        returned = time.time_ns()
        if how == "freeze event":
            page.evaluate("document.dispatchEvent(new Event('resume'))")
        page.clock.fast_forward(2000)  # the page's clock jumps as a frozen page's does when it runs again
        page.clock.resume()
        time.sleep(1.0)  # the finger still on HOLD, the stick still pushed
        after = _twists(page, back)
        assert after, "the page sent nothing once back"
        assert not any(m["deadman"] for m in after), f"{sum(m['deadman'] for m in after)} held twists once back"
        assert not w.moving_echoes(returned)
        assert not _held(page)
        assert "deadman released: " in _events(page)
        _fresh_press_moves(stack, page, fingers)
        fingers.lift(1)
        fingers.lift(0)
    finally:
        if page is not None:
            with contextlib.suppress(Exception):
                page.context.close()


def test_a_network_lost_for_two_seconds_while_hold_is_held_stops_and_needs_a_fresh_press(stack, browser) -> None:
    """Found: with the network gone (Chromium offline: the socket stays open and carries nothing) the page went on
    holding HOLD and queueing held twists in its socket, which reached the server in a burst on return; only the
    edge's resume rule and its stale-view check refused them, and the page said nothing of the network (only "no
    data from the console's server"). Now going offline releases the hold and says so, a press while offline does
    nothing (and says why), and on return nothing moves until HOLD is pressed anew."""
    page = None
    try:
        page = open_console(browser, stack.url)
        page.evaluate(TWIST_HOOK)
        fingers = Fingers(page)
        w = stack.watch
        since = time.time_ns()
        drive(page, fingers, 0.0, -1.0)
        w.wait(lambda: len(w.moving_echoes(since)) > 20, 5.0, "the robot moving")
        page.context.set_offline(True)
        elapsed, stopped_by, _ = w.stop_after(since)
        assert elapsed <= 0.3, f"stopped {1000 * elapsed:.0f} ms after the last command ({stopped_by})"
        page.wait_for_function("[...document.querySelectorAll('#events li')].some((li) => "
                               "li.textContent.includes('offline: no network'))", timeout=2_000)
        cut = page.evaluate("window.__twists.length")  # (what the page sent since the network went)
        assert "deadman released: this device lost its network" in _events(page)
        fingers.press(2, *fingers.centre("#deadman"))  # another press, while offline
        time.sleep(0.3)
        assert not _held(page)
        assert "HOLD does nothing until it is back" in _events(page)
        fingers.lift(2)
        time.sleep(1.4)
        page.context.set_offline(False)
        returned = time.time_ns()
        time.sleep(1.0)  # the finger still on HOLD, the stick still pushed
        sent = _twists(page, cut)
        assert sent and not any(m["deadman"] for m in sent), f"{sum(m['deadman'] for m in sent)} held twists"
        assert not w.moving_echoes(returned)
        assert "online: network back" in _events(page)
        _fresh_press_moves(stack, page, fingers)
        fingers.lift(1)
        fingers.lift(0)
    finally:
        if page is not None:
            with contextlib.suppress(Exception):
                page.context.set_offline(False)
                page.context.close()


def test_the_same_physician_on_two_devices_has_one_driver_and_the_other_page_says_where(stack, browser) -> None:
    """Found: the physician's second device (a tablet beside the phone that drives) read "controlled by physician"
    and "press Take control", which the server then refused. Now it says that this user holds control from another
    page and must release it there; its press on HOLD and its sticks move nothing."""
    first = open_console(browser, stack.url)
    second = None
    try:
        second = open_console(browser, stack.url, control=False)
        second.wait_for_function("document.getElementById('control').textContent === "
                                 "'controlled by you on another page'", timeout=10_000)
        assert second.text_content("#reason").startswith(f"you hold control of {ROBOT} from another page")
        assert first.text_content("#control") == "Release control"
        second.click("#control")  # refused, saying why
        second.wait_for_function("[...document.querySelectorAll('#events li')].some((li) => "
                                 f"li.textContent.includes('{ROBOT} is controlled by physician from another page'))",
                                 timeout=10_000)
        assert second.is_disabled("#deadman")
        w = stack.watch
        tried = time.time_ns()
        fingers = Fingers(second)
        drive(second, fingers, 1.0, 0.0)
        time.sleep(1.0)
        assert not w.moving_echoes(tried)
        assert first.text_content("#control") == "Release control"
        fingers.lift(1)
        fingers.lift(0)
    finally:
        if second is not None:
            second.context.close()
        first.context.close()


def test_a_reload_or_the_back_button_brings_a_fresh_page_that_holds_nothing(stack, browser) -> None:
    """Measured right, with no test until now: a reload while driving releases control (the old page's socket
    closes) and the new page offers "Take control"; leaving the console and coming back with the back button loads
    it afresh (its "/" is no-store: no back-forward cache; a restored page would reload itself), holding nothing.
    Nothing moves in either case."""
    page = open_console(browser, stack.url)
    try:
        fingers = Fingers(page)
        w = stack.watch
        since = time.time_ns()
        drive(page, fingers, 0.0, 1.0)
        w.wait(lambda: len(w.moving_echoes(since)) > 20, 5.0, "the robot moving")
        page.reload()
        reloaded = time.time_ns()
        page.wait_for_function("window.iorthand && window.iorthand.socket === 'open'")
        w.stop_after(since)
        page.wait_for_function("document.getElementById('control').textContent === 'Take control'", timeout=10_000)
        w.wait(lambda: w.safety and not w.safety[-1].owner, 5.0, "control released")
        assert not w.moving_echoes(reloaded)

        page.click("#control")
        page.wait_for_function("document.getElementById('control').textContent === 'Release control'",
                               timeout=10_000)
        page.evaluate("window.__left = true")
        page.goto(stack.url + "/login")
        w.wait(lambda: w.safety and not w.safety[-1].owner, 5.0, "control released on leaving")
        page.go_back()
        page.wait_for_function("window.iorthand && window.iorthand.socket === 'open'")
        assert page.evaluate("window.__left") is None, "restored from the back-forward cache"
        page.wait_for_function("document.getElementById('control').textContent === 'Take control'", timeout=10_000)
        assert not w.moving_echoes(reloaded)
    finally:
        page.context.close()
