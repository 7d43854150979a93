"""How many survey targets a plan's ``sampling.min_feature_mm`` asks for (docs/generated_objects.md,
"The smallest feature the survey finds").

The requirement: every disc of diameter d = ``min_feature_mm`` lying on the probe-able top
holds a survey target. That holds when the targets' covering radius R (the farthest any
probe-able point lies from its nearest target) is at most d / 2. For targets of mean
spacing s = sqrt(A / N) over a probe-able area A, a hexagonal lattice has R = 0.62 s
(R = s / sqrt 3, A / N = (sqrt 3 / 2) s^2); the neural gas is less regular. Measured
on the generated suite's scanned clouds (the probe-able part, points at least d / 2 inside
its rim, the plan rule's neural gas, the targets left after make_targets, 40-160 units on
1004, 1005, 1006; the 99th percentile is 0.63-0.66 s, the largest 0.71-0.79 s), so
``COVER_FACTOR`` = 0.8 and

    N = ceil(A (2 x COVER_FACTOR / d)^2)

(d = 15 mm: one unit per 88 mm^2; a perfect hexagonal lattice would need one per
146 mm^2, spacing 0.87 d: the neural gas's irregularity costs two-thirds more units).
Targets closer than ``MERGE_FRACTION`` x s are merged
(learning.targets.TargetRules.min_spacing_mm): the default merge distance, two tip radii,
is larger than s for small features, and with it more units gave FEWER targets (on 1004,
160 units gave 51 targets and a covering radius of 13.8 mm; unmerged, 6.6 mm).

On a dome it was not measured on (tests/test_survey_density.py) the gas left one hole of
R = 0.875 s (2 of 13 177 points 8.2 mm from a target at d = 15 mm): the guarantee is
nearly every disc of d, and every disc of 1.1 d.

A target inside the disc is where the survey presses; whether its dent reads as the
inclusion's material when it lands near the seam is the regions' and densify's matter
(a target can lie just inside the seam: the guarantee is "contains", not "centred").

Frames and units: object frame, mm, mm^2.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

COVER_FACTOR = 0.8
MERGE_FRACTION = 0.5
AREA_CELL_MM = 5.0     # the targets' density radius: a probe-able point has cloud points this close


def probeable_area_mm2(points_mm: np.ndarray, cell_mm: float = AREA_CELL_MM) -> float:
    """The area (mm^2) the probe-able points (P, 3) cover, seen from above: occupied squares
    of ``cell_mm``. A probe-able point has at least ten cloud points within 5 mm
    (learning.targets.TargetRules), so the set has no hole of a whole cell inside; along its
    rim the count over-reaches by up to a cell, so the area errs large (more units, not fewer).
    The tilt (at most the plan's limit) is left out: the area seen from above is at most
    1/cos(tilt) smaller than the surface's."""
    pts = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    if len(pts) == 0:
        return 0.0
    cells = np.unique(np.floor(pts[:, :2] / cell_mm).astype(np.int64), axis=0)
    return float(len(cells) * cell_mm * cell_mm)


def units_for_min_feature(area_mm2: float, min_feature_mm: float) -> int:
    """Neural-gas units such that every disc of diameter ``min_feature_mm`` on a probe-able
    area of ``area_mm2`` holds a target (module docstring)."""
    return int(math.ceil(area_mm2 * (2.0 * COVER_FACTOR / min_feature_mm) ** 2))


def survey_units(plan_units: int, min_feature_mm: float | None, probeable_mm: np.ndarray) -> int:
    """The survey's unit count: the plan's ``units``, raised for ``min_feature_mm`` (None: not)."""
    if min_feature_mm is None or plan_units == 0:
        return plan_units
    return max(plan_units, units_for_min_feature(probeable_area_mm2(probeable_mm), min_feature_mm))


def merge_spacing_mm(default_mm: float, min_feature_mm: float | None) -> float:
    """Targets closer than this are merged: the default (two tip radii), or for a
    ``min_feature_mm`` survey at most half its mean spacing (module docstring)."""
    if min_feature_mm is None:
        return default_mm
    return min(default_mm, MERGE_FRACTION * min_feature_mm / (2.0 * COVER_FACTOR))


def covering_radius_mm(surface_mm: np.ndarray, targets_mm: np.ndarray) -> np.ndarray:
    """(S,) distance (mm) from each surface point (S, 3) to its nearest target (T, 3): a disc
    of diameter d centred at a point holds a target iff this is at most d / 2."""
    dist, _ = cKDTree(np.asarray(targets_mm, dtype=float).reshape(-1, 3)).query(
        np.asarray(surface_mm, dtype=float).reshape(-1, 3))
    return np.asarray(dist)
