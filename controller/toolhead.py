"""The toolhead: the motion primitives every routine drives a cell through.

A :class:`Toolhead` moves the probe on any :class:`~elastoprobe.controller.core.devices.Cell`
(simulated, loopback or a real UR arm, through the cell registry): validated straight moves
and travel at a safe height, contact search, force regulation, retracts, holds and tares,
still F/T averages, scan bursts at rest and scans while moving. Every motion is validated
before it is sent (a :class:`MotionValidator`: reachability along the straight path, tool
shapes against the scene), every wait polls the arm's trip and status bits, and the F/T
samples and poses seen while waiting are recorded (:attr:`Toolhead.recorder`) so that scans
can be given the pose and force at their exposure.

The probe executor (``controller/probe.py``) builds a probe from these primitives and the
calibration routines (``calibration/``) build their touch-offs, F/T poses and sweeps from
the same ones. A failure raises :class:`ProbeFault` with the fault kind the plan's fault
policy names; a refused motion raises ``MotionRefused`` with the arm where it was.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from .core.devices import ArmStatus, Cell, Motion, MotionState, Scan, Trip, WrenchBlock
from .core.errors import DeviceError, MotionRefused
from .core.geometry import Pose, matrix_to_rotvec, rotvec_to_matrix

# Where a wound wrist that cannot unwind in place unwinds instead: this far (mm) out from
# the robot's base axis, nearest first. The scanner turning about the tool sweeps a circle
# of about its offset from the tool axis (~150 mm on the shipped mount); a few of those
# clear a keep-out the tool stood next to.
UNWIND_AWAY_MM = (75.0, 150.0, 300.0)
# One straight leg of a turn about the tool axis: a full turn is three (a straight move
# turns the shorter way, so a half turn in one leg has no defined direction).
WRIST_TURN_LEG_RAD = float(np.radians(120.0))


class ProbeFault(Exception):
    """A motion or measurement could not be completed; ``kind`` matches the plan's fault policy keys."""

    def __init__(self, kind: str, message: str, trip: Trip | None = None) -> None:
        super().__init__(message)
        self.kind = kind
        self.message = message
        self.trip = trip


class MotionValidator(Protocol):
    def validate_path(self, start: Pose, end: Pose, contact_allowed: bool = False) -> None:
        """Raise MotionRefused if the straight TCP path is unreachable or collides."""
        ...


@dataclass(frozen=True)
class MotionSettings:
    """Speeds, contact search and polling of a toolhead (mm, mm/s, mm/s^2, N, s)."""

    contact_force_n: float
    contact_speed_mm_s: float
    free_speed_mm_s: float
    free_accel_mm_s2: float
    poll_period_s: float = 0.01
    # While the arm holds still or holds a regulated force and the controller only records
    # F/T and poses (the settle wait, tare waits, scan bursts), it polls this often. The
    # safety check-and-stop runs where the data arrives on every sample whatever the poll
    # (controller/core/forceloop.py): a crossing stops the arm at the same sample; the controller sees the
    # same F/T blocks in bigger pieces. Motion and contact search keep poll_period_s.
    hold_poll_period_s: float = 0.1
    scan_timeout_factor: float = 3.0


@dataclass(frozen=True)
class Retracted:
    """What a retract did: ``asked_mm`` and ``moved_mm`` along its direction, and ``refused``,
    the refusal of the first longer move tried ('' when it went the whole way)."""

    asked_mm: float
    moved_mm: float
    refused: str = ""

    @property
    def shortened(self) -> bool:
        return self.moved_mm < self.asked_mm


@dataclass
class Recorder:
    """F/T samples and arm poses logged while a wait loop runs (pose times in the cell clock's s)."""

    blocks: list[WrenchBlock] = field(default_factory=list)
    pose_t_s: list[float] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    rotations: list[np.ndarray] = field(default_factory=list)

    def clear(self) -> None:
        self.blocks.clear()
        self.pose_t_s.clear()
        self.poses.clear()
        self.rotations.clear()

    def wrench(self) -> WrenchBlock:
        """Every F/T sample recorded since the last clear, as one block."""
        return WrenchBlock.concat(self.blocks)


class Toolhead:
    """Validated motion primitives on a cell (see the module docstring).

    ``travel_z_mm``: the height (base frame, TCP) the toolhead travels at between places;
    ``should_stop``: polled on every wait, True raises ProbeFault("operator_stop").
    """

    def __init__(self, cell: Cell, settings: MotionSettings, validator: MotionValidator, travel_z_mm: float,
                 should_stop: Callable[[], bool] = lambda: False) -> None:
        self.cell = cell
        self.s = settings
        self.validator = validator
        self.travel_z_mm = float(travel_z_mm)
        self.should_stop = should_stop
        self.recorder = Recorder()
        self.robot_time_s = 0.0
        # A trip the caller has acknowledged while it unloads and retracts: moving away
        # from the surface is what brings the force back under the hysteresis level.
        self.acknowledged_trip: Trip | None = None
        # Where the arm was when the toolhead was made: a known-good place to route through.
        self.park_pose: Pose | None = cell.arm.status().tcp_pose

    # ------------------------------------------------------------------ moves
    def pose(self) -> Pose:
        """The TCP pose the arm reports (base frame)."""
        return self.cell.arm.status().tcp_pose

    def move(self, target: Pose, speed_mm_s: float | None = None, contact_allowed: bool = False) -> None:
        """A validated straight move from where the arm is (MotionRefused, the arm not moved,
        if the path is not clear); ``contact_allowed`` lets the tip touch along the way."""
        here = self.pose()
        d_mm, d_deg = here.distance_to(target)
        if d_mm < 0.01 and d_deg < 0.01:
            return
        self.validator.validate_path(here, target, contact_allowed=contact_allowed)
        self._send_move(target, speed_mm_s or self.s.free_speed_mm_s)

    def travel_to(self, target: Pose, then: tuple[Pose, Pose] | None = None) -> None:
        """Up to travel height, across, then down to ``target``; every leg validated.
        ``then``, a move to make from there, is validated with each route (and not made): a
        route it cannot follow from is not taken.

        If the direct route is refused (e.g. the wrist would swing the scanner into a
        keep-out), go by the park pose, where the arm started. If that is refused too, turn
        the tool about its axis at travel height first (120 or 240 deg, either way) and go
        from there: a change of approach that turns the tool half over about its axis
        (45 -> 135 deg) can need the last wrist joint past its limit on the geodesic, while
        the same end pose is reached within it the other way round. Last, with the last
        wrist joint still wound beyond half a turn (its unwinding where the arm is was
        refused: near the robot, the turning scanner meets the column's keep-out), turn back
        what the column allows, move out from the robot and finish unwinding there
        (:meth:`_unwound_away_route`).
        """
        self.sync_validator()
        wound = not self._unwind_wrist()
        here = self.pose()
        routes = [lambda: self._route(here, target)]
        if self.park_pose is not None:
            park = self.park_pose
            routes.append(lambda: self._route(here, park) + self._route(park, target))
        for turns in (1, -1, 2, -2):
            routes.append(lambda turns=turns: self._turned_route(here, target, turns))
        if wound:
            for turns_here in (0, 1, 2):
                for out_mm in UNWIND_AWAY_MM:
                    for sign in (-1, 1):
                        routes.append(lambda sign=sign, out_mm=out_mm, turns_here=turns_here:
                                      self._unwound_away_route(here, target, sign, out_mm, turns_here))
        refused: MotionRefused | None = None
        for route in routes:
            try:
                self._travel_legs(route(), then)
                return
            except MotionRefused as exc:
                refused = refused or exc       # the direct route's reason is the telling one
        assert refused is not None
        raise refused

    def retract(self, direction: np.ndarray, distance_mm: float, speed_mm_s: float | None = None,
                min_distance_mm: float | None = None) -> Retracted:
        """Back out of a contact: a validated straight move of ``distance_mm`` along the unit
        vector ``direction`` (base frame; the tip may touch on the way), at ``speed_mm_s``
        (default twice the contact speed). Unloads a regulated force before anything else.

        With ``min_distance_mm``, a refused move is tried shorter (halved, down to that
        distance) before MotionRefused: backing out along a tilted normal beyond the
        approach's own checked path can lead the tool into a keep-out's margin (generated
        composite 1211: the flange 1.8 mm from the robot column, 5 mm past the standoff),
        and the fault's unvalidated retract then takes it there anyway. Returns how far it
        went and, when that is short of ``distance_mm``, why the longer moves were refused."""
        self.sync_validator()
        e = np.asarray(direction, dtype=float)
        here = self.pose()
        tries = [float(distance_mm)]
        if min_distance_mm is not None:
            while tries[-1] / 2.0 > min_distance_mm:
                tries.append(tries[-1] / 2.0)
            if min_distance_mm < tries[-1]:
                tries.append(float(min_distance_mm))
        refused: MotionRefused | None = None
        for length_mm in tries:
            away = Pose(here.position_mm + e * length_mm, here.rotation)
            try:
                self.validator.validate_path(here, away, contact_allowed=True)
            except MotionRefused as exc:
                refused = refused or exc
                continue
            self._send_move(away, speed_mm_s or self.s.contact_speed_mm_s * 2.0)
            return Retracted(float(distance_mm), length_mm, "" if refused is None else str(refused))
        assert refused is not None
        raise refused

    def lift_to_travel(self) -> None:
        """Straight up to travel height if the TCP is below it (validated)."""
        here = self.pose()
        if here.position_mm[2] < self.travel_z_mm:
            up = Pose(np.array([*here.position_mm[:2], self.travel_z_mm]), here.rotation)
            self.validator.validate_path(here, up)
            self._send_move(up, self.s.free_speed_mm_s)

    def safe_retract(self, unload_direction: np.ndarray | None = None) -> None:
        """After a fault: unload slowly along ``unload_direction`` (unit, base frame: the
        surface normal of the probe in flight, when there was one) or else straight up
        along +z of the base, then up to travel height, unvalidated (the scene around a
        faulted arm is not known); nothing if an operator, an emergency stop or a lost link
        has the arm.

        Why the normal: the guard lets a motion through a latched trip only if it moves
        away from the contact (forceloop). A push at 170 degrees on a face tilted a few
        degrees points slightly up; straight up then runs 0.08 into the contact, the retract
        tripped again and an overnight run paused (generated composite plate 1011). Along
        the normal every push angle of the plan (10-170 degrees) is left behind."""
        arm = self.cell.arm
        status = arm.status()
        # An operator who stopped the robot's program has the arm: it is not moved until resumed.
        if status.emergency_stop or not status.connected or status.operator_stop:
            return
        arm.stop()
        pose = status.tcp_pose
        up = np.array([0.0, 0.0, 1.0])
        e = up
        if unload_direction is not None:
            d = np.asarray(unload_direction, dtype=float)
            norm = float(np.linalg.norm(d))
            if norm > 0.0 and float(d @ up) > 0.0:
                e = d / norm
        lift_mm = max(0.0, self.travel_z_mm - pose.position_mm[2])
        slow = Pose(pose.position_mm + e * min(20.0, lift_mm), pose.rotation)
        self._send_move(slow, self.s.contact_speed_mm_s * 2)
        rest_mm = max(0.0, self.travel_z_mm - slow.position_mm[2])
        self._send_move(Pose(slow.position_mm + up * rest_mm, pose.rotation), self.s.free_speed_mm_s)

    # ------------------------------------------------------------------ force
    def seek_contact(self, direction: np.ndarray, max_distance_mm: float, speed_mm_s: float | None = None) -> bool:
        """Move along the unit vector ``direction`` (base frame) at ``speed_mm_s`` (default: the
        contact speed; never faster) until the force reaches the contact force: True at rest in
        contact, False when ``max_distance_mm`` passed with nothing touched. The whole path is
        validated first, the tip allowed to touch."""
        e = np.asarray(direction, dtype=float)
        here = self.pose()
        self.validator.validate_path(here, Pose(here.position_mm + e * max_distance_mm, here.rotation),
                                     contact_allowed=True)
        s = self.s
        speed = s.contact_speed_mm_s if speed_mm_s is None else min(float(speed_mm_s), s.contact_speed_mm_s)
        motion = self.cell.arm.seek_contact(e, speed, s.contact_force_n, max_distance_mm)
        state = self._wait(motion, timeout_s=max_distance_mm / speed * 2.0 + 5.0)
        if state == MotionState.NO_CONTACT:
            return False
        self._expect(state, MotionState.CONTACT, "seek_contact")
        return True

    def regulate_force(self, direction: np.ndarray, force_n: float, rate_n_s: float) -> tuple[float, float]:
        """Ramp the contact force along the unit vector ``direction`` to ``force_n`` at ``rate_n_s`` and hold it
        (the arm's force loop); returns (command time, settled time) on the cell clock (s).
        The recorder is cleared at the command: it holds the ramp's samples afterwards."""
        self.recorder.clear()
        t_command = self.cell.clock.now_s()
        motion = self.cell.arm.regulate_force(np.asarray(direction, dtype=float), force_n, rate_n_s)
        state = self._wait(motion, timeout_s=force_n / rate_n_s * 3.0 + 10.0)
        self._expect(state, MotionState.DONE, "regulate_force")
        return t_command, self.cell.clock.now_s()

    # ------------------------------------------------------------------ sensing
    def hold(self, duration_s: float) -> None:
        """Wait ``duration_s`` (s) recording F/T and poses, polling every hold_poll_period_s
        (the last poll shortened so the wait ends on time)."""
        clock = self.cell.clock
        end = clock.now_s() + duration_s
        while clock.now_s() < end - 1e-9:
            self._tick(min(self.s.hold_poll_period_s, end - clock.now_s()))

    def tare(self) -> None:
        """Re-tare in free air: F/T drift is large against 0.1 N forces."""
        self.hold(0.2)
        self.cell.ft.tare()
        self.hold(0.05)

    def still_wrench(self, settle_s: float, average_s: float, min_samples: int = 10) -> tuple[np.ndarray, np.ndarray, int]:
        """Mean force (N) and torque (N m), sensor frame, of the healthy samples over
        ``average_s`` (s) after ``settle_s`` (s) at rest, and their count."""
        self.hold(settle_s)
        self.recorder.clear()
        self.hold(average_s)
        block = self.recorder.wrench()
        ok = block.status == 0
        if ok.sum() < min_samples:
            raise ProbeFault("device", f"only {int(ok.sum())} healthy F/T samples while averaging")
        return block.force_n[ok].mean(axis=0), block.torque_nm[ok].mean(axis=0), int(ok.sum())

    def scan_burst(self, count: int) -> tuple[list[Scan], np.ndarray]:
        """``count`` profiles with the arm where it is, and the TCP pose (mm + rotation vector)
        at each exposure. The recorder is cleared first: it holds the burst's samples after."""
        scanner = self.cell.scanner
        self.recorder.clear()
        scanner.read_scans()   # drop anything stale
        # The pose at the burst's start: exposures begin before the first (hold-period) poll.
        try:
            status = self.cell.arm.status()
        except DeviceError as exc:
            raise ProbeFault("device", str(exc)) from exc
        self._record_pose(status)
        scanner.start_burst(count)
        scans: list[Scan] = []
        deadline = self.cell.clock.now_s() + count / scanner.rate_hz * self.s.scan_timeout_factor + 1.0
        while len(scans) < count:
            if self.cell.clock.now_s() > deadline:
                raise ProbeFault("scanner", f"scanner delivered {len(scans)} of {count} profiles in time")
            self._tick(self.s.hold_poll_period_s)
            try:
                scans.extend(scanner.read_scans())
            except DeviceError as exc:          # a timeout included
                raise ProbeFault("scanner", str(exc)) from exc
        scans = scans[:count]
        return scans, self.poses_at([sc.exposure_t_s for sc in scans])

    def scan_while_moving(self, start: Pose, end: Pose, speed_mm_s: float) -> tuple[list[Scan], np.ndarray]:
        """Travel to ``start``, then scan continuously while moving in a straight line to ``end``.

        The scan's path is validated with the route to its start, before the arm moves: a
        refused scan raises MotionRefused with the arm where it was. Returns the scans and
        the TCP pose (mm + rotation vector) at each exposure.
        """
        self.travel_to(start, then=(start, end))
        self.validator.validate_path(start, end)
        scanner = self.cell.scanner
        length_mm = float(np.linalg.norm(end.position_mm - start.position_mm))
        duration_s = length_mm / speed_mm_s
        count = max(1, int(duration_s * scanner.rate_hz))
        self.recorder.clear()
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
        return scans, self.poses_at([sc.exposure_t_s for sc in scans])

    def poses_at(self, times_s: list[float]) -> np.ndarray:
        """TCP poses (mm + rotation vector) at the given times, from the poses recorded while waiting."""
        rec = self.recorder
        t = np.asarray(rec.pose_t_s)
        out = np.zeros((len(times_s), 6))
        if len(t) == 0:
            out[:] = self.pose().to_list()
            return _round_pose(out)
        pos = np.asarray(rec.poses)
        for i, ts in enumerate(times_s):
            for axis in range(3):
                out[i, axis] = np.interp(ts, t, pos[:, axis])
            j = int(np.clip(np.searchsorted(t, ts), 0, len(t) - 1))
            out[i, 3:] = matrix_to_rotvec(rec.rotations[j])
        return _round_pose(out)

    def forces_at(self, times_s: list[float], window_s: float = 0.01) -> np.ndarray:
        """Mean F/T force (base frame, N) over a window (s) around each of ``times_s``."""
        rec = self.recorder
        block = rec.wrench()
        out = np.full((len(times_s), 3), np.nan)
        if not len(block):
            return out
        tcp_to_sensor = self.cell.tcp_to_sensor
        pose_t = np.asarray(rec.pose_t_s)
        for i, ts in enumerate(times_s):
            sel = np.abs(block.t_s - ts) <= window_s / 2 + 1e-9
            if not sel.any():
                sel = np.zeros(len(block), bool)
                sel[int(np.argmin(np.abs(block.t_s - ts)))] = True
            f_sensor = block.force_n[sel].mean(axis=0)
            j = int(np.clip(np.searchsorted(pose_t, ts), 0, len(pose_t) - 1)) if len(pose_t) else 0
            r_base_tcp = rec.rotations[j] if len(pose_t) else self.pose().rotation
            out[i] = r_base_tcp @ (tcp_to_sensor.rotation @ f_sensor)
        return out

    def sync_validator(self) -> None:
        """Plan from the joints the arm really has: moves made without validation (a
        retract after a fault, a force loop) or cut short by a stop leave the planner's seed stale."""
        if hasattr(self.validator, "seed_joints"):
            self.validator.seed_joints = np.asarray(self.cell.arm.status().joints_rad, dtype=float)  # type: ignore[attr-defined]

    # ------------------------------------------------------------------ routes
    def _turned_route(self, here: Pose, target: Pose, turns: int) -> list[tuple[Pose, Pose]]:
        """Up to travel height, ``turns`` x 120 deg about the tool axis (sign = direction),
        then the usual route to ``target``."""
        legs, turned = self._wrist_turn_legs(here, turns, WRIST_TURN_LEG_RAD)
        return legs + self._route(turned, target)

    def _wrist_turn_legs(self, here: Pose, turns: int, turn_rad: float) -> tuple[list[tuple[Pose, Pose]], Pose]:
        """Up to travel height, then ``abs(turns)`` straight turns of ``turn_rad`` about the
        tool axis (the sign of ``turns`` their direction) -> (legs, the pose they end at)."""
        top = Pose(np.array([*here.position_mm[:2], max(self.travel_z_mm, here.position_mm[2])]), here.rotation)
        legs: list[tuple[Pose, Pose]] = [(here, top)] if top.distance_to(here)[0] > 0.05 else []
        start = top
        for k in range(1, abs(turns) + 1):
            turned = Pose(top.position_mm,
                          top.rotation @ rotvec_to_matrix(np.array([0.0, 0.0, np.sign(turns) * k * turn_rad])))
            legs.append((start, turned))
            start = turned
        return legs, start

    def _unwound_away_route(self, here: Pose, target: Pose, sign: int, out_mm: float,
                            turns_here: int) -> list[tuple[Pose, Pose]]:
        """Up to travel height, ``turns_here`` of the unwinding's three 120 deg legs about the
        tool axis where the arm is (``sign``: their direction), ``out_mm`` straight away from
        the robot's base axis with the tool as it then is, the rest of the full turn there,
        then the usual route to ``target``.

        Out from the base axis the base joint keeps its angle and the wound joint turns
        little, and the turning scanner clears the robot's column; a joint wound within a
        few degrees of its limit turns back a leg or two where it is first (as far as the
        column allows) to have room for the move out."""
        radial = np.array([here.position_mm[0], here.position_mm[1]])
        norm = float(np.linalg.norm(radial))
        if norm < 1e-6:
            raise MotionRefused("no direction away from the base axis")
        legs, turned = self._wrist_turn_legs(here, turns_here * sign, WRIST_TURN_LEG_RAD)
        spot = Pose(np.array([*(turned.position_mm[:2] + radial / norm * out_mm), turned.position_mm[2]]),
                    turned.rotation)
        rest, unwound = self._wrist_turn_legs(spot, (3 - turns_here) * sign, WRIST_TURN_LEG_RAD)
        return legs + [(turned, spot)] + rest + self._route(unwound, target)

    def _unwind_wrist(self, max_wrist_rad: float = np.pi, leg_rad: float = WRIST_TURN_LEG_RAD) -> bool:
        """Turn the last wrist joint back by a full turn at travel height when it has wound
        beyond half a turn.

        Straight moves keep the joints continuous, so the last joint winds up over
        many contacts by whole turns that depend on the arm's history; wound up, a
        route may be refused for joint limits that an unwound arm would take. A resumed
        session starts from another history than an uninterrupted one, so the wrist is
        brought back into (-180, 180] deg before every travel: routes then depend on
        where the arm is, not on how it got there. Three 120 deg turns about the tool
        axis (each a valid straight move); skipped if refused. Returns False when the wrist
        stays wound.
        """
        arm = self.cell.arm
        q = np.asarray(arm.status().joints_rad, dtype=float)
        if abs(q[5]) <= max_wrist_rad or not hasattr(self.validator, "seed_joints"):
            return True
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
                return True
        return False

    def _route(self, here: Pose, target: Pose) -> list[tuple[Pose, Pose]]:
        travel_z = self.travel_z_mm
        legs: list[Pose] = []
        if here.position_mm[2] < travel_z - 1.0:
            legs.append(Pose(np.array([*here.position_mm[:2], travel_z]), here.rotation))
        above = Pose(np.array([*target.position_mm[:2], max(travel_z, target.position_mm[2])]), target.rotation)
        legs += [above, target]
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
            self._send_move(leg, self.s.free_speed_mm_s)

    def _send_move(self, target: Pose, speed_mm_s: float) -> None:
        """Send a straight move (already validated, or a fault's retract) and wait for it."""
        motion = self.cell.arm.move_linear(target, speed_mm_s, self.s.free_accel_mm_s2)
        dist = float(np.linalg.norm(target.position_mm - self.pose().position_mm))
        state = self._wait(motion, timeout_s=dist / speed_mm_s * 3.0 + 10.0)
        self._expect(state, MotionState.DONE, "move_linear")

    # ------------------------------------------------------------------ waiting
    def _record_pose(self, status: ArmStatus) -> None:
        self.recorder.pose_t_s.append(status.t_s)
        self.recorder.poses.append(status.tcp_pose.position_mm)
        self.recorder.rotations.append(status.tcp_pose.rotation)

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
            self.recorder.blocks.append(block)
            if len(self.recorder.blocks) > 2000:
                del self.recorder.blocks[:1000]
        self._record_pose(status)
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
