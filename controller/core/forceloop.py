"""The force loop: contact search, force regulation and the trip policy, once for every backend.

A device gives primitives: its state, a straight move, a speed command, a stop, blocks of
F/T samples. What the probe does with them is decided here, by :class:`ForceSupervisor`:

- **contact search**: a speed command along the push direction d; the first F/T sample whose
  |F| reaches the threshold stops it (CONTACT); travelling ``max_distance_mm`` without one
  stops it too (NO_CONTACT).
- **force regulation**: a PI loop on |F| with feed-forward of the reference ramp, commanding
  the speed along d once per ``ForceLoopGains.period_s``; its gain follows an online
  estimate of the contact stiffness (N/mm from successive (dF, du) pairs), because rubber is
  ~50x stiffer than foam. The estimate starts from ``initial_stiffness_n_mm``, a guess: the
  first pair whose force changed by more than the loop's tolerance replaces it, and a
  regulation that follows another on the same contact (same push, nothing commanded between:
  the next force level) starts from where that one's estimate ended. The first regulation
  after a contact search starts from the touch's own stiffness when that is stiffer than the
  guess: the force's rise from half the threshold to the threshold over the search's speed
  (:meth:`ForceSupervisor.seek_samples`). A guess 50x too soft commands 50x the speed, and
  with the arm's acceleration limit the probe bounced off hard rubber and came back at the
  loop's top speed: 3-4x the target force at every level, and force-rate trips. DONE once
  |error| <= max(tolerance_n, tolerance_rel x target) for ``settle_updates`` periods at the
  target; then it keeps holding (foam creeps: the integrator keeps pushing) until the next
  command.
- **the trip policy**: the first crossing of a safety limit (:class:`~.safety.SafetyGuard`,
  checked where the data arrives) stops the arm and latches. While it is latched, a motion
  commanded after the trip that *unloads* — it moves away from the contact and the force
  does not rise — goes through the guard, so a force trip does not block its own retract;
  anything else is stopped again.

Backends call it where their data arrives, with the same gains (the cell file's
``force_loop:`` section):

- the simulated arm (``elastoprobe.sim.arm``), in virtual time: the world hands every
  sub-chunk's F/T samples to the contact check and cuts sub-chunks at each regulation
  update, so a contact or a crossing stops the arm at its sample's instant;
- the hardware process (``controller/drivers/hardware.py``), in real time: its safety
  thread calls :meth:`ForceSupervisor.on_block` on every F/T block, its control thread
  :meth:`ForceSupervisor.on_tick` at the loop period;
- the scripted arm (``controller/drivers/scripted.py``), a light fake for tests.

Units: mm, mm/s, mm/s^2, N, s. Directions are unit vectors in the robot base frame.
"""
from __future__ import annotations

import enum
import hashlib
import itertools
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from .devices import MotionState, Trip, WrenchBlock
from .errors import MotionRefused
from .safety import SafetyLimits

# The stiffness estimate: a pair of updates counts when the probe moved more than this (mm)
# into a load above this (N) and the force changed with the motion; each estimate is
# clamped to a physical range (N/mm: from soft foam to a rigid table) and blended into a
# running geometric mean with this weight.
_STIFFNESS_MIN_STEP_MM = 2e-3
_STIFFNESS_MIN_FORCE_N = 0.3
_STIFFNESS_RANGE_N_MM = (0.05, 1000.0)
_STIFFNESS_BLEND = 0.2
# A regulation carries the previous one's estimate only along the same push (within ~2.6 deg):
# the stiffness along another direction of the same contact is another number.
_SAME_PUSH_COS = 0.999

# While a trip is latched, a motion that unloads may see the force stay above the limit
# for a while (the arm decelerates, the material relaxes): a reading more than this
# fraction above the latched peak (or the limit, if higher) is a force that rises, and stops
# it. The F/T noise is ~0.04 N against limits of tens of newtons; a motion pushing into the
# contact instead passes this margin within a few millimetres on any probed material.
UNLOAD_RISE_FRACTION = 0.1

# The force kinds of crossing: after a trip of one of them, an unloading motion may go on
# through any of them (unloading moves the force, its rate and the torque together) while the
# force does not rise. A crossing of another kind (a stale or frozen stream, a status word,
# slip) goes through only after a trip of that same kind, for a motion away from the contact.
FORCE_KINDS = frozenset({"force", "force_rate", "lateral_force", "torque"})

# The regulation acts only on fresh readings: when the newest F/T sample is older than this
# many loop periods (a stream that stalls: a network hiccup, a starved process), it commands
# no speed and keeps its state until samples come again, instead of pushing on an old force.
# The guard's own stale limit (ft_stale_ms) trips the arm if the stall goes on.
STALE_PERIODS = 2.0

_CODE_SHA256 = hashlib.sha256(Path(__file__).read_bytes()).hexdigest()


@dataclass(frozen=True)
class ForceLoopGains:
    """The tuning of the contact search and the force loop (the cell file's ``force_loop:``).

    ``period_s``: one regulation update per period (the speed command follows it);
    ``gain``: the fraction of the force error corrected per period; ``integral_per_s``:
    integral action; both are divided by the stiffness estimate (N/mm), which starts at
    ``initial_stiffness_n_mm``. ``max_speed_mm_s`` and ``accel_mm_s2`` bound the speed
    commands of the regulation; ``seek_accel_mm_s2`` is the contact search's. The force the
    loop reads is |mean| of the latest ``force_window`` F/T samples.
    """

    period_s: float = 0.01
    gain: float = 0.3
    integral_per_s: float = 1.5
    max_speed_mm_s: float = 15.0
    accel_mm_s2: float = 500.0
    tolerance_n: float = 0.1
    tolerance_rel: float = 0.02
    settle_updates: int = 10
    initial_stiffness_n_mm: float = 2.0
    force_window: int = 10
    seek_accel_mm_s2: float = 500.0

    def tolerance_n_at(self, target_n: float) -> float:
        """The band (N) the force must stay in, around ``target_n``, to count as settled."""
        return max(self.tolerance_n, self.tolerance_rel * target_n)


def measured_force_n(recent_force_n: np.ndarray) -> float:
    """The force the loop acts on: |mean| of the latest F/T samples (rows, N), 0 without any.

    The mean and the norm are spelled out (numpy's mean is a sum then a division, its norm
    sqrt(x . x)): the same numbers without their Python-level overhead, on the hot path.
    """
    n = recent_force_n.shape[0]
    if n == 0:
        return 0.0
    mean = np.add.reduce(recent_force_n, axis=0) / n
    return math.sqrt(float(mean.dot(mean)))


def force_magnitudes_n(block: WrenchBlock) -> np.ndarray:
    """|F| (N) of every sample of ``block``."""
    f = block.force_n
    return np.sqrt(np.einsum("ij,ij->i", f, f))


# ---------------------------------------------------------------------------- the loops
@dataclass
class Regulation:
    """State of one force regulation (a new command starts a new one; so does a new contact).

    Pure in its own fields: :meth:`update` changes only this object, so a backend may run the
    law on a copy (the simulator's batched holds do).
    """

    gains: ForceLoopGains
    direction: np.ndarray
    target_n: float
    rate_n_s: float
    start_n: float
    stiffness_n_mm: float
    stiffness_measured: bool = False     # the estimate rests on a measured pair, not the guess
    integral: float = 0.0
    last_force_n: float | None = None
    last_u_mm: float = 0.0
    in_band: int = 0
    updates: int = 0

    def reference_n(self, elapsed_s: float) -> float:
        """The force asked for ``elapsed_s`` after the regulation began: a ramp at the rate."""
        if self.target_n >= self.start_n:
            return min(self.target_n, self.start_n + self.rate_n_s * elapsed_s)
        return max(self.target_n, self.start_n - self.rate_n_s * elapsed_s)

    def update(self, elapsed_s: float, force_n: float, u_mm: float) -> float:
        """One update ``elapsed_s`` after the regulation began, from the measured |F| (N) and
        the position along the direction (mm, any origin): the speed to command (mm/s,
        positive along the direction)."""
        g = self.gains
        period_s = g.period_s
        if self.last_force_n is not None:
            du = u_mm - self.last_u_mm
            df = force_n - self.last_force_n
            if abs(du) > _STIFFNESS_MIN_STEP_MM and force_n > _STIFFNESS_MIN_FORCE_N and df * du > 0:
                k_obs = min(max(df / du, _STIFFNESS_RANGE_N_MM[0]), _STIFFNESS_RANGE_N_MM[1])
                if not self.stiffness_measured and abs(df) > g.tolerance_n:
                    # The first pair the force noise cannot make: evidence, where the
                    # estimate so far was a guess (blending it in would take ~10 periods).
                    self.stiffness_n_mm = k_obs
                    self.stiffness_measured = True
                else:
                    self.stiffness_n_mm = math.exp((1.0 - _STIFFNESS_BLEND) * math.log(self.stiffness_n_mm)
                                                   + _STIFFNESS_BLEND * math.log(k_obs))
        self.last_force_n, self.last_u_mm = force_n, u_mm
        ref = self.reference_n(elapsed_s)
        ref_next = self.reference_n(elapsed_s + period_s)
        err = ref - force_n
        k = self.stiffness_n_mm
        self.integral += err * period_s
        limit = g.max_speed_mm_s * k / max(g.integral_per_s, 1e-9)
        self.integral = min(max(self.integral, -limit), limit)
        speed = ((ref_next - ref) / period_s) / k + g.gain * err / (k * period_s) + g.integral_per_s * self.integral / k
        speed = min(max(speed, -g.max_speed_mm_s), g.max_speed_mm_s)
        self.in_band = self.in_band + 1 if (ref == self.target_n and abs(err) <= g.tolerance_n_at(self.target_n)) else 0
        self.updates += 1
        return speed

    @property
    def settled(self) -> bool:
        return self.in_band >= self.gains.settle_updates

    def progress(self) -> float:
        if self.target_n <= 0 or self.last_force_n is None:
            return 1.0 if self.target_n <= 0 else 0.0
        return self.last_force_n / self.target_n

    def contact_began(self) -> None:
        """A new contact: the loop's memory of the old one is worthless."""
        self.integral = 0.0
        self.last_force_n = None
        self.in_band = 0


@dataclass(frozen=True)
class ContactSearch:
    """A contact search: ``speed_mm_s`` along ``direction`` from ``start_mm`` until |F| reaches
    ``threshold_n`` or the probe has travelled ``max_distance_mm``."""

    direction: np.ndarray
    speed_mm_s: float
    threshold_n: float
    max_distance_mm: float
    start_mm: np.ndarray

    def velocity_mm_s(self) -> np.ndarray:
        return self.direction * self.speed_mm_s

    def first_contact(self, force_magnitude_n: np.ndarray) -> int | None:
        """Index of the first sample at or above the threshold, or None."""
        hit = np.flatnonzero(force_magnitude_n >= self.threshold_n)
        return int(hit[0]) if hit.size else None

    def travelled_mm(self, position_mm: np.ndarray) -> float:
        return float((np.asarray(position_mm, float) - self.start_mm) @ self.direction)


@dataclass(frozen=True)
class TripLatch:
    """A trip that stopped the arm, until the guard is re-armed.

    ``away_base``: the direction that unloads the contact (unit, base frame): opposite the
    push of the contact search or regulation that tripped, else the direction of the force
    the environment exerted on the tool; None when neither is known. ``peak_force_n``: |F|
    at the trip.
    """

    kind: str
    t_s: float
    peak_force_n: float
    away_base: np.ndarray | None


class Verdict(enum.Enum):
    """What a crossing calls for."""

    STOP = "stop"                 # stop the arm now
    LET_THROUGH = "let_through"   # a motion that unloads the latched trip's contact: leave it
    IGNORE = "ignore"             # latched and nothing moves: the arm is already stopped


# ---------------------------------------------------------------------------- motions
class SupervisedMotion:
    """Handle of one arm command (implements :class:`~.devices.Motion`) on every backend.

    ``direction_base``: where the command moves the tool (unit, base frame; None for a
    rotation only). ``after_trip``: commanded while a trip was latched (only such a motion
    can be let through it). A regulation that reaches its force is DONE and keeps
    ``holding`` it until the next command: it can still end (stopped, tripped, a fault).
    """

    # Ids unique across processes and restarts (a stale handle never aliases a new motion).
    _ids = itertools.count(time.time_ns() // 1000 % 10**12)

    def __init__(self, kind: str, direction_base: np.ndarray | None = None,
                 state: MotionState = MotionState.RUNNING, after_trip: bool = False) -> None:
        self.id = next(self._ids)
        self._kind = kind
        self._state = state
        self._progress = 0.0 if state == MotionState.RUNNING else 1.0
        self.direction_base = direction_base
        self.after_trip = after_trip
        self.holding = False
        self.note = ""

    @property
    def kind(self) -> str:
        return self._kind

    def state(self) -> MotionState:
        return self._state

    def progress(self) -> float:
        return float(min(max(self._progress, 0.0), 1.0))

    def set_progress(self, fraction: float) -> None:
        if self._state == MotionState.RUNNING:
            self._progress = float(fraction)

    @property
    def active(self) -> bool:
        """Still commanding the arm: RUNNING, or a regulation holding its force."""
        return self._state == MotionState.RUNNING or self.holding

    def finish(self, state: MotionState, note: str = "") -> None:
        if self.active:
            self._state = state
            self.holding = False
            self.note = note
            if state in (MotionState.DONE, MotionState.CONTACT, MotionState.NO_CONTACT):
                self._progress = 1.0

    def settle(self) -> None:
        """A regulation reached its force: DONE, and it goes on holding it."""
        if self._state == MotionState.RUNNING:
            self._state = MotionState.DONE
            self._progress = 1.0
            self.holding = True


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, float).reshape(3)
    n = float(np.linalg.norm(v))
    if not math.isfinite(n) or n < 1e-12:
        raise MotionRefused("direction has zero length")
    return v / n


@dataclass(frozen=True)
class BlockVerdict:
    """What one F/T block calls for (:meth:`ForceSupervisor.on_block`): ``stop`` the arm now,
    because of ``trip`` or a contact at ``contact_t_s``; ``let_through`` counts crossings left
    to an unloading motion."""

    stop: bool = False
    trip: Trip | None = None
    contact_t_s: float | None = None
    let_through: bool = False
    peak_force_n: float = 0.0


@dataclass(frozen=True)
class TickCommand:
    """What a control tick calls for (:meth:`ForceSupervisor.on_tick`): ``stop`` the arm (the
    contact search ran out), or a new ``velocity_mm_s`` (base frame) at ``accel_mm_s2``."""

    stop: bool = False
    velocity_mm_s: np.ndarray | None = None
    accel_mm_s2: float = 0.0


@dataclass
class SupervisorCounts:
    """What the supervisor did (every backend reports it: the proof that this loop ran)."""

    moves: int = 0
    seeks: int = 0
    contacts: int = 0
    no_contacts: int = 0
    regulations: int = 0
    updates: int = 0
    settled: int = 0
    trips: int = 0
    let_through: int = 0
    stale_holds: int = 0


class ForceSupervisor:
    """The skill in flight (a move, a contact search, a regulation) and the trip latch.

    ``limits``: the guard's limits (the force limit bounds an unloading motion's force);
    ``tcp_to_sensor_rotation``: rotation tcp <- F/T sensor (maps readings into the base
    frame with the arm's pose). Not thread-safe by itself: a threaded backend serialises
    calls that change the skill (the hardware process does, with its gate lock).
    """

    def __init__(self, gains: ForceLoopGains, limits: SafetyLimits,
                 tcp_to_sensor_rotation: np.ndarray | None = None) -> None:
        self.gains = gains
        self.limits = limits
        self._r_tcp_sensor = np.eye(3) if tcp_to_sensor_rotation is None else np.asarray(tcp_to_sensor_rotation, float)
        self.motion: SupervisedMotion | None = None
        self.search: ContactSearch | None = None
        self.regulation: Regulation | None = None
        self.latch: TripLatch | None = None
        self.counts = SupervisorCounts()
        self._recent = np.zeros((max(1, gains.force_window), 3))
        self._recent_n = 0
        self._reg_t0_s = 0.0
        self._next_update_s = 0.0
        self._contact_threshold_n: float | None = None      # the last contact search's
        # The running search's force rise: the last sample below half its threshold and the
        # first at it, (t s, |F| N); at the contact, the touch's stiffness along the push.
        self._rise_below: tuple[float, float] | None = None
        self._rise_hit: tuple[float, float] | None = None
        self._touch: tuple[np.ndarray, float] | None = None  # (push direction, N/mm)
        self._newest_t_s: float | None = None               # the newest remembered sample's time

    # ------------------------------------------------------------------ what runs here
    def identity(self) -> dict:
        """This loop's identity: its code (a hash of this module) and its gains (journaled with
        the arm's identity: a dry run and a night on the arm can be shown to share them)."""
        return {"module": __name__, "class": type(self).__name__, "code_sha256": _CODE_SHA256,
                "gains": asdict(self.gains)}

    def describe(self) -> dict:
        """:meth:`identity` and what the loop did."""
        return {**self.identity(), "counts": asdict(self.counts)}

    # ------------------------------------------------------------------ commands
    def _begin(self, kind: str, direction_base: np.ndarray | None) -> SupervisedMotion:
        if kind != "regulate_force":
            self._touch = None                  # the probe leaves (or searches for) its contact
        self._rise_below = self._rise_hit = None
        old = self.motion
        if old is not None and old.active:
            old.finish(MotionState.STOPPED, "superseded")
        self.search = None
        self.regulation = None
        motion = SupervisedMotion(kind, direction_base, after_trip=self.latch is not None)
        self.motion = motion
        return motion

    def begin_move(self, start_mm: np.ndarray, target_mm: np.ndarray) -> SupervisedMotion:
        """A straight move from ``start_mm`` to ``target_mm`` (the device runs and times it)."""
        step = np.asarray(target_mm, float) - np.asarray(start_mm, float)
        length = float(np.linalg.norm(step))
        self.counts.moves += 1
        return self._begin("move_linear", step / length if length > 1e-9 else None)

    def begin_seek(self, direction: np.ndarray, speed_mm_s: float, threshold_n: float, max_distance_mm: float,
                   start_mm: np.ndarray, t_s: float | None = None) -> SupervisedMotion:
        """A contact search; the caller commands :meth:`ContactSearch.velocity_mm_s` at
        ``gains.seek_accel_mm_s2`` now (``t_s``), and :meth:`on_tick` repeats it every period."""
        if not (speed_mm_s > 0 and threshold_n > 0 and max_distance_mm > 0):
            raise MotionRefused("seek_contact needs a positive speed, force threshold and distance")
        d = _unit(direction)
        motion = self._begin("seek_contact", d)
        self.search = ContactSearch(d, float(speed_mm_s), float(threshold_n), float(max_distance_mm),
                                    np.asarray(start_mm, float).copy())
        self._contact_threshold_n = float(threshold_n)
        if t_s is not None:
            self._next_update_s = float(t_s) + self.gains.period_s
        self.counts.seeks += 1
        return motion

    def begin_regulation(self, direction: np.ndarray, target_n: float, rate_n_s: float, t_s: float,
                         force_n: float) -> SupervisedMotion:
        """A force regulation whose reference ramps from ``force_n`` (the force the loop reads
        now); its first update is due at ``t_s``.

        Directly after a regulation along the same push (nothing commanded between: the probe
        still presses the same contact), it starts from that one's stiffness estimate; directly
        after a contact search along it, from the touch's when stiffer than the guess; else
        from the guess."""
        if not (target_n >= 0 and rate_n_s > 0):
            raise MotionRefused("regulate_force needs a target >= 0 N and a positive rate")
        d = _unit(direction)
        before, touch = self.regulation, self._touch
        motion = self._begin("regulate_force", d)
        stiffness, measured = self.gains.initial_stiffness_n_mm, False
        if before is not None and before.stiffness_measured and float(before.direction @ d) >= _SAME_PUSH_COS:
            stiffness, measured = before.stiffness_n_mm, True
        elif touch is not None and float(touch[0] @ d) >= _SAME_PUSH_COS and touch[1] > stiffness:
            # The touch only ever makes the loop more careful: a softer contact's rise is
            # slow and its first ramp pair measures it well enough.
            stiffness, measured = touch[1], True
        self.regulation = Regulation(self.gains, d, float(target_n), float(rate_n_s), float(force_n),
                                     stiffness, stiffness_measured=measured)
        self._reg_t0_s = self._next_update_s = float(t_s)
        self.counts.regulations += 1
        return motion

    def stopped(self, note: str = "stop requested") -> None:
        """The controller stopped the arm: the current motion ends STOPPED."""
        self._end(MotionState.STOPPED, note)

    def faulted(self, note: str) -> None:
        """The arm refused or lost the motion (protective stop, e-stop, program stopped, link)."""
        self._end(MotionState.FAULT, note)

    def _end(self, state: MotionState, note: str) -> None:
        if self.motion is not None:
            self.motion.finish(state, note)
        self.search = None
        self.regulation = None

    # ------------------------------------------------------------------ the sensor path
    def remember(self, block: WrenchBlock) -> None:
        """Keep the latest force samples of ``block`` (N, sensor frame) for the loop's reading."""
        if not len(block):
            return
        self._newest_t_s = float(block.t_s[-1])
        force_n = block.force_n
        buf = self._recent
        k = min(force_n.shape[0], buf.shape[0])
        if k == 0:
            return
        if k == buf.shape[0]:
            buf[:] = force_n[-k:]
        else:
            buf[:-k] = buf[k:]
            buf[-k:] = force_n[-k:]
        self._recent_n = min(self._recent_n + k, buf.shape[0])

    def force_now_n(self) -> float:
        """The force the loop reads now (:func:`measured_force_n` of the remembered samples)."""
        return measured_force_n(self._recent[self._recent.shape[0] - self._recent_n:])

    def forget_samples(self) -> None:
        """A deliberate step in the stream (a tare): the old samples no longer apply."""
        self._recent_n = 0
        self._newest_t_s = None

    def first_contact(self, force_magnitude_n: np.ndarray) -> int | None:
        """Index of the first sample that ends a running contact search, or None."""
        s, m = self.search, self.motion
        if s is None or m is None or m.state() != MotionState.RUNNING:
            return None
        return s.first_contact(force_magnitude_n)

    def seek_samples(self, t_s: np.ndarray, force_magnitude_n: np.ndarray) -> None:
        """Samples the sensor delivered while a contact search runs (times s, |F| N, in order,
        up to the one that met the threshold): they give the touch's stiffness at the contact.
        The real-time backends' blocks come through :meth:`on_block`; the simulator calls this
        with each committed sub-chunk."""
        s = self.search
        if s is None or self._rise_hit is not None or not len(t_s):
            return
        f = np.asarray(force_magnitude_n, float)
        hit = np.flatnonzero(f >= s.threshold_n)
        end = int(hit[0]) if hit.size else f.size
        below = np.flatnonzero(f[:end] < 0.5 * s.threshold_n)
        if below.size:
            self._rise_below = (float(t_s[below[-1]]), float(f[below[-1]]))
        if hit.size:
            self._rise_hit = (float(t_s[end]), float(f[end]))

    def _touch_stiffness_n_mm(self, search: ContactSearch) -> float | None:
        """The stiffness (N/mm) the search's force rise shows: from the last sample below half
        the threshold to the first at it, at the search's speed; None without both."""
        if self._rise_below is None or self._rise_hit is None:
            return None
        (t0, f0), (t1, f1) = self._rise_below, self._rise_hit
        # On the microsecond grid: the difference of two float clock readings carries the
        # rounding of their absolute size, and a step must give the same numbers whenever
        # it runs (a resumed session replays it at another time).
        dt_s = round((t1 - t0) * 1e6) / 1e6
        if dt_s <= 0 or f1 <= f0:
            return None
        k = (f1 - f0) / (search.speed_mm_s * dt_s)
        return min(max(k, _STIFFNESS_RANGE_N_MM[0]), _STIFFNESS_RANGE_N_MM[1])

    def contact(self, note: str = "") -> None:
        """The search met its threshold (the caller stops the arm): CONTACT."""
        if self.motion is not None and self.search is not None:
            self.motion.finish(MotionState.CONTACT, note)
            self.counts.contacts += 1
            k = self._touch_stiffness_n_mm(self.search)
            self._touch = None if k is None else (self.search.direction, k)
        self.search = None

    def verdict(self, trip: Trip, peak_force_n: float) -> Verdict:
        """What the first crossing of a block calls for, the latch included.

        The first trip stops the arm (and latches, :meth:`tripped`). While latched, a crossing
        of the latched kind (any of the force kinds after a force trip) is let through for a
        motion commanded after the trip that unloads: it moves away from the contact
        (``direction . away > 0``, when the contact is known) and, for the force kinds, |F|
        stays within ``UNLOAD_RISE_FRACTION`` of the latched peak (or the limit, if higher;
        the peak follows the force while the arm stands stopped). Anything else that moves is
        stopped; with nothing moving there is nothing to stop.
        """
        latch, m = self.latch, self.motion
        if latch is None:
            return Verdict.STOP
        if m is not None and m.active and self._unloads(latch, m, trip, peak_force_n):
            self.counts.let_through += 1
            return Verdict.LET_THROUGH
        # The latched level follows the force while the arm stands stopped (a motion stopped
        # for pushing on adds to it): an unloading motion is judged against where it started.
        if trip.kind in FORCE_KINDS and peak_force_n > latch.peak_force_n:
            self.latch = replace(latch, peak_force_n=float(peak_force_n))
        return Verdict.STOP if m is not None and m.active else Verdict.IGNORE

    def _unloads(self, latch: TripLatch, m: SupervisedMotion, trip: Trip, peak_force_n: float) -> bool:
        force_kind = trip.kind in FORCE_KINDS
        if not m.after_trip or not (trip.kind == latch.kind or (force_kind and latch.kind in FORCE_KINDS)):
            return False
        if latch.away_base is not None:
            if m.direction_base is None or float(m.direction_base @ latch.away_base) <= 0.0:
                return False
        elif force_kind:
            return False            # a force with no known contact: nothing says this motion unloads it
        if force_kind:
            return peak_force_n <= (1.0 + UNLOAD_RISE_FRACTION) * max(latch.peak_force_n, self.limits.max_force_n)
        return True

    def tripped(self, trip: Trip, peak_force_n: float, force_base_n: np.ndarray | None) -> None:
        """The arm was stopped for ``trip``: the motion ends TRIPPED; the first trip latches.

        ``peak_force_n``: the largest |F| of the block that crossed; ``force_base_n``: the
        force the environment exerted on the tool at the trip, in the base frame (None if
        unknown). The contact to unload is the push of the contact search or regulation that
        tripped; else, when that force is at least the last contact search's threshold (the
        probe's own measure of being in contact), the direction it pushes the tool."""
        if self.latch is None:
            away = None
            if self.motion is not None and self.motion.kind in ("seek_contact", "regulate_force") \
                    and self.motion.direction_base is not None:
                away = -self.motion.direction_base
            elif force_base_n is not None and self._contact_threshold_n is not None:
                norm = float(np.linalg.norm(force_base_n))
                if norm >= self._contact_threshold_n:
                    away = np.asarray(force_base_n, float) / norm
            peak = max(float(trip.value) if trip.kind == "force" else 0.0, float(peak_force_n))
            self.latch = TripLatch(trip.kind, float(trip.t_s), peak, away)
            self.counts.trips += 1
        self._end(MotionState.TRIPPED, trip.message)

    def rearmed(self) -> None:
        """The guard was re-armed: forget the latch."""
        self.latch = None

    def force_base_n(self, base_to_tcp_rotation: np.ndarray) -> np.ndarray | None:
        """The latest remembered force (sensor frame) in the base frame at an arm orientation
        (base <- tcp), or None before any sample."""
        if not self._recent_n:
            return None
        return np.asarray(base_to_tcp_rotation, float) @ (self._r_tcp_sensor @ self._recent[-1])

    def on_block(self, block: WrenchBlock, trip: Trip | None) -> BlockVerdict:
        """The sensor path of a real-time backend, for one block the guard just checked
        (``trip``: its first crossing, or None): remember the samples, then what to do.

        A verdict with ``stop`` must be acted on before anything else; then call
        :meth:`tripped` (a trip) — the contact is already recorded."""
        contact_t: float | None = None
        peak = 0.0
        if len(block):
            fmag = force_magnitudes_n(block)
            contact_at = self.first_contact(fmag)
            self.seek_samples(block.t_s, fmag)
            self.remember(block)
            peak = float(fmag.max())
            if contact_at is not None:
                contact_t = float(block.t_s[contact_at])
        if trip is not None and (contact_t is None or trip.t_s <= contact_t):
            verdict = self.verdict(trip, peak)
            if verdict == Verdict.STOP:
                # Nothing of the skill may command the arm after this (the stop follows).
                self._end(MotionState.TRIPPED, trip.message)
                return BlockVerdict(stop=True, trip=trip, peak_force_n=peak)
            if verdict == Verdict.LET_THROUGH:
                return BlockVerdict(let_through=True, trip=trip)
            return BlockVerdict(trip=trip)
        if contact_t is not None:
            self.contact(f"contact at t={contact_t:.4f} s")
            return BlockVerdict(stop=True, contact_t_s=contact_t)
        return BlockVerdict()

    # ------------------------------------------------------------------ the control path
    def search_exhausted(self, position_mm: np.ndarray) -> bool:
        """True (and NO_CONTACT: the caller stops the arm) once a running contact search has
        travelled its distance; else updates its progress."""
        s, m = self.search, self.motion
        if s is None or m is None or m.state() != MotionState.RUNNING:
            return False
        travelled = s.travelled_mm(position_mm)
        m.set_progress(travelled / s.max_distance_mm)
        if travelled < s.max_distance_mm - 1e-9:         # a position's round trip is not exact
            return False
        m.finish(MotionState.NO_CONTACT, f"no contact within {s.max_distance_mm:.1f} mm")
        self.search = None
        self.counts.no_contacts += 1
        return True

    @property
    def next_update_s(self) -> float | None:
        """When the next speed command of the running regulation or contact search is due (s),
        None without one."""
        return self._next_update_s if (self.regulation is not None or self.search is not None) else None

    def regulate(self, elapsed_s: float, force_n: float, u_mm: float, sample_age_s: float = 0.0) -> float:
        """One update of the running regulation, ``elapsed_s`` after it began: the speed along
        its direction (mm/s); the motion is DONE once settled. ``sample_age_s``: how old the
        newest F/T sample is; beyond ``STALE_PERIODS`` periods the loop commands no speed and
        keeps its state (it does not push on an old force)."""
        reg = self.regulation
        assert reg is not None, "no regulation runs"
        if sample_age_s > STALE_PERIODS * self.gains.period_s:
            self.counts.stale_holds += 1
            return 0.0
        speed = reg.update(elapsed_s, force_n, u_mm)
        self.counts.updates += 1
        m = self.motion
        if m is not None and m.state() == MotionState.RUNNING:
            m.set_progress(reg.progress())
            if reg.settled:
                m.settle()
                self.counts.settled += 1
        return speed

    def on_tick(self, t_s: float, position_mm: np.ndarray, force_n: float | None = None) -> TickCommand:
        """The control path of a real-time backend at ``t_s`` (s) with the arm at
        ``position_mm`` (base): the search's distance, and once per period (on schedule from
        the start; a late tick does not make up for missed ones) the speed command: the
        search's again (a speed command lost on its way must not leave the probe standing
        short of the surface) or the regulation's update from ``force_n`` (default:
        :meth:`force_now_n`)."""
        if self.search_exhausted(position_mm):
            return TickCommand(stop=True)
        reg, search = self.regulation, self.search
        if (reg is None and search is None) or t_s < self._next_update_s - 1e-9:
            return TickCommand()
        period = self.gains.period_s
        self._next_update_s += period
        if self._next_update_s <= t_s:
            self._next_update_s = t_s + period
        if search is not None:
            return TickCommand(velocity_mm_s=search.velocity_mm_s(), accel_mm_s2=self.gains.seek_accel_mm_s2)
        assert reg is not None
        age = 0.0 if self._newest_t_s is None else t_s - self._newest_t_s
        force = self.force_now_n() if force_n is None else float(force_n)
        speed = self.regulate(t_s - self._reg_t0_s, force, float(np.asarray(position_mm, float) @ reg.direction), age)
        return TickCommand(velocity_mm_s=reg.direction * speed, accel_mm_s2=self.gains.accel_mm_s2)

    def contact_began(self) -> None:
        """A new contact began under a running regulation (the simulator sees it happen)."""
        if self.regulation is not None:
            self.regulation.contact_began()


__all__ = ["ForceLoopGains", "ForceSupervisor", "Regulation", "ContactSearch", "TripLatch", "Verdict",
           "SupervisedMotion", "BlockVerdict", "TickCommand", "SupervisorCounts", "measured_force_n",
           "force_magnitudes_n", "UNLOAD_RISE_FRACTION", "FORCE_KINDS"]
