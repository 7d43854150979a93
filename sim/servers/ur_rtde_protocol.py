"""RTDE wire format, as a UR controller (PolyScope 5.x, protocol version 2) speaks it.

Framing: every packet is ``>HB`` (total size in bytes including this 3-byte header,
command byte) followed by a payload. Commands (ASCII):

- ``V`` (86) request protocol version: client sends ``>H`` version, server answers ``>B`` accepted.
- ``v`` (118) controller version: server answers ``>IIII`` major, minor, bugfix, build.
- ``O`` (79) output recipe (v2): client sends ``>d`` frequency + comma-separated names;
  server answers ``>B`` recipe id + comma-separated types (``NOT_FOUND`` for unknown names).
- ``I`` (73) input recipe: client sends comma-separated names; server answers ``>B``
  recipe id + types (``NOT_FOUND`` unknown, ``IN_USE`` owned by another client).
- ``S`` (83) start / ``P`` (80) pause: server answers ``>B`` accepted.
- ``U`` (85) data: ``>B`` recipe id + the recipe's values packed big-endian, both ways.
- ``M`` (77) text message (server to client).

Only the variables listed here exist; the names and types follow UR's RTDE guide.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

HEADER = struct.Struct(">HB")

CMD_REQUEST_PROTOCOL_VERSION = 86   # V
CMD_GET_URCONTROL_VERSION = 118     # v
CMD_TEXT_MESSAGE = 77               # M
CMD_DATA_PACKAGE = 85               # U
CMD_SETUP_OUTPUTS = 79              # O
CMD_SETUP_INPUTS = 73               # I
CMD_START = 83                      # S
CMD_PAUSE = 80                      # P

# RTDE type name -> struct format (big-endian is applied by the packer).
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

N_REGISTERS = 48  # int and double registers 0..47 (24..47 are the "upper range")


def _output_variables() -> dict[str, str]:
    v: dict[str, str] = {
        "timestamp": "DOUBLE",
        "target_q": "VECTOR6D", "target_qd": "VECTOR6D", "target_qdd": "VECTOR6D",
        "target_current": "VECTOR6D", "target_moment": "VECTOR6D",
        "actual_q": "VECTOR6D", "actual_qd": "VECTOR6D", "actual_current": "VECTOR6D",
        "actual_current_window": "VECTOR6D", "actual_current_as_torque": "VECTOR6D",
        "joint_control_output": "VECTOR6D",
        "actual_TCP_pose": "VECTOR6D", "actual_TCP_speed": "VECTOR6D", "actual_TCP_force": "VECTOR6D",
        "target_TCP_pose": "VECTOR6D", "target_TCP_speed": "VECTOR6D",
        "actual_digital_input_bits": "UINT64", "joint_temperatures": "VECTOR6D",
        "actual_execution_time": "DOUBLE", "robot_mode": "INT32", "joint_mode": "VECTOR6INT32",
        "safety_mode": "INT32", "safety_status": "INT32",
        "actual_tool_accelerometer": "VECTOR3D", "speed_scaling": "DOUBLE",
        "target_speed_fraction": "DOUBLE", "actual_momentum": "DOUBLE",
        "actual_main_voltage": "DOUBLE", "actual_robot_voltage": "DOUBLE",
        "actual_robot_current": "DOUBLE", "actual_joint_voltage": "VECTOR6D",
        "actual_digital_output_bits": "UINT64", "runtime_state": "UINT32",
        "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D",
        "robot_status_bits": "UINT32", "safety_status_bits": "UINT32",
        "analog_io_types": "UINT32",
        "standard_analog_input0": "DOUBLE", "standard_analog_input1": "DOUBLE",
        "standard_analog_output0": "DOUBLE", "standard_analog_output1": "DOUBLE",
        "io_current": "DOUBLE",
        "euromap67_input_bits": "UINT32", "euromap67_output_bits": "UINT32",
        "euromap67_24V_voltage": "DOUBLE", "euromap67_24V_current": "DOUBLE",
        "tool_mode": "UINT32", "tool_analog_input_types": "UINT32",
        "tool_analog_input0": "DOUBLE", "tool_analog_input1": "DOUBLE",
        "tool_output_voltage": "INT32", "tool_output_current": "DOUBLE", "tool_temperature": "DOUBLE",
        "tcp_force_scalar": "DOUBLE",
        "output_bit_registers0_to_31": "UINT32", "output_bit_registers32_to_63": "UINT32",
        "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
        "tool_output_mode": "UINT8", "tool_digital_output0_mode": "UINT8",
        "tool_digital_output1_mode": "UINT8",
        "payload": "DOUBLE", "payload_cog": "VECTOR3D", "payload_inertia": "VECTOR6D",
        "script_control_line": "UINT32", "ft_raw_wrench": "VECTOR6D",
        "joint_position_deviation_ratio": "DOUBLE", "collision_detection_ratio": "DOUBLE",
        "time_scale_source": "UINT32",
    }
    for i in range(64, 128):
        v[f"output_bit_register_{i}"] = "BOOL"
        v[f"input_bit_register_{i}"] = "BOOL"
    for i in range(N_REGISTERS):
        v[f"output_int_register_{i}"] = "INT32"
        v[f"output_double_register_{i}"] = "DOUBLE"
        v[f"input_int_register_{i}"] = "INT32"
        v[f"input_double_register_{i}"] = "DOUBLE"
    return v


def _input_variables() -> dict[str, str]:
    v: dict[str, str] = {
        "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
        "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
        "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
        "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
        "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
        "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
        "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
        "external_force_torque": "VECTOR6D",
    }
    for i in range(64, 128):
        v[f"input_bit_register_{i}"] = "BOOL"
    for i in range(N_REGISTERS):
        v[f"input_int_register_{i}"] = "INT32"
        v[f"input_double_register_{i}"] = "DOUBLE"
    return v


OUTPUT_VARIABLES: dict[str, str] = _output_variables()
INPUT_VARIABLES: dict[str, str] = _input_variables()


@dataclass(frozen=True)
class Recipe:
    """A negotiated recipe: its id, variable names and the struct packing them (no id byte)."""

    recipe_id: int
    names: tuple[str, ...]
    types: tuple[str, ...]
    codec: struct.Struct
    frequency_hz: float = 0.0

    @staticmethod
    def build(recipe_id: int, names: list[str], types: list[str], frequency_hz: float = 0.0) -> "Recipe":
        fmt = ">" + "".join(TYPE_FORMATS[t] for t in types)
        return Recipe(recipe_id, tuple(names), tuple(types), struct.Struct(fmt), frequency_hz)

    def pack(self, values: dict[str, object]) -> bytes:
        """``U`` payload (recipe id byte + values), taking each name's value from ``values``."""
        flat: list[object] = []
        for name, typ in zip(self.names, self.types):
            value = values[name]
            if typ.startswith("VECTOR"):
                flat.extend(value)  # type: ignore[arg-type]
            else:
                flat.append(value)
        return bytes([self.recipe_id]) + self.codec.pack(*flat)

    def unpack(self, data: bytes) -> dict[str, object]:
        """Values of a ``U`` payload without its id byte, by name."""
        flat = list(self.codec.unpack(data))
        out: dict[str, object] = {}
        i = 0
        for name, typ in zip(self.names, self.types):
            n = int(TYPE_FORMATS[typ][0]) if TYPE_FORMATS[typ][0].isdigit() else 1
            out[name] = flat[i] if n == 1 else tuple(flat[i:i + n])
            i += n
        return out


def frame(command: int, payload: bytes = b"") -> bytes:
    """One RTDE packet: header (size incl. header, command) + payload."""
    return HEADER.pack(HEADER.size + len(payload), command) + payload


def parse_names(payload: bytes) -> list[str]:
    """Comma-separated variable names (tolerates a trailing NUL or spaces)."""
    text = payload.decode("ascii", errors="replace").strip("\x00 \r\n")
    return [n.strip() for n in text.split(",") if n.strip()]
