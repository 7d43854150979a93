"""The check-and-stop path: safety limits over blocks of F/T samples.

UR's own force limit has a 25 N tolerance, so probing limits are enforced here,
from the ATI reading. :meth:`SafetyGuard.check_block` is vectorised over a block
and returns the FIRST crossing of any limit; the owner of the F/T stream and the
arm driver calls it where the data arrives and stops the arm at once, then tells
the state machine. The simulator runs the same function inside its step, in
virtual time.

Checks: |F|, |T|, the force perpendicular to the probe axis (bending load on the
probe), the force rate (over a short window, because a per-sample difference of
noisy 1 kHz data is mostly noise), a device status word, a frozen stream (every
channel bit-identical for ``ft_frozen_ms``: a live sensor always has noise) and,
separately, a stale stream (no sample for ``ft_stale_ms``) and tip slip.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from .devices import Trip, WrenchBlock


@dataclass(frozen=True)
class SafetyLimits:
    """Limits of one cell (a plan may only tighten them). Units in the names."""

    max_force_n: float
    max_torque_nm: float
    max_lateral_force_n: float
    max_force_rate_n_s: float
    ft_stale_ms: float
    ft_frozen_ms: float
    slip_mm: float
    rearm_fraction: float = 0.8
    rate_window_ms: float = 10.0

    def tightened(self, **overrides: float | None) -> "SafetyLimits":
        """A copy with some limits lowered; raises ValueError if any would loosen."""
        values = dict(self.__dict__)
        for name, value in overrides.items():
            if value is None:
                continue
            if name not in values:
                raise ValueError(f"unknown limit {name!r}")
            if name in ("rearm_fraction", "rate_window_ms"):
                raise ValueError(f"{name} is a cell property, not a limit a plan can set")
            if value > values[name]:
                raise ValueError(f"{name} = {value} is looser than the cell's {values[name]}")
            values[name] = float(value)
        return SafetyLimits(**values)


class SafetyGuard:
    """Stateful, vectorised limit checker for one F/T stream.

    ``probe_axis_sensor`` is the probe axis (unit vector) in the sensor frame; the
    force perpendicular to it is the bending load on the probe.
    """

    def __init__(self, limits: SafetyLimits, probe_axis_sensor: np.ndarray = np.array([0.0, 0.0, 1.0]),
                 rate_hz: float = 1000.0, history_s: float = 3.0) -> None:
        self.limits = limits
        axis = np.asarray(probe_axis_sensor, dtype=float)
        self._axis = axis / np.linalg.norm(axis)
        self._rate_window = max(1, int(round(limits.rate_window_ms * 1e-3 * rate_hz)))
        self._frozen_samples = max(2, int(round(limits.ft_frozen_ms * 1e-3 * rate_hz)))
        # Carry-over between blocks: the last samples (for the rate window) and the
        # current run of identical readings (for the frozen detector).
        self._prev_t_s = np.zeros(0)
        self._prev_fmag_n = np.zeros(0)
        self._last_row: np.ndarray | None = None
        self._same_run = 0
        self._last_sample_t_s: float | None = None
        self._last_fmag_n = 0.0
        self._last_tmag_nm = 0.0
        self._history: deque[WrenchBlock] = deque()
        self._history_s = history_s
        self.tripped: Trip | None = None

    # -- the hot path -----------------------------------------------------------------
    def check_block(self, block: WrenchBlock) -> Trip | None:
        """Check every sample of ``block``; return the earliest crossing, or None."""
        n = len(block)
        if n == 0:
            return None
        self._remember(block)
        lim = self.limits
        f = block.force_n
        t = block.torque_nm
        fmag = np.sqrt(np.einsum("ij,ij->i", f, f))
        tmag = np.sqrt(np.einsum("ij,ij->i", t, t))
        along = f @ self._axis
        lateral = np.sqrt(np.maximum(fmag * fmag - along * along, 0.0))

        # Force rate over a window of samples, continuing the previous block.
        all_t = np.concatenate([self._prev_t_s, block.t_s])
        all_f = np.concatenate([self._prev_fmag_n, fmag])
        w = self._rate_window
        first = len(self._prev_t_s)
        idx = np.arange(first, first + n)
        back = np.maximum(idx - w, 0)
        dt = all_t[idx] - all_t[back]
        with np.errstate(divide="ignore", invalid="ignore"):
            rate = np.where(dt > 0, np.abs(all_f[idx] - all_f[back]) / np.where(dt > 0, dt, 1.0), 0.0)
        keep = max(w, 1)
        self._prev_t_s = all_t[-keep:]
        self._prev_fmag_n = all_f[-keep:]

        # Frozen stream: runs of bit-identical 6-channel readings.
        rows = np.concatenate([f, t], axis=1)
        same = np.empty(n, dtype=bool)
        same[0] = self._last_row is not None and bool(np.array_equal(rows[0], self._last_row))
        if n > 1:
            same[1:] = np.all(rows[1:] == rows[:-1], axis=1)
        run = _run_lengths(same, self._same_run)
        self._same_run = int(run[-1])
        self._last_row = rows[-1].copy()

        checks = (
            ("force", fmag, lim.max_force_n, "N", fmag > lim.max_force_n),
            ("torque", tmag, lim.max_torque_nm, "N·m", tmag > lim.max_torque_nm),
            ("lateral_force", lateral, lim.max_lateral_force_n, "N", lateral > lim.max_lateral_force_n),
            ("force_rate", rate, lim.max_force_rate_n_s, "N/s", rate > lim.max_force_rate_n_s),
            ("frozen", run.astype(float), float(self._frozen_samples), "samples", run >= self._frozen_samples),
            ("ft_status", block.status.astype(float), 0.0, "", block.status != 0),
        )
        best: tuple[int, str, np.ndarray, float, str] | None = None
        for kind, values, limit, unit, crossed in checks:
            if crossed.any():
                i = int(np.argmax(crossed))
                if best is None or i < best[0]:
                    best = (i, kind, values, limit, unit)
        self._last_sample_t_s = float(block.t_s[-1])
        self._last_fmag_n = float(fmag[-1])
        self._last_tmag_nm = float(tmag[-1])
        if best is None:
            return None
        i, kind, values, limit, unit = best
        value = float(values[i])
        if kind == "ft_status":
            message = f"F/T status word 0x{int(block.status[i]):08x} (sensor reports an error)"
        elif kind == "frozen":
            message = f"F/T stream frozen: {int(value)} identical samples (limit {limit:.0f})"
        else:
            message = f"{kind.replace('_', ' ')} {value:.3g} {unit} exceeds {limit:.3g} {unit}"
        return self._trip(kind, float(block.t_s[i]), value, float(limit), message)

    # -- checks that are not per-sample -------------------------------------------------
    def check_stale(self, now_s: float) -> Trip | None:
        """Trip when no sample arrived for longer than ``ft_stale_ms``."""
        if self._last_sample_t_s is None:
            return None
        age_ms = (now_s - self._last_sample_t_s) * 1e3
        if age_ms > self.limits.ft_stale_ms:
            return self._trip("stale", now_s, age_ms, self.limits.ft_stale_ms,
                              f"F/T stream stale: no sample for {age_ms:.0f} ms (limit {self.limits.ft_stale_ms:.0f} ms)")
        return None

    def check_slip(self, tip_slip_mm: float, t_s: float) -> Trip | None:
        """Trip when the tip has slid along the surface farther than ``slip_mm``."""
        if abs(tip_slip_mm) > self.limits.slip_mm:
            return self._trip("slip", t_s, abs(tip_slip_mm), self.limits.slip_mm,
                              f"tip slipped {abs(tip_slip_mm):.2f} mm along the surface (limit {self.limits.slip_mm} mm)")
        return None

    def mark_connection_lost(self, t_s: float, what: str) -> Trip:
        return self._trip("connection", t_s, 0.0, 0.0, what)

    # -- hysteresis -----------------------------------------------------------------------
    def can_rearm(self) -> bool:
        """True when the latest reading is below the hysteresis level of every limit."""
        k = self.limits.rearm_fraction
        return (self._last_fmag_n < k * self.limits.max_force_n
                and self._last_tmag_nm < k * self.limits.max_torque_nm)

    def rearm(self) -> bool:
        """Clear the trip if below the hysteresis level (the caller also requires a state change)."""
        if self.tripped is not None and not self.can_rearm():
            return False
        self.tripped = None
        self._same_run = 0
        return True

    def note_stream_restart(self) -> None:
        """Forget carry-over state after a deliberate gap (e.g. a tare or a reconnect)."""
        self._prev_t_s = np.zeros(0)
        self._prev_fmag_n = np.zeros(0)
        self._last_row = None
        self._same_run = 0
        self._last_sample_t_s = None

    def raw_history(self) -> WrenchBlock:
        """The raw samples of the last ``history_s`` seconds (kept with every fault)."""
        return WrenchBlock.concat(list(self._history)).tail(self._history_s)

    # -- internals --------------------------------------------------------------------------
    def _remember(self, block: WrenchBlock) -> None:
        self._history.append(block)
        newest = float(block.t_s[-1])
        while self._history and float(self._history[0].t_s[-1]) < newest - self._history_s:
            self._history.popleft()

    def _trip(self, kind: str, t_s: float, value: float, limit: float, message: str) -> Trip:
        trip = Trip(kind=kind, t_s=t_s, value=value, limit=limit, message=message, raw=self.raw_history())
        if self.tripped is None:
            self.tripped = trip
        return trip


def stream_health_guard(limits: SafetyLimits, rate_hz: float) -> SafetyGuard:
    """A guard over the F/T stream's health only: frozen, stale, a device status word and the
    force rate; the load limits (force, torque, lateral force) are lifted.

    Why: after a fault the probe may still press on the object (the load is what the retract
    removes), but a retract started while the stream is still frozen or still ringing from a
    spike trips again on the same fault. Samples this guard passes are fresh."""
    lifted = replace(limits, max_force_n=math.inf, max_torque_nm=math.inf, max_lateral_force_n=math.inf)
    return SafetyGuard(lifted, rate_hz=rate_hz)


def _run_lengths(same_as_previous: np.ndarray, carried: int) -> np.ndarray:
    """Length of the run of identical readings ending at each sample (1 = not repeated)."""
    n = same_as_previous.shape[0]
    idx = np.arange(n)
    # Index where the current run started (last sample that was NOT a repeat).
    starts = np.where(same_as_previous, -1, idx)
    np.maximum.accumulate(starts, out=starts)
    run = idx - starts + 1
    # Runs that began before this block continue the carried count.
    continuing = starts < 0
    run[continuing] = carried + idx[continuing] + 1
    return run
