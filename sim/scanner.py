"""Simulated eye-in-hand laser line scanner (implements LineScanner).

Geometry: mounted at ``tcp <- scanner`` (the cell file; miscalibrated if the cell asks).
The laser fan lies in the scanner x-z plane (which contains the probe axis); its
``samples`` rays span ``field_of_view_deg`` symmetrically about the optical axis
(scanner z); a sample reports (x, z) of the hit in the scanner frame, NaN if missing.
The camera sits ``camera_baseline_mm`` along scanner +y (triangulation), so a sample
is also lost when the probe blocks the camera's view of it.

Per profile (at its exposure instant, from the world's true state):
1. the fan is ray-cast against the undeformed object mesh and the table plane z = 0
   (:mod:`elastoprobe.sim.raycast`; the plane cut is cached and reused while the
   scanner moves within its own plane, e.g. while the probe holds or pushes);
2. each ray that hit the object is followed on to where it meets the deformed surface
   (the undeformed surface displaced along -n by the ContactModel's ``depth_profile_mm``
   at the current force and creep state, or by permanent dents from earlier presses, also
   out of contact): a bracketed root find per ray (:func:`dented_hit_depth_mm`), since
   the dent's depth at the point the ray reaches is not its depth where the ray met the
   undeformed surface wherever the dent slopes and the ray is oblique; the undeformed
   point beneath a ray point is found on the plane cut of step 1, so curved and faceted
   surfaces are exact too;
3. samples are lost: the probe cylinder or the tip sphere on the laser ray or on the
   camera's line of sight (the probe's shadow, on the side the probe is on), steep
   incidence beyond the material's ``steep_incidence_deg``, a per-material base
   dropout (dark foam loses more than rubber), and extra losses around the deformed tip;
4. noise along the range: independent per sample (``scanner_noise_mm``) plus a
   correlated component fixed for a burst (a smooth random shape along the line with
   RMS ``noise_corr_floor_mm``): averaging N scans lowers the RMS error as 1/sqrt(N)
   down to that floor.

Timing: ``start_burst(n)`` schedules n exposures at ``rate_hz`` from the next control
period; a profile can be read ``latency_ms`` after its exposure.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np

from elastoprobe.controller.core.devices import DeviceIdentity, Scan
from elastoprobe.controller.core.geometry import Pose

from .raycast import PlaneCut, PlaneSlicer, cast_fan, plane_hits, segments_blocked
from .world import US_PER_S, Stream, WorldSnapshot

if TYPE_CHECKING:   # pragma: no cover
    from .world import SimWorld


@dataclass(frozen=True)
class ScannerSettings:
    """The scanner's optics and timing (units in the names)."""

    samples: int = 256
    rate_hz: float = 50.0
    field_of_view_deg: float = 40.0
    max_range_mm: float = 400.0
    min_range_mm: float = 40.0
    noise_scale: float = 1.0
    camera_baseline_mm: float = 80.0
    latency_ms: float = 4.0
    table_noise_mm: float = 0.01
    table_corr_floor_mm: float = 0.002
    table_dropout_prob: float = 0.002
    tip_dropout_prob: float = 0.3          # extra loss where the surface is pressed in near the tip
    probe_shadow: bool = True              # tests of the contact physics can switch the probe off
    cache_cuts: bool = True                # plane cuts and burst shadow masks (the benchmark's baseline: off)
    # The dented-hit root find starts with secant steps, and keeps the cut's offsets through a
    # burst (with cache_cuts); off: bracketed from 0 and the depth at the crossing, offsets
    # prepared per profile (the benchmark's previous renderer).
    secant_root_find: bool = True


@dataclass(frozen=True)
class ProbeGeometry:
    """The probe body and tip, in the TCP frame (mm): a cylinder from ``axis_a`` to ``axis_b``."""

    axis_a_mm: np.ndarray
    axis_b_mm: np.ndarray
    radius_mm: float
    tip_centre_mm: np.ndarray
    tip_radius_mm: float


@dataclass(eq=False)
class _Burst:
    exposures_us: list[int]
    correlated_shape: np.ndarray     # unit-RMS shape along the line, fixed for the burst


# Where the undeformed point beneath a ray cannot be found on the cut (no segment near the
# hits), the hit face's plane stands in; a ray more grazing on it than this |cos| is advanced
# as if at this cosine, which keeps that step bounded (the shipped materials lose samples
# beyond 55-75 deg, i.e. |cos| under 0.26-0.57, so they are lost anyway).
_MIN_FACE_COS = 0.2
_DENT_TOL_MM = 1e-4          # 0.1 um: far under any scanner's noise
_DENT_ITERATIONS = 30        # bound of the root find (Illinois: a handful suffice)


def dented_hit_depth_mm(depth_at: Callable[[np.ndarray], np.ndarray], h0_mm: np.ndarray, dirs: np.ndarray,
                        face_normals: np.ndarray, n: np.ndarray,
                        advance_at: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                        secant_start: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Where rays that met the undeformed surface at ``h0_mm`` (M,3) meet the dented one.

    The dented surface is {q - d(q) n : q on the undeformed surface}, d = ``depth_at`` (mm,
    along -n). Near each hit the undeformed surface is its face's plane (normal
    ``face_normals``): the ray point h0 + s dir lies at depth d below the plane point
    q = h0 + s dir + d n when s = -d (n . n_f) / (dir . n_f). The ray meets the dented
    surface where f(d) = d - d(q(d)) = 0; the depth there is not the depth at h0 wherever
    the dent slopes and the ray is oblique (the ray moves along t as it goes in). Two
    secant steps from f(0) = -d(h0) settle nearly every ray (f is close to linear: exactly
    so where the depth does not change over the step, a uniform sink far from the tip);
    the rest are bracketed from the points seen (stepping out by the deepest depth where
    all lie on one side) and solved by the Illinois variant of regula falsi, vectorised —
    a plain fixed-point step would diverge where a steep foam dent is seen at a low angle.

    ``advance_at(d, rows)``, if given, replaces the face's plane by the mesh itself: the
    advance (mm) along rows' rays at which the undeformed surface lies d mm further along
    n, NaN where it cannot tell (the plane is used there). On a curved surface a deep dent
    seen obliquely moves q off the hit face, and the plane misplaces it by ~ step^2 / 2R
    (0.3 mm for a 5 mm sponge dent on the 65 mm ball).

    ``secant_start=False`` skips the secant steps: the bracket comes from f(0) and f(d(h0))
    (the same roots within the tolerance, more evaluations; kept for the benchmark).

    Returns (depth mm at the meeting point along -n, advance mm along each ray).
    """
    h0 = np.asarray(h0_mm, dtype=float)
    cos_face = -np.maximum(np.abs(np.einsum("ij,ij->i", dirs, face_normals)), _MIN_FACE_COS)
    along = -(face_normals @ n) / cos_face          # advance along the ray per mm of depth

    def advance_of(d: np.ndarray, rows: np.ndarray) -> np.ndarray:
        plane = d * along[rows]
        if advance_at is None:
            return plane
        exact = advance_at(d, rows)
        return np.where(np.isfinite(exact), exact, plane)

    def f_of(d: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(f(d), the advance along the ray at d) for rows."""
        adv = advance_of(d, rows)
        q = h0[rows] + adv[:, None] * dirs[rows] + d[:, None] * n
        return d - depth_at(q), adv

    d0 = np.asarray(depth_at(h0), dtype=float)
    depth = d0.copy()
    advance = depth * along
    rows = np.flatnonzero(np.abs(d0) > _DENT_TOL_MM)
    if rows.size == 0:
        return depth, advance
    d_start = d0[rows]
    if secant_start:
        # f is close to linear in d (the dent's depth changes little between where the ray
        # meets the undeformed surface and where it meets the dent): secant steps from
        # f(0) = -d0 find the root within the tolerance mostly at once. The first takes its
        # second point on the hit face's plane (a depth lookup without the mesh), the second
        # is exact.
        q_plane = h0[rows] + d_start[:, None] * (along[rows, None] * dirs[rows] + n)
        d_try = _secant_from_zero(d_start, d_start, d_start - np.asarray(depth_at(q_plane), dtype=float))
    else:
        d_try = d_start
    points = [(np.zeros(rows.size), -d_start)]          # (d, f(d)) seen, per row
    for step in range(2 if secant_start else 1):
        if step:
            d_try = _secant_from_zero(d_start, *points[-1])
        f_try, adv = f_of(d_try, rows)
        settled = np.abs(f_try) <= _DENT_TOL_MM
        depth[rows], advance[rows] = d_try, adv
        keep = ~settled
        rows, d_start = rows[keep], d_start[keep]
        points = [(x[keep], f[keep]) for x, f in points] + [(d_try[keep], f_try[keep])]
        if rows.size == 0:
            return depth, advance
    # The points seen in increasing d; f rises through its root (f(lo) <= 0 <= f(hi)): take
    # the tightest pair around a sign change, or the pair at the end the root lies beyond.
    xs = np.column_stack([x for x, _ in points])
    fs = np.column_stack([f for _, f in points])
    order = np.argsort(xs, axis=1, kind="stable")
    xs, fs = np.take_along_axis(xs, order, axis=1), np.take_along_axis(fs, order, axis=1)
    rising = fs >= 0.0
    k = np.clip(np.where(rising.any(axis=1), np.argmax(rising, axis=1), xs.shape[1]), 1, xs.shape[1] - 1)
    idx = np.arange(rows.size)
    lo, f_lo, hi, f_hi = xs[idx, k - 1], fs[idx, k - 1], xs[idx, k], fs[idx, k]
    deepest = float(np.max(np.abs(d0))) * 1.05 + _DENT_TOL_MM
    for _ in range(8):
        # The root lies beyond the pair (f of one sign at both): step out past it by at least
        # the deepest depth seen, keeping the old end as the other side.
        below, above = f_hi < 0, f_lo > 0
        moved = below | above
        if not np.any(moved):
            break
        step = np.maximum(deepest, np.abs(np.where(below, f_hi, f_lo)))
        probe = np.where(below, hi + step, lo - step)
        f_probe = np.zeros(rows.size)
        f_probe[moved] = f_of(probe[moved], rows[moved])[0]
        lo, f_lo, hi, f_hi = (np.where(below, hi, np.where(above, probe, lo)),
                              np.where(below, f_hi, np.where(above, f_probe, f_lo)),
                              np.where(above, lo, np.where(below, probe, hi)),
                              np.where(above, f_lo, np.where(below, f_probe, f_hi)))
    # Illinois on the bracket, row by row: a row that meets the tolerance is settled and
    # leaves the iteration.
    side = np.zeros(rows.size, dtype=int)         # which end was replaced last
    for _ in range(_DENT_ITERATIONS):
        denom = f_hi - f_lo
        safe = np.abs(denom) > 1e-15
        d = np.where(safe, hi - f_hi * (hi - lo) / np.where(safe, denom, 1.0), 0.5 * (lo + hi))
        f, adv = f_of(d, rows)
        settled = np.abs(f) <= _DENT_TOL_MM
        depth[rows], advance[rows] = d, adv
        if settled.all():
            break
        up = f > 0
        hi, f_hi = np.where(up, d, hi), np.where(up, f, f_hi)
        lo, f_lo = np.where(up, lo, d), np.where(up, f_lo, f)
        f_lo = np.where(up & (side == 1), 0.5 * f_lo, f_lo)
        f_hi = np.where(~up & (side == -1), 0.5 * f_hi, f_hi)
        side = np.where(up, 1, -1)
        go = ~settled
        rows, lo, f_lo, hi, f_hi, side = rows[go], lo[go], f_lo[go], hi[go], f_hi[go], side[go]
    return depth, advance


def _secant_from_zero(d0: np.ndarray, d: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Where the line through (0, -``d0``) and (``d``, ``f``) crosses zero (mm); 2 ``d`` where
    it is flat (the bracket search takes over from there)."""
    slope = (f + d0) / np.where(d != 0.0, d, 1.0)
    steep = (np.abs(slope) > 1e-6) & (d != 0.0)
    return np.where(steep, d - f / np.where(steep, slope, 1.0), 2.0 * d)


class SimLineScanner:
    """The simulated scanner; the world calls ``_sim_capture`` at each exposure."""

    def __init__(self, world: "SimWorld", tcp_to_scanner: Pose, probe: ProbeGeometry,
                 settings: ScannerSettings = ScannerSettings(), serial: str = "SIM-LLS-0001") -> None:
        self._world = world
        self._tcp_to_scanner = tcp_to_scanner
        self._probe = probe
        self._s = settings
        self._serial = serial
        half = math.radians(settings.field_of_view_deg) / 2.0
        self._angles = np.linspace(-half, half, settings.samples)
        self._dirs_local = np.column_stack([np.sin(self._angles), np.zeros(settings.samples), np.cos(self._angles)])
        obj = world.obj
        self._slicer = PlaneSlicer(obj.mesh.vertices, obj.mesh.faces)
        self._face_normals = np.asarray(obj.mesh.face_normals, float)
        labels = np.asarray(getattr(obj, "face_labels", np.zeros(len(obj.mesh.faces), dtype=int)))
        self._face_labels = labels
        mats = obj.materials
        self._mat_noise = np.array([m.scanner_noise_mm for m in mats])
        self._mat_floor = np.array([m.noise_corr_floor_mm for m in mats])
        self._mat_dropout = np.array([m.dropout_prob for m in mats])
        self._mat_steep_cos = np.cos(np.radians([m.steep_incidence_deg for m in mats]))
        self._cut_key: tuple | None = None
        self._cut: PlaneCut | None = None
        self._pending: list[_Burst] = []
        self._ready: list[tuple[int, Scan]] = []
        self._frame = 0
        self._noise_rng = np.random.default_rng(0)
        self._dropout_rng = np.random.default_rng(0)
        self._burst_index = 0
        self._shadow_cache: tuple | None = None
        self._advance_cache: tuple | None = None
        self._face_cache: tuple | None = None
        self._lateral_cache: tuple | None = None
        self.stats = {"captures": 0, "cuts": 0}

    # ------------------------------------------------------------------ LineScanner
    def identity(self) -> DeviceIdentity:
        return DeviceIdentity("scanner", "laser line scanner (simulated)", self._serial, "2.3-sim",
                              {"samples": self._s.samples, "fov_deg": self._s.field_of_view_deg})

    @property
    def samples_per_profile(self) -> int:
        return self._s.samples

    @property
    def rate_hz(self) -> float:
        return self._s.rate_hz

    def start_burst(self, count: int) -> None:
        if count <= 0:
            return
        w = self._world
        deliver = w.faults._sim_scanner_limit(int(count))
        period = int(round(US_PER_S / self._s.rate_hz))
        first = w.now_us + w.control_period_us
        exposures = [first + k * period for k in range(deliver)]
        if not exposures:
            return              # a scanner that times out: the trigger is taken, nothing comes
        # Each burst of a step gets its own correlated shape, keyed by its index in the step.
        self._burst_index += 1
        self._shadow_cache = None
        self._advance_cache = None
        seed, step, attempt = w.step_key
        rng = np.random.default_rng([seed & 0xFFFFFFFF, step & 0xFFFFFFFF, attempt & 0xFFFFFFFF,
                                     int(Stream.SCAN_CORRELATED), self._burst_index])
        self._pending.append(_Burst(exposures, self._correlated_shape(rng)))

    def read_scans(self) -> list[Scan]:
        now = self._world.now_us
        out = [scan for ready, scan in self._ready if ready <= now]
        self._ready = [(ready, scan) for ready, scan in self._ready if ready > now]
        return out

    # ------------------------------------------------------------------ world hooks
    def _sim_begin_step(self) -> None:
        w = self._world
        self._noise_rng = w.rng(Stream.SCAN_NOISE)
        self._dropout_rng = w.rng(Stream.SCAN_DROPOUT)
        self._burst_index = 0
        self._shadow_cache = None
        self._advance_cache = None

    def _sim_due(self, start_us: int, end_us: int) -> list[int]:
        """Exposure instants in (start, end]."""
        due = []
        for burst in self._pending:
            due.extend(t for t in burst.exposures_us if start_us < t <= end_us)
        return sorted(due)

    def _sim_capture(self, snap: WorldSnapshot) -> None:
        burst = next((b for b in self._pending if snap.t_us in b.exposures_us), None)
        if burst is None:
            return
        burst.exposures_us.remove(snap.t_us)
        if not burst.exposures_us:
            self._pending = [b for b in self._pending if b is not burst]
        x, z = self.profile(snap, noise=True, correlated_shape=burst.correlated_shape)
        self._frame += 1
        ready = snap.t_us + int(round(self._s.latency_ms * 1000.0))
        self._ready.append((ready, Scan(self._frame, snap.t_us / US_PER_S, x, z)))
        self.stats["captures"] += 1

    # ------------------------------------------------------------------ the optics
    def _correlated_shape(self, rng: np.random.Generator) -> np.ndarray:
        """A smooth unit-RMS random shape along the line (a few low Fourier modes)."""
        k = np.arange(1, 6)
        amp = rng.normal(0.0, 1.0, k.size) / k
        phase = rng.uniform(0.0, 2.0 * np.pi, k.size)
        s = np.linspace(0.0, 1.0, self._s.samples)
        shape = (amp[None, :] * np.cos(2.0 * np.pi * k[None, :] * s[:, None] / 2.0 + phase[None, :])).sum(axis=1)
        shape += rng.normal()     # an offset is part of the correlated error too
        rms = float(np.sqrt(np.mean(shape * shape)))
        return shape / rms if rms > 0 else shape

    def profile(self, snap: WorldSnapshot, noise: bool = True,
                correlated_shape: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(x, z) (mm, scanner frame; NaN = missing) of one profile in the state ``snap``.

        ``noise=False`` gives the noise-free, dropout-free profile (geometric losses stay)."""
        s = self._s
        b2o = snap.base_to_object
        base_scanner = snap.tcp_pose.compose(self._tcp_to_scanner)
        obj_scanner = b2o.inverse().compose(base_scanner)
        o = obj_scanner.position_mm
        rot = obj_scanner.rotation
        x_ax, y_ax, z_ax = rot[:, 0], rot[:, 1], rot[:, 2]
        cut = self._plane_cut(o, y_ax, b2o)
        rng_mesh, face = cast_fan(cut, o, x_ax, z_ax, self._angles, s.max_range_mm)
        dirs = self._dirs_local @ rot.T                       # object frame
        rng_table = plane_hits(o, dirs, np.zeros(3), np.array([0.0, 0.0, 1.0]), s.max_range_mm)
        on_table = rng_table < rng_mesh
        r = np.where(on_table, rng_table, rng_mesh)
        hit = np.isfinite(r) & (r >= s.min_range_mm)
        face = np.where(on_table | ~hit, -1, face)
        n_s = s.samples
        on_mesh, normals, steep_cos, drop_base, sigma, floor = self._face_terms(face)
        cos_inc = -np.einsum("ij,ij->i", dirs, normals)
        # Deformation: follow each object hit's ray on to the dented surface.
        r = r.copy()
        near_tip = np.zeros(n_s, dtype=bool)
        on_obj = on_mesh & hit
        field = self._dent_field(snap, o, dirs, r, on_obj)
        if field is not None:
            depth_at, n_dent = field
            rows = np.flatnonzero(on_obj)
            h0 = o + r[rows, None] * dirs[rows]
            advance_at = self._advance_on_cut(cut, o, x_ax, y_ax, z_ax, rows, r[rows], normals[rows], n_dent)
            depth_rows, advance = dented_hit_depth_mm(depth_at, h0, dirs[rows], normals[rows], n_dent, advance_at,
                                                      secant_start=s.secant_root_find)
            r[rows] += advance
            depth = np.zeros(n_s)
            depth[rows] = depth_rows
            peak = float(np.max(depth_rows)) if rows.size else 0.0
            if snap.contact is not None and peak > 0.05:
                near_tip = on_obj & (depth > 0.3 * peak)
        # Losses.
        lost = ~hit
        lost |= self._shadowed(o, dirs, r, snap, obj_scanner, hit)
        lost |= cos_inc < steep_cos
        if noise:
            p_drop = np.where(near_tip, np.maximum(drop_base, s.tip_dropout_prob), drop_base)
            lost |= self._dropout_rng.random(n_s) < p_drop
            shape = correlated_shape if correlated_shape is not None else np.zeros(n_s)
            r = r + self._noise_rng.standard_normal(n_s) * sigma + shape * floor
        r = np.where(lost, np.nan, r)
        return r * np.sin(self._angles), r * np.cos(self._angles)

    def _advance_on_cut(self, cut: PlaneCut, o: np.ndarray, x_ax: np.ndarray, y_ax: np.ndarray, z_ax: np.ndarray,
                        rows: np.ndarray, r0_mm: np.ndarray, face_normals: np.ndarray, n: np.ndarray
                        ) -> Callable[[np.ndarray, np.ndarray], np.ndarray] | None:
        """For :func:`dented_hit_depth_mm`: the advance along the rays of ``rows`` (which met the
        undeformed mesh at ranges ``r0_mm``) at which the mesh lies d mm further along n.

        That is where the ray shifted by d n meets the mesh, found in the laser plane against
        the cut's segments: exact for the mesh when n lies in the laser plane (the probe's
        plane). Where it does not (a turned scanner; a permanent dent's normal seen from another
        probe) the point beneath leaves the plane by d (n . y); across the plane the surface is
        taken to rise as the hit face does, which folds that part of the shift into the plane.
        NaN where the shifted ray meets none of the segments near the hits (the caller then
        uses the hit face's plane)."""
        if rows.size == 0 or cut.p1.shape[0] == 0:
            return None
        # Within a burst the scanner holds its plane and turns not at all; it moves only along
        # the probe's push, inside that plane. What prepare() computes from the cut's segments
        # relative to the scanner is then reused from the burst's first profile, corrected by
        # the origin's shift (a per-ray offset and range). Reset every burst and every step.
        key = (x_ax.tobytes(), z_ax.tobytes(), rows.tobytes())
        reuse = self._s.cache_cuts and self._s.secant_root_find
        cached = self._advance_cache if reuse else None
        if cached is not None and cached[0] is cut and cached[1] == key:
            o_ref, prepared = cached[2], cached[3]
        else:
            o_ref, prepared = o.copy(), {}
            if reuse:
                self._advance_cache = (cut, key, o_ref, prepared)
        rays = np.column_stack([np.sin(self._angles[rows]), np.cos(self._angles[rows])])
        # The shift in the plane per mm of depth, per ray: n's in-plane part, plus, for its
        # part across the plane, the in-plane step that keeps to the hit face's slope there.
        nf2 = np.column_stack([face_normals @ x_ax, face_normals @ z_ax])
        nf2_sq = np.einsum("ij,ij->i", nf2, nf2)
        fold = np.where(nf2_sq > 1e-6, float(n @ y_ax) * (face_normals @ y_ax) / np.maximum(nf2_sq, 1e-6), 0.0)
        n2 = np.array([float(n @ x_ax), float(n @ z_ax)])[None, :] + fold[:, None] * nf2
        k_all = n2[:, 0] * rays[:, 1] - n2[:, 1] * rays[:, 0]
        along_all = np.einsum("ij,ij->i", rays, n2)
        # The origin's shift from the reference: it lowers each segment's offset across a ray by
        # (shift x u) and its range along it by (shift . u).
        shift = o - o_ref
        shift2 = np.array([float(shift @ x_ax), float(shift @ z_ax)])
        off_shift = shift2[0] * rays[:, 1] - shift2[1] * rays[:, 0]
        rng_shift = rays @ shift2

        def prepare(sub: np.ndarray) -> None:
            # For the rays the root find asks about first (those in the dent), relative to the
            # reference origin: each near segment's offset across the ray (p x u) and range along
            # it (p . u) at its start, and their changes along it. The ray shifted by d n2,
            # d n2 + r u, is the line p x u = d (n2 x u): a segment meets it where its offset
            # passes that value, at r = p . u - d (n2 . u).
            seg_a = np.column_stack([(cut.p1 - o_ref) @ x_ax, (cut.p1 - o_ref) @ z_ax])
            seg_b = np.column_stack([(cut.p2 - o_ref) @ x_ax, (cut.p2 - o_ref) @ z_ax])
            ray = rays[sub]
            e = seg_b - seg_a
            off_a = seg_a[None, :, 0] * ray[:, None, 1] - seg_a[None, :, 1] * ray[:, None, 0]
            d_off = e[None, :, 0] * ray[:, None, 1] - e[None, :, 1] * ray[:, None, 0]
            rng_a, d_rng = ray @ seg_a.T, ray @ e.T
            # Per ray only the segments in front of the scanner that pass within 25 mm of the
            # ray's line (the shifted ray lies d (n2 x u) off it: a few dent depths at most),
            # wherever along it: at an edge the dented ray may pass the near surface and meet
            # one behind it. Packed per ray, in the cut's order, padded with entries that
            # never cross.
            margin_mm = 25.0
            near = ((np.minimum(off_a, off_a + d_off) <= margin_mm) & (np.maximum(off_a, off_a + d_off) >= -margin_mm)
                    & (np.maximum(rng_a, rng_a + d_rng) > 0.0))
            row, col = np.nonzero(near)                 # by row, then in the cut's order
            count = np.bincount(row, minlength=near.shape[0])
            slot = np.arange(row.size) - np.repeat(np.cumsum(count) - count, count)
            width = int(count.max(initial=0))

            def packed(values: np.ndarray, fill: float) -> np.ndarray:
                out = np.full((near.shape[0], width), fill)
                out[row, slot] = values[row, col]
                return out

            d_off = packed(d_off, 0.0)
            crossed = np.abs(d_off) > 1e-12
            prepared.clear()
            prepared.update(
                rows=sub.copy(), off_a=packed(off_a, 0.0),
                inv_off=np.where(crossed, 1.0 / np.where(crossed, d_off, 1.0), np.nan),   # NaN: never crossed
                rng_a=packed(rng_a, 0.0), d_rng=packed(d_rng, 0.0))

        def advance_at(d: np.ndarray, sub: np.ndarray) -> np.ndarray:
            if not prepared:
                prepare(sub)
            known = prepared["rows"]
            if sub.size == known.size and np.array_equal(sub, known):
                pick: slice | np.ndarray = slice(None)
            else:
                pick = np.searchsorted(known, sub)          # the root find narrows its rows
                if np.any(pick >= known.size) or not np.array_equal(known[np.minimum(pick, known.size - 1)], sub):
                    prepare(sub)
                    pick = slice(None)
            P = prepared
            if P["off_a"].shape[1] == 0:
                return np.full(sub.size, np.nan)
            frac = ((d * k_all[sub] + off_shift[sub])[:, None] - P["off_a"][pick]) * P["inv_off"][pick]
            r = P["rng_a"][pick] + frac * P["d_rng"][pick] - (d * along_all[sub] + rng_shift[sub])[:, None]
            ok = (frac >= -1e-9) & (frac <= 1.0 + 1e-9) & (r > 0.0)
            # Of several crossings, the one nearest the original hit (the dent is local).
            gap = np.where(ok, np.abs(r - r0_mm[sub, None]), np.inf)
            best = np.argmin(gap, axis=1)
            idx = np.arange(sub.size)
            return np.where(np.isfinite(gap[idx, best]), r[idx, best] - r0_mm[sub], np.nan)

        return advance_at

    def _face_terms(self, face: np.ndarray) -> tuple[np.ndarray, ...]:
        """What each sample's hit face alone decides: (on the mesh, surface normal, cosine of the
        steepest visible incidence, base dropout probability, noise sigma mm, correlated floor mm).

        A pure function of the face indices (-1: table or nothing), kept for the last set of
        faces: within a burst the laser line crosses the same faces profile after profile."""
        cached = self._face_cache
        if cached is not None and np.array_equal(cached[0], face):
            return cached[1]
        s = self._s
        on_mesh = face >= 0
        normals = np.zeros((face.shape[0], 3))
        normals[:, 2] = 1.0
        normals[on_mesh] = self._face_normals[face[on_mesh]]
        label = np.maximum(np.where(on_mesh, self._face_labels[np.maximum(face, 0)], -1), 0)
        steep_cos = np.where(on_mesh, self._mat_steep_cos[label], math.cos(math.radians(85.0)))
        drop_base = np.where(on_mesh, self._mat_dropout[label], s.table_dropout_prob)
        sigma = np.where(on_mesh, self._mat_noise[label], s.table_noise_mm) * s.noise_scale
        floor = np.where(on_mesh, self._mat_floor[label], s.table_corr_floor_mm) * s.noise_scale
        terms = (on_mesh, normals, steep_cos, drop_base, sigma, floor)
        for arr in terms:
            arr.setflags(write=False)       # shared between profiles: never modified in place
        if s.cache_cuts:
            self._face_cache = (face.copy(), terms)
        return terms

    def _plane_cut(self, o: np.ndarray, y_ax: np.ndarray, b2o: Pose) -> PlaneCut:
        key = (tuple(np.round(y_ax, 12)), round(float(o @ y_ax), 9), tuple(np.round(b2o.position_mm, 9)))
        if not self._s.cache_cuts or key != self._cut_key or self._cut is None:
            self._cut = self._slicer.cut(o, y_ax)
            self._cut_key = key
            self.stats["cuts"] += 1
        return self._cut

    def _dent_field(self, snap: WorldSnapshot, o: np.ndarray, dirs: np.ndarray, r: np.ndarray,
                    on_obj: np.ndarray) -> tuple[Callable[[np.ndarray], np.ndarray], np.ndarray] | None:
        """The dent in ``snap`` as (depth_at(points) -> depth mm along -n, n), or None without one.

        ``depth_at`` takes object-frame points on (or displaced from) the undeformed surface
        and gives the dent's depth at their position across the contact (x along t, and the
        distance off the line), which is what the contact model defines."""
        w = self._world
        if not np.any(on_obj):
            return None
        c = snap.contact
        if c is not None and c.model is not None:
            # The contact's lateral axis n x t, once per contact (its geometry is fixed from first touch).
            lc = self._lateral_cache
            if lc is None or lc[0] is not c:
                lc = self._lateral_cache = (c, np.cross(c.normal_obj, c.t_obj))
            model, point, t, lateral_axis = c.model, c.point_obj, c.t_obj, lc[1]
            force_n, hold_s, n = snap.force_n, snap.hold_s, c.normal_obj
        else:
            if not w.presses:
                return None
            pts = o + np.where(on_obj, r, 0.0)[:, None] * dirs
            centre = pts[on_obj].mean(axis=0)
            press = min(w.presses, key=lambda p: float(np.linalg.norm(p.point_obj - centre)))
            if float(np.min(np.linalg.norm(pts[on_obj] - press.point_obj, axis=1))) > 30.0:
                return None
            line = pts[on_obj][-1] - pts[on_obj][0]
            n = press.normal_obj
            t = line - float(line @ n) * n
            if np.linalg.norm(t) < 1e-9:
                return None
            t = t / np.linalg.norm(t)
            model = w.obj.contact_model(press.point_obj, n, t, 90.0, w.tip_radius_mm)
            point, lateral_axis, force_n, hold_s = press.point_obj, np.cross(n, t), 0.0, math.inf

        def depth_at(points_mm: np.ndarray) -> np.ndarray:
            rel = points_mm - point
            x = rel @ t
            lateral = rel @ lateral_axis
            # The laser line runs through the tip; off the line (miscalibration) use the
            # distance from the tip with the sign of x (the dent is nearly axisymmetric).
            return model.depth_profile_mm(np.sign(x) * np.sqrt(x * x + lateral * lateral), force_n, hold_s)

        return depth_at, n

    def _shadowed(self, o: np.ndarray, dirs: np.ndarray, r: np.ndarray, snap: WorldSnapshot,
                  obj_scanner: Pose, hit: np.ndarray) -> np.ndarray:
        """Samples whose laser ray or camera view is blocked by the probe or its tip."""
        if not self._s.probe_shadow or not np.any(hit):
            return np.zeros(r.shape[0], dtype=bool)
        # Within a burst the arm holds still but for micrometres of force-loop motion: reuse
        # the mask while the pose and every range stay within 0.01 mm (reset every burst
        # and every step, so it never depends on history).
        key_pose = np.concatenate([snap.tcp_pose.position_mm, snap.tcp_pose.rotation.ravel() * 100.0])
        cached = self._shadow_cache if self._s.cache_cuts else None
        if cached is not None:
            c_pose, c_r, c_hit, c_mask = cached
            if (np.array_equal(c_hit, hit) and float(np.max(np.abs(c_pose - key_pose))) < 0.01
                    and float(np.max(np.abs(c_r[hit] - r[hit]))) < 0.01):
                return c_mask
        mask = self._shadow_mask(o, dirs, r, snap, obj_scanner, hit)
        self._shadow_cache = (key_pose, r.copy(), hit.copy(), mask)
        return mask

    def _shadow_mask(self, o: np.ndarray, dirs: np.ndarray, r: np.ndarray, snap: WorldSnapshot,
                     obj_scanner: Pose, hit: np.ndarray) -> np.ndarray:
        p = self._probe
        obj_tcp = snap.base_to_object.inverse().compose(snap.tcp_pose)
        a = obj_tcp.apply(p.axis_a_mm)
        b = obj_tcp.apply(p.axis_b_mm)
        tip = obj_tcp.apply(p.tip_centre_mm)
        rr = np.where(hit, r, 0.0)
        pts = o + rr[:, None] * dirs
        # Stop the segments just short of the surface so the tip touching it does not count.
        back = 0.5
        laser_end = o + np.maximum(rr - back, 0.0)[:, None] * dirs
        origin = np.broadcast_to(o, pts.shape)
        blocked = segments_blocked(origin, laser_end, a, b, p.radius_mm)
        blocked |= segments_blocked(origin, laser_end, tip, tip, p.tip_radius_mm)
        camera = obj_scanner.apply(np.array([0.0, self._s.camera_baseline_mm, 0.0]))
        view_dir = camera - pts
        view_len = np.linalg.norm(view_dir, axis=1, keepdims=True)
        start = pts + view_dir / np.maximum(view_len, 1e-9) * back
        cam = np.broadcast_to(camera, pts.shape)
        blocked |= segments_blocked(start, cam, a, b, p.radius_mm)
        blocked |= segments_blocked(start, cam, tip, tip, p.tip_radius_mm)
        return blocked & hit
