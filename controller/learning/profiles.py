"""Deformation profiles (DESIGN §3): scans -> object frame -> depth on a fixed grid.

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

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..geometry import Pose

# A gap between two valid samples wider than this many sample spacings is not
# bridged by interpolation: the surface there was not seen (shadow, dark texture).
GAP_SPACINGS: float = 3.0


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


def height_on_grid(points_mm: np.ndarray, contact_point_mm: np.ndarray, normal: np.ndarray,
                   t: np.ndarray, grid: ProfileGrid, max_gap_mm: float | None = None) -> np.ndarray:
    """Surface height h (mm along n) of one object-frame scan on the grid, NaN where unseen."""
    x, h = local_coordinates(points_mm, contact_point_mm, normal, t)
    return resample_on_grid(x, h, grid.x_mm, max_gap_mm)


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
