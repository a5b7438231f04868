"""Interpreter of ur_rtde's ``rtde_control.script`` register protocol.

The real script runs a loop once per control cycle (``sync()``):

* it reads the command id from ``input_int_register_0`` (+ offset);
* real-time commands (speedL, speedJ, servo*, forceMode, kickWatchdog's NO_CMD, getters such as
  getJointTorques) are executed and the script answers ``output_int_register_0 = 1`` (ready) at once;
* other commands are executed once (until the client writes 0 again) and answered with 2 (done) when they
  finish — a synchronous moveL or a speedStop's ``stopl`` blocks the loop until the arm has stopped;
* command 255 (stopScript) ends the program without answering.

Parameters come from ``input_double_register_0..``/``input_int_register_1..`` as laid out by the recipes of
``RTDEControlInterface::setupRecipes``; results go to ``output_double_register_0..`` / ``output_int_register_1``.
"""

from __future__ import annotations

import re

from .controller import Controller, Program, _AsyncProgress
from .kinematics import HOME_Q, MotionMode, matvec, pose_trans, rotvec_to_matrix

# Commands whose loop iteration answers "ready" immediately (the script's real-time list).
REALTIME = {24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71}

NAMES = {
    1: "moveJ", 2: "moveJ_IK", 3: "moveL", 4: "moveL_FK", 6: "forceMode", 7: "forceModeStop",
    8: "zeroFtSensor", 9: "speedJ", 10: "speedL", 11: "servoJ", 12: "servoC", 13: "setStandardDigitalOut",
    14: "setToolDigitalOut", 15: "speedStop", 16: "servoStop", 17: "setPayload", 18: "teachMode",
    19: "endTeachMode", 20: "forceModeSetDamping", 21: "forceModeSetGainScaling", 22: "setSpeedSlider",
    23: "setAnalogOutput", 24: "servoL", 25: "toolContact", 26: "getStepTime",
    27: "getActualJointPositionsHistory", 28: "getTargetWaypoint", 29: "setTcp", 30: "getInverseKinematics",
    31: "triggerProtectiveStop", 33: "stopL", 34: "stopJ", 35: "setWatchdog", 36: "isPoseWithinSafetyLimits",
    37: "isJointsWithinSafetyLimits", 38: "getJointTorques", 39: "poseTrans", 40: "getTCPOffset",
    41: "jogStart", 42: "jogStop", 43: "getForwardKinematics", 44: "getForwardKinematics(q)", 45: "movePath",
    46: "getInverseKinematics", 47: "isSteady", 48: "setConfigurableDigitalOut", 51: "moveUntilContact",
    52: "freedriveMode", 53: "endFreedriveMode", 58: "getActualToolFlangePose", 255: "stopScript",
}

_MOVEL_RE = re.compile(r"movel\(\s*p\[([^\]]*)\]\s*,\s*a\s*=\s*([-\d.eE+]+)\s*,\s*v\s*=\s*([-\d.eE+]+)")


class ControlScriptProgram(Program):
    """Emulates ``def rtde_control(): ... end`` as uploaded by RTDEControlInterface."""

    def __init__(self, name: str, text: str) -> None:
        self.name = name
        m = re.search(r"global\s+reg_offset_int\s*=\s*(\d+)", text)
        self.int_off = int(m.group(1)) if m else 0
        m = re.search(r"global\s+reg_offset_float\s*=\s*(\d+)", text)
        self.float_off = int(m.group(1)) if m else 0
        # moveL/moveJ(path) and movePath inject the path as movel(...) lines into exec_move_path().
        self.path: list[tuple[list[float], float, float]] = []
        body = text.split("def exec_move_path():", 1)[1].split("\n    end", 1)[0] if (
            "def exec_move_path():" in text) else ""
        for pose_s, a_s, v_s in _MOVEL_RE.findall(body):
            self.path.append(([float(x) for x in pose_s.split(",")], float(v_s), float(a_s)))
        self.executing = False
        self.blocking: str | None = None  # a synchronous motion the main loop waits for
        self.pending_path: list[tuple[list[float], float, float]] = []
        self.async_move = False
        self.progress = _AsyncProgress()
        self.unsupported_logged: set[int] = set()
        self.last_cmd = -1

    # register helpers (with the offsets injected into the script)
    def _i(self, c: Controller, idx: int) -> int:
        return c.in_int[idx + self.int_off]

    def _d(self, c: Controller, idx: int) -> float:
        return c.in_double[idx + self.float_off]

    def _dv(self, c: Controller, idx: int, n: int = 6) -> list[float]:
        return [c.in_double[idx + self.float_off + k] for k in range(n)]

    def _out_i(self, c: Controller, idx: int, v: int) -> None:
        c.write_out_int(idx + self.int_off, v)

    def _out_d(self, c: Controller, idx: int, values: list[float] | tuple[float, ...]) -> None:
        for k, v in enumerate(values):
            c.write_out_double(idx + self.float_off + k, v)

    def start(self, ctrl: Controller) -> None:
        ctrl.write_out_int(2 + self.int_off, self.progress.value(-1))  # reset_async_progress()
        self._out_i(ctrl, 0, 1)  # signal_ready()

    # -- main loop, one iteration per control cycle ------------------------------------------------------

    def step(self, ctrl: Controller, now: float) -> bool:
        if self.blocking is not None:
            if ctrl.model.mode in (MotionMode.MOVE, MotionMode.STOPPING):
                return True  # still inside movel()/stopl(): the loop does not read commands
            if self.pending_path:
                pose, v, a = self.pending_path.pop(0)
                ctrl.model.movel(pose, v, a)
                return True
            self.blocking = None
            self._out_i(ctrl, 0, 2)  # signal_done_with_cmd() after the blocking motion
        if self.async_move and ctrl.model.mode is not MotionMode.MOVE:
            if self.pending_path:  # next waypoint of an asynchronous path
                pose, v, a = self.pending_path.pop(0)
                ctrl.model.movel(pose, v, a)
            else:
                self.async_move = False
                ctrl.write_out_int(2 + self.int_off, self.progress.value(-1))

        cmd = self._i(ctrl, 0)
        new = cmd != self.last_cmd
        self.last_cmd = cmd
        if cmd in REALTIME:
            if new:  # the register keeps the id: the script re-executes it every cycle, count it once
                ctrl.count(NAMES.get(cmd, f"command {cmd}"))
            keep = self._process(ctrl, cmd)
            self._out_i(ctrl, 0, 1)
            return keep
        if cmd == 0:
            self.executing = False
            self._out_i(ctrl, 0, 1)
            return True
        if not self.executing:
            self.executing = True
            keep = self._process(ctrl, cmd)
            if keep and self.blocking is None:
                self._out_i(ctrl, 0, 2)
            return keep
        return True

    def _start_move(self, ctrl: Controller, moves: list[tuple[list[float], float, float]], asynchronous: bool) -> None:
        if self.async_move:  # stop_async_move(): a new move replaces a running async one
            ctrl.write_out_int(2 + self.int_off, self.progress.value(-1))
            self.async_move = False
        if not moves:
            return
        first, *rest = moves
        ctrl.model.movel(first[0], first[1], first[2])
        self.pending_path = rest
        if asynchronous:
            self.async_move = True
            ctrl.write_out_int(2 + self.int_off, self.progress.value(0))
        else:
            self.blocking = "move"

    def _process(self, c: Controller, cmd: int) -> bool:
        m = c.model
        name = NAMES.get(cmd, f"command {cmd}")
        if cmd not in REALTIME:
            c.count(name)
        if cmd == 10:  # speedL: xd in d0..5, acceleration d6, time d7 (the time is irrelevant: it repeats)
            m.speedl(self._dv(c, 0), self._d(c, 6))
            self.pending_path = []
        elif cmd == 15:  # speedStop: stopl(a), blocking until stopped
            m.stopl(self._d(c, 0))
            self.blocking = "stop"
        elif cmd in (33, 34):  # stopL / stopJ (async flag in int 1)
            m.stopl(self._d(c, 0))
            self.pending_path = []
            if self._i(c, 1) != 1:
                self.blocking = "stop"
        elif cmd == 3:  # moveL: pose d0..5, speed d6, acceleration d7, async int1
            self._start_move(c, [(self._dv(c, 0), self._d(c, 6), self._d(c, 7))], self._i(c, 1) == 1)
        elif cmd == 2:  # moveJ_IK: no joint model; move linearly at a moderate tool speed
            self._start_move(c, [(self._dv(c, 0), min(self._d(c, 6), 0.25), min(self._d(c, 7), 1.2))],
                             self._i(c, 1) == 1)
        elif cmd == 45:  # movePath / moveL(path): the moves were injected into the script text
            self._start_move(c, list(self.path), self._i(c, 1) == 1)
        elif cmd == 41:  # jogStart: speeds d0..5, feature d6 (0 base, 1 tool), acc d7
            speeds = self._dv(c, 0)
            if int(self._d(c, 6)) == 1:
                rot = rotvec_to_matrix((m.pose[3], m.pose[4], m.pose[5]))
                lin = matvec(rot, (speeds[0], speeds[1], speeds[2]))
                ang = matvec(rot, (speeds[3], speeds[4], speeds[5]))
                speeds = [*lin, *ang]
            m.speedl(speeds, self._d(c, 7))
        elif cmd in (42, 7, 16):  # jogStop / forceModeStop / servoStop
            m.stopl(1.2 if cmd == 42 else 10.0)
            self.blocking = "stop"
        elif cmd == 8:  # zeroFtSensor
            c.ft_offset = list(c.raw_force)
        elif cmd == 35:  # setWatchdog: min frequency in d0, watches input_int_register_0 (+ offset)
            freq = self._d(c, 0)
            c.watchdog = (f"input_int_register_{self.int_off}", freq) if freq > 0 else None
            c.event(f"RTDE watchdog set on input_int_register_{self.int_off} at {freq:g} Hz")
        elif cmd == 31:  # triggerProtectiveStop
            c.protective_stop("triggerProtectiveStop() from the control script")
            return False
        elif cmd == 17:  # setPayload: mass d0, cog d1..3
            c.payload = self._d(c, 0)
            c.payload_cog = self._dv(c, 1, 3)
        elif cmd in (28, 43, 44, 58):  # FK, flange pose, target waypoint: the TCP offset is zero here
            self._out_d(c, 0, m.pose)
        elif cmd == 39:  # poseTrans
            self._out_d(c, 0, pose_trans(self._dv(c, 0), self._dv(c, 6)))
        elif cmd == 40:  # getTCPOffset
            self._out_d(c, 0, [0.0] * 6)
        elif cmd in (30, 46):  # inverse kinematics: the emulator has one joint vector
            self._out_d(c, 0, HOME_Q)
        elif cmd in (36, 37):  # within safety limits
            self._out_i(c, 1, 1)
        elif cmd == 47:  # isSteady
            self._out_i(c, 1, 1 if m.steady and m.mode in (MotionMode.IDLE, MotionMode.SPEED) else 0)
        elif cmd == 26:  # getStepTime
            self._out_d(c, 0, [1.0 / c.config.frequency])
        elif cmd in (38, 27):  # getJointTorques / joint history
            self._out_d(c, 0, [0.0] * 6 if cmd == 38 else list(HOME_Q))
        elif cmd == 255:  # stopScript
            return False
        elif cmd not in self.unsupported_logged:
            # Everything else is acknowledged so that ur_rtde does not wait for its 300 s timeout.
            self.unsupported_logged.add(cmd)
            c.event(f"control script: {name} acknowledged without effect (not emulated)")
        return True
