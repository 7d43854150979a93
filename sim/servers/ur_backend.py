"""The arm the UR emulator drives: a small Protocol, and a kinematic stand-in for tests.

Units and frames follow ur_rtde: poses are ``[x, y, z, rx, ry, rz]`` of the TCP in the
robot base frame, metres and a rotation vector in radians; speeds in m/s (rad/s for the
rotational part), accelerations in m/s^2, joint angles in rad. Time ``t_s`` is the
emulator's monotonic wall clock in seconds (ur_rtde runs on the wall clock).

The emulator calls a backend from one thread at a time (under its lock), at its tick
rate (500 Hz); a backend never blocks.

Tool frames: a backend's poses are those of ITS tool point, ``tool_ur()`` from the flange
(:class:`KinematicBackend`: the flange itself; the simulated world: the cell file's TCP).
The emulator re-expresses them in the TCP the robot program set (``set_tcp``), as a real
controller reports and takes TCP poses for its active TCP offset.
"""
from __future__ import annotations

import math
from typing import Protocol, runtime_checkable

import numpy as np

from elastoprobe.controller.core import kinematics as kin
from elastoprobe.controller.core.geometry import Pose, matrix_to_rotvec, rotvec_to_matrix


@runtime_checkable
class ArmBackend(Protocol):
    """What the UR emulator needs from an arm (simulated world or kinematic stand-in)."""

    def advance(self, t_s: float) -> None:
        """Integrate the arm up to wall time ``t_s`` (s, monotonic)."""
        ...

    def move_linear(self, pose_ur: np.ndarray, speed_m_s: float, accel_m_s2: float) -> None:
        """Start a straight-line TCP move (trapezoidal) to ``pose_ur``; returns at once."""
        ...

    def move_joint(self, q_rad: np.ndarray, speed_rad_s: float, accel_rad_s2: float) -> None:
        """Start a joint-space move to ``q_rad``; raises NotImplementedError if unsupported."""
        ...

    def speed_linear(self, xd: np.ndarray, accel_m_s2: float) -> None:
        """Accelerate the TCP towards the spatial velocity ``xd`` (m/s, rad/s) and keep it."""
        ...

    def stop(self, decel_m_s2: float) -> None:
        """Decelerate any motion to rest at ``decel_m_s2``."""
        ...

    def tcp_pose_ur(self) -> np.ndarray:
        """Actual pose (6,) of the backend's tool point (``tool_ur``), m + rotation vector."""
        ...

    def tool_ur(self) -> np.ndarray:
        """The backend's tool point in the flange frame (6,), m + rotation vector (zeros: the flange)."""
        ...

    def tcp_speed_ur(self) -> np.ndarray:
        """Actual TCP spatial velocity (6,), m/s + rad/s, base frame."""
        ...

    def joints_rad(self) -> np.ndarray:
        """Actual joint angles (6,), rad."""
        ...

    def tcp_force_ur(self) -> np.ndarray:
        """Wrench at the TCP (6,), N and N m, base frame (what RTDE calls actual_TCP_force)."""
        ...

    def is_moving(self) -> bool:
        """True while any commanded motion (including a deceleration) is under way."""
        ...

    def protective_stop_requested(self) -> str | None:
        """A reason when the arm itself detected a protective-stop condition (e.g. a
        collision in the simulated world), else None. Polled every tick."""
        ...

    def set_force_mode(self, active: bool, task_frame_ur: np.ndarray | None = None,
                       selection: np.ndarray | None = None, wrench: np.ndarray | None = None,
                       limits: np.ndarray | None = None) -> None:
        """Enter (with its parameters) or leave UR force mode."""
        ...

    def zero_ft_sensor(self) -> None:
        """Zero the arm's built-in F/T reading."""
        ...


# A pure rotation "costs" this many metres per radian when timing a move, so a
# rotation-only moveL takes a sensible time instead of zero.
ROT_EQUIV_M_PER_RAD = 0.1


def trapezoid_position(length: float, speed: float, accel: float, tau_s: float) -> tuple[float, float, float]:
    """Distance covered and speed after ``tau_s`` of a rest-to-rest trapezoid (or triangle).

    Returns (s, s_dot, duration_s) in the units of ``length`` (m or rad).
    """
    if length <= 0.0:
        return 0.0, 0.0, 0.0
    v = max(speed, 1e-9)
    a = max(accel, 1e-9)
    t_acc = v / a
    d_acc = 0.5 * a * t_acc * t_acc
    if 2.0 * d_acc > length:       # triangular: never reaches the cruise speed
        t_acc = math.sqrt(length / a)
        v = a * t_acc
        d_acc = 0.5 * length
    t_cruise = (length - 2.0 * d_acc) / v
    total = 2.0 * t_acc + t_cruise
    t = min(max(tau_s, 0.0), total)
    if t < t_acc:
        return 0.5 * a * t * t, a * t, total
    if t < t_acc + t_cruise:
        return d_acc + v * (t - t_acc), v, total
    td = total - t
    return length - 0.5 * a * td * td, a * td, total


_UR5E = kin.ur5e()


def _forward_ur(q_rad: np.ndarray) -> np.ndarray:
    """The flange pose [m, rad] (ur units) of a UR5e at joints ``q_rad`` (rad)."""
    return np.asarray(kin.forward(_UR5E, np.asarray(q_rad, dtype=float)).to_ur(), dtype=float)


def _inverse_ur(pose_ur: np.ndarray, seed_q_rad: np.ndarray) -> np.ndarray | None:
    """Joints (rad) putting the flange at ``pose_ur`` [m, rad], nearest ``seed_q_rad``; None
    out of reach (the backend then keeps the last joints)."""
    q = kin.inverse(_UR5E, Pose.from_ur(pose_ur), np.asarray(seed_q_rad, dtype=float))
    return None if q is None else np.asarray(q, dtype=float)


class KinematicBackend:
    """A real-time TCP mover without dynamics or contact: trapezoidal straight-line moves,
    speedL with an acceleration limit, stops at a deceleration. Joint angles are a UR5e's
    (``elastoprobe.controller.core.kinematics``), following the pose.

    ``initial_pose_ur``: start pose [m, rad]. ``t0_s``: the time of that state.
    """

    def __init__(self, initial_pose_ur: "np.ndarray | list[float]" = (0.4, -0.1, 0.3, 0.0, math.pi, 0.0),
                 t0_s: float = 0.0, initial_q_rad: "np.ndarray | None" = None) -> None:
        p = np.asarray(initial_pose_ur, dtype=float)
        self._pos_m = p[:3].copy()
        self._rot = rotvec_to_matrix(p[3:6])
        self._lin_vel = np.zeros(3)
        self._ang_vel = np.zeros(3)
        self._t_s = float(t0_s)
        self._mode = "idle"              # idle | move | speed | decel | joint
        self._move: dict[str, object] = {}
        self._target_vel = np.zeros(6)
        self._accel = 1.0
        self._decel = 1.0
        self._q = np.zeros(6) if initial_q_rad is None else np.asarray(initial_q_rad, dtype=float)
        self._q_valid_t_s = -1.0
        self.force_mode_active = False
        self.ft_zeroed_count = 0
        self.commands: list[tuple[str, float]] = []   # (kind, t_s), for tests and diagnostics

    # -- ArmBackend ---------------------------------------------------------------------
    def move_linear(self, pose_ur: np.ndarray, speed_m_s: float, accel_m_s2: float) -> None:
        goal = np.asarray(pose_ur, dtype=float)
        r_goal = rotvec_to_matrix(goal[3:6])
        rel = matrix_to_rotvec(self._rot.T @ r_goal)
        length = max(float(np.linalg.norm(goal[:3] - self._pos_m)),
                      float(np.linalg.norm(rel)) * ROT_EQUIV_M_PER_RAD)
        self._move = {"p0": self._pos_m.copy(), "r0": self._rot.copy(), "p1": goal[:3].copy(), "rel": rel,
                      "length": length, "speed": float(speed_m_s), "accel": float(accel_m_s2), "t0": self._t_s}
        self._mode = "move" if length > 1e-9 else "idle"
        self.commands.append(("move_linear", self._t_s))

    def move_joint(self, q_rad: np.ndarray, speed_rad_s: float, accel_rad_s2: float) -> None:
        q0 = self.joints_rad().copy()
        q1 = np.asarray(q_rad, dtype=float)
        lead = float(np.max(np.abs(q1 - q0)))
        self._move = {"q0": q0, "q1": q1, "length": lead, "speed": float(speed_rad_s),
                      "accel": float(accel_rad_s2), "t0": self._t_s}
        self._mode = "joint" if lead > 1e-9 else "idle"
        self.commands.append(("move_joint", self._t_s))

    def speed_linear(self, xd: np.ndarray, accel_m_s2: float) -> None:
        if self._mode != "speed":
            self.commands.append(("speed_linear", self._t_s))
        self._target_vel = np.asarray(xd, dtype=float).copy()
        self._accel = max(float(accel_m_s2), 1e-6)
        self._mode = "speed"

    def stop(self, decel_m_s2: float) -> None:
        if self._mode == "idle":
            return
        self._decel = max(float(decel_m_s2), 1e-6)
        self._mode = "decel"
        self.commands.append(("stop", self._t_s))

    def tcp_pose_ur(self) -> np.ndarray:
        return np.concatenate([self._pos_m, matrix_to_rotvec(self._rot)])

    def tool_ur(self) -> np.ndarray:
        """No tool: the poses are the flange's."""
        return np.zeros(6)

    def tcp_speed_ur(self) -> np.ndarray:
        return np.concatenate([self._lin_vel, self._ang_vel])

    def joints_rad(self) -> np.ndarray:
        if self._q_valid_t_s != self._t_s:
            q = _inverse_ur(self.tcp_pose_ur(), self._q)
            if q is not None:
                self._q = q
            self._q_valid_t_s = self._t_s
        return self._q

    def tcp_force_ur(self) -> np.ndarray:
        return np.zeros(6)

    def is_moving(self) -> bool:
        return self._mode != "idle"

    def protective_stop_requested(self) -> str | None:
        return None

    def set_force_mode(self, active: bool, task_frame_ur: np.ndarray | None = None,
                       selection: np.ndarray | None = None, wrench: np.ndarray | None = None,
                       limits: np.ndarray | None = None) -> None:
        # Nothing to push against in free space: force mode is only recorded. The control
        # script re-issues real-time commands every cycle, so record changes only.
        if bool(active) != self.force_mode_active:
            self.commands.append(("force_mode" if active else "force_mode_stop", self._t_s))
        self.force_mode_active = bool(active)

    def zero_ft_sensor(self) -> None:
        self.ft_zeroed_count += 1

    # -- integration --------------------------------------------------------------------
    def advance(self, t_s: float) -> None:
        dt = float(t_s) - self._t_s
        if dt <= 0.0:
            return
        self._t_s = float(t_s)
        if self._mode == "move":
            self._advance_move()
        elif self._mode == "joint":
            self._advance_joint()
        elif self._mode in ("speed", "decel"):
            self._advance_velocity(dt)
        else:
            self._lin_vel[:] = 0.0
            self._ang_vel[:] = 0.0

    def _advance_move(self) -> None:
        m = self._move
        length = float(m["length"])  # type: ignore[arg-type]
        s, s_dot, total = trapezoid_position(length, float(m["speed"]), float(m["accel"]),  # type: ignore[arg-type]
                                             self._t_s - float(m["t0"]))  # type: ignore[arg-type]
        f = s / length
        p0, p1, r0, rel = m["p0"], m["p1"], m["r0"], m["rel"]
        self._pos_m = p0 + f * (p1 - p0)  # type: ignore[operator]
        self._rot = r0 @ rotvec_to_matrix(f * rel)  # type: ignore[operator]
        self._lin_vel = (s_dot / length) * (p1 - p0)  # type: ignore[operator]
        self._ang_vel = (s_dot / length) * (r0 @ rel)  # type: ignore[operator]
        if self._t_s - float(m["t0"]) >= total:  # type: ignore[arg-type]
            self._mode = "idle"
            self._lin_vel[:] = 0.0
            self._ang_vel[:] = 0.0

    def _advance_joint(self) -> None:
        m = self._move
        length = float(m["length"])  # type: ignore[arg-type]
        s, _, total = trapezoid_position(length, float(m["speed"]), float(m["accel"]),  # type: ignore[arg-type]
                                         self._t_s - float(m["t0"]))  # type: ignore[arg-type]
        q = m["q0"] + (s / length) * (m["q1"] - m["q0"])  # type: ignore[operator]
        old = self.tcp_pose_ur()
        pose = _forward_ur(q)
        self._q = np.asarray(q, dtype=float)
        self._q_valid_t_s = self._t_s
        self._pos_m = pose[:3].copy()
        self._rot = rotvec_to_matrix(pose[3:6])
        self._lin_vel = (pose[:3] - old[:3]) * 0.0  # joint moves report no Cartesian speed
        if self._t_s - float(m["t0"]) >= total:  # type: ignore[arg-type]
            self._mode = "idle"

    def _advance_velocity(self, dt: float) -> None:
        if self._mode == "decel":
            target = np.zeros(6)
            rate = self._decel
        else:
            target = self._target_vel
            rate = self._accel
        vel = np.concatenate([self._lin_vel, self._ang_vel])
        # Linear and angular parts approach their targets at the same rate (m/s^2, rad/s^2).
        for sl in (slice(0, 3), slice(3, 6)):
            diff = target[sl] - vel[sl]
            n = float(np.linalg.norm(diff))
            step = rate * dt
            vel[sl] = target[sl] if n <= step else vel[sl] + diff * (step / n)
        mean_lin = 0.5 * (self._lin_vel + vel[:3])
        mean_ang = 0.5 * (self._ang_vel + vel[3:])
        self._pos_m = self._pos_m + mean_lin * dt
        self._rot = rotvec_to_matrix(mean_ang * dt) @ self._rot
        self._lin_vel = vel[:3]
        self._ang_vel = vel[3:]
        if self._mode == "decel" and not np.any(vel):
            self._mode = "idle"
