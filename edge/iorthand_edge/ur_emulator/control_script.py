"""Interpreter of ur_rtde's ``rtde_control.script`` register protocol.

The real script runs a loop once per control cycle (``sync()``):

* it reads the command id from ``input_int_register_0`` (+ offset);
* real-time commands (speedL, speedJ, servoJ, servoL, forceMode, kickWatchdog's NO_CMD, getters such as
  getJointTorques) are executed and the script answers ``output_int_register_0 = 1`` (ready) at once;
* other commands are executed once (until the client writes 0 again) and answered with 2 (done) when they
  finish — a synchronous moveL or a speedStop's ``stopl`` blocks the loop until the arm has stopped;
* command 255 (stopScript) ends the program without answering.

Parameters come from ``input_double_register_0..``/``input_int_register_1..`` as laid out by the recipes of
``RTDEControlInterface::setupRecipes``; results go to ``output_double_register_0..`` / ``output_int_register_1``.

A target without inverse kinematics solution (moveL, moveJ_IK, servoL, getInverseKinematics) makes URScript's
interpreter fail: the program stops with a runtime error, the arm does not move and ur_rtde's pending call
answers False ("RTDE control script is not running") or raises ("... did not succeed"), as with a controller.
"""

from __future__ import annotations

import re

from .arm import ForceMode, Unreachable
from .controller import Controller, Program, _AsyncProgress
from .kinematics import MotionMode, matvec, pose_trans, rotvec_to_matrix

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
    52: "freedriveMode", 53: "endFreedriveMode", 58: "getActualToolFlangePose",
    60: "getInverseKinematicsHasSolution", 61: "getInverseKinematicsHasSolution(qnear)", 255: "stopScript",
}

# A path's entries as ur_rtde's PathEntry writes them: movel/movej to a pose (p[...]) or to joints ([...]).
_MOVE_RE = re.compile(
    r"(movel|movej)\(\s*(p?)\[([^\]]*)\]\s*,\s*a\s*=\s*([-\d.eE+]+)\s*,\s*v\s*=\s*([-\d.eE+]+)")

#: One motion: kind ("l" movel to a pose, "l_fk" movel to joints, "j" movej to joints, "j_ik" movej to a pose),
#: target, speed, acceleration.
Move = tuple[str, list[float], float, float]
_KINDS = {("movel", True): "l", ("movel", False): "l_fk", ("movej", True): "j_ik", ("movej", False): "j"}

_BLOCKING = (MotionMode.MOVE, MotionMode.MOVE_JOINT, MotionMode.STOPPING)
_MOVING = (MotionMode.MOVE, MotionMode.MOVE_JOINT)


class ControlScriptProgram(Program):
    """Emulates ``def rtde_control(): ... end`` as uploaded by RTDEControlInterface."""

    def __init__(self, name: str, text: str) -> None:
        self.name = name
        m = re.search(r"global\s+reg_offset_int\s*=\s*(\d+)", text)
        self.int_off = int(m.group(1)) if m else 0
        m = re.search(r"global\s+reg_offset_float\s*=\s*(\d+)", text)
        self.float_off = int(m.group(1)) if m else 0
        # moveL/moveJ(path) and movePath inject the path as movel(...)/movej(...) lines into exec_move_path().
        self.path: list[Move] = []
        body = text.split("def exec_move_path():", 1)[1].split("\n    end", 1)[0] if (
            "def exec_move_path():" in text) else ""
        for fn, p, values, a_s, v_s in _MOVE_RE.findall(body):
            self.path.append((_KINDS[fn, p == "p"], [float(x) for x in values.split(",")], float(v_s), float(a_s)))
        self.executing = False
        self.blocking: str | None = None  # a synchronous motion the main loop waits for
        self.pending_path: list[Move] = []
        self.speed_type = "l"  # the last speed command, speedL or speedJ: speedStop stops it with stopl or stopj
        self.last_realtime: tuple[object, ...] | None = None  # the parameters of the last real-time command run
        self.async_move = False
        self.progress = _AsyncProgress()
        self.unsupported_logged: set[int | str] = set()
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

    def _run(self, ctrl: Controller, move: Move) -> bool:
        """Start one motion; False (the program has stopped) if its target has no inverse kinematics solution."""
        kind, target, v, a = move
        m = ctrl.model
        try:
            if kind == "l":
                m.movel(target, v, a)
            elif kind == "l_fk":
                m.movel_fk(target, v, a)
            elif kind == "j":
                m.movej(target, v, a)
            else:
                m.movej_ik(target, v, a)
        except Unreachable as exc:
            ctrl.runtime_exception(str(exc))
            return False
        return True

    def step(self, ctrl: Controller, now: float) -> bool:
        if self.blocking is not None:
            if ctrl.model.mode in _BLOCKING:
                return True  # still inside movel()/movej()/stopl(): the loop does not read commands
            if self.pending_path:
                return self._run(ctrl, self.pending_path.pop(0))
            self.blocking = None
            self._out_i(ctrl, 0, 2)  # signal_done_with_cmd() after the blocking motion
        if self.async_move and ctrl.model.mode not in _MOVING:
            if self.pending_path:  # next waypoint of an asynchronous path
                if not self._run(ctrl, self.pending_path.pop(0)):
                    return False
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

    def _start_move(self, ctrl: Controller, moves: list[Move], asynchronous: bool) -> bool:
        if self.async_move:  # stop_async_move(): a new move replaces a running async one
            ctrl.write_out_int(2 + self.int_off, self.progress.value(-1))
            self.async_move = False
        if not moves:
            return True
        first, *rest = moves
        if not self._run(ctrl, first):
            return False
        self.pending_path = rest
        if asynchronous:
            self.async_move = True
            ctrl.write_out_int(2 + self.int_off, self.progress.value(0))
        else:
            self.blocking = "move"
        return True

    def _process(self, c: Controller, cmd: int) -> bool:
        name = NAMES.get(cmd, f"command {cmd}")
        if cmd not in REALTIME:
            c.count(name)
        try:
            return self._execute(c, cmd, name)
        except Unreachable as exc:  # get_inverse_kin failed inside the command: a runtime error stops the program
            c.runtime_exception(f"{name}: {exc}")
            return False

    def _execute(self, c: Controller, cmd: int, name: str) -> bool:
        m = c.model
        if cmd in (24, 11, 6):
            # servoL/servoJ/forceMode run again every cycle while the register holds them: redo the work (an
            # inverse kinematics for servoL) only when the client sent new parameters.
            params = (cmd, *c.in_double[self.float_off:self.float_off + 18], *c.in_int[self.int_off:self.int_off + 8])
            if params == self.last_realtime:
                return True
            self.last_realtime = params
        else:
            self.last_realtime = None
        if cmd == 10:  # speedL: xd in d0..5, acceleration d6, time d7 (the time is irrelevant: it repeats)
            m.speedl(self._dv(c, 0), self._d(c, 6))
            self.speed_type = "l"
            self.pending_path = []
        elif cmd == 9:  # speedJ: qd in d0..5, acceleration d6, time d7
            m.speedj(self._dv(c, 0), self._d(c, 6))
            self.speed_type = "j"
            self.pending_path = []
        elif cmd == 15:  # speedStop: stopl(a) after speedL, stopj(a) after speedJ; blocking until stopped
            if self.speed_type == "j":
                m.stopj(self._d(c, 0))
            else:
                m.stopl(self._d(c, 0))
            self.blocking = "stop"
        elif cmd in (33, 34):  # stopL / stopJ (async flag in int 1)
            if cmd == 34:
                m.stopj(self._d(c, 0))
            else:
                m.stopl(self._d(c, 0))
            self.pending_path = []
            if self._i(c, 1) != 1:
                self.blocking = "stop"
        elif cmd in (1, 2, 3, 4):  # moveJ, moveJ_IK, moveL, moveL_FK: target d0..5, speed d6, acc d7, async int1
            kind = {1: "j", 2: "j_ik", 3: "l", 4: "l_fk"}[cmd]
            return self._start_move(c, [(kind, self._dv(c, 0), self._d(c, 6), self._d(c, 7))], self._i(c, 1) == 1)
        elif cmd == 45:  # movePath / moveL(path) / moveJ(path): the moves were injected into the script text
            return self._start_move(c, list(self.path), self._i(c, 1) == 1)
        elif cmd == 11:  # servoJ: q d0..5, speed d6, acc d7, time d8, lookahead d9, gain d10
            m.servoj(self._dv(c, 0), self._d(c, 9))
        elif cmd == 24:  # servoL: the script's q = get_inverse_kin(pose), then servoj(q)
            m.servol(self._dv(c, 0), self._d(c, 9))
        elif cmd == 6:  # forceMode: task frame d0..5, wrench d6..11, limits d12..17, type int1, selection int2..7
            kind = self._i(c, 1)
            if kind != 2 and "force_mode_type" not in self.unsupported_logged:
                self.unsupported_logged.add("force_mode_type")
                c.event(f"control script: force mode type {kind} emulated as type 2 (task frame as given)")
            m.force_mode(ForceMode(self._dv(c, 0), [self._i(c, 2 + k) != 0 for k in range(6)], self._dv(c, 6),
                                   self._dv(c, 12), gain=c.config.force_gain))
        elif cmd == 7:  # forceModeStop: end_force_mode(), stopl(10)
            m.end_force_mode()
            m.stopl(10.0)
            self.blocking = "stop"
        elif cmd == 41:  # jogStart: speeds d0..5, feature d6 (0 base, 1 tool), acc d7
            speeds = self._dv(c, 0)
            if int(self._d(c, 6)) == 1:
                rot = rotvec_to_matrix((m.pose[3], m.pose[4], m.pose[5]))
                lin = matvec(rot, (speeds[0], speeds[1], speeds[2]))
                ang = matvec(rot, (speeds[3], speeds[4], speeds[5]))
                speeds = [*lin, *ang]
            m.speedl(speeds, self._d(c, 7))
        elif cmd in (42, 16):  # jogStop: stopl(1.2); servoStop: stopl(a) with a in d0
            m.stopl(1.2 if cmd == 42 else self._d(c, 0))
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
        elif cmd == 28:  # getTargetWaypoint
            self._out_d(c, 0, m.pose)
        elif cmd == 43:  # getForwardKinematics(): the TCP at the current joints
            self._out_d(c, 0, m.fk(m.q))
        elif cmd == 44:  # getForwardKinematics(q, tcp_offset): q d0..5, offset d6..11
            self._out_d(c, 0, m.fk(self._dv(c, 0), self._dv(c, 6)))
        elif cmd == 58:  # getActualToolFlangePose
            self._out_d(c, 0, m.flange_pose())
        elif cmd == 29:  # setTcp: pose d0..5
            m.set_tcp(self._dv(c, 0))
        elif cmd == 39:  # poseTrans
            self._out_d(c, 0, pose_trans(self._dv(c, 0), self._dv(c, 6)))
        elif cmd == 40:  # getTCPOffset
            self._out_d(c, 0, m.tcp_offset)
        elif cmd in (30, 46):  # getInverseKinematics: x d0..5 (and qnear d6..11); no solution: runtime error
            q, why = m.ik(self._dv(c, 0), self._dv(c, 6) if cmd == 30 else None)
            if q is None:
                raise Unreachable(f"get_inverse_kin: {why}")
            self._out_d(c, 0, q.tolist())
        elif cmd in (60, 61):  # getInverseKinematicsHasSolution: answers instead of failing
            q, _why = m.ik(self._dv(c, 0), self._dv(c, 6) if cmd == 61 else None)
            self._out_i(c, 1, 0 if q is None else 1)
        elif cmd == 36:  # isPoseWithinSafetyLimits: reachable within the joint limits
            self._out_i(c, 1, 0 if m.ik(self._dv(c, 0))[0] is None else 1)
        elif cmd == 37:  # isJointsWithinSafetyLimits
            self._out_i(c, 1, 1 if m.within_limits(self._dv(c, 0)) else 0)
        elif cmd == 47:  # isSteady
            steady_modes = (MotionMode.IDLE, MotionMode.SPEED, MotionMode.SERVO)
            self._out_i(c, 1, 1 if m.steady and m.mode in steady_modes else 0)
        elif cmd == 26:  # getStepTime
            self._out_d(c, 0, [1.0 / c.config.frequency])
        elif cmd in (38, 27):  # getJointTorques / joint history
            self._out_d(c, 0, [0.0] * 6 if cmd == 38 else m.q.tolist())
        elif cmd == 255:  # stopScript
            return False
        elif cmd not in self.unsupported_logged:
            # Everything else is acknowledged so that ur_rtde does not wait for its 300 s timeout.
            self.unsupported_logged.add(cmd)
            c.event(f"control script: {name} acknowledged without effect (not emulated)")
        return True
