"""The operator console: a textual app over :class:`ConsoleController`. Rendering only; logic lives in the
controller and :mod:`model`.

Keys go to the keyboard input device (hold-to-move; see :mod:`iorthand_operator.inputs.keyboard`) when it is
the active device; with a gamepad, the keyboard still has e-stop and the pose list. ``ctrl+c`` quits like
``q``: the client releases control on the way out.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from typing import Any, ClassVar

from rich.table import Table
from rich.text import Text
from textual import events, work
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Grid, Vertical
from textual.css.query import NoMatches
from textual.message import Message
from textual.screen import ModalScreen
from textual.widgets import Footer, OptionList, RichLog, Static

from iorthand.protocol import printable
from iorthand_operator.client import ControlRefused
from iorthand_operator.console.controller import ConsoleController, ConsoleView
from iorthand_operator.inputs.keyboard import KeyboardInput, read_time


def _yes(flag: bool, yes: str = "yes", no: str = "no") -> Text:
    return Text(yes if flag else no, style="bold green" if flag else "bold red")


def _stale(text: str, old: str) -> Text:
    """A value from the edge that is no longer current (a safety status, a servo or torch state), with its age:
    "yes (stale 3.2 s)"."""
    return Text(f"{text} ({old})", style="grey50")


def _fmt(values: list[float], unit: str, prec: int = 1) -> str:
    return "  ".join(f"{v:+.{prec}f}" for v in values) + f" {unit}" if values else "—"


class PoseScreen(ModalScreen[None]):
    """Safety poses: list → preview on the twin (its verdict shown) → confirm to execute."""

    BINDINGS: ClassVar = [Binding("escape", "dismiss_screen", "back"), Binding("y", "confirm", "execute previewed pose")]
    DEFAULT_CSS = """
    PoseScreen { align: center middle; }
    #pose-box { width: 80; height: auto; max-height: 30; border: thick $accent; background: $surface; padding: 1; }
    #pose-verdict { height: auto; min-height: 3; }
    """

    def __init__(self, controller: ConsoleController) -> None:
        super().__init__()
        self.controller = controller
        self.poses: list[dict[str, Any]] = []
        self.preview: tuple[str, str] | None = None  # (name, token) of an ok preview

    def compose(self) -> ComposeResult:
        with Vertical(id="pose-box"):
            yield Static("Safety poses — enter: preview on the twin, y: execute, escape: back", id="pose-title")
            yield OptionList(id="pose-list")
            yield Static("loading…", id="pose-verdict")

    def on_mount(self) -> None:
        self.load_poses()

    @work(thread=True, exclusive=True, group="poses")
    def load_poses(self) -> None:
        try:
            poses = self.controller.client.list_poses()
            text = f"{len(poses)} poses" if poses else "the edge has no safety poses"
        except (ControlRefused, RuntimeError) as exc:
            poses, text = [], printable(f"cannot list poses: {exc}")
        self.app.call_from_thread(self._show_poses, poses, text)

    def _show_poses(self, poses: list[dict[str, Any]], text: str) -> None:
        self.poses = poses
        ol = self.query_one("#pose-list", OptionList)
        ol.clear_options()
        # Text, not a string: a string is read as markup, and a name with a closing tag ("[/]") would close the console.
        ol.add_options([Text(printable(str(p.get("name", "?")) + (f" — {p['description']}" if p.get("description") else "")))
                        for p in poses])
        self.query_one("#pose-verdict", Static).update(Text(text))
        ol.focus()

    def on_option_list_option_selected(self, event: OptionList.OptionSelected) -> None:
        if 0 <= event.option_index < len(self.poses):
            self.preview = None
            self.query_one("#pose-verdict", Static).update("previewing on the twin…")
            self.run_preview(str(self.poses[event.option_index].get("name", "")))

    @work(thread=True, exclusive=True, group="poses")
    def run_preview(self, name: str) -> None:
        try:
            reply = self.controller.client.preview_pose(name)
            detail = _detail(reply.detail)
            token = str(detail.get("token", ""))
            verdict = detail.get("verdict", "ok" if reply.ok else "refused")
            text = Text.assemble(
                (printable(f"preview {name}: {verdict}"), "bold green" if reply.ok else "bold red"),
                f"\n{printable(reply.reason)}" if reply.reason else "",
                "\n" + printable(", ".join(f"{k}: {v}" for k, v in detail.items() if k not in ("token", "verdict"))),
                ("\npress y to execute" if reply.ok and token else ""),
            )
            ok = reply.ok
        except (ControlRefused, RuntimeError) as exc:
            text, token, ok = Text(printable(f"preview unavailable: {exc}"), style="bold red"), "", False
        self.app.call_from_thread(self._previewed, name, token if ok else "", text)

    def _previewed(self, name: str, token: str, text: Text) -> None:
        self.preview = (name, token) if token else None
        self.query_one("#pose-verdict", Static).update(text)

    def action_confirm(self) -> None:
        if self.preview is None:
            self.query_one("#pose-verdict", Static).update(Text("preview a pose first (enter)", style="yellow"))
            return
        self.run_goto(*self.preview)

    @work(thread=True, exclusive=True, group="poses")
    def run_goto(self, name: str, token: str) -> None:
        try:
            reply = self.controller.client.goto_pose(name, token)
            text = Text(printable(f"goto {name}: {'started' if reply.ok else 'refused'} {reply.reason}"),
                        style="bold green" if reply.ok else "bold red")
        except (ControlRefused, RuntimeError) as exc:
            text = Text(printable(f"goto {name} failed: {exc}"), style="bold red")
        self.app.call_from_thread(self.query_one("#pose-verdict", Static).update, text)

    def action_dismiss_screen(self) -> None:
        self.dismiss(None)


def _detail(text: str) -> dict[str, Any]:
    try:
        data = json.loads(text) if text else {}
    except json.JSONDecodeError:
        return {"detail": text}
    return data if isinstance(data, dict) else {"detail": data}


class UiAction(Message):
    """An input action the UI handles (pose list, quit), posted from the input thread."""

    def __init__(self, action: str) -> None:
        super().__init__()
        self.action = action


class OperatorConsole(App[int]):
    TITLE = "iorthand operator"
    # The banner (the force light and the edge's status) is docked: on any terminal, 40×12 too, it is the first
    # line. The panels take at most what leaves the event log a few lines, and scroll within that.
    CSS = """
    Screen { layout: vertical; }
    #banner { dock: top; height: 1; }
    #grid { grid-size: 3; grid-columns: 1fr 1fr 1fr; grid-rows: auto; height: auto; max-height: 70%; overflow-y: auto; }
    .panel { border: round $primary; padding: 0 1; height: auto; min-height: 7; }
    #force { border: round $primary; padding: 0 1; }
    #events { border: round $primary; height: 1fr; min-height: 3; }
    """
    # The footer names the keys of the default keymap; ctrl+c also quits but is not the key to show.
    BINDINGS: ClassVar = [
        Binding("ctrl+c", "quit_console", "quit", priority=True, show=False),
        Binding("q", "quit_console", "quit"),
        Binding("x", "keymap('estop')", "e-stop"),
        Binding("e", "keymap('acquire')", "take control"),
        Binding("space", "keymap('deadman')", "deadman"),
    ]

    def __init__(self, controller: ConsoleController) -> None:
        super().__init__()
        self.controller = controller
        self.view_model = ConsoleView()
        self._events_shown = 0  # the number (Event.n) of the newest event written into the log
        controller.on_ui_action = self._ui_action_from_thread
        self.keyboard = controller.device if isinstance(controller.device, KeyboardInput) else None

    def compose(self) -> ComposeResult:
        yield Static(id="banner")
        with Grid(id="grid"):
            yield Static(id="status", classes="panel")
            yield Static(id="force", classes="panel")
            yield Static(id="link", classes="panel")
            yield Static(id="pose", classes="panel")
            yield Static(id="profile", classes="panel")
            yield Static(id="input", classes="panel")
        yield RichLog(id="events", max_lines=500, wrap=True)
        yield Footer()

    def on_mount(self) -> None:
        for wid, title in (("status", "robot"), ("force", "force"), ("link", "link quality"), ("pose", "tool"),
                           ("profile", "speed profile"), ("input", "input / camera")):
            self.query_one(f"#{wid}").border_title = title
        log = self.query_one("#events")
        log.border_title = "refusals, stops and actions"
        # Focused, the log would scroll the screen to itself on a short terminal, and the panels' first lines (the
        # force light among them) off it; keys are the robot's here, the mouse wheel still scrolls the log.
        log.can_focus = False
        self.set_interval(1.0 / self.controller.settings.refresh_hz, self.refresh_view)
        self.refresh_view()

    # ------------------------------------------------------------------ keys

    def on_resize(self, event: events.Resize) -> None:
        """Three columns of panels on a wide terminal, two on an 80-column one, one on a narrow one: a panel
        narrower than ~35 columns cuts its labels to a letter or two."""
        columns = max(1, min(3, event.size.width // 40))
        grid = self.query_one("#grid", Grid)
        grid.styles.grid_size_columns = columns
        grid.styles.grid_columns = " ".join(["1fr"] * columns)

    def on_key(self, event: events.Key) -> None:
        if len(self.screen_stack) > 1:
            return  # the pose screen has the keys; holding a move key there must not move the robot
        key = event.key
        if self.keyboard is not None and self.keyboard.key(key, read_time(event.time, time.monotonic())):
            event.stop()
            return
        # With a gamepad the keyboard still stops the robot and opens the pose list.
        fallback = {"x": "estop", "g": "poses", "q": "quit", "escape": "estop"}.get(key)
        if fallback:
            event.stop()
            self.controller.dispatch(fallback)

    def _ui_action_from_thread(self, action: str) -> None:
        # post_message is thread-safe and does not wait: the input thread must never block on the UI.
        self.post_message(UiAction(action))

    def on_app_blur(self, _event: events.AppBlur) -> None:
        """The terminal lost focus: the keys typed next go elsewhere, so none counts as held any more and a
        toggled deadman is let go (the robot stops; pressing it again is the operator's fresh intent)."""
        if self.keyboard is not None:
            self.keyboard.release_all()

    def on_ui_action(self, message: UiAction) -> None:
        self.ui_action(message.action)

    def ui_action(self, action: str) -> None:
        if action == "quit":
            self.action_quit_console()
        elif action == "poses" and len(self.screen_stack) == 1:
            if self.keyboard is not None:
                self.keyboard.release_all()
            self.push_screen(PoseScreen(self.controller))

    def action_quit_console(self) -> None:
        self.exit(0)

    def action_keymap(self, binding: str) -> None:
        """Footer entries for keys the keymap handles (on_key, before any binding): nothing more to do here."""

    # ------------------------------------------------------------------ rendering

    def refresh_view(self) -> None:
        v = self.controller.view()
        self.view_model = v
        # NoMatches: the console is closing, and a last tick of the refresh timer came after its panels were removed.
        with contextlib.suppress(NoMatches):
            self._draw(v)

    def _draw(self, v: ConsoleView) -> None:
        self.query_one("#banner", Static).update(self._banner(v))
        self.query_one("#status", Static).update(self._status(v))
        self.query_one("#force", Static).update(self._force(v))
        # textual's CSS colours differ from rich's: grey50 is "grey" there.
        self.query_one("#force").styles.border = ("round", "grey" if v.force.colour.startswith("grey") else v.force.colour)
        self.query_one("#link", Static).update(self._link(v))
        self.query_one("#pose", Static).update(self._pose(v))
        self.query_one("#profile", Static).update(self._profile(v))
        self.query_one("#input", Static).update(self._input(v))
        log = self.query_one("#events", RichLog)
        # New events only, by their numbers: two alike lines (the same refusal twice in a second, a stop between
        # them) are two events. The view has the latest 50: a burst of more between two refreshes says so.
        new = v.events_logged - self._events_shown
        if new > 0:
            if new > len(v.events):
                log.write(Text(f"… {new - len(v.events)} more events came at once: the latest {len(v.events)} follow",
                               style="yellow"))
            for line in v.events[max(0, len(v.events) - new):]:
                style = "red" if (" refused " in line or " stop " in line or " input " in line) else ""
                log.write(Text(line, style=style))
            self._events_shown = v.events_logged

    @staticmethod
    def _table() -> Table:
        t = Table.grid(padding=(0, 1))
        t.add_column(style="bold")
        t.add_column()
        return t

    @staticmethod
    def _banner(v: ConsoleView) -> Text:
        """One line that every terminal shows: the force light, then the edge's status and reason (as the robot
        panel shows them: greyed and aged when old)."""
        f = v.force
        fg = "black" if f.colour in ("green", "yellow") else "white"
        status = f"{v.edge_status} {v.edge_reason}".strip() or "no safety status"
        halted = v.edge_reason and v.edge_status not in ("ok", "idle")
        shown = _stale(status, v.safety_stale) if v.safety_stale else Text(status, style="bold red" if halted else "")
        return Text.assemble((f" {f.label} ", f"bold {fg} on {f.colour}"), " ", shown, no_wrap=True, overflow="ellipsis")

    def _status(self, v: ConsoleView) -> Table:
        t = self._table()
        t.add_row("router", Text(v.router or "—") + Text("  connected" if v.connected else "  no data", style="green" if v.connected else "red"))
        online = {"online": "bold green", "offline": "bold red"}.get(v.robot_online, "grey50")
        t.add_row("robot", Text(v.robot_online.upper(), style=online) + Text("" if v.state_fresh else "  (no fresh state)", style="yellow"))
        old = v.safety_stale  # the edge's last word, however old: greyed and aged, never green
        t.add_row("armed", _stale("yes" if v.armed else "no", old) if old else _yes(v.armed))
        owner = v.owner or "nobody"
        t.add_row("owner", _stale(owner, old) if old else Text(owner, style="bold green" if v.we_own else "bold yellow"))
        edge = _stale("ON" if v.edge_deadman else "off", old) if old else _yes(v.edge_deadman, "ON", "off")
        t.add_row("deadman", Text.assemble("sent ", _yes(v.deadman, "ON", "off"), "  edge ", edge))
        status = f"{v.edge_status} {v.edge_reason}".strip() or "—"
        halted = v.edge_reason and v.edge_status not in ("ok", "idle")
        t.add_row("status", _stale(status, old) if old else Text(status, style="red" if halted else ""))
        if v.hint:
            t.add_row("next", Text(v.hint, style="bold yellow"))
        return t

    def _force(self, v: ConsoleView) -> Table:
        f = v.force
        t = Table.grid(padding=(0, 1))
        t.add_column()
        fg = "black" if f.colour in ("green", "yellow") else "white"
        t.add_row(Text(f"  {f.label:^12}  ", style=f"bold {fg} on {f.colour}"))
        t.add_row(Text(f.detail))
        t.add_row(Text("F " + _fmt(v.wrench[:3], "N") if v.wrench else "wrench: no fresh sample", style="" if v.wrench else "grey50"))
        if v.wrench:
            t.add_row(Text("T " + _fmt(v.wrench[3:], "N·m", 2)))
        t.add_row(Text(v.spark or "", style=f.colour))
        if v.vitals:
            t.add_row(Text("patient: " + v.vitals, style="cyan"))
        return t

    def _link(self, v: ConsoleView) -> Table:
        t = self._table()
        for row in v.link:
            t.add_row(row.label, Text(row.text, style=f"bold {row.colour}"))
        t.add_row("sent", str(v.sent))
        t.add_row("at edge", Text(f"{v.edge_judged} judged, {v.edge_superseded} superseded",
                                  style="yellow" if v.edge_superseded else ""))
        return t

    def _pose(self, v: ConsoleView) -> Table:
        t = self._table()
        p = v.tcp_pose_mm_deg
        t.add_row("xyz", _fmt(p[:3], "mm") if p else "—")
        t.add_row("rxyz", _fmt(p[3:], "°") if p else "—")
        t.add_row("speed", "—" if math.isnan(v.tcp_speed_mm_s) else f"{v.tcp_speed_mm_s:.1f} mm/s")
        t.add_row("command", _fmt(v.command[:3], "mm/s") if v.command else "—")
        if v.markers_note:
            t.add_row("markers", Text(v.markers_note, style="bold red" if v.markers_failed else "yellow"))
        else:
            t.add_row("markers", ", ".join(map(str, v.markers)) or "none in view")
        return t

    def _profile(self, v: ConsoleView) -> Table:
        t = self._table()
        t.add_row("profile", _stale(v.profile or "—", v.safety_stale) if v.safety_stale else
                  Text(v.profile or "—", style="bold cyan"))
        t.add_row("frame", Text("probe (tool)" if v.frame == "tool" else "base", style="bold" if v.frame == "tool" else ""))
        t.add_row("contact", Text(v.contact or "off", style="bold magenta" if v.contact else ""))
        if v.task:
            t.add_row("task", Text(v.task, style="bold"))
        t.add_row("linear", "—" if math.isnan(v.linear_limit_mm_s) else f"{v.linear_limit_mm_s:.1f} mm/s")
        t.add_row("angular", "—" if math.isnan(v.angular_limit_deg_s) else f"{v.angular_limit_deg_s:.1f} °/s")
        t.add_row("limits hit", Text(", ".join(v.limits_hit) or "none", style="yellow" if v.limits_hit else ""))
        return t

    def _input(self, v: ConsoleView) -> Table:
        t = self._table()
        t.add_row("device", Text(v.input_name))  # a gamepad's name is the device's own: never read as markup
        t.add_row("state", Text(v.input_status or "—", style="" if v.input_connected else "bold red"))
        # The edge's last word, however old: greyed and aged once its heartbeat has stopped, never as if current.
        t.add_row("camera", _stale(v.camera, v.camera_stale) if v.camera_stale else v.camera or "—")
        t.add_row("torch", _stale(v.torch, v.torch_stale) if v.torch_stale else v.torch or "—")
        return t
