"""Typed interfaces of the cell's devices, shared by the real drivers and the simulator.

The controller programs against these Protocols only. Two backends implement
them: ``elastoprobe.sim`` (in-process, virtual time) and the real drivers in
``controller/drivers`` (ur_rtde, ATI Net F/T over UDP, the serial line scanner).

Units are in the names. Frames (docs/frames.md):
- base: the robot base; poses of the TCP are ``base <- tcp`` in mm.
- tcp / tool: +z along the probe, pointing from the flange to the tip (the push
  direction d); +x in the laser plane. The TCP is the probe tip centre.
- sensor: the F/T sensor frame; the cell file gives ``tcp <- sensor``.
  ``WrenchBlock.force_n`` is the force exerted ON the tool BY the environment
  (contact, plus payload gravity when not compensated), in the sensor frame: pressing
  the probe into an object gives a negative z component.
- scanner: origin at the optical centre, x along the laser line, z along the optical
  axis (away from the scanner); the cell gives ``tcp <- scanner``.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from .clock import Clock
from .geometry import Pose


@dataclass(frozen=True)
class DeviceIdentity:
    """Who a device is, for provenance (journaled with every session)."""

    kind: str            # "arm", "ft", "scanner"
    model: str
    serial: str
    firmware: str
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class WrenchBlock:
    """A block of F/T samples, oldest first.

    ``t_s``: time of each sample on the controller's clock (s).
    ``seq``: unwrapped sample sequence numbers (strictly increasing; a gap means loss).
    ``force_n`` (N,3), ``torque_nm`` (N,3): sensor frame, bias removed.
    ``status``: device status word per sample, 0 = healthy.
    """

    t_s: np.ndarray
    seq: np.ndarray
    force_n: np.ndarray
    torque_nm: np.ndarray
    status: np.ndarray

    @staticmethod
    def empty() -> "WrenchBlock":
        return WrenchBlock(np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros((0, 3)),
                           np.zeros((0, 3)), np.zeros(0, dtype=np.uint32))

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    @staticmethod
    def concat(blocks: "list[WrenchBlock]") -> "WrenchBlock":
        blocks = [b for b in blocks if len(b)]
        if not blocks:
            return WrenchBlock.empty()
        return WrenchBlock(
            np.concatenate([b.t_s for b in blocks]),
            np.concatenate([b.seq for b in blocks]),
            np.concatenate([b.force_n for b in blocks]),
            np.concatenate([b.torque_nm for b in blocks]),
            np.concatenate([b.status for b in blocks]),
        )

    def tail(self, duration_s: float) -> "WrenchBlock":
        """The samples of the last ``duration_s`` seconds."""
        if not len(self):
            return self
        keep = self.t_s >= self.t_s[-1] - duration_s
        return WrenchBlock(self.t_s[keep], self.seq[keep], self.force_n[keep],
                           self.torque_nm[keep], self.status[keep])

    def force_magnitude_n(self) -> np.ndarray:
        return np.linalg.norm(self.force_n, axis=1)


@dataclass
class Scan:
    """One laser line profile, in the scanner frame.

    ``x_mm`` (L,): position along the laser line; ``z_mm`` (L,): range along the optical
    axis; NaN where the sample is missing. ``exposure_t_s`` is on the controller clock.
    """

    frame_counter: int
    exposure_t_s: float
    x_mm: np.ndarray
    z_mm: np.ndarray


class MotionState(enum.Enum):
    RUNNING = "running"        # still executing
    DONE = "done"              # reached its goal (for regulate_force: at force, now holding)
    CONTACT = "contact"        # seek_contact: contact found, motion stopped
    NO_CONTACT = "no_contact"  # seek_contact: search distance exhausted without contact
    STOPPED = "stopped"        # stopped on request (stop()) or superseded by a new command
    TRIPPED = "tripped"        # stopped by the safety path (see Arm.trip())
    FAULT = "fault"            # the arm refused or lost it (protective stop, e-stop, connection)


@runtime_checkable
class Motion(Protocol):
    """Handle of an asynchronous arm command."""

    @property
    def kind(self) -> str: ...

    def state(self) -> MotionState: ...

    def progress(self) -> float:
        """Fraction done in [0, 1] (distance for moves, force for ramps)."""
        ...


@dataclass(frozen=True)
class ArmStatus:
    """A snapshot of the arm, as a real controller's status bits report it.

    ``operator_stop``: the robot's program was stopped or paused by someone at the pendant
    or the dashboard (no safety stop explains it); ``stop_reason`` says so in the robot's
    words. The arm is the operator's then: nothing moves it until the session is resumed.
    ``link_generation``: how many times the control link to the robot has been lost (and
    re-established) since the driver started: a loss and a return between two status reads
    leaves ``connected`` True but this count higher, so a caller that compares it across a
    span of work (a recovery) sees a connection lost inside it.
    """

    t_s: float
    tcp_pose: Pose
    joints_rad: np.ndarray
    tcp_speed_mm_s: float
    program_running: bool
    protective_stop: bool
    emergency_stop: bool
    is_moving: bool
    connected: bool = True
    operator_stop: bool = False
    stop_reason: str = ""
    link_generation: int = 0


@dataclass(frozen=True)
class Trip:
    """A crossed safety limit: what, when, and the raw F/T data that led to it."""

    kind: str                 # force, torque, lateral_force, force_rate, stale, frozen, slip,
                              # workspace, protective_stop, emergency_stop, connection
    t_s: float
    value: float
    limit: float
    message: str
    raw: WrenchBlock | None = field(default=None, repr=False)


def same_trip(a: Trip | None, b: Trip | None) -> bool:
    """Whether two reports name the same latched crossing (kind and instant): a driver in
    another process hands back a fresh copy of its trip on every call."""
    if a is None or b is None:
        return a is b
    return a.kind == b.kind and a.t_s == b.t_s


@runtime_checkable
class Arm(Protocol):
    """A 6-axis arm carrying the probe, with its safety path armed from the F/T stream: the
    toolhead the controller (and calibration) drives.

    ``move_linear`` and ``stop`` are the device's primitives; ``seek_contact`` and
    ``regulate_force`` are the force loop's skills
    (:class:`~elastoprobe.controller.core.forceloop.ForceSupervisor`), run on the device's
    primitives (a speed command, a stop) with the cell's ``force_loop`` gains wherever the
    device's data arrives: in virtual time in the simulated cell, in the hardware process
    on the real one.
    """

    def identity(self) -> DeviceIdentity: ...

    def status(self) -> ArmStatus: ...

    def inverse_kinematics(self, tcp_pose: Pose, seed_joints_rad: np.ndarray | None = None) -> np.ndarray | None:
        """Joint angles (rad) reaching ``tcp_pose`` within joint limits, or None."""
        ...

    def move_linear(self, target: Pose, speed_mm_s: float, accel_mm_s2: float) -> Motion:
        """Straight-line TCP move (trapezoidal profile); returns at once."""
        ...

    def seek_contact(self, direction: np.ndarray, speed_mm_s: float, contact_force_n: float,
                     max_distance_mm: float) -> Motion:
        """Move along ``direction`` (base frame) until |F| >= contact_force_n, then stop."""
        ...

    def regulate_force(self, direction: np.ndarray, target_force_n: float, rate_n_s: float) -> Motion:
        """Regulate the force along ``direction`` on the F/T reading: ramp at ``rate_n_s``
        to ``target_force_n``, then hold it (state DONE once settled) until the next command."""
        ...

    def stop(self) -> None:
        """Stop any motion now (decelerate at the arm's stop deceleration)."""
        ...

    def trip(self) -> Trip | None:
        """The trip that stopped the arm, if any (cleared by ``rearm``). While it is latched,
        a motion commanded after it that unloads the contact (away from it, the force not
        rising) goes through the guard; anything else is stopped again."""
        ...

    def rearm(self) -> bool:
        """Re-arm the safety path after a trip; refused (False) above the hysteresis level."""
        ...

    def recover_protective_stop(self) -> bool:
        """Bounded recovery from a protective stop; never clears an emergency stop."""
        ...


@runtime_checkable
class ForceTorqueSensor(Protocol):
    """A 6-axis F/T stream (ATI Net F/T or simulated), delivered in blocks."""

    def identity(self) -> DeviceIdentity: ...

    @property
    def rate_hz(self) -> float: ...

    def read_block(self) -> WrenchBlock:
        """Every sample that arrived since the previous call (may be empty)."""
        ...

    def tare(self) -> None:
        """Software bias: the current reading becomes zero (do it in free air)."""
        ...


@runtime_checkable
class LineScanner(Protocol):
    """An eye-in-hand laser line scanner."""

    def identity(self) -> DeviceIdentity: ...

    @property
    def samples_per_profile(self) -> int: ...

    @property
    def rate_hz(self) -> float: ...

    def start_burst(self, count: int) -> None:
        """Trigger a burst of ``count`` profiles; they arrive through ``read_scans``."""
        ...

    def read_scans(self) -> list[Scan]:
        """Profiles completed since the previous call, oldest first."""
        ...


@runtime_checkable
class GroundTruth(Protocol):
    """What only a simulated cell knows: used by ``evaluate``, never by the controller."""

    def region_of(self, points_mm: np.ndarray) -> np.ndarray:
        """True region label (int) of surface points (N,3) in the object frame."""
        ...

    def true_profile_mm(self, point_mm: np.ndarray, normal: np.ndarray, t: np.ndarray,
                        force_n: float, angle_deg: float, x_mm: np.ndarray) -> np.ndarray:
        """Noise-free depth (mm, along -n, positive into the object) at ``point + x t``."""
        ...

    def region_names(self) -> list[str]: ...


@runtime_checkable
class Cell(Protocol):
    """Everything the controller drives, built from a cell YAML by ``controller.cellfactory``."""

    clock: Clock
    arm: Arm
    ft: ForceTorqueSensor
    scanner: LineScanner
    tcp_to_scanner: Pose          # tcp <- scanner
    tcp_to_sensor: Pose           # tcp <- F/T sensor
    base_to_object: Pose          # base <- object (registration)
    is_simulated: bool

    def begin_step(self, step_key: tuple[int, int, int]) -> None:
        """Called before each step with (seed, step, attempt); the simulator keys its
        noise with it so a resumed session reproduces an uninterrupted one. Real cells
        ignore it."""
        ...

    def ground_truth(self) -> GroundTruth | None: ...

    def close(self) -> None: ...
