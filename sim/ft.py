"""Simulated 6-axis F/T sensor on the flange (implements ForceTorqueSensor).

1 kHz samples with time stamps (virtual time) and unwrapped sequence numbers. What a
sample contains, in the sensor frame (``WrenchBlock`` convention: the load ON the
tool, pressing gives a negative z):

    contact reaction (+ its torque about the sensor origin, applied at the tip)
  + payload gravity (mass and centre of mass from the cell; miscalibrated if asked)
  + bias (per seed) + drift (a per-step random rate, restarting at begin_step)
  + white noise (per-step keyed stream, paged so grouping never changes the draws)
  -> saturation: each channel clipped at the sensor range (status word bit set)
  -> software tare (subtracted by the "driver": :meth:`tare`)
  -> faults (spike, frozen values, stalled stream) from the injector.

``read_block`` returns every sample since the previous call (a bounded buffer: an
unread backlog beyond ``buffer_s`` is lost, as UDP datagrams are).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from elastoprobe.controller.core.devices import DeviceIdentity, WrenchBlock
from elastoprobe.controller.core.geometry import Pose

from .world import US_PER_S, PagedNormal, Stream

if TYPE_CHECKING:   # pragma: no cover
    from .world import SimWorld

GRAVITY_MM_S2 = np.array([0.0, 0.0, -9.80665])   # m/s^2 in the base frame (N per kg)
STATUS_SATURATED = 0x0002_0000


@dataclass(frozen=True)
class FTSettings:
    """Noise and range of the simulated sensor (units in the names)."""

    noise_n: float = 0.04
    noise_nm: float = 0.002
    drift_n_per_h: float = 0.2
    drift_nm_per_h: float = 0.01
    bias_n: float = 1.5                   # per-seed constant offset (removed by tare)
    bias_nm: float = 0.05
    range_n: float = 290.0
    range_nm: float = 10.0
    rate_hz: float = 1000.0
    buffer_s: float = 10.0
    tare_samples: int = 16


@dataclass
class FTSamples:
    """A sub-chunk of samples before commit (``delivered`` False: lost in a stalled stream)."""

    ts_us: np.ndarray
    seq: np.ndarray
    raw: np.ndarray          # (n, 6) untared, after saturation
    out: np.ndarray          # (n, 6) what the driver delivers (tared, faults applied)
    status: np.ndarray
    delivered: np.ndarray
    all_delivered: bool = True
    fmag: np.ndarray | None = None      # |F| of ``out`` (N)
    tmag2: np.ndarray | None = None     # |T|^2 of ``out`` (N·m)^2
    status_clear: bool = False          # True: every status word is 0 (nothing saturated)

    def block(self, cut: int) -> WrenchBlock:
        if self.all_delivered:
            out = self.out[:cut]
            return WrenchBlock(self.ts_us[:cut] / US_PER_S, self.seq[:cut], out[:, :3], out[:, 3:],
                               self.status[:cut])
        keep = self.delivered[:cut]
        out = self.out[:cut][keep]
        return WrenchBlock(self.ts_us[:cut][keep] / US_PER_S, self.seq[:cut][keep], out[:, :3], out[:, 3:],
                           self.status[:cut][keep])

    def magnitudes_n(self) -> np.ndarray:
        """|F| of each sample as the driver sees it (0 for samples that never arrived)."""
        if self.all_delivered:
            return self.fmag
        return np.where(self.delivered, self.fmag, 0.0)


class SimForceTorque:
    """The simulated sensor; the world feeds it, the controller reads it."""

    def __init__(self, world: "SimWorld", tcp_to_sensor: Pose, payload_mass_kg: float,
                 payload_com_tcp_mm: np.ndarray, settings: FTSettings = FTSettings(),
                 serial: str = "SIM-FT-45-0001") -> None:
        self._world = world
        self._s = settings
        self._serial = serial
        self._r_ts = tcp_to_sensor.rotation
        sensor_from_tcp = tcp_to_sensor.inverse()
        self._tip_in_sensor_mm = sensor_from_tcp.apply(np.zeros(3))
        self._mass_kg = float(payload_mass_kg)
        self._com_sensor_mm = sensor_from_tcp.apply(np.asarray(payload_com_tcp_mm, float))
        self._period_us = int(round(US_PER_S / settings.rate_hz))
        if self._period_us != world.sample_period_us:
            raise ValueError("the F/T rate must match the world's sample period")
        rng = world.constants_rng()
        self._bias = np.concatenate([rng.normal(0.0, settings.bias_n, 3), rng.normal(0.0, settings.bias_nm, 3)])
        self._sigma = np.array([settings.noise_n] * 3 + [settings.noise_nm] * 3)
        self._range = np.array([settings.range_n] * 3 + [settings.range_nm] * 3)
        self._range_min = float(self._range.min())
        self._noise = PagedNormal(6)
        self._drift_per_us = np.zeros(6)
        self._tare = np.zeros(6)
        self._buffer: deque[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = deque()
        self._buffered = 0
        self._recent = _Recent(64)
        self._last_out: np.ndarray | None = None
        self._newest_us: int | None = None
        # Torque of a force applied at the tip / at the payload's centre of mass: r x F = F @ K(r)^T.
        self._k_tip_t = _skew(self._tip_in_sensor_mm * 1e-3).T
        self._k_com_t = _skew(self._com_sensor_mm * 1e-3).T
        self._gravity_cache: tuple[bytes, np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------ ForceTorqueSensor
    def identity(self) -> DeviceIdentity:
        return DeviceIdentity("ft", "ATI Mini45 / Net F/T (simulated)", self._serial, "1.0-sim",
                              {"counts_per_force": 1_000_000, "counts_per_torque": 1_000_000,
                               "range_n": self._s.range_n, "range_nm": self._s.range_nm})

    @property
    def rate_hz(self) -> float:
        return self._s.rate_hz

    def read_block(self) -> WrenchBlock:
        if not self._buffer:
            return WrenchBlock.empty()
        if len(self._buffer) == 1:
            t, seq, out, status = self._buffer.popleft()
            self._buffered = 0
            return WrenchBlock(t / US_PER_S, seq, out[:, :3].copy(), out[:, 3:].copy(), status)
        parts = list(self._buffer)
        self._buffer.clear()
        self._buffered = 0
        t = np.concatenate([p[0] for p in parts])
        seq = np.concatenate([p[1] for p in parts])
        out = np.concatenate([p[2] for p in parts])
        status = np.concatenate([p[3] for p in parts])
        return WrenchBlock(t / US_PER_S, seq, out[:, :3].copy(), out[:, 3:].copy(), status)

    def tare(self) -> None:
        """Software bias: the mean of the latest raw samples becomes zero."""
        raw = self._recent.latest_raw(self._s.tare_samples)
        if raw.shape[0]:
            self._tare = raw.mean(axis=0)
            # The driver owns both the stream and the guard: a deliberate step in the
            # readings is not a force rate (SafetyGuard.note_stream_restart).
            self._world.guard_restart()

    # ------------------------------------------------------------------ world hooks
    def _sim_begin_step(self) -> None:
        w = self._world
        self._noise.reset(w.rng(Stream.FT_NOISE))
        rng = w.rng(Stream.FT_DRIFT)
        per_h = np.concatenate([rng.normal(0.0, self._s.drift_n_per_h, 3), rng.normal(0.0, self._s.drift_nm_per_h, 3)])
        self._drift_per_us = per_h / (3600.0 * US_PER_S)

    def _gravity_wrench(self, r_bs: np.ndarray) -> np.ndarray:
        """Payload gravity (6,) in the sensor frame for one sensor orientation."""
        g = (self._mass_kg * GRAVITY_MM_S2) @ r_bs
        return np.concatenate([g, g @ self._k_com_t])

    def _static_terms(self, rot_base_tcp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(R_bs, gravity + bias (6,)) for one TCP orientation, cached: the arm holds its
        orientation for whole motions, so this is the same for thousands of sub-chunks."""
        key = rot_base_tcp.tobytes()
        cache = self._gravity_cache
        if cache is not None and cache[0] == key:
            return cache[1], cache[2]
        r_bs = rot_base_tcp @ self._r_ts
        static = self._gravity_wrench(r_bs) + self._bias
        self._gravity_cache = (key, r_bs, static)
        return r_bs, static

    def _sim_synthesize(self, ts_us: np.ndarray, force_base: np.ndarray, rot_base_tcp: np.ndarray,
                        now_us: int) -> FTSamples:
        w = self._world
        n = ts_us.shape[0]
        raw = np.empty((n, 6))
        if rot_base_tcp.ndim == 2:
            r_bs, static = self._static_terms(rot_base_tcp)
            f_contact = force_base @ r_bs                       # R_bs^T F for each row
            raw[:, :3] = f_contact
            raw[:, 3:] = f_contact @ self._k_tip_t
            raw += static
        else:
            r_bs = rot_base_tcp @ self._r_ts
            f_contact = np.einsum("nij,ni->nj", r_bs, force_base)
            g = np.einsum("nij,i->nj", r_bs, self._mass_kg * GRAVITY_MM_S2)
            raw[:, :3] = f_contact + g
            raw[:, 3:] = f_contact @ self._k_tip_t + g @ self._k_com_t
            raw += self._bias
        step_start = w.step_start_us
        first = (int(ts_us[0]) - step_start) // self._period_us - 1
        # Drift: the outer product of elapsed time and the per-µs rate (np.outer, unrolled).
        raw += (ts_us - step_start).astype(float)[:, None] * self._drift_per_us[None, :]
        raw += self._noise.take(first, n) * self._sigma
        faults = w.faults
        active = faults._sim_any_active()
        if active:
            spike = faults._sim_ft_spike(ts_us)
            if spike is not None:
                raw[:, :3] += spike
        # Saturation: one bound check of the whole block first (the common case is far inside).
        if float(np.abs(raw).max()) > self._range_min:
            clipped = np.abs(raw) > self._range
        else:
            clipped = None
        if clipped is not None and clipped.any():
            status = np.where(clipped.any(axis=1), STATUS_SATURATED, 0).astype(np.uint32)
            raw = np.clip(raw, -self._range, self._range)
        else:
            status = _ZEROS_U32[:n] if n <= _ZEROS_U32.shape[0] else np.zeros(n, dtype=np.uint32)
        out = raw - self._tare
        delivered = _ALL_TRUE[:n] if n <= _ALL_TRUE.shape[0] else np.ones(n, dtype=bool)
        all_delivered = True
        if active:
            frozen = faults._sim_ft_frozen(ts_us)
            if frozen is not None and frozen.any():
                held = self._last_out if self._last_out is not None else out[0]
                for i in np.flatnonzero(frozen):
                    out[i] = held if i == 0 or not frozen[i - 1] else out[i - 1]
            delivered = ~faults._sim_ft_stalled(ts_us)
            all_delivered = bool(delivered.all())
        seq = ts_us // self._period_us
        f, t = out[:, :3], out[:, 3:]
        fmag = np.sqrt(np.einsum("ij,ij->i", f, f))
        tmag2 = np.einsum("ij,ij->i", t, t)
        return FTSamples(ts_us, seq, raw, out, status, delivered, all_delivered, fmag, tmag2,
                         status_clear=clipped is None or not clipped.any())

    def _sim_offset_force_n(self, ts_us: np.ndarray, rot_base_tcp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The delivered force channels less the contact's part, for one TCP orientation:
        (gravity + bias + drift + noise - tare) (n, 3) N in the sensor frame, and R_bs.

        What a batched hold's force loop adds to the contact force it computes itself
        (:meth:`SimWorld._hold_span`); no faults, no saturation (the batch is screened
        and redone sub-chunk by sub-chunk if either could matter). Reads the same noise
        rows :meth:`_sim_synthesize` then delivers (PagedNormal re-reads them)."""
        r_bs, static = self._static_terms(rot_base_tcp)
        step_start = self._world.step_start_us
        first = (int(ts_us[0]) - step_start) // self._period_us - 1
        f = static[:3] + (ts_us - step_start).astype(float)[:, None] * self._drift_per_us[None, :3]
        f += self._noise.take(first, ts_us.shape[0])[:, :3] * self._sigma[:3]
        f -= self._tare[:3]
        return f, r_bs

    def _sim_commit(self, samples: FTSamples, cut: int) -> None:
        if samples.all_delivered:
            t = samples.ts_us[:cut]
            seq = samples.seq[:cut]
            out = samples.out[:cut]
            raw = samples.raw[:cut]
            status = samples.status[:cut]
        else:
            keep = samples.delivered[:cut]
            if not keep.any():
                return
            t, seq = samples.ts_us[:cut][keep], samples.seq[:cut][keep]
            out, raw, status = samples.out[:cut][keep], samples.raw[:cut][keep], samples.status[:cut][keep]
        self._buffer.append((t, seq, out, status))
        self._buffered += t.shape[0]
        limit = int(self._s.buffer_s * self._s.rate_hz)
        while self._buffered > limit and len(self._buffer) > 1:
            self._buffered -= self._buffer.popleft()[0].shape[0]
        self._recent.push(raw, out)
        self._last_out = out[-1]
        self._newest_us = int(t[-1])

    def _sim_noiseless(self) -> bool:
        return not bool(np.all(self._sigma > 0.0))

    def _sim_recent(self, count: int) -> np.ndarray:
        """The latest delivered (tared) forces (count, 3), for the arm's force loop."""
        return self._recent.latest_out(count)[:, :3]

    def _sim_newest_us(self) -> int | None:
        """The time (µs) of the newest delivered sample, None before any (the force loop's freshness)."""
        return self._newest_us


_ALL_TRUE = np.ones(4096, dtype=bool)
_ALL_TRUE.setflags(write=False)
_ZEROS_U32 = np.zeros(4096, dtype=np.uint32)
_ZEROS_U32.setflags(write=False)


class _Recent:
    """The latest raw and delivered samples (ring buffer of ``size`` rows)."""

    def __init__(self, size: int) -> None:
        self._raw = np.zeros((2 * size, 6))
        self._out = np.zeros((2 * size, 6))
        self._size = size
        self._n = 0          # rows filled in the double-length buffer

    def push(self, raw: np.ndarray, out: np.ndarray) -> None:
        k = raw.shape[0]
        if k >= self._size:
            self._raw[:self._size] = raw[-self._size:]
            self._out[:self._size] = out[-self._size:]
            self._n = self._size
            return
        if self._n + k > 2 * self._size:
            keep = self._size - k
            self._raw[:keep] = self._raw[self._n - keep:self._n]
            self._out[:keep] = self._out[self._n - keep:self._n]
            self._n = keep
        self._raw[self._n:self._n + k] = raw
        self._out[self._n:self._n + k] = out
        self._n += k

    def latest_raw(self, count: int) -> np.ndarray:
        return self._raw[max(self._n - count, 0):self._n]

    def latest_out(self, count: int) -> np.ndarray:
        return self._out[max(self._n - count, 0):self._n]


def _skew(r: np.ndarray) -> np.ndarray:
    """K(r) with K(r) F = r x F."""
    return np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
