"""The simulated cell's world: single-threaded, event-driven, in virtual time (docs/design.md §8).

:class:`SimWorld` is a listener of :class:`~elastoprobe.controller.core.clock.VirtualClock`.
When the controller sleeps, ``advance_to(t)`` integrates the arm, the contact, the
F/T stream, the scanner and the safety path up to ``t`` — nothing sleeps, no threads.

Time: an integer grid of microseconds. The arm's control period is 2 ms (UR's
500 Hz); the F/T sensor samples every 1 ms; world time only takes values on the
1 ms sample grid and ``advance_to`` stops on the 2 ms control grid, so float
accumulation in the clock never shifts the grid between runs.

Each ``advance_to`` is cut into sub-chunks (at most ``max_chunk_us``; the force loop
and scheduled faults cut them too). A sub-chunk is first computed "dry" as pure
functions of the state at its start (trajectory, contact force, F/T samples); then
the first event in it (contact begins or ends, the seek threshold, the UR's own
force limit, slip) shortens it; then the F/T block is checked by the controller's
:class:`~elastoprobe.controller.core.safety.SafetyGuard` — the same vectorised function a
real driver runs where the data arrives — and on a crossing the arm is stopped at
the crossing sample's virtual time; then the state is committed.

Batched holds: while the arm only holds a regulated force on the object (the
controller polls every 100 ms then, ProbeSettings.hold_poll_period_s), one sleep of
P force-loop periods is one scalar recurrence over the P loop updates plus one block
of samples (:meth:`SimWorld._hold_span`); a span in which anything could end the hold
(guard screen, contact end, UR force limit, slip, path range, a fault) is redone
sub-chunk by sub-chunk from its start, so it stops at the same sample.

Randomness: every draw comes from a generator keyed by (seed, step, attempt,
stream) (:func:`keyed_rng`); ``begin_step`` re-seeds all of them, and slowly varying
random processes (F/T drift) restart at the begin_step instant, so the same commands
after the same ``begin_step`` from the same state give the same bytes, whatever the
absolute virtual time.

Contact (docs/design.md §3, §8): the tip is a sphere of radius R at the TCP. It touches
when the tip centre comes within R of the object (``closest_surface``) or of the
table plane z = 0 (object frame). At first touch the world records the contact point
p and normal n and derives the physical approach from the push direction
d = tool +z alone: t = the tangential part of d, normalised (a = 90: the tool x axis
projected on the tangent plane), a = asin(-d . n) in (0, 90] — a push at a with t is
the same physics as 180 - a with -t. One ContactModel per contact; push = (tip -
tip at touch) . d; |F| = force at push with creep; the reaction on the tool is
-|F| d. Creep is a state c in (1 - beta, 1] (the fraction of equilibrium indentation
reached): it relaxes toward 1 with the material's time constant while loaded, and new
loading enters un-crept (weighted by the push it adds), so "hold time" counts from
when the load last rose, without a hard reset at every jitter of the force loop.
"""
from __future__ import annotations

import enum
import math
from bisect import bisect_right
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Callable

import numpy as np

from elastoprobe.controller.core.clock import VirtualClock
from elastoprobe.controller.core.devices import Trip, WrenchBlock
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.core.safety import SafetyGuard, SafetyLimits

if TYPE_CHECKING:   # pragma: no cover
    from .arm import SimArm
    from .faults import FaultInjector
    from .ft import SimForceTorque
    from .scanner import SimLineScanner

US_PER_S = 1_000_000

# Before the first begin_step (and for per-seed constants) the step key is "outside any step".
PRE_STEP = 2**32 - 1


class Stream(enum.IntEnum):
    """Ids of the independent random streams (the fourth element of every key)."""

    FT_NOISE = 1
    FT_DRIFT = 2
    SCAN_NOISE = 3
    SCAN_DROPOUT = 4
    SCAN_CORRELATED = 5
    FAULTS = 6
    CONSTANTS = 7        # per-seed constants (F/T bias, miscalibration): key (seed, PRE_STEP, 0)


def keyed_rng(seed: int, step: int, attempt: int, stream: int) -> np.random.Generator:
    """A generator determined by (seed, step, attempt, stream) alone."""
    key = [int(seed) & 0xFFFFFFFF, int(step) & 0xFFFFFFFF, int(attempt) & 0xFFFFFFFF, int(stream)]
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(key)))


class PagedNormal:
    """Standard-normal rows addressed by index (0 = the first draw since ``reset``).

    Rows are drawn in fixed pages, in order, so ``take(i, n)`` returns the same numbers
    however indices are grouped into calls. Old pages are dropped; re-reading the
    current or the two previous pages is allowed (a sub-chunk cut short is re-synthesised).
    """

    def __init__(self, width: int, page_rows: int = 1024) -> None:
        self.width = int(width)
        self.page_rows = int(page_rows)
        self._rng: np.random.Generator | None = None
        self._pages: dict[int, np.ndarray] = {}
        self._next_page = 0

    def reset(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self._pages.clear()
        self._next_page = 0

    def _page(self, k: int) -> np.ndarray:
        page = self._pages.get(k)
        if page is not None:
            return page
        if self._rng is None:
            raise RuntimeError("PagedNormal used before reset()")
        if k < self._next_page:
            raise RuntimeError(f"page {k} was dropped; indices must move forward")
        while self._next_page <= k:
            self._pages[self._next_page] = self._rng.standard_normal((self.page_rows, self.width))
            self._next_page += 1
        for old in [p for p in self._pages if p < k - 2]:
            del self._pages[old]
        return self._pages[k]

    def take(self, first: int, count: int) -> np.ndarray:
        """Rows ``first .. first + count - 1`` as a (count, width) array."""
        if count <= 0:
            return np.zeros((0, self.width))
        p0, o0 = divmod(int(first), self.page_rows)
        p1, o1 = divmod(int(first) + int(count) - 1, self.page_rows)
        if p0 == p1:
            return self._page(p0)[o0:o1 + 1]
        parts = [self._page(p0)[o0:]]
        parts.extend(self._page(k) for k in range(p0 + 1, p1))
        parts.append(self._page(p1)[:o1 + 1])
        return np.concatenate(parts)


# ------------------------------------------------------------------------------ contact

# Force/push table of one contact: equilibrium |F| (N) against equilibrium push (mm).
_FORCE_GRID_N = np.concatenate([[0.0], np.geomspace(1e-3, 600.0, 320)])
_ONES = np.ones(4096)
_ONES.setflags(write=False)
_FORCE_GRID_LIST = _FORCE_GRID_N.tolist()
_FORCE_END_SLOPE = (_FORCE_GRID_LIST[-1] - _FORCE_GRID_LIST[-2])
_SHIFT_FORCE_N = np.concatenate([[0.0], np.geomspace(1e-3, 600.0, 48)])


def _force_at(eq_push_mm: float, push_grid: list[float]) -> float:
    """|F| (N) at one equilibrium push (mm) on a contact's force table (scalar Contact.forces_n)."""
    if eq_push_mm >= push_grid[-1]:
        return _FORCE_GRID_LIST[-1] + (eq_push_mm - push_grid[-1]) * _FORCE_END_SLOPE / (push_grid[-1] - push_grid[-2])
    j = bisect_right(push_grid, eq_push_mm) - 1
    return _FORCE_GRID_LIST[j] + (eq_push_mm - push_grid[j]) * (
        (_FORCE_GRID_LIST[j + 1] - _FORCE_GRID_LIST[j]) / (push_grid[j + 1] - push_grid[j]))
TABLE_STIFFNESS_N_MM = 400.0     # the table is rigid next to any probed material
MIN_APPROACH_DEG = 2.0           # a grazing touch is treated as this shallow a push


@dataclass
class Contact:
    """One contact, from first touch until the push returns to zero (all of it is world state).

    ``model`` is None for the table. Object-frame geometry: ``point_obj`` p, ``normal_obj``
    n, ``t_obj`` the physical scan direction, ``angle_deg`` the physical approach angle.
    Base frame: ``d_base`` the push direction, ``tip_touch_base`` the tip centre at first touch.
    """

    model: object | None
    point_obj: np.ndarray
    normal_obj: np.ndarray
    t_obj: np.ndarray
    angle_deg: float
    d_base: np.ndarray
    tip_touch_base: np.ndarray
    started_us: int
    push_grid_mm: np.ndarray | None = None      # equilibrium push at _FORCE_GRID_N
    creep_beta: float = 0.0
    creep_tau_s: float = 1.0
    creep_c: float = 1.0
    push_max_mm: float = 0.0
    push_mm: float = 0.0
    force_n: float = 0.0
    max_force_n: float = 0.0
    slip_extra_mm: float = 0.0                 # injected slip (fault), mm along t
    shift_grid_mm: np.ndarray | None = None    # tip shift along t at _SHIFT_FORCE_N
    sliding: bool = False                      # Q > mu P at this angle: the tip slides (gross slip)

    def slip_mm(self, force_n: float) -> float:
        """How far the tip has slid along the surface (mm): the tip shift once in gross slip."""
        if not self.sliding or self.shift_grid_mm is None:
            return 0.0
        return abs(float(np.interp(force_n, _SHIFT_FORCE_N, self.shift_grid_mm)))

    def hold_s(self) -> float:
        """The hold time equivalent to the creep state (for the model's creep law)."""
        return self.hold_s_at(self.creep_c)

    def hold_s_at(self, creep_c: float) -> float:
        """The hold time (s) equivalent to creep state ``creep_c``."""
        if self.creep_beta <= 0.0 or creep_c >= 1.0:
            return math.inf
        return -self.creep_tau_s * math.log(max((1.0 - creep_c) / self.creep_beta, 1e-300))

    def forces_n(self, push_mm: np.ndarray, creep_c: np.ndarray) -> np.ndarray:
        """|F| at pushes (mm) with creep states c (vectorised)."""
        if self.model is None:
            return TABLE_STIFFNESS_N_MM * np.maximum(push_mm, 0.0)
        eq = np.maximum(push_mm, 0.0) / creep_c
        grid = self.push_grid_mm
        f = np.interp(eq, grid, _FORCE_GRID_N)      # 0 at push <= 0 (the grid starts at 0 N, 0 mm)
        if float(eq.max()) > grid[-1]:
            slope = (_FORCE_GRID_N[-1] - _FORCE_GRID_N[-2]) / (grid[-1] - grid[-2])
            f = np.where(eq > grid[-1], _FORCE_GRID_N[-1] + (eq - grid[-1]) * slope, f)
        return f

    def creep_after(self, c0: float, push0_mm: float, push1_mm: float, dt_s: float,
                    push_max_mm: float | None = None) -> float:
        """Creep state after ``dt_s`` in which the push went from push0 to push1 (mm);
        ``push_max_mm`` is the deepest push so far (default: this contact's)."""
        if self.creep_beta <= 0.0:
            return 1.0
        push_max = self.push_max_mm if push_max_mm is None else push_max_mm
        c = 1.0 - (1.0 - c0) * math.exp(-dt_s / self.creep_tau_s) if push0_mm > 0.0 else c0
        if push1_mm > push_max and push1_mm > 0.0:
            # New loading enters un-crept: blend by the equilibrium push it adds.
            old = max(push_max, 0.0)
            fresh = 1.0 - self.creep_beta
            c = (c * old + fresh * (push1_mm - old)) / push1_mm
        return min(max(c, 1.0 - self.creep_beta), 1.0)


def make_contact(obj, point_obj: np.ndarray, normal_obj: np.ndarray, d_obj: np.ndarray, tool_x_obj: np.ndarray,
                 d_base: np.ndarray, tip_touch_base: np.ndarray, tip_radius_mm: float, started_us: int,
                 table: bool) -> Contact:
    """The contact at first touch: physical t and angle from the push direction alone."""
    n = normal_obj / np.linalg.norm(normal_obj)
    d = d_obj / np.linalg.norm(d_obj)
    tangential = d - float(d @ n) * n
    if np.linalg.norm(tangential) < 1e-6:
        tangential = tool_x_obj - float(tool_x_obj @ n) * n
        if np.linalg.norm(tangential) < 1e-9:
            tangential = np.cross(n, [0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.cross(n, [1.0, 0.0, 0.0])
    t = tangential / np.linalg.norm(tangential)
    angle_deg = math.degrees(math.asin(min(1.0, max(-1.0, -float(d @ n)))))
    angle_deg = min(90.0, max(MIN_APPROACH_DEG, angle_deg))
    contact = Contact(model=None, point_obj=np.asarray(point_obj, float), normal_obj=n, t_obj=t,
                      angle_deg=angle_deg, d_base=np.asarray(d_base, float), tip_touch_base=np.asarray(tip_touch_base, float),
                      started_us=started_us)
    if table:
        return contact
    model = obj.contact_model(contact.point_obj, n, t, angle_deg, tip_radius_mm)
    contact.model = model
    contact.push_grid_mm = _push_table(model)
    contact.shift_grid_mm = np.array([model.tip_shift_mm(float(f)) for f in _SHIFT_FORCE_N])
    contact.sliding = model.slip_margin(5.0) > 1.0
    # Creep law c(h) = 1 - beta exp(-h / tau), read back through the public API.
    f_ref = 5.0
    eq = model.push_mm_at_force(f_ref, math.inf)
    if eq > 0:
        beta = 1.0 - model.push_mm_at_force(f_ref, 0.0) / eq
        if beta > 1e-9:
            tau_probe_s = 1.0
            c1 = model.push_mm_at_force(f_ref, tau_probe_s) / eq
            ratio = (1.0 - c1) / beta
            contact.creep_beta = beta
            contact.creep_tau_s = -tau_probe_s / math.log(ratio) if 0.0 < ratio < 1.0 else 1.0
            contact.creep_c = 1.0 - beta
    return contact


def _push_table(model) -> np.ndarray:
    """Equilibrium push (mm) at each force of _FORCE_GRID_N, strictly increasing for np.interp."""
    push = np.array([model.push_mm_at_force(float(f), math.inf) for f in _FORCE_GRID_N])
    push = np.maximum.accumulate(push) + np.arange(push.size) * 1e-12
    return push


# ------------------------------------------------------------------------------ the world

@dataclass
class ArmPlan:
    """The arm's dry trajectory over a sub-chunk: TCP positions (n,3) mm, rotations (3,3) or (n,3,3),
    the path rate du/dt (n,) and the path's mm per unit u."""

    position_mm: np.ndarray
    rotation: np.ndarray
    du: np.ndarray
    speed_scale: float = 1.0

    @property
    def speed_mm_s(self) -> np.ndarray:
        """TCP speed (n,) mm/s (computed on demand: the stepping itself never needs it)."""
        return np.abs(self.du) * self.speed_scale


@dataclass
class WorldSnapshot:
    """What the scanner needs at an exposure instant (true state, never shown to the controller)."""

    t_us: int
    tcp_pose: Pose
    base_to_object: Pose
    contact: Contact | None
    force_n: float
    hold_s: float


@dataclass
class _Dry:
    """One sub-chunk computed before commit."""

    ts_us: np.ndarray
    plan: ArmPlan
    tips_base: np.ndarray
    force_base: np.ndarray           # (n,3) force ON the tool from the contact (base frame)
    force_mag_n: np.ndarray
    push_mm: np.ndarray
    creep_c: np.ndarray
    slip_mm: np.ndarray
    contact_ends_at: int | None = None
    slip_const_mm: float | None = None     # slip_mm is this value at every sample (no slip fault)


@dataclass
class Press:
    """A finished contact, for permanent dents (object frame)."""

    point_obj: np.ndarray
    normal_obj: np.ndarray
    max_force_n: float


class SimWorld:
    """Virtual-time world: owns time, the object placement, the contact and the safety guard.

    Devices (:class:`~elastoprobe.sim.arm.SimArm`, :class:`~elastoprobe.sim.ft.SimForceTorque`,
    :class:`~elastoprobe.sim.scanner.SimLineScanner`) and the
    :class:`~elastoprobe.sim.faults.FaultInjector` are attached by the cell.
    """

    def __init__(self, clock: VirtualClock, obj, base_to_object: Pose, tip_radius_mm: float, seed: int,
                 limits: SafetyLimits, probe_axis_sensor: np.ndarray = np.array([0.0, 0.0, 1.0]),
                 control_period_us: int = 2000, sample_period_us: int = 1000, max_chunk_us: int = 10_000,
                 tip_offset_tcp_mm: np.ndarray | None = None, ur_force_limit_n: float = 150.0,
                 guard_batch_us: int = 200_000) -> None:
        if control_period_us % sample_period_us:
            raise ValueError("the control period must be a whole number of F/T sample periods")
        self.clock = clock
        self.obj = obj
        self.base_to_object_nominal = base_to_object
        self.base_to_object = base_to_object
        self.tip_radius_mm = float(tip_radius_mm)
        self.seed = int(seed)
        self.control_period_us = int(control_period_us)
        self.sample_period_us = int(sample_period_us)
        self.max_chunk_us = int(max_chunk_us)
        # The true tip centre in the TCP frame (0 unless the cell is miscalibrated).
        self.tip_offset_tcp_mm = np.zeros(3) if tip_offset_tcp_mm is None else np.asarray(tip_offset_tcp_mm, float)
        self.ur_force_limit_n = float(ur_force_limit_n)
        self._tip_offset_zero = not self.tip_offset_tcp_mm.any()
        self.limits = limits
        self.guard = SafetyGuard(limits, probe_axis_sensor, rate_hz=US_PER_S / sample_period_us)
        # The guard sees every sample. Blocks that a conservative screen proves cannot cross
        # any limit are handed to it in batches of up to guard_batch_us (0: every sub-chunk);
        # any block the screen cannot clear is checked at once, so a crossing still stops
        # the arm at its sample's instant. 200 ms: holding and scanning, nearly every block
        # is cleared, and one check_block over 200 samples costs little more than over 50;
        # everything that reads the guard's state (rearm, tare, a trip) flushes it first.
        self.guard_batch_us = int(guard_batch_us)
        # Pending screened samples: (ts_us, seq, out (n,6), status) slices, made into one
        # WrenchBlock at the flush (one division and one concatenation per batch).
        self._guard_pending: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self._guard_pending_n = 0
        self._rate_window = max(1, int(round(limits.rate_window_ms * 1e-3 * US_PER_S / sample_period_us)))
        self._screen_prev = (0.0, 0.0)
        self._screen_count = 0
        self._screen_force_limit = min(limits.max_force_n, limits.max_lateral_force_n)
        self._screen_torque2 = (0.98 * limits.max_torque_nm) ** 2
        self._screen_noiseless = False
        self.now_us = self._grid_floor(self._to_us(clock.now_s()), self.control_period_us)
        self.step_key: tuple[int, int, int] = (self.seed, PRE_STEP, 0)
        self.step_start_us = self.now_us
        self.contact: Contact | None = None
        self.presses: list[Press] = []
        self.trip: Trip | None = None
        self._latched_force_n = 0.0
        self._latched_us = 0
        self._obj_bounds = np.asarray(obj.mesh.bounds, dtype=float) if obj is not None else None
        # Clearance bookkeeping: the tip is free anywhere within _free_radius of _free_centre.
        self._free_centre: np.ndarray | None = None
        self._free_radius = 0.0
        self._listeners_step: list[Callable[[tuple[int, int, int]], None]] = []
        self.arm: SimArm | None = None
        self.ft: SimForceTorque | None = None
        self.scanner: SimLineScanner | None = None
        self.faults: FaultInjector | None = None
        self._advancing = False
        # Batched holds (_hold_span): whole force-loop periods of one sleep in one block while
        # the arm only holds a regulated force (False: every period is its own sub-chunk).
        self.hold_batching = True
        self.stats = {"subchunks": 0, "distance_queries": 0, "guard_blocks": 0, "hold_spans": 0,
                      "hold_periods": 0, "hold_fallbacks": 0}
        clock.add_listener(self.advance_to)

    # ------------------------------------------------------------------ wiring, keys
    def attach(self, arm: SimArm, ft: SimForceTorque, scanner: SimLineScanner, faults: FaultInjector) -> None:
        self.arm, self.ft, self.scanner, self.faults = arm, ft, scanner, faults
        self._screen_noiseless = ft._sim_noiseless()
        self.begin_step(self.step_key)

    def rng(self, stream: Stream) -> np.random.Generator:
        """A fresh generator for ``stream`` under the current step key."""
        seed, step, attempt = self.step_key
        return keyed_rng(seed, step, attempt, int(stream))

    def constants_rng(self) -> np.random.Generator:
        """Per-seed constants (bias, miscalibration): independent of steps."""
        return keyed_rng(self.seed, PRE_STEP, 0, int(Stream.CONSTANTS))

    def begin_step(self, step_key: tuple[int, int, int]) -> None:
        """Re-seed every random stream from (seed, step, attempt); drift restarts now."""
        self.step_key = (int(step_key[0]), int(step_key[1]), int(step_key[2]))
        self.step_start_us = self.now_us
        for device in (self.ft, self.scanner, self.faults):
            if device is not None:
                device._sim_begin_step()

    # ------------------------------------------------------------------ time
    @staticmethod
    def _to_us(t_s: float) -> int:
        return int(round(t_s * US_PER_S))

    @staticmethod
    def _grid_floor(t_us: int, period_us: int) -> int:
        return t_us - t_us % period_us

    def now_s(self) -> float:
        return self.now_us / US_PER_S

    def advance_to(self, t_s: float) -> None:
        """Integrate everything up to ``t_s`` (floored onto the control grid)."""
        target = self._grid_floor(self._to_us(t_s), self.control_period_us)
        if self._advancing:
            raise RuntimeError("SimWorld.advance_to re-entered")
        self._advancing = True
        try:
            guard_loops = 0
            batch = self.hold_batching
            while self.now_us < target:
                if batch and self.contact is not None and self.arm._sim_hold_ready(self.now_us):
                    done = self._hold_span(target)
                    if done is None:
                        batch = False          # the span needs sub-chunks: do not retry in this call
                    elif done:
                        continue
                end = min(target, self.now_us + self.max_chunk_us)
                end = self.arm._sim_bound_end(self.now_us, end)
                end = self.faults._sim_bound_end(self.now_us, end)
                if end <= self.now_us:
                    end = self.now_us + self.sample_period_us
                self._run(end)
                guard_loops += 1
                if guard_loops > 10_000_000:   # bounded: ~ 3 h of virtual time per call
                    raise RuntimeError("SimWorld.advance_to did not converge")
        finally:
            self._advancing = False

    # ------------------------------------------------------------------ one sub-chunk
    def _run(self, end_us: int) -> None:
        self.stats["subchunks"] += 1
        self.faults._sim_on_time(self.now_us)
        sp = self.sample_period_us
        ts = np.arange(self.now_us + sp, end_us + 1, sp, dtype=np.int64)
        if ts.size == 0:
            return
        plan = self.arm._sim_plan(ts)
        rot = plan.rotation
        offset = self.tip_offset_tcp_mm
        if self._tip_offset_zero:
            tips = plan.position_mm
        elif rot.ndim == 2:
            tips = plan.position_mm + (rot @ offset)
        else:
            tips = plan.position_mm + np.einsum("nij,j->ni", rot, offset)
        n = ts.size
        if self.contact is None:
            k = self._first_touch(tips, plan)
            if k is not None:
                if k > 0:
                    n = k          # commit the free samples; contact begins in the next sub-chunk
                else:
                    self._begin_contact(tips, plan, ts)
        dry = self._dry(ts[:n], plan, tips[:n], n)
        cut = dry.ts_us.size
        if dry.contact_ends_at is not None:
            cut = min(cut, dry.contact_ends_at + 1)
        # The F/T stream as the sensor delivers it (tared, with faults), then the arm's own events.
        samples = self.ft._sim_synthesize(dry.ts_us[:cut], dry.force_base[:cut], self._rotations(dry.plan, cut),
                                          self.now_us)
        event = None
        arm_event = self.arm._sim_event(dry.ts_us[:cut], samples)
        if arm_event is not None and arm_event < cut:
            cut, event = arm_event + 1, "arm"
        slip_trip_at = None
        fmax_cut = (cut, float(dry.force_mag_n[:cut].max())) if self.contact is not None else None
        if self.contact is not None:
            if fmax_cut[1] > self.ur_force_limit_n:
                over = np.flatnonzero(dry.force_mag_n[:cut] > self.ur_force_limit_n)
                cut, event = int(over[0]) + 1, "ur_force"
            slip_max = dry.slip_const_mm if dry.slip_const_mm is not None else float(dry.slip_mm[:cut].max())
            if slip_max > self.limits.slip_mm:
                slipping = np.flatnonzero(dry.slip_mm[:cut] > self.limits.slip_mm)
                slip_trip_at = int(slipping[0])
                cut, event = slip_trip_at + 1, "slip"
        # The check-and-stop path on the block as it arrives.
        trip = None
        if samples.all_delivered or samples.delivered[:cut].any():
            trip = self._guard_check(samples, cut)
            if trip is not None:
                i = int(np.searchsorted(dry.ts_us[:cut], self._to_us(trip.t_s)))
                cut, event = max(1, min(cut, i + 1)), "trip"
        else:
            self.guard_flush()
            trip = self.guard.check_stale(dry.ts_us[cut - 1] / US_PER_S)
            if trip is not None:
                event = "trip"
        if event == "slip" and trip is None:
            trip = self.guard.check_slip(float(dry.slip_mm[slip_trip_at]), float(dry.ts_us[slip_trip_at]) / US_PER_S)
        self.ft._sim_commit(samples, cut)
        self.arm._sim_seek_samples(samples, cut)
        self._commit(dry, cut, fmax_cut[1] if fmax_cut is not None and fmax_cut[0] == cut else None)
        if trip is not None and self.trip is None:
            self.trip = _trip_truncated(trip, self.guard)
            self._latched_force_n = max(float(trip.value) if trip.kind == "force" else 0.0,
                                        float(np.max(samples.fmag[:cut])) if samples.fmag is not None else 0.0)
            self._latched_us = self.now_us
            self.arm._sim_halt(self.now_us, "tripped")
        elif trip is not None and self._halts_recovery(trip, samples, cut):
            self.arm._sim_halt(self.now_us, "tripped")
        elif event == "ur_force":
            self.arm._sim_protective_stop(self.now_us, f"UR force limit: |F| {dry.force_mag_n[cut - 1]:.0f} N")
        elif event == "arm":
            self.arm._sim_on_event(self.now_us)

    # ------------------------------------------------------------------ batched holds
    def _hold_span(self, target_us: int) -> bool | None:
        """Run whole force-loop periods of a regulated hold up to ``target_us`` in one batch.

        While the arm only holds a force (:meth:`SimArm._sim_hold_ready`), on an object
        contact, with no fault active or starting in the span, a sleep of P loop periods
        costs one scalar recurrence over the P loop updates (the PI law, the contact's
        push and creep, the mean F/T reading the loop acts on) and one vectorised block of
        P x 10 samples (trajectory, contact force, F/T synthesis, the guard's screen and
        the guard itself, scanner exposures), instead of P sub-chunks.

        The block is screened before anything is committed: if any sample could end the
        hold — the contact ending, the UR's own force limit, slip, the path's validated
        range, anything the guard's screen cannot clear (checked period by period, as the
        sub-chunk path screens) — nothing is committed and None is returned: the caller
        redoes the span sub-chunk by sub-chunk, which stops at the exact sample. Returns
        True when the span was committed, False when batching does not apply here.

        The recurrence is the same physics and the same noise as the sub-chunk path, in
        another floating-point order (the force loop reads its mean force as
        contact + offsets rather than summing ten delivered samples): values agree to
        ~1e-12 relative, not bit for bit; the same commands still give the same bytes.
        """
        arm, c, faults = self.arm, self.contact, self.faults
        sp = self.sample_period_us
        period = arm.loop_period_us
        m = period // sp
        if c is None or c.model is None or period % sp or m < self._rate_window or self.trip is not None:
            return False
        n_periods = (target_us - self.now_us) // period
        if n_periods < 2:
            return False
        now = self.now_us
        end = now + n_periods * period
        faults._sim_on_time(now)
        # A fault that fired just now may have ended the hold already (a protective stop
        # halts the arm and is over in the same instant, so it is not active any more).
        if (faults._sim_any_active() or faults._sim_bound_end(now, end) != end
                or not arm._sim_hold_ready(now)):
            return False
        path = arm._path
        rot = path.r0
        n = n_periods * m
        ts = np.arange(now + sp, end + 1, sp, dtype=np.int64)
        offsets, r_bs = self.ft._sim_offset_force_n(ts, rot)
        offset_mean = offsets.reshape(n_periods, m, 3).mean(axis=1).tolist()
        w0, w1, w2 = (-(c.d_base @ r_bs)).tolist()     # sensor force per N of contact force
        tip0 = path.p0 if self._tip_offset_zero else path.p0 + rot @ self.tip_offset_tcp_mm
        pc = float((tip0 - c.tip_touch_base) @ c.d_base)
        vd = float(path.v @ c.d_base)
        grid = c.push_grid_mm.tolist()
        t_s = [(j + 1) * sp / US_PER_S for j in range(m)]       # sample instants after each update (s)
        frac = [(j + 1) * sp / period for j in range(m)]        # creep interpolation, as in _dry
        t_first, t_last, t_mid = t_s[0], t_s[-1], sum(t_s) / m
        accel = arm.gains.accel_mm_s2
        beta = c.creep_beta
        dt_s = period / US_PER_S

        # The recurrence: one force-loop update per period, on a copy of the regulator.
        reg = replace(arm._regulator)
        loop_speed = arm._force_loop_speed
        u, du = arm._u, arm._du
        measured = arm._measured_force_n()
        push0, push_max, c0 = c.push_mm, c.push_max_mm, c.creep_c
        laws = []                  # per period: u0, v0, v1, a, t_r
        creep_ends = []            # per period: (creep at its start, creep_after at its end)
        for k in range(n_periods):
            v1 = loop_speed(reg, now + k * period, measured, u)
            dv = v1 - du
            a = math.copysign(accel, dv)
            t_r = abs(dv) / accel
            laws.append((u, du, v1, a, t_r))
            tr = t_last if t_last < t_r else t_r
            u_end = u + du * tr + 0.5 * a * tr * tr + v1 * max(t_last - t_r, 0.0)
            du_end = du + a * t_last if t_last < t_r else v1
            push_end = pc + u_end * vd
            c_end = c.creep_after(c0, push0, push_end, dt_s, push_max) if beta > 0.0 else 1.0
            creep_ends.append((c0, c_end))
            # The loop's next reading: the mean of this period's ten samples.
            f_mean = None
            if beta <= 0.0 and t_r <= t_first:
                # A straight line over the whole period: the push is linear in t, so where
                # the ten pushes share one segment of the force table the mean force is the
                # force at the mean push.
                p_first = pc + (u + du * t_r + 0.5 * a * t_r * t_r + v1 * (t_first - t_r)) * vd
                if p_first > 0.0 and push_end > 0.0:
                    j = bisect_right(grid, p_first) - 1
                    if j == bisect_right(grid, push_end) - 1 and j < len(grid) - 1:
                        p_mid = pc + (u + du * t_r + 0.5 * a * t_r * t_r + v1 * (t_mid - t_r)) * vd
                        f_mean = _FORCE_GRID_LIST[j] + (p_mid - grid[j]) * (
                            (_FORCE_GRID_LIST[j + 1] - _FORCE_GRID_LIST[j]) / (grid[j + 1] - grid[j]))
            if f_mean is None:
                total = 0.0
                for j in range(m):
                    t = t_s[j]
                    tr = t if t < t_r else t_r
                    push_j = pc + (u + du * tr + 0.5 * a * tr * tr + v1 * max(t - t_r, 0.0)) * vd
                    cj = c0 + (c_end - c0) * frac[j] if beta > 0.0 else 1.0
                    total += _force_at(max(push_j, 0.0) / cj, grid)
                f_mean = total / m
            e = offset_mean[k]
            fx, fy, fz = f_mean * w0 + e[0], f_mean * w1 + e[1], f_mean * w2 + e[2]
            measured = math.sqrt(fx * fx + fy * fy + fz * fz)
            u, du = u_end, du_end
            push0 = push_end
            push_max = max(push_max, push_end)
            c0 = c0 + (c_end - c0) * frac[-1]       # the committed state is the last sample's, as in _dry

        # The block: every sample of the span from the per-period laws (the same
        # expressions as the recurrence, so its last sample is the recurrence's state).
        law = np.repeat(np.array(laws), m, axis=0)
        u0v, v0v, v1v, av, trv = law[:, 0], law[:, 1], law[:, 2], law[:, 3], law[:, 4]
        t = np.tile(np.array(t_s), n_periods)
        tr = np.minimum(t, trv)
        u_all = u0v + v0v * tr + 0.5 * av * tr * tr + v1v * np.maximum(t - trv, 0.0)
        du_all = np.where(t < trv, v0v + av * t, v1v)
        push = pc + u_all * vd
        if beta > 0.0:
            ce = np.repeat(np.array(creep_ends), m, axis=0)
            creep = ce[:, 0] + (ce[:, 1] - ce[:, 0]) * np.tile(np.array(frac), n_periods)
        else:
            creep = np.ones(n)
        force = c.forces_n(push, creep)
        # Anything that could end the hold inside the span: redo it sub-chunk by sub-chunk.
        lo, hi = path.u_table[0], path.u_table[-1]
        if (float(push.min()) <= 1e-6 or float(force.max()) > 0.99 * self.ur_force_limit_n
                or float(u_all.min()) < lo or float(u_all.max()) > hi):
            return self._hold_fallback()
        if c.sliding and c.shift_grid_mm is not None:
            slip = np.abs(np.interp(force[m - 1::m], _SHIFT_FORCE_N, c.shift_grid_mm))
            if float(slip.max()) > 0.99 * self.limits.slip_mm:
                return self._hold_fallback()
        samples = self.ft._sim_synthesize(ts, -force[:, None] * c.d_base[None, :], rot, now)
        if not self._screen_span(samples, n_periods, m):
            return self._hold_fallback()

        # Commit: the guard, the scanner's exposures, the F/T stream, the contact, the arm.
        if self.guard_batch_us > 0:
            self._guard_pending.append((ts, samples.seq, samples.out, samples.status))
            self._guard_pending_n += n
            trip = self.guard_flush() if self._guard_pending_n * sp >= self.guard_batch_us else None
        else:
            self.stats["guard_blocks"] += 1
            trip = self.guard.check_block(samples.block(n))
        for t_exp in self.scanner._sim_due(now, end):
            i = min(int(np.searchsorted(ts, t_exp)), n - 1)
            # As in _commit: the contact's creep state at the start of the sample's period.
            hold_s = c.hold_s_at(creep_ends[i // m][0])
            self.scanner._sim_capture(WorldSnapshot(int(ts[i]), Pose(path.p0 + u_all[i] * path.v, rot),
                                                    self.base_to_object, c, float(force[i]), hold_s))
        self.ft._sim_commit(samples, n)
        c.push_mm = float(push[-1])
        c.push_max_mm = push_max
        c.creep_c = float(creep[-1])
        c.force_n = float(force[-1])
        c.max_force_n = max(c.max_force_n, float(force.max()))
        u0, v0, v1, _, _ = laws[-1]
        arm._sim_hold_commit(reg, end - period, u0, v0, v1, float(u_all[-1]), float(du_all[-1]))
        self.now_us = end
        self.stats["hold_spans"] += 1
        self.stats["hold_periods"] += n_periods
        if trip is not None:
            # The screen clears only blocks that cannot cross a limit; kept for safety.
            if self.trip is None:
                self.trip = _trip_truncated(trip, self.guard)
                self._latched_force_n = max(float(trip.value) if trip.kind == "force" else 0.0, float(force.max()))
                self._latched_us = self.now_us
            arm._sim_halt(self.now_us, "tripped")
        return True

    def _hold_fallback(self) -> None:
        self.stats["hold_fallbacks"] += 1
        return None

    def _screen_span(self, samples, n_periods: int, m: int) -> bool:
        """:meth:`_screen` applied to each force-loop period of a batched span in turn
        (vectorised): True when every period would have been cleared as its own sub-chunk.
        Updates the screen's carry-over only when it clears the whole span."""
        if self._screen_noiseless or not samples.status_clear or self.faults._sim_frozen_possible():
            return False
        if self._screen_count < self._rate_window:
            return False
        fm = samples.fmag.reshape(n_periods, m)
        fmax, fmin = fm.max(axis=1), fm.min(axis=1)
        if float(fmax.max()) > 0.98 * self._screen_force_limit or float(samples.tmag2.max()) > self._screen_torque2:
            return False
        prev_max = np.concatenate([[self._screen_prev[0]], fmax[:-1]])
        prev_min = np.concatenate([[self._screen_prev[1]], fmin[:-1]])
        dt_min = self._rate_window * self.sample_period_us / US_PER_S
        spread = np.maximum(fmax, prev_max) - np.minimum(fmin, prev_min)
        if float(spread.max()) / dt_min > 0.9 * self.limits.max_force_rate_n_s:
            return False
        self._screen_prev = (float(fmax[-1]), float(fmin[-1]))
        self._screen_count += n_periods * m
        return True

    # ------------------------------------------------------------------ the safety guard
    def _guard_check(self, samples, cut: int) -> Trip | None:
        clear = self._screen(samples, cut)
        if clear and self.guard_batch_us > 0:
            if samples.all_delivered:
                part = (samples.ts_us[:cut], samples.seq[:cut], samples.out[:cut], samples.status[:cut])
            else:
                keep = samples.delivered[:cut]
                part = (samples.ts_us[:cut][keep], samples.seq[:cut][keep], samples.out[:cut][keep],
                        samples.status[:cut][keep])
            self._guard_pending.append(part)
            self._guard_pending_n += part[0].shape[0]
            if self._guard_pending_n * self.sample_period_us >= self.guard_batch_us:
                return self.guard_flush()
            return None
        late = self.guard_flush()
        self.stats["guard_blocks"] += 1
        trip = self.guard.check_block(samples.block(cut))
        return trip if trip is not None else late

    def guard_flush(self) -> Trip | None:
        """Hand the screened, batched samples to the guard (before anything reads its state)."""
        pending = self._guard_pending
        if not pending:
            return None
        if len(pending) == 1:
            ts_us, seq, out, status = pending[0]
        else:
            ts_us = np.concatenate([p[0] for p in pending])
            seq = np.concatenate([p[1] for p in pending])
            out = np.concatenate([p[2] for p in pending])
            status = np.concatenate([p[3] for p in pending])
        pending.clear()
        self._guard_pending_n = 0
        self.stats["guard_blocks"] += 1
        if not ts_us.shape[0]:
            return None
        return self.guard.check_block(WrenchBlock(ts_us / US_PER_S, seq, out[:, :3], out[:, 3:], status))

    def guard_restart(self) -> None:
        """A deliberate step in the stream (tare): flush, then let the guard forget its carry-over."""
        self.guard_flush()
        self.guard.note_stream_restart()
        self._screen_prev = (0.0, 0.0)
        self._screen_count = 0

    def _screen(self, samples, cut: int) -> bool:
        """True when no sample of the block can make SafetyGuard.check_block trip (conservative).

        Force, torque and the lateral force (never above |F|) below 98 % of their limits;
        no status bit; the force rate bounded by the range of |F| over this block and the
        previous one divided by the guard's rate window (only once the guard has a full
        window behind it); and identical consecutive readings impossible (noise on, no
        frozen-stream fault).
        """
        lim = self.limits
        fmag = samples.fmag[:cut] if samples.all_delivered else samples.fmag[:cut][samples.delivered[:cut]]
        if fmag.shape[0] == 0:
            return True
        fmax, fmin = float(fmag.max()), float(fmag.min())
        prev_max, prev_min = self._screen_prev
        self._screen_prev = (fmax, fmin)
        enough_history = self._screen_count >= self._rate_window
        self._screen_count += fmag.shape[0]
        margin = 0.98
        if fmax > margin * self._screen_force_limit:
            return False
        tmag2 = samples.tmag2[:cut]
        if float(tmag2.max()) > self._screen_torque2:
            return False
        if not samples.status_clear and samples.status[:cut].any():
            return False
        if not enough_history or fmag.shape[0] < self._rate_window:
            return False
        dt_min = self._rate_window * self.sample_period_us / US_PER_S
        if (max(fmax, prev_max) - min(fmin, prev_min)) / dt_min > 0.9 * lim.max_force_rate_n_s:
            return False
        if self._screen_noiseless or self.faults._sim_frozen_possible():
            return False
        return True

    def _halts_recovery(self, trip: Trip, samples, cut: int) -> bool:
        """While a trip is latched, the controller unloads and retracts: the arm's force-loop
        supervisor (controller/core/forceloop.py) lets a crossing through for a motion that unloads
        the contact (away from it, the force not rising); anything else is stopped again
        (the UR's own force limit still applies)."""
        if self.trip is None:
            return True
        fmax = float(np.max(samples.fmag[:cut])) if samples.fmag is not None and cut else 0.0
        return not self.arm._sim_lets_through(trip, fmax)

    def _rotations(self, plan: ArmPlan, n: int) -> np.ndarray:
        return plan.rotation if plan.rotation.ndim == 2 else plan.rotation[:n]

    # ------------------------------------------------------------------ contact physics (dry)
    def _dry(self, ts: np.ndarray, plan: ArmPlan, tips: np.ndarray, n: int) -> _Dry:
        if n == plan.position_mm.shape[0]:
            plan_n = plan
        else:
            plan_n = ArmPlan(plan.position_mm[:n], plan.rotation if plan.rotation.ndim == 2 else plan.rotation[:n],
                             plan.du[:n], plan.speed_scale)
        c = self.contact
        if c is None:
            zeros = np.zeros(n)
            return _Dry(ts, plan_n, tips, np.zeros((n, 3)), zeros, zeros, np.ones(n), zeros)
        if c.model is None:
            # Table: penetration of the tip sphere below z = R, along the table normal.
            z_obj = self._to_object(tips)[:, 2]
            pen = self.tip_radius_mm - z_obj
            force = TABLE_STIFFNESS_N_MM * np.maximum(pen, 0.0)
            up_base = self.base_to_object.rotation[:, 2]
            ends = np.flatnonzero(pen < -1e-9)
            return _Dry(ts, plan_n, tips, force[:, None] * up_base[None, :], force, pen, np.ones(n), np.zeros(n),
                        int(ends[0]) if ends.size else None)
        push = (tips - c.tip_touch_base) @ c.d_base
        if c.creep_beta > 0.0:
            dt_s = (ts[-1] - self.now_us) / US_PER_S
            c_end = c.creep_after(c.creep_c, c.push_mm, float(push[-1]), dt_s)
            frac = (ts - self.now_us) / max(ts[-1] - self.now_us, 1)
            creep = c.creep_c + (c_end - c.creep_c) * frac
        else:
            creep = _ONES[:n] if n <= _ONES.shape[0] else np.ones(n)
        force = c.forces_n(push, creep)
        slip_const: float | None = c.slip_mm(float(force[-1]))
        slip = np.full(n, slip_const)
        if self.faults._sim_any_active():
            slip = slip + self.faults._sim_slip_mm(ts, c)
            slip_const = None
        ends = np.flatnonzero(push < -1e-9) if float(push.min()) < -1e-9 else ()
        return _Dry(ts, plan_n, tips, -force[:, None] * c.d_base[None, :], force, push, creep, slip,
                    int(ends[0]) if len(ends) else None, slip_const)

    def _commit(self, dry: _Dry, cut: int, force_max_n: float | None = None) -> None:
        last = cut - 1
        t_end = int(dry.ts_us[last])
        exposures = self.scanner._sim_due(self.now_us, t_end)
        for t_exp in exposures:
            i = int(np.searchsorted(dry.ts_us, t_exp))
            i = min(i, last)
            self.scanner._sim_capture(self._snapshot(dry, i))
        c = self.contact
        if c is not None:
            c.push_mm = float(dry.push_mm[last])
            c.push_max_mm = max(c.push_max_mm, c.push_mm)
            c.creep_c = float(dry.creep_c[last])
            c.force_n = float(dry.force_mag_n[last])
            c.max_force_n = max(c.max_force_n, force_max_n if force_max_n is not None
                                else float(np.max(dry.force_mag_n[:cut])))
        self.arm._sim_commit(dry.ts_us[:cut], last)
        self.now_us = t_end
        if c is not None and dry.contact_ends_at is not None and dry.contact_ends_at <= last:
            self._end_contact()

    def _snapshot(self, dry: _Dry, i: int) -> WorldSnapshot:
        rot = dry.plan.rotation if dry.plan.rotation.ndim == 2 else dry.plan.rotation[i]
        c = self.contact
        return WorldSnapshot(int(dry.ts_us[i]), Pose(dry.plan.position_mm[i], rot), self.base_to_object, c,
                             float(dry.force_mag_n[i]) if c is not None else 0.0,
                             c.hold_s() if c is not None else math.inf)

    def snapshot_now(self) -> WorldSnapshot:
        c = self.contact
        return WorldSnapshot(self.now_us, self.arm._sim_tcp_pose(), self.base_to_object, c,
                             c.force_n if c is not None else 0.0, c.hold_s() if c is not None else math.inf)

    # ------------------------------------------------------------------ contact onset and end
    def _to_object(self, points_base: np.ndarray) -> np.ndarray:
        b2o = self.base_to_object
        return (points_base - b2o.position_mm) @ b2o.rotation

    def _distances(self, tips_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Signed distance of tip centres to the object and to the table (object frame)."""
        self.stats["distance_queries"] += 1
        closest, normals, _ = self.obj.closest_surface(tips_obj)
        signed = np.einsum("ij,ij->i", tips_obj - closest, normals)
        gap = np.linalg.norm(tips_obj - closest, axis=1)
        dist_obj = np.where(signed < 0.0, -gap, gap)
        return dist_obj, tips_obj[:, 2], closest, normals

    def _lower_bound_distance(self, tip_obj: np.ndarray) -> float:
        """A cheap lower bound of the tip's distance to the object: its distance to the bounding box."""
        lo, hi = self._obj_bounds
        outside = np.maximum(np.maximum(lo - tip_obj, tip_obj - hi), 0.0)
        return float(np.linalg.norm(outside))

    def _first_touch(self, tips_base: np.ndarray, plan: ArmPlan) -> int | None:
        """Index of the first sample whose tip sphere touches the object or the table, or None.

        A ball around the last queried point is known free; exact queries happen only when
        the tip leaves it, so a long approach costs a handful of closest-point queries.
        """
        tips = self._to_object(tips_base)
        r = self.tip_radius_mm
        i = 0
        n = tips.shape[0]
        while i < n:
            if self._free_centre is not None:
                out = np.flatnonzero(np.linalg.norm(tips[i:] - self._free_centre, axis=1) >= self._free_radius)
                if out.size == 0:
                    return None
                i += int(out[0])
            bound = min(self._lower_bound_distance(tips[i]), tips[i, 2]) - r
            if bound > 1.0:
                self._free_centre, self._free_radius = tips[i].copy(), bound
                continue
            dist_obj, z, _, _ = self._distances(tips[i:i + 1])
            gap = min(float(dist_obj[0]), float(z[0])) - r
            if gap <= 0.0:
                return i
            if gap < 0.25:
                # Close: check every remaining sample of this sub-chunk at once.
                d_all, z_all, _, _ = self._distances(tips[i:])
                touching = np.flatnonzero(np.minimum(d_all, z_all) - r <= 0.0)
                if touching.size:
                    return i + int(touching[0])
                j = n - 1
                self._free_centre = tips[j].copy()
                self._free_radius = max(float(min(d_all[-1], z_all[-1])) - r, 0.0)
                return None
            self._free_centre, self._free_radius = tips[i].copy(), gap
        return None

    def _begin_contact(self, tips_base: np.ndarray, plan: ArmPlan, ts: np.ndarray) -> None:
        """First touch between the current tip and the first sample: interpolate the touch point."""
        prev_tip = self.arm._sim_tip_base(self.tip_offset_tcp_mm)
        tips_obj = self._to_object(np.vstack([prev_tip, tips_base[0]]))
        d_obj_all, z_all, closest, normals = self._distances(tips_obj)
        r = self.tip_radius_mm
        g0 = min(d_obj_all[0], z_all[0]) - r
        g1 = min(d_obj_all[1], z_all[1]) - r
        # Already touching at the current position (a sub-chunk was cut at the touch): touch here.
        f = 0.0 if g0 <= 0.0 else float(np.clip(g0 / max(g0 - g1, 1e-12), 0.0, 1.0))
        touch_base = prev_tip + f * (tips_base[0] - prev_tip)
        touch_obj = self._to_object(touch_base[None])[0]
        rot = plan.rotation if plan.rotation.ndim == 2 else plan.rotation[0]
        d_base = rot[:, 2]
        d_obj = self.base_to_object.rotation.T @ d_base
        x_obj = self.base_to_object.rotation.T @ rot[:, 0]
        table = z_all[1] <= d_obj_all[1]
        if table:
            point = np.array([touch_obj[0], touch_obj[1], 0.0])
            normal = np.array([0.0, 0.0, 1.0])
        else:
            cl, nl, _ = self.obj.closest_surface(touch_obj[None])
            point, normal = cl[0], nl[0]
        self.contact = make_contact(self.obj, point, normal, d_obj, x_obj, d_base, touch_base, self.tip_radius_mm,
                                    self.now_us, bool(table))
        if table:
            # The table pushes along its normal; the push is the penetration below z = R.
            self.contact.d_base = -self.base_to_object.rotation[:, 2]
        self._free_centre = None
        self.arm._sim_contact_began()

    def _end_contact(self) -> None:
        c = self.contact
        self.contact = None
        self._free_centre = None
        if c is not None and c.model is not None and c.max_force_n > 0.0:
            press = Press(c.point_obj.copy(), c.normal_obj.copy(), c.max_force_n)
            self._record_press(press)

    def _record_press(self, press: Press) -> None:
        """Permanent dents depend only on the MAX force ever applied near a point.

        The object adds up the dents it is given, so a press near an old one that goes
        higher replaces that one's force and the object's dents are rebuilt from the maxima.
        """
        for old in self.presses:
            if np.linalg.norm(old.point_obj - press.point_obj) < 0.5:
                if old.max_force_n >= press.max_force_n:
                    return
                old.max_force_n = press.max_force_n
                self.obj.reset_history()
                for p in self.presses:
                    self.obj.add_permanent_dent(p.point_obj, p.normal_obj, p.max_force_n)
                return
        self.presses.append(press)
        self.obj.add_permanent_dent(press.point_obj, press.normal_obj, press.max_force_n)

    def restore_history(self, presses: list[tuple[np.ndarray, np.ndarray, float]]) -> None:
        """Rebuild persistent object state (permanent dents) on resume."""
        self.obj.reset_history()
        self.presses.clear()
        for point, normal, force in presses:
            self._record_press(Press(np.asarray(point, float), np.asarray(normal, float), float(force)))

    def move_object(self, offset_obj_mm: np.ndarray) -> None:
        """Shift the true object placement (the controller keeps believing the nominal one)."""
        shift = Pose(np.asarray(offset_obj_mm, float), np.eye(3))
        self.base_to_object = self.base_to_object.compose(shift)
        self._free_centre = None

    def clear_trip(self) -> None:
        self.trip = None


def _trip_truncated(trip: Trip, guard: SafetyGuard) -> Trip:
    """The trip with its raw data cut at the crossing (nothing after the instant it happened)."""
    raw = trip.raw if trip.raw is not None else guard.raw_history()
    if raw is not None and len(raw):
        keep = raw.t_s <= trip.t_s + 1e-9
        raw = WrenchBlock(raw.t_s[keep], raw.seq[keep], raw.force_n[keep], raw.torque_nm[keep], raw.status[keep])
    return Trip(trip.kind, trip.t_s, trip.value, trip.limit, trip.message, raw)
