"""One probe: standoff, reference scan, contact, force levels with scan bursts, unload, retract.

The executor drives a :class:`~elastoprobe.controller.core.devices.Cell` through the
motion primitives of a :class:`~.toolhead.Toolhead` (validated moves, contact search,
force regulation, retracts, scan bursts: the same ones calibration uses) and fires the
session state machine's triggers between them. Each force level ends in one callback
(the journal's one transaction per step). A failure raises :class:`ProbeFault`; the
caller applies the plan's fault policy.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .core.devices import Cell, Scan, Trip, WrenchBlock
from .core.geometry import Pose, probe_tcp_pose, scan_points_base
from .machine import SessionMachine
from .placement import PlacementMonitor
from .toolhead import MotionSettings, MotionValidator, ProbeFault, Toolhead

# The least a refused unload backs out (mm), the tip's lowest point off the nominal surface:
# the extra 5 mm the full unload goes past the standoff, so a slowly recovering dent
# (creep) does not meet the tip on the way up.
RETRACT_CLEAR_MM = 5.0

__all__ = ["ForceLevel", "MotionValidator", "ProbeExecutor", "ProbeFault", "ProbeSettings", "ProbeTarget",
           "StepData", "regulation_record", "standoff_pose"]


@dataclass(frozen=True)
class ProbeTarget:
    """A point to probe, in the object frame (mm), with its outward normal and scan direction t."""

    index: int
    point_mm: np.ndarray
    normal: np.ndarray
    t: np.ndarray


@dataclass(frozen=True)
class ForceLevel:
    step_id: int
    force_n: float


@dataclass
class StepData:
    """What one force step measured (all poses base <- tcp, forces in the base frame)."""

    step_id: int
    force_target_n: float
    angle_deg: float
    scans_xz_mm: np.ndarray          # (S, L, 2) float32: scanner-frame x, z (NaN missing)
    scan_t_s: np.ndarray             # (S,)
    scan_pose: np.ndarray            # (S, 6) tcp pose at exposure: mm + rotation vector
    scan_force_n: np.ndarray         # (S, 3) mean contact force around each exposure, base frame
    reference_xz_mm: np.ndarray      # (R, L, 2) zero-force reference scans of the same place
    reference_pose: np.ndarray       # (R, 6)
    robot_time_s: float

    def force_magnitude_n(self) -> float:
        return float(np.linalg.norm(self.scan_force_n.mean(axis=0)))

    def measured_direction(self) -> np.ndarray:
        """Unit vector of the mean force the probe exerted (base frame)."""
        f = -self.scan_force_n.mean(axis=0)
        n = np.linalg.norm(f)
        return f / n if n > 0 else f


def standoff_pose(point_mm: np.ndarray, normal: np.ndarray, t: np.ndarray, angle_deg: float,
                  tip_radius_mm: float, standoff_mm: float) -> Pose:
    """TCP (tip centre) pose ``standoff_mm`` back along the probe from touching ``point``.

    A spherical tip touches a surface where the surface normal passes through its
    centre, whatever the approach angle: the centre sits at ``point + R n`` at first
    touch, and the probe approaches it along d from ``standoff_mm`` away.
    """
    centre = np.asarray(point_mm, dtype=float) + tip_radius_mm * np.asarray(normal, dtype=float)
    return probe_tcp_pose(centre, normal, t, angle_deg, offset_mm=standoff_mm)


@dataclass
class ProbeSettings:
    scans_per_step: int
    settle_s: float
    standoff_mm: float
    force_rate_n_s: float
    force_tolerance_n: float
    contact_force_n: float
    contact_speed_mm_s: float
    free_speed_mm_s: float
    free_accel_mm_s2: float
    search_distance_mm: float
    tip_radius_mm: float
    clearance_mm: float = 60.0          # travel height above the object's top
    poll_period_s: float = 0.01
    hold_poll_period_s: float = 0.1      # see MotionSettings
    reference_scans: int = 10
    scan_timeout_factor: float = 3.0

    def motion(self) -> MotionSettings:
        """The toolhead's share of these settings."""
        return MotionSettings(contact_force_n=self.contact_force_n, contact_speed_mm_s=self.contact_speed_mm_s,
                              free_speed_mm_s=self.free_speed_mm_s, free_accel_mm_s2=self.free_accel_mm_s2,
                              poll_period_s=self.poll_period_s, hold_poll_period_s=self.hold_poll_period_s,
                              scan_timeout_factor=self.scan_timeout_factor)

    @property
    def search_mm(self) -> float:
        """How far the contact search may travel from the standoff (mm): the standoff itself
        plus ``search_distance_mm`` past the nominal surface."""
        return self.standoff_mm + self.search_distance_mm


class ProbeExecutor:
    """Runs probes on a cell through its :attr:`toolhead`, firing the state machine's triggers as it goes."""

    def __init__(self, cell: Cell, machine: SessionMachine, settings: ProbeSettings,
                 validator: MotionValidator, object_top_z_mm: float,
                 should_stop: Callable[[], bool] = lambda: False,
                 placement: PlacementMonitor | None = None) -> None:
        self.cell = cell
        self.machine = machine
        self.s = settings
        self.object_top_z_mm = object_top_z_mm
        self.toolhead = Toolhead(cell, settings.motion(), validator, object_top_z_mm + settings.clearance_mm,
                                 should_stop)
        # Checks every reference and loaded scan burst against the registered object.
        self.placement = placement
        self.on_placement: Callable[[str, dict], None] = lambda what, est: None
        # How each force level was reached (regulation_record): for the session's log.
        self.on_regulated: Callable[[dict], None] = lambda record: None
        # An unload the limits cut short (asked_mm, moved_mm, refused): the arm stopped short of
        # where a user would expect it, so the session's log says so and why.
        self.on_unload_shortened: Callable[[dict], None] = lambda record: None
        # The surface normal and point (base frame) of the probe in flight, from its approach
        # until its unload ends: a fault's retract backs out along it (see safe_retract).
        self.contact_normal_base: np.ndarray | None = None
        self.contact_point_base_mm: np.ndarray | None = None

    # The session swaps these while it runs (a new scene after registration, a pause flag,
    # a trip it acknowledged while it retracts); they live on the toolhead that uses them.
    @property
    def validator(self) -> MotionValidator:
        return self.toolhead.validator

    @validator.setter
    def validator(self, value: MotionValidator) -> None:
        self.toolhead.validator = value

    @property
    def should_stop(self) -> Callable[[], bool]:
        return self.toolhead.should_stop

    @should_stop.setter
    def should_stop(self, value: Callable[[], bool]) -> None:
        self.toolhead.should_stop = value

    @property
    def acknowledged_trip(self) -> Trip | None:
        return self.toolhead.acknowledged_trip

    @acknowledged_trip.setter
    def acknowledged_trip(self, value: Trip | None) -> None:
        self.toolhead.acknowledged_trip = value

    # ------------------------------------------------------------------ public
    def probe(self, target: ProbeTarget, angle_deg: float, levels: list[ForceLevel],
              on_step_done: Callable[[StepData], None],
              before_level: Callable[[ForceLevel], None] = lambda level: None,
              at_standoff: Callable[[], None] = lambda: None) -> None:
        """Probe one target at one angle through ``levels`` (increasing forces).

        Calls ``at_standoff`` once the arm rests at the standoff (before the tare: what
        follows depends only on the target, not on where the arm came from — the
        session keys the simulator's noise there), ``before_level`` before each force
        ramp and ``on_step_done`` once per completed level; raises ProbeFault on failure
        (the arm is stopped; the caller unloads/retracts via :meth:`safe_retract`).
        """
        s = self.s
        head = self.toolhead
        standoff, _ = self.contact_search_path(target, angle_deg)
        d = standoff.rotation[:, 2]
        n = self.cell.base_to_object.apply_vector(target.normal)
        point = self.cell.base_to_object.apply(target.point_mm)

        self.machine.fire("go_to_target")
        head.travel_to(standoff)
        self.contact_normal_base, self.contact_point_base_mm = n, point
        at_standoff()
        self.machine.fire("at_standoff")
        head.tare()
        ref_scans, ref_poses = head.scan_burst(s.reference_scans)
        self._check_placement(ref_scans, ref_poses, "the reference scans")
        self.machine.fire("reference_ok")
        # Contact search, to the deepest allowed point (the path validated with the tip
        # allowed to touch the object).
        if not head.seek_contact(d, s.search_mm):
            raise ProbeFault("no_contact", f"no contact within {s.search_mm:.0f} mm of the standoff "
                             f"(object moved or missing?)")
        self.machine.fire("contact")
        for k, level in enumerate(levels):
            if k > 0:
                self.machine.fire("next_level")
            before_level(level)
            t_command, t_done = head.regulate_force(d, level.force_n, s.force_rate_n_s)
            self.machine.fire("at_force")
            head.hold(s.settle_s)
            self.on_regulated({"step": level.step_id, **regulation_record(
                head.recorder.wrench(), level.force_n, t_command, t_done, self.cell.ft.rate_hz)})
            self.machine.fire("settled")
            step_start_s = self.cell.clock.now_s()
            scans, poses = head.scan_burst(s.scans_per_step)
            forces = head.forces_at([sc.exposure_t_s for sc in scans])
            self._check_force_held(forces, level.force_n)
            tip_base = Pose.from_list(poses.mean(axis=0)).position_mm - n * s.tip_radius_mm
            self._check_placement(scans, poses, f"the scans at {level.force_n:g} N", tip_base)
            on_step_done(StepData(
                step_id=level.step_id, force_target_n=level.force_n, angle_deg=angle_deg,
                scans_xz_mm=_stack_scans(scans), scan_t_s=np.array([sc.exposure_t_s for sc in scans]),
                scan_pose=poses, scan_force_n=forces, reference_xz_mm=_stack_scans(ref_scans),
                reference_pose=ref_poses, robot_time_s=round(self.cell.clock.now_s() - step_start_s, 6)))
        self.machine.fire("unload")
        # Unload along the normal first (backing out along -d at 10 deg would drag the tip);
        # where the limits refuse the whole way, as far as they allow once the tip is
        # RETRACT_CLEAR_MM off the nominal surface.
        depth_mm = float((point - head.pose().position_mm) @ n) + s.tip_radius_mm
        unload = head.retract(n, s.standoff_mm + 5.0, s.contact_speed_mm_s * 2.0,
                              min_distance_mm=max(depth_mm, 0.0) + RETRACT_CLEAR_MM)
        if unload.shortened:
            self.on_unload_shortened({"asked_mm": round(unload.asked_mm, 3), "moved_mm": round(unload.moved_mm, 3),
                                      "refused": unload.refused})
        self.contact_normal_base = self.contact_point_base_mm = None
        self.machine.fire("retract")
        head.lift_to_travel()

    def contact_search_path(self, target: ProbeTarget, angle_deg: float) -> tuple[Pose, Pose]:
        """(standoff, deepest) TCP poses (base frame) of the contact search at one angle: the
        probe starts ``standoff_mm`` back along its axis and may go ``search_distance_mm``
        past the nominal surface before it gives up."""
        s = self.s
        b2o = self.cell.base_to_object
        standoff = standoff_pose(b2o.apply(target.point_mm), b2o.apply_vector(target.normal),
                                 b2o.apply_vector(target.t), angle_deg, s.tip_radius_mm, s.standoff_mm)
        return standoff, Pose(standoff.position_mm + standoff.rotation[:, 2] * s.search_mm, standoff.rotation)

    def scan_while_moving(self, start: Pose, end: Pose, speed_mm_s: float) -> tuple[list[Scan], np.ndarray]:
        """The toolhead's :meth:`~.toolhead.Toolhead.scan_while_moving` (the cloud sweep's line)."""
        return self.toolhead.scan_while_moving(start, end, speed_mm_s)

    def safe_retract(self) -> None:
        """After a fault: the toolhead's :meth:`~.toolhead.Toolhead.safe_retract`, unloading along
        the surface normal of the probe in flight (straight up can run into a push at 170
        degrees on a tilted face, which points slightly up) while the arm is still where that
        probe can have taken it; else straight up (moved since, by an operator)."""
        normal, point = self.contact_normal_base, self.contact_point_base_mm
        self.contact_normal_base = self.contact_point_base_mm = None
        if normal is not None and point is not None:
            reach_mm = self.s.standoff_mm + self.s.search_mm + self.s.tip_radius_mm
            if float(np.linalg.norm(self.toolhead.pose().position_mm - point)) > reach_mm:
                normal = None
        self.toolhead.safe_retract(normal)

    # ------------------------------------------------------------------ checks
    def _check_placement(self, scans: list[Scan], poses: np.ndarray, what: str,
                         loaded_at_mm: np.ndarray | None = None, dent_radius_mm: float = 45.0) -> None:
        """Raise ProbeFault("object_moved") when the scans show the object shifted sideways.

        Checked before contact (the reference scans) and before each force level is
        committed (the loaded scans, the dent left out): a step measured on a moved
        object must not be stored as done.
        """
        if self.placement is None:
            return
        # Every profile, not the burst's mean: beside a loaded dent only a few samples per
        # profile are left, and the mean profile would keep only those seen in all of them.
        pts = scan_points_base(_stack_scans(scans), poses, self.cell.tcp_to_scanner)
        est = self.placement.estimate(pts, self.cell.base_to_object, loaded_at_mm,
                                      dent_radius_mm if loaded_at_mm is not None else 0.0, max_points=600)
        self.on_placement(what, est.as_dict())
        if self.placement.moved(est):
            self.cell.arm.stop()
            raise ProbeFault("object_moved", f"{what} show the object {est.horizontal_mm:.1f} mm from where it "
                             f"is registered (shift {np.round(est.shift_mm, 1).tolist()} mm, fit RMS "
                             f"{est.rms_before_mm:.2f} -> {est.rms_after_mm:.2f} mm): it moved, or the "
                             f"scanner's calibration is off")

    def _check_force_held(self, forces_n: np.ndarray, target_n: float) -> None:
        magnitude = np.linalg.norm(forces_n, axis=1)
        err = float(np.nanmax(np.abs(magnitude - target_n))) if len(magnitude) else np.inf
        # The force must stay at the level while the scans are taken (the paper keeps it constant).
        if not np.isfinite(err) or err > max(self.s.force_tolerance_n * 3.0, 0.15 * target_n):
            raise ProbeFault("force_not_held", f"force strayed {err:.2f} N from {target_n:.1f} N during the scans")


def regulation_record(block: WrenchBlock, target_n: float, t_command_s: float, t_done_s: float,
                      rate_hz: float, window_s: float = 0.01, tail_s: float = 0.5) -> dict:
    """How a force level was reached, from the F/T samples of its ramp and settle: ``peak_n``
    and ``overshoot_n`` (peak minus target; negative: never reached) of |F| averaged over
    ``window_s`` (the force loop's own reading, not single noisy samples), ``settle_s`` from
    the command to DONE, and ``held_error_n``: mean |F| over the last ``tail_s`` minus target."""
    fmag = block.force_magnitude_n() if len(block) else np.zeros(0)
    n = max(1, int(round(window_s * rate_hz)))
    if fmag.size >= n:
        smooth = np.convolve(fmag, np.ones(n) / n, mode="valid")
        peak = float(smooth.max())
        tail = fmag[block.t_s >= block.t_s[-1] - tail_s]
        held = float(tail.mean()) - target_n
    else:
        return {"target_n": round(float(target_n), 6), "peak_n": None, "overshoot_n": None, "held_error_n": None,
                "settle_s": round(t_done_s - t_command_s, 4)}
    return {"target_n": round(float(target_n), 6), "peak_n": round(peak, 4), "overshoot_n": round(peak - target_n, 4),
            "held_error_n": round(held, 4), "settle_s": round(t_done_s - t_command_s, 4)}


def _stack_scans(scans: list[Scan]) -> np.ndarray:
    if not scans:
        return np.zeros((0, 0, 2), dtype=np.float32)
    return np.stack([np.stack([sc.x_mm, sc.z_mm], axis=1) for sc in scans]).astype(np.float32)
