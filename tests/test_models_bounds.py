"""Served profiles stay physical over the whole trained (F, angle) range (property test).

Region data come from the simulator's own contact physics (the composite's foam pillow
and cardboard box, the rubber ball) at two points per region, measured the way the
scanner sees a dent: only on the side the tangential load pushes toward, beyond the tip,
with scan noise, plus the tip's own position and depth. Hypothesis then draws thousands
of in-range queries per region and checks every served sample: no deeper than 1.5 x the
deepest true dent of the region, no more than 1 mm above the undeformed surface.

The same check fails on a model trained the way it was before complete targets and
served bounds (``test_the_check_catches_an_unbounded_model``): the test can fail.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from elastoprobe.controller.learning.models import RegionModel, TrainConfig, fit_region_model
from elastoprobe.controller.learning.profiles import ProfileGrid
from elastoprobe.controller.learning.support import RegionSteps
from elastoprobe.controller.phases import fit_region
from elastoprobe.sim.objects import load_object

ROOT = Path(__file__).resolve().parent.parent
GRID = ProfileGrid(80.0, 256)
TIP_RADIUS_MM = 5.0
ANGLES_DEG = (10.0, 25.0, 45.0, 75.0, 90.0, 105.0, 135.0, 155.0, 170.0)
FORCES_N = (2.0, 5.0, 9.0, 14.0, 20.0)
NOISE_MM = 0.02
QUERIES = 2000


def _points(obj, label: int, count: int = 2) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` face centres of region ``label`` facing up, far apart, away from its edges."""
    centres, normals = obj.mesh.triangles_center, obj.mesh.face_normals
    ok = np.flatnonzero((obj.face_labels == label) & (normals[:, 2] > 0.98))
    dist, _ = obj.boundary_distance_mm(centres[ok])
    ok = ok[np.argsort(-np.nan_to_num(dist, posinf=1e9))][: max(count * 20, 1)]
    picks = [ok[0], ok[np.argmax(np.linalg.norm(centres[ok] - centres[ok[0]], axis=1))]]
    return [(centres[i], normals[i]) for i in picks[:count]]


def _measured(obj, point: np.ndarray, normal: np.ndarray, rng: np.random.Generator, pid: int) -> dict:
    t = np.cross(normal, [1.0, 0.0, 0.0])
    t /= np.linalg.norm(t)
    x = GRID.x_mm
    rows: dict[str, list] = {k: [] for k in ("f", "lvl", "a", "d", "p", "tx", "td", "rh", "truth")}
    for a in ANGLES_DEG:
        model = obj.contact_model(point, normal, t, a, TIP_RADIUS_MM)
        for f in FORCES_N:
            truth = model.depth_profile_mm(x, f) - model.depth_profile_mm(x, 0.0)
            k = int(np.argmax(truth))
            lead = 1.0 if a <= 90.0 else -1.0
            seen = lead * (x - x[k]) > TIP_RADIUS_MM + 1.0
            rows["f"].append(f)
            rows["lvl"].append(f)
            rows["a"].append(a)
            rows["d"].append(np.where(seen, truth + rng.normal(0.0, NOISE_MM, x.shape), np.nan))
            rows["p"].append(pid)
            rows["tx"].append(x[k])
            rows["td"].append(truth[k])
            rows["rh"].append(rng.normal(0.0, NOISE_MM / 2, x.shape))
            rows["truth"].append(truth)
    return rows


def region_data(obj_file: str, label: int, seed: int) -> tuple[RegionSteps, float]:
    """(the region's steps at two points, the deepest true dent over them in mm)."""
    obj = load_object(ROOT / "config" / "objects" / obj_file)
    rng = np.random.default_rng(seed)
    rows: dict[str, list] = {}
    for pid, (p, n) in enumerate(_points(obj, label)):
        for k, v in _measured(obj, p, n, rng, pid).items():
            rows.setdefault(k, []).extend(v)
    arr = {k: np.array(v) for k, v in rows.items()}
    steps = RegionSteps(GRID.x_mm, arr["f"], arr["lvl"], arr["a"], arr["d"], arr["p"].astype(np.int64),
                        arr["tx"], arr["td"], arr["rh"])
    return steps, float(arr["truth"].max())


REGIONS = {"foam": ("composite.yaml", 1), "box": ("composite.yaml", 0), "rubber": ("rubber_ball.yaml", 0)}


@pytest.fixture(scope="module", params=sorted(REGIONS))
def served(request: pytest.FixtureRequest) -> tuple[RegionModel, float]:
    steps, deepest = region_data(*REGIONS[request.param], seed=3)
    config = TrainConfig(ensemble=1, seed=5, basis_spacing_mm=TIP_RADIUS_MM / 5.0)
    model, _ = fit_region(steps, config, TIP_RADIUS_MM, NOISE_MM)
    return model, deepest


def violations(model: RegionModel, deepest_true_mm: float, forces_n: np.ndarray, angles_deg: np.ndarray,
               raw: bool = False) -> np.ndarray:
    """(Q,) True where a query's profile has a sample deeper than 1.5 x the deepest true dent,
    more than 1 mm above the surface, or not a number."""
    d = model.raw_batch_mm(forces_n, angles_deg) if raw else model.predict_batch_mm(forces_n, angles_deg)
    return ~np.all(np.isfinite(d) & (d <= 1.5 * deepest_true_mm) & (d >= -1.0), axis=1)


@settings(max_examples=QUERIES, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(u=st.floats(0.0, 1.0), v=st.floats(0.0, 1.0))
def test_every_in_range_query_is_served_within_physical_bounds(served: tuple[RegionModel, float],
                                                               u: float, v: float) -> None:
    model, deepest = served
    lim = model.limits
    assert lim is not None
    f = lim.force_range_n[0] + u * (lim.force_range_n[1] - lim.force_range_n[0])
    a = lim.angle_range_deg[0] + v * (lim.angle_range_deg[1] - lim.angle_range_deg[0])
    profile = model.serve(f, a)
    assert not violations(model, deepest, np.array([f]), np.array([a]))[0], (f, a, profile.depth_mm.min(),
                                                                               profile.depth_mm.max(), deepest)
    assert not profile.extrapolated and np.all(profile.support >= 0)


def test_the_check_catches_an_unbounded_model() -> None:
    """Trained as before (measured samples only, no bounds), the same data give a model
    that the check rejects somewhere in range: the property above can fail."""
    steps, deepest = region_data("composite.yaml", 1, seed=3)
    old = fit_region_model(steps.force_n, steps.angle_deg, steps.depth_mm, steps.x_mm, point_ids=steps.point_ids,
                           config=TrainConfig(ensemble=0, seed=5), noise_mm=NOISE_MM)
    rng = np.random.default_rng(0)
    f = rng.uniform(min(FORCES_N), max(FORCES_N), QUERIES)
    a = rng.uniform(min(ANGLES_DEG), max(ANGLES_DEG), QUERIES)
    assert violations(old, deepest, f, a).any()
