"""Simulated UR5e-like arm: device primitives in virtual time, supervised by the controller's force loop.

Kinematics come from :mod:`elastoprobe.controller.core.kinematics`. Every command is a
straight TCP path ``p(u) = p0 + u v``, ``R(u) = R0 exp(u w)`` and a motion law u(t)
evaluated in closed form over a sub-chunk of sample instants (no per-sample Python).

The primitives (what a UR controller offers):

- ``move_linear``: refused (MotionRefused) above the TCP speed/acceleration limits or when
  IK along the straight line fails (reach, joint limits, singularity margins, branch
  flips); timed like a UR moveL (one trapezoid in the path parameter, slowed by the
  rotation and the joint-speed limits, the rules of ``kinematics.move_duration_s``).
- ``speed_linear``: speedL along an IK-validated straight line: the TCP speed ramps to the
  commanded one at the given acceleration and keeps it.
- ``stop``: decelerates along the current path at ``stop_decel_mm_s2``.

Contact search and force regulation are not this arm's: they are
:class:`~elastoprobe.controller.core.forceloop.ForceSupervisor`'s, the same code and gains (the
cell file's ``force_loop:``) that run in the real cell's hardware process. ``seek_contact``
and ``regulate_force`` hand the supervisor its skill and run its speed commands on the
primitives; the world calls the supervisor where the data arrives, in virtual time: every
sub-chunk's F/T samples go to its contact check (a contact stops the arm at its sample),
sub-chunks are cut at each regulation update (every ``ForceLoopGains.period_s``), and the
world's guard asks it whether a crossing while a trip is latched belongs to a motion that
unloads (:meth:`SimArm._sim_lets_through`).

A new command starts from rest at the current pose (a real UR blends; the controller
never supersedes a fast motion). Status joints are interpolated between IK waypoints
of the current path (<= ``ik_step_mm`` apart); the pose is exact.

The UR's own safety: a protective stop when the true contact force exceeds its own
limit (150 N: UR's force limit has a 25 N tolerance, so probing limits come from the
F/T) or a path leaves its validated range; an emergency stop stays until an operator
clears it (:meth:`SimCell.operator_clear_estop`); ``recover_protective_stop`` waits
>= 5 s of virtual time, then unlocks and restarts the program.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from elastoprobe.controller.core.devices import ArmStatus, DeviceIdentity, MotionState, Trip
from elastoprobe.controller.core.errors import MotionRefused
from elastoprobe.controller.core.forceloop import (ForceLoopGains, ForceSupervisor, Regulation, SupervisedMotion, Verdict,
                                              measured_force_n)
from elastoprobe.controller.core.geometry import Pose, matrix_to_rotvec, rotvec_to_matrix
from elastoprobe.controller.core.kinematics import ArmModel, forward, inverse, linear_path_joints
from elastoprobe.controller.core.safety import SafetyLimits

from .world import US_PER_S, ArmPlan

if TYPE_CHECKING:   # pragma: no cover
    from .world import SimWorld


# --------------------------------------------------------------------------- paths and laws

class _Path:
    """p(u) = p0 + u v (mm), R(u) = R0 exp(u w) (w: rotation vector per unit u)."""

    def __init__(self, p0: np.ndarray, v: np.ndarray, r0: np.ndarray, w: np.ndarray,
                 u_table: np.ndarray, joints_table: np.ndarray) -> None:
        self.p0 = np.asarray(p0, float)
        self.v = np.asarray(v, float)
        self.r0 = np.asarray(r0, float)
        self.w = np.asarray(w, float)
        self.speed_scale = float(np.linalg.norm(self.v))       # mm per unit u
        self.u_table = u_table
        self.joints_table = joints_table
        theta = float(np.linalg.norm(self.w))
        self._rotating = theta > 1e-12
        if self._rotating:
            axis = self.w / theta
            k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
            self._k, self._k2, self._theta = k, k @ k, theta

    def positions(self, u: np.ndarray) -> np.ndarray:
        return self.p0 + u[:, None] * self.v

    def rotations(self, u: np.ndarray) -> np.ndarray:
        """(3,3) when the path does not rotate, else (n,3,3) (vectorised Rodrigues)."""
        if not self._rotating:
            return self.r0
        ang = u * self._theta
        rel = (np.eye(3)[None] + np.sin(ang)[:, None, None] * self._k[None]
               + (1.0 - np.cos(ang))[:, None, None] * self._k2[None])
        return np.einsum("ij,njk->nik", self.r0, rel)

    def pose(self, u: float) -> Pose:
        rot = self.r0 @ rotvec_to_matrix(self.w * u) if self._rotating else self.r0
        return Pose(self.p0 + u * self.v, rot)

    def joints(self, u: float) -> np.ndarray:
        """Joints (rad) at u, linear between IK waypoints (clamped to the table's ends)."""
        table, q = self.u_table, self.joints_table
        if table.size == 1 or u <= table[0]:
            return q[0].copy()
        if u >= table[-1]:
            return q[-1].copy()
        j = int(np.searchsorted(table, u))
        f = (u - table[j - 1]) / (table[j] - table[j - 1])
        return q[j - 1] + f * (q[j] - q[j - 1])


def trapezoid_u(t_s: np.ndarray, u0: float, u1: float, rate: float, accel: float) -> tuple[np.ndarray, np.ndarray]:
    """Rest-to-rest trapezoid from u0 to u1 (vectorised; the closed form of kinematics.trapezoid_state)."""
    dist = abs(u1 - u0)
    sign = 1.0 if u1 >= u0 else -1.0
    t = np.maximum(np.asarray(t_s, float), 0.0)
    if dist == 0.0:
        return np.full(t.shape, u0), np.zeros(t.shape)
    if dist <= rate * rate / accel:
        t_ramp = math.sqrt(dist / accel)
        v_peak = accel * t_ramp
    else:
        t_ramp = rate / accel
        v_peak = rate
    total = dist / v_peak + t_ramp
    d_ramp = 0.5 * accel * t_ramp * t_ramp
    if t.size:
        # Most sub-chunks lie within one phase: evaluate that phase alone (the same
        # expressions as the general case below, so the same numbers).
        lo, hi = float(t.min()), float(t.max())
        if hi < t_ramp:
            return u0 + sign * (0.5 * accel * t * t), sign * (accel * t)
        if lo >= t_ramp and hi <= total - t_ramp:
            return u0 + sign * (d_ramp + v_peak * (t - t_ramp)), np.full(t.shape, sign * v_peak)
        if lo >= total:
            return np.full(t.shape, u0 + sign * dist), np.full(t.shape, sign * 0.0)
    pos = np.where(t < t_ramp, 0.5 * accel * t * t,
                   np.where(t <= total - t_ramp, d_ramp + v_peak * (t - t_ramp),
                            dist - 0.5 * accel * np.maximum(total - t, 0.0) ** 2))
    vel = np.where(t < t_ramp, accel * t, np.where(t <= total - t_ramp, v_peak, accel * np.maximum(total - t, 0.0)))
    done = t >= total
    pos = np.where(done, dist, pos)
    vel = np.where(done, 0.0, vel)
    return u0 + sign * pos, sign * vel


def trapezoid_total_s(dist: float, rate: float, accel: float) -> float:
    dist = abs(dist)
    if dist == 0.0:
        return 0.0
    if dist <= rate * rate / accel:
        return 2.0 * math.sqrt(dist / accel)
    return dist / rate + rate / accel


def ramp_to_u(t_s: np.ndarray, u0: float, v0: float, v1: float, accel: float) -> tuple[np.ndarray, np.ndarray]:
    """From (u0, v0), change the rate to v1 at ``accel`` then keep it (vectorised)."""
    t = np.maximum(np.asarray(t_s, float), 0.0)
    dv = v1 - v0
    if dv == 0.0 or accel <= 0.0:
        return u0 + v0 * t, np.full(t.shape, v0)
    a = math.copysign(accel, dv)
    t_r = abs(dv) / accel
    if t.size and t_r <= float(t.min()):
        # The (short) change of rate is over before the first instant: a straight line.
        return (u0 + v0 * t_r + 0.5 * a * t_r * t_r - v1 * t_r) + v1 * t, np.full(t.shape, v1)
    tr = np.minimum(t, t_r)
    u = u0 + v0 * tr + 0.5 * a * tr * tr + v1 * np.maximum(t - t_r, 0.0)
    v = np.where(t < t_r, v0 + a * t, v1)
    return u, v


# --------------------------------------------------------------------------- motions

@dataclass
class _Law:
    """A motion law u(t) from t0 on (µs); kind: trapezoid | ramp | stop | hold. ``end_us``: when
    the law's motion ends (a move arrives; a contact search has travelled its distance)."""

    kind: str
    t0_us: int
    u0: float
    u1: float = 0.0
    v0: float = 0.0
    v1: float = 0.0
    rate: float = 0.0
    accel: float = 0.0
    end_us: int | None = None

    def evaluate(self, ts_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = (ts_us - self.t0_us) / US_PER_S
        if self.kind == "trapezoid":
            return trapezoid_u(t, self.u0, self.u1, self.rate, self.accel)
        if self.kind == "ramp":
            return ramp_to_u(t, self.u0, self.v0, self.v1, self.accel)
        if self.kind == "stop":
            return ramp_to_u(t, self.u0, self.v0, 0.0, self.accel)
        return np.full(t.shape, self.u0), np.zeros(t.shape)


def ramp_reach_s(distance: float, rate: float, accel: float) -> float:
    """Time (s) for a ramp from rest to ``rate`` at ``accel`` to cover ``distance`` (> 0)."""
    t_ramp = rate / accel
    d_ramp = 0.5 * accel * t_ramp * t_ramp
    if distance <= d_ramp:
        return math.sqrt(2.0 * distance / accel)
    return t_ramp + (distance - d_ramp) / rate


@dataclass(frozen=True)
class ArmSettings:
    """Behaviour of the simulated arm as a device (defaults: UR5e-like). The force loop's
    tuning is the cell's (``ForceLoopGains``), not the arm's."""

    stop_decel_mm_s2: float = 2500.0        # stopL / safety stop deceleration
    halt_decel_mm_s2: float = 8000.0        # protective / emergency stop (category 1)
    regulate_range_mm: tuple[float, float] = (-30.0, 60.0)   # validated line around the start
    ik_step_mm: float = 20.0
    ik_step_deg: float = 10.0
    recovery_wait_s: float = 5.0
    rotation_equiv_mm_per_rad: float = 100.0


# speedL lines are validated (IK) over this range around the start, tried from long to short.
SPEED_LINE_RANGES_MM = ((-150.0, 200.0), (-60.0, 100.0), (-20.0, 40.0))


class SimArm:
    """The simulated arm: primitives, status bits, the protective stop and recovery; the
    contact search and force regulation of :class:`ForceSupervisor` run on it.

    ``gains``: the cell's force loop; ``limits``: the cell's safety limits (the supervisor's
    trip policy); ``tcp_to_sensor_rotation``: the believed tcp <- sensor rotation.
    """

    def __init__(self, world: "SimWorld", model: ArmModel, home_joints_rad: np.ndarray,
                 settings: ArmSettings = ArmSettings(), serial: str = "SIM-UR5E-0001", *,
                 gains: ForceLoopGains = ForceLoopGains(), limits: SafetyLimits | None = None,
                 tcp_to_sensor_rotation: np.ndarray | None = None) -> None:
        self._world = world
        self._model = model
        self._settings = settings
        self._serial = serial
        self.gains = gains
        self.supervisor = ForceSupervisor(gains, limits if limits is not None else world.limits, tcp_to_sensor_rotation)
        self._r_tcp_sensor = np.eye(3) if tcp_to_sensor_rotation is None else np.asarray(tcp_to_sensor_rotation, float)
        self.loop_period_us = int(round(gains.period_s * US_PER_S))
        q = np.asarray(home_joints_rad, float)
        pose = forward(model, q)
        self._path = _Path(pose.position_mm, np.zeros(3), pose.rotation, np.zeros(3), np.zeros(1), q[None, :])
        self._law = _Law("hold", world.now_us, 0.0)
        self._u = 0.0
        self._du = 0.0
        self._motion: SupervisedMotion | None = None
        self._speed_line: np.ndarray | None = None      # direction of the speedL line in use (primitive)
        self._reg_t0_us = 0
        self._next_update_us = 0
        self._last_plan_u: np.ndarray | None = None
        self._last_plan_du: np.ndarray | None = None
        self._move_target: Pose | None = None
        self._protective_since_us: int | None = None
        self._estop = False
        self._connected = True
        self._program_running = True
        self._link_generation = 0          # connection losses so far (ArmStatus.link_generation)

    @property
    def _regulator(self) -> Regulation | None:
        """The regulation in flight (the supervisor's)."""
        return self.supervisor.regulation

    # ------------------------------------------------------------------ Arm protocol
    def identity(self) -> DeviceIdentity:
        return DeviceIdentity("arm", "UR5e (simulated)", self._serial, "5.15.0-sim",
                              {"control_period_ms": self._world.control_period_us / 1000.0,
                               "force_loop": self.supervisor.identity()})

    def status(self) -> ArmStatus:
        """The arm's state bits; without a connection, the last known pose and connected=False."""
        connected = self._world.faults._sim_connected()
        u = self._u
        pose = self._path.pose(u)
        return ArmStatus(t_s=self._world.now_s(), tcp_pose=pose, joints_rad=self._path.joints(u),
                         tcp_speed_mm_s=abs(self._du) * self._path.speed_scale,
                         program_running=self._program_running,
                         protective_stop=self._protective_since_us is not None,
                         emergency_stop=self._estop, is_moving=abs(self._du) * self._path.speed_scale > 1e-3,
                         connected=connected, link_generation=self._link_generation)

    def inverse_kinematics(self, tcp_pose: Pose, seed_joints_rad: np.ndarray | None = None) -> np.ndarray | None:
        seed = self._path.joints(self._u) if seed_joints_rad is None else seed_joints_rad
        return inverse(self._model, tcp_pose, seed)

    def move_linear(self, target: Pose, speed_mm_s: float, accel_mm_s2: float) -> SupervisedMotion:
        refused = self._refuse_if_not_ready("move_linear")
        if refused is not None:
            return refused
        m = self._model
        if not (0.0 < speed_mm_s <= m.max_tcp_speed_mm_s):
            raise MotionRefused(f"speed {speed_mm_s} mm/s outside (0, {m.max_tcp_speed_mm_s}] mm/s")
        if not (0.0 < accel_mm_s2 <= m.max_tcp_accel_mm_s2):
            raise MotionRefused(f"acceleration {accel_mm_s2} mm/s^2 outside (0, {m.max_tcp_accel_mm_s2}] mm/s^2")
        start = self._path.pose(self._u)
        seed = self._path.joints(self._u)
        if inverse(m, target, seed) is None:
            raise MotionRefused(f"target {np.round(target.position_mm, 1).tolist()} mm is out of reach or joint limits")
        table = self._path_joints(start, target, seed)
        if table is None:
            raise MotionRefused("no straight-line path: IK fails along it (reach, joint limits or a singularity)")
        rel = matrix_to_rotvec(start.rotation.T @ target.rotation)
        u_table = np.linspace(0.0, 1.0, table.shape[0])
        path = _Path(start.position_mm, target.position_mm - start.position_mm, start.rotation, rel, u_table, table)
        rate, accel = self._move_rates(path, table, speed_mm_s, accel_mm_s2)
        now = self._world.now_us
        total_us = int(math.ceil(trapezoid_total_s(1.0, rate, accel) * US_PER_S))
        motion = self.supervisor.begin_move(start.position_mm, target.position_mm)
        self._start(motion, path, _Law("trapezoid", now, 0.0, 1.0, rate=rate, accel=accel, end_us=now + total_us))
        self._move_target = target
        return motion

    def speed_linear(self, velocity_mm_s: np.ndarray, accel_mm_s2: float) -> None:
        """speedL (primitive): the TCP speed ramps to ``velocity_mm_s`` (base frame) at
        ``accel_mm_s2`` and keeps it.

        Along the line in use (the same or the opposite direction) only the rate changes; a
        new direction starts a new line from the current pose, IK-validated over the longest
        of ``SPEED_LINE_RANGES_MM`` that is reachable (a protective stop if none is). Zero
        decelerates to rest on the line in use."""
        self._connected_or_raise("speed_linear")
        if self._estop or self._protective_since_us is not None or not self._program_running:
            return
        now = self._world.now_us
        accel = max(float(accel_mm_s2), 1.0)
        v = np.asarray(velocity_mm_s, float).reshape(3)
        speed = float(np.linalg.norm(v))
        on_line = self._speed_line is not None and self._motion is not None and self._motion.active
        if speed < 1e-9:
            if on_line:
                self._set_rate(0.0, accel)
            else:
                self._halt(now, accel)
            return
        e = v / speed
        if on_line and abs(float(e @ self._speed_line)) > 1.0 - 1e-9:
            self._set_rate(speed * math.copysign(1.0, float(e @ self._speed_line)), accel)
            return
        for lo, hi in SPEED_LINE_RANGES_MM:
            try:
                path = self._line_path(e, lo, hi)
                break
            except MotionRefused:
                continue
        else:
            self._sim_protective_stop(now, "speedL: no reachable straight line along the commanded direction")
            return
        self._start(SupervisedMotion("speed_linear", e), path, _Law("ramp", now, 0.0, v0=0.0, v1=speed, accel=accel))
        self._speed_line = e

    def seek_contact(self, direction: np.ndarray, speed_mm_s: float, contact_force_n: float,
                     max_distance_mm: float) -> SupervisedMotion:
        refused = self._refuse_if_not_ready("seek_contact")
        if refused is not None:
            return refused
        if not (0.0 < speed_mm_s <= self._model.max_tcp_speed_mm_s):
            raise MotionRefused(f"seek speed {speed_mm_s} mm/s out of range")
        if contact_force_n <= 0.0 or max_distance_mm <= 0.0:
            raise MotionRefused("seek_contact needs a positive force threshold and distance")
        e = _unit(direction)
        accel = self.gains.seek_accel_mm_s2
        # Validated beyond the search distance by the stop that follows it (and the sample
        # the distance is reached at).
        over_mm = speed_mm_s * speed_mm_s / (2.0 * self._settings.stop_decel_mm_s2) \
            + speed_mm_s * self._world.sample_period_us / US_PER_S
        path = self._line_path(e, 0.0, float(max_distance_mm) + over_mm)
        start = self._path.pose(self._u)
        motion = self.supervisor.begin_seek(e, speed_mm_s, contact_force_n, max_distance_mm, start.position_mm)
        now = self._world.now_us
        reach_us = int(math.ceil(ramp_reach_s(float(max_distance_mm), float(speed_mm_s), accel) * US_PER_S))
        self._start(motion, path, _Law("ramp", now, 0.0, v0=0.0, v1=float(speed_mm_s), accel=accel,
                                       end_us=now + reach_us))
        return motion

    def regulate_force(self, direction: np.ndarray, target_force_n: float, rate_n_s: float) -> SupervisedMotion:
        refused = self._refuse_if_not_ready("regulate_force")
        if refused is not None:
            return refused
        if target_force_n < 0.0 or rate_n_s <= 0.0:
            raise MotionRefused("regulate_force needs a target >= 0 N and a positive rate")
        e = _unit(direction)
        lo, hi = self._settings.regulate_range_mm
        path = self._line_path(e, lo, hi)
        now = self._world.now_us
        motion = self.supervisor.begin_regulation(e, target_force_n, rate_n_s, now / US_PER_S,
                                                  self._measured_force_n())
        self._start(motion, path, _Law("hold", now, 0.0))
        self._speed_line = e
        self._reg_t0_us = self._next_update_us = now
        return motion

    def stop(self, decel_mm_s2: float | None = None) -> None:
        """Stop any motion now at ``decel_mm_s2`` (default: the arm's stop deceleration)."""
        if not self._connected_or_raise("stop"):
            return
        self._halt(self._world.now_us, self._settings.stop_decel_mm_s2 if decel_mm_s2 is None
                   else max(float(decel_mm_s2), 1.0))
        self.supervisor.stopped()
        if self._motion is not None:
            self._motion.finish(MotionState.STOPPED, "stop requested")

    def trip(self) -> Trip | None:
        return self._world.trip

    def rearm(self) -> bool:
        self._world.guard_flush()
        if self._world.trip is None:
            self._world.guard.rearm()
            self.supervisor.rearmed()
            return True
        if not self._world.guard.rearm():
            return False
        self._world.clear_trip()
        self.supervisor.rearmed()
        return True

    def recover_protective_stop(self) -> bool:
        """Wait until >= 5 s after the stop (virtual time), unlock, restart the program."""
        self._world.faults._sim_check_connection("recover_protective_stop")
        if self._estop:
            return False
        if self._protective_since_us is None:
            if not self._program_running:
                self._program_running = True
            return True
        ready_us = self._protective_since_us + int(self._settings.recovery_wait_s * US_PER_S)
        wait_us = ready_us - self._world.now_us
        if wait_us > 0:
            self._world.clock.sleep_s(wait_us / US_PER_S + 1e-6)
        if self._estop or self._protective_since_us is None:
            return not self._estop
        self._protective_since_us = None
        self._program_running = True
        return True

    # ------------------------------------------------------------------ command helpers
    def _refuse_if_not_ready(self, what: str) -> SupervisedMotion | None:
        self._connected_or_raise(what)
        if self._estop or self._protective_since_us is not None or not self._program_running:
            return SupervisedMotion(what, state=MotionState.FAULT)
        return None

    def _connected_or_raise(self, what: str) -> bool:
        self._world.faults._sim_check_connection(what)
        return True

    def _line_path(self, e: np.ndarray, lo_mm: float, hi_mm: float) -> _Path:
        """A line along e from the current pose, IK-validated over [lo, hi] mm."""
        start = self._path.pose(self._u)
        seed = self._path.joints(self._u)
        a = Pose(start.position_mm + lo_mm * e, start.rotation)
        b = Pose(start.position_mm + hi_mm * e, start.rotation)
        table = self._path_joints(a, b, seed)
        if table is None:
            raise MotionRefused(f"no straight-line path along {np.round(e, 3).tolist()} over "
                                f"[{lo_mm:.0f}, {hi_mm:.0f}] mm (reach, joint limits or a singularity)")
        u_table = np.linspace(lo_mm, hi_mm, table.shape[0])
        return _Path(start.position_mm, e, start.rotation, np.zeros(3), u_table, table)

    def _path_joints(self, start: Pose, end: Pose, seed: np.ndarray) -> np.ndarray | None:
        """IK along the straight path: coarse waypoints first (fast); before refusing, the
        kinematics module's own fine waypoints, so a refusal means what it means there."""
        s = self._settings
        table = linear_path_joints(self._model, start, end, seed, step_mm=s.ik_step_mm, step_deg=s.ik_step_deg)
        if table is None:
            table = linear_path_joints(self._model, start, end, seed)
        return table

    def _move_rates(self, path: _Path, table: np.ndarray, speed: float, accel: float) -> tuple[float, float]:
        """Peak du/dt and d2u/dt2 (u in [0, 1]): TCP, rotation and joint limits, like move_duration_s."""
        s = self._settings
        dist = path.speed_scale
        angle = float(np.linalg.norm(path.w))
        rates, accels = [], []
        if dist > 1e-9:
            rates.append(speed / dist)
            accels.append(accel / dist)
        if angle > 1e-12:
            rates.append(speed / s.rotation_equiv_mm_per_rad / angle)
            accels.append(accel / s.rotation_equiv_mm_per_rad / angle)
        if table.shape[0] > 1:
            dq_du = np.max(np.abs(np.diff(table, axis=0)), axis=0) * (table.shape[0] - 1)
            moving = dq_du > 1e-12
            if moving.any():
                rates.append(float(np.min(self._model.max_joint_speed_rad_s[moving] / dq_du[moving])))
                accels.append(float(np.min(self._model.max_joint_accel_rad_s2[moving] / dq_du[moving])))
        if not rates:
            return 1e6, 1e9       # no motion at all
        return min(rates), min(accels)

    def _start(self, motion: SupervisedMotion, path: _Path, law: _Law) -> SupervisedMotion:
        if self._motion is not None and self._motion is not motion:
            self._motion.finish(MotionState.STOPPED, "superseded")
        self._path, self._law, self._u, self._du = path, law, float(law.u0), 0.0
        self._motion = motion
        self._move_target = None
        self._speed_line = None
        return motion

    def _set_rate(self, rate: float, accel_mm_s2: float) -> None:
        """A new speed along the line in use (mm/s of the path parameter), from the current state."""
        self._law = _Law("ramp", self._world.now_us, self._u, v0=self._du, v1=rate, accel=accel_mm_s2)

    def _halt(self, t_us: int, decel_mm_s2: float) -> None:
        """Decelerate along the current path from the current rate (motion law 'stop')."""
        scale = max(self._path.speed_scale, 1e-9)
        if self._path.speed_scale < 1e-9 and np.linalg.norm(self._path.w) > 0:
            scale = self._settings.rotation_equiv_mm_per_rad * float(np.linalg.norm(self._path.w))
        self._law = _Law("stop", t_us, self._u, v0=self._du, accel=decel_mm_s2 / scale)

    def _measured_force_n(self, samples: int | None = None) -> float:
        """|mean| of the latest tared F/T samples (what the force loop reads)."""
        recent = self._world.ft._sim_recent(self.gains.force_window if samples is None else samples)
        if recent is None:
            return 0.0
        return measured_force_n(recent)

    # ------------------------------------------------------------------ world hooks (simulator internals)
    def _sim_tcp_pose(self) -> Pose:
        return self._path.pose(self._u)

    def _sim_tip_base(self, tip_offset_tcp_mm: np.ndarray) -> np.ndarray:
        pose = self._path.pose(self._u)
        return pose.position_mm + pose.rotation @ tip_offset_tcp_mm

    def _sim_bound_end(self, now_us: int, end_us: int) -> int:
        if self.supervisor.regulation is not None:
            nxt = self._next_update_us if self._next_update_us > now_us else self._next_update_us + self.loop_period_us
            return min(end_us, nxt)
        law = self._law
        if law.end_us is not None and now_us < law.end_us < end_us:
            # End exactly where the move ends (the state changes there).
            grid = self._world.sample_period_us
            return min(end_us, law.end_us + (-law.end_us) % grid)
        return end_us

    def _sim_hold_ready(self, now_us: int) -> bool:
        """True when the arm only holds a regulated force: a finished regulate_force whose
        loop update is due at ``now_us``, on a straight line path without rotation (the
        world may then run whole force-loop periods in one batch, :meth:`SimWorld._hold_span`)."""
        reg, motion = self.supervisor.regulation, self._motion
        return (reg is not None and motion is not None and self._next_update_us == now_us
                and motion.kind == "regulate_force" and motion.state() == MotionState.DONE
                and not self._path._rotating and self._path.u_table.size > 1
                and self._protective_since_us is None and not self._estop and self._program_running)

    def _sim_hold_commit(self, reg: Regulation, t0_us: int, u0: float, v0: float, v1: float,
                         u: float, du: float) -> None:
        """Take the state a batched hold ended in: the regulation (run on a copy by the world),
        the last loop period's law (from ``t0_us``: u0, rate v0 -> v1), and u, du/dt at its
        last sample."""
        sup = self.supervisor
        before = sup.regulation.updates if sup.regulation is not None else 0
        sup.regulation = reg
        sup.counts.updates += reg.updates - before
        self._next_update_us = t0_us + self.loop_period_us
        self._law = _Law("ramp", t0_us, u0, v0=v0, v1=v1, accel=self.gains.accel_mm_s2)
        self._u, self._du = float(u), float(du)

    def _force_loop_speed(self, reg: Regulation, t_us: int, force: float, u: float) -> float:
        """One update of ``reg`` (the supervisor's law) at ``t_us`` from the measured |F| (N)
        and the path position u (mm): the commanded speed (mm/s). Changes only ``reg``, so the
        world's batched hold (:meth:`SimWorld._hold_span`) runs it on a copy."""
        return reg.update((t_us - self._reg_t0_us) / US_PER_S, force, u)

    def _sim_plan(self, ts_us: np.ndarray) -> ArmPlan:
        now = self._world.now_us
        if self.supervisor.regulation is not None and now >= self._next_update_us:
            self._regulate_update(now)
        u, du = self._law.evaluate(ts_us)
        self._last_plan_u, self._last_plan_du = u, du
        return ArmPlan(self._path.positions(u), self._path.rotations(u), du, self._path.speed_scale)

    def _sim_event(self, ts_us: np.ndarray, samples) -> int | None:
        """Index of the first sample that ends a contact search, or None: the supervisor's
        threshold, or the search distance reached (the arm stops from that sample, as the
        real arm's loop stops it from its next cycle, not a sub-chunk later beyond the
        validated line)."""
        if self.supervisor.search is None:
            return None
        law = self._law
        ends = None
        if law.kind == "ramp" and law.end_us is not None:
            k = int(np.searchsorted(ts_us, law.end_us))
            ends = k if k < ts_us.size else None
        mags = samples.magnitudes_n()
        hit = None if mags is None else self.supervisor.first_contact(mags)
        if hit is None or (ends is not None and ends < hit):
            return ends
        return hit

    def _sim_seek_samples(self, samples, cut: int) -> None:
        """The committed samples of a sub-chunk, while a contact search runs: to the
        supervisor, as the real sensor's blocks reach it (the touch's force rise)."""
        if self.supervisor.search is None:
            return
        mags = samples.fmag[:cut] if samples.fmag is not None else None
        if mags is None:
            return
        ts_s = samples.ts_us[:cut] / US_PER_S
        if not samples.all_delivered:
            keep = samples.delivered[:cut]
            ts_s, mags = ts_s[keep], mags[keep]
        self.supervisor.seek_samples(ts_s, mags)

    def _sim_on_event(self, t_us: int) -> None:
        """The contact search met its threshold at the last committed sample: stop, CONTACT."""
        if self.supervisor.search is not None:
            self._halt(t_us, self._settings.stop_decel_mm_s2)
            self.supervisor.contact(f"contact at t={t_us / US_PER_S:.4f} s")

    def _sim_commit(self, ts_us: np.ndarray, last: int) -> None:
        self._u = float(self._last_plan_u[last])
        self._du = float(self._last_plan_du[last])
        t = int(ts_us[last])
        law, motion = self._law, self._motion
        if motion is None:
            return
        if law.kind == "trapezoid":
            span = law.u1 - law.u0
            motion.set_progress((self._u - law.u0) / span if span else 1.0)
            if law.end_us is not None and t >= law.end_us:
                self._u, self._du = law.u1, 0.0
                self._law = _Law("hold", t, law.u1)
                motion.finish(MotionState.DONE)
                target = self._move_target
                if motion.kind == "move_linear" and target is not None:
                    # Hold exactly the commanded pose (bit for bit, whatever the path's rounding).
                    q = self._path.joints_table[-1:]
                    self._path = _Path(target.position_mm, np.zeros(3), target.rotation, np.zeros(3),
                                       np.zeros(1), q)
                    self._u, self._du = 0.0, 0.0
                    self._law = _Law("hold", t, 0.0)
        elif law.kind == "ramp" and self.supervisor.search is not None:
            search = self.supervisor.search
            # At the law's end instant the search distance is reached by construction (rounded
            # up onto the sample grid): float rounding must not leave it a hair short.
            reached = law.end_us is not None and t >= law.end_us
            travelled = max(self._u, search.max_distance_mm) if reached else self._u
            if self.supervisor.search_exhausted(search.start_mm + travelled * search.direction):
                self._halt(t, self._settings.stop_decel_mm_s2)
        elif law.kind == "stop" and self._du == 0.0:
            self._law = _Law("hold", t, self._u)
        lo, hi = self._path.u_table[0], self._path.u_table[-1]
        if self._path.u_table.size > 1 and not (lo - 1e-6 <= self._u <= hi + 1e-6):
            self._sim_protective_stop(t, "path left its validated range (reach or joint limits)")

    def _sim_contact_began(self) -> None:
        """A new contact: the force loop's internal state starts afresh."""
        self.supervisor.contact_began()

    def _sim_lets_through(self, trip: Trip, peak_force_n: float) -> bool:
        """While a trip is latched: does the supervisor let this crossing through (a motion
        that unloads the contact)?"""
        return self.supervisor.verdict(trip, peak_force_n) == Verdict.LET_THROUGH

    def _sim_halt(self, t_us: int, reason: str) -> None:
        """Stopped by the safety path (a trip) at ``t_us``."""
        self._halt(t_us, self._settings.stop_decel_mm_s2)
        trip = self._world.trip
        if trip is None:
            self.supervisor.stopped(reason)
            return
        force_base = None
        if trip.raw is not None and len(trip.raw):
            force_base = self._path.pose(self._u).rotation @ (self._r_tcp_sensor @ trip.raw.force_n[-1])
        self.supervisor.tripped(trip, self._world._latched_force_n, force_base)
        if self._motion is not None:
            self._motion.finish(MotionState.TRIPPED, trip.message)

    def _sim_protective_stop(self, t_us: int, reason: str) -> None:
        self._halt(t_us, self._settings.halt_decel_mm_s2)
        if self._protective_since_us is None:
            self._protective_since_us = t_us
        self._program_running = False
        self._fault(reason)

    def _sim_emergency_stop(self, t_us: int) -> None:
        self._halt(t_us, self._settings.halt_decel_mm_s2)
        self._estop = True
        self._program_running = False
        self._fault("emergency stop")

    def _sim_clear_estop(self) -> None:
        """The operator released the e-stop: the program stays stopped until recovered."""
        self._estop = False
        if self._protective_since_us is None:
            self._protective_since_us = self._world.now_us

    def _sim_connection_lost(self, t_us: int) -> None:
        """RTDE lost: the robot-side watchdog stops the program."""
        self._link_generation += 1
        self._halt(t_us, self._settings.stop_decel_mm_s2)
        self._program_running = False
        self._fault("connection lost")

    def _sim_connection_restored(self) -> None:
        self._program_running = self._protective_since_us is None and not self._estop

    def _fault(self, note: str) -> None:
        self.supervisor.faulted(note)
        if self._motion is not None:
            self._motion.finish(MotionState.FAULT, note)

    # ------------------------------------------------------------------ the force loop's updates
    def _regulate_update(self, t_us: int) -> None:
        """The supervisor's regulation update due at ``t_us``; its speed along the line."""
        newest = self._world.ft._sim_newest_us()
        age_s = 0.0 if newest is None else (t_us - newest) / US_PER_S
        speed = self.supervisor.regulate((t_us - self._reg_t0_us) / US_PER_S, self._measured_force_n(), self._u, age_s)
        self._next_update_us = t_us + self.loop_period_us
        self._law = _Law("ramp", t_us, self._u, v0=self._du, v1=speed, accel=self.gains.accel_mm_s2)


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, float)
    n = float(np.linalg.norm(v))
    if n < 1e-12:
        raise MotionRefused("direction has zero length")
    return v / n
