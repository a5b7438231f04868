"""Universal Robots backend over ur_rtde, safe against its traps.

ur_rtde 1.6.5 facts this design follows (FACTS.md, issue 5):
- Its constructors hold the GIL and can hang forever on a half-open socket. So the driver runs in a **child
  process** (``_driver_main``), talking to the agent over a pipe; the agent gives it ``connect_timeout`` to
  report ready and kills it otherwise. A dead or hung child is a fault: stop, report, reconnect with back-off.
- ``speedL`` keeps the last velocity forever; only the controller's RTDE watchdog (``setWatchdog``) stops a
  program whose inputs went silent. The child sets it after every connect and kicks it only while the agent
  keeps talking to it (a heartbeat each control cycle): a frozen agent lets the controller stop the robot —
  the second safety layer. The child also stops the robot itself when the agent goes silent.
- On a lost link ``speedL`` still returns True: link health is ``isConnected()`` **and** an advancing
  controller timestamp.
- ``disconnect()`` stops neither motion nor the program: shut down with speedStop → stopScript → disconnect.
- A re-uploaded control script replays the stale command left in the input registers: every connection
  starts with speedStop, and reconnects always kill the old driver and use a fresh constructor, never
  ``reuploadScript()``. A stale speedL never runs again (tested against the emulator).
- A protective stop kills the script and the controller refuses to unlock for 5 s; the receive interface's
  safety mode names it (the control and receive streams can disagree for one period: a stopped program is only
  judged once it has been stopped for ``link_timeout`` with no safety stop seen).
- A safeguard stop (a door, a light curtain) pauses the program on an e-Series, which resumes by itself when the
  safeguard is reset, with whatever command is left in its registers. The edge shows "safeguard stop" and stops;
  the driver writes a stop into the registers once it sees the program paused, and when any stop of the
  controller's own (safety stop, e-stop, power off) is cleared it reconnects with a fresh script (whose first
  command is a stop) instead of driving the resumed one. The supervisor stays latched meanwhile: motion needs the
  safeguard reset **and** an operator's re-acquire and fresh press.
- **A program stopped from outside the edge disarms it** (the lead's decision). Somebody who stops the program on
  the teach pendant or the dashboard is at the robot and has it: the agent disarms with
  :data:`PROGRAM_STOPPED_OUTSIDE`, and the driver does not upload its script again until the edge is armed again
  (``iorthand arm``, the on-site confirmation: :meth:`URRobot.allow_restart`). A stop is told from the
  controller's RTDE watchdog expiring on the edge's own lateness (a vCPU stall, a frozen agent) by the driver
  child, which times its writes to the controller: if it left the controller without a write for
  :data:`LATE_FRACTION` of the watchdog's period or more around the stop, the stop may be its own and it keeps
  the old behaviour (fault, reconnect, latched until a fresh press), so that a stall does not strand a remote
  physician. Otherwise the stop is taken as from outside. Neither RTDE nor the dashboard says which it was
  (``programState`` answers STOPPED after both), so the case between, writes that left on time but reached the
  controller late (a link delaying them by more than the rest of the period), is taken as from outside: the safe
  side, at the price of a re-arm. A runtime error of the script (it is only sent speedL and stops) lands there too.
- **Local control is watched on the dashboard** (RTDE has no bit for it): the child asks ``is in remote control``
  about once a second from a thread of its own (:data:`DASHBOARD_PERIOD_S`, each exchange bounded by
  :data:`DASHBOARD_TIMEOUT_S`); "false" stops the arm and the script and disarms the edge
  (:data:`LOCAL_TAKEOVER`), as a stop from outside does. A dashboard that does not answer is no fault by itself:
  logged once, asked again, and the mode says ", no dashboard" while local control cannot be seen.
- **A program played over the edge's script takes over too.** Somebody who plays a program of their own (the
  pendant's Play, the dashboard's ``load`` + ``play``) replaces the script, and RTDE still reports a program
  running: ``speedL`` answers True into registers nobody reads, and ``speedStop`` waits for a "done" their program
  never writes. The same dashboard poll asks ``programState``, which names the running program: another name than
  the one it gave right after the connect (when this script was known to run) disarms the edge
  (:func:`foreign_program`, with the name) and the driver ends at once without writing to the controller again:
  their program runs on, no stop, no stopScript, no new upload until the edge is armed again. Seen within about a
  second (the edge's speedL meanwhile reaches no motion). A reconnect after a fault asks first, and holds instead
  of uploading over a program of another name (the agent keeps the script's name between connections; arming
  forgets it). A connect with no script of the edge's known to run (at start, after arming) never uploads over any
  program that runs or is paused (ur_rtde's constructor would write a stop into its registers, wait 3 s for an
  answer it never gets, then stop it on the dashboard): the driver says :func:`program_running` and re-checks at
  each reconnect, connecting once it is stopped (the edge stays armed; motion needs a re-acquire and a fresh
  press, as after any fault). Not seen: their program under the very name the dashboard gave the script (a
  controller that names the loaded .urp for both), and a replacement before the first answer when the dashboard is
  down at connect.
- ur_rtde's commands block (speedStop until the arm is at rest): the child streams state from a reader
  thread of its own so that a long stop never looks like a hung driver.
- Faults never resume motion: after a reconnect the supervisor stays latched until an operator re-acquires.
- The controller's own settings change what a command does: the teach pendant's speed slider slows every motion
  (RTDE ``target_speed_fraction``): ``send_twist`` returns the twist the arm really makes, the mode says
  "speed 30%" and the edge logs a warning whenever the slider is below 100 %. The installation's TCP and
  payload are checked against ``goto.tcp_offset`` (the kinematics' tool point) and ``payload_kg``: the workspace box
  guards the configured tool point and the force levels assume the configured payload. Checked before the upload,
  from RTDE (``payload``, and ``tcp_offset`` where the controller publishes it: :func:`read_tcp_offset`), so that
  no script is uploaded onto an installation known to be wrong (said once, re-checked at each reconnect, connected
  once it is set right); and again after it with the script's ``getTCPOffset``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import multiprocessing as mp
import select
import socket
import struct
import time
from collections.abc import Sequence
from dataclasses import asdict
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from iorthand.geometry import rotvec_to_matrix
from iorthand.process import REALTIME_PRIORITY, exit_reason, raise_priority
from iorthand_edge.robots import rtde_wire
from iorthand_edge.robots.base import Robot, RobotFault, RobotReading, Vector
from iorthand_edge.robots.config import URRobotConfig

log = logging.getLogger("iorthand.edge.ur")

# UR safety modes (RTDE safety_mode) that forbid motion, with what the operator should do.
SAFETY_MODES = {
    3: "protective stop: clear it on the teach pendant (or the dashboard), then re-acquire control",
    4: "safety recovery mode: move the arm back within its safety limits on the teach pendant, then re-acquire "
       "control",
    5: "safeguard stop: a safeguard input (door, light curtain, external stop) is open; close and reset it, "
       "then re-acquire control",
    6: "system emergency stop: release the emergency stop, reset on the teach pendant, power on, release the "
       "brakes, then re-acquire control",
    7: "robot emergency stop: release the emergency stop button, reset on the teach pendant, power on, release "
       "the brakes, then re-acquire control",
    8: "safety violation: restart safety on the teach pendant, power on, then re-acquire control",
    9: "safety fault: restart safety on the teach pendant, power on, then re-acquire control",
}
SAFETY_NAMES = {3: "protective stop", 4: "recovery", 5: "safeguard stop", 6: "system e-stop",
                7: "robot e-stop", 8: "violation", 9: "safety fault"}
SAFETY_MODE_REDUCED = 2
FULL_SPEED = 0.999  # a speed slider at or above this is at 100 %
LOCAL_CONTROL = ("the controller is in local control: switch it to remote control on the teach pendant, then "
                 "re-acquire control")
ROBOT_MODE_RUNNING = 7
PROGRAM_STOPPED_OUTSIDE = ("the program was stopped on the teach pendant (or the dashboard): the person at the robot "
                           "has it; arm again at the edge when they are done")
LOCAL_TAKEOVER = ("the controller was switched to local control on the teach pendant: the person at the robot has "
                  "it; arm again at the edge when they are done (and it is back in remote control)")


def foreign_program(name: str) -> str:
    """The takeover when somebody at the robot plays a program of their own over the edge's script."""
    return (f"another program ({name[:60]}) was started on the teach pendant: the person at the robot has it; arm "
            "again at the edge when they are done")


def program_running(name: str) -> str:
    """Why the driver does not upload the edge's script (which would stop it): a program the edge did not start runs,
    or is paused, on the controller when no script of the edge's was running (the edge just armed, or started)."""
    return (f"another program ({name[:60]}) is running on the controller: stop it on the teach pendant first; the "
            "edge connects once it has stopped")


# A silence of the driver's writes to the controller this long, in watchdog periods, may have let the RTDE watchdog
# expire on the edge's own account (the rest of the period for the link and the controller's cycle).
LATE_FRACTION = 0.8
DASHBOARD_PORT = 29999
DASHBOARD_PERIOD_S = 1.0  # how often the driver asks the dashboard about remote control and the running program
DASHBOARD_TIMEOUT_S = 0.5  # for one exchange with it (connect, or a question and its answer)
MODE_MAX, FAULT_MAX = 40, 200  # the lengths RobotState accepts: a longer text would make its encode() fail
# The driver's command thread (it kicks the controller's watchdog) at real time, under the edge's control loop and
# under the UR emulator that stands for the controller in tests and benchmarks (EMULATOR_PRIORITY). At normal
# priority, two CPU hogs delayed a kick past the 100 ms watchdog in 2 of 3 one-minute runs of bench_cpu_hogs.py.
DRIVER_PRIORITY = max(1, REALTIME_PRIORITY - 6)
# ur_rtde's own threads stay normal on every kernel. On a PREEMPT_RT kernel (a Pi's, say) ur_rtde 1.6.5 otherwise
# puts its receive threads, and the thread calling its constructors, at SCHED_FIFO 90: above the control loop and
# the command thread (seen with a faked /sys/kernel/realtime, tests/test_ur_backend.py). The driver's other threads
# at real time, one step under the command thread, showed no fewer false faults under two CPU hogs on the test VM
# (those follow the hypervisor taking a whole vCPU for 100 ms, which no priority prevents), and ur_rtde then
# crashed (SIGSEGV) when the link to the controller dropped, in 1 of 2 CI runs; tests/test_ur_stack.py's link kill
# alone failed 1 of 37 runs so, 0 of 24 with them normal (benchmarks/README.md). A negative value is
# ur_rtde's "not on purpose"; it then logs a "Failed to set realtime priority" warning that means just that.
UR_RTDE_RT_PRIORITY = -1
SPAWN_TIMEOUT = 15.0  # s for the driver child to start Python and import ur_rtde (not the controller's fault)
ROBOT_MODES = {-1: "no controller", 0: "disconnected", 1: "confirm safety", 2: "booting", 3: "power off",
               4: "power on", 5: "idle", 6: "backdrive", 7: "running", 8: "updating firmware"}


def not_running(robot_mode: int) -> str:
    """Why an arm that is not running cannot move (at connect and while connected), and what to do."""
    return (f"robot not running ({ROBOT_MODES.get(robot_mode, str(robot_mode))}): power it on and release the "
            "brakes on the teach pendant, then re-acquire control")


def installation_mismatch(cfg: dict[str, Any], tcp: Sequence[float] | None, payload: float) -> str:
    """Why the controller's active TCP offset or payload is not the configured one ("" when it is, or when the
    configuration does not say; ``tcp`` None: not known yet, not checked). Names both values: the fix is on the
    pendant or in the configuration."""
    problems = []
    expected = cfg.get("tcp_offset")
    if expected is not None and tcp is not None:
        dp = math.dist(tcp[:3], expected[:3])
        rel = rotvec_to_matrix(expected[3:6]).T @ rotvec_to_matrix(tcp[3:6])
        angle = math.acos(max(-1.0, min(1.0, (float(np.trace(rel)) - 1.0) / 2.0)))
        if dp > cfg["tcp_tolerance_m"] or angle > cfg["tcp_tolerance_rad"]:
            problems.append(f"TCP offset {_fmt(tcp)} differs from goto.tcp_offset {_fmt(expected)} "
                            f"by {1000 * dp:.1f} mm, {math.degrees(angle):.1f}°")
    if cfg.get("payload_kg") is not None and abs(payload - cfg["payload_kg"]) > cfg["payload_tolerance_kg"]:
        problems.append(f"payload {payload:.3f} kg differs from robot.payload_kg {cfg['payload_kg']:.3f} kg")
    if not problems:
        return ""
    return ("the controller's " + "; its ".join(problems) + ": the workspace box and the force levels would guard "
            "another tool; set the installation's TCP and payload on the teach pendant or correct the configuration")


def _fmt(values: Sequence[float]) -> str:
    return "[" + ", ".join(f"{float(v):.4f}" for v in values) + "]"


class WriteTimeline:
    """When the driver last wrote to the controller (a command or a watchdog kick), and the end of its last silence
    long enough (``late_gap``) to have let the controller's RTDE watchdog expire on the driver's account. A silence
    is measured from the start of one write call to the return of the next, the longest it can have been."""

    def __init__(self, late_gap: float, now: float) -> None:
        self.late_gap = late_gap
        self.last_start = now  # monotonic start of the last write call that returned
        self.late_until = -math.inf  # monotonic end of the last late silence

    def wrote(self, started: float, now: float) -> None:
        """A write call that started at ``started`` returned at ``now``."""
        if now - self.last_start >= self.late_gap:
            self.late_until = now
        self.last_start = started

    def late_between(self, since: float, now: float) -> bool:
        """Whether a late silence overlapped [since, now], the one still going on at ``now`` included."""
        return self.late_until >= since or now - self.last_start >= self.late_gap


def send_without_blocking(conn: Connection, msg: tuple[Any, ...]) -> str:
    """Hand ``msg`` (a few hundred bytes at most) to the driver child; "" when it went, else why not. Never blocks:
    a child whose main thread hangs inside ur_rtde (a speedStop waiting for a "done" nobody writes) stops reading,
    the pipe fills at the control rate, and a blocking send froze the agent's control loop and every rule in it.
    A socket that ``select`` calls writable has a quarter of its buffer free at least: the message fits."""
    try:
        if not select.select([], [conn], [], 0)[1]:
            return "the UR driver stopped reading its commands (hung inside ur_rtde)"
        conn.send(msg)
    except (BrokenPipeError, OSError):
        return "UR driver pipe broken"
    return ""


class DashboardLink:
    """A connection to the controller's dashboard server (:data:`DASHBOARD_PORT`), past its welcome line: the one
    way this module (and the tests' teach pendant) talks to it. The connect and every exchange (a question and its
    answer) are bounded by ``timeout``; a refusal, a timeout or a closed connection raises OSError."""

    def __init__(self, host: str, timeout: float = DASHBOARD_TIMEOUT_S) -> None:
        self._sock = socket.create_connection((host, DASHBOARD_PORT), timeout=timeout)
        self._stream = self._sock.makefile("rw", encoding="utf-8", newline="\n")
        try:
            self._answer()  # its welcome line
        except OSError:
            self.close()
            raise

    def ask(self, question: str) -> str:
        """One question; its answer."""
        self._stream.write(question + "\n")
        self._stream.flush()
        return self._answer()

    def _answer(self) -> str:
        line = self._stream.readline()
        if not line:
            raise OSError("the dashboard closed the connection")
        return line.strip()

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._stream.close()  # its flush may fail on a broken connection: the socket is closed all the same
        self._sock.close()

    def __enter__(self) -> DashboardLink:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


def foreign_program_playing(host: str, script_name: str | None) -> str:
    """Before the driver uploads the edge's script (which would replace whatever runs): the name of a program other
    than ``script_name`` (what the dashboard called the edge's script on the last connection; None: no script of
    the edge's is known to run, so any program is another's) that the controller runs or has paused, "" when none or
    when the dashboard does not answer (then nothing can be told)."""
    try:
        with DashboardLink(host) as dashboard:
            state, _, name = dashboard.ask("programState").partition(" ")
    except OSError:
        return ""
    return name if state.upper() != "STOPPED" and name != script_name else ""


INSTALLATION_TIMEOUT_S = 1.0  # for reading the installation's TCP offset over RTDE (connect, each answer)


def read_tcp_offset(host: str, timeout: float = INSTALLATION_TIMEOUT_S) -> list[float] | None:
    """The installation's active TCP offset, from the controller's RTDE output ``tcp_offset`` on a connection of its
    own, before anything is uploaded: ur_rtde 1.6.5's receive interface has no getter for it, and its control
    interface's ``getTCPOffset`` asks the uploaded script. None when the controller does not publish it (older
    software answers NOT_FOUND): the TCP is then known only once the script runs. Raises OSError on a link that
    fails or a controller that does not answer within ``timeout``."""
    deadline = time.monotonic() + 3 * timeout  # a controller that only sends other packages does not keep us here
    with socket.create_connection((host, rtde_wire.PORT), timeout=timeout) as sock:

        def exchange(kind: int, payload: bytes = b"", send: bool = True) -> bytes:
            """Send a package of ``kind`` (unless not ``send``) and return the payload of the next one of that kind;
            the controller's others (text messages) are skipped."""
            if send:
                sock.sendall(rtde_wire.pack_message(kind, payload))
            while time.monotonic() < deadline:
                got, body = rtde_wire.read_message(sock)  # ConnectionError (an OSError) when it closes
                if got == kind:
                    return body
            raise OSError(f"no RTDE package {chr(kind)!r} from the controller within {3 * timeout:g} s")

        if exchange(rtde_wire.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2))[:1] != b"\x01":
            raise OSError("the controller refused RTDE protocol 2")
        reply = exchange(rtde_wire.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 10.0) + b"tcp_offset")
        if reply[1:] != b"VECTOR6D":  # NOT_FOUND
            return None
        if exchange(rtde_wire.CONTROL_PACKAGE_START)[:1] != b"\x01":
            raise OSError("the controller refused to start the RTDE output")
        data = exchange(rtde_wire.DATA_PACKAGE, send=False)  # recipe id, then the 6 doubles
        return [float(v) for v in struct.unpack_from(">6d", data, 1)]


# ---------------------------------------------------------------------------------------------------------
# The child process. It imports only ur_rtde, so it starts fast and a hang in it cannot freeze the agent.


def _driver_main(conn: Connection, cfg: dict[str, Any]) -> None:
    """The driver child. Two threads: a **reader** that streams the controller's state to the agent at the RTDE
    rate, and this main thread, which executes the agent's commands and kicks the watchdog. They are separate
    because ur_rtde's commands block (``speedStop`` returns only once the arm is at rest, 0.2 s for 20 mm/s at
    0.1 m/s², and ``speedL`` waits for the controller's acknowledgement): state must keep flowing meanwhile or
    the agent would take a long stop for a hung driver. ur_rtde's methods release the GIL (its constructors do
    not), so the threads really run side by side."""
    import os
    import signal
    import threading

    # Ctrl-C reaches the whole process group, and `systemctl stop` signals every process of the service: they are
    # the agent's to handle. It stops the arm, then closes this driver; gone, its pipe's end makes this driver stop
    # the arm itself (shutdown below). Killed by either signal, it stopped nothing: only the controller's watchdog.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    import rtde_control
    import rtde_receive

    period = 1.0 / cfg["rtde_frequency"]
    # The connect timeout runs from here: starting Python and importing takes seconds on a busy Pi and says
    # nothing about the controller.
    conn.send(("connecting", ""))
    # Uploading the edge's script would stop whatever program runs: ur_rtde's constructor first writes a stop into
    # the registers (its own script's; another program never answers, and it waits 3 s), then stops the program on
    # the dashboard. So a program the edge did not start is never uploaded over. After a fault (the dashboard's name
    # for the edge's script known), one played meanwhile is a takeover: somebody at the robot has it (the last driver
    # may not have lived to see it). With no script of the edge's known to run (the edge just started, or was armed
    # on site), any program is somebody else's: the driver waits, re-checking at each reconnect, until it is stopped.
    theirs = foreign_program_playing(cfg["host"], cfg["script_name"])
    if theirs:
        with contextlib.suppress(OSError):
            conn.send(("takeover", foreign_program(theirs)) if cfg["script_name"] is not None
                      else ("wait", program_running(theirs)))
        os._exit(0)
    ctrl = None
    try:
        recv = rtde_receive.RTDEReceiveInterface(cfg["host"], cfg["rtde_frequency"], rt_priority=UR_RTDE_RT_PRIORITY)
        # No script can run in a protective stop (or worse), or with the arm off: say so instead of a confusing
        # upload failure.
        safety_mode, robot_mode = recv.getSafetyMode(), recv.getRobotMode()
        if safety_mode in SAFETY_MODES:
            raise RuntimeError(f"controller in {SAFETY_MODES[safety_mode]}")
        if robot_mode != ROBOT_MODE_RUNNING:
            raise RuntimeError(not_running(robot_mode))
        # An installation set up for another tool is known before the upload (RTDE publishes the payload, and the
        # TCP offset on current software): nothing is uploaded onto it, which would only disturb the pendant (a
        # program started and stopped at every reconnect). The driver ends with the reason; each reconnect re-checks.
        try:
            tcp = read_tcp_offset(cfg["host"]) if cfg["tcp_offset"] is not None else None
        except OSError as exc:
            raise RuntimeError(f"reading the installation's TCP offset over RTDE failed ({exc})") from None
        mismatch = installation_mismatch(cfg, tcp, float(recv.getPayload()))
        if mismatch:
            with contextlib.suppress(OSError):
                conn.send(("wait", mismatch))
            os._exit(0)
        try:
            ctrl = rtde_control.RTDEControlInterface(cfg["host"], cfg["rtde_frequency"],
                                                     rt_priority=UR_RTDE_RT_PRIORITY)
        except RuntimeError as exc:  # ur_rtde's own words for local control are a programmer's
            raise RuntimeError(LOCAL_CONTROL if "remote control" in str(exc) else str(exc)) from None
        # The constructor uploads the control script. The controller's input registers outlive a program, and a
        # re-uploaded script executes whatever command is still in them (the stale speedL of a driver that died
        # mid-motion). So the first command of every connection is a stop; it also clears that register.
        if not ctrl.speedStop(cfg["stop_deceleration"]):
            raise RuntimeError("speedStop after connecting was refused (control script not running)")
        # Again with the script's own TCP offset: a controller that does not publish it over RTDE is checked here
        # (and an installation changed in between).
        installation = (list(ctrl.getTCPOffset()), float(recv.getPayload()))
        mismatch = installation_mismatch(cfg, *installation)
        if mismatch:
            raise RuntimeError(mismatch)
        # This thread only (reset on fork): ur_rtde's threads, started before, and the reader, started after, stay
        # normal, or their work at the RTDE rate would take the CPU from the edge's command path. Raised before
        # the watchdog is set: from then on the program lives on this thread's kicks, and at normal priority a
        # loaded machine delayed the first one past the watchdog's 100 ms (the emulator stopped the program
        # 0.103 s after the watchdog was set, 1 connection in 20 beside stress-ng --cpu 2).
        priority = raise_priority(cfg["realtime"], DRIVER_PRIORITY)
        # The watchdog lives in the program: every new script needs it set again.
        started = time.monotonic()
        if not ctrl.setWatchdog(cfg["watchdog_hz"]):
            raise RuntimeError("setWatchdog was refused (control script not running)")
        writes = WriteTimeline(LATE_FRACTION / cfg["watchdog_hz"], started)
    except Exception as exc:  # ur_rtde raises RuntimeError mostly; report whatever it is
        if ctrl is not None:
            # A script is running (a refused installation, a refused watchdog): leave none behind, before the
            # agent, told, kills this process. The controller answered a moment ago: this does not hang on a dead one.
            with contextlib.suppress(Exception):
                ctrl.stopScript()
        with contextlib.suppress(OSError):
            conn.send(("error", str(exc) if isinstance(exc, RuntimeError) else f"{type(exc).__name__}: {exc}"))
        os._exit(0)  # no destructors: they talk to the controller and can block on a dead one

    send_lock = threading.Lock()
    done = threading.Event()
    # Set by the reader once it has seen the program running and then not (stopped or paused): no more kicks (no
    # program to keep alive, and ur_rtde prints a line for every command a paused program refuses) until it runs.
    program_stopped = threading.Event()
    takeover: list[str] = []  # why somebody at the robot has it (local control), set once by the dashboard watch
    dashboard = {"problem": ""}  # why local control cannot be seen ("" while the dashboard answers)

    def send(msg: tuple[Any, ...]) -> bool:
        with send_lock:
            try:
                conn.send(msg)
                return True
            except (BrokenPipeError, OSError):
                done.set()  # the agent is gone
                return False

    def reader() -> None:
        next_tick = time.monotonic()
        watchdog_period = 1.0 / cfg["watchdog_hz"]
        seen_running = -math.inf  # monotonic time the program was last seen running
        stop_late: bool | None = None  # for a program seen stopped: whether the driver's writes were late then
        while not done.is_set():
            try:
                running = ctrl.isProgramRunning()
                now = time.monotonic()
                if running:
                    seen_running, stop_late = now, None
                    program_stopped.clear()
                elif stop_late is None and seen_running > -math.inf:
                    # The program stopped between the last time it was seen running and now (the state is one RTDE
                    # period late at most; the watchdog counts a whole period of silence before it stops one): were
                    # this driver's writes late around then? Judged once, before the kicks stop.
                    stop_late = writes.late_between(seen_running - watchdog_period, now)
                    program_stopped.set()
                state = (
                    list(recv.getActualTCPPose()), list(recv.getActualTCPSpeed()), list(recv.getActualQ()),
                    recv.getTimestamp(), recv.getRobotMode(), recv.getSafetyMode(), recv.isConnected(),
                    running, list(recv.getActualTCPForce()), ctrl.isConnected(), recv.getTargetSpeedFraction(),
                    stop_late, dashboard["problem"],
                )
            except RuntimeError as exc:  # ur_rtde's own reconnect failed inside a call
                send(("lost", f"RTDE link to the controller lost ({exc})"))
                shutdown()
            if not send(("state", state)):
                return
            next_tick += period
            delay = next_tick - time.monotonic()
            if delay > 0:
                done.wait(delay)
            else:
                next_tick = time.monotonic()

    def watch_dashboard() -> None:
        """About once a second, on the dashboard (RTDE has no bit for either): whether the controller is still in
        remote control, and which program it runs. On "false", tell the agent and have the main thread stop the arm
        and the script. A program of somebody else's, played over this script (the pendant's Play, or the
        dashboard's ``load`` + ``play``), leaves RTDE saying "program running" and ur_rtde's commands answering True
        into registers nobody reads: it is told by ``programState`` naming another program than the one it named
        while this script was known to run (asked first right after the connect, whose speedStop only this
        script answers; a controller's name for an uploaded script is its own). Then the agent is told and this
        process ends at once, writing nothing more: a stop or a stopScript would go to their program's registers,
        and a speedStop would wait for an answer that never comes. A dashboard that does not answer is asked again
        on a new connection (``dashboard["problem"]`` says so meanwhile)."""
        link: DashboardLink | None = None
        ours: str | None = None  # the name the dashboard gives this script
        while not done.is_set():
            try:
                if link is None:
                    link = DashboardLink(cfg["host"])
                remote = link.ask("is in remote control")
                program_state, _, program = link.ask("programState").partition(" ")
            except OSError as exc:  # refused, timed out, closed
                if link is not None:
                    link.close()
                link = None
                dashboard["problem"] = f"the dashboard ({cfg['host']}:{DASHBOARD_PORT}) does not answer ({exc})"
                done.wait(DASHBOARD_PERIOD_S)
                continue
            if remote.lower() == "false":
                takeover.append(LOCAL_TAKEOVER)
                send(("takeover", LOCAL_TAKEOVER))
                return
            if ours is None:
                ours = program
                send(("script", ours))
            elif program != ours and program_state.upper() != "STOPPED":
                # Theirs runs: stopping it is theirs too. Exit holding the pipe's lock, so that the takeover is the
                # last whole message the agent gets; ending the process closes the links to the controller.
                with send_lock:
                    with contextlib.suppress(OSError):
                        conn.send(("takeover", foreign_program(program)))
                    os._exit(0)
            dashboard["problem"] = "" if remote.lower() == "true" else (
                f"the dashboard answers {remote[:60]!r} to 'is in remote control'")
            done.wait(DASHBOARD_PERIOD_S)

    def shutdown() -> None:
        done.set()
        for step in (lambda: ctrl.speedStop(cfg["stop_deceleration"]), ctrl.stopScript, ctrl.disconnect,
                     recv.disconnect):
            with contextlib.suppress(Exception):  # best effort: the link may already be gone
                step()
        os._exit(0)

    send(("ready", (priority, *installation)))
    threading.Thread(target=reader, name="ur-driver-reader", daemon=True).start()
    threading.Thread(target=watch_dashboard, name="ur-driver-dashboard", daemon=True).start()
    parent_timeout = cfg["parent_timeout"]
    last_parent = time.monotonic()
    moving = False
    next_kick = time.monotonic()
    while not done.is_set():
        if takeover:
            # Local control: the person at the robot has it. Stop the arm and the script (the reader streams on
            # meanwhile), then leave; the agent, told already, keeps the driver down until the edge is armed again.
            for step in (lambda: ctrl.speedStop(cfg["stop_deceleration"]), ctrl.stopScript):
                with contextlib.suppress(Exception):
                    step()
            shutdown()
        if moving and program_stopped.is_set():
            # Stopped or paused under a motion: a speedStop, which ur_rtde turns into a cleared command register
            # when the program does not run, so that a paused program that resumes finds no stale speedL there.
            with contextlib.suppress(RuntimeError):
                ctrl.speedStop(cfg["stop_deceleration"])
            moving = False
        commanded = False
        try:
            if conn.poll(max(0.0, next_kick - time.monotonic())):
                while conn.poll(0):
                    kind, *args = conn.recv()
                    last_parent = time.monotonic()
                    started = time.monotonic()
                    if kind == "twist":
                        twist, acceleration = args
                        # speedL answers False when no script runs; on a dead link it answers True (the link
                        # checks are the reader's job). A refusal is logged by the agent; the state decides.
                        if not ctrl.speedL(twist, acceleration, 0.0):
                            send(("refused", "speedL refused by the controller (program not running?)"))
                        moving, commanded = any(twist), True
                        writes.wrote(started, time.monotonic())
                    elif kind == "stop":
                        ctrl.speedStop(args[0])
                        moving, commanded = False, True
                        writes.wrote(started, time.monotonic())
                    elif kind == "close":
                        shutdown()
        except (EOFError, OSError):  # the agent is gone: stop the robot and leave
            shutdown()
        except RuntimeError as exc:  # ur_rtde raises when its own reconnect to a lost controller fails
            send(("lost", f"RTDE link to the controller lost ({exc})"))
            shutdown()
        now = time.monotonic()
        if now < next_kick and not commanded:
            continue
        next_kick = now + period
        agent_alive = now - last_parent < parent_timeout
        if not agent_alive and moving:
            # The agent went silent (hung, not killed: a killed one closes the pipe). Stop here first; the
            # controller's watchdog, no longer kicked, is the next layer.
            with contextlib.suppress(Exception):
                ctrl.speedStop(cfg["stop_deceleration"])
            moving = False
        elif agent_alive and not commanded and not program_stopped.is_set():
            try:
                ctrl.kickWatchdog()  # a command written this cycle already counts as a kick
                writes.wrote(now, time.monotonic())
            except RuntimeError as exc:
                send(("lost", f"RTDE link to the controller lost ({exc})"))
                shutdown()
    shutdown()


# ---------------------------------------------------------------------------------------------------------
# The agent side.


class URRobot(Robot):
    """The agent's side: a driver child process in one of three phases, ``down`` → ``connecting`` → ``up``.
    Every method returns at once; a fault sends the phase back to ``down`` and schedules a reconnect with
    back-off (0.5 s doubling to ``reconnect_max_s``)."""

    def __init__(self, config: URRobotConfig, stop_deceleration: float, realtime: bool = True,
                 tcp_offset: Sequence[float] | None = None) -> None:
        self.config = config
        self.tcp_offset = None if tcp_offset is None else [float(v) for v in tcp_offset]  # goto.tcp_offset
        self.stop_deceleration = stop_deceleration  # the safety config's, for the child's own stops
        self.realtime = realtime  # the edge's setting: real time for the driver's command thread where allowed
        self.driver_priority = ""  # what the driver's command thread got, once connected
        self._ctx = mp.get_context("spawn")  # never fork a process that holds Zenoh threads
        self._proc: mp.process.BaseProcess | None = None
        self._conn: Connection | None = None
        self._phase = "down"
        self._connecting_since = 0.0
        self._state: tuple | None = None
        self._state_at = 0.0  # monotonic time the newest state arrived
        self._stamp_changed_at = 0.0  # monotonic time the controller timestamp last advanced
        self._fault = "not connected"
        self._backoff = 0.5
        self._retry_at = 0.0
        self._closing = False
        self._refusal_logged = 0.0
        self._child_started = False
        self._stopped_since: float | None = None  # monotonic time the program was first seen stopped
        self._controller_stop = ""  # a stop of the controller's own seen on this connection (its name), until cleared
        self._held = ""  # somebody at the robot took it over (why): no driver until allow_restart()
        # What the dashboard called the edge's script on the last connection (None: not known): a reconnect after a
        # fault does not upload over a program of another name (somebody's at the robot).
        self._script_name: str | None = None
        self._dashboard_problem = ""  # why local control cannot be seen ("" while the dashboard answers)
        self._speed_fraction: float | None = None  # the pendant's speed slider as last reported; None: not yet
        self.installation: tuple[list[float], float] | None = None  # the controller's TCP offset and payload (kg)

    @property
    def control_period(self) -> float:
        return 1.0 / self.config.control_rate_hz

    # ---------------------------------------------------------------- process management

    def _spawn(self) -> None:
        parent, child = self._ctx.Pipe()
        cfg = {k: v for k, v in asdict(self.config).items() if k in (
            "host", "rtde_frequency", "watchdog_hz", "tcp_tolerance_m", "tcp_tolerance_rad", "payload_kg",
            "payload_tolerance_kg")}
        cfg["tcp_offset"] = self.tcp_offset
        cfg["stop_deceleration"] = self.stop_deceleration
        cfg["realtime"] = self.realtime
        cfg["script_name"] = self._script_name
        # The agent heartbeats every control cycle; silence for two watchdog periods means it is frozen.
        cfg["parent_timeout"] = max(2.0 / self.config.watchdog_hz, 3 * self.control_period)
        self._proc = self._ctx.Process(target=_driver_main, args=(child, cfg), name="ur-driver", daemon=True)
        self._proc.start()
        child.close()
        self._conn = parent
        self._phase, self._connecting_since, self._child_started = "connecting", time.monotonic(), False

    def _kill(self) -> None:
        if self._proc is not None and self._proc.is_alive():
            self._proc.kill()
            self._proc.join(2.0)
        if self._conn is not None:
            self._conn.close()
        self._proc, self._conn, self._phase = None, None, "down"

    def _fail(self, reason: str) -> None:
        """A fault: kill the driver, keep the reason, schedule a reconnect (none while held, see _hold)."""
        if self._held:
            reason = self._held  # the driver's end after a takeover is no news: the takeover stays the reason
        if reason != self._fault:
            log.error("UR driver fault: %s", reason)
        self._fault = reason
        self._kill()
        self._retry_at = time.monotonic() + self._backoff
        self._backoff = min(self._backoff * 2, self.config.reconnect_max_s)

    def _hold(self, reason: str) -> None:
        """Somebody at the robot took it over: the reason is the fault and the takeover the agent disarms on, and
        no driver starts again until :meth:`allow_restart`. The current one is left to end by itself (after local
        control it stops the arm and the script first; after another program was played it leaves at once, writing
        nothing to their program) or by the next fault check."""
        if not self._held:
            log.warning("UR: %s — the driver stays down until the edge is armed again", reason)
        self._held = self._fault = reason

    def allow_restart(self) -> None:
        """The edge was armed again (the on-site confirmation): a held driver connects again at once."""
        if self._held:
            log.info("UR: armed again after \"%s\": reconnecting", self._held)
            self._held = ""
            self._script_name = None  # armed on site: no script of the edge's is known to run (nor uploaded over any)
            self._retry_at = time.monotonic()
            self._backoff = 0.5

    def _check_ready(self) -> None:
        """In ``connecting``: take the driver's first message if there is one, or time out."""
        assert self._conn is not None and self._proc is not None
        waited = time.monotonic() - self._connecting_since
        if not self._conn.poll(0):
            if not self._child_started and waited > SPAWN_TIMEOUT:
                self._fail(f"UR driver process did not start within {SPAWN_TIMEOUT:g} s (machine overloaded?)")
            elif self._child_started and waited > self.config.connect_timeout:
                self._fail(f"UR controller at {self.config.host} did not answer within "
                           f"{self.config.connect_timeout:g} s (hung or half-open connection?)")
            elif not self._proc.is_alive():
                self._fail(f"UR driver for {self.config.host} exited while connecting")
            return
        try:
            kind, text = self._conn.recv()
        except (EOFError, OSError):
            self._fail(f"UR driver for {self.config.host} died while connecting")
            return
        if kind == "connecting":
            self._connecting_since, self._child_started = time.monotonic(), True
            return
        if kind == "takeover":  # another program plays: the driver left without uploading the edge's script
            self._hold(text)
            self._fail(text)
            return
        if kind == "wait":  # what must change at the controller first; it left without uploading, and is retried
            self._fail(text)
            return
        if kind != "ready":
            self._fail(f"cannot connect to the UR controller at {self.config.host}: {text}")
            return
        now = time.monotonic()
        self._phase, self._fault, self._state = "up", "", None
        self._stopped_since, self._speed_fraction, self._controller_stop = None, None, ""
        self._state_at = self._stamp_changed_at = now
        self._backoff = 0.5
        priority, tcp, payload = text
        log.info("connected to UR controller at %s (watchdog %.0f Hz; the driver's command thread at %s priority; "
                 "TCP offset %s, payload %.3f kg)", self.config.host, self.config.watchdog_hz, priority, _fmt(tcp),
                 payload)
        if self.installation is None:  # once: the configuration does not change between reconnects
            for setting_name, expected, value in (
                    ("goto.tcp_offset", self.tcp_offset, f"TCP offset {_fmt(tcp)}"),
                    ("robot.payload_kg", self.config.payload_kg, f"payload {payload:.3f} kg")):
                if expected is None:
                    log.warning("%s is not set: the controller's %s is not checked against what the workspace "
                                "box, the kinematics and the force levels assume", setting_name, value)
        self.driver_priority, self.installation = priority, (tcp, payload)

    def connect(self) -> None:
        """Connect, waiting up to ``connect_timeout``; raise RobotFault with the reason otherwise."""
        self._closing = False
        self._spawn()
        while self._phase == "connecting":
            if self._conn is not None:
                self._conn.poll(0.01)  # wake on the driver's message rather than sleeping past it
            self._check_ready()
        if self._phase != "up":
            raise RobotFault(self._fault)

    # ---------------------------------------------------------------- Robot interface

    def _pump(self) -> None:
        """In ``up``: take every message the driver sent, check the link's health, send the heartbeat."""
        assert self._conn is not None and self._proc is not None
        try:
            while self._conn.poll(0):
                kind, payload = self._conn.recv()
                if kind == "state":
                    if self._state is None or payload[3] != self._state[3]:
                        self._stamp_changed_at = time.monotonic()
                    self._state, self._state_at = payload, time.monotonic()
                    self._note_speed_fraction(float(payload[10]))
                    self._note_dashboard(payload[12])
                elif kind == "takeover":
                    self._hold(payload)
                elif kind == "script":
                    self._script_name = payload
                elif kind == "lost":
                    self._fail(payload)
                    return
                elif kind == "refused":
                    # Not a fault by itself: the state (program running, safety mode) tells why, next cycle.
                    now = time.monotonic()
                    if now - self._refusal_logged > 1.0:
                        log.warning("UR driver: %s", payload)
                        self._refusal_logged = now
        except (EOFError, OSError):
            code = self._proc.exitcode
            self._fail("UR driver process " + ("closed its pipe to the agent" if code is None else exit_reason(code)))
            return
        now = time.monotonic()
        if not self._proc.is_alive():
            self._fail(f"UR driver process {exit_reason(self._proc.exitcode)}")
        elif now - self._state_at > self.config.link_timeout:
            self._fail(f"no state from the UR driver for {1000 * (now - self._state_at):.0f} ms (driver hung)")
        elif self._state is not None and not (self._state[6] and self._state[9]):
            which = "receive" if not self._state[6] else "control"
            self._fail(f"RTDE link to the controller lost ({which} interface disconnected)")
        elif now - self._stamp_changed_at > self.config.link_timeout:
            self._fail(f"controller timestamp frozen for {1000 * (now - self._stamp_changed_at):.0f} ms (link lost)")
        elif problem := send_without_blocking(self._conn, ("heartbeat",)):
            self._fail(problem)

    def _note_speed_fraction(self, fraction: float) -> None:
        """Warn when the pendant's speed slider leaves 100 % (and at connect when it is already below), and when it
        comes back: the operator's commanded speeds are then not what the arm does."""
        previous, self._speed_fraction = self._speed_fraction, fraction
        if previous is not None and abs(fraction - previous) < 0.005:
            return
        if fraction < FULL_SPEED:
            log.warning("UR speed slider at %.0f %%: the arm moves at %.0f %% of every commanded speed (set it to "
                        "100 %% on the teach pendant)", 100 * fraction, 100 * fraction)
        elif previous is not None:
            log.info("UR speed slider back at 100 %%")

    def _note_dashboard(self, problem: str) -> None:
        """Log once when the dashboard stops answering (local control can then not be seen) and when it is back."""
        if problem != self._dashboard_problem:
            if problem:
                log.warning("UR: %s: a switch to local control on the teach pendant cannot be seen meanwhile "
                            "(asked again every %g s)", problem, DASHBOARD_PERIOD_S)
            else:
                log.info("UR: the dashboard answers again")
            self._dashboard_problem = problem

    def _health(self) -> str:
        if self._phase != "up" or self._fault:
            return self._fault or "UR driver connecting"
        if self._state is None:
            return ""
        robot_mode, safety_mode, program_running, stop_late = (self._state[4], self._state[5], self._state[7],
                                                               self._state[11])
        if safety_mode in SAFETY_MODES or robot_mode != ROBOT_MODE_RUNNING:
            # The driver stays up: the controller must be cleared by a person first.
            self._stopped_since = None
            self._controller_stop = SAFETY_NAMES.get(safety_mode) or ROBOT_MODES.get(robot_mode, "not running")
            return SAFETY_MODES[safety_mode] if safety_mode in SAFETY_MODES else not_running(robot_mode)
        if self._controller_stop:
            # Cleared. A fresh connection (a new script, whose first command is a stop) whether the program was
            # stopped (protective stop, e-stop, power off) or paused and resumed by itself (a safeguard stop): a
            # resumed script runs whatever command is left in its registers. The supervisor stays latched.
            self._fail(f"{self._controller_stop} cleared on the controller: reconnecting with a fresh control script")
            return self._fault
        if program_running:
            self._stopped_since = None
            return ""
        # ur_rtde's control and receive streams lag each other by up to a period: a protective stop may show as a
        # stopped program before its safety mode arrives. Report at once, but judge the stop only once the program
        # has been stopped for link_timeout with no stop of the controller's own seen meanwhile.
        now = time.monotonic()
        if self._stopped_since is None:
            self._stopped_since = now
        if now - self._stopped_since < self.config.link_timeout:
            return "control script not running on the controller"
        if stop_late is False:
            # The driver wrote on time: stopped from outside the edge (the module's docstring says why this is the
            # side taken when in doubt). The agent disarms; no new script until the edge is armed again.
            self._hold(PROGRAM_STOPPED_OUTSIDE)
            self._fail(PROGRAM_STOPPED_OUTSIDE)
            return self._fault
        # The driver's writes were late around the stop (or it never saw this script run): the RTDE watchdog may
        # have expired on the edge's account. A fresh connection uploads the script and sets the watchdog again;
        # the supervisor stays latched meanwhile.
        self._fail("control script not running on the controller (the RTDE watchdog: the edge's writes were late)")
        return self._fault

    def read_state(self) -> RobotReading:
        if self._phase == "up":
            self._pump()
        elif self._phase == "connecting":
            self._check_ready()
        elif not self._closing and not self._held and time.monotonic() >= self._retry_at:
            self._spawn()
        fault = self._health()
        if self._state is None:
            zeros = np.zeros(6)
            return RobotReading(zeros, zeros, zeros, time.time_ns(), mode="disconnected", connected=False,
                                fault=(fault or "no state from the controller yet")[:FAULT_MAX], takeover=self._held)
        pose, speed, q, stamp, robot_mode, safety_mode, connected, running, force, _, fraction, _, _ = self._state
        # A short mode (state/robot allows 40 characters; the fault carries the long explanation).
        mode = SAFETY_NAMES.get(safety_mode) or ROBOT_MODES.get(robot_mode, f"mode {robot_mode}")
        if safety_mode == SAFETY_MODE_REDUCED:  # the safety system's lower limits apply
            mode += ", reduced"
        if not running:
            mode += ", no program"
        if fraction < FULL_SPEED:  # the operator's screen says why the arm is slower than commanded
            mode += f", speed {100 * fraction:.0f}%"
        if self._dashboard_problem and self._phase == "up":  # local control cannot be seen meanwhile
            mode += ", no dashboard"
        return RobotReading(
            tcp_pose=np.array(pose), tcp_speed=np.array(speed), q=np.array(q), timestamp_ns=time.time_ns(),
            robot_time=float(stamp), mode=mode[:MODE_MAX],
            connected=bool(connected) and self._phase == "up", fault=fault[:FAULT_MAX], tcp_force=np.array(force),
            takeover=self._held,
        )

    def send_twist(self, twist: Sequence[float], acceleration: float) -> Vector:
        fault = self._health()
        if fault or self._conn is None:
            raise RobotFault(fault or "UR driver not connected")
        sent = [float(v) for v in twist]
        if problem := send_without_blocking(self._conn, ("twist", sent, float(acceleration))):
            self._fail(problem)
            raise RobotFault(self._fault)
        # The pendant's speed slider scales the controller's speedL: what the arm makes is the twist times it, and
        # that is what the applied echo and state/robot report.
        fraction = 1.0 if self._speed_fraction is None else min(max(self._speed_fraction, 0.0), 1.0)
        return np.array(sent) * fraction

    def stop(self, deceleration: float) -> None:
        if self._phase != "up" or self._conn is None:
            return  # no driver: nothing moves through us, and the controller's watchdog covers the rest
        if problem := send_without_blocking(self._conn, ("stop", float(deceleration))):
            self._fail(problem)

    def disconnect(self) -> None:
        self._closing = True
        if (self._phase == "up" and self._conn is not None and self._proc is not None
                and not send_without_blocking(self._conn, ("close",))):
            self._proc.join(self.config.connect_timeout)  # its own stop and goodbye to the controller first
        self._kill()
        self._fault = "disconnected"
