"""Deformation profiles: scans -> object frame -> depth on a fixed grid.

A profile is the depth of the surface along ``-n`` (mm, positive into the object)
relative to a zero-force reference scan of the same place, sampled on a fixed grid
of ``L`` positions ``x_mm`` along the scan direction ``t`` centred on the contact
point ``p``. Every scan is mapped through the TCP pose at its exposure into the
object frame first, so profiles are comparable across forces, angles and points.

Frames: scanner (x along the laser line, z along the optical axis, y = 0 is the
laser plane) -> tcp (``tcp <- scanner``) -> base (``base <- tcp`` at exposure) ->
object (``base <- object`` is the registration). Missing samples are NaN throughout.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..core.geometry import Pose

# A gap between two valid samples wider than this many sample spacings is not
# bridged by interpolation: the surface there was not seen (shadow, dark texture).
GAP_SPACINGS: float = 3.0
# Steeper than 60 degrees from the tangent plane at the contact, the line has left the
# probed face (a rim, a wall): rise over run.
MAX_FACE_SLOPE: float = float(np.tan(np.radians(60.0)))


@dataclass(frozen=True)
class ProfileGrid:
    """The fixed sampling grid of profiles: ``samples`` positions over ``span_mm``, centred on 0."""

    span_mm: float = 80.0
    samples: int = 256

    def __post_init__(self) -> None:
        if not (self.span_mm > 0.0) or self.samples < 2:
            raise ValueError("ProfileGrid needs span_mm > 0 and samples >= 2")

    @property
    def x_mm(self) -> np.ndarray:
        """(L,) sample positions along t (mm), symmetric about the contact point."""
        return np.linspace(-self.span_mm / 2.0, self.span_mm / 2.0, self.samples)

    @property
    def spacing_mm(self) -> float:
        return self.span_mm / (self.samples - 1)


def scan_to_object_points(scan_x_mm: np.ndarray, scan_z_mm: np.ndarray, base_to_tcp: Pose,
                          tcp_to_scanner: Pose, base_to_object: Pose) -> np.ndarray:
    """Map one scan (scanner frame, mm) into the object frame: (L,3), NaN rows where missing.

    ``base_to_tcp`` is the TCP pose at the scan's exposure (``base <- tcp``).
    """
    x = np.asarray(scan_x_mm, dtype=float).reshape(-1)
    z = np.asarray(scan_z_mm, dtype=float).reshape(-1)
    if x.shape != z.shape:
        raise ValueError(f"scan x and z lengths differ: {x.shape} vs {z.shape}")
    pts_scanner = np.column_stack([x, np.zeros_like(x), z])
    object_to_scanner = base_to_object.inverse().compose(base_to_tcp).compose(tcp_to_scanner)
    pts = object_to_scanner.apply(pts_scanner)
    pts[~(np.isfinite(x) & np.isfinite(z))] = np.nan
    return pts


def step_scan_points(scans_xz_mm: np.ndarray, tcp_poses: np.ndarray, tcp_to_scanner: Pose,
                     base_to_object: Pose) -> list[np.ndarray]:
    """All scans of one step into the object frame.

    ``scans_xz_mm`` (S,L,2): scanner-frame x, z; ``tcp_poses`` (S,6): ``base <- tcp`` at each
    exposure as mm + rotation vector (rad), the storage form of :meth:`Pose.to_list`.
    """
    xz = np.asarray(scans_xz_mm, dtype=float)
    poses = np.asarray(tcp_poses, dtype=float).reshape(-1, 6)
    if xz.ndim != 3 or xz.shape[2] != 2 or xz.shape[0] != poses.shape[0]:
        raise ValueError(f"expected (S,L,2) scans and (S,6) poses, got {xz.shape} and {poses.shape}")
    return [scan_to_object_points(xz[i, :, 0], xz[i, :, 1], Pose.from_list(poses[i]),
                                  tcp_to_scanner, base_to_object) for i in range(xz.shape[0])]


def local_coordinates(points_mm: np.ndarray, contact_point_mm: np.ndarray, normal: np.ndarray,
                      t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, h) of object-frame points: x = (q - p)·t along the scan, h = (q - p)·n height (mm)."""
    q = np.asarray(points_mm, dtype=float).reshape(-1, 3) - np.asarray(contact_point_mm, dtype=float)
    n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    tt = np.asarray(t, dtype=float) / np.linalg.norm(t)
    return q @ tt, q @ n


def resample_on_grid(x_mm: np.ndarray, values: np.ndarray, grid_x_mm: np.ndarray,
                     max_gap_mm: float | None = None) -> np.ndarray:
    """Linear interpolation of scattered (x, value) onto ``grid_x_mm`` without bridging gaps.

    NaN outside the valid samples' x range (no extrapolation) and inside any gap between
    consecutive valid samples wider than ``max_gap_mm`` (default: ``GAP_SPACINGS`` times
    the larger of the grid spacing and the scan's own median spacing).
    """
    grid = np.asarray(grid_x_mm, dtype=float)
    x = np.asarray(x_mm, dtype=float).reshape(-1)
    v = np.asarray(values, dtype=float).reshape(-1)
    ok = np.isfinite(x) & np.isfinite(v)
    out = np.full(grid.shape, np.nan)
    if np.count_nonzero(ok) < 2:
        return out
    order = np.argsort(x[ok], kind="stable")
    xs, vs = x[ok][order], v[ok][order]
    steps = np.diff(xs)
    if max_gap_mm is None:
        grid_step = float(np.median(np.diff(grid))) if grid.size > 1 else 0.0
        native = float(np.median(steps[steps > 0])) if np.any(steps > 0) else 0.0
        max_gap_mm = GAP_SPACINGS * max(grid_step, native)
    out = np.interp(grid, xs, vs)
    inside = (grid >= xs[0]) & (grid <= xs[-1])
    # The valid pair enclosing each grid sample; a sample inside a wide gap stays missing.
    right = np.clip(np.searchsorted(xs, grid, side="left"), 1, xs.size - 1)
    gap = xs[right] - xs[right - 1]
    exact = np.isclose(grid, xs[right]) | np.isclose(grid, xs[right - 1])
    out[~inside | ((gap > max_gap_mm) & ~exact)] = np.nan
    return out


def scan_segments(x_mm: np.ndarray, h_mm: np.ndarray) -> list[np.ndarray]:
    """Indices of the continuous pieces of one scan line, in the scanner's sample order.

    A line over an object is not a function of x: past a rim it runs down a wall and on
    across the table, which in the probe's (t, n) frame lies under the surface at the same
    x. Consecutive valid samples belong to one piece unless more than ``GAP_SPACINGS``
    samples are missing between them or the step between them is longer than
    ``GAP_SPACINGS`` times the line's typical step per sample (an occlusion: the ray jumped
    to another surface).
    """
    x = np.asarray(x_mm, dtype=float).reshape(-1)
    h = np.asarray(h_mm, dtype=float).reshape(-1)
    idx = np.flatnonzero(np.isfinite(x) & np.isfinite(h))
    if idx.size < 2:
        return [idx] if idx.size else []
    step = np.hypot(np.diff(x[idx]), np.diff(h[idx]))
    missing = np.diff(idx)
    adjacent = step[missing == 1]
    typical = float(np.median(adjacent)) if adjacent.size else float(np.median(step / missing))
    cut = (missing > GAP_SPACINGS) | (step > GAP_SPACINGS * missing * max(typical, 1e-9))
    return np.split(idx, np.flatnonzero(cut) + 1)


def height_on_grid(points_mm: np.ndarray, contact_point_mm: np.ndarray, normal: np.ndarray,
                   t: np.ndarray, grid: ProfileGrid, max_gap_mm: float | None = None) -> np.ndarray:
    """Surface height h (mm along n) of one object-frame scan on the grid, NaN where unseen.

    ``points_mm`` in the scanner's sample order. Each continuous piece of the line
    (:func:`scan_segments`) is resampled on its own and the grid keeps the highest piece
    at each x: the surface seen from above along n, never a blend of the object's top
    and the table beneath its rim.
    """
    x, h = local_coordinates(points_mm, contact_point_mm, normal, t)
    out = np.full(grid.samples, np.nan)
    for piece in scan_segments(x, h):
        if piece.size >= 2:
            out = np.fmax(out, resample_on_grid(x[piece], h[piece], grid.x_mm, max_gap_mm))
    return out


def reference_height(reference_points: Sequence[np.ndarray], contact_point_mm: np.ndarray,
                     normal: np.ndarray, t: np.ndarray, grid: ProfileGrid,
                     max_gap_mm: float | None = None) -> np.ndarray:
    """NaN-aware mean height (L,) of the zero-force reference scans of the same place."""
    heights = np.stack([height_on_grid(r, contact_point_mm, normal, t, grid, max_gap_mm)
                        for r in reference_points])
    return average_profiles(heights)[0]


def scan_depths(scan_points: Sequence[np.ndarray], contact_point_mm: np.ndarray, normal: np.ndarray,
                t: np.ndarray, grid: ProfileGrid, reference_points: Sequence[np.ndarray],
                max_gap_mm: float | None = None) -> np.ndarray:
    """Depth (S,L) of each scan: ``h_ref(x) - h(x)`` (mm, positive into the object), NaN missing."""
    if len(reference_points) == 0:
        raise ValueError("a profile needs at least one zero-force reference scan")
    h_ref = reference_height(reference_points, contact_point_mm, normal, t, grid, max_gap_mm)
    if len(scan_points) == 0:
        return np.zeros((0, grid.samples))
    h = np.stack([height_on_grid(s, contact_point_mm, normal, t, grid, max_gap_mm) for s in scan_points])
    return h_ref[None, :] - h


def profile_from_scans(scan_points: Sequence[np.ndarray], contact_point_mm: np.ndarray,
                       normal: np.ndarray, t: np.ndarray, grid: ProfileGrid,
                       reference_points: Sequence[np.ndarray],
                       max_gap_mm: float | None = None) -> np.ndarray:
    """The averaged depth profile (L,) of one force step (mm along -n), NaN where never seen.

    ``scan_points``: the step's scans already in the object frame (see
    :func:`scan_to_object_points`); ``reference_points``: the zero-force reference scans.
    Use :func:`scan_depths` + :func:`average_profiles` to also get counts and spread.
    """
    return average_profiles(scan_depths(scan_points, contact_point_mm, normal, t, grid,
                                        reference_points, max_gap_mm))[0]


def average_profiles(depths_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """NaN-aware statistics over scans: (mean (L,), count (L,), std (L,)).

    ``std`` is the sample standard deviation of the single scans (ddof=1; NaN where
    fewer than two scans saw the sample); the mean's standard error is ``std/sqrt(count)``.
    """
    d = np.asarray(depths_mm, dtype=float)
    if d.ndim == 1:
        d = d[None, :]
    ok = np.isfinite(d)
    count = ok.sum(axis=0)
    filled = np.where(ok, d, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = filled.sum(axis=0) / count
        dev2 = np.where(ok, (d - mean[None, :]) ** 2, 0.0).sum(axis=0)
        std = np.sqrt(dev2 / (count - 1))
    mean = np.where(count > 0, mean, np.nan)
    std = np.where(count > 1, std, np.nan)
    return mean, count.astype(np.int64), std


def far_field_error_mm(depth_mm: np.ndarray, x_mm: np.ndarray, inner_mm: float, min_samples: int = 8
                       ) -> np.ndarray:
    """(N,2) what averaged profiles (N,L) read beyond ``inner_mm`` of the contact: per profile
    the median depth there (mm; the error common to the line) and the scatter of one sample
    (mm; 1.4826 x the median absolute difference of neighbouring samples over sqrt(2)).
    NaN where fewer than ``min_samples`` samples are seen that far out.

    Where a stiff material's dent has faded (an elastic dent falls as 1/r: a few per cent
    of its peak 15-40 mm out) the depth is the measurement's own error:
    the loaded burst's and the reference burst's correlated shapes (the scanner's floor,
    common to all scans of one burst, so no number of scans averages it out) and each
    sample's independent noise from both. The scatter of the loaded scans about their mean
    sees only the last of these. A soft material's dent reaches further: its far field
    overstates the error, harmless beside a dent of millimetres.
    """
    d = np.asarray(depth_mm, dtype=float)
    d = d[None, :] if d.ndim == 1 else d
    far = np.abs(np.asarray(x_mm, dtype=float)) > inner_mm
    out = np.full((d.shape[0], 2), np.nan)
    for i, row in enumerate(d):
        seen = row[far & np.isfinite(row)]
        if seen.size >= min_samples:
            out[i] = np.median(seen), 1.4826 * np.median(np.abs(np.diff(seen))) / np.sqrt(2.0)
    return out


@dataclass(frozen=True)
class RobustMean:
    """A step's averaged profile after outlier rejection, and what was rejected.

    ``mean_mm`` (L,) NaN where nothing is left; ``count`` (L,) scans kept per sample;
    ``stderr_mm`` (L,) standard error of the mean (NaN with fewer than two scans);
    ``rejected_scan_samples``: single-scan values dropped across scans;
    ``rejected_line_samples``: averaged samples blanked as spikes along the line.
    """

    mean_mm: np.ndarray
    count: np.ndarray
    stderr_mm: np.ndarray
    rejected_scan_samples: int
    rejected_line_samples: int


def robust_mean(depths_mm: np.ndarray, k_mad: float = 4.0, k_line: float = 6.0) -> RobustMean:
    """Mean over scans (S,L) that rejects scattered returns across scans and along the line.

    Across scans: per sample, values beyond ``k_mad`` scaled MADs of the scans' median
    are dropped (a laser on dark, rough fabric returns single scans millimetres off; a
    plain mean keeps them as spikes). Samples seen by fewer than 3 scans keep a plain mean.
    Along the line: an averaged sample that its neighbours do not predict
    (:func:`line_spikes`, ``k_line``) is blanked. A smooth dent, steep or not, is predicted
    by its neighbours; a sample that a few scans pulled off is not.
    """
    d = np.asarray(depths_mm, dtype=float)
    if d.ndim == 1:
        d = d[None, :]
    samples = d.shape[-1]
    if d.shape[0] == 0:
        nan = np.full(samples, np.nan)
        return RobustMean(nan, np.zeros(samples, np.int64), nan.copy(), 0, 0)
    seen = np.isfinite(d)
    count_all = seen.sum(axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=RuntimeWarning)
        med = np.nanmedian(d, axis=0)
        mad = np.nanmedian(np.abs(d - med), axis=0)
    scale = np.maximum(1.4826 * np.nan_to_num(mad), 1e-3)
    with np.errstate(invalid="ignore"):
        keep = seen & ((np.abs(d - med) <= k_mad * scale) | (count_all < 3)[None, :])
    mean, count, std = average_profiles(np.where(keep, d, np.nan))
    with np.errstate(invalid="ignore", divide="ignore"):
        stderr = std / np.sqrt(count)
    rejected_scans = int(np.count_nonzero(seen & ~keep))
    spikes = line_spikes(mean, stderr, k_line)
    mean = np.where(spikes, np.nan, mean)
    return RobustMean(mean, count, stderr, rejected_scans, int(np.count_nonzero(spikes)))


def line_spikes(profile_mm: np.ndarray, stderr_mm: np.ndarray | None = None, k: float = 6.0,
                passes: int = 4) -> np.ndarray:
    """(L,) True where a sample stands out of its neighbours along the line.

    Each finite sample is predicted from its neighbours: the median of the straight line
    through the samples either side, and the straight lines through the two on its left and
    the two on its right (so a sample at the edge of a gap, on a steep dent wall, is
    predicted by extrapolating along the wall, not by a flat median). A sample whose
    residual exceeds ``k`` times the robust scatter (1.4826 MAD) of all residuals, and ``k``
    standard errors when given, and is the largest such residual among its neighbours, is
    flagged; the prediction is repeated without it (``passes`` times at most), so one spike
    does not make its neighbours look like spikes. ``k`` = 6: a Gaussian residual passes
    6 sigma about once in 5e8 samples, so only values some scans pulled off go.
    """
    v = np.asarray(profile_mm, dtype=float).copy()
    out = np.zeros(v.shape, dtype=bool)
    se = None if stderr_mm is None else np.asarray(stderr_mm, dtype=float)
    for _ in range(passes):
        resid = _neighbour_residuals(v)
        known = np.isfinite(resid)
        if known.sum() < 5:
            break
        scatter = 1.4826 * float(np.median(np.abs(resid[known])))
        limit = np.full(v.shape, k * max(scatter, 1e-4))
        if se is not None:
            limit = np.fmax(limit, k * se)
        size = np.where(known, np.abs(resid), 0.0)
        padded = np.pad(size, 2)
        local_max = size >= np.max(np.lib.stride_tricks.sliding_window_view(padded, 5), axis=1)
        flag = known & (size > limit) & local_max
        if not flag.any():
            break
        out |= flag
        v[flag] = np.nan
    return out


def _neighbour_residuals(v: np.ndarray) -> np.ndarray:
    """v minus its prediction from neighbours (see :func:`line_spikes`); NaN where unknown."""
    pad = np.pad(v, 2, constant_values=np.nan)
    l2, l1, r1, r2 = pad[:-4], pad[1:-3], pad[3:-1], pad[4:]
    candidates = np.stack([0.5 * (l1 + r1), 2.0 * l1 - l2, 2.0 * r1 - r2])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=RuntimeWarning)
        predicted = np.nanmedian(candidates, axis=0)
    return v - predicted


def probed_face(reference_h_mm: np.ndarray, x_mm: np.ndarray, max_slope: float = MAX_FACE_SLOPE) -> np.ndarray:
    """(L,) True on the face the probe pressed: from the contact outwards while the reference
    surface stays within ``max_slope`` (rise over run) of the tangent plane.

    Past an object's rim the line runs down a wall and on over the table (or onto a
    neighbouring part): heights there belong to another surface, and a depth against
    them says nothing about this dent. The walk starts at the finite sample nearest
    x = 0 and stops, each way, at the first step steeper than ``max_slope`` (gaps are
    judged by the slope across them). The sample before such a step is not on the face
    either (the contact's own sample excepted): its bin straddles the edge, and a line
    shifted a fraction of a sample between the reference and the loaded scans reads the
    wall's drop there as a dent of millimetres. NaN samples inside the face stay False.
    """
    h = np.asarray(reference_h_mm, dtype=float)
    x = np.asarray(x_mm, dtype=float)
    out = np.zeros(h.shape, dtype=bool)
    idx = np.flatnonzero(np.isfinite(h))
    if idx.size == 0:
        return out
    start = int(np.argmin(np.abs(x[idx])))
    out[idx[start]] = True
    for order in (idx[start:], idx[:start + 1][::-1]):
        for a, b in zip(order, order[1:]):
            if abs(h[b] - h[a]) > max_slope * abs(x[b] - x[a]):
                out[a] = a == idx[start]
                break
            out[b] = True
    return out


@dataclass(frozen=True)
class StepMeasurement:
    """One force step's profile and the facts behind it (see :func:`measure_step`).

    ``depth_mm`` (L,) averaged depth along -n, NaN where not measured or rejected;
    ``stderr_mm`` (L,) its standard error over the scans; ``reference_h_mm`` (L,) the
    zero-force surface's height along n (the reference scans'); ``tip_x_mm`` where the tip's
    centre was along t while loaded; ``tip_depth_mm`` how far the tip's lowest point was
    below the reference surface there (mm, from the arm's own poses; NaN if unknown).
    The counts say how many samples were dropped and why.
    """

    depth_mm: np.ndarray
    stderr_mm: np.ndarray
    reference_h_mm: np.ndarray
    tip_x_mm: float
    tip_depth_mm: float
    rejected_scan_samples: int
    rejected_line_samples: int
    implausible_samples: int
    off_face_samples: int

    def facts(self) -> dict[str, float | int | None]:
        """JSON-able summary for the journal (the step result's ``summary``)."""
        def num(v: float) -> float | None:
            return round(float(v), 6) if np.isfinite(v) else None
        return {"tip_x_mm": num(self.tip_x_mm), "tip_depth_mm": num(self.tip_depth_mm),
                "rejected_scan_samples": self.rejected_scan_samples,
                "rejected_line_samples": self.rejected_line_samples,
                "implausible_samples": self.implausible_samples, "off_face_samples": self.off_face_samples}


def measure_step(scan_points: Sequence[np.ndarray], reference_points: Sequence[np.ndarray],
                 tip_centres_mm: np.ndarray, contact_point_mm: np.ndarray, normal: np.ndarray, t: np.ndarray,
                 grid: ProfileGrid, tip_radius_mm: float, margin_mm: float = 2.0) -> StepMeasurement:
    """A step's averaged profile from its scans, all in the object frame.

    ``scan_points``/``reference_points``: the loaded and zero-force scans (see
    :func:`step_scan_points`); ``tip_centres_mm`` (S,3): the tip's centre (the TCP) at
    each loaded exposure. The depth is the reference height minus each scan's height,
    averaged by :func:`robust_mean`; samples off the probed face (:func:`probed_face`)
    are dropped, and so are depths the probe cannot have made: deeper than the tip's
    own indentation plus ``margin_mm`` or above the surface by more than ``margin_mm``
    (occlusion artefacts where the reference and the loaded scans saw different things).
    The face is cut before averaging, so the line-spike test judges a sample by the face's
    own scatter: past a box's edge the wall and the foam below read residuals of
    millimetres, which let a sample a single scan caught at the tool shadow's edge, 0.06 mm
    off a 0.015 mm dent, pass as a dent (composite box 1010).
    """
    if len(reference_points) == 0:
        raise ValueError("a profile needs at least one zero-force reference scan")
    x = grid.x_mm
    h_ref = reference_height(reference_points, contact_point_mm, normal, t, grid)
    face = probed_face(h_ref, x)
    if len(scan_points):
        h = np.stack([height_on_grid(sp, contact_point_mm, normal, t, grid) for sp in scan_points])
        per_scan = h_ref[None, :] - h
        seen_off_face = ~face & np.isfinite(per_scan).any(axis=0)
        rm = robust_mean(np.where(face[None, :], per_scan, np.nan))
    else:
        seen_off_face = np.zeros(grid.samples, dtype=bool)
        rm = robust_mean(np.zeros((0, grid.samples)))
    centre = np.nanmean(np.asarray(tip_centres_mm, dtype=float).reshape(-1, 3), axis=0)
    tip_x, tip_h = (float(v[0]) for v in local_coordinates(centre, contact_point_mm, normal, t))
    tip_depth = surface_height_at(h_ref, face, x, tip_x, tip_radius_mm) - (tip_h - tip_radius_mm)
    depth = rm.mean_mm.copy()
    bound = max(tip_depth, 0.0) + margin_mm if np.isfinite(tip_depth) else np.inf
    with np.errstate(invalid="ignore"):
        implausible = np.isfinite(depth) & ((depth > bound) | (depth < -margin_mm))
    depth[implausible] = np.nan
    return StepMeasurement(depth, rm.stderr_mm, h_ref, tip_x, float(tip_depth), rm.rejected_scan_samples,
                           rm.rejected_line_samples, int(implausible.sum()), int(seen_off_face.sum()))


def surface_height_at(h_mm: np.ndarray, face: np.ndarray, x_mm: np.ndarray, at_mm: float, reach_mm: float) -> float:
    """The reference surface's height (mm along n) at ``at_mm``: interpolated over the face
    samples within ``reach_mm`` (a straight-line fit when they lie on one side only); 0 (the
    contact point is on the surface by construction) when none are that close."""
    x = np.asarray(x_mm, dtype=float)
    near = face & np.isfinite(h_mm) & (np.abs(x - at_mm) <= reach_mm)
    if near.sum() < 2:
        return 0.0
    xs, hs = x[near], np.asarray(h_mm, dtype=float)[near]
    if xs[0] <= at_mm <= xs[-1]:
        return float(np.interp(at_mm, xs, hs))
    slope, offset = np.polyfit(xs, hs, 1)
    return float(slope * at_mm + offset)


def depth_scale_mm(depths_mm: np.ndarray) -> float:
    """The per-region normalisation scale: the deepest finite depth (mm); 1.0 if none is positive."""
    d = np.asarray(depths_mm, dtype=float)
    finite = d[np.isfinite(d)]
    peak = float(finite.max()) if finite.size else 0.0
    return peak if peak > 0.0 else 1.0


def normalize(depth_mm: np.ndarray, scale_mm: float) -> np.ndarray:
    """Depth (mm) -> [0, 1] by the region's scale (zero depth stays 0; noise may dip slightly below)."""
    if not scale_mm > 0.0:
        raise ValueError("scale_mm must be positive")
    return np.asarray(depth_mm, dtype=float) / scale_mm


def denormalize(depth_norm: np.ndarray, scale_mm: float) -> np.ndarray:
    """Normalised depth -> mm (inverse of :func:`normalize`)."""
    return np.asarray(depth_norm, dtype=float) * scale_mm


def mirror_angle_deg(angle_deg: float | np.ndarray) -> float | np.ndarray:
    """α -> 180° − α: the same push seen with t flipped."""
    if np.ndim(angle_deg):
        return 180.0 - np.asarray(angle_deg, dtype=float)
    return 180.0 - float(angle_deg)


def mirror(profile: np.ndarray, x_mm: np.ndarray) -> np.ndarray:
    """A profile (…, L) seen with t flipped: value at x becomes value at −x on the same grid.

    On a grid symmetric about 0 this is an exact reversal; otherwise the profile is
    interpolated at −x (NaN outside its range).
    """
    p = np.asarray(profile, dtype=float)
    x = np.asarray(x_mm, dtype=float)
    if np.allclose(x, -x[::-1], atol=1e-9 * max(1.0, float(np.abs(x).max()))):
        return p[..., ::-1].copy()
    flat = p.reshape(-1, p.shape[-1])
    out = np.stack([resample_on_grid(-x, row, x) for row in flat])
    return out.reshape(p.shape)
