"""Schemas of cell and plan files (YAML, mm and degrees), validated with positions.

A cell file describes the hardware: robot, tool geometry, F/T sensor, scanner,
where the object sits, the safety limits and, for simulated cells, the simulation.
A plan file describes one session: how to get the cloud, how many neural-gas
units, the phases and their forces and angles, budgets, a deadline, the fault
policy. A plan may only tighten a cell's limits (checked in :func:`load_session_inputs`).
Every error is reported as ``path:line:col: message``.
"""
from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import AfterValidator, Field, ValidationInfo, field_validator, model_validator

from .calfile import believed_cell
from .errors import InputError, InputErrors
from .faultkinds import POLICY_FAULT_KINDS, InjectedFault
from .forceloop import ForceLoopGains
from .geometry import NINE_ANGLES_DEG, Pose, rotvec_to_matrix
from .safety import SafetyLimits
from .yamlio import Spec, YamlDoc, load_validated

Vec3 = tuple[float, float, float]
PositiveFloat = Annotated[float, Field(gt=0)]


def _file_name(value: str) -> str:
    # An empty name ('' or "$UNSET") would resolve to the file's own folder or be read as
    # "not given" and fall back to a default the user did not choose.
    if not value.strip():
        raise ValueError("the file name is empty")
    return value


FileName = Annotated[str, AfterValidator(_file_name)]


# Regions of different elasticity differ in survey depth by at least this factor (the
# composite's box and foam: ~10x; the user object's halves: ~25x). Within one material
# the dent varies by more than geometry's ~1.3x: how the material is supported matters.
# The composite's box top, clamped by its walls, dents 2.3x deeper at its centre than
# 15 mm from a wall; neural-gas units gather by the walls, so the mixture often cuts the
# top into a centre and a rim with medians ~1.9x apart. A plan probing materials that
# differ by less sets phases.survey.min_contrast lower.
MIN_CONTRAST = 2.5


def rpy_deg_to_matrix(rpy_deg: Vec3) -> np.ndarray:
    """Roll, pitch, yaw (deg) about fixed x, y, z (R = Rz @ Ry @ Rx)."""
    rx, ry, rz = np.radians(rpy_deg)
    return (rotvec_to_matrix(np.array([0.0, 0.0, rz])) @ rotvec_to_matrix(np.array([0.0, ry, 0.0]))
            @ rotvec_to_matrix(np.array([rx, 0.0, 0.0])))


class PoseSpec(Spec):
    """A rigid transform: position in mm, orientation as roll/pitch/yaw in degrees."""

    position_mm: Vec3 = (0.0, 0.0, 0.0)
    rpy_deg: Vec3 = (0.0, 0.0, 0.0)

    def pose(self) -> Pose:
        return Pose(np.array(self.position_mm), rpy_deg_to_matrix(self.rpy_deg))


class BoxSpec(Spec):
    """An axis-aligned box in the robot base frame (mm)."""

    name: str = "box"
    min_mm: Vec3
    max_mm: Vec3

    @model_validator(mode="after")
    def _ordered(self) -> "BoxSpec":
        if any(lo >= hi for lo, hi in zip(self.min_mm, self.max_mm)):
            raise ValueError("min_mm must be below max_mm on every axis")
        return self

    def contains(self, point_mm: np.ndarray) -> bool:
        p = np.asarray(point_mm)
        return bool(np.all(p >= np.array(self.min_mm)) and np.all(p <= np.array(self.max_mm)))


class ToolShapeSpec(Spec):
    """Collision geometry carried by the arm, in the TCP frame."""

    name: str
    kind: Literal["cylinder", "box"]
    pose: PoseSpec = PoseSpec()
    radius_mm: float = Field(0.0, ge=0)
    length_mm: float = Field(0.0, ge=0)
    size_mm: Vec3 | None = None

    @model_validator(mode="after")
    def _dimensions(self) -> "ToolShapeSpec":
        if self.kind == "cylinder" and (self.radius_mm <= 0 or self.length_mm <= 0):
            raise ValueError("a cylinder needs radius_mm > 0 and length_mm > 0")
        if self.kind == "box" and (self.size_mm is None or min(self.size_mm) <= 0):
            raise ValueError("a box needs size_mm with three positive values")
        return self


JointDeg = Annotated[float, Field(ge=-360.0, le=360.0)]


class RobotSpec(Spec):
    model: Literal["UR5e"] = "UR5e"
    host: str = "127.0.0.1"
    joint_limits_deg: list[tuple[float, float]] | None = None
    # Where the arm rests (and the seed of inverse kinematics): within the UR's +-360 deg per joint.
    home_joints_deg: tuple[JointDeg, JointDeg, JointDeg, JointDeg, JointDeg, JointDeg] = (0.0, -90.0, 90.0, -90.0,
                                                                                          -90.0, 0.0)

    @field_validator("joint_limits_deg")
    @classmethod
    def _six_limits(cls, v: list[tuple[float, float]] | None) -> list[tuple[float, float]] | None:
        if v is not None:
            if len(v) != 6:
                raise ValueError("joint_limits_deg needs six [min, max] pairs")
            for lo, hi in v:
                if not (-360.0 <= lo < hi <= 360.0):
                    raise ValueError("each joint limit must satisfy -360 <= min < max <= 360")
        return v

    @field_validator("home_joints_deg")
    @classmethod
    def _home_within_limits(cls, v: tuple[float, ...], info: ValidationInfo) -> tuple[float, ...]:
        for i, (q, (lo, hi)) in enumerate(zip(v, info.data.get("joint_limits_deg") or [])):
            if not lo <= q <= hi:
                raise ValueError(f"joint {i + 1} at {q:g} deg lies outside its limits [{lo:g}, {hi:g}] "
                                 f"(joint_limits_deg)")
        return v

    def joint_limits_rad(self) -> np.ndarray | None:
        """The joint limits as (6, 2) [min, max] in radians; None: the arm's own (+-2 pi)."""
        return None if self.joint_limits_deg is None else np.radians(np.asarray(self.joint_limits_deg, dtype=float))


class ToolSpec(Spec):
    tip_radius_mm: float = Field(gt=0, le=50)
    flange_to_tcp: PoseSpec
    tcp_to_sensor: PoseSpec
    tcp_to_scanner: PoseSpec
    payload_mass_kg: float = Field(ge=0, le=5)
    payload_com_mm: Vec3 = (0.0, 0.0, 0.0)
    shapes: list[ToolShapeSpec] = []


class FTSpec(Spec):
    host: str = "127.0.0.1"
    rdt_port: int = Field(49152, ge=1, le=65535)
    calinfo_port: int = Field(49151, ge=1, le=65535)
    rate_hz: float = Field(1000.0, gt=0, le=7000)
    range_n: float = Field(290.0, gt=0)
    range_nm: float = Field(10.0, gt=0)


class ScannerSpec(Spec):
    url: str = "sim://"
    samples_per_profile: int = Field(256, ge=16, le=4096)
    rate_hz: float = Field(50.0, gt=0, le=2000)
    field_of_view_deg: float = Field(40.0, gt=0, lt=120)
    max_range_mm: float = Field(400.0, gt=0)


class ObjectPlacementSpec(Spec):
    """Where the object sits: its model file and the nominal base <- object transform."""

    file: str
    base_to_object: PoseSpec


class LimitsSpec(Spec):
    """Cell safety and motion limits (units in names)."""

    max_force_n: float = Field(gt=0, le=300)
    max_torque_nm: float = Field(gt=0, le=50)
    max_lateral_force_n: float = Field(gt=0, le=300)
    max_force_rate_n_s: float = Field(gt=0, le=10000)
    contact_force_n: float = Field(gt=0, le=10)
    contact_speed_mm_s: float = Field(gt=0, le=50)
    free_speed_mm_s: float = Field(gt=0, le=1000)
    free_accel_mm_s2: float = Field(500.0, gt=0, le=5000)
    search_distance_mm: float = Field(gt=0, le=200)
    ft_stale_ms: float = Field(gt=0, le=1000)
    ft_frozen_ms: float = Field(gt=0, le=5000)
    slip_mm: float = Field(gt=0, le=50)
    rearm_fraction: float = Field(0.8, gt=0, lt=1)
    workspace: BoxSpec
    keep_out: list[BoxSpec] = []

    def safety(self) -> SafetyLimits:
        return SafetyLimits(max_force_n=self.max_force_n, max_torque_nm=self.max_torque_nm,
                            max_lateral_force_n=self.max_lateral_force_n,
                            max_force_rate_n_s=self.max_force_rate_n_s, ft_stale_ms=self.ft_stale_ms,
                            ft_frozen_ms=self.ft_frozen_ms, slip_mm=self.slip_mm,
                            rearm_fraction=self.rearm_fraction)


class ForceLoopSpec(Spec):
    """The contact search's and the force loop's tuning (controller/core/forceloop.py): one set for
    every backend, the simulated cell and the real arm alike.

    ``gain`` is the fraction of the force error corrected per period and ``integral_per_s``
    the integral action, both divided by the loop's estimate of the contact stiffness (which
    starts at ``initial_stiffness_n_mm``); the loop reads |mean| of the latest
    ``force_window`` F/T samples. A gain of 1 or more would correct more than the whole error
    every period (it overshoots on every update).
    """

    period_ms: float = Field(10.0, ge=1, le=100)
    gain: float = Field(0.3, gt=0, lt=1)
    integral_per_s: float = Field(1.5, ge=0, le=50)
    max_speed_mm_s: float = Field(15.0, gt=0, le=100)
    accel_mm_s2: float = Field(500.0, gt=0, le=5000)
    tolerance_n: float = Field(0.1, gt=0, le=10)
    tolerance_rel: float = Field(0.02, ge=0, le=0.5)
    settle_updates: int = Field(10, ge=1, le=1000)
    initial_stiffness_n_mm: float = Field(2.0, gt=0, le=1000)
    force_window: int = Field(10, ge=1, le=1000)
    seek_accel_mm_s2: float = Field(500.0, gt=0, le=5000)

    def gains(self) -> ForceLoopGains:
        return ForceLoopGains(period_s=self.period_ms * 1e-3, gain=self.gain, integral_per_s=self.integral_per_s,
                              max_speed_mm_s=self.max_speed_mm_s, accel_mm_s2=self.accel_mm_s2,
                              tolerance_n=self.tolerance_n, tolerance_rel=self.tolerance_rel,
                              settle_updates=self.settle_updates, initial_stiffness_n_mm=self.initial_stiffness_n_mm,
                              force_window=self.force_window, seek_accel_mm_s2=self.seek_accel_mm_s2)


class FaultSpec(Spec):
    """A fault the simulator injects: at a step, at a rate per 100 steps, or as a follow-up
    of other faults (a rate per 100 faults that fire, ``delay_s`` after each: faults come
    in bursts, and one lands while the controller recovers from another)."""

    # Lax: the cell file gives the kind's name, the enum is what the simulator reads.
    kind: InjectedFault = Field(strict=False)
    step: int | None = Field(None, ge=0)
    rate_per_100_steps: float | None = Field(None, gt=0, le=100)
    rate_per_100_faults: float | None = Field(None, gt=0, le=100)
    clear_after_s: float | None = Field(None, gt=0)   # emergency stop: operator clears it after this
    delay_s: float | None = Field(None, ge=0, le=3600)          # after the step begins (default: drawn 0.2-2 s)
    duration_s: float | None = Field(None, gt=0, le=3600)       # default per kind (sim/faults.py)
    magnitude: float | None = Field(None, gt=0, le=1000)        # spike N, shift mm, slip mm/s, burst fraction

    @model_validator(mode="after")
    def _when(self) -> "FaultSpec":
        if sum(v is not None for v in (self.step, self.rate_per_100_steps, self.rate_per_100_faults)) != 1:
            raise ValueError("give exactly one of step, rate_per_100_steps or rate_per_100_faults")
        if self.rate_per_100_faults is not None and self.kind is InjectedFault.DISK_ERROR:
            raise ValueError("a disk error happens at a journal write, not as a follow-up of another fault")
        return self


class MiscalibrationSpec(Spec):
    enabled: bool = False
    payload_mass_rel: float = Field(0.1, ge=0, le=1)
    payload_com_mm: float = Field(5.0, ge=0, le=50)
    tip_mm: float = Field(2.0, ge=0, le=20)
    scanner_deg: float = Field(2.0, ge=0, le=20)
    scanner_mm: float = Field(3.0, ge=0, le=30)
    object_mm: float = Field(0.0, ge=0, le=30)      # the object set down off its placement (horizontal)
    # The miscalibration belongs to the physical cell, not to a run: drawn from this
    # cell-level seed, so calibrating and running (with any --seed) meet the same cell.
    seed: int = Field(0, ge=0, lt=2**31)


class SimulationSpec(Spec):
    control_period_ms: float = Field(2.0, gt=0, le=20)
    ft_noise_n: float = Field(0.04, ge=0, le=5)
    ft_noise_nm: float = Field(0.002, ge=0, le=1)
    ft_drift_n_per_h: float = Field(0.2, ge=0, le=50)
    scanner_noise_scale: float = Field(1.0, ge=0, le=20)
    miscalibration: MiscalibrationSpec = MiscalibrationSpec()
    faults: list[FaultSpec] = []


class NotifySpec(Spec):
    """A user command run with a JSON payload on stdin when something happens."""

    command: list[str] = Field(min_length=1)
    on: list[Literal["pause", "fault", "finish", "finish_by"]] = ["pause", "fault", "finish", "finish_by"]
    timeout_s: float = Field(10.0, gt=0, le=300)


class CellSpec(Spec):
    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    kind: Literal["simulated", "ur", "loopback"]
    robot: RobotSpec = RobotSpec()
    tool: ToolSpec
    ft: FTSpec = FTSpec()
    scanner: ScannerSpec = ScannerSpec()
    object: ObjectPlacementSpec
    limits: LimitsSpec
    force_loop: ForceLoopSpec = ForceLoopSpec()
    calibration_file: FileName | None = None
    calibration_max_age_days: float = Field(30.0, gt=0)
    simulation: SimulationSpec = SimulationSpec()
    notify: NotifySpec | None = None


# ----------------------------------------------------------------------------- plans
AngleDeg = Annotated[float, Field(gt=0, lt=180)]
ForceN = Annotated[float, Field(gt=0, le=300)]


def _strictly_increasing(values: list[float], what: str) -> list[float]:
    if any(b <= a for a, b in zip(values, values[1:])):
        raise ValueError(f"{what} must be strictly increasing")
    return values


class CloudSpec(Spec):
    source: Literal["scan", "file"] = "scan"
    file: FileName | None = None
    # Between profiles along a line (the sweep's speed is this x the scanner's rate). Finer than
    # 0.1 mm is below what a line scanner resolves along its own line (0.2-0.5 mm between
    # samples) and only slows the sweep and fills memory: at 1e-300 mm one line never ended
    # and held gigabytes of profiles.
    sweep_spacing_mm: float = Field(3.0, ge=0.1, le=50)
    sweep_height_mm: float = Field(40.0, gt=0, le=1000)   # tip above the object's top
    max_points: int = Field(200_000, ge=1000, le=5_000_000)

    @model_validator(mode="after")
    def _file(self) -> "CloudSpec":
        if self.source == "file" and not self.file:
            raise ValueError("source: file needs file:")
        return self


class SamplingSpec(Spec):
    # 0: no neural gas, the plan's explicit targets are the survey (a fixed-point plan such
    # as the loopback comparison, where two runs must press the same points).
    units: int = Field(60, ge=0, le=5000)
    steps_per_unit: int = Field(200, ge=10, le=100_000)
    geometry_weight: float = Field(1.0, ge=0, le=100)
    edge_clearance_mm: float = Field(15.0, ge=0, le=200)
    max_tilt_deg: float = Field(60.0, gt=0, le=90)
    # Projected on each tangent plane, the scan direction t the angles are measured from; a
    # survey line that would cross a border inside the dent's window turns a quarter turn
    # (docs/design.md §3).
    reference_direction: Vec3 = (1.0, 0.0, 0.0)
    # The smallest inclusion (mm across) the survey must land on: the session raises
    # `units` until every disc this wide on the probe-able top holds a target
    # (learning/survey_density.py). None: `units` as given. At least 5 mm: a dent is wider
    # than the tip (2.5-5 mm radius on the shipped cells), a narrower inclusion is not read.
    min_feature_mm: float | None = Field(None, ge=5, le=500)

    @field_validator("units")
    @classmethod
    def _units(cls, v: int) -> int:
        if 0 < v < 4:
            raise ValueError("units must be 0 (explicit targets only) or at least 4")
        return v

    @field_validator("reference_direction")
    @classmethod
    def _reference_off_every_normal(cls, v: tuple[float, float, float], info: ValidationInfo) -> tuple[float, float, float]:
        # The scan direction is this vector projected on the tangent plane. Parallel to a
        # probe-able normal (tilted up to max_tilt_deg from vertical) it projects to nothing
        # there, and the angles would mean different things from point to point.
        norm = math.hypot(*v)
        if norm < 1e-9:
            raise ValueError("reference_direction is the zero vector: it has no direction")
        from_vertical_deg = math.degrees(math.acos(min(1.0, abs(v[2]) / norm)))
        max_tilt_deg = info.data.get("max_tilt_deg")
        # A level reference is always taken: with max_tilt_deg 90 nothing else would be, and
        # only faces that are themselves vertical fall back (geometry.scan_direction).
        if max_tilt_deg is not None and from_vertical_deg <= min(max_tilt_deg, 89.0):
            raise ValueError(f"reference_direction is {from_vertical_deg:.1f} deg from vertical, within "
                             f"max_tilt_deg = {max_tilt_deg:g} of it: it would be parallel to some probe-able "
                             f"surface normal (give a direction across the object, e.g. [0, 1, 0])")
        return v

    @field_validator("min_feature_mm")
    @classmethod
    def _feature_needs_units(cls, v: float | None, info: ValidationInfo) -> float | None:
        if v is not None and info.data.get("units") == 0:
            raise ValueError("min_feature_mm raises the neural gas's units, and units is 0 (explicit targets "
                             "only): set units, or leave min_feature_mm out")
        return v


class SurveySpec(Spec):
    angles_deg: list[AngleDeg] = Field([90.0], min_length=1)
    forces_n: list[ForceN] = Field([4.0, 12.0], min_length=1)
    # Two regions are two materials only when their survey dents differ by this factor.
    min_contrast: float = Field(MIN_CONTRAST, ge=1.0, le=100.0)

    @field_validator("forces_n")
    @classmethod
    def _increasing(cls, v: list[float]) -> list[float]:
        return _strictly_increasing(v, "forces_n")


class CharacterizeSpec(Spec):
    points_per_region: int = Field(2, ge=1, le=50)
    angles_deg: list[AngleDeg] = Field(list(NINE_ANGLES_DEG), min_length=1)
    forces_n: list[ForceN] = Field([2.0, 5.0, 9.0, 14.0, 20.0], min_length=1)

    @field_validator("forces_n")
    @classmethod
    def _increasing(cls, v: list[float]) -> list[float]:
        return _strictly_increasing(v, "forces_n")


class DensifySpec(Spec):
    rounds: int = Field(2, ge=0, le=50)
    points_per_round: int = Field(8, ge=1, le=500)
    min_spacing_mm: float = Field(5.0, gt=0, le=200)
    resolution_mm: float = Field(12.0, gt=0, le=200)
    # How near a sharp edge densify may follow a seam that runs out toward the rim, where the
    # survey kept `sampling.edge_clearance_mm` (docs/design.md, Densify). None: one tip
    # radius, the ball resting wholly on the face. At or above the edge clearance: never
    # nearer than the survey.
    rim_clearance_mm: float | None = Field(None, ge=0, le=200)

    @model_validator(mode="after")
    def _splittable(self) -> "DensifySpec":
        # A new point goes midway along a disagreeing edge: edges just above the
        # resolution can be split only if half of them still keeps min_spacing_mm.
        if self.resolution_mm < 2.0 * self.min_spacing_mm:
            raise ValueError("resolution_mm must be at least 2 x min_spacing_mm, or no edge can be split")
        return self


class PhasesSpec(Spec):
    survey: SurveySpec = SurveySpec()
    characterize: CharacterizeSpec = CharacterizeSpec()
    densify: DensifySpec = DensifySpec()


class ProbingSpec(Spec):
    scans_per_step: int = Field(40, ge=1, le=200)
    settle_s: float = Field(3.0, ge=0, le=120)
    standoff_mm: float = Field(15.0, gt=0, le=200)
    force_rate_n_s: float = Field(10.0, gt=0, le=200)
    force_tolerance_n: float = Field(0.5, gt=0, le=20)
    # The scans see the object this far (horizontally) from where it is registered: it
    # moved (an object_moved fault, then re-registration). Above the calibration's
    # tolerance, under the shifts that matter for a region map; null turns the check off.
    object_moved_mm: float | None = Field(6.0, gt=0, le=100)


class BudgetSpec(Spec):
    max_steps: int = Field(2000, ge=1, le=1_000_000)
    max_robot_hours: float = Field(12.0, gt=0, le=24 * 14)


class ModelSpec(Spec):
    hidden_units: int = Field(45, ge=2, le=1000)
    ensemble: int = Field(5, ge=1, le=50)
    max_epochs: int = Field(3000, ge=10, le=100_000)
    profile_span_mm: float = Field(80.0, gt=0, le=1000)
    profile_samples: int = Field(256, ge=8, le=4096)


class FaultActionSpec(Spec):
    action: Literal["retry", "skip_target", "pause", "abort"]
    retries: int = Field(2, ge=0, le=20)


class FaultPolicySpec(Spec):
    """What to do for each kind of trip or fault; kinds not listed use ``default``."""

    default: FaultActionSpec = FaultActionSpec(action="retry", retries=2)
    kinds: dict[str, FaultActionSpec] = {}

    @field_validator("kinds")
    @classmethod
    def _known(cls, v: dict[str, FaultActionSpec]) -> dict[str, FaultActionSpec]:
        for k in v:
            if k not in POLICY_FAULT_KINDS:
                raise ValueError(f"unknown fault kind {k!r} (known: {', '.join(sorted(POLICY_FAULT_KINDS))})")
        return v

    def for_kind(self, kind: str) -> FaultActionSpec:
        if kind == "emergency_stop" and kind not in self.kinds:
            return FaultActionSpec(action="pause", retries=0)   # never auto-cleared
        return self.kinds.get(kind, self.default)


class PlanLimitsSpec(Spec):
    """Limits a plan may set; each must be at or below the cell's."""

    max_force_n: float | None = Field(None, gt=0)
    max_torque_nm: float | None = Field(None, gt=0)
    max_lateral_force_n: float | None = Field(None, gt=0)
    max_force_rate_n_s: float | None = Field(None, gt=0)
    contact_speed_mm_s: float | None = Field(None, gt=0)
    free_speed_mm_s: float | None = Field(None, gt=0)
    search_distance_mm: float | None = Field(None, gt=0)
    slip_mm: float | None = Field(None, gt=0)


class ExtraTargetSpec(Spec):
    """A probe point the plan asks for explicitly (object frame, mm)."""

    point_mm: Vec3
    normal: Vec3 = (0.0, 0.0, 1.0)


class PlanSpec(Spec):
    name: str = Field(min_length=1, max_length=80, pattern=r"^[A-Za-z0-9_.-]+$")
    cell: FileName | None = None
    simulated_object: FileName | None = None
    seed: int = Field(0, ge=0, le=2**31 - 1)
    cloud: CloudSpec = CloudSpec()
    sampling: SamplingSpec = SamplingSpec()
    probing: ProbingSpec = ProbingSpec()
    phases: PhasesSpec = PhasesSpec()
    budget: BudgetSpec = BudgetSpec()
    model: ModelSpec = ModelSpec()
    limits: PlanLimitsSpec = PlanLimitsSpec()
    fault_policy: FaultPolicySpec = FaultPolicySpec()
    targets: list[ExtraTargetSpec] = []
    finish_by: _dt.datetime | None = None
    notify: NotifySpec | None = None

    @field_validator("finish_by", mode="before")
    @classmethod
    def _parse_time(cls, v: object) -> object:
        if isinstance(v, str):
            try:
                t = _dt.datetime.fromisoformat(v)
            except ValueError:
                raise ValueError("finish_by must be an ISO 8601 date-time, e.g. 2026-11-23T07:00:00+01:00") from None
            return t if t.tzinfo else t.astimezone()
        return v


# ------------------------------------------------------------------------ loading
@dataclass(frozen=True)
class SessionInputs:
    """A validated plan and cell, with their paths and texts (hashed into the journal)."""

    plan: PlanSpec
    cell: CellSpec
    plan_path: Path
    cell_path: Path
    plan_doc: YamlDoc
    cell_doc: YamlDoc
    limits: SafetyLimits
    # ``cell`` is what the controller believes: the cell file with its calibration file's
    # corrections applied (calibration.calfile.believed_cell); ``cell_file`` is the file as
    # written (a simulated cell's true tool is built from it). None: same as ``cell``.
    cell_file: CellSpec | None = None
    # Why ``cell`` may not be the cell (calibration missing, partial, stale or unusable),
    # found once when the inputs are loaded: the CLI prints it, the session logs it.
    calibration_problems: tuple[str, ...] = ()

    def resolve(self, relative_to: Path, name: str) -> Path:
        p = Path(name)
        return p if p.is_absolute() else (relative_to.parent / p)

    def object_file(self) -> Path:
        """The simulated object: the plan's choice, else the cell's."""
        if self.plan.simulated_object and self.cell.kind != "ur":
            return self.resolve(self.plan_path, self.plan.simulated_object)
        return self.resolve(self.cell_path, self.cell.object.file)


def load_cell(path: str | Path) -> tuple[CellSpec, YamlDoc]:
    cell, doc = load_validated(path, CellSpec)
    _check_force_loop(cell, doc)
    return cell, doc


def _check_force_loop(cell: CellSpec, doc: YamlDoc) -> None:
    """What the force loop's fields mean together with the rest of the cell."""
    loop = cell.force_loop
    window_ms = loop.force_window / cell.ft.rate_hz * 1e3
    if window_ms > loop.period_ms + 1e-9:
        # The loop would act on samples older than its last update: a delay in every update.
        raise doc.error(("force_loop", "force_window"),
                        f"force_window = {loop.force_window} samples spans {window_ms:g} ms at the F/T's "
                        f"{cell.ft.rate_hz:g} Hz, longer than the loop period ({loop.period_ms:g} ms)")


def load_plan(path: str | Path) -> tuple[PlanSpec, YamlDoc]:
    return load_validated(path, PlanSpec)


DEFAULT_CELL = Path(__file__).resolve().parents[2] / "config" / "cells" / "sim.yaml"


def load_session_inputs(plan_path: str | Path, cell_path: str | Path | None = None) -> SessionInputs:
    """Load and cross-check a plan and its cell; raise InputError(s) with positions."""
    plan, plan_doc = load_plan(plan_path)
    if cell_path is None:
        cell_path = (Path(plan_path).parent / plan.cell) if plan.cell else DEFAULT_CELL
    cell_file, cell_doc = load_cell(cell_path)

    cell, calibration = believed_cell(cell_file, cell_path)
    errors: list[InputError] = []
    lim = cell.limits
    # A plan may only tighten the cell's limits.
    overrides = {}
    for name, value in plan.limits.model_dump().items():
        if value is None:
            continue
        cell_value = getattr(lim, name)
        if value > cell_value:
            errors.append(plan_doc.error(("limits", name),
                                         f"limits.{name} = {value} is looser than the cell's {cell_value} "
                                         f"({cell_doc.path}:{cell_doc.where(('limits', name))[0]})"))
        overrides[name] = value
    max_force_n = plan.limits.max_force_n or lim.max_force_n
    for phase in ("survey", "characterize"):
        forces = getattr(plan.phases, phase).forces_n
        for i, f in enumerate(forces):
            if f > max_force_n:
                errors.append(plan_doc.error(("phases", phase, "forces_n", i),
                                             f"force {f} N exceeds the limit max_force_n = {max_force_n} N"))
            if f <= lim.contact_force_n:
                errors.append(plan_doc.error(("phases", phase, "forces_n", i),
                                             f"force {f} N is not above the contact threshold "
                                             f"{lim.contact_force_n} N"))
    if plan.sampling.units == 0 and not plan.targets:
        errors.append(plan_doc.error(("sampling", "units"),
                                     "units: 0 means explicit targets only, but the plan has no targets: list"))
    base_to_object = cell.object.base_to_object.pose()
    for i, target in enumerate(plan.targets):
        p_base = base_to_object.apply(np.array(target.point_mm))
        if not lim.workspace.contains(p_base):
            errors.append(plan_doc.error(("targets", i, "point_mm"),
                                         f"target {list(target.point_mm)} mm (base {np.round(p_base, 1).tolist()}) "
                                         f"is outside the cell workspace"))
        for box in lim.keep_out:
            if box.contains(p_base):
                errors.append(plan_doc.error(("targets", i, "point_mm"),
                                             f"target lies inside keep-out box {box.name!r}"))
        if np.linalg.norm(target.normal) < 1e-9:
            errors.append(plan_doc.error(("targets", i, "normal"), "normal must not be zero"))
    if errors:
        raise InputErrors(errors)
    limits = lim.safety().tightened(**{k: v for k, v in overrides.items()
                                       if k in SafetyLimits.__dataclass_fields__})
    inputs = SessionInputs(plan=plan, cell=cell, plan_path=Path(plan_path), cell_path=Path(cell_path),
                           plan_doc=plan_doc, cell_doc=cell_doc, limits=limits, cell_file=cell_file,
                           calibration_problems=tuple(calibration.problems))
    obj = inputs.object_file()
    if not obj.exists():
        where = (plan_doc, ("simulated_object",)) if plan.simulated_object else (cell_doc, ("object", "file"))
        raise where[0].error(where[1], f"object file {str(obj)!r} does not exist")
    return inputs


def effective_motion_limits(inputs: SessionInputs) -> dict[str, float]:
    """Speeds and distances after the plan's tightening."""
    lim, pl = inputs.cell.limits, inputs.plan.limits
    return {
        "contact_speed_mm_s": pl.contact_speed_mm_s or lim.contact_speed_mm_s,
        "free_speed_mm_s": pl.free_speed_mm_s or lim.free_speed_mm_s,
        "search_distance_mm": pl.search_distance_mm or lim.search_distance_mm,
        "free_accel_mm_s2": lim.free_accel_mm_s2,
        "contact_force_n": lim.contact_force_n,
    }
