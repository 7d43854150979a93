"""The simulated probing cell (implements :class:`~elastoprobe.controller.core.devices.Cell`).

:class:`SimCellParams` carries what a cell file describes (tool geometry, scanner
mount, payload, limits, the simulation section: noise, miscalibration, faults) as
plain values; :func:`params_from_cell` maps a validated ``CellSpec`` onto it.
:class:`SimCell` builds the virtual clock, the world and its devices:

    cell = SimCell(params_from_cell(cell_spec, object_path, seed=7))
    cell.begin_step((7, step_id, attempt))
    motion = cell.arm.move_linear(pose, 100.0, 500.0)
    cell.clock.sleep_s(0.01)          # the world integrates up to the new time

What the world IS and what the controller BELIEVES are kept apart:

- true: the cell file's nominal tool and placement plus the cell's miscalibration (when
  the cell enables it), drawn from the cell-level ``Miscalibration.seed`` — a property
  of the physical cell, the same for every run seed (the run seed drives noise only).
  The physical tool is fixed to the flange, so the truth is held against the flange.
- believed (:class:`Believed`): what the controller uses — the cell file corrected by
  its calibration file (``calibration.calfile.believed_cell``); the nominal values when
  there is none. The arm's TCP is the believed ``flange_to_tcp`` (what the controller
  sets on the robot), and ``SimCell.tcp_to_scanner``/``tcp_to_sensor``/``base_to_object``
  are the believed ones the controller maps readings with.

The world, the F/T sensor and the scanner get the true tool expressed in the frame of
the TCP the arm reports (an "object moved" fault shifts the true placement later).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from elastoprobe.controller.core.clock import VirtualClock
from elastoprobe.controller.core.forceloop import ForceLoopGains
from elastoprobe.controller.core.geometry import Pose, rotvec_to_matrix
from elastoprobe.controller.core.kinematics import forward, ur5e
from elastoprobe.controller.core.safety import SafetyLimits

from .arm import ArmSettings, SimArm
from .faults import FaultInjector, FaultPlan
from .ft import FTSettings, SimForceTorque
from .scanner import ProbeGeometry, ScannerSettings, SimLineScanner
from .truth_surface import DEFAULT_SPACING_MM, TopSurface, top_surface
from .world import SimWorld


@dataclass(frozen=True)
class Miscalibration:
    """How far the true cell differs from its file (drawn from the seed when enabled).

    Each magnitude is exact, its direction random: the payload mass is off by
    +-``payload_mass_rel``, its centre of mass by ``payload_com_mm``, the tip by
    ``tip_mm``, the scanner mount by ``scanner_mm`` and ``scanner_deg``.
    """

    enabled: bool = False
    payload_mass_rel: float = 0.1
    payload_com_mm: float = 5.0
    tip_mm: float = 2.0
    scanner_deg: float = 2.0
    scanner_mm: float = 3.0
    object_mm: float = 0.0                # horizontal shift of the object off its placement
    seed: int = 0                         # cell-level: the same cell whatever the run's seed


@dataclass(frozen=True)
class Believed:
    """The geometry the controller uses (mm, TCP frame = the believed TCP; kg)."""

    flange_to_tcp: Pose
    tcp_to_scanner: Pose
    tcp_to_sensor: Pose
    base_to_object: Pose
    payload_mass_kg: float
    payload_com_mm: np.ndarray            # centre of mass in the believed TCP frame


@dataclass(frozen=True)
class TrueGeometry:
    """The simulated cell's true tool and placement (mm, kg), the tool in the cell FILE's TCP frame.

    The physical tool is fixed to the flange, so :meth:`in_tcp` re-expresses it in the
    frame of any TCP the arm is told to use (the believed one). Scoring calibrations
    uses :meth:`as_dict` (the routines measure against the file's TCP).
    """

    file_flange_to_tcp: Pose
    payload_mass_kg: float
    payload_com_mm: np.ndarray            # centre of mass
    tip_offset_mm: np.ndarray             # tip centre (0 when the tip is where the file says)
    tcp_to_scanner: Pose
    tcp_to_sensor: Pose
    base_to_object: Pose

    def as_dict(self) -> dict:
        """{"mass", "com", "tip_offset", "tcp_to_scanner", "tcp_to_sensor", "base_to_object"} (file TCP frame)."""
        return {"mass": self.payload_mass_kg, "com": self.payload_com_mm, "tip_offset": self.tip_offset_mm,
                "tcp_to_scanner": self.tcp_to_scanner, "tcp_to_sensor": self.tcp_to_sensor,
                "base_to_object": self.base_to_object}

    def in_tcp(self, flange_to_tcp: Pose) -> dict:
        """:meth:`as_dict` with the tool in the frame of ``flange_to_tcp`` (the file's TCP: unchanged, exactly)."""
        out = self.as_dict()
        if np.array_equal(flange_to_tcp.matrix(), self.file_flange_to_tcp.matrix()):
            return out
        move = flange_to_tcp.inverse().compose(self.file_flange_to_tcp)     # new tcp <- file tcp
        out.update(com=move.apply(self.payload_com_mm), tip_offset=move.apply(self.tip_offset_mm),
                   tcp_to_scanner=move.compose(self.tcp_to_scanner), tcp_to_sensor=move.compose(self.tcp_to_sensor))
        return out


@dataclass
class SimCellParams:
    """Plain parameters of a simulated cell (mm, deg, N, kg, s)."""

    object: object                        # path of an object YAML, or a SimObject
    base_to_object: Pose
    tip_radius_mm: float
    flange_to_tcp: Pose
    tcp_to_scanner: Pose
    tcp_to_sensor: Pose
    payload_mass_kg: float
    payload_com_mm: np.ndarray            # centre of mass in the TCP frame
    limits: SafetyLimits
    seed: int = 0
    home_joints_deg: tuple[float, ...] = (0.0, -90.0, 90.0, -90.0, -90.0, 0.0)
    joint_limits_deg: list[tuple[float, float]] | None = None
    probe_radius_mm: float = 4.0          # the probe cylinder (its shadow), TCP frame z from a to b
    probe_z_range_mm: tuple[float, float] = (-148.0, -8.0)
    control_period_ms: float = 2.0
    ft: FTSettings = FTSettings()
    scanner: ScannerSettings = ScannerSettings()
    arm: ArmSettings = ArmSettings()
    force_loop: ForceLoopGains = ForceLoopGains()     # the cell's (the same on the real arm)
    miscalibration: Miscalibration = Miscalibration()
    faults: list[FaultPlan] = field(default_factory=list)
    start_time_s: float = 0.0
    believed: Believed | None = None      # None: the controller believes the nominal values above

    def believed_geometry(self) -> Believed:
        if self.believed is not None:
            return self.believed
        return Believed(self.flange_to_tcp, self.tcp_to_scanner, self.tcp_to_sensor, self.base_to_object,
                        self.payload_mass_kg, np.asarray(self.payload_com_mm, float))


class SimGroundTruth:
    """Ground truth over the object, in the OBJECT frame (only evaluate uses it)."""

    def __init__(self, obj, tip_radius_mm: float) -> None:
        self._obj = obj
        self._tip_radius_mm = tip_radius_mm

    def region_of(self, points_mm: np.ndarray) -> np.ndarray:
        return self._obj.region_of(np.atleast_2d(points_mm))

    def true_profile_mm(self, point_mm: np.ndarray, normal: np.ndarray, t: np.ndarray, force_n: float,
                        angle_deg: float, x_mm: np.ndarray) -> np.ndarray:
        return self._obj.true_profile_mm(point_mm, normal, t, force_n, angle_deg, x_mm, self._tip_radius_mm)

    def region_names(self) -> list[str]:
        return list(self._obj.region_names)

    def closest_surface(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(closest undeformed surface points (N,3) mm, outward unit normals (N,3), region labels (N,))."""
        return self._obj.closest_surface(np.atleast_2d(np.asarray(points_mm, dtype=float)))

    def boundary_distance_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """(N,) distance (mm) of each point to the nearest boundary between materials (inf: none)."""
        return self._obj.boundary_distance_mm(np.atleast_2d(points_mm))[0]

    def top_surface(self, max_tilt_deg: float, spacing_mm: float = DEFAULT_SPACING_MM) -> TopSurface:
        """The true top seen from above within ``max_tilt_deg``, one sample per ``spacing_mm``^2 of
        projected area with its surface area and true label (sim/truth_surface.py)."""
        return top_surface(self._obj, max_tilt_deg, spacing_mm)


def _random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


class SimCell:
    """The in-process simulated cell: clock, world, arm, F/T, scanner, faults."""

    is_simulated = True

    def __init__(self, params: SimCellParams, clock: VirtualClock | None = None) -> None:
        from .objects import load_object

        self.params = params
        obj = load_object(params.object) if isinstance(params.object, (str, Path)) else params.object
        self.clock = clock if clock is not None else VirtualClock(params.start_time_s)
        believed = params.believed_geometry()
        # What the controller reads from the cell (it maps every reading with these).
        self.tcp_to_scanner = believed.tcp_to_scanner
        self.tcp_to_sensor = believed.tcp_to_sensor
        self.base_to_object = believed.base_to_object
        self.payload_mass_kg = believed.payload_mass_kg
        self.payload_com_tcp_mm = believed.payload_com_mm
        self.truth = true_geometry(params)
        # The true tool in the frame of the TCP the arm reports (the believed one).
        true = self.truth.in_tcp(believed.flange_to_tcp)
        probe_axis_sensor = true["tcp_to_sensor"].rotation.T @ np.array([0.0, 0.0, 1.0])
        period_us = int(round(params.control_period_ms * 1000.0))
        self.world = SimWorld(self.clock, obj, true["base_to_object"], params.tip_radius_mm, params.seed,
                              params.limits, probe_axis_sensor, control_period_us=period_us,
                              tip_offset_tcp_mm=true["tip_offset"])
        limits_rad = None if params.joint_limits_deg is None else np.radians(np.asarray(params.joint_limits_deg, float))
        self._model = ur5e(believed.flange_to_tcp, limits_rad)
        # The force loop maps readings with what the controller believes (the sensor mount).
        self.arm = SimArm(self.world, self._model, np.radians(params.home_joints_deg), params.arm,
                          gains=params.force_loop, limits=params.limits,
                          tcp_to_sensor_rotation=believed.tcp_to_sensor.rotation)
        self.ft = SimForceTorque(self.world, true["tcp_to_sensor"], true["mass"], true["com"], params.ft)
        # The probe body is fixed to the flange: its nominal TCP-frame axis, moved into the arm's TCP frame.
        z0, z1 = params.probe_z_range_mm
        axis_a, axis_b = np.array([0.0, 0.0, z0]), np.array([0.0, 0.0, z1])
        if not np.array_equal(believed.flange_to_tcp.matrix(), params.flange_to_tcp.matrix()):
            arm_from_file = believed.flange_to_tcp.inverse().compose(params.flange_to_tcp)
            axis_a, axis_b = arm_from_file.apply(axis_a), arm_from_file.apply(axis_b)
        probe = ProbeGeometry(axis_a, axis_b, params.probe_radius_mm, true["tip_offset"], params.tip_radius_mm)
        self.scanner = SimLineScanner(self.world, true["tcp_to_scanner"], probe, params.scanner)
        self.faults = FaultInjector(self.world, params.faults)
        self.world.attach(self.arm, self.ft, self.scanner, self.faults)

    def true_geometry(self) -> dict:
        """The truth in the cell FILE's TCP frame (what calibration routines measure; scoring only)."""
        return self.truth.as_dict()

    def _true_geometry(self, p: SimCellParams) -> dict:
        """Kept for old callers: :meth:`true_geometry` of a cell built from ``p``."""
        return true_geometry(p).as_dict()

    # ------------------------------------------------------------------ Cell protocol
    def begin_step(self, step_key: tuple[int, int, int]) -> None:
        self.world.begin_step(step_key)

    def ground_truth(self) -> SimGroundTruth:
        return SimGroundTruth(self.world.obj, self.params.tip_radius_mm)

    def close(self) -> None:
        """Nothing to release (no threads, no sockets)."""

    # ------------------------------------------------------------------ simulator extras
    def home_pose(self) -> Pose:
        """The TCP pose at the home joints (base frame)."""
        return forward(self._model, np.radians(self.params.home_joints_deg))

    def restore_history(self, presses: list[tuple[np.ndarray, np.ndarray, float]]) -> None:
        """Rebuild permanent dents on resume: (point in the object frame, normal, max force N)."""
        self.world.restore_history(presses)

    def press_history(self) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """What :meth:`restore_history` needs to rebuild the object's state."""
        return [(p.point_obj.copy(), p.normal_obj.copy(), p.max_force_n) for p in self.world.presses]

    def operator_clear_estop(self) -> None:
        """An operator releases the emergency stop (the controller never does this)."""
        self.faults.operator_clear_estop()

    def validity_report(self, max_force_n: float) -> list[str]:
        return self.world.obj.validity_report(max_force_n, self.params.tip_radius_mm)


def true_geometry(p: SimCellParams) -> TrueGeometry:
    """The true tool and placement: the nominal values plus the miscalibration, if enabled.

    Drawn from the cell-level ``p.miscalibration.seed`` alone (not from the run seed or
    steps): the physical cell is what it is, for every session and every calibration run.
    """
    m = p.miscalibration
    truth = TrueGeometry(p.flange_to_tcp, p.payload_mass_kg, np.asarray(p.payload_com_mm, float), np.zeros(3),
                         p.tcp_to_scanner, p.tcp_to_sensor, p.base_to_object)
    if not m.enabled:
        return truth
    from .world import PRE_STEP, Stream, keyed_rng
    rng = keyed_rng(m.seed, PRE_STEP, 1, int(Stream.CONSTANTS))
    mass = p.payload_mass_kg * (1.0 + m.payload_mass_rel * rng.choice([-1.0, 1.0]))
    com = truth.payload_com_mm + m.payload_com_mm * _random_unit(rng)
    tip = m.tip_mm * _random_unit(rng)
    turn = Pose(m.scanner_mm * _random_unit(rng), rotvec_to_matrix(np.radians(m.scanner_deg) * _random_unit(rng)))
    b2o = p.base_to_object
    if m.object_mm > 0.0:
        # Set down off its place on the table: a shift in the table plane (base x, y).
        heading = rng.uniform(0.0, 2.0 * np.pi)
        b2o = Pose(b2o.position_mm + m.object_mm * np.array([np.cos(heading), np.sin(heading), 0.0]), b2o.rotation)
    return replace(truth, payload_mass_kg=float(mass), payload_com_mm=com, tip_offset_mm=tip,
                   tcp_to_scanner=p.tcp_to_scanner.compose(turn), base_to_object=b2o)


def believed_from_cell(cell) -> Believed:  # noqa: ANN001 — controller.config.CellSpec (as the controller believes it)
    """The geometry a controller holding ``cell`` uses."""
    tool = cell.tool
    return Believed(flange_to_tcp=tool.flange_to_tcp.pose(), tcp_to_scanner=tool.tcp_to_scanner.pose(),
                    tcp_to_sensor=tool.tcp_to_sensor.pose(), base_to_object=cell.object.base_to_object.pose(),
                    payload_mass_kg=float(tool.payload_mass_kg), payload_com_mm=np.asarray(tool.payload_com_mm, float))


def params_from_cell(cell, object_path: str | Path | None = None, seed: int = 0,  # noqa: ANN001
                     believed=None) -> SimCellParams:  # noqa: ANN001
    """Map a validated ``controller.config.CellSpec`` onto :class:`SimCellParams`.

    ``cell`` is the cell FILE (the truth is built from it); ``believed`` the cell spec as
    the controller believes it (calibrated), or None for the file's nominal values.
    ``object_path`` defaults to the cell's object file (relative paths are the caller's
    to resolve). The probe cylinder is the tool shape named "probe" if there is one.
    ``seed`` is the run's seed (noise); the miscalibration has its own, in the cell.
    """
    tool = cell.tool
    sim = cell.simulation
    probe_radius, probe_range = 4.0, (-148.0, -8.0)
    for shape in tool.shapes:
        if shape.name == "probe" and shape.kind == "cylinder":
            centre = shape.pose.pose()
            axis = centre.rotation[:, 2]
            if abs(abs(axis[2]) - 1.0) < 1e-6 and np.allclose(centre.position_mm[:2], 0.0):
                z = centre.position_mm[2]
                probe_radius = shape.radius_mm
                probe_range = (z - shape.length_mm / 2.0, z + shape.length_mm / 2.0)
    mis = sim.miscalibration
    faults = [FaultPlan(kind=f.kind, step=f.step, rate_per_100_steps=f.rate_per_100_steps,
                        rate_per_100_faults=f.rate_per_100_faults, clear_after_s=f.clear_after_s,
                        delay_s=f.delay_s, duration_s=f.duration_s, magnitude=f.magnitude) for f in sim.faults]
    return SimCellParams(
        object=object_path if object_path is not None else cell.object.file,
        base_to_object=cell.object.base_to_object.pose(),
        tip_radius_mm=tool.tip_radius_mm,
        flange_to_tcp=tool.flange_to_tcp.pose(),
        tcp_to_scanner=tool.tcp_to_scanner.pose(),
        tcp_to_sensor=tool.tcp_to_sensor.pose(),
        payload_mass_kg=tool.payload_mass_kg,
        payload_com_mm=np.asarray(tool.payload_com_mm, float),
        limits=cell.limits.safety(),
        seed=seed,
        home_joints_deg=tuple(cell.robot.home_joints_deg),
        joint_limits_deg=cell.robot.joint_limits_deg,
        probe_radius_mm=probe_radius,
        probe_z_range_mm=probe_range,
        control_period_ms=sim.control_period_ms,
        force_loop=cell.force_loop.gains(),
        ft=FTSettings(noise_n=sim.ft_noise_n, noise_nm=sim.ft_noise_nm, drift_n_per_h=sim.ft_drift_n_per_h,
                      range_n=cell.ft.range_n, range_nm=cell.ft.range_nm, rate_hz=cell.ft.rate_hz),
        scanner=ScannerSettings(samples=cell.scanner.samples_per_profile, rate_hz=cell.scanner.rate_hz,
                                field_of_view_deg=cell.scanner.field_of_view_deg,
                                max_range_mm=cell.scanner.max_range_mm, noise_scale=sim.scanner_noise_scale),
        miscalibration=Miscalibration(enabled=mis.enabled, payload_mass_rel=mis.payload_mass_rel,
                                      payload_com_mm=mis.payload_com_mm, tip_mm=mis.tip_mm,
                                      scanner_deg=mis.scanner_deg, scanner_mm=mis.scanner_mm,
                                      object_mm=mis.object_mm, seed=mis.seed),
        faults=faults,
        believed=None if believed is None else believed_from_cell(believed),
    )
