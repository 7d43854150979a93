"""Complete training targets for the region models, and where each sample's value comes from.

The scanner never sees the whole profile: the tip hides the surface under it, and the
probe body shadows one side of the line (at every angle the side behind the tangential
load: the scanner turns with the wrist at 90 degrees, so alpha and 180 - alpha both see
the side their load pushes toward). A model trained on the measured samples alone is
unconstrained exactly there. Every sample of a training target gets a value and a
support code:

- ``measured``: the step's own averaged profile;
- ``mirrored``: the same point's profile at 180 - alpha (the same force level) read at
  -x, where this step's own is missing; and at 90 degrees the step's own profile at -x
  (a normal push on an isotropic material makes a symmetric dent). Used only where the
  region's measured mirror residual allows it (:func:`mirror_test`);
- ``tip``: under a normal push the surface follows the tip's sphere, at the depth the
  arm's own poses put the tip (:class:`profiles.StepMeasurement`), within the half-width
  where the sphere is within ``eps`` (10 % of the indentation) of its lowest point:
  whatever the material's contact radius, the surface there lies between the sphere
  and the tip's lowest point (a normal push is deepest under the tip), so the sample is
  right to within ``eps``. Under an oblique push the contact patch sits on the side of
  the sphere that faces the load, not at its lowest point, and the deepest point of the
  dent moves with the tangential load: there the sphere only bounds the surface (it
  cannot be above the tip) and the samples come from the inferred profile below;
- ``inferred``: at an oblique angle, the unseen samples follow the same point's complete
  90-degree profile at the same normal load F sin(alpha), centred on the tip, plus the
  body's sink, plus the tangential load's odd term read off the seen side and reversed (the
  normal and tangential contact problems decouple to first order: the tangential load
  shifts the dent and adds an odd term that decays away from the contact). Used only where
  the mirror is admitted (the 90-degree profile's unseen half is a mirror). Under a normal
  push, the gap between the tip's zone and the first seen sample on each side follows the
  contact's shape (:mod:`contact`: the sphere out to the contact's edge, then a fall fitted
  to the region's own seen samples);
- ``unsupported``: none of the above; filled by shape-preserving interpolation between
  supported samples, so the value is bounded by its supported neighbours, and flagged.
  Beyond the last supported sample towards the grid's end the dent decays towards the
  undeformed surface as the region's own measured tails do (:func:`tail_exponent`: a
  power of the distance from the tip, fitted to the measured samples beyond the contact;
  held flat when nothing measured it). Where the mirror is not admitted the unseen side
  of a row is first guessed from the row's own reflection about the tip (a dent falls
  off beyond the tip on both sides), flagged unsupported all the same.

Everything is numpy; depths in mm along -n (positive into the object), x in mm along t.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import contact

MEASURED, MIRRORED, TIP, INFERRED, UNSUPPORTED = 0, 1, 2, 3, 4
SUPPORT_NAMES: tuple[str, ...] = ("measured", "mirrored", "tip", "inferred", "unsupported")
# The sphere stands in for the surface where it is within this fraction of the tip's
# indentation from its lowest point (see the module docstring).
TIP_TOLERANCE_FRACTION = 0.1
NORMAL_ANGLE_DEG = 90.0
# How often the mirror test may reject a region whose dent is in fact symmetric, and the
# asymmetry (RMS, as a fraction of the region's deepest dent) below which it does not matter.
MIRROR_FALSE_REJECTION = 1e-3
MIRROR_MARGIN = 0.05
# Beyond this many tip radii from the tip the odd part of an oblique push is taken to have
# fallen off (:func:`_infer_oblique`).
ODD_FAR_RADII = 4.0


@dataclass(frozen=True)
class RegionSteps:
    """One region's measured steps (M of them) on the grid ``x_mm`` (L,).

    ``force_n`` (M,) measured |F|; ``force_level_n`` (M,) the planned level (groups the
    steps of one force); ``angle_deg`` (M,); ``depth_mm`` (M,L) averaged profiles, NaN
    missing; ``point_ids`` (M,); ``tip_x_mm``, ``tip_depth_mm`` (M,) from the arm's poses
    (NaN unknown); ``reference_h_mm`` (M,L) the zero-force surface's height along n (the
    reference scans', NaN unknown).
    """

    x_mm: np.ndarray
    force_n: np.ndarray
    force_level_n: np.ndarray
    angle_deg: np.ndarray
    depth_mm: np.ndarray
    point_ids: np.ndarray
    tip_x_mm: np.ndarray
    tip_depth_mm: np.ndarray
    reference_h_mm: np.ndarray

    def __len__(self) -> int:
        return int(self.force_n.shape[0])


@dataclass
class MirrorTest:
    """The region's measured mirror symmetry (see :func:`mirror_test`)."""

    admitted: bool
    residual_mm: float | None            # RMS shape residual of alpha vs 180 - alpha (rigid part removed)
    yardstick_mm: float | None           # what it would be for a symmetric dent (repeatability and view)
    pairs: int
    reason: str

    def to_dict(self) -> dict[str, Any]:
        def num(v: float | None) -> float | None:
            return None if v is None or not np.isfinite(v) else round(float(v), 6)
        return {"admitted": self.admitted, "residual_mm": num(self.residual_mm),
                "yardstick_mm": num(self.yardstick_mm), "pairs": self.pairs, "reason": self.reason}


@dataclass
class CompletedTargets:
    """Training targets (M,L) with no missing sample, their support codes (M,L) int8, and
    what was decided for the region."""

    depth_mm: np.ndarray
    support: np.ndarray
    mirror: MirrorTest
    counts: dict[str, int] = field(default_factory=dict)
    tail_exponent: float = 0.0           # the unsupported tails' decay (:func:`tail_exponent`)


# --------------------------------------------------------------------------- helpers

def fill_gaps(x_mm: np.ndarray, values: np.ndarray, centre_mm: float = 0.0, exponent: float = 0.0,
              near_mm: float = 1.0) -> np.ndarray:
    """NaN samples filled by monotone (PCHIP) interpolation between finite ones; beyond the
    first and last, the end value times (r_end / r) ** ``exponent``, r the distance from
    ``centre_mm`` (the tip) but at least ``near_mm`` (0: held flat); all NaN stays all NaN.
    Never overshoots its neighbours, and the ends only decay towards zero."""
    x = np.asarray(x_mm, dtype=float)
    v = np.asarray(values, dtype=float)
    ok = np.isfinite(v)
    if ok.all() or not ok.any():
        return v.copy()
    if ok.sum() == 1:
        out = np.full_like(v, v[ok][0])
    else:
        from scipy.interpolate import PchipInterpolator   # training only: predict needs only the names here

        out = PchipInterpolator(x[ok], v[ok], extrapolate=False)(x)
    r = np.maximum(np.abs(x - centre_mm), near_mm)
    for end, beyond in ((np.flatnonzero(ok)[0], x < x[ok][0]), (np.flatnonzero(ok)[-1], x > x[ok][-1])):
        # A decay only away from the tip: an end on the tip's near side holds flat.
        decay = np.minimum((r[end] / r[beyond]) ** exponent, 1.0) if exponent > 0.0 else 1.0
        out[beyond] = v[end] * decay
    return np.where(ok, v, out)


def tail_exponent(steps: RegionSteps, tip_radius_mm: float, min_samples: int = 8) -> float:
    """How the region's measured dents decay beyond the contact: the median, over every row
    and side, of the log-log slope of depth against the distance from the tip, fitted to the
    measured samples more than two tip radii from it and deeper than 10 % of the row's
    deepest sample (the tail above the noise). 0 (no decay) when no row has ``min_samples``
    such samples over a distance ratio of 1.35 or more.

    A dent in a half-space falls off as a power of the distance from the load (1/r for a
    point load far from it); a layer on a support, or a body that sinks as a whole, falls
    off faster or slower, so the power is the region's own, not assumed. Clipped to [0, 3].
    """
    x = steps.x_mm
    slopes: list[float] = []
    for k in range(len(steps)):
        d = steps.depth_mm[k]
        if not np.isfinite(d).any():
            continue
        centre = _centre(steps.tip_x_mm[k])
        peak = float(np.nanmax(d))
        for side in (-1.0, 1.0):
            r = side * (x - centre)
            use = np.isfinite(d) & (r > 2.0 * tip_radius_mm) & (d > 0.1 * peak) & (d > 0.0)
            if use.sum() < min_samples or np.ptp(np.log(r[use])) < np.log(1.35):
                continue
            slopes.append(-float(np.polyfit(np.log(r[use]), np.log(d[use]), 1)[0]))
    return float(np.clip(np.median(slopes), 0.0, 3.0)) if slopes else 0.0


def sphere_depth_mm(x_mm: np.ndarray, tip_x_mm: float, tip_depth_mm: float, radius_mm: float) -> np.ndarray:
    """Depth of the tip's lower surface (mm along -n) on the grid, NaN outside its footprint.

    ``tip_depth_mm``: the depth of its lowest point at ``tip_x_mm`` (the reference surface
    is taken flat over the footprint: its own curvature over a contact of a few mm is far
    below the indentation)."""
    x = np.asarray(x_mm, dtype=float)
    out = np.full(x.shape, np.nan)
    inside = np.abs(x - tip_x_mm) < radius_mm
    out[inside] = tip_depth_mm - radius_mm + np.sqrt(radius_mm ** 2 - (x[inside] - tip_x_mm) ** 2)
    return out


def tip_half_width_mm(tip_depth_mm: float, radius_mm: float) -> float:
    """Half-width where the sphere is within TIP_TOLERANCE_FRACTION of the indentation of its
    lowest point (0 when the tip did not go in)."""
    if not np.isfinite(tip_depth_mm) or tip_depth_mm <= 0.0:
        return 0.0
    eps = min(TIP_TOLERANCE_FRACTION * tip_depth_mm, radius_mm)
    return float(np.sqrt(2.0 * radius_mm * eps - eps * eps))


def _is_normal(angle_deg: float) -> bool:
    return abs(float(angle_deg) - NORMAL_ANGLE_DEG) < 1e-6


def _group(steps: RegionSteps) -> dict[tuple[int, float, float], int]:
    """(point, angle, force level) -> row (the last row wins if a step was repeated)."""
    return {(int(p), round(float(a), 6), round(float(f), 6)): k
            for k, (p, a, f) in enumerate(zip(steps.point_ids, steps.angle_deg, steps.force_level_n))}


# --------------------------------------------------------------------------- the mirror

def mirror_test(steps: RegionSteps, false_rejection: float = MIRROR_FALSE_REJECTION) -> MirrorTest:
    """Is the region's dent mirror symmetric, as far as its measurements can tell?

    The mirror residual: for every measured pair (alpha, 180 - alpha) at one point and
    force level, d(alpha, x) - d(180 - alpha, -x) over the samples both saw, less its
    median (a rigid sink of the whole body along a slanted push differs between the two;
    it is not a property of the material and does not enter a normal push).

    What it would be for a symmetric dent, from the same session's measurements: (1) the
    region's repeatability, the same residual between the same angle and force at two
    points of the region (scan noise, registration, point-to-point variation), and (2)
    the difference between the two views, which a mirrored pair adds (the scanner sees
    alpha and 180 - alpha from opposite sides): the pair's zero-force reference heights
    are one surface seen from both sides, so their residual (median removed) measures it;
    a depth is a difference of two heights from one view, hence twice its mean square.

    The mirror is not admitted when the residual is both significant and large enough to
    matter: its mean square exceeds the expected one by more than an F test allows at
    ``false_rejection`` (pairs as the degrees of freedom, since samples along a line are
    not independent: a symmetric region is rejected by chance that rarely), and its RMS
    exceeds ``MIRROR_MARGIN`` of the region's deepest dent (the accuracy the models are
    held to: a mirrored sample is off by about the residual, so a smaller asymmetry, real
    or not, cannot make a model miss it; the residual's view-dependent part on a dented
    surface, which the zero-force references cannot measure, stays below it). A region
    with no measured pair is not admitted.
    """
    rows = _group(steps)
    mirror_res: list[np.ndarray] = []
    view_res: list[np.ndarray] = []
    for (p, a, f), k in rows.items():
        other = rows.get((p, round(180.0 - a, 6), f))
        if a >= NORMAL_ANGLE_DEG or other is None:
            continue
        r = _shape_residual(steps.depth_mm[k], steps.depth_mm[other][::-1])
        if r is not None:
            mirror_res.append(r)
        v = _shape_residual(steps.reference_h_mm[k], steps.reference_h_mm[other])
        if v is not None:
            view_res.append(v)
    by_condition: dict[tuple[float, float], list[int]] = {}
    for (p, a, f), k in sorted(rows.items()):
        by_condition.setdefault((a, f), []).append(k)
    same_res: list[np.ndarray] = []
    for ks in by_condition.values():
        for k, m in zip(ks, ks[1:]):           # each point against the next one at the same (angle, force)
            r = _shape_residual(steps.depth_mm[k], steps.depth_mm[m])
            if r is not None:
                same_res.append(r)
    if not mirror_res:
        return MirrorTest(False, None, None, 0, "not admitted: no angle was measured with its mirror "
                                                 "(180 - angle) at a point")
    residual_ms = float(np.mean(np.concatenate(mirror_res) ** 2))
    same_ms = float(np.mean(np.concatenate(same_res) ** 2)) if same_res else 0.0
    view_ms = float(np.mean(np.concatenate(view_res) ** 2)) if view_res else 0.0
    expected_ms = same_ms + 2.0 * view_ms
    residual, yardstick = float(np.sqrt(residual_ms)), float(np.sqrt(expected_ms))
    if not expected_ms > 0.0:
        return MirrorTest(False, residual, None, len(mirror_res),
                          "not admitted: nothing measured the region's repeatability")
    from scipy.special import fdtri   # training only, like scipy.interpolate above

    dof_yard = max(1, len(same_res) + len(view_res))
    limit = float(fdtri(len(mirror_res), dof_yard, 1.0 - false_rejection))
    peak = float(np.nanmax(np.concatenate([steps.depth_mm.ravel(), steps.tip_depth_mm.ravel(), [0.0]])))
    significant = residual_ms > limit * expected_ms
    matters = residual > MIRROR_MARGIN * peak
    admitted = not (significant and matters)
    verdict = "admitted" if admitted else "not admitted"
    return MirrorTest(admitted, residual, yardstick, len(mirror_res),
                      f"{verdict}: mirror residual {residual:.3f} mm against {yardstick:.3f} mm expected from "
                      f"repeatability ({len(same_res)} point pairs) and view ({len(view_res)} reference pairs), "
                      f"limit x{np.sqrt(limit):.2f}; {100.0 * residual / peak if peak > 0 else 0.0:.1f} % of the "
                      f"deepest dent {peak:.2f} mm (margin {100.0 * MIRROR_MARGIN:.0f} %)")


def _rigid_offset(a: np.ndarray, b: np.ndarray, min_samples: int = 8) -> float:
    """The median of a - b over the samples both have (0 if too few): what a rigid sink of
    the whole body along a slanted push adds to a and not to its mirror b."""
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < min_samples:
        return 0.0
    return float(np.median(a[ok] - b[ok]))


def _shape_residual(a: np.ndarray, b: np.ndarray, min_samples: int = 8) -> np.ndarray | None:
    """a - b over the samples both have, less its median (:func:`_rigid_offset`); None if too few."""
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < min_samples:
        return None
    r = a[ok] - b[ok]
    return r - np.median(r)


# --------------------------------------------------------------------------- completion

def complete_targets(steps: RegionSteps, tip_radius_mm: float) -> CompletedTargets:
    """Every sample of every step's profile with a value and a support code (module docstring)."""
    x = steps.x_mm
    m, length = steps.depth_mm.shape
    depth = np.array(steps.depth_mm, dtype=float, copy=True)
    support = np.full((m, length), UNSUPPORTED, dtype=np.int8)
    measured = np.isfinite(depth)
    support[measured] = MEASURED
    mirror = mirror_test(steps)
    power = tail_exponent(steps, tip_radius_mm)
    rows = _group(steps)
    if mirror.admitted:
        for (p, a, f), k in rows.items():
            other = rows.get((p, round(180.0 - a, 6), f))
            if other is None:
                continue
            mirrored = steps.depth_mm[other][::-1] + _rigid_offset(steps.depth_mm[k], steps.depth_mm[other][::-1])
            fill = ~np.isfinite(depth[k]) & np.isfinite(mirrored)
            depth[k, fill] = mirrored[fill]
            support[k, fill] = MIRRORED
    else:
        # Nothing supports the unseen side: rather than hold the last seen depth flat out to
        # the grid's end, guess that the dent falls off beyond the tip as it does on the seen
        # side (the row reflected about the tip), flagged unsupported.
        for k in range(m):
            _reflect_about_tip(x, depth[k], float(steps.tip_x_mm[k]))
    normal_rows = [k for k in range(m) if _is_normal(steps.angle_deg[k])]
    zones = {k: _normal_seen(x, depth[k], support[k], float(steps.tip_x_mm[k]), float(steps.tip_depth_mm[k]),
                             tip_radius_mm, mirror.admitted) for k in normal_rows}
    join_weight = contact.fit_join_weight(
        [(x, _supported(depth[k], support[k]), zones[k], _centre(steps.tip_x_mm[k]), float(steps.tip_depth_mm[k]))
         for k in normal_rows if zones[k].any()], tip_radius_mm)
    for k in normal_rows:
        _fill_normal(x, depth[k], support[k], zones[k], float(steps.tip_x_mm[k]), float(steps.tip_depth_mm[k]),
                     tip_radius_mm, power, join_weight)
    family = _normal_families(steps, depth, normal_rows)
    for k in range(m):
        if _is_normal(steps.angle_deg[k]):
            continue
        fam = family.get(int(steps.point_ids[k]))
        if mirror.admitted and fam is not None:
            _infer_oblique(x, depth[k], support[k], float(steps.force_n[k]), float(steps.angle_deg[k]), fam,
                           tip_radius_mm, float(steps.tip_x_mm[k]))
        _respect_tip(x, depth[k], float(steps.tip_x_mm[k]), float(steps.tip_depth_mm[k]), tip_radius_mm)
        depth[k] = fill_gaps(x, depth[k], _centre(steps.tip_x_mm[k]), power, tip_radius_mm)
    counts = {name: int(np.count_nonzero(support == code)) for code, name in enumerate(SUPPORT_NAMES)}
    return CompletedTargets(depth, support, mirror, counts, power)


def _centre(tip_x_mm: float) -> float:
    """The tip's position along t (0, the planned point, when the poses did not give it)."""
    return float(tip_x_mm) if np.isfinite(tip_x_mm) else 0.0


def _reflect_about_tip(x: np.ndarray, depth: np.ndarray, tip_x: float) -> None:
    """Missing samples from the row's own reflection about the tip's position (0 if unknown);
    the support code stays unsupported."""
    centre = _centre(tip_x)
    seen = np.isfinite(depth)
    if seen.sum() < 2:
        return
    reflected = np.interp(2.0 * centre - x, x[seen], depth[seen], left=np.nan, right=np.nan)
    gap = ~seen & np.isfinite(reflected)
    # Only where the reflection lands on seen samples (interp bridges gaps; keep to real ones).
    near = np.abs(np.interp(2.0 * centre - x[gap], x, np.where(seen, 0.0, 1.0))) < 0.5
    idx = np.flatnonzero(gap)[near]
    depth[idx] = reflected[idx]


def _supported(depth: np.ndarray, support: np.ndarray) -> np.ndarray:
    """The row with NaN wherever nothing supports its value (a guess stays out of a fit)."""
    return np.where(support == UNSUPPORTED, np.nan, depth)


def _normal_seen(x: np.ndarray, depth: np.ndarray, support: np.ndarray, tip_x: float, tip_depth: float,
                 radius: float, mirror_admitted: bool) -> np.ndarray:
    """A 90-degree row's supported samples in place: its own mirror (when admitted: the row
    is its own pair) and the tip within its half-width. Returns the tip's zone (L,) bool."""
    if mirror_admitted:
        own = depth[::-1].copy()
        fill = ~np.isfinite(depth) & np.isfinite(own)
        depth[fill] = own[fill]
        support[fill] = MIRRORED
    half = tip_half_width_mm(tip_depth, radius)
    zone = np.abs(x - tip_x) <= half if half > 0.0 else np.zeros(x.shape, dtype=bool)
    depth[zone] = sphere_depth_mm(x, tip_x, tip_depth, radius)[zone]
    support[zone] = TIP
    return zone


def _fill_normal(x: np.ndarray, depth: np.ndarray, support: np.ndarray, zone: np.ndarray, tip_x: float,
                 tip_depth: float, radius: float, tail_power: float, join_weight: float) -> None:
    """The rest of a 90-degree row in place: between the tip's zone and the first supported
    sample on each side the contact's shape (:mod:`contact`, flagged inferred), then the
    remaining gaps; every filled sample kept between the sphere (the surface cannot be above
    the tip) and the tip's depth (a normal push is deepest under the tip)."""
    sphere = sphere_depth_mm(x, tip_x, tip_depth, radius)
    gap = ~np.isfinite(depth)
    if zone.any():
        for g, inside, _ in contact.side_gaps(x, _supported(depth, support), zone, _centre(tip_x), tip_depth, radius):
            inside = inside[support[inside] == UNSUPPORTED]
            depth[inside] = contact.gap_fill(g, np.abs(x[inside] - _centre(tip_x)), join_weight)
            support[inside] = INFERRED
            gap[inside] = True
    filled = fill_gaps(x, depth, _centre(tip_x), tail_power, radius)
    if np.isfinite(tip_depth) and tip_depth > 0.0:
        under = gap & np.isfinite(sphere)
        filled[under] = np.clip(filled[under], sphere[under], tip_depth)
    depth[gap] = filled[gap]


def _normal_families(steps: RegionSteps, depth: np.ndarray, normal_rows: list[int]
                     ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Point -> (forces (K,), complete 90-degree profiles (K,L)), forces increasing, with
    the zero profile at 0 N first. Steps are grouped by their planned force level (the
    repeats of a level are averaged, and so are their measured forces): grouped by the
    measured force instead, two repeats a few mN apart would make two knots whose profiles
    differ by the scans' noise, and the interpolation between them swings by far more."""
    by_point: dict[int, dict[float, list[int]]] = {}
    for k in normal_rows:
        if np.all(np.isfinite(depth[k])):
            by_point.setdefault(int(steps.point_ids[k]), {}).setdefault(
                round(float(steps.force_level_n[k]), 6), []).append(k)
    out = {}
    for p, levels in by_point.items():
        groups = [levels[level] for level in sorted(levels)]
        forces = np.array([np.mean(steps.force_n[rows]) for rows in groups])
        profiles = np.array([np.mean(depth[rows], axis=0) for rows in groups])
        keep = np.concatenate([[True], np.diff(forces) > 0.0])   # the interpolation needs increasing forces
        out[p] = (np.concatenate([[0.0], forces[keep]]), np.vstack([np.zeros(profiles.shape[1]), profiles[keep]]))
    return out


def normal_profile_at(forces_n: np.ndarray, profiles_mm: np.ndarray, load_n: float) -> np.ndarray:
    """The 90-degree profile at normal load ``load_n``: monotone interpolation in force per
    sample between the measured levels (from the zero profile at 0 N); the deepest level's
    profile beyond the largest force."""
    f = np.asarray(forces_n, dtype=float)
    y = np.asarray(profiles_mm, dtype=float)
    if load_n >= f[-1]:
        return y[-1].copy()
    if f.shape[0] == 2:
        w = max(load_n, 0.0) / f[1]
        return (1.0 - w) * y[0] + w * y[1]
    from scipy.interpolate import PchipInterpolator

    return PchipInterpolator(f, y, axis=0)(max(load_n, 0.0))


def _infer_oblique(x: np.ndarray, depth: np.ndarray, support: np.ndarray, force_n: float, angle_deg: float,
                   family: tuple[np.ndarray, np.ndarray], radius: float, tip_x: float) -> None:
    """Unseen samples of an oblique row: the even part, the 90-degree profile E at the same
    normal load centred on the tip (s, its position along t, at most a tip radius off the
    point), plus the body's sink c, plus the tangential load's odd part O read off the seen
    side and reversed.

    A tangential load sinks the surface ahead of it and lifts it behind (Cerruti): with
    u = x - s, the row is E(u) + O(u) + c with O(-u) = -O(u), so the seen side gives
    O = depth - E - c there and the unseen side gets E - O + c. c is the median of
    depth - E over the seen samples at least ``ODD_FAR_RADII`` tip radii from the tip (where
    the odd part of a contact a few mm wide has fallen off; over the farther half of the
    seen samples if too few lie there). Between the tip and the first seen sample O runs
    monotonically from 0 (it is odd) to its first seen value (the seen side's own gap is
    filled the same way); beyond the last, it falls off as 1/|u| (Cerruti's far field).

    Offsetting E by the mean difference to the seen side (before) put the seen side's odd
    part on the unseen side with the wrong sign: on the demo pillow the 170-degree rows'
    far side came out 1-3 mm too deep.
    """
    seen = np.isfinite(depth)
    if not seen.any():
        return
    even = normal_profile_at(*family, force_n * np.sin(np.radians(angle_deg)))
    if not float(np.max(even)) > 0.0:
        return
    s = float(np.clip(tip_x, -radius, radius)) if np.isfinite(tip_x) else 0.0
    u = x - s
    even = np.interp(u, x, even)
    far = seen & (np.abs(u) >= ODD_FAR_RADII * radius)
    if far.sum() < 3:
        far = seen & (np.abs(u) >= np.median(np.abs(u[seen])))
    c = float(np.median(depth[far] - even[far]))
    lead = 1.0 if np.mean(u[seen]) >= 0.0 else -1.0      # the side the scanner saw
    on_lead = seen & (lead * u > 0.0)
    if not on_lead.any():
        return
    order = np.argsort(np.abs(u[on_lead]))
    known_u = np.concatenate([[0.0], np.abs(u[on_lead])[order]])
    known_odd = np.concatenate([[0.0], (depth - even - c)[on_lead][order]])
    from scipy.interpolate import PchipInterpolator

    r = np.abs(u)
    odd = PchipInterpolator(known_u, known_odd, extrapolate=False)(np.minimum(r, known_u[-1]))
    beyond = r > known_u[-1]
    odd[beyond] = known_odd[-1] * known_u[-1] / r[beyond]
    # The reversed odd part may lift the far side above the surface (as Cerruti's does),
    # but no higher than the row's own highest seen sample: nothing measured such a rise.
    floor = min(0.0, float(np.min(depth[seen])))
    inferred = np.maximum(even + np.where(lead * u > 0.0, odd, -odd) + c, floor)
    fill = ~seen
    depth[fill] = inferred[fill]
    support[fill] = INFERRED


def _respect_tip(x: np.ndarray, depth: np.ndarray, tip_x: float, tip_depth: float, radius: float) -> None:
    """The surface cannot be above the tip's lower surface: raise no sample, deepen any the
    sphere passes below (finite samples only)."""
    if not np.isfinite(tip_depth):
        return
    sphere = sphere_depth_mm(x, tip_x, tip_depth, radius)
    under = np.isfinite(sphere) & np.isfinite(depth) & (depth < sphere)
    depth[under] = sphere[under]


# --------------------------------------------------------------------------- serving

def support_table(force_level_n: np.ndarray, angle_deg: np.ndarray, support: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Support codes per trained angle and force level: (forces (F,), angles (A,), codes
    (A,F,L) int8), each cell the most common code over the region's points (the weaker code
    on a tie). A force level not measured at an angle takes the nearest level's codes
    at that angle."""
    levels = np.round(np.asarray(force_level_n, dtype=float), 6)
    angles = np.round(np.asarray(angle_deg, dtype=float), 6)
    codes = np.asarray(support, dtype=np.int8)
    forces_u, angles_u = np.unique(levels), np.unique(angles)
    table = np.full((angles_u.size, forces_u.size, codes.shape[1]), UNSUPPORTED, dtype=np.int8)
    for i, a in enumerate(angles_u):
        have = []
        for j, f in enumerate(forces_u):
            rows = codes[(angles == a) & (levels == f)]
            if rows.shape[0]:
                counts = np.stack([(rows == c).sum(axis=0) for c in range(len(SUPPORT_NAMES))])
                # argmax picks the first maximum: reversed, ties go to the weaker support.
                table[i, j] = len(SUPPORT_NAMES) - 1 - np.argmax(counts[::-1], axis=0)
                have.append(j)
        for j in range(forces_u.size):
            if j not in have and have:
                table[i, j] = table[i, min(have, key=lambda k: abs(forces_u[k] - forces_u[j]))]
    return forces_u, angles_u, table
