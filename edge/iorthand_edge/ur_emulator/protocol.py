"""RTDE wire format: message framing, package types and the variable → data type table.

Every RTDE message is ``uint16 size (including the 3-byte header) | uint8 type | payload``, big-endian. The
variable types follow UR's RTDE guide; a name that is not in the tables answers ``NOT_FOUND`` (outputs) like
a controller does, and ur_rtde then raises with the list of unknown names.
"""

from __future__ import annotations

import re

# The framing and package types, shared with the edge's UR driver (which reads one output ur_rtde has no getter for).
from iorthand_edge.robots.rtde_wire import (  # noqa: F401 (the emulator's modules take them from here)
    CONTROL_PACKAGE_PAUSE,
    CONTROL_PACKAGE_SETUP_INPUTS,
    CONTROL_PACKAGE_SETUP_OUTPUTS,
    CONTROL_PACKAGE_START,
    DATA_PACKAGE,
    GET_URCONTROL_VERSION,
    HEADER,
    REQUEST_PROTOCOL_VERSION,
    TEXT_MESSAGE,
    pack_message,
    read_message,
    recv_exact,
)

#: struct format of each RTDE data type (without byte order).
TYPE_FORMATS: dict[str, str] = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}

OUTPUT_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE",
    "target_q": "VECTOR6D",
    "target_qd": "VECTOR6D",
    "target_qdd": "VECTOR6D",
    "target_current": "VECTOR6D",
    "target_moment": "VECTOR6D",
    "actual_q": "VECTOR6D",
    "actual_qd": "VECTOR6D",
    "actual_qdd": "VECTOR6D",
    "actual_current": "VECTOR6D",
    "actual_current_window": "VECTOR6D",
    "actual_current_as_torque": "VECTOR6D",
    "joint_control_output": "VECTOR6D",
    "actual_TCP_pose": "VECTOR6D",
    "actual_TCP_speed": "VECTOR6D",
    "actual_TCP_force": "VECTOR6D",
    "target_TCP_pose": "VECTOR6D",
    "target_TCP_speed": "VECTOR6D",
    "actual_digital_input_bits": "UINT64",
    "joint_temperatures": "VECTOR6D",
    "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32",
    "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE",
    "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE",
    "actual_joint_voltage": "VECTOR6D",
    "actual_digital_output_bits": "UINT64",
    "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D",
    "elbow_velocity": "VECTOR3D",
    "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32",
    "analog_io_types": "UINT32",
    "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE",
    "io_current": "DOUBLE",
    "tool_mode": "UINT32",
    "tool_analog_input_types": "UINT32",
    "tool_analog_input0": "DOUBLE",
    "tool_analog_input1": "DOUBLE",
    "tool_output_voltage": "INT32",
    "tool_output_current": "DOUBLE",
    "tool_temperature": "DOUBLE",
    "tcp_force_scalar": "DOUBLE",
    "output_bit_registers0_to_31": "UINT32",
    "output_bit_registers32_to_63": "UINT32",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "tool_output_mode": "UINT8",
    "tool_digital_output0_mode": "UINT8",
    "tool_digital_output1_mode": "UINT8",
    "payload": "DOUBLE",
    "payload_cog": "VECTOR3D",
    "payload_inertia": "VECTOR6D",
    "script_control_line": "UINT32",
    "ft_raw_wrench": "VECTOR6D",
    "joint_position_deviation_ratio": "DOUBLE",
    "collision_detection_ratio": "DOUBLE",
    "time_scale_source": "UINT32",
    "tcp_offset": "VECTOR6D",  # the installation's active TCP (Universal_Robots_Client_Library's RTDE table has it)
}

INPUT_TYPES: dict[str, str] = {
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": "VECTOR6D",
}

N_REGISTERS = 48  # int and double registers 0..47 (0..23 "lower range", 24..47 "upper range")

REGISTER_RE = re.compile(r"^(input|output)_(int|double|bit)_register_(\d+)$")


def register_type(name: str) -> tuple[str, str, int] | None:
    """``("output", "int", 3)`` for ``output_int_register_3``; None if not a valid single-register name."""
    m = REGISTER_RE.match(name)
    if not m:
        return None
    direction, kind, idx_s = m.groups()
    idx = int(idx_s)
    if kind == "bit":
        # Single bit registers exist only for 64..127; 0..63 are read as the two 32-bit words.
        return (direction, kind, idx) if 64 <= idx <= 127 else None
    return (direction, kind, idx) if idx < N_REGISTERS else None


def output_type(name: str) -> str | None:
    reg = register_type(name)
    if reg is not None:
        return {"int": "INT32", "double": "DOUBLE", "bit": "BOOL"}[reg[1]]
    return OUTPUT_TYPES.get(name)


def input_type(name: str) -> str | None:
    reg = register_type(name)
    if reg is not None:
        if reg[0] != "input":
            return None
        return {"int": "INT32", "double": "DOUBLE", "bit": "BOOL"}[reg[1]]
    return INPUT_TYPES.get(name)


def flatten(values: list[object]) -> list[object]:
    """Flatten vector values for ``struct.pack``."""
    out: list[object] = []
    for v in values:
        if isinstance(v, (list, tuple)):
            out.extend(v)
        else:
            out.append(v)
    return out
