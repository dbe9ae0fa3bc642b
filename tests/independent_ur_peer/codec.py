"""The RTDE protocol's codec: the controller's input and output variables and their types
(names and types as in UR's RTDE guide) and their big-endian struct formats.
"""

from __future__ import annotations

import struct

TYPE_FORMATS = {
    "DOUBLE": "d",
    "UINT64": "Q",
    "UINT32": "I",
    "INT32": "i",
    "UINT8": "B",
    "BOOL": "?",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}


def _output_types() -> dict[str, str]:
    """Return the controller's output variable types by name."""
    v6 = "VECTOR6D"
    t: dict[str, str] = {
        "timestamp": "DOUBLE",
        "target_q": v6,
        "target_qd": v6,
        "target_qdd": v6,
        "target_current": v6,
        "target_moment": v6,
        "actual_q": v6,
        "actual_qd": v6,
        "actual_current": v6,
        "actual_current_window": v6,
        "actual_current_as_torque": v6,
        "joint_control_output": v6,
        "actual_TCP_pose": v6,
        "actual_TCP_speed": v6,
        "actual_TCP_force": v6,
        "target_TCP_pose": v6,
        "target_TCP_speed": v6,
        "actual_digital_input_bits": "UINT64",
        "joint_temperatures": v6,
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
        "actual_joint_voltage": v6,
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
        "euromap67_input_bits": "UINT32",
        "euromap67_output_bits": "UINT32",
        "euromap67_24V_voltage": "DOUBLE",
        "euromap67_24V_current": "DOUBLE",
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
        "payload_inertia": v6,
        "script_control_line": "UINT32",
        "ft_raw_wrench": v6,
        "joint_position_deviation_ratio": v6,
        "collision_detection_ratio": "DOUBLE",
        "time_scale_source": "UINT32",
    }
    for i in range(64, 128):
        t[f"output_bit_register_{i}"] = "BOOL"
        t[f"input_bit_register_{i}"] = "BOOL"
    for i in range(48):
        t[f"output_int_register_{i}"] = "INT32"
        t[f"output_double_register_{i}"] = "DOUBLE"
        t[f"input_int_register_{i}"] = "INT32"
        t[f"input_double_register_{i}"] = "DOUBLE"
    return t


def _input_types() -> dict[str, str]:
    """Return the controller's input variable types by name."""
    t: dict[str, str] = {
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
    for i in range(64, 128):
        t[f"input_bit_register_{i}"] = "BOOL"
    for i in range(48):
        t[f"input_int_register_{i}"] = "INT32"
        t[f"input_double_register_{i}"] = "DOUBLE"
    return t


OUTPUT_TYPES = _output_types()
INPUT_TYPES = _input_types()


def struct_for(types: list[str]) -> struct.Struct:
    return struct.Struct(">" + "".join(TYPE_FORMATS[t] for t in types))
