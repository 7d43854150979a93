"""Regions of similar elasticity from the survey (docs/design.md §2, §7; the paper's clusters).

Input: per surveyed point a feature vector from the cheap probes (see
:func:`survey_features`: peak depth and dent width at each survey force, compliance
slope), and the surface graph (neighbour pairs of the neural-gas units).

1. Features are standardised and projected on their principal components (enough for
   95 % of the variance, at most ``max_dims``), which decorrelates the strongly
   correlated depth features so a small mixture can describe them.
2. The number of regions comes from the data: Gaussian mixtures for k = 1..kmax,
   the one with the lowest BIC wins. Optionally, clusters whose centroids differ by
   less than ``merge_sigmas`` measurement noises in every feature are merged (the
   mixture may split a material whose features are not Gaussian). Then clusters that the
   contrast rule does not call two materials are merged (:func:`_merge_by_contrast`:
   median peak depths a factor ``min_contrast`` apart, beyond the measured noise of a
   peak, at a survey force where a dent is measured; two regions of the previous round only on a
   contrast measured and found wanting): BIC finds any structure,
   including the smooth drift of one material's visible dent with the local geometry
   (rims, slopes, tilt) and with its support (a plate clamped at its edges), which is
   not a different elasticity; nor is a dent read farther from the contact (a wall hides
   the contact: ``seen_from_mm``), whose peaks are lower bounds. A
   homogeneous object gives one region.
3. Spatial coherence on the surface graph: a few passes of iterated conditional
   modes (each point takes the region maximising its feature log-likelihood plus
   ``beta`` per neighbour already in that region: ambiguous points follow their
   neighbours, clear ones keep their own), then connected components per label
   smaller than ``min_island_points`` are relabelled to their neighbours' majority
   (recorded in ``stats["islands"]``, so densification can look there again); and a
   region that is only the blend along the seams of others (each of its connected pieces
   sandwiched between two regions, smaller than both, its dent between theirs, or beyond
   a neighbour's lower bound, or below a neighbour's dent that is within its noise:
   :func:`_absorb_transition_bands`) is split
   between them, and so is each such piece of a real region
   (``stats["transition_band_points"]``); and a connected piece of points that its region
   explains badly, enclosed by that region and another material by the contrast rule, is
   taken out again (:func:`_enclosed_materials`, ``stats["enclosed_material_points"]``):
   the neighbours' votes must not outvote a small inclusion's own dents.
4. Region ids are sorted by the mean of one feature (default column 0, the peak depth
   at the smallest survey force: region 0 is the stiffest), so reruns on the same data
   give the same ids.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..core.config import MIN_CONTRAST
from . import surface_map as sm

_MAX_ICM_PASSES = 20
# The floor under log peak depths when the plan's noise is not known (mm): a dent this
# shallow is about the standard error of an averaged survey profile.
DEFAULT_LOG_FLOOR_MM = 0.005
_MAX_ISLAND_PASSES = 10
# A dent (+ the noise floor) within this many scatters of a peak (peak_noise_mm) is not
# measured: the peak of a profile that flat is the largest of its noisy samples near the
# contact (about two noises above the dent on the 10-20 samples there), so two such peaks
# say nothing of which material is stiffer. See _merge_by_contrast.
MEASURED_DENT_NOISES = 5.0
# A cluster with fewer points is split off only by a contrast that holds at every measured
# survey force (see _merge_by_contrast).
MIN_POINTS_FOR_ONE_FORCE = 3


# -- features ----------------------------------------------------------------------------------

NEAR_CONTACT_BAND_MM = 3.0
# The feature that says how far from the contact a point's peaks were read (mm).
SEEN_FROM_FEATURE = "seen_from_mm"


def _half_max_width_mm(x_mm: np.ndarray, depth_mm: np.ndarray,
                       band_mm: float = NEAR_CONTACT_BAND_MM) -> tuple[float, float]:
    """(peak depth, full width at half peak) of one profile; widths interpolated between samples.

    The peak is the deepest sample among those nearest the contact: within ``band_mm`` of
    the seen sample closest to x = 0. The tip hides the dent's centre and the probe shadows
    one side, so the deepest SEEN sample is the one nearest the contact; a deeper value far
    out is an occlusion artefact (a box's edge or wall in the scan line), not the dent.

    The last seen sample before a gap, on the side away from the contact, is not read
    (:func:`_outer_run_ends`): where the line leaves the face at a rim, a tenth of a
    millimetre's shift of where the loaded and the reference scans last hit it changes that
    sample's depth by the rim's drop. On suite slab 1001 (seed 2) an elastomer probe 3.5 mm
    from the slab's rim saw 4 samples; the last read 0.082 and 0.085 mm at 1.5 and 4.5 N
    (the other three 0.02 and 0.05, the elastomer's dent), and that one sample made a
    third region of one probe.
    """
    ok = np.isfinite(depth_mm) & ~_outer_run_ends(x_mm, depth_mm)
    if np.count_nonzero(ok) < 3:
        return np.nan, np.nan
    x, d = x_mm[ok], depth_mm[ok]
    near = np.abs(x) <= np.min(np.abs(x)) + band_mm
    i = int(np.flatnonzero(near)[np.argmax(d[near])])
    peak = float(d[i])
    if peak <= 0.0:
        return peak, 0.0
    half = peak / 2.0

    def crossing(step: int) -> float:
        j = i
        while 0 <= j + step < d.size and d[j + step] > half:
            j += step
        k = j + step
        if not 0 <= k < d.size:
            return float(x[j])
        # Linear interpolation between the last sample above half and the first below.
        frac = (d[j] - half) / (d[j] - d[k]) if d[j] != d[k] else 0.0
        return float(x[j] + frac * (x[k] - x[j]))

    return peak, crossing(1) - crossing(-1)


def _outer_run_ends(x_mm: np.ndarray, depth_mm: np.ndarray) -> np.ndarray:
    """(L,) True at each seen sample whose next sample AWAY from the contact (x = 0) is
    unseen: where a seen run ends short of the profile's ends (a rim, an occluder, a
    dropout). The contact's side of a run (the tip's shadow) and the profile's own ends
    are not run ends."""
    x = np.asarray(x_mm, dtype=float)
    seen = np.isfinite(np.asarray(depth_mm, dtype=float))
    next_unseen = np.append(~seen[1:], False)        # outward for x > 0
    previous_unseen = np.insert(~seen[:-1], 0, False)  # outward for x < 0
    return seen & np.where(x > 0, next_unseen, (x < 0) & previous_unseen)


def survey_features(depth_mm: np.ndarray, x_mm: np.ndarray, forces_n: np.ndarray
                    ) -> tuple[np.ndarray, list[str]]:
    """Features (N,D) of surveyed points and their names.

    ``depth_mm`` (N,F,L): each point's averaged profile at each survey force (same angle,
    e.g. 90°); ``forces_n`` (F,) the measured (or commanded) forces, increasing.
    Features: ``peak_mm@F`` and ``width_mm@F`` (full width at half peak) for each force,
    and ``compliance_mm_per_n`` (least-squares slope of peak depth against force) when F > 1,
    and ``seen_from_mm`` (:data:`SEEN_FROM_FEATURE`): how far from the contact the peaks were
    read. A wall or a deep dent hides the surface near the contact, and a peak read 13 mm out
    is a third of one read 3 mm out on the same gel: only a lower bound of the dent, which
    the contrast rule must not take for a stiffer material (:func:`_merge_by_contrast`).
    """
    d = np.asarray(depth_mm, dtype=float)
    x = np.asarray(x_mm, dtype=float)
    f = np.asarray(forces_n, dtype=float).reshape(-1)
    if d.ndim != 3 or d.shape[1] != f.shape[0] or d.shape[2] != x.shape[0]:
        raise ValueError(f"need (N,F,L) depths for F forces on an L grid; got {d.shape}")
    n, nf, _ = d.shape
    peaks = np.empty((n, nf))
    widths = np.empty((n, nf))
    for i in range(n):
        for j in range(nf):
            peaks[i, j], widths[i, j] = _half_max_width_mm(x, d[i, j])
    names = [f"peak_mm@{v:g}N" for v in f] + [f"width_mm@{v:g}N" for v in f]
    cols = [peaks, widths]
    if nf > 1:
        fc = f - f.mean()
        with warnings.catch_warnings():
            # A target the scanner never saw has all-NaN peaks: its slope is NaN, no warning.
            warnings.simplefilter("ignore", category=RuntimeWarning)
            slope = ((peaks - np.nanmean(peaks, axis=1, keepdims=True)) * fc).sum(axis=1) / (fc ** 2).sum()
        cols.append(slope[:, None])
        names.append("compliance_mm_per_n")
    cols.append(_seen_from_mm(d, x)[:, None])
    names.append(SEEN_FROM_FEATURE)
    return np.concatenate(cols, axis=1), names


def _seen_from_mm(depth_mm: np.ndarray, x_mm: np.ndarray) -> np.ndarray:
    """(N,) how far from the contact (mm) each point's peaks were read: per survey force the
    distance of the seen sample nearest the contact, the largest over the forces (NaN where
    a profile has no peak, see :func:`_half_max_width_mm`)."""
    seen = np.isfinite(depth_mm)
    dist = np.where(seen, np.abs(x_mm)[None, None, :], np.inf).min(axis=2)        # (N,F)
    dist[seen.sum(axis=2) < 3] = np.nan
    return dist.max(axis=1)


# -- graph helpers -----------------------------------------------------------------------------

def _adjacency(n: int, edges: np.ndarray) -> list[np.ndarray]:
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    e = e[(e[:, 0] != e[:, 1])]
    if e.size and (e.min() < 0 or e.max() >= n):
        raise ValueError("an edge names a point that does not exist")
    both = np.concatenate([e, e[:, ::-1]]) if e.size else np.zeros((0, 2), dtype=np.int64)
    order = np.lexsort((both[:, 1], both[:, 0]))
    both = both[order]
    starts = np.searchsorted(both[:, 0], np.arange(n + 1))
    return [np.unique(both[starts[i]:starts[i + 1], 1]) for i in range(n)]


def _neighbour_counts(labels: np.ndarray, neighbours: list[np.ndarray], k: int, idx: int) -> np.ndarray:
    nb = neighbours[idx]
    lab = labels[nb]
    lab = lab[lab >= 0]
    return np.bincount(lab, minlength=k).astype(float)


# -- the region map ----------------------------------------------------------------------------

@dataclass
class RegionMap:
    """Regions of the surveyed points.

    ``labels`` (N,): region id per point (0..n_regions-1); ``centroids``/``spread`` (K,D):
    mean and std of the raw features per region; ``counts`` (K,); ``feature_names``;
    the classifier (standardisation, projection, per-region Gaussians with a pooled
    covariance) used by :func:`label_new_points` and :meth:`loglik`; ``stats`` holds the
    BIC per k, the chosen k, merges, ICM changes and the relabelled islands.
    """

    labels: np.ndarray
    n_regions: int
    centroids: np.ndarray
    spread: np.ndarray
    counts: np.ndarray
    feature_names: list[str]
    scaler_mean: np.ndarray
    scaler_std: np.ndarray
    projection: np.ndarray          # (P,D): standardised features -> model space
    region_means: np.ndarray        # (K,P) in model space
    pooled_cov: np.ndarray          # (P,P)
    log_prior: np.ndarray           # (K,)
    stats: dict[str, Any] = field(default_factory=dict)
    log_columns: list[int] = field(default_factory=list)    # raw features taken as log(value + floor)
    log_floor_mm: float = 0.0

    def transform(self, features: np.ndarray) -> np.ndarray:
        """Raw features (M,D) -> model space (M,P); NaN features are replaced by the mean."""
        x = _log_features(np.asarray(features, dtype=float), self.log_columns, self.log_floor_mm)
        z = (x - self.scaler_mean) / self.scaler_std
        return np.where(np.isfinite(z), z, 0.0) @ self.projection.T

    def loglik(self, features: np.ndarray) -> np.ndarray:
        """(M,K) log prior + log density of each point's features under each region."""
        z = self.transform(features)
        return _gauss_loglik(z, self.region_means, self.pooled_cov) + self.log_prior

    def posterior(self, features: np.ndarray) -> np.ndarray:
        """(M,K) region probabilities from the features alone."""
        from scipy.special import logsumexp

        ll = self.loglik(features)
        return np.exp(ll - logsumexp(ll, axis=1, keepdims=True))

    def ambiguity(self, features: np.ndarray) -> np.ndarray:
        """(M,) 1 − (p_best − p_second) in [0, 1]: 1 = the features cannot tell two regions apart."""
        if self.n_regions < 2:
            return np.zeros(np.asarray(features).shape[0])
        p = np.sort(self.posterior(features), axis=1)
        return 1.0 - (p[:, -1] - p[:, -2])

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form for the journal."""
        out: dict[str, Any] = {}
        for k, v in self.__dict__.items():
            out[k] = v.tolist() if isinstance(v, np.ndarray) else v
        out["stats"] = _jsonable(self.stats)
        return out

    @staticmethod
    def from_dict(d: dict[str, Any]) -> "RegionMap":
        arrays = {"labels", "centroids", "spread", "counts", "scaler_mean", "scaler_std", "projection",
                  "region_means", "pooled_cov", "log_prior"}
        kw = {k: (np.asarray(v, dtype=np.int64 if k in ("labels", "counts") else float) if k in arrays else v)
              for k, v in d.items()}
        return RegionMap(**kw)


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def _log_features(features: np.ndarray, columns: list[int], floor_mm: float) -> np.ndarray:
    """``features`` with the given columns replaced by log(max(value, 0) + floor_mm) (NaN stays NaN)."""
    if not columns:
        return features
    out = np.array(features, dtype=float, copy=True)
    with np.errstate(invalid="ignore"):
        out[:, columns] = np.log(np.maximum(out[:, columns], 0.0) + floor_mm)
    return out


def _gauss_loglik(z: np.ndarray, means: np.ndarray, cov: np.ndarray) -> np.ndarray:
    p = z.shape[1]
    chol = np.linalg.cholesky(cov)
    logdet = 2.0 * np.log(np.diag(chol)).sum()
    out = np.empty((z.shape[0], means.shape[0]))
    for k in range(means.shape[0]):
        sol = np.linalg.solve(chol, (z - means[k]).T)
        out[:, k] = -0.5 * (np.sum(sol ** 2, axis=0) + logdet + p * np.log(2.0 * np.pi))
    return out


def _fit_gaussians(z: np.ndarray, labels: np.ndarray, k: int, reg: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-region means, a pooled within-region covariance (robust for small regions), log priors."""
    p = z.shape[1]
    means = np.stack([z[labels == j].mean(axis=0) for j in range(k)])
    resid = z - means[labels]
    dof = max(z.shape[0] - k, 1)
    cov = resid.T @ resid / dof + reg * np.eye(p)
    counts = np.bincount(labels, minlength=k).astype(float)
    return means, cov, np.log(counts / counts.sum())


def _standardise(features: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    mean = np.nanmean(features, axis=0)
    std = np.nanstd(features, axis=0)
    std = np.where(std > 1e-12 * np.maximum(np.abs(mean), 1.0), std, 1.0)
    z = (features - mean) / std
    return np.where(np.isfinite(z), z, 0.0), mean, std


def _projection(z: np.ndarray, max_dims: int, variance: float = 0.95) -> np.ndarray:
    if z.shape[0] < 2:
        return np.eye(z.shape[1])[:1]
    _, s, vt = np.linalg.svd(z - z.mean(axis=0), full_matrices=False)
    var = s ** 2
    if var.sum() <= 0:
        return vt[:1]
    keep = int(np.searchsorted(np.cumsum(var) / var.sum(), variance) + 1)
    return vt[:max(1, min(keep, max_dims, z.shape[0] - 1))]


def _choose_mixture(z: np.ndarray, kmax: int, seed: int) -> tuple[np.ndarray, dict[int, float]]:
    """Labels from the Gaussian mixture with the lowest BIC over k = 1..kmax."""
    from sklearn.mixture import GaussianMixture
    from threadpoolctl import threadpool_limits   # a dependency of scikit-learn

    # The matrices are tiny: multithreaded BLAS only contends (10x slower on a busy machine).
    with threadpool_limits(limits=1):
        return _bic_search(z, kmax, seed, GaussianMixture)


def _bic_search(z: np.ndarray, kmax: int, seed: int, mixture: Any) -> tuple[np.ndarray, dict[int, float]]:
    n = z.shape[0]
    bics: dict[int, float] = {}
    best_labels = np.zeros(n, dtype=np.int64)
    best_bic = np.inf
    for k in range(1, max(1, min(kmax, n // 2)) + 1):
        gm = mixture(n_components=k, covariance_type="full", reg_covar=1e-3, n_init=4,
                             random_state=seed, max_iter=300)
        gm.fit(z)
        bic = float(gm.bic(z))
        bics[k] = bic
        if bic < best_bic:
            best_bic, best_labels = bic, gm.predict(z).astype(np.int64)
    return best_labels, bics


def _compact(labels: np.ndarray) -> tuple[np.ndarray, int]:
    uniq, inv = np.unique(labels, return_inverse=True)
    return inv.astype(np.int64), int(uniq.shape[0])


def _merge_by_noise(features: np.ndarray, labels: np.ndarray, noise: np.ndarray, sigmas: float
                    ) -> tuple[np.ndarray, int]:
    """Merge clusters whose mean features differ by less than ``sigmas`` noises in every feature."""
    merges = 0
    while True:
        labels, k = _compact(labels)
        if k < 2:
            return labels, merges
        cent = np.stack([np.nanmean(features[labels == j], axis=0) for j in range(k)])
        best: tuple[float, int, int] | None = None
        for i in range(k):
            for j in range(i + 1, k):
                sep = float(np.nanmax(np.abs(cent[i] - cent[j]) / noise))
                if sep < sigmas and (best is None or sep < best[0]):
                    best = (sep, i, j)
        if best is None:
            return labels, merges
        labels = np.where(labels == best[2], best[1], labels)
        merges += 1


def _merge_by_contrast(features: np.ndarray, labels: np.ndarray, depth_columns: list[int],
                       min_contrast: float, floor_mm: float = 0.0,
                       far_field_mm: np.ndarray | None = None,
                       seen_from_mm: np.ndarray | None = None,
                       previous_labels: np.ndarray | None = None,
                       edges: np.ndarray | None = None, pooled_scatter: bool = False
                       ) -> tuple[np.ndarray, int]:
    """Merge clusters that are not two materials, closest pair first. Two clusters are two
    materials when, at some survey force at which either dent is measured (deeper than
    ``MEASURED_DENT_NOISES`` x the scatter of one of its points' peak depth, measured from
    its points' far fields ``far_field_mm`` (N,2), see :func:`peak_noise_mm`; ``floor_mm``
    without them), their median depths (+ ``floor_mm``) differ by at least a factor
    ``min_contrast`` and by more than 3 standard errors of the difference of the medians
    (:func:`_difference_standard_error`), and at no
    measured force is the other one deeper by more than 3 standard errors; a cluster of
    fewer than ``MIN_POINTS_FOR_ONE_FORCE`` points must be deeper (or shallower) by 3
    standard errors at every measured force. ``depth_columns``: the peak-depth features.
    ``seen_from_mm`` (N,): how far from the contact each point's peaks were read
    (:data:`SEEN_FROM_FEATURE`); a cluster whose median lies beyond another's by more than
    the band a peak is read in (:data:`NEAR_CONTACT_BAND_MM`) has only lower bounds of its
    dents beside the other's peaks: that it is deeper is evidence, that it is shallower is
    none (and refutes nothing); read farther out within that band, its peaks are lower by
    about the ratio of the distances (a dent outside the contact falls off about as 1/r), and
    "deeper than it" must show the contrast times that ratio. ``previous_labels`` (N,): each
    point's region in the previous round (-1: new); two clusters drawn from two different
    previous regions were told apart by this rule then, and are joined now only by a contrast
    measured and found wanting, not because neither dent counts as measured any more.
    ``edges`` (E,2): the surface graph's neighbour pairs; with them, each cluster is measured
    (medians, counts, far-field scatter, where its peaks were read) on its interior points
    (:func:`_measured_points`). ``pooled_scatter``: every cluster's peak scatter is read on all
    the points' far fields together (see :func:`_enclosed_materials`).

    Why the interior: a probe whose surface neighbour lies in another cluster stands within
    a probe spacing of the seam, and a tip there presses both materials, so its dent lies
    between theirs. Densification bisects exactly those gaps, so each round adds seam probes
    to both sides: on suite slab 1012 with 3 mm densification, 33 of the hard-rubber ellipse's
    39 probes stood within 3 mm of its seam by round 4; their median at 4.5 N was 0.025 mm
    against 0.019 for those more than 2 mm inside (the elastomer: 0.066), the pair fell under the
    contrast, and a material told apart in rounds 0-3 joined the elastomer.

    Why the previous round counts: whether a dent is measured rests on the scatter of the
    cluster's far fields, and a few points' far fields scatter with where they lie. On suite
    slab 1003 the elastomer ellipse (0.057 mm at 4.5 N, the truth's peak scatter 0.005 mm)
    and the hard-rubber disc (0.016 mm) were two regions in round 0; in round 1 the ellipse's
    eight interior points read a far-field scatter of 0.020 mm (the gel's dent beside them
    reaches into their far fields), neither dent counted as measured, and the two
    inclusions became one region.

    Why: where a wall hides the surface near the contact, the scanner sees a dent from
    ~13 mm out. On generated composite 3007 the gel at the foot of the box wall read
    0.18-0.20 mm at 9 N there, the gel elsewhere 0.50-0.58 mm from 3.3 mm out (the truth
    reads 0.18 mm 13 mm out of either): 2.7x, a third region between the gel and the hard
    rubber. A soft foam's own dent hides its contact too (read 7-9 mm out on suite slabs
    1002-1004), but it is the deepest material there, which its lower bounds still show.

    The mixture splits one material wherever geometry shifts the visible dent (the rim of
    a pillow, a slope, a tilted ball surface: up to ~30 % deeper in the simulator, where
    the probe's shadow ends closer to the contact); that is not a different elasticity.

    Why only measured forces count: at a small force a stiff material's peak is the largest
    of the noisy samples near the contact, not its dent. On generated slab 2001 hard rubber
    and elastomer read 0.009 and 0.019 mm at 2 N and 0.016 and 0.066 mm at 6.5 N (peak
    scatter ~0.008 mm), and the mixture cut the hard rubber into clusters by its 2 N noise,
    some reading as deep as the elastomer there. Requiring the contrast at every force
    merged the two materials (one region in round 0) or joined half the hard rubber to the
    elastomer; the contrast at any force, noise included, split the hard rubber in two. Why
    not only the largest force: a foam's dent saturates (on suite block 1004 sponge and
    foam read 0.72 and 1.95 mm at 3 N, 2.0 and 2.5 mm at 9 N). A stiffer material dents
    less at every force, so an order clearly reversed at another force refutes the pair;
    one merely unresolved there does not. A pair measured at no force is one material as
    far as the survey can tell.
    """
    merges = 0
    if not depth_columns or min_contrast <= 1.0:
        return _compact(labels)[0], 0
    cols = features[:, depth_columns]
    floor = max(floor_mm, 1e-6)
    log_c = float(np.log(min_contrast))
    labels, k = _compact(labels)
    far = np.full((labels.shape[0], 2), np.nan) if far_field_mm is None else np.asarray(far_field_mm, dtype=float)
    seen_from = (np.zeros(labels.shape[0]) if seen_from_mm is None
                 else np.asarray(seen_from_mm, dtype=float).reshape(-1))

    interior = None if edges is None else sm.interior_seeds(labels, edges)
    pooled = peak_noise_mm(far, floor) if pooled_scatter else None

    def measure(c: int) -> tuple[np.ndarray, float, np.ndarray, float]:
        # (median depths + floor (C,), peak scatter, finite counts (C,), median seen-from) of cluster c
        basis = _measured_points(labels, c, interior)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            depth = np.maximum(np.nanmedian(cols[basis], axis=0), 0.0) + floor
            where = float(np.nanmedian(seen_from[basis]))
        scatter = pooled if pooled is not None else peak_noise_mm(far[basis], floor)
        return depth, scatter, np.sum(np.isfinite(cols[basis]), axis=0).astype(float), where

    measured_clusters = [measure(c) for c in range(k)]
    med = np.stack([m[0] for m in measured_clusters])
    noise = np.array([m[1] for m in measured_clusters])
    count = np.stack([m[2] for m in measured_clusters])
    read_at = np.array([m[3] for m in measured_clusters])                       # (k,) mm
    prev = (np.full(labels.shape[0], -1, dtype=np.int64) if previous_labels is None
            else np.asarray(previous_labels, dtype=np.int64).reshape(-1))
    came_from = np.array([_one_previous(prev[labels == c]) for c in range(k)], dtype=np.int64)
    while k > 1:
        logs = np.log(med)
        signed = logs[:, None, :] - logs[None, :, :]                       # (k,k,F)
        finite = np.isfinite(signed)
        seen = med > MEASURED_DENT_NOISES * noise[:, None]                   # (k,F)
        measured = finite & (seen[:, None, :] | seen[None, :, :])
        seen_at_all = measured.any(axis=2)
        diff_mm = med[:, None, :] - med[None, :, :]                         # > 0: i deeper
        margin = 3.0 * _difference_standard_error(noise, count)
        # i deeper than j by the contrast and by 3 standard errors at some measured force,
        # and j nowhere clearly deeper (and the other way round).
        deeper = measured & (diff_mm > margin)
        # j's peaks read farther out than i's: "i deeper than j" is no evidence.
        with np.errstate(invalid="ignore"):
            farther = read_at[None, :] > read_at[:, None] + NEAR_CONTACT_BAND_MM   # (i, j): j farther
        deeper &= ~farther[:, :, None]
        # j's peaks read farther out, but within the band: a dent falls off about as 1/r
        # outside the contact, so "i deeper than j" must beat the contrast by the ratio of
        # the distances too.
        with np.errstate(invalid="ignore", divide="ignore"):
            falloff = np.log(np.clip(read_at[None, :] / read_at[:, None], 1.0, None))
        shows = np.any(deeper & (signed >= log_c + np.nan_to_num(falloff)[:, :, None]), axis=2)
        # A cluster of one or two points is one or two measurements: one scattered return can
        # fake a contrast at one force, so it must be clearly deeper (or shallower) at every
        # measured force.
        few = np.minimum(count.min(axis=1)[:, None], count.min(axis=1)[None, :]) < MIN_POINTS_FOR_ONE_FORCE
        everywhere = np.all(deeper | ~measured, axis=2)
        shows &= ~few | everywhere
        shows = (shows & ~np.any(deeper.transpose(1, 0, 2), axis=2)) | (shows.T & ~np.any(deeper, axis=2))
        # Merge order: the ratio at the measured forces (at all forces for a pair measured at none).
        absd = np.where(measured, np.abs(signed), -np.inf).max(axis=2)
        gap = np.where(seen_at_all, absd, np.where(finite, np.abs(signed), -np.inf).max(axis=2))
        same = ~shows
        told_apart = ((came_from[:, None] >= 0) & (came_from[None, :] >= 0)
                      & (came_from[:, None] != came_from[None, :]))
        same &= ~(told_apart & ~seen_at_all)
        same &= np.triu(np.ones((k, k), dtype=bool), 1) & np.isfinite(gap)
        if not same.any():
            break
        i, j = np.unravel_index(int(np.argmin(np.where(same, gap, np.inf))), same.shape)
        labels = np.where(labels == j, i, labels)
        labels = np.where(labels > j, labels - 1, labels)
        k -= 1
        members = labels == i
        med, count, noise, read_at = (np.delete(a, j, axis=0) for a in (med, count, noise, read_at))
        # Only the joined cluster changes: its points that bordered each other are interior now.
        interior = None if edges is None else sm.interior_seeds(labels, edges)
        med[i], noise[i], count[i], read_at[i] = measure(int(i))
        came_from = np.delete(came_from, j)
        came_from[i] = _one_previous(prev[members])
        merges += 1
    return labels, merges


def _measured_points(labels: np.ndarray, cluster: int, interior: np.ndarray | None) -> np.ndarray:
    """The points cluster ``cluster`` is measured on: its interior (``interior`` (N,), from
    :func:`surface_map.interior_seeds`: points with a surface neighbour, all of them in their
    own cluster) when that holds ``surface_map.MIN_INTERIOR_SEEDS`` points or more, else all
    its points (a cluster that is all seam, or no graph given). See :func:`_merge_by_contrast`."""
    members = np.flatnonzero(labels == cluster)
    if interior is None:
        return members
    inner = members[interior[members]]
    return inner if inner.size >= sm.MIN_INTERIOR_SEEDS else members


def _one_previous(previous: np.ndarray) -> int:
    """The previous round's region that most of these points came from (more than half of
    those it knows; new points, -1, aside), or -1 when none did or all are new.

    Why most, not all: one blended seam probe that the previous round put in the other
    region would otherwise erase a piece's origin, and with it the rule that keeps two
    regions of the previous round apart. On suite slab 1003 (seed 2, round 2 of a run with
    the far-field spread of docs/generated_objects.md, "Stop 35") the elastomer piece took
    in one hard-rubber probe that read the elastomer's level, lost its origin, and the
    hard-rubber disc then joined it: three regions of four. Screened on all 142 recorded
    regions rounds of 39 sessions, no other round changes."""
    known = previous[previous >= 0]
    if known.size == 0:
        return -1
    values, counts = np.unique(known, return_counts=True)
    top = int(np.argmax(counts))
    return int(values[top]) if 2 * int(counts[top]) > known.size else -1


def peak_noise_mm(far_field_mm: np.ndarray, floor_mm: float) -> float:
    """The scatter (mm) of one point's peak depth among points of one material, from what
    their averaged profiles read far from the contact (``far_field_mm`` (M,2): median depth
    and one sample's scatter there, see :func:`profiles.far_field_error_mm`): the RMS of the
    far-field level (1.4826 x its median absolute value) and the median sample scatter,
    combined; ``floor_mm`` (the scans' standard error) when no point saw its far field.

    Measured on each probe's own profile, not from differences between neighbouring
    probes, so a seam between two materials cannot inflate it. Against the simulator's
    truth (the peaks' scatter among probes of one material more than 8 mm from a seam) on
    the generated objects' recorded surveys: hard rubber 0.0055-0.0067 mm against
    0.007-0.0105 mm, elastomer 0.0036-0.0078 mm against 0.002-0.0055 mm, gel 0.014-0.027 mm
    against 0.013-0.017 mm. The scans' standard error (the scatter of one step's loaded
    scans over sqrt(scans)) misses the reference scans' noise and the correlated floor
    (0.0026 mm on slab 2001), and comes from the session's first steps, whichever material
    they pressed (0.012 mm, foam's, on composite box 1010): no floor for another material.
    """
    f = np.asarray(far_field_mm, dtype=float).reshape(-1, 2)
    level, scatter = f[np.isfinite(f[:, 0]), 0], f[np.isfinite(f[:, 1]), 1]
    if level.size == 0:
        return float(floor_mm)
    common = 1.4826 * float(np.median(np.abs(level)))
    one = float(np.median(scatter)) if scatter.size else 0.0
    return max(float(np.hypot(common, one)), 1e-6)


def _difference_standard_error(noise_mm: np.ndarray, count: np.ndarray) -> np.ndarray:
    """(k, k, C) standard error (mm) of the difference of two regions' median peak depths
    from the measurement alone: each region's peak scatter ``noise_mm`` (k,) over sqrt(n),
    times sqrt(pi / 2) from three points on (a median's efficiency against the mean's).
    A material's own drift with geometry and support is not measurement error: the
    contrast factor is what tells it from another material."""
    eff = np.where(count >= 3, np.pi / 2.0, 1.0) / np.maximum(count, 1.0)
    var = np.asarray(noise_mm, dtype=float)[:, None] ** 2 * eff                  # (k,C)
    return np.sqrt(var[:, None, :] + var[None, :, :])


def _icm(loglik: np.ndarray, labels: np.ndarray, neighbours: list[np.ndarray], beta: float,
         free: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Iterated conditional modes of loglik + beta * (neighbours in the region); bounded passes."""
    labels = labels.copy()
    k = loglik.shape[1]
    idx = np.arange(labels.shape[0]) if free is None else np.flatnonzero(free)
    changes = 0
    for _ in range(_MAX_ICM_PASSES):
        changed = 0
        for i in idx:
            score = loglik[i] + beta * _neighbour_counts(labels, neighbours, k, i)
            best = int(np.argmax(score))
            if best != labels[i] and score[best] > score[labels[i]] + 1e-12:
                labels[i] = best
                changed += 1
        changes += changed
        if not changed:
            break
    return labels, changes


def _remove_islands(labels: np.ndarray, edges: np.ndarray, neighbours: list[np.ndarray],
                    min_island_points: int,
                    distinct: Callable[[np.ndarray, np.ndarray], bool] | None = None
                    ) -> tuple[np.ndarray, list[int], list[int]]:
    """Relabel connected same-label components smaller than ``min_island_points`` to the
    majority label of the points bordering them; isolated points (no neighbours) are kept.

    With ``distinct(members, region)`` (point indices of the island and of the bordering
    majority region): an island it calls another material is kept: one probe on a small
    inclusion is a material, not noise. Returns (labels, relabelled point indices, kept
    island point indices).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    labels = labels.copy()
    n = labels.shape[0]
    relabelled: list[int] = []
    kept: set[int] = set()
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    for _ in range(_MAX_ISLAND_PASSES):
        same = e[labels[e[:, 0]] == labels[e[:, 1]]] if e.size else e
        graph = coo_matrix((np.ones(same.shape[0]), (same[:, 0], same[:, 1])), shape=(n, n))
        _, comp = connected_components(graph, directed=False)
        sizes = np.bincount(comp)
        changed = False
        # Smallest islands first, so a pair of touching islands resolves predictably.
        for c in np.argsort(sizes, kind="stable"):
            if sizes[c] >= min_island_points:
                break
            members = np.flatnonzero(comp == c)
            if kept.issuperset(members.tolist()):
                continue
            border = np.concatenate([neighbours[i] for i in members]) if members.size else members
            border = border[labels[border] != labels[members[0]]]
            if border.size == 0:
                continue
            votes = np.bincount(labels[border])
            new = int(np.argmax(votes))
            if distinct is not None and distinct(members, np.flatnonzero(labels == new)):
                kept.update(int(i) for i in members)
                continue
            labels[members] = new
            relabelled.extend(int(i) for i in members)
            changed = True
        if not changed:
            break
    return labels, sorted(set(relabelled)), sorted(kept)


def odd_scores(peaks_mm: np.ndarray, median_mm: np.ndarray, scatter_mm: float, floor_mm: float,
               min_contrast: float) -> np.ndarray:
    """(M,) how far each point's peak depths (M,F) lie beyond its region's median (F,), in
    units of what tells another material: > 1 when at every survey force where the point's
    dent or the median is measured (+ ``floor_mm``, beyond ``MEASURED_DENT_NOISES`` x the
    region's peak scatter ``scatter_mm``, :func:`peak_noise_mm`), and there is one, the peak
    (+ ``floor_mm``) lies a factor ``min_contrast`` deeper than the median (+ ``floor_mm``)
    and more than 3 scatters from it; < -1 when shallower so at every measured force; the
    score is the smallest of those margins (log ratio over log ``min_contrast``, distance
    over 3 scatters) with its side, 0 where the sides differ or no force is measured.
    Negative readings count as 0 in the ratio.

    In mm and per force, not in log depth over the region's spread: a stiff material's log
    depths scatter widely (its dents lie near the noise), which hides a softer inclusion
    in it (:func:`_enclosed_materials`, :func:`survey_misfit`)."""
    peaks = np.asarray(peaks_mm, dtype=float)
    med = np.maximum(np.asarray(median_mm, dtype=float), 0.0)
    floor = max(float(floor_mm), 1e-6)
    value = np.maximum(peaks, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        measured = np.maximum(value, med) + floor > MEASURED_DENT_NOISES * scatter_mm
        apart = np.abs(peaks - med) / (3.0 * scatter_mm)
        contrast = np.abs(np.log((value + floor) / (med + floor))) / np.log(min_contrast)
        margin = np.where(peaks > med, 1.0, -1.0) * np.minimum(apart, contrast)
        margin = np.where(measured & np.isfinite(margin), margin, np.nan)
    # Unmeasured forces drop out: +inf in the smallest margin, -inf in the largest.
    low = np.min(np.where(np.isnan(margin), np.inf, margin), axis=1)
    high = np.max(np.where(np.isnan(margin), -np.inf, margin), axis=1)
    return np.where(np.isfinite(low) & (low > 0.0), low, np.where(np.isfinite(high) & (high < 0.0), high, 0.0))


def _enclosed_materials(features: np.ndarray, labels: np.ndarray, neighbours: list[np.ndarray],
                        depth_columns: list[int], min_contrast: float, floor_mm: float,
                        far_field_mm: np.ndarray | None, seen_from_mm: np.ndarray | None,
                        distinct: Callable[..., bool],
                        unread: np.ndarray | None = None) -> tuple[np.ndarray, list[int]]:
    """Give back a material that the spatial steps folded into the region around it.

    A point is odd in its region when, at every survey force where its dent or the region's
    median is measured (+ ``floor_mm``, beyond ``MEASURED_DENT_NOISES`` of the region's peak
    scatters: :func:`peak_noise_mm` of its far fields ``far_field_mm``), and there is one,
    its peak (+ ``floor_mm``) lies a factor ``min_contrast`` beyond the region's median
    (+ ``floor_mm``) and more than 3 scatters away, all on one side (:func:`odd_scores`
    beyond 1). Every measured force,
    not one: a softer material dents deeper at every force by about one factor, and on suite
    slab 1012 (round 4 of a recorded run) two neighbouring elastomer probes 40 mm inside
    read 3x their region at 1.5 N and 1.3-1.7x at 4.5 N. Odd points of one region, odd the
    same way and connected on the surface graph, form a piece; a piece of two points or more
    whose every neighbour outside it lies in the region (enclosed: not a blend along a seam,
    which :func:`_absorb_transition_bands` weighs) and that ``distinct(piece, rest,
    pooled_scatter=True)`` (the contrast rule, with one peak scatter for both, read on their
    far fields together) calls another material is taken out: it joins the other region
    that rule does not tell it from (nearest median in log depth), or becomes a region of
    its own. A point read farther out than its region
    (``seen_from_mm`` beyond the region's median by :data:`NEAR_CONTACT_BAND_MM`) reads
    lower bounds: shallower is not odd. A point in ``unread`` (N,) (its dent falls as the
    force rises, :func:`dent_falls_with_force`: it did not read its dent) is never odd: on
    the same slab two trios of hard-rubber probes 40-70 mm from any seam read 0.034-0.047 mm
    at 1.5 N and 0.011-0.026 mm at 4.5 N, which the contrast rule alone calls softer.

    Why: iterated conditional modes weighs each point's likelihood under Gaussians with one
    pooled covariance in log depth against its neighbours' votes, and a stiff material's
    log depths scatter widely (its dents lie near the noise), so the likelihood of a point
    on a small stiff-ish inclusion barely prefers its own cluster. On unseen slab 1703 (run
    seed 1) seven survey probes on an elastomer ellipse (semi-axes 16.2 and 10.0 mm) read
    0.038-0.054 mm at 4.5 N inside hard rubber at 0.013 mm (peak scatter 0.0076 mm); the
    mixture gave them a cluster, with 13 hard-rubber probes from its tails, that the contrast
    rule kept, and each probe, its neighbours mostly hard rubber, joined the hard rubber:
    three regions of four in every round, the misfit rule (log depths again) saw nothing to
    probe. Why one scatter for both: a piece's far fields, read 15 mm and more from each
    contact, lie on the region around it and carry the piece's own dent's tail; on 1703's
    round 1 the ellipse's eight odd probes read a far-field level of 0.004-0.014 mm (the hard
    rubber's: about 0), a scatter of 0.0107 mm against the hard rubber's 0.0071, under which
    their median of 0.047 mm at 4.5 N was no measured dent, and the ellipse, taken out in
    round 0, was folded in again from round 1 on. Why two points: one deep reading among
    hundreds of one material is a scattered return (four of 379 hard-rubber probes on that
    slab read 0.033-0.065 mm, scattered).
    Returns (labels, indices of the points taken out).
    """
    labels = labels.copy()
    if not depth_columns or min_contrast <= 1.0:
        return labels, []
    peaks = features[:, depth_columns]
    floor = max(float(floor_mm), 1e-6)
    seen_from = (np.zeros(labels.shape[0]) if seen_from_mm is None
                 else np.asarray(seen_from_mm, dtype=float).reshape(-1))
    taken: list[int] = []
    for region in range(int(labels.max(initial=-1)) + 1):
        members = np.flatnonzero(labels == region)
        if members.size < 3:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.maximum(np.nanmedian(peaks[members], axis=0), 0.0)
            read_at = float(np.nanmedian(seen_from[members]))
        noise = (peak_noise_mm(far_field_mm[members], floor) if far_field_mm is not None else floor)
        score = odd_scores(peaks[members], med, noise, floor, min_contrast)
        readable = np.ones(members.size, dtype=bool) if unread is None else ~unread[members]
        odd_deeper = (score > 1.0) & readable
        odd_shallower = (score < -1.0) & readable & ~(seen_from[members] > read_at + NEAR_CONTACT_BAND_MM)
        for odd in (members[odd_deeper], members[odd_shallower]):
            for piece in _pieces(odd, neighbours):
                if piece.size < 2:
                    continue
                border = np.setdiff1d(np.concatenate([neighbours[i] for i in piece]), piece)
                if border.size == 0 or np.any(labels[border] != region):
                    continue
                rest = np.setdiff1d(np.flatnonzero(labels == region), piece)
                if not distinct(piece, rest, pooled_scatter=True):
                    continue
                k = int(labels.max()) + 1
                with np.errstate(all="ignore"), warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    level = np.log(np.nanmedian(np.maximum(peaks[piece], 0.0), axis=0) + floor)
                    joins = [(float(np.nanmean(np.abs(level - np.log(np.nanmedian(
                        np.maximum(peaks[labels == q], 0.0), axis=0) + floor)))), q)
                        for q in range(k) if q != region and np.any(labels == q)
                        and not distinct(piece, np.flatnonzero(labels == q), pooled_scatter=True)]
                labels[piece] = min(joins)[1] if joins else k
                taken.extend(int(i) for i in piece)
    return labels, sorted(taken)


def _region_medians(columns: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """(k, C) NaN-aware median of each column over each region's points (NaN: none seen)."""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.stack([np.nanmedian(columns[labels == j], axis=0) for j in range(k)])


def _absorb_transition_bands(features: np.ndarray, labels: np.ndarray, neighbours: list[np.ndarray],
                             depth_columns: list[int], seen_from_mm: np.ndarray | None = None,
                             far_field_mm: np.ndarray | None = None, floor_mm: float = 0.0
                             ) -> tuple[np.ndarray, list[int]]:
    """Relabel a region that is only the blend between others into those others.

    Where two materials meet, a probe on the seam presses both: its dent lies between
    theirs, and densification, which bisects the seam, puts several probes there. They
    form a "region" of their own that is no material. A piece of a region (connected on the
    surface graph) is such a transition band when it is sandwiched between two regions A and
    B: the piece runs along their seam (every point of it borders A or B, and borders both
    or a point of the piece that does), the piece's median peak depth lies strictly between
    A's and B's at every survey force, and the piece has fewer points than either. Each
    point of the piece joins A or B, whichever median it is nearer to in log depth. A region
    whose pieces are all bands goes; a band piece of a real region leaves it on its own: on
    unseen slab 1612 (run seed 1) a hard-rubber disc's seam probes that read at a gel's level
    joined the gel's region as five pieces on the disc's seam, away from the gel strip, and
    drew the disc's rim as gel. The pieces may lie on different seams (A, B differing per
    piece): on suite slab 1003 (two inclusions, hard rubber and elastomer, in a gel) the
    probes on both inclusions' seams read alike and formed one fifth region.
    A real material probed only along seams looks the same; once probed off the seam it
    has interior points and is kept. The piece, not the region, is weighed against A and B:
    densification keeps adding seam probes, and on slab 1003's round 3 the band's 12 (on two
    seams) matched the hard-rubber disc's 12 interior probes, so a region-wide count kept a
    fifth region. A band two probes thick has probes that border one side only, behind
    probes that border both: on unseen slab 1612 (run seed 1) one of a hard-rubber disc's
    four seam probes in round 1, and two of seven in rounds 2-3, bordered the sponge and the
    band, not the disc's interior, and a fourth region of three materials stayed. A piece
    with a point of its own interior (bordering neither A nor B), or with a point that
    borders one side only and no neighbour in the piece that borders both, is no band: a
    strip of a real material between two others has probes that border one of them only.

    ``seen_from_mm`` (N,): where each point's peaks were read (:data:`SEEN_FROM_FEATURE`). A
    region whose peaks were read (median) farther out than the piece's by more than
    :data:`NEAR_CONTACT_BAND_MM` has only lower bounds of its dents, so a piece deeper than
    it at some force does not refute the blend, as long as the piece lies strictly between
    A and B at some other force (the contrast rule reads lower bounds the same way,
    :func:`_merge_by_contrast`). On suite slab
    1002 (seed 2) 11 gel probes on the foam's seam read 0.55-1.1 mm at 2 N, between the gel's
    0.18 and the foam's 1.41, and 1.3-2.2 mm at 6 N beside the foam's 1.97 read 8 mm out (the
    piece's from 3.6 mm): a fourth region of no material.

    ``far_field_mm`` (N,2), ``floor_mm``: each region's peak noise (:func:`peak_noise_mm`).
    At a force where the shallower region's dent is not measured (its median + ``floor_mm``
    within ``MEASURED_DENT_NOISES`` noises, as in :func:`_merge_by_contrast`), a piece that
    reads shallower still is within that region's noise there, which refutes nothing; it
    must lie strictly between at some other force. On unseen slab 1312 (run seed 1) seven
    hard-rubber probes within 2 mm of the gel's seam read 0.023-0.052 mm at 4.5 N, between
    the hard rubber's 0.021 and the gel's 0.34, in five pieces; one piece's median at 1.5 N
    read 0.010 mm, under the hard rubber's 0.013, whose dent there is within its noise (5 x
    0.0074 mm): a fourth region of three materials in every round. Returns (labels,
    relabelled point indices).
    """
    relabelled: list[int] = []
    if not depth_columns:
        return labels, relabelled
    labels = labels.copy()
    cols = np.log(np.maximum(features[:, depth_columns], 1e-6))
    seen_from = (np.zeros(labels.shape[0]) if seen_from_mm is None
                 else np.asarray(seen_from_mm, dtype=float).reshape(-1))
    moved = np.zeros(labels.shape[0], dtype=bool)
    while True:
        labels, k = _compact(labels)
        if k < 3:
            return labels, relabelled
        med = _region_medians(cols, labels, k)
        sizes = np.bincount(labels, minlength=k)
        read_at = _region_medians(seen_from[:, None], labels, k)[:, 0]
        unmeasured = None
        if far_field_mm is not None:
            noise = np.array([peak_noise_mm(far_field_mm[labels == r], floor_mm) for r in range(k)])
            with np.errstate(invalid="ignore"):
                unmeasured = np.exp(med) + floor_mm <= MEASURED_DENT_NOISES * noise[:, None]   # (k,F)
        done = True
        for band in np.argsort(sizes, kind="stable"):
            pieces = _pieces(np.flatnonzero(labels == band), neighbours)
            sides = [_sandwich(piece, int(band), labels, neighbours, cols, med, sizes, seen_from, read_at,
                               unmeasured) for piece in pieces]
            blends = [(piece, pair) for piece, pair in zip(pieces, sides) if pair is not None]
            if len(blends) < len(pieces):
                # Part of a real region: its blend pieces go, the region stays. A point moves
                # once this way, so the loop ends (otherwise the region count falls each pass).
                blends = [(piece, pair) for piece, pair in blends if not moved[piece].any()]
            if not blends:
                continue
            for piece, (a, b) in blends:
                with np.errstate(all="ignore"):
                    da = np.nanmean(np.abs(cols[piece] - med[a]), axis=1)
                    db = np.nanmean(np.abs(cols[piece] - med[b]), axis=1)
                labels[piece] = np.where(np.nan_to_num(da, nan=np.inf) <= np.nan_to_num(db, nan=np.inf), a, b)
                moved[piece] = True
                relabelled.extend(int(i) for i in piece)
            done = False
            break
        if done:
            return labels, relabelled


def _pieces(members: np.ndarray, neighbours: list[np.ndarray]) -> list[np.ndarray]:
    """The connected pieces of a set of points on the surface graph (sorted point indices each)."""
    inside = set(int(i) for i in members)
    pieces: list[np.ndarray] = []
    while inside:
        stack, piece = [min(inside)], set()
        while stack:
            i = stack.pop()
            if i in piece:
                continue
            piece.add(i)
            stack.extend(int(j) for j in neighbours[i] if int(j) in inside and int(j) not in piece)
        inside -= piece
        pieces.append(np.array(sorted(piece), dtype=np.int64))
    return pieces


def _sandwich(piece: np.ndarray, band: int, labels: np.ndarray, neighbours: list[np.ndarray],
              log_depth: np.ndarray, region_median: np.ndarray, sizes: np.ndarray,
              seen_from_mm: np.ndarray, region_read_at_mm: np.ndarray,
              region_unmeasured: np.ndarray | None = None) -> tuple[int, int] | None:
    """The pair of regions (a, b) a piece of region ``band`` is the blend of, or None: the
    piece runs along their seam (every point borders a or b, and borders both or a point
    of the piece that does), both regions have more points than the piece, and at
    every force the piece's median log depth lies strictly between theirs, or beyond the
    deeper one's where that one's peaks were read farther out than the piece's by more than
    :data:`NEAR_CONTACT_BAND_MM` (lower bounds), or below the shallower one's where that one's
    dent is not measured (``region_unmeasured`` (k,F), True there); strictly between at one
    force at least."""
    touching = [set(int(v) for v in labels[neighbours[i]]) - {band} for i in piece]
    around = set.union(*touching) if touching else set()
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mid = np.nanmedian(log_depth[piece], axis=0)
        piece_read_at = float(np.nanmedian(seen_from_mm[piece]))

    def blend_of(a: int, b: int) -> bool:
        if not (np.all(np.isfinite(region_median[[a, b]])) and np.all(np.isfinite(mid))):
            return False
        between = (mid - region_median[a]) * (mid - region_median[b]) < 0
        deeper = np.where(region_median[a] >= region_median[b], a, b)             # per force
        with np.errstate(invalid="ignore"):
            lower_bound = region_read_at_mm[deeper] > piece_read_at + NEAR_CONTACT_BAND_MM
        beyond = (mid >= region_median[deeper, np.arange(mid.size)]) & lower_bound
        shallower = np.where(region_median[a] >= region_median[b], b, a)          # per force
        in_noise = np.zeros(mid.size, dtype=bool) if region_unmeasured is None \
            else region_unmeasured[shallower, np.arange(mid.size)]
        below = (mid <= region_median[shallower, np.arange(mid.size)]) & in_noise
        return bool(np.any(between) and np.all(between | beyond | below))

    position = {int(i): n for n, i in enumerate(piece)}

    def on_seam(a: int, b: int) -> bool:
        # Every point is on the piece's edge (no interior of its own) and borders both A
        # and B or a point of the piece that does: the piece runs along the A|B seam.
        if not all(t & {a, b} for t in touching):
            return False
        both = [{a, b} <= t for t in touching]
        return all(both[n] or any(both[position[int(j)]] for j in neighbours[i] if int(j) in position)
                   for n, i in enumerate(piece))

    return next(((a, b) for a in sorted(around) for b in sorted(around)
                 if a < b and sizes[a] > piece.size and sizes[b] > piece.size and on_seam(a, b)
                 and blend_of(a, b)), None)


def cluster_regions(features: np.ndarray, edges: np.ndarray, feature_names: list[str] | None = None, *,
                    kmax: int = 6, beta: float = 1.5, min_island_points: int = 2,
                    feature_noise: np.ndarray | None = None, merge_sigmas: float = 4.0,
                    min_contrast: float = MIN_CONTRAST, max_dims: int = 3, order_feature: int = 0,
                    seed: int = 0, noise_mm: float | None = None,
                    previous_labels: np.ndarray | None = None,
                    far_field_mm: np.ndarray | None = None) -> RegionMap:
    """Cluster surveyed points (features (N,D), surface graph edges (E,2)) into regions.

    ``feature_noise`` (D,): measurement noise of each feature (e.g. the standard error of
    the peak depth); when given, clusters closer than ``merge_sigmas`` noises in every
    feature are merged. Clusters whose peak depths (features named ``peak...``) differ
    by less than a factor ``min_contrast`` at every force are merged. ``noise_mm``: the
    standard error of an averaged survey profile (mm), the floor under the peak depths'
    logarithms (default :data:`DEFAULT_LOG_FLOOR_MM`). ``previous_labels`` (N,): each
    point's region in the previous round (-1 for points added since): regions separated
    then stay separable now (see the module docstring). ``far_field_mm`` (N,2): what each
    point's averaged profile at the smallest survey force reads far from the contact
    (:func:`profiles.far_field_error_mm`), from which the contrast rule measures the scatter
    of a peak depth per cluster (:func:`peak_noise_mm`); without it the scatter is
    ``noise_mm``. See the module docstring for the steps.
    """
    x = np.asarray(features, dtype=float)
    if x.ndim != 2 or x.shape[0] == 0:
        raise ValueError("features must be (N,D) with N >= 1")
    n, d = x.shape
    names = list(feature_names) if feature_names is not None else [f"f{i}" for i in range(d)]
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    neighbours = _adjacency(n, e)
    depth_cols = [j for j, name in enumerate(names) if name.startswith("peak")]
    seen_from = x[:, names.index(SEEN_FROM_FEATURE)] if SEEN_FROM_FEATURE in names else None
    floor_mm = DEFAULT_LOG_FLOOR_MM if noise_mm is None else max(float(noise_mm), 1e-6)
    log_cols = list(depth_cols)
    if log_cols:
        # Peak depths of different materials differ by factors: their logarithms, unscaled,
        # are the model space (standardising would let the softest material's spread
        # squeeze two stiff materials together).
        xl = _log_features(x, log_cols, floor_mm)
        mean = np.nanmean(xl, axis=0)
        std = np.ones(d)
        z_std = np.where(np.isfinite(xl - mean), xl - mean, 0.0)
        proj = np.eye(d)[log_cols]
    else:
        z_std, mean, std = _standardise(x)
        proj = _projection(z_std, max_dims)
    z = z_std @ proj.T

    stats: dict[str, Any] = {}
    far = None
    if far_field_mm is not None:
        far = np.asarray(far_field_mm, dtype=float)
        if far.shape != (n, 2):
            raise ValueError(f"far_field_mm must be (N,2) for N={n} points; got {far.shape}")
        stats["peak_noise_mm"] = peak_noise_mm(far, floor_mm)
    if n >= 4:
        labels, bics = _choose_mixture(z, kmax, seed)
    else:
        labels, bics = np.arange(n, dtype=np.int64), {1: float("nan")}
    stats["bic"] = {int(k): v for k, v in bics.items()}
    labels, k = _compact(labels)
    stats["mixture_k"] = k
    if log_cols and min_contrast > 1.0:
        # The mixture may put two lone probes of two different inclusions in one component
        # (one component per probe costs more than the likelihood it buys): split every
        # cluster by the materials that the contrast rule alone finds among single points.
        alone, _ = _merge_by_contrast(x, np.arange(n), depth_cols, min_contrast, floor_mm, far, seen_from)
        labels, k = _compact(labels * (int(alone.max()) + 1) + alone)
    prev = None
    if previous_labels is not None:
        prev = np.asarray(previous_labels, dtype=np.int64).reshape(-1)
        if prev.shape[0] != n:
            raise ValueError("previous_labels must give one label (or -1) per point")
        # Split every cluster by the previous round's regions: a material separated then
        # is a candidate again now, and only the contrast rule below may join it back (on a
        # contrast it measures, see _merge_by_contrast).
        labels, k = _compact(labels * (int(prev.max(initial=-1)) + 2) + (prev + 1))
    merges = 0
    if feature_noise is not None and k > 1:
        # Where a peak was read says nothing of the material: not a feature to tell two apart by.
        material = [j for j, name in enumerate(names) if name != SEEN_FROM_FEATURE]
        labels, merges = _merge_by_noise(x[:, material], labels,
                                         np.asarray(feature_noise, dtype=float)[material], merge_sigmas)
        labels, k = _compact(labels)
    stats["merged"] = merges
    if k > 1:
        labels, contrast_merges = _merge_by_contrast(x, labels, depth_cols, min_contrast, floor_mm, far,
                                                     seen_from, previous_labels=prev, edges=e)
        labels, k = _compact(labels)
        stats["merged_by_contrast"] = contrast_merges

    reg = 1e-3
    icm_changes = 0
    kept: list[int] = []
    if k > 1:
        means, cov, log_prior = _fit_gaussians(z, labels, k, reg)
        labels, icm_changes = _icm(_gauss_loglik(z, means, cov) + log_prior, labels, neighbours, beta)
        def distinct(members: np.ndarray, region: np.ndarray, pooled_scatter: bool = False) -> bool:
            # Another material by the same contrast rule that made the regions.
            both = np.concatenate([members, region])
            two = np.concatenate([np.zeros(members.size, np.int64), np.ones(region.size, np.int64)])
            return int(_merge_by_contrast(x[both], two, depth_cols, min_contrast, floor_mm,
                                          None if far is None else far[both],
                                          None if seen_from is None else seen_from[both],
                                          pooled_scatter=pooled_scatter)[0].max()) > 0

        labels, islands, kept = _remove_islands(labels, e, neighbours, min_island_points,
                                                distinct if log_cols and min_contrast > 1.0 else None)
        labels, bands = _absorb_transition_bands(x, labels, neighbours, depth_cols, seen_from, far, floor_mm)
        labels, enclosed = (_enclosed_materials(x, labels, neighbours, depth_cols, min_contrast, floor_mm, far,
                                                seen_from, distinct, dent_falls_with_force(x, names, floor_mm))
                            if log_cols and min_contrast > 1.0 else (labels, []))
        labels, k = _compact(labels)
    else:
        islands, bands, enclosed = [], [], []
    stats["icm_changes"] = icm_changes
    stats["islands"] = islands
    stats["distinct_islands"] = kept
    stats["transition_band_points"] = bands
    stats["enclosed_material_points"] = enclosed

    # Stable ids: sort regions by the mean of one feature (then by size, then by first index).
    order_key = [(float(np.nanmean(x[labels == j, order_feature])), -int(np.sum(labels == j)),
                  int(np.flatnonzero(labels == j)[0])) for j in range(k)]
    order = sorted(range(k), key=lambda j: order_key[j])
    remap = np.empty(k, dtype=np.int64)
    remap[order] = np.arange(k)
    labels = remap[labels]
    means, cov, log_prior = _fit_gaussians(z, labels, k, reg)
    centroids = np.stack([np.nanmean(x[labels == j], axis=0) for j in range(k)])
    spread = np.stack([np.nanstd(x[labels == j], axis=0) for j in range(k)])
    stats["n_regions"] = k
    return RegionMap(labels=labels, n_regions=k, centroids=centroids, spread=spread,
                     counts=np.bincount(labels, minlength=k).astype(np.int64), feature_names=names,
                     scaler_mean=mean, scaler_std=std, projection=proj, region_means=means,
                     pooled_cov=cov, log_prior=log_prior, stats=stats, log_columns=log_cols,
                     log_floor_mm=floor_mm if log_cols else 0.0)


def _peak_columns(feature_names: list[str]) -> list[int]:
    """Indices of the peak-depth features (named ``peak...``, one per survey force)."""
    return [j for j, name in enumerate(feature_names) if name.startswith("peak")]


def log_peaks(features: np.ndarray, feature_names: list[str], noise_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(log(peak + noise) (N,F), relative noise noise / (peak + noise) (N,F)) of the peak-depth
    features (named ``peak...``), one column per survey force; ``noise_mm`` the standard
    error of an averaged survey profile."""
    x = np.asarray(features, dtype=float)
    cols = _peak_columns(feature_names)
    floor = max(float(noise_mm), 1e-6)
    peaks = np.maximum(x[:, cols], 0.0)
    return np.log(peaks + floor), floor / (peaks + floor)


def peaks_mm(features: np.ndarray, feature_names: list[str]) -> np.ndarray:
    """(N,F) each point's peak depth (mm, negative readings as 0) at each survey force (the
    features named ``peak...``)."""
    return np.maximum(np.asarray(features, dtype=float)[:, _peak_columns(feature_names)], 0.0)


def mean_peak_mm(features: np.ndarray, feature_names: list[str]) -> np.ndarray:
    """(N,) each point's peak depth (mm, negative readings as 0) averaged over the survey
    forces (:func:`peaks_mm`): the level the final map draws seams through when it has no
    peaks per force (with them it weighs the forces per pair of regions,
    surface_map._pair_levels), and the three-region bands are read on.
    In mm and not in log: a tip straddling a seam dents as the weighted mean of the two
    materials' dents (surface_map.seam_fractions)."""
    return peaks_mm(features, feature_names).mean(axis=1)


def dent_falls_with_force(features: np.ndarray, feature_names: list[str], noise_mm: float,
                          sigmas: float = 3.0) -> np.ndarray:
    """(N,) True where a point's peak depth falls as the survey force rises: its least-squares
    slope against force (the ``compliance_mm_per_n`` feature) lies more than ``sigmas``
    standard errors below zero, the error from ``noise_mm`` (the part of one peak's error
    that differs between the forces of one probe, mm: the loaded scans' standard error, as
    the probe's reference scans serve all its forces). A passive material's dent only
    deepens under more force, so such a point did not read its dent: the scanner saw only
    the dent's fading tail, from farther out at the larger force (the contact hidden; a
    thin layer at the foot of a dome reads 0.13-0.20 mm at 1.5 N and nothing at 4.5 N,
    suite 1007). False without the feature (one survey force) or where it is NaN."""
    names = list(feature_names)
    x = np.asarray(features, dtype=float)
    if "compliance_mm_per_n" not in names:
        return np.zeros(x.shape[0], dtype=bool)
    forces = np.array([float(names[j].split("@", 1)[1].rstrip("N")) for j in _peak_columns(names)])
    spread = float(np.sqrt(np.sum((forces - forces.mean()) ** 2)))
    if spread <= 0.0:
        return np.zeros(x.shape[0], dtype=bool)
    slope = x[:, names.index("compliance_mm_per_n")]
    return np.nan_to_num(slope, nan=0.0) < -sigmas * float(noise_mm) / spread


def survey_misfit(features: np.ndarray, labels: np.ndarray, feature_names: list[str], noise_mm: float,
                  min_contrast: float = MIN_CONTRAST, sigmas: float = 3.0,
                  far_field_mm: np.ndarray | None = None) -> np.ndarray:
    """(N,) how far each point's peak depths lie from its region's, in units of what the
    region can explain; > 1 means "another material may be here".

    Per survey force, the deviation |log(peak + noise) - median over the region| is
    compared with the larger of ``sigmas`` x the region's robust spread (1.4826 MAD of
    the same logarithms: the dent's drift with geometry and support within one material),
    ``sigmas`` x the point's own relative noise, and the contrast that makes two materials
    (log(min_contrast): a point that far from its region is another material by the rule
    that made the regions; within one material geometry alone moves a dent by up to ~2x,
    e.g. where the scan line runs off a block's shoulder). The result is the largest ratio
    over the forces; NaN features give 0. A point whose peaks were read beyond its region's
    band (``seen_from_mm``, see :func:`_merge_by_contrast`) has lower bounds only: reading
    shallower than its region is no misfit (the gel at the foot of a wall on generated
    composite 3007 reads 2.7x shallower from 13 mm out), reading deeper still is.

    A model fitted to the region's survey profiles predicts about their mean at the survey
    settings, pulled toward the misfit itself; the median is not.

    With ``far_field_mm`` (N,2) (what each point's profile reads far from the contact, as
    :func:`cluster_regions` takes it), a point is also a misfit by the test that gives an
    enclosed material back (:func:`odd_scores` against its region's peak scatter, in mm;
    not where its dent falls with force, :func:`dent_falls_with_force`): the larger of the
    two scores. Why: in a stiff region the logarithms' spread is the noise's, and on unseen
    slab 1703 (hard rubber, log MAD x 3 = 1.47) seven probes on an elastomer ellipse reading
    4x deeper (log 1.27 to 1.4) were no misfit, so nothing was probed around them in four
    rounds; one such probe alone is the case that matters, as the regions step needs two.
    """
    lab = np.asarray(labels, dtype=np.int64).reshape(-1)
    out = np.zeros(lab.shape[0])
    if lab.shape[0] == 0 or not any(name.startswith("peak") for name in feature_names):
        return out
    y, rel_noise = log_peaks(features, feature_names, noise_mm)
    contrast = float(np.log(min_contrast))
    floor = max(float(noise_mm), 1e-6)
    far = None if far_field_mm is None else np.asarray(far_field_mm, dtype=float).reshape(-1, 2)
    if far is not None:
        if far.shape[0] != lab.shape[0]:
            raise ValueError(f"far_field_mm must be (N,2) for N={lab.shape[0]} points; got {far.shape}")
        peaks = np.asarray(features, dtype=float)[:, _peak_columns(feature_names)]
        unread = dent_falls_with_force(features, feature_names, floor)
    seen_from = (np.asarray(features, dtype=float)[:, feature_names.index(SEEN_FROM_FEATURE)]
                 if SEEN_FROM_FEATURE in feature_names else np.zeros(lab.shape[0]))
    for region in np.unique(lab):
        members = np.flatnonzero(lab == region)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(y[members], axis=0)
            mad = 1.4826 * np.nanmedian(np.abs(y[members] - med), axis=0)
            read_far = seen_from[members] > np.nanmedian(seen_from[members]) + NEAR_CONTACT_BAND_MM
        allowed = np.maximum(np.maximum(sigmas * np.nan_to_num(mad), sigmas * rel_noise[members]), contrast)
        deviation = y[members] - med
        deviation = np.where(read_far[:, None], np.maximum(deviation, 0.0), np.abs(deviation))
        ratio = deviation / allowed
        out[members] = np.nanmax(np.where(np.isfinite(ratio), ratio, 0.0), axis=1)
        if far is not None and members.size >= 3:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                med_mm = np.nanmedian(peaks[members], axis=0)
            odd = odd_scores(peaks[members], med_mm, peak_noise_mm(far[members], floor), floor, min_contrast)
            odd = np.where(read_far, np.maximum(odd, 0.0), np.abs(odd)) * ~unread[members]
            out[members] = np.maximum(out[members], odd)
    return out


def label_new_points(region_map: RegionMap, new_features: np.ndarray, edges: np.ndarray,
                     beta: float = 1.5) -> np.ndarray:
    """Labels (M,) of densified points, without re-clustering.

    ``edges`` (E,2) index the combined set: 0..N-1 are the map's points (their labels
    stay fixed), N..N+M-1 the new ones in order. Each new point takes the region that
    maximises its feature log-likelihood plus ``beta`` per neighbour in the region.
    """
    f = np.asarray(new_features, dtype=float)
    n_old = region_map.labels.shape[0]
    m = f.shape[0]
    if m == 0:
        return np.zeros(0, dtype=np.int64)
    ll = region_map.loglik(f)
    total = np.concatenate([region_map.labels, np.argmax(ll, axis=1)])
    full_ll = np.zeros((n_old + m, region_map.n_regions))
    full_ll[n_old:] = ll
    free = np.zeros(n_old + m, dtype=bool)
    free[n_old:] = True
    labels, _ = _icm(full_ll, total, _adjacency(n_old + m, edges), beta, free=free)
    return labels[n_old:]


def propagate_labels(unit_positions_mm: np.ndarray, unit_labels: np.ndarray,
                     points_mm: np.ndarray) -> np.ndarray:
    """Region of every cloud point (P,3): the label of its nearest labelled unit."""
    from scipy.spatial import cKDTree

    _, idx = cKDTree(np.asarray(unit_positions_mm, dtype=float)).query(np.asarray(points_mm, dtype=float))
    return np.asarray(unit_labels)[idx]
