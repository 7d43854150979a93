"""Fault injection for the simulated cell (docs/design.md §8 "Faults on demand").

A :class:`FaultPlan` says what and when: at a step index (first attempt only, so a
retry can succeed), at a virtual time, at a rate per 100 steps drawn from the
keyed RNG (seed, step, attempt, FAULTS), or as a follow-up: at a rate per 100 faults,
drawn each time another fault fires and due ``delay_s`` (drawn 0.3-3 s) after it —
while the controller stops, unloads and retracts from the first. Within a step the
fault fires ``delay_s`` after ``begin_step`` (drawn from the keyed RNG when not given).
A follow-up never has follow-ups of its own.

Every fault is visible only through what a real device would show: F/T data (a
spike, repeated values, missing samples), status bits (protective stop, emergency
stop, connected), missing scans, exceptions from commands (DeviceError while the
connection is lost), and the physics (object moved: contact early, late or never;
slip: the tip slides and the slip monitor trips). The controller-facing devices have
no attribute that tells. Disk errors are decided here (same schedule as every fault)
but played by the controller's journal write: the session asks
:meth:`FaultInjector.take_disk_error` before committing a step.

Rate faults are drawn only under real step keys (a probe step or the sweep), never
under the start-up key: a process's start is not a step, and a resumed process would
otherwise meet the same start-up fault every time.

Ground truth that survives a kill: with ``ELASTOPROBE_SIM_FAULT_LOG=path`` set, every
fault that fires appends one JSON line (pid, kind, virtual time, step key, plan index)
to ``path``, and faults whose effect depends on what the controller does (a scanner
fault needs a scan request, a slip needs a contact) append an ``effect`` line the first
time they change what a device shows; a stop, e-stop or lost connection that fires while
the arm already shows it, or an F/T fault while the tripped guard holds the arm (a
follow-up during the first one's recovery), is marked ``"effective": false``. The soak reads it (bench/soak.py); the in-memory
:attr:`FaultInjector.injected` dies with a killed process.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from elastoprobe.controller.core.errors import DeviceError
from elastoprobe.controller.core.faultkinds import INJECTED_FAULT_NAMES, InjectedFault

from .world import PRE_STEP, US_PER_S, Stream, keyed_rng

if TYPE_CHECKING:   # pragma: no cover
    from .world import Contact, SimWorld


# Defaults per kind: (duration_s, magnitude). Magnitudes: spike N, object shift mm, slip mm/s,
# short burst: fraction of the profiles delivered.
_DEFAULTS: dict[str, tuple[float, float]] = {
    InjectedFault.FORCE_SPIKE: (0.005, 80.0),
    InjectedFault.FT_STALL: (0.25, 0.0),
    InjectedFault.FT_FROZEN: (0.25, 0.0),
    InjectedFault.SCANNER_TIMEOUT: (math.inf, 0.0),
    InjectedFault.SCANNER_SHORT_BURST: (math.inf, 0.5),
    InjectedFault.PROTECTIVE_STOP: (0.0, 0.0),
    InjectedFault.CONNECTION_LOSS: (1.0, 0.0),
    InjectedFault.EMERGENCY_STOP: (math.inf, 0.0),
    InjectedFault.OBJECT_MOVED: (0.0, 12.0),
    InjectedFault.SLIP: (math.inf, 20.0),
    InjectedFault.DISK_ERROR: (0.0, 0.0),
}

FAULT_LOG_ENV = "ELASTOPROBE_SIM_FAULT_LOG"
# Streams of the follow-up draws: one per fault fired in a step (above every Stream id).
_FOLLOW_UP_STREAM = 1000
# Kinds that may fire without changing anything a device shows (no scan, no contact).
_CONDITIONAL = ("scanner_timeout", "scanner_short_burst", "slip")


@dataclass(frozen=True)
class FaultPlan:
    """One scheduled fault; exactly one of ``step``, ``at_t_s``, ``rate_per_100_steps``."""

    kind: str
    step: int | None = None
    at_t_s: float | None = None
    rate_per_100_steps: float | None = None
    rate_per_100_faults: float | None = None   # a follow-up of other faults
    delay_s: float | None = None          # after begin_step (step and rate faults); after the other fault
    duration_s: float | None = None
    magnitude: float | None = None
    clear_after_s: float | None = None    # emergency stop: the operator clears it after this

    def __post_init__(self) -> None:
        if self.kind not in INJECTED_FAULT_NAMES:
            raise ValueError(f"unknown fault kind {self.kind!r}")
        # The plain name: records, logs and comparisons see what the cell file said.
        object.__setattr__(self, "kind", InjectedFault(self.kind).value)
        given = [x is not None for x in (self.step, self.at_t_s, self.rate_per_100_steps, self.rate_per_100_faults)]
        if sum(given) != 1:
            raise ValueError("give exactly one of step, at_t_s, rate_per_100_steps, rate_per_100_faults")
        if self.rate_per_100_faults is not None and self.kind == "disk_error":
            raise ValueError("a disk error cannot be a follow-up (it is played at a journal write)")


@dataclass
class _Active:
    kind: str
    start_us: int
    end_us: float          # may be inf
    magnitude: float
    clear_us: float = math.inf
    fired: bool = False
    vector: np.ndarray | None = None
    key: tuple[int, int, int] | None = None     # the step key it was drawn under (None: on demand)
    plan_index: int | None = None
    effective: bool = False
    follows: str | None = None                  # the kind of the fault it follows up


def _append_record(record: dict) -> None:
    """One line of the durable fault record (``ELASTOPROBE_SIM_FAULT_LOG``), if asked for.

    Written and closed per line: a SIGKILL after the write loses nothing (the page
    cache keeps it); faults are rare, so the cost does not matter."""
    path = os.environ.get(FAULT_LOG_ENV)
    if not path:
        return
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps({"pid": os.getpid(), **record}) + "\n")


class FaultInjector:
    """Schedules faults and applies them through the world's devices."""

    def __init__(self, world: "SimWorld", plans: list[FaultPlan] | None = None) -> None:
        self._world = world
        self._plans = list(plans or [])
        self._active: list[_Active] = []
        self._at_time_done: set[int] = set()
        self._connected = True
        self._disk_due: set[tuple[int, int, int]] = set()   # step keys whose journal write fails
        self._disk_plan_index: dict[tuple[int, int, int], int | None] = {}
        self._fired_in_key = 0                              # faults fired since begin_step: follow-up draws
        self.injected: list[tuple[str, float]] = []   # (kind, virtual time s): for tests and reports

    # ------------------------------------------------------------------ operator and schedule
    def inject(self, kind: str, delay_s: float = 0.0, duration_s: float | None = None,
               magnitude: float | None = None, clear_after_s: float | None = None) -> None:
        """Inject a fault now (+ delay) on demand."""
        start = self._world.now_us + int(round(delay_s * US_PER_S))
        self._schedule(kind, start, duration_s, magnitude, clear_after_s, np.random.default_rng(0))

    def operator_clear_estop(self) -> None:
        """An operator releases the emergency stop (never done automatically)."""
        self._active = [a for a in self._active if a.kind != "emergency_stop"]
        self._world.arm._sim_clear_estop()

    def take_disk_error(self, step_id: int, attempt: int) -> bool:
        """Whether the journal write of ``step_id`` (at retry ``attempt``) fails now; True
        once per scheduled disk error, which is then recorded as injected."""
        key = (self._world.step_key[0], int(step_id), int(attempt))
        if key not in self._disk_due:
            return False
        self._disk_due.discard(key)
        t_s = self._world.now_us / US_PER_S
        self.injected.append(("disk_error", t_s))
        _append_record({"event": "injected", "kind": "disk_error", "t_s": t_s, "key": list(key),
                        "plan": self._disk_plan_index.get(key)})
        return True

    def _schedule(self, kind: str, start_us: int, duration_s: float | None, magnitude: float | None,
                  clear_after_s: float | None, rng: np.random.Generator,
                  key: tuple[int, int, int] | None = None, plan_index: int | None = None,
                  follows: str | None = None) -> None:
        if kind == "disk_error":
            # The controller's journal plays it, at this step's write (see take_disk_error).
            if key is not None:
                self._disk_due.add(key)
                self._disk_plan_index[key] = plan_index
            return
        d_default, m_default = _DEFAULTS[kind]
        duration = d_default if duration_s is None else duration_s
        end = math.inf if math.isinf(duration) else start_us + int(round(duration * US_PER_S))
        act = _Active(kind, start_us, end, m_default if magnitude is None else magnitude,
                      key=key, plan_index=plan_index, follows=follows)
        if clear_after_s is not None:
            act.clear_us = start_us + int(round(clear_after_s * US_PER_S))
        if kind == "object_moved":
            phi = rng.uniform(0.0, 2.0 * math.pi)
            act.vector = act.magnitude * np.array([math.cos(phi), math.sin(phi), 0.0])
        self._active.append(act)

    # ------------------------------------------------------------------ world hooks
    def _sim_begin_step(self) -> None:
        w = self._world
        seed, step, attempt = w.step_key
        rng = w.rng(Stream.FAULTS)
        self._fired_in_key = 0
        # Faults scoped to a step (scanner, slip) end with it.
        self._active = [a for a in self._active if a.kind not in ("scanner_timeout", "scanner_short_burst", "slip")
                        or a.start_us > w.now_us]
        for i, plan in enumerate(self._plans):
            draw = rng.random()          # always drawn, so one plan never shifts another's numbers
            delay = rng.uniform(0.2, 2.0)
            if plan.step is not None:
                due = plan.step == step and attempt == 0
            elif plan.rate_per_100_steps is not None:
                due = step != PRE_STEP and draw < plan.rate_per_100_steps / 100.0
            else:
                continue
            if due:
                start = w.now_us + int(round((plan.delay_s if plan.delay_s is not None else delay) * US_PER_S))
                self._schedule(plan.kind, start, plan.duration_s, plan.magnitude, plan.clear_after_s, rng,
                               key=(seed, step, attempt), plan_index=i)

    def _sim_bound_end(self, now_us: int, end_us: int) -> int:
        """Cut sub-chunks where a fault starts or ends."""
        best = end_us
        for a in self._active:
            for t in (a.start_us, a.end_us, a.clear_us):
                if now_us < t < best:
                    best = int(t)
        for i, plan in enumerate(self._plans):
            if plan.at_t_s is not None and i not in self._at_time_done:
                t = int(round(plan.at_t_s * US_PER_S))
                if now_us < t < best:
                    best = t
        grid = self._world.sample_period_us
        return best + (-best) % grid if best != end_us else end_us

    def _sim_on_time(self, now_us: int) -> None:
        """Fire faults due at ``now_us`` and end those that are over."""
        w = self._world
        for i, plan in enumerate(self._plans):
            if plan.at_t_s is not None and i not in self._at_time_done and now_us >= int(round(plan.at_t_s * US_PER_S)):
                self._at_time_done.add(i)
                self._schedule(plan.kind, now_us, plan.duration_s, plan.magnitude, plan.clear_after_s,
                               w.rng(Stream.FAULTS), plan_index=i)
        for a in list(self._active):
            if not a.fired and now_us >= a.start_us:
                a.fired = True
                a.effective = a.kind not in _CONDITIONAL
                self.injected.append((a.kind, now_us / US_PER_S))
                record = {"event": "injected", "kind": a.kind, "t_s": now_us / US_PER_S,
                          "key": None if a.key is None else list(a.key), "plan": a.plan_index}
                if a.follows is not None:
                    record["follows"] = a.follows
                if self._already_so(a.kind):
                    record["effective"] = False       # a second stop of a stopped arm changes nothing
                _append_record(record)
                self._fire(a, now_us)
                if a.follows is None:
                    self._follow_ups(a, now_us)
            if a.fired and now_us >= a.end_us:
                self._expire(a)
            elif a.fired and now_us >= a.clear_us and a.kind == "emergency_stop":
                self.operator_clear_estop()

    def _follow_ups(self, parent: _Active, now_us: int) -> None:
        """Draw the follow-up plans after ``parent`` fired (keyed by the step and how many
        faults fired in it before, so a resumed process draws the same)."""
        follow = [(i, p) for i, p in enumerate(self._plans) if p.rate_per_100_faults is not None]
        if not follow:
            return
        seed, step, attempt = self._world.step_key
        rng = keyed_rng(seed, step, attempt, _FOLLOW_UP_STREAM + self._fired_in_key)
        self._fired_in_key += 1
        for i, plan in follow:
            draw, delay = rng.random(), rng.uniform(0.3, 3.0)      # always drawn: plans stay independent
            if draw < float(plan.rate_per_100_faults) / 100.0:
                start = now_us + int(round((plan.delay_s if plan.delay_s is not None else delay) * US_PER_S))
                self._schedule(plan.kind, start, plan.duration_s, plan.magnitude, plan.clear_after_s, rng,
                               key=parent.key if parent.key is not None else self._world.step_key, plan_index=i,
                               follows=parent.kind)

    def _already_so(self, kind: str) -> bool:
        """Whether the arm already shows what ``kind`` would make it show (stopped, e-stopped,
        disconnected; for an F/T fault: the safety guard has tripped and holds the arm until
        it is re-armed): then firing it changes nothing any device shows."""
        arm = self._world.arm
        if kind in ("force_spike", "ft_stall", "ft_frozen"):
            return self._world.trip is not None
        if kind == "protective_stop":
            return arm._protective_since_us is not None or arm._estop
        if kind == "emergency_stop":
            return bool(arm._estop)
        if kind == "connection_loss":
            return not self._connected
        return False

    def _fire(self, a: _Active, now_us: int) -> None:
        arm = self._world.arm
        if a.kind == "protective_stop":
            arm._sim_protective_stop(now_us, "injected protective stop")
        elif a.kind == "emergency_stop":
            arm._sim_emergency_stop(now_us)
        elif a.kind == "connection_loss":
            self._connected = False
            arm._sim_connection_lost(now_us)
        elif a.kind == "object_moved":
            self._world.move_object(a.vector)

    def _expire(self, a: _Active) -> None:
        if a in self._active:
            self._active.remove(a)
        if a.kind == "connection_loss" and not any(x.kind == "connection_loss" and x.fired for x in self._active):
            self._connected = True
            self._world.arm._sim_connection_restored()

    def _sim_any_active(self) -> bool:
        return bool(self._active)

    def _sim_frozen_possible(self) -> bool:
        return any(a.kind == "ft_frozen" for a in self._active)

    def _window(self, kind: str, ts_us: np.ndarray) -> np.ndarray | None:
        mask = None
        for a in self._active:
            if a.kind == kind:
                m = (ts_us >= a.start_us) & (ts_us < a.end_us)
                mask = m if mask is None else (mask | m)
        return mask

    def _sim_ft_spike(self, ts_us: np.ndarray) -> np.ndarray | None:
        """Force added to the F/T samples (n, 3): a half-sine pulse pressing along sensor -z."""
        out = None
        for a in self._active:
            if a.kind != "force_spike":
                continue
            m = (ts_us >= a.start_us) & (ts_us <= a.end_us)
            if not m.any():
                continue
            span = max(a.end_us - a.start_us, 1)
            phase = np.clip((ts_us - a.start_us) / span, 0.0, 1.0)
            pulse = np.where(m, a.magnitude * np.sin(np.pi * phase), 0.0)
            if not pulse.any():
                pulse = np.where(m, a.magnitude, 0.0)
            add = np.zeros((ts_us.shape[0], 3))
            add[:, 2] = -pulse
            out = add if out is None else out + add
        return out

    def _sim_ft_frozen(self, ts_us: np.ndarray) -> np.ndarray | None:
        return self._window("ft_frozen", ts_us)

    def _sim_ft_stalled(self, ts_us: np.ndarray) -> np.ndarray:
        mask = self._window("ft_stall", ts_us)
        return np.zeros(ts_us.shape[0], dtype=bool) if mask is None else mask

    def _sim_slip_mm(self, ts_us: np.ndarray, contact: "Contact") -> np.ndarray:
        """Extra tangential sliding of the tip (mm) while a slip fault is active."""
        extra = np.zeros(ts_us.shape[0])
        for a in self._active:
            if a.kind == "slip" and a.fired:
                since = max(a.start_us, contact.started_us)
                add = a.magnitude * np.maximum(ts_us - since, 0) / US_PER_S
                if add.any():
                    self._mark_effective(a)
                extra += add
        return extra

    def _mark_effective(self, a: _Active) -> None:
        """The first time a conditional fault changes what a device shows."""
        if not a.effective:
            a.effective = True
            _append_record({"event": "effect", "kind": a.kind, "t_s": self._world.now_us / US_PER_S,
                            "key": None if a.key is None else list(a.key), "plan": a.plan_index})

    def _sim_scanner_limit(self, requested: int) -> int:
        """How many profiles of a burst the scanner will actually deliver now."""
        now = self._world.now_us
        count = requested
        for a in self._active:
            if a.start_us <= now < a.end_us:
                if a.kind == "scanner_timeout":
                    count = 0
                    self._mark_effective(a)
                elif a.kind == "scanner_short_burst":
                    count = min(count, int(requested * a.magnitude))
                    if count < requested:
                        self._mark_effective(a)
        return count

    def _sim_connected(self) -> bool:
        return self._connected

    def _sim_check_connection(self, what: str) -> None:
        if not self._connected:
            raise DeviceError(f"{what}: connection to the robot lost")
