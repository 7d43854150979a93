"""Survey -> regions -> map over a dense surface -> scores against the truth -> densify proposals."""
import numpy as np

from elastoprobe.controller.learning.densify import plan_round
from elastoprobe.controller.learning.evaluate import region_map_scores
from elastoprobe.controller.learning.models import TrainConfig, fit_region_model
from elastoprobe.controller.learning.profiles import ProfileGrid
from elastoprobe.controller.learning.regions import cluster_regions, propagate_labels, survey_features

X_MM = ProfileGrid(80.0, 256).x_mm
FORCES_N = np.array([4.0, 12.0])
NOISE_MM = 0.02
SPACING_MM = 8.0
N = 12
CENTRE, RADIUS_MM = np.array([50.0, 44.0]), 27.0       # a stiff disc in a soft sheet


def hertz_normal_mm(x_mm, force_n, e_mpa, nu=0.45, tip_radius_mm=5.0):
    a = (3 * force_n * tip_radius_mm * (1 - nu ** 2) / (4 * e_mpa)) ** (1 / 3)
    r = np.abs(x_mm)
    ro = np.maximum(r, a)
    out = a ** 2 / (np.pi * tip_radius_mm) * ((2 - ro ** 2 / a ** 2) * np.arcsin(a / ro) + np.sqrt(ro ** 2 / a ** 2 - 1))
    return np.where(r <= a, a ** 2 / tip_radius_mm - r ** 2 / (2 * tip_radius_mm), out)


def truth_of(xy):
    return (np.linalg.norm(xy[:, :2] - CENTRE, axis=1) < RADIUS_MM).astype(int)


def test_survey_to_scored_map_and_boundary_proposals():
    rng = np.random.default_rng(0)
    g = np.arange(N) * SPACING_MM
    gx, gy = np.meshgrid(g, g, indexing="ij")
    pos = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(N * N)])
    edges = np.array([(i * N + j, (i + 1) * N + j) for i in range(N - 1) for j in range(N)]
                     + [(i * N + j, i * N + j + 1) for i in range(N) for j in range(N - 1)])
    true_units = truth_of(pos)
    # Dents 2.9x apart: two materials at the default contrast (2.5x).
    e_mpa = np.where(true_units == 1, 4.0, 0.8) * (1 + 0.05 * rng.normal(size=N * N))
    d = np.stack([[hertz_normal_mm(X_MM, f, e) for f in FORCES_N] for e in e_mpa])
    d += rng.normal(0, NOISE_MM, d.shape)
    feats, names = survey_features(d, X_MM, FORCES_N)
    rm = cluster_regions(feats, edges, names, seed=0)
    assert rm.n_regions == 2

    # The map over a dense "reachable scanned surface" (1 mm cloud) against the truth.
    c = np.arange(0.0, g[-1] + 0.5, 1.0)
    cx, cy = np.meshgrid(c, c, indexing="ij")
    cloud = np.column_stack([cx.ravel(), cy.ravel(), np.zeros(cx.size)])
    pred = propagate_labels(pos, rm.labels, cloud)
    s = region_map_scores(pred, truth_of(cloud), np.ones(cloud.shape[0]), cloud)
    assert s["mislabelled_fraction"] < 0.08
    assert s["worst_region_iou"] > 0.8
    # Nearest-unit labelling places the boundary within about half a unit spacing.
    assert s["boundary_mm_mean"] < SPACING_MM / 2 and s["boundary_mm_p90"] < SPACING_MM

    # Region models from the survey points of each region, then one densify round.
    models = {}
    for k in range(2):
        idx = np.flatnonzero(rm.labels == k)[:6]
        f = np.repeat(FORCES_N[None], idx.size, axis=0).ravel()
        prof = d[idx].reshape(-1, X_MM.size)
        models[k] = fit_region_model(f, np.full(f.size, 90.0), prof, X_MM, point_ids=np.repeat(idx, 2),
                                     config=TrainConfig(ensemble=3, stages=1, epochs_per_stage=300, seed=k),
                                     noise_mm=NOISE_MM)
    rnd = plan_round(0, pos, edges, rm.labels, models, FORCES_N, np.array([90.0]), NOISE_MM,
                     budget=10, min_spacing_mm=3.0, resolution_mm=6.0, posterior=rm.posterior(feats))
    prop = np.asarray(rnd.proposed_mm)
    assert not rnd.resolved and prop.shape[0] == 10
    dist_to_true_boundary = np.abs(np.linalg.norm(prop[:, :2] - CENTRE, axis=1) - RADIUS_MM)
    assert np.all(dist_to_true_boundary < SPACING_MM)
