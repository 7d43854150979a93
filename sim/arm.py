"""Simulated UR5e-like arm (implements :class:`~elastoprobe.controller.devices.Arm`).

Kinematics come from :mod:`elastoprobe.controller.kinematics`. Every command is a
straight TCP path ``p(u) = p0 + u v``, ``R(u) = R0 exp(u w)`` and a motion law u(t)
evaluated in closed form over a sub-chunk of sample instants (no per-sample Python):

- ``move_linear``: refused (MotionRefused) above the TCP speed/acceleration limits or when
  IK along the straight line fails (reach, joint limits, singularity margins, branch
  flips); timed like a UR moveL (one trapezoid in the path parameter, slowed by the
  rotation and the joint-speed limits, the rules of ``kinematics.move_duration_s``).
- ``seek_contact``: a trapezoid over the search distance at the given speed; the first
  F/T sample whose |F| (the tared reading, what the driver sees) reaches the threshold
  stops it (CONTACT); reaching the end is NO_CONTACT.
- ``regulate_force``: a PI outer loop on the simulated F/T reading commanding the TCP
  speed along the direction, every ``force_loop_period_us`` (10 ms, as a speedL-based
  outer loop); the reference ramps at the rate, DONE once within tolerance for
  ``settle_updates`` loop periods, then it keeps holding (foam creeps: the integrator
  keeps pushing). The loop's gain follows an online estimate of the contact stiffness
  (N/mm from successive (dF, du) pairs), because rubber is ~50x stiffer than foam.
- ``stop``: decelerates along the current path at ``stop_decel_mm_s2``.

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

from elastoprobe.controller.devices import ArmStatus, DeviceIdentity, MotionState, Trip
from elastoprobe.controller.errors import MotionRefused
from elastoprobe.controller.geometry import Pose, matrix_to_rotvec, rotvec_to_matrix
from elastoprobe.controller.kinematics import ArmModel, forward, inverse, linear_path_joints

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

class SimMotion:
    """Handle of one asynchronous command (implements the Motion protocol)."""

    def __init__(self, kind: str, state: MotionState = MotionState.RUNNING) -> None:
        self._kind = kind
        self._state = state
        self._progress = 0.0 if state == MotionState.RUNNING else 1.0

    @property
    def kind(self) -> str:
        return self._kind

    def state(self) -> MotionState:
        return self._state

    def progress(self) -> float:
        return float(min(max(self._progress, 0.0), 1.0))

    def _finish(self, state: MotionState) -> None:
        if self._state == MotionState.RUNNING or (self._kind == "regulate_force" and self._state == MotionState.DONE):
            self._state = state


@dataclass
class _Law:
    """A motion law u(t) from t0 on (µs); kind: trapezoid | ramp | stop | hold."""

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


@dataclass
class _Regulator:
    """PI force loop state (reset at every new command and every new contact)."""

    direction: np.ndarray
    target_n: float
    rate_n_s: float
    start_n: float
    t0_us: int
    next_update_us: int
    stiffness_n_mm: float = 2.0
    integral: float = 0.0
    last_force_n: float | None = None
    last_u: float = 0.0
    in_band: int = 0
    done: bool = False

    def reference_n(self, t_us: int) -> float:
        elapsed = (t_us - self.t0_us) / US_PER_S
        if self.target_n >= self.start_n:
            return min(self.target_n, self.start_n + self.rate_n_s * elapsed)
        return max(self.target_n, self.start_n - self.rate_n_s * elapsed)


@dataclass(frozen=True)
class ArmSettings:
    """Behaviour of the simulated arm (defaults: UR5e-like)."""

    stop_decel_mm_s2: float = 2500.0        # stopL / safety stop deceleration
    halt_decel_mm_s2: float = 8000.0        # protective / emergency stop (category 1)
    seek_accel_mm_s2: float = 500.0
    force_loop_period_us: int = 10_000
    regulate_max_speed_mm_s: float = 15.0
    regulate_accel_mm_s2: float = 500.0
    regulate_loop_gain: float = 0.3         # fraction of the force error corrected per loop period
    regulate_integral_per_s: float = 1.5
    regulate_tolerance_n: float = 0.1
    regulate_tolerance_rel: float = 0.02
    settle_updates: int = 10
    regulate_range_mm: tuple[float, float] = (-30.0, 60.0)   # validated line around the start
    ik_step_mm: float = 20.0
    ik_step_deg: float = 10.0
    recovery_wait_s: float = 5.0
    rotation_equiv_mm_per_rad: float = 100.0


class SimArm:
    """The simulated arm: commands, status bits, the protective stop and recovery."""

    def __init__(self, world: "SimWorld", model: ArmModel, home_joints_rad: np.ndarray,
                 settings: ArmSettings = ArmSettings(), serial: str = "SIM-UR5E-0001") -> None:
        self._world = world
        self._model = model
        self._settings = settings
        self._serial = serial
        q = np.asarray(home_joints_rad, float)
        pose = forward(model, q)
        self._path = _Path(pose.position_mm, np.zeros(3), pose.rotation, np.zeros(3), np.zeros(1), q[None, :])
        self._law = _Law("hold", world.now_us, 0.0)
        self._u = 0.0
        self._du = 0.0
        self._motion: SimMotion | None = None
        self._regulator: _Regulator | None = None
        self._seek_threshold_n: float | None = None
        self._last_plan_u: np.ndarray | None = None
        self._last_plan_du: np.ndarray | None = None
        self._move_target: Pose | None = None
        self._motion_started_us = world.now_us
        self._protective_since_us: int | None = None
        self._estop = False
        self._connected = True
        self._program_running = True

    # ------------------------------------------------------------------ Arm protocol
    def identity(self) -> DeviceIdentity:
        return DeviceIdentity("arm", "UR5e (simulated)", self._serial, "5.15.0-sim",
                              {"control_period_ms": self._world.control_period_us / 1000.0})

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
                         connected=connected)

    def inverse_kinematics(self, tcp_pose: Pose, seed_joints_rad: np.ndarray | None = None) -> np.ndarray | None:
        seed = self._path.joints(self._u) if seed_joints_rad is None else seed_joints_rad
        return inverse(self._model, tcp_pose, seed)

    def move_linear(self, target: Pose, speed_mm_s: float, accel_mm_s2: float) -> SimMotion:
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
        motion = self._start(SimMotion("move_linear"), path,
                             _Law("trapezoid", now, 0.0, 1.0, rate=rate, accel=accel, end_us=now + total_us))
        self._move_target = target
        return motion

    def seek_contact(self, direction: np.ndarray, speed_mm_s: float, contact_force_n: float,
                     max_distance_mm: float) -> SimMotion:
        refused = self._refuse_if_not_ready("seek_contact")
        if refused is not None:
            return refused
        if not (0.0 < speed_mm_s <= self._model.max_tcp_speed_mm_s):
            raise MotionRefused(f"seek speed {speed_mm_s} mm/s out of range")
        if contact_force_n <= 0.0 or max_distance_mm <= 0.0:
            raise MotionRefused("seek_contact needs a positive force threshold and distance")
        e = _unit(direction)
        path = self._line_path(e, 0.0, float(max_distance_mm))
        accel = self._settings.seek_accel_mm_s2
        now = self._world.now_us
        total_us = int(math.ceil(trapezoid_total_s(max_distance_mm, speed_mm_s, accel) * US_PER_S))
        motion = self._start(SimMotion("seek_contact"), path,
                             _Law("trapezoid", now, 0.0, float(max_distance_mm), rate=speed_mm_s, accel=accel,
                                  end_us=now + total_us))
        self._seek_threshold_n = float(contact_force_n)
        return motion

    def regulate_force(self, direction: np.ndarray, target_force_n: float, rate_n_s: float) -> SimMotion:
        refused = self._refuse_if_not_ready("regulate_force")
        if refused is not None:
            return refused
        if target_force_n < 0.0 or rate_n_s <= 0.0:
            raise MotionRefused("regulate_force needs a target >= 0 N and a positive rate")
        e = _unit(direction)
        lo, hi = self._settings.regulate_range_mm
        path = self._line_path(e, lo, hi)
        now = self._world.now_us
        motion = self._start(SimMotion("regulate_force"), path, _Law("hold", now, 0.0))
        self._regulator = _Regulator(e, float(target_force_n), float(rate_n_s), self._measured_force_n(), now,
                                     next_update_us=now, last_u=0.0)
        return motion

    def stop(self) -> None:
        if not self._connected_or_raise("stop"):
            return
        self._halt(self._world.now_us, self._settings.stop_decel_mm_s2)
        if self._motion is not None:
            self._motion._finish(MotionState.STOPPED)

    def trip(self) -> Trip | None:
        return self._world.trip

    def rearm(self) -> bool:
        self._world.guard_flush()
        if self._world.trip is None:
            self._world.guard.rearm()
            return True
        if not self._world.guard.rearm():
            return False
        self._world.clear_trip()
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
    def _refuse_if_not_ready(self, what: str) -> SimMotion | None:
        self._connected_or_raise(what)
        if self._estop or self._protective_since_us is not None or not self._program_running:
            return SimMotion(what, MotionState.FAULT)
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

    def _start(self, motion: SimMotion, path: _Path, law: _Law) -> SimMotion:
        if self._motion is not None:
            self._motion._finish(MotionState.STOPPED)
        self._path, self._law, self._u, self._du = path, law, float(law.u0), 0.0
        self._motion = motion
        self._motion_started_us = self._world.now_us
        self._regulator = None
        self._seek_threshold_n = None
        self._move_target = None
        return motion

    def _halt(self, t_us: int, decel_mm_s2: float) -> None:
        """Decelerate along the current path from the current rate (motion law 'stop')."""
        scale = max(self._path.speed_scale, 1e-9)
        if self._path.speed_scale < 1e-9 and np.linalg.norm(self._path.w) > 0:
            scale = self._settings.rotation_equiv_mm_per_rad * float(np.linalg.norm(self._path.w))
        self._law = _Law("stop", t_us, self._u, v0=self._du, accel=decel_mm_s2 / scale)
        self._regulator = None
        self._seek_threshold_n = None

    def _measured_force_n(self, samples: int = 10) -> float:
        """|mean| of the latest tared F/T samples (what a driver's force loop reads)."""
        recent = self._world.ft._sim_recent(samples)
        if recent is None or recent.shape[0] == 0:
            return 0.0
        # The mean and norm spelled out (numpy's mean is a sum then a division; norm is
        # sqrt(x . x)): the same numbers without their Python-level overhead.
        mean = np.add.reduce(recent, axis=0) / recent.shape[0]
        return math.sqrt(float(mean.dot(mean)))

    # ------------------------------------------------------------------ world hooks (simulator internals)
    def _sim_motion_started_after(self, t_us: int) -> bool:
        return self._motion is not None and self._motion_started_us > t_us

    def _sim_tcp_pose(self) -> Pose:
        return self._path.pose(self._u)

    def _sim_tip_base(self, tip_offset_tcp_mm: np.ndarray) -> np.ndarray:
        pose = self._path.pose(self._u)
        return pose.position_mm + pose.rotation @ tip_offset_tcp_mm

    def _sim_bound_end(self, now_us: int, end_us: int) -> int:
        reg = self._regulator
        if reg is not None:
            nxt = reg.next_update_us if reg.next_update_us > now_us else reg.next_update_us + self._settings.force_loop_period_us
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
        reg, motion = self._regulator, self._motion
        return (reg is not None and motion is not None and reg.next_update_us == now_us
                and motion.kind == "regulate_force" and motion.state() == MotionState.DONE
                and not self._path._rotating and self._path.u_table.size > 1
                and self._protective_since_us is None and not self._estop and self._program_running)

    def _sim_hold_commit(self, reg: "_Regulator", t0_us: int, u0: float, v0: float, v1: float,
                         u: float, du: float) -> None:
        """Take the state a batched hold ended in: the regulator, the last loop period's law
        (from ``t0_us``: u0, rate v0 -> v1), and u, du/dt at its last sample."""
        self._regulator = reg
        self._law = _Law("ramp", t0_us, u0, v0=v0, v1=v1, accel=self._settings.regulate_accel_mm_s2)
        self._u, self._du = float(u), float(du)

    def _sim_plan(self, ts_us: np.ndarray) -> ArmPlan:
        reg = self._regulator
        if reg is not None and self._world.now_us >= reg.next_update_us:
            self._regulate_update(self._world.now_us)
        u, du = self._law.evaluate(ts_us)
        self._last_plan_u, self._last_plan_du = u, du
        return ArmPlan(self._path.positions(u), self._path.rotations(u), du, self._path.speed_scale)

    def _sim_event(self, ts_us: np.ndarray, samples) -> int | None:
        """Index of the first sample that ends the current motion (seek threshold), or None."""
        if self._seek_threshold_n is None or self._motion is None or self._motion.state() != MotionState.RUNNING:
            return None
        mags = samples.magnitudes_n()
        if mags is None:
            return None
        hit = np.flatnonzero(mags >= self._seek_threshold_n)
        return int(hit[0]) if hit.size else None

    def _sim_on_event(self, t_us: int) -> None:
        """The seek threshold was reached at the last committed sample: stop, CONTACT."""
        if self._motion is not None and self._motion.kind == "seek_contact":
            self._halt(t_us, self._settings.stop_decel_mm_s2)
            self._motion._finish(MotionState.CONTACT)
            self._motion._progress = 1.0

    def _sim_commit(self, ts_us: np.ndarray, last: int) -> None:
        self._u = float(self._last_plan_u[last])
        self._du = float(self._last_plan_du[last])
        t = int(ts_us[last])
        law, motion = self._law, self._motion
        if motion is None:
            return
        if law.kind == "trapezoid":
            span = law.u1 - law.u0
            motion._progress = (self._u - law.u0) / span if span else 1.0
            if law.end_us is not None and t >= law.end_us:
                self._u, self._du = law.u1, 0.0
                self._law = _Law("hold", t, law.u1)
                if motion.kind == "seek_contact":
                    motion._finish(MotionState.NO_CONTACT)
                    self._seek_threshold_n = None
                else:
                    motion._finish(MotionState.DONE)
                    target = self._move_target
                    if motion.kind == "move_linear" and target is not None:
                        # Hold exactly the commanded pose (bit for bit, whatever the path's rounding).
                        q = self._path.joints_table[-1:]
                        self._path = _Path(target.position_mm, np.zeros(3), target.rotation, np.zeros(3),
                                           np.zeros(1), q)
                        self._u, self._du = 0.0, 0.0
                        self._law = _Law("hold", t, 0.0)
        elif law.kind == "stop" and self._du == 0.0:
            self._law = _Law("hold", t, self._u)
        lo, hi = self._path.u_table[0], self._path.u_table[-1]
        if self._path.u_table.size > 1 and not (lo - 1e-6 <= self._u <= hi + 1e-6):
            self._sim_protective_stop(t, "path left its validated range (reach or joint limits)")

    def _sim_contact_began(self) -> None:
        """A new contact: the force loop's internal state starts afresh."""
        reg = self._regulator
        if reg is not None:
            reg.integral = 0.0
            reg.last_force_n = None
            reg.in_band = 0

    def _sim_halt(self, t_us: int, reason: str) -> None:
        """Stopped by the safety path (a trip) at ``t_us``."""
        self._halt(t_us, self._settings.stop_decel_mm_s2)
        if self._motion is not None:
            self._motion._finish(MotionState.TRIPPED)

    def _sim_protective_stop(self, t_us: int, reason: str) -> None:
        self._halt(t_us, self._settings.halt_decel_mm_s2)
        if self._protective_since_us is None:
            self._protective_since_us = t_us
        self._program_running = False
        if self._motion is not None:
            self._motion._finish(MotionState.FAULT)

    def _sim_emergency_stop(self, t_us: int) -> None:
        self._halt(t_us, self._settings.halt_decel_mm_s2)
        self._estop = True
        self._program_running = False
        if self._motion is not None:
            self._motion._finish(MotionState.FAULT)

    def _sim_clear_estop(self) -> None:
        """The operator released the e-stop: the program stays stopped until recovered."""
        self._estop = False
        if self._protective_since_us is None:
            self._protective_since_us = self._world.now_us

    def _sim_connection_lost(self, t_us: int) -> None:
        """RTDE lost: the robot-side watchdog stops the program."""
        self._halt(t_us, self._settings.stop_decel_mm_s2)
        self._program_running = False
        if self._motion is not None:
            self._motion._finish(MotionState.FAULT)

    def _sim_connection_restored(self) -> None:
        self._program_running = self._protective_since_us is None and not self._estop

    # ------------------------------------------------------------------ the force loop
    def _regulate_update(self, t_us: int) -> None:
        reg = self._regulator
        s = self._settings
        speed = self._force_loop_speed(reg, t_us, self._measured_force_n(), self._u)
        self._law = _Law("ramp", t_us, self._u, v0=self._du, v1=speed, accel=s.regulate_accel_mm_s2)
        motion = self._motion
        if motion is not None and motion.state() == MotionState.RUNNING:
            motion._progress = reg.last_force_n / reg.target_n if reg.target_n > 0 else 1.0
            if reg.in_band >= s.settle_updates:
                motion._finish(MotionState.DONE)
                motion._progress = 1.0

    def _force_loop_speed(self, reg: _Regulator, t_us: int, force: float, u: float) -> float:
        """One update of the PI force loop at ``t_us`` from the measured |F| (N) and the
        path position u (mm); returns the commanded speed (mm/s) and advances ``reg``.

        Pure in the arm's state (only ``reg`` changes), so the world's batched hold
        (:meth:`SimWorld._hold_span`) runs it on a copy of the regulator."""
        s = self._settings
        period_s = s.force_loop_period_us / US_PER_S
        if reg.last_force_n is not None:
            du = u - reg.last_u
            df = force - reg.last_force_n
            # Online stiffness (N/mm) from successive loop periods while moving into the load.
            if abs(du) > 2e-3 and force > 0.3 and df * du > 0:
                k_obs = min(max(df / du, 0.05), 1000.0)
                reg.stiffness_n_mm = math.exp(0.8 * math.log(reg.stiffness_n_mm) + 0.2 * math.log(k_obs))
        reg.last_force_n, reg.last_u = force, u
        ref = reg.reference_n(t_us)
        ref_next = reg.reference_n(t_us + s.force_loop_period_us)
        err = ref - force
        k = reg.stiffness_n_mm
        reg.integral += err * period_s
        limit = s.regulate_max_speed_mm_s * k / max(s.regulate_integral_per_s, 1e-9)
        reg.integral = min(max(reg.integral, -limit), limit)
        speed = ((ref_next - ref) / period_s) / k + s.regulate_loop_gain * err / (k * period_s) \
            + s.regulate_integral_per_s * reg.integral / k
        speed = min(max(speed, -s.regulate_max_speed_mm_s), s.regulate_max_speed_mm_s)
        reg.next_update_us = t_us + s.force_loop_period_us
        tol = max(s.regulate_tolerance_n, s.regulate_tolerance_rel * reg.target_n)
        at_target = ref == reg.target_n
        reg.in_band = reg.in_band + 1 if (at_target and abs(err) <= tol) else 0
        return speed


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, float)
    n = float(np.linalg.norm(v))
    if n < 1e-12:
        raise MotionRefused("direction has zero length")
    return v / n
