"""The dent between the tip's contact and the first sample the scanner saw, under a normal push.

The probe hides the surface around its tip: under a normal push the scanner's first sample
on each side lies a few mm beyond the zone where the tip's sphere stands in for the surface
(:func:`support.tip_half_width_mm`). Across that gap the surface first stays on the sphere
out to the edge of the contact, then leaves it with the sphere's slope and flattens
towards the seen samples. Two shapes bracket what materials do there, and the region's own
measurements choose between them:

- **Hertz's free surface** (an elastic half-space under a sphere): beyond the contact
  radius a the surface is ``b + A H(r / a)``, H(rho) = (2/pi)((2 - rho^2) asin(1/rho) +
  sqrt(rho^2 - 1)) (H(1) = 1, H'(1) = -2, H ~ 4/(3 pi rho) far away), continuous in value
  and slope with the sphere at a (A = -a s'(a) / 2, b = s(a) - A; b is the rest of the
  body's sink), a solved so that the curve meets the first seen sample. A contact that
  grows as Hertz's (a layer, a plate, a rubber) leaves the sphere late and steeply.
- **The smoothest join**: the cubic through the tip zone's edge and the first seen sample,
  continuous in value and slope with both (the sphere's slope at the zone's edge, the seen
  samples' at theirs). A soft foam whose contact spreads wider than Hertz's leaves the
  sphere earlier and more gently than Hertz's shape, and lies nearer this one.

The fill is w x the join + (1 - w) x Hertz's shape, w fitted per region by holding back
(:func:`fit_join_weight`): on every normal row the seen samples within one tip radius of
the first are treated as unseen, filled from the next ones, and compared with what was
measured there. On the simulator's objects (the demo's box, a plate on foam, and foam
pillow; the rubber ball, sessions 1 and 2; generated objects 1001, 1004, 1006 and 1008,
elastomers and sponges) the held-back choice of w cut the gap's error against the truth
from 0.025-0.48 mm RMS (plain monotone interpolation, before) to 0.004-0.13 mm in 12 of 13
regions (one sponge region of 1008 went from 0.025 to 0.029 mm).

Distances r are along t from the tip, outward (> 0); depths in mm along -n.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# How many seen samples beyond the gap give the slope there, and how far beyond the first
# seen sample (in tip radii) the held-back check reaches.
SLOPE_SAMPLES = 5
HOLD_BACK_RADII = 1.0
# The least share of Hertz's free surface a seen dent reaches (:func:`saw_its_dent`).
MIN_SEEN_FRACTION = 0.1


@dataclass(frozen=True)
class Gap:
    """One side of one row: the sphere (tip depth and radius), the zone's edge r0, the first
    seen sample at r1 with its depth and outward slope, all in mm."""

    tip_depth_mm: float
    radius_mm: float
    r0_mm: float
    r1_mm: float
    depth1_mm: float
    slope1: float

    def sphere(self, r: np.ndarray | float) -> np.ndarray:
        rr = np.minimum(np.abs(np.asarray(r, dtype=float)), self.radius_mm)
        return self.tip_depth_mm - self.radius_mm + np.sqrt(self.radius_mm ** 2 - rr ** 2)

    def sphere_slope(self, r: float) -> float:
        return -r / np.sqrt(max(self.radius_mm ** 2 - r * r, 1e-12))


def hertz_free_surface(rho: np.ndarray) -> np.ndarray:
    """Hertz's surface outside the contact, normalised to 1 at the contact's edge (rho = r / a >= 1)."""
    q = np.maximum(np.asarray(rho, dtype=float), 1.0)
    return (2.0 / np.pi) * ((2.0 - q * q) * np.arcsin(1.0 / q) + np.sqrt(q * q - 1.0))


def saw_its_dent(x_mm: np.ndarray, depth_mm: np.ndarray, tip_x_mm: float, tip_depth_mm: float,
                 radius_mm: float, noise_mm: float, min_fraction: float = MIN_SEEN_FRACTION) -> bool:
    """Whether a normal push's profile (``depth_mm`` on ``x_mm``, NaN unseen) saw the dent the
    tip made (the tip's lowest point ``tip_depth_mm`` deep at ``tip_x_mm``, from the arm's poses).

    It did unless its deepest seen sample stays below ``min_fraction`` of Hertz's free
    surface at the seen sample nearest the tip (for a contact of radius sqrt(R d): what the
    surface an elastic body bends around the tip still sinks there) by more than 3
    ``noise_mm`` (the standard error of an averaged profile). Past a low rim the line runs
    on over the table, which does not move: a sponge pressed 2 mm deep then reads 0.000 mm
    at every seen sample, while Hertz's surface is 0.6 mm down at the first of them. The
    noise term keeps a stiff material's dent, which Hertz puts below the noise 4 mm out,
    from being refuted by the noise itself (a profile whose every sample the scanner's
    correlated floor put below zero included). See docs/generated_objects.md for the figures.
    True (nothing to refute) without a seen sample or a dent.
    """
    x = np.asarray(x_mm, dtype=float)
    d = np.asarray(depth_mm, dtype=float)
    seen = np.isfinite(d)
    if not seen.any() or not np.isfinite(tip_depth_mm) or tip_depth_mm <= 0.0 or not np.isfinite(tip_x_mm):
        return True
    a = float(np.sqrt(radius_mm * tip_depth_mm))
    nearest_mm = float(np.min(np.abs(x[seen] - tip_x_mm)))
    expected_mm = 0.5 * tip_depth_mm * float(hertz_free_surface(max(nearest_mm, a) / a))
    threshold_mm = min_fraction * expected_mm - 3.0 * noise_mm
    # Without power (the share of Hertz's figure within the noise) nothing is refuted: a
    # stiff dent's profile offset below zero by the scanner's correlated floor is noise.
    return bool(threshold_mm <= 0.0 or np.max(d[seen]) >= threshold_mm)


def join_fill(gap: Gap, r: np.ndarray) -> np.ndarray:
    """The cubic continuous in value and slope with the sphere at r0 and the seen samples at r1."""
    h = gap.r1_mm - gap.r0_mm
    t = (np.asarray(r, dtype=float) - gap.r0_mm) / h
    p0, m0 = float(gap.sphere(gap.r0_mm)), gap.sphere_slope(gap.r0_mm)
    return ((2 * t ** 3 - 3 * t ** 2 + 1) * p0 + (t ** 3 - 2 * t ** 2 + t) * h * m0
            + (-2 * t ** 3 + 3 * t ** 2) * gap.depth1_mm + (t ** 3 - t ** 2) * h * gap.slope1)


def hertz_fill(gap: Gap, r: np.ndarray) -> np.ndarray:
    """Hertz's free surface leaving the sphere at the contact edge a in [r0, min(r1, R)),
    a chosen so that it meets the first seen sample (the nearer end when none does)."""
    from scipy.optimize import brentq   # training only: predict needs nothing here

    def shape(a: float) -> tuple[float, float]:
        amp = -a * gap.sphere_slope(a) / 2.0
        return amp, float(gap.sphere(a)) - amp

    def miss(a: float) -> float:
        amp, base = shape(a)
        return base + amp * float(hertz_free_surface(gap.r1_mm / a)) - gap.depth1_mm

    lo, hi = gap.r0_mm, min(gap.r1_mm, gap.radius_mm) * (1.0 - 1e-6)
    if hi <= lo:
        a = lo
    elif miss(lo) * miss(hi) < 0.0:
        a = brentq(miss, lo, hi)
    else:
        a = lo if abs(miss(lo)) <= abs(miss(hi)) else hi
    amp, base = shape(a)
    rr = np.asarray(r, dtype=float)
    return np.where(rr <= a, gap.sphere(rr), base + amp * hertz_free_surface(rr / max(a, 1e-9)))


def gap_fill(gap: Gap, r: np.ndarray, join_weight: float) -> np.ndarray:
    """The fill at distances r (r0 < r < r1): w x :func:`join_fill` + (1 - w) x :func:`hertz_fill`."""
    return join_weight * join_fill(gap, r) + (1.0 - join_weight) * hertz_fill(gap, r)


def side_gaps(x_mm: np.ndarray, depth_mm: np.ndarray, in_zone: np.ndarray, tip_x_mm: float, tip_depth_mm: float,
              radius_mm: float) -> list[tuple[Gap, np.ndarray, np.ndarray]]:
    """Each side's gap of one row: (gap, indices of the unseen samples in it, indices of the
    seen samples beyond it, nearest first). ``in_zone``: the samples the sphere stands in
    for; seen: finite samples outside it. A side without a zone edge or a seen sample beyond
    it has no gap."""
    out = []
    seen = np.isfinite(depth_mm) & ~in_zone
    for side in (-1.0, 1.0):
        r = side * (np.asarray(x_mm, dtype=float) - tip_x_mm)
        outward = np.flatnonzero(r > 0.0)
        outward = outward[np.argsort(r[outward])]
        zone = outward[in_zone[outward]]
        if zone.size == 0:
            continue
        r0 = float(r[zone[-1]])
        beyond = outward[seen[outward] & (r[outward] > r0)]
        if beyond.size == 0:
            continue
        first = beyond[0]
        inside = outward[(r[outward] > r0) & (r[outward] < r[first])]
        if inside.size == 0:
            continue
        nxt = beyond[:SLOPE_SAMPLES]
        slope = float(np.polyfit(r[nxt], depth_mm[nxt], 1)[0]) if nxt.size >= 3 else 0.0
        out.append((Gap(float(tip_depth_mm), float(radius_mm), r0, float(r[first]), float(depth_mm[first]),
                        min(slope, 0.0)), inside, beyond))
    return out


def fit_join_weight(rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, float, float]], radius_mm: float,
                    default: float = 1.0) -> float:
    """The region's w in [0, 1] by holding back: ``rows`` are (x, depth with the zone filled
    by the sphere and NaN unseen, in_zone mask, tip x, tip depth) of its normal rows. For
    each side the seen samples within ``HOLD_BACK_RADII`` tip radii of the first are filled
    from the next seen ones; w minimises the squared misses over all of them (closed form).
    ``default`` (the smoothest join) when no side has enough seen samples to hold back."""
    join_miss: list[np.ndarray] = []
    hertz_miss: list[np.ndarray] = []
    for x, depth, in_zone, tip_x, tip_depth in rows:
        for gap, _, beyond in side_gaps(x, depth, in_zone, tip_x, tip_depth, radius_mm):
            r = np.abs(x - tip_x)
            held = beyond[r[beyond] <= gap.r1_mm + HOLD_BACK_RADII * radius_mm]
            rest = beyond[r[beyond] > gap.r1_mm + HOLD_BACK_RADII * radius_mm]
            if held.size < 2 or rest.size < 3:
                continue
            nxt = rest[:SLOPE_SAMPLES]
            slope = min(float(np.polyfit(r[nxt], depth[nxt], 1)[0]), 0.0)
            back = Gap(gap.tip_depth_mm, gap.radius_mm, gap.r0_mm, float(r[rest[0]]), float(depth[rest[0]]), slope)
            join_miss.append(join_fill(back, r[held]) - depth[held])
            hertz_miss.append(hertz_fill(back, r[held]) - depth[held])
    if not join_miss:
        return default
    a, b = np.concatenate(join_miss), np.concatenate(hertz_miss)
    spread = float(np.sum((a - b) ** 2))
    if not spread > 0.0:
        return default
    return float(np.clip(np.sum(b * (b - a)) / spread, 0.0, 1.0))
