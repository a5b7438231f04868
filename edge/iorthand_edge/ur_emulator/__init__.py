"""UR e-Series controller emulator that the real ur_rtde library (1.6.5) accepts.

It serves, on one loopback address, what ur_rtde talks to:

* RTDE (30004): protocol v2, controller version (5.15.2 by default, so ur_rtde takes its e-Series paths),
  output/input recipes with the controller's variable types (``NOT_FOUND`` / ``IN_USE`` answers like a
  controller), streaming at each client's frequency, input packages; several clients at once.
* Dashboard (29999): PolyScope 5 answers (version, serial number, remote control, robot/safety mode, program
  state, play/stop/pause, power, brake release, unlock protective stop with PolyScope's 5 s refusal, popups).
* Script (30003, also 30002): receives the uploaded control script and runs an interpreter of its register
  protocol (:mod:`.control_script`): speedL/J, speedStop, stopL/J, moveL/J (sync/async, _IK/_FK), movePath,
  servoL/J, forceMode, jog, setTcp, setWatchdog (+ kickWatchdog), zeroFtSensor, triggerProtectiveStop,
  stopScript, getters (forward/inverse kinematics, poseTrans, isSteady, safety limits, ...).
* An arm with joints (:mod:`.arm`, UR3e or UR5e): Cartesian commands move the TCP (:mod:`.kinematics`: ramps
  with the commanded accelerations, straight-line moveL) and the joints follow by inverse kinematics
  (:mod:`iorthand.kinematics`, the solution nearest the previous joints); joint commands move the joints and the
  TCP follows. A target out of reach fails the program (runtime error, the arm does not move); a joint limit
  or a singularity met during a motion is a protective stop.
* A force/torque sensor: the injected wrench plus the contact with a phantom
  (:mod:`iorthand_edge.force.contact`) at the TCP; force mode regulates it by a simple admittance.
* Fault injection (:class:`UREmulator` methods, or the JSON-lines control socket, default port 30101, used by
  :class:`ControlClient` and ``--inject``): link drop, frozen output stream, protective/emergency stop, TCP
  force, hung controller, a silent dashboard; placing the arm (pose, joints) and the phantom; and what a person at
  the teach pendant does (speed slider, local control, safety modes: a safeguard stop pauses the program, which
  resumes at the reset, as on an e-Series).

ur_rtde 1.6.5 hard-codes its ports, so emulators coexist on different loopback addresses (127.0.0.2, ...),
which ur_rtde accepts as hostnames. Run it with :func:`main` / ``python -m iorthand_edge.ur_emulator``.
"""

from .arm import ArmModel, ForceMode, Unreachable
from .cli import main
from .controller import Controller, ControllerConfig, RobotMode, RuntimeState, SafetyMode
from .emulator import DEFAULT_CONTROL_PORT, EmulatorConfig, UREmulator
from .faults import OPS, ControlClient
from .kinematics import HOME_POSE, HOME_Q

__all__ = [
    "DEFAULT_CONTROL_PORT",
    "HOME_POSE",
    "HOME_Q",
    "OPS",
    "ArmModel",
    "ControlClient",
    "Controller",
    "ControllerConfig",
    "EmulatorConfig",
    "ForceMode",
    "RobotMode",
    "RuntimeState",
    "SafetyMode",
    "UREmulator",
    "Unreachable",
    "main",
]
