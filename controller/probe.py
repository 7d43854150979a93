"""One probe: standoff, reference scan, contact, force levels with scan bursts, unload, retract.

The executor drives a :class:`~elastoprobe.controller.core.devices.Cell` through the
session state machine. Every motion is validated before it is sent
(:class:`MotionValidator`), every wait polls the arm's trip and status bits, and
each force level ends in one callback (the journal's one transaction per step).
A failure raises :class:`ProbeFault`; the caller applies the plan's fault policy.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from .core.devices import ArmStatus, Cell, Motion, MotionState, Scan, Trip, WrenchBlock
from .core.errors import DeviceError, DeviceTimeout, MotionRefused
from .core.geometry import Pose, matrix_to_rotvec, probe_tcp_pose, rotvec_to_matrix, scan_points_base
from .machine import SessionMachine
from .placement import PlacementMonitor


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


class ProbeFault(Exception):
    """The probe could not be completed; ``kind`` matches the plan's fault policy keys."""

    def __init__(self, kind: str, message: str, trip: Trip | None = None) -> None:
        super().__init__(message)
        self.kind = kind
        self.message = message
        self.trip = trip


class MotionValidator(Protocol):
    def validate_path(self, start: Pose, end: Pose, contact_allowed: bool = False) -> None:
        """Raise MotionRefused if the straight TCP path is unreachable or collides."""
        ...


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
    # While the arm holds still or holds a regulated force and the controller only records
    # F/T and poses (the settle wait, tare waits, scan bursts), it polls this often. The
    # safety check-and-stop runs where the data arrives on every sample whatever the poll
    # (controller/core/forceloop.py): a crossing stops the arm at the same sample; the controller sees the
    # same F/T blocks in bigger pieces. Motion and contact search keep poll_period_s.
    hold_poll_period_s: float = 0.1
    reference_scans: int = 10
    scan_timeout_factor: float = 3.0

    @property
    def search_mm(self) -> float:
        """How far the contact search may travel from the standoff (mm): the standoff itself
        plus ``search_distance_mm`` past the nominal surface."""
        return self.standoff_mm + self.search_distance_mm


@dataclass
class _Recorder:
    """F/T samples and arm poses logged while a wait loop runs."""

    blocks: list[WrenchBlock] = field(default_factory=list)
    pose_t_s: list[float] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    rotations: list[np.ndarray] = field(default_factory=list)

    def clear(self) -> None:
        self.blocks.clear()
        self.pose_t_s.clear()
        self.poses.clear()
        self.rotations.clear()


class ProbeExecutor:
    """Runs probes on a cell, firing the state machine's triggers as it goes."""

    def __init__(self, cell: Cell, machine: SessionMachine, settings: ProbeSettings,
                 validator: MotionValidator, object_top_z_mm: float,
                 should_stop: Callable[[], bool] = lambda: False,
                 placement: PlacementMonitor | None = None) -> None:
        self.cell = cell
        self.machine = machine
        self.s = settings
        self.validator = validator
        self.object_top_z_mm = object_top_z_mm
        self.should_stop = should_stop
        self._rec = _Recorder()
        self.robot_time_s = 0.0
        # A trip the session has acknowledged while it unloads and retracts: moving away
        # from the surface is what brings the force back under the hysteresis level.
        self.acknowledged_trip: Trip | None = None
        # Where the arm was when the session began: a known-good place to route through.
        self.park_pose: Pose | None = cell.arm.status().tcp_pose
        # Checks every reference and loaded scan burst against the registered object.
        self.placement = placement
        self.on_placement: Callable[[str, dict], None] = lambda what, est: None
        # How each force level was reached (regulation_record): for the session's log.
        self.on_regulated: Callable[[dict], None] = lambda record: None

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
        standoff, deepest = self.contact_search_path(target, angle_deg)
        d = standoff.rotation[:, 2]
        n = self.cell.base_to_object.apply_vector(target.normal)

        self.machine.fire("go_to_target")
        self._travel_to(standoff)
        at_standoff()
        self.machine.fire("at_standoff")
        self._tare()
        ref_scans, ref_poses = self._scan_burst(s.reference_scans)
        self._check_placement(ref_scans, ref_poses, "the reference scans")
        self.machine.fire("reference_ok")
        # Contact search: the path from standoff to the deepest allowed point is validated
        # with the tip allowed to touch the object.
        search_mm = s.search_mm
        self.validator.validate_path(standoff, deepest, contact_allowed=True)
        motion = self.cell.arm.seek_contact(d, s.contact_speed_mm_s, s.contact_force_n, search_mm)
        state = self._wait(motion, timeout_s=search_mm / s.contact_speed_mm_s * 2.0 + 5.0)
        if state == MotionState.NO_CONTACT:
            raise ProbeFault("no_contact", f"no contact within {search_mm:.0f} mm of the standoff "
                             f"(object moved or missing?)")
        self._expect(state, MotionState.CONTACT, "seek_contact")
        self.machine.fire("contact")
        for k, level in enumerate(levels):
            if k > 0:
                self.machine.fire("next_level")
            before_level(level)
            self._rec.clear()
            t_command = self.cell.clock.now_s()
            motion = self.cell.arm.regulate_force(d, level.force_n, s.force_rate_n_s)
            ramp_s = level.force_n / s.force_rate_n_s
            state = self._wait(motion, timeout_s=ramp_s * 3.0 + 10.0)
            self._expect(state, MotionState.DONE, "regulate_force")
            t_done = self.cell.clock.now_s()
            self.machine.fire("at_force")
            self._hold(s.settle_s)
            self.on_regulated({"step": level.step_id, **regulation_record(
                WrenchBlock.concat(self._rec.blocks), level.force_n, t_command, t_done, self.cell.ft.rate_hz)})
            self.machine.fire("settled")
            step_start_s = self.cell.clock.now_s()
            scans, poses = self._scan_burst(s.scans_per_step)
            forces = self._forces_at([sc.exposure_t_s for sc in scans])
            self._check_force_held(forces, level.force_n)
            tip_base = Pose.from_list(poses.mean(axis=0)).position_mm - n * s.tip_radius_mm
            self._check_placement(scans, poses, f"the scans at {level.force_n:g} N", tip_base)
            on_step_done(StepData(
                step_id=level.step_id, force_target_n=level.force_n, angle_deg=angle_deg,
                scans_xz_mm=_stack_scans(scans), scan_t_s=np.array([sc.exposure_t_s for sc in scans]),
                scan_pose=poses, scan_force_n=forces, reference_xz_mm=_stack_scans(ref_scans),
                reference_pose=ref_poses, robot_time_s=round(self.cell.clock.now_s() - step_start_s, 6)))
        self.machine.fire("unload")
        self._unload_and_retract(n)

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
        """Travel to ``start``, then scan continuously while moving in a straight line to ``end``.

        The scan's path is validated with the route to its start, before the arm moves: a
        refused scan raises MotionRefused with the arm where it was. Returns the scans and
        the TCP pose (mm + rotation vector) at each exposure.
        """
        self._travel_to(start, then=(start, end))
        self.validator.validate_path(start, end)
        scanner = self.cell.scanner
        length_mm = float(np.linalg.norm(end.position_mm - start.position_mm))
        duration_s = length_mm / speed_mm_s
        count = max(1, int(duration_s * scanner.rate_hz))
        self._rec.clear()
        scanner.read_scans()
        motion = self.cell.arm.move_linear(end, speed_mm_s, self.s.free_accel_mm_s2)
        scanner.start_burst(count)
        scans: list[Scan] = []
        deadline = self.cell.clock.now_s() + duration_s * 3.0 + 10.0
        while motion.state() == MotionState.RUNNING or len(scans) < count:
            if self.cell.clock.now_s() > deadline:
                self.cell.arm.stop()
                raise ProbeFault("scanner", f"sweep got {len(scans)} of {count} profiles in time")
            self._tick()
            scans.extend(scanner.read_scans())
            if motion.state() not in (MotionState.RUNNING, MotionState.DONE):
                self._expect(motion.state(), MotionState.DONE, "sweep move")
        return scans, self._poses_at([sc.exposure_t_s for sc in scans])

    def safe_retract(self) -> None:
        """After a fault: unload along the normal if in contact, then move up to travel height."""
        arm = self.cell.arm
        status = arm.status()
        # An operator who stopped the robot's program has the arm: it is not moved until resumed.
        if status.emergency_stop or not status.connected or status.operator_stop:
            return
        arm.stop()
        pose = status.tcp_pose
        up = np.array([0.0, 0.0, 1.0])
        # Unload: straight up along +z of the base (the surface normal is not known here)
        # slowly, until the force is gone, then to travel height.
        lift_mm = max(0.0, self.object_top_z_mm + self.s.clearance_mm - pose.position_mm[2])
        slow = Pose(pose.position_mm + up * min(20.0, lift_mm), pose.rotation)
        self._move(slow, self.s.contact_speed_mm_s * 2, check=False)
        self._move(Pose(pose.position_mm + up * lift_mm, pose.rotation), self.s.free_speed_mm_s, check=False)

    # ------------------------------------------------------------------ motions
    def _travel_to(self, standoff: Pose, then: tuple[Pose, Pose] | None = None) -> None:
        """Up to travel height, across, then down to the standoff; every leg validated.
        ``then``, a move to make from there, is validated with each route (and not made): a
        route it cannot follow from is not taken.

        If the direct route is refused (e.g. the wrist would swing the scanner into a
        keep-out), go by the park pose, where the arm started the session. If that is
        refused too, turn the tool about its axis at travel height first (120 or 240 deg,
        either way) and go from there: a change of approach that turns the tool half
        over about its axis (45 -> 135 deg) can need the last wrist joint past its limit
        on the geodesic, while the same end pose is reached within it the other way round.
        """
        self._sync_validator()
        self._unwind_wrist()
        here = self.cell.arm.status().tcp_pose
        routes = [lambda: self._route(here, standoff)]
        if self.park_pose is not None:
            park = self.park_pose
            routes.append(lambda: self._route(here, park) + self._route(park, standoff))
        for turns in (1, -1, 2, -2):
            routes.append(lambda turns=turns: self._turned_route(here, standoff, turns))
        refused: MotionRefused | None = None
        for route in routes:
            try:
                self._travel_legs(route(), then)
                return
            except MotionRefused as exc:
                refused = refused or exc       # the direct route's reason is the telling one
        assert refused is not None
        raise refused

    def _turned_route(self, here: Pose, standoff: Pose, turns: int) -> list[tuple[Pose, Pose]]:
        """Up to travel height, ``turns`` x 120 deg about the tool axis (sign = direction),
        then the usual route to the standoff."""
        legs, turned = self._wrist_turn_legs(here, turns, np.radians(120.0))
        return legs + self._route(turned, standoff)

    def _wrist_turn_legs(self, here: Pose, turns: int, turn_rad: float) -> tuple[list[tuple[Pose, Pose]], Pose]:
        """Up to travel height, then ``abs(turns)`` straight turns of ``turn_rad`` about the
        tool axis (the sign of ``turns`` their direction) -> (legs, the pose they end at)."""
        travel_z = self.object_top_z_mm + self.s.clearance_mm
        top = Pose(np.array([*here.position_mm[:2], max(travel_z, here.position_mm[2])]), here.rotation)
        legs: list[tuple[Pose, Pose]] = [(here, top)] if top.distance_to(here)[0] > 0.05 else []
        start = top
        for k in range(1, abs(turns) + 1):
            turned = Pose(top.position_mm,
                          top.rotation @ rotvec_to_matrix(np.array([0.0, 0.0, np.sign(turns) * k * turn_rad])))
            legs.append((start, turned))
            start = turned
        return legs, start

    def _sync_validator(self) -> None:
        """Plan from the joints the arm really has: moves made without validation (a
        retract after a fault) or cut short by a stop leave the planner's seed stale."""
        if hasattr(self.validator, "seed_joints"):
            self.validator.seed_joints = np.asarray(self.cell.arm.status().joints_rad, dtype=float)  # type: ignore[attr-defined]

    def _unwind_wrist(self, max_wrist_rad: float = np.pi, leg_rad: float = np.radians(120.0)) -> None:
        """Turn the last wrist joint back by a full turn at travel height when it has wound
        beyond half a turn.

        Straight moves keep the joints continuous, so the last joint winds up over
        many contacts by whole turns that depend on the arm's history; wound up, a
        route may be refused for joint limits that an unwound arm would take. A resumed
        session starts from another history than an uninterrupted one, so the wrist is
        brought back into (-180, 180] deg before every travel: routes then depend on
        where the arm is, not on how it got there. Three 120 deg turns about the tool
        axis (each a valid straight move); skipped if refused.
        """
        arm = self.cell.arm
        q = np.asarray(arm.status().joints_rad, dtype=float)
        if abs(q[5]) <= max_wrist_rad or not hasattr(self.validator, "seed_joints"):
            return
        here = arm.status().tcp_pose
        saved = np.array(self.validator.seed_joints, dtype=float)   # type: ignore[attr-defined]
        for sign in (-1, 1):
            legs, _ = self._wrist_turn_legs(here, 3 * sign, leg_rad)
            try:
                for a, b in legs:
                    self.validator.validate_path(a, b)
            except MotionRefused:
                self.validator.seed_joints = saved   # type: ignore[attr-defined]
                continue
            end_q6 = float(self.validator.seed_joints[5])   # type: ignore[attr-defined]
            self.validator.seed_joints = saved   # type: ignore[attr-defined]
            if abs(end_q6) < abs(q[5]) - np.pi:
                self._travel_legs(legs)
                return

    def _route(self, here: Pose, standoff: Pose) -> list[tuple[Pose, Pose]]:
        travel_z = self.object_top_z_mm + self.s.clearance_mm
        legs: list[Pose] = []
        if here.position_mm[2] < travel_z - 1.0:
            legs.append(Pose(np.array([*here.position_mm[:2], travel_z]), here.rotation))
        above = Pose(np.array([*standoff.position_mm[:2], max(travel_z, standoff.position_mm[2])]),
                     standoff.rotation)
        legs += [above, standoff]
        route = []
        start = here
        for leg in legs:
            if start.distance_to(leg)[0] < 0.05 and start.distance_to(leg)[1] < 0.05:
                continue
            route.append((start, leg))
            start = leg
        return route

    def _travel_legs(self, route: list[tuple[Pose, Pose]], then: tuple[Pose, Pose] | None = None) -> None:
        saved = getattr(self.validator, "seed_joints", None)
        try:
            for start, leg in route:
                self.validator.validate_path(start, leg)
            arrived = getattr(self.validator, "seed_joints", None)
            if then is not None:
                self.validator.validate_path(*then)
                if arrived is not None:
                    self.validator.seed_joints = arrived   # type: ignore[attr-defined]
        except MotionRefused:
            if saved is not None:
                self.validator.seed_joints = saved   # type: ignore[attr-defined]
            raise
        for _, leg in route:
            self._move(leg, self.s.free_speed_mm_s)

    def _move(self, target: Pose, speed_mm_s: float, check: bool = True) -> None:
        motion = self.cell.arm.move_linear(target, speed_mm_s, self.s.free_accel_mm_s2)
        dist = float(np.linalg.norm(target.position_mm - self.cell.arm.status().tcp_pose.position_mm))
        state = self._wait(motion, timeout_s=dist / speed_mm_s * 3.0 + 10.0)
        self._expect(state, MotionState.DONE, "move_linear")

    def _unload_and_retract(self, n_base: np.ndarray) -> None:
        """Unload along the normal first (backing out along -d at 10 deg would drag the tip)."""
        arm = self.cell.arm
        self._sync_validator()
        pose = arm.status().tcp_pose
        away = Pose(pose.position_mm + n_base * (self.s.standoff_mm + 5.0), pose.rotation)
        self.validator.validate_path(pose, away, contact_allowed=True)
        self._move(away, self.s.contact_speed_mm_s * 2.0)
        self.machine.fire("retract")
        here = arm.status().tcp_pose
        travel_z = self.object_top_z_mm + self.s.clearance_mm
        if here.position_mm[2] < travel_z:
            up = Pose(np.array([*here.position_mm[:2], travel_z]), here.rotation)
            self.validator.validate_path(here, up)
            self._move(up, self.s.free_speed_mm_s)

    # ------------------------------------------------------------------ sensing
    def _tare(self) -> None:
        """Re-tare in free air at the standoff: F/T drift is large against 0.1 N forces."""
        self._hold(0.2)
        self.cell.ft.tare()
        self._hold(0.05)

    def _hold(self, duration_s: float) -> None:
        """Wait ``duration_s`` (s) recording F/T and poses, polling every hold_poll_period_s
        (the last poll shortened so the wait ends on time)."""
        clock = self.cell.clock
        end = clock.now_s() + duration_s
        while clock.now_s() < end - 1e-9:
            self._tick(min(self.s.hold_poll_period_s, end - clock.now_s()))

    def _scan_burst(self, count: int) -> tuple[list[Scan], np.ndarray]:
        scanner = self.cell.scanner
        self._rec.clear()
        scanner.read_scans()   # drop anything stale
        # The pose at the burst's start: exposures begin before the first (hold-period) poll.
        try:
            status = self.cell.arm.status()
        except DeviceError as exc:
            raise ProbeFault("device", str(exc)) from exc
        self._rec.pose_t_s.append(status.t_s)
        self._rec.poses.append(status.tcp_pose.position_mm)
        self._rec.rotations.append(status.tcp_pose.rotation)
        scanner.start_burst(count)
        scans: list[Scan] = []
        deadline = self.cell.clock.now_s() + count / scanner.rate_hz * self.s.scan_timeout_factor + 1.0
        while len(scans) < count:
            if self.cell.clock.now_s() > deadline:
                raise ProbeFault("scanner", f"scanner delivered {len(scans)} of {count} profiles in time")
            self._tick(self.s.hold_poll_period_s)
            try:
                scans.extend(scanner.read_scans())
            except DeviceTimeout as exc:
                raise ProbeFault("scanner", str(exc)) from exc
            except DeviceError as exc:
                raise ProbeFault("scanner", str(exc)) from exc
        scans = scans[:count]
        return scans, self._poses_at([sc.exposure_t_s for sc in scans])

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

    def _tick(self, period_s: float | None = None) -> None:
        """One poll period (default poll_period_s, s): let time pass, collect F/T and pose,
        check for trips and faults."""
        period_s = self.s.poll_period_s if period_s is None else period_s
        self.cell.clock.sleep_s(period_s)
        self.robot_time_s += period_s
        try:
            block = self.cell.ft.read_block()
            status = self.cell.arm.status()
        except DeviceError as exc:
            raise ProbeFault("device", str(exc)) from exc
        if len(block):
            self._rec.blocks.append(block)
            if len(self._rec.blocks) > 2000:
                del self._rec.blocks[:1000]
        self._rec.pose_t_s.append(status.t_s)
        self._rec.poses.append(status.tcp_pose.position_mm)
        self._rec.rotations.append(status.tcp_pose.rotation)
        trip = self.cell.arm.trip()
        if trip is not None and trip is not self.acknowledged_trip:
            raise ProbeFault(trip.kind, trip.message, trip)
        if status.emergency_stop:
            raise ProbeFault("emergency_stop", "emergency stop is pressed")
        if status.protective_stop:
            raise ProbeFault("protective_stop", "the robot is in a protective stop")
        if not status.connected:
            raise ProbeFault("connection", "lost the connection to the robot")
        if not status.program_running:
            raise self._program_stopped(status, "the probe")
        if self.should_stop():
            raise ProbeFault("operator_stop", "stop requested with elastoprobe stop")

    def _wait(self, motion: Motion, timeout_s: float) -> MotionState:
        deadline = self.cell.clock.now_s() + timeout_s
        while True:
            state = motion.state()
            if state != MotionState.RUNNING:
                return state
            if self.cell.clock.now_s() > deadline:
                self.cell.arm.stop()
                raise ProbeFault("device", f"{motion.kind} did not finish within {timeout_s:.1f} s")
            self._tick()

    def _expect(self, state: MotionState, wanted: MotionState, what: str) -> None:
        if state == wanted:
            return
        trip = self.cell.arm.trip()
        if trip is not None and trip is not self.acknowledged_trip:
            raise ProbeFault(trip.kind, trip.message, trip)
        status = self.cell.arm.status()
        if status.emergency_stop:
            raise ProbeFault("emergency_stop", "emergency stop is pressed")
        if status.protective_stop:
            raise ProbeFault("protective_stop", f"protective stop during {what}")
        if not status.connected:
            raise ProbeFault("connection", f"lost the connection to the robot during {what}")
        if not status.program_running:
            raise self._program_stopped(status, what)
        raise ProbeFault("device", f"{what} ended {state.value}, expected {wanted.value}")

    def _program_stopped(self, status: ArmStatus, what: str, wait_s: float = 1.0) -> ProbeFault:
        """The robot's program stopped with no safety stop: whose stop was it?

        The arm says so a moment later (a link tells an operator's stop from its own watchdog
        once the safety bits have had time to explain it), so wait for that (bounded) before
        naming the fault: an operator's stop pauses the session, nothing else may take the arm
        back from them."""
        clock = self.cell.clock
        deadline = clock.now_s() + wait_s
        while (not status.program_running and not status.operator_stop and not status.protective_stop
               and not status.emergency_stop and status.connected and clock.now_s() < deadline):
            clock.sleep_s(0.05)
            try:
                status = self.cell.arm.status()
            except DeviceError as exc:
                return ProbeFault("device", f"the robot program stopped during {what}: {exc}")
        if status.operator_stop:
            return ProbeFault("operator_stop", status.stop_reason or f"the robot program was stopped during {what}")
        if status.emergency_stop:
            return ProbeFault("emergency_stop", "emergency stop is pressed")
        if status.protective_stop:
            return ProbeFault("protective_stop", f"protective stop during {what}")
        return ProbeFault("device", f"the robot program stopped during {what} (no safety stop, no operator's)")

    def _poses_at(self, times_s: list[float]) -> np.ndarray:
        """TCP poses (mm + rotation vector) at the given times, from the poses logged while waiting."""
        t = np.asarray(self._rec.pose_t_s)
        out = np.zeros((len(times_s), 6))
        if len(t) == 0:
            pose = self.cell.arm.status().tcp_pose
            out[:] = pose.to_list()
            return _round_pose(out)
        pos = np.asarray(self._rec.poses)
        for i, ts in enumerate(times_s):
            for axis in range(3):
                out[i, axis] = np.interp(ts, t, pos[:, axis])
            j = int(np.clip(np.searchsorted(t, ts), 0, len(t) - 1))
            out[i, 3:] = matrix_to_rotvec(self._rec.rotations[j])
        return _round_pose(out)

    def _forces_at(self, times_s: list[float], window_s: float = 0.01) -> np.ndarray:
        """Mean F/T force (base frame) over a window around each exposure."""
        block = WrenchBlock.concat(self._rec.blocks)
        out = np.full((len(times_s), 3), np.nan)
        if not len(block):
            return out
        tcp_to_sensor = self.cell.tcp_to_sensor
        pose_t = np.asarray(self._rec.pose_t_s)
        for i, ts in enumerate(times_s):
            sel = np.abs(block.t_s - ts) <= window_s / 2 + 1e-9
            if not sel.any():
                sel = np.zeros(len(block), bool)
                sel[int(np.argmin(np.abs(block.t_s - ts)))] = True
            f_sensor = block.force_n[sel].mean(axis=0)
            j = int(np.clip(np.searchsorted(pose_t, ts), 0, len(pose_t) - 1)) if len(pose_t) else 0
            r_base_tcp = self._rec.rotations[j] if len(pose_t) else self.cell.arm.status().tcp_pose.rotation
            out[i] = r_base_tcp @ (tcp_to_sensor.rotation @ f_sensor)
        return out

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


def _round_pose(poses: np.ndarray) -> np.ndarray:
    """Poses (N, 6: mm + rotation vector rad) rounded to 1 nm and 1 nrad.

    Interpolating at absolute times leaves last-bit differences that depend on when a
    step ran; a resumed session runs its steps at other absolute times than an
    uninterrupted one and must store the same numbers (far below any measurement).
    """
    out = np.asarray(poses, dtype=float).reshape(-1, 6).copy()
    out[:, :3] = np.round(out[:, :3], 6)
    out[:, 3:] = np.round(out[:, 3:], 9)
    out[out == 0.0] = 0.0
    return out
