"""The simulated world behind the real protocols: an ArmBackend for the UR emulator, and the
sources the simulated Net F/T and line scanner serve, all driven by one SimCell in real time.

The UR emulator (sim/servers/ur_emulator.py) moves :class:`WorldBackend`'s arm; the contact
physics of the same world produces the forces that sim/servers/netft_server.py streams
(:meth:`WorldBackend.ft_source`, counts) and the profiles sim/servers/scanner_serial.py
serves (:meth:`WorldBackend.profile_source`, from the world's scanner at the arm's real
pose). The controller sees only the protocols.

Time: the world runs on its own :class:`VirtualClock`, which this backend advances with the
wall clock (``time.monotonic()``): virtual t = wall t - ``t0_wall_s``. Three threads call in
(the emulator's tick, the Net F/T server, the scanner server); one lock serialises them, and
every entry point first brings the world up to "now".

Units: ArmBackend methods take and return ur_rtde units (m, rad, rotation vectors, m/s,
m/s^2, base frame); the world works in mm. Forces in the F/T source are sensor-frame
counts (``counts_per_force`` per N, ``counts_per_torque`` per N*m), the load ON the tool
(``WrenchBlock`` convention), untared: the Net F/T device has its own bias (0x42) and the
driver its software tare. Scanner profiles are resampled from the simulated scanner's fan
onto the server's fixed x grid (scanner frame, mm).

What a real UR would do and this backend does too: a moveL the arm cannot make (reach,
joint limits, speed) and a path that leaves its reachable range end in a protective stop;
the simulated UR force limit (150 N) protective-stops. The world's own copy of the F/T
safety guard is disabled here: on the protocols, the check-and-stop path belongs to the
controller's hardware process (controller/drivers/hardware.py), not to the robot.
"""
from __future__ import annotations

import threading
import time
from dataclasses import replace

import numpy as np

from elastoprobe.controller.core.errors import MotionRefused
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.core.safety import SafetyLimits

from ..cell import SimCell, SimCellParams
from ..world import US_PER_S

# A guard that never trips: the robot side has no ATI limits (see the module docstring).
_UNTRIPPABLE = SafetyLimits(max_force_n=1e9, max_torque_nm=1e9, max_lateral_force_n=1e9,
                            max_force_rate_n_s=1e12, ft_stale_ms=1e9, ft_frozen_ms=1e9, slip_mm=1e9)

# Samples the F/T source may keep queued beyond what the server asks for: the world and the
# server pace on the same wall clock, so a longer queue would only be a constant lag (a lag
# in the force loop of the controller, which made it oscillate).
_FT_QUEUE_MAX = 2


def untrippable_params(params: SimCellParams) -> SimCellParams:
    """The cell's parameters with the world's ATI guard disabled and no scheduled faults."""
    return replace(params, limits=_UNTRIPPABLE, faults=[])


class WorldBackend:
    """ArmBackend over a :class:`SimCell`'s arm, advanced in wall time.

    ``cell``: the simulated cell (built with :func:`untrippable_params`). ``t0_wall_s``: the
    wall time (monotonic, s) at which the world's virtual time is ``cell.clock.now_s()``.
    """

    def __init__(self, cell: SimCell, t0_wall_s: float | None = None, counts_per_force: int = 1_000_000,
                 counts_per_torque: int = 1_000_000) -> None:
        self.cell = cell
        self.world = cell.world
        self.arm = cell.arm
        self.lock = threading.RLock()
        now = time.monotonic() if t0_wall_s is None else float(t0_wall_s)
        self._offset_s = now - cell.clock.now_s()          # wall = virtual + offset
        self.counts_per_force = int(counts_per_force)
        self.counts_per_torque = int(counts_per_torque)
        self._ft_queue = np.zeros((0, 6))
        self._last_ft = np.zeros(6)
        self._last_status = 0
        self._pstop_reason: str | None = None
        self._prev_pose: tuple[float, np.ndarray] | None = None
        self._velocity = np.zeros(6)
        self.force_mode_active = False
        self.ft_zeroed_count = 0
        self.commands: list[tuple[str, float]] = []

    # ------------------------------------------------------------------ time
    def _virtual_s(self, wall_s: float) -> float:
        return wall_s - self._offset_s

    def _advance_locked(self, wall_s: float) -> None:
        target = self._virtual_s(wall_s)
        dt = target - self.cell.clock.now_s()
        if dt > 0:
            self.cell.clock.sleep_s(dt)
        self._pull_ft()
        self._note_velocity()
        arm = self.arm
        if arm._protective_since_us is not None and self._pstop_reason is None:
            self._pstop_reason = "simulated arm: protective stop (UR force limit or path out of range)"

    def advance(self, t_s: float) -> None:
        with self.lock:
            self._advance_locked(float(t_s))

    def _note_velocity(self) -> None:
        pose = self.arm._sim_tcp_pose()
        t = self.world.now_s()
        if self._prev_pose is not None and t > self._prev_pose[0]:
            dt = t - self._prev_pose[0]
            self._velocity[:3] = (pose.position_mm - self._prev_pose[1]) / dt * 1e-3
        self._prev_pose = (t, pose.position_mm.copy())

    # ------------------------------------------------------------------ ArmBackend: commands
    def move_linear(self, pose_ur: np.ndarray, speed_m_s: float, accel_m_s2: float) -> None:
        with self.lock:
            self.commands.append(("move_linear", time.monotonic()))
            try:
                self.arm.move_linear(Pose.from_ur(np.asarray(pose_ur, float)), float(speed_m_s) * 1e3,
                                     float(accel_m_s2) * 1e3)
            except MotionRefused as exc:
                self._pstop_reason = f"moveL refused: {exc}"

    def move_joint(self, q_rad: np.ndarray, speed_rad_s: float, accel_rad_s2: float) -> None:
        raise NotImplementedError("moveJ is not emulated on the simulated world (the controller uses moveL)")

    def speed_linear(self, xd: np.ndarray, accel_m_s2: float) -> None:
        """speedL: the simulated arm's primitive (``SimArm.speed_linear``: successive commands
        along one line change the speed on it, a new direction starts a new line). Rotational
        speeds are ignored (the controller never sends them)."""
        with self.lock:
            v = np.asarray(xd, float)[:3] * 1e3
            if self.arm._speed_line is None and float(np.linalg.norm(v)) > 1e-9:
                self.commands.append(("speed_linear", time.monotonic()))
            self.arm.speed_linear(v, max(float(accel_m_s2) * 1e3, 1.0))

    def stop(self, decel_m_s2: float) -> None:
        with self.lock:
            self.commands.append(("stop", time.monotonic()))
            self.arm.stop(max(float(decel_m_s2) * 1e3, 1.0))

    def set_force_mode(self, active: bool, task_frame_ur: np.ndarray | None = None,
                       selection: np.ndarray | None = None, wrench: np.ndarray | None = None,
                       limits: np.ndarray | None = None) -> None:
        # The controller regulates force with speedL on the ATI reading; UR force mode is
        # only recorded (a real arm would use its own, less precise, joint-torque estimate).
        with self.lock:
            if bool(active) != self.force_mode_active:
                self.commands.append(("force_mode" if active else "force_mode_stop", time.monotonic()))
            self.force_mode_active = bool(active)

    def zero_ft_sensor(self) -> None:
        with self.lock:
            self.ft_zeroed_count += 1

    # ------------------------------------------------------------------ ArmBackend: state
    def tcp_pose_ur(self) -> np.ndarray:
        with self.lock:
            return np.asarray(self.arm._sim_tcp_pose().to_ur(), float)

    def tool_ur(self) -> np.ndarray:
        """The simulated arm's TCP in the flange frame: the one its kinematic model (and so every
        pose of this backend) uses — the cell file's, where the served world's true tool is
        expressed."""
        return np.asarray(self.cell._model.flange_to_tcp.to_ur(), float)

    def grid_ur(self) -> tuple[float, float]:
        """(period (s), a wall time (monotonic s) on the grid): the world's state changes only at
        wall times anchor + k * period (its control grid)."""
        return self.world.control_period_us / US_PER_S, self._offset_s

    def pose_sample_ur(self) -> tuple[float, np.ndarray]:
        """(wall time (monotonic s) of the world state, the TCP pose (ur units) in it), read together.

        The world moves on its control grid (2 ms): a pose read at wall time t shows the arm
        at the grid instant at or before t, and other threads (the F/T and scanner servers)
        may advance the world between two reads; the pose and its instant must be one read."""
        with self.lock:
            return self.world.now_s() + self._offset_s, np.asarray(self.arm._sim_tcp_pose().to_ur(), float)

    def tcp_speed_ur(self) -> np.ndarray:
        with self.lock:
            return self._velocity.copy()

    def joints_rad(self) -> np.ndarray:
        with self.lock:
            return np.asarray(self.arm._path.joints(self.arm._u), float)

    def tcp_force_ur(self) -> np.ndarray:
        """The true contact force on the tool (N, base frame); torques 0 (UR's estimate is coarse)."""
        with self.lock:
            c = self.world.contact
            out = np.zeros(6)
            if c is not None:
                out[:3] = -np.asarray(c.d_base, float) * float(c.force_n)
            return out

    def is_moving(self) -> bool:
        with self.lock:
            arm = self.arm
            kind = arm._law.kind
            if kind in ("trapezoid", "stop"):
                return True
            if kind == "ramp":
                return abs(arm._du) > 1e-9 or abs(arm._law.v1) > 1e-9
            return False

    def protective_stop_requested(self) -> str | None:
        """Reported once; the emulator owns the protective stop from then on (its dashboard
        unlocks it), so the simulated arm's own stop state is cleared here."""
        with self.lock:
            reason, self._pstop_reason = self._pstop_reason, None
            if reason is not None:
                arm = self.arm
                arm._halt(self.world.now_us, arm._settings.halt_decel_mm_s2)
                arm._protective_since_us = None
                arm._program_running = True
                arm._speed_line = None
            return reason

    # ------------------------------------------------------------------ the F/T source
    def _pull_ft(self) -> None:
        block = self.cell.ft.read_block()
        if not len(block):
            return
        rows = np.concatenate([block.force_n, block.torque_nm], axis=1)
        self._last_status = int(block.status[-1])
        self._ft_queue = np.concatenate([self._ft_queue, rows])[-4096:]

    def ft_source(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """``n`` samples for the Net F/T server: (counts (n, 6) int64, status (n,) uint32).

        The world is brought up to now (and at most ``n`` ms beyond, when the server's own
        pacing runs ahead of it); a backlog beyond ``_FT_QUEUE_MAX`` samples is dropped
        from the old end so the stream never lags the world."""
        with self.lock:
            self._advance_locked(time.monotonic())
            short = n - self._ft_queue.shape[0]
            if short > 0:
                self.cell.clock.sleep_s(short * self.world.sample_period_us / US_PER_S)
                self._pull_ft()
            q = self._ft_queue
            if q.shape[0] > n + _FT_QUEUE_MAX:
                q = q[-(n + _FT_QUEUE_MAX):]
            take, self._ft_queue = q[:n], q[n:]
            if take.shape[0] < n:        # a stalled world stream: repeat the last reading
                last = take[-1] if take.shape[0] else self._last_ft
                take = np.vstack([take, np.repeat(last[None, :], n - take.shape[0], axis=0)])
            self._last_ft = take[-1].copy()
            scale = np.array([self.counts_per_force] * 3 + [self.counts_per_torque] * 3, dtype=float)
            counts = np.rint(take * scale).astype(np.int64)
            return counts, np.full(n, self._last_status, dtype=np.uint32)

    # ------------------------------------------------------------------ the scanner source
    def profile_xz(self, device_t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The simulated scanner's fan (x, z) (mm, scanner frame, NaN missing) at the arm's pose now."""
        x, z, _ = self.profile_xz_at(device_t_s)
        return x, z

    def profile_xz_at(self, device_t_s: float) -> tuple[np.ndarray, np.ndarray, float]:
        """The fan (x, z) and the wall time (monotonic s; the served scanner's device clock is
        the wall clock) of the world state it shows.

        The world only has a present: a frame due at ``device_t_s`` that is rendered late
        (a busy scanner thread, the world lock held by the controller tick) shows the arm
        where it is when rendered, so that instant is its true exposure time.
        """
        with self.lock:
            self._advance_locked(max(device_t_s, time.monotonic()))
            snap = self.world.snapshot_now()
            x, z = self.cell.scanner.profile(snap, noise=True)
            # The instant of the world state shown (on the control grid), not the clock's:
            # the clock may be up to a control period past it.
            return x, z, snap.t_us / US_PER_S + self._offset_s

    def profile_source(self, x_grid_mm: np.ndarray):
        """A ``ProfileSource`` for ScannerPtyServer: (z (mm) on the server's fixed ``x_grid_mm``,
        the true exposure time) — see :meth:`profile_xz_at`."""
        grid = np.asarray(x_grid_mm, float)

        def source(frame_counter: int, device_t_s: float) -> tuple[np.ndarray, float]:
            x, z, wall_s = self.profile_xz_at(device_t_s)
            return resample_profile(x, z, grid), wall_s

        return source

    def native_profile_source(self):
        """A ``ProfileSource`` giving the world scanner's own samples (x, z) and the true
        exposure time: the served frames carry explicit x, so the controller receives the
        very points the in-process scanner gives (no resampling onto a fixed grid, which
        halved the points on the object and interpolated across silhouettes)."""

        def source(frame_counter: int, device_t_s: float) -> tuple[np.ndarray, np.ndarray, float]:
            return self.profile_xz_at(device_t_s)

        return source

    @property
    def scanner_samples(self) -> int:
        """Samples per profile of the world's scanner."""
        return int(self.cell.scanner.samples_per_profile)

    # ------------------------------------------------------------------ test hooks
    def inject(self, kind: str, **kwargs: float) -> None:
        """Inject a world fault now (e.g. ``force_spike`` with magnitude, duration_s)."""
        with self.lock:
            self._advance_locked(time.monotonic())
            self.cell.faults.inject(kind, **kwargs)


def resample_profile(x_mm: np.ndarray, z_mm: np.ndarray, grid_mm: np.ndarray, max_gap_factor: float = 2.5) -> np.ndarray:
    """z on ``grid_mm`` by linear interpolation between neighbouring valid fan samples.

    A grid point is missing (NaN) when it falls outside the valid samples or between two
    valid samples farther apart than ``max_gap_factor`` x the median spacing (a hole: a
    shadow, a dropout or an edge must stay a hole, not become a bridge)."""
    ok = np.isfinite(x_mm) & np.isfinite(z_mm)
    out = np.full(grid_mm.shape, np.nan)
    if ok.sum() < 2:
        return out
    xs, zs = x_mm[ok], z_mm[ok]
    order = np.argsort(xs)
    xs, zs = xs[order], zs[order]
    gaps = np.diff(xs)
    typical = float(np.median(gaps))
    j = np.searchsorted(xs, grid_mm)
    inside = (j > 0) & (j < xs.size)
    jj = np.clip(j, 1, xs.size - 1)
    span = xs[jj] - xs[jj - 1]
    inside &= span <= max_gap_factor * max(typical, 1e-9)
    f = np.where(span > 0, (grid_mm - xs[jj - 1]) / np.where(span > 0, span, 1.0), 0.0)
    z = zs[jj - 1] + f * (zs[jj] - zs[jj - 1])
    out[inside] = z[inside]
    return out
