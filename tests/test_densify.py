import json

import numpy as np
import pytest

from elastoprobe.controller.learning.densify import (
    _crossing_fraction, averaged_noise_mm, boundaries_resolved, candidate_points, edge_scores, pair_scores, plan_round,
    point_scores, propose_points,
)
from elastoprobe.controller.learning.models import TrainConfig, fit_region_model
from elastoprobe.controller.learning.profiles import ProfileGrid, average_profiles

X_MM = ProfileGrid(80.0, 256).x_mm
SURVEY_F = np.array([4.0, 12.0])
SURVEY_A = np.array([90.0])
NOISE_MM = 0.02


def hertz_normal_mm(x_mm, force_n, e_mpa, nu=0.45, tip_radius_mm=5.0):
    a = (3 * force_n * tip_radius_mm * (1 - nu ** 2) / (4 * e_mpa)) ** (1 / 3)
    r = np.abs(x_mm)
    w = np.where(r <= a, a ** 2 / tip_radius_mm - r ** 2 / (2 * tip_radius_mm), 0.0)
    ro = np.maximum(r, a)
    out = a ** 2 / (np.pi * tip_radius_mm) * ((2 - ro ** 2 / a ** 2) * np.arcsin(a / ro) + np.sqrt(ro ** 2 / a ** 2 - 1))
    return np.where(r <= a, w, out)


def region_model(e_mpa, seed):
    """A region model from 3 surveyed points of one material (averaged noisy profiles)."""
    rng = np.random.default_rng(seed)
    forces = np.array([2.0, 4.0, 8.0, 12.0, 16.0])
    f = np.tile(forces, 3)
    ids = np.repeat(np.arange(3), forces.size)
    e = np.repeat(e_mpa * (1 + 0.03 * rng.normal(size=3)), forces.size)
    d = np.stack([hertz_normal_mm(X_MM, fi, ei) for fi, ei in zip(f, e)]) + rng.normal(0, NOISE_MM, (f.size, X_MM.size))
    cfg = TrainConfig(ensemble=3, stages=1, epochs_per_stage=300, seed=seed)
    return fit_region_model(f, np.full(f.size, 90.0), d, X_MM, point_ids=ids, config=cfg, noise_mm=NOISE_MM)


@pytest.fixture(scope="module")
def models():
    return {0: region_model(2.0, 1), 1: region_model(0.7, 2), 2: region_model(2.0, 3)}


def grid_graph(n, spacing_mm=10.0):
    gx, gy = np.meshgrid(np.arange(n) * spacing_mm, np.arange(n) * spacing_mm, indexing="ij")
    pos = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(n * n)])
    edges = [(i * n + j, (i + 1) * n + j) for i in range(n - 1) for j in range(n)]
    edges += [(i * n + j, i * n + j + 1) for i in range(n) for j in range(n - 1)]
    return pos, np.array(edges)


N = 10
POS, EDGES = grid_graph(N)
LABELS = (POS[:, 0] >= 50.0).astype(int)          # boundary between x = 40 and x = 50


def test_different_materials_disagree_same_material_does_not(models):
    scores = pair_scores(np.array([0, 1, 2]), models, SURVEY_F, SURVEY_A, NOISE_MM)
    assert scores[(0, 1)] > 10.0 and scores[(1, 2)] > 10.0
    assert scores[(0, 2)] < 3.0
    missing = pair_scores(np.array([0, 5]), models, SURVEY_F, SURVEY_A, NOISE_MM)
    assert missing[(0, 5)] == np.inf


def test_proposes_on_the_boundary_not_in_interiors(models):
    rnd = plan_round(0, POS, EDGES, LABELS, {0: models[0], 1: models[1]}, SURVEY_F, SURVEY_A, NOISE_MM,
                     budget=6, min_spacing_mm=4.0, resolution_mm=8.0)
    assert not rnd.resolved and not rnd.stop and "longer than 8 mm" in rnd.reason
    prop = np.asarray(rnd.proposed_mm)
    assert prop.shape == (6, 3)
    assert np.all(np.abs(prop[:, 0] - 45.0) < 1e-9)           # midpoints of crossing edges
    gaps = np.linalg.norm(prop[:, None] - prop[None], axis=2) + np.eye(6) * 1e9
    assert gaps.min() >= 4.0
    assert len(rnd.disagreeing_edges) == N
    json.dumps(rnd.to_dict(), allow_nan=False)
    # Midpoints 5 mm from their ends cannot keep 6 mm: the round says so and stops.
    tight = plan_round(1, POS, EDGES, LABELS, {0: models[0], 1: models[1]}, SURVEY_F, SURVEY_A, NOISE_MM,
                       budget=6, min_spacing_mm=6.0, resolution_mm=8.0)
    assert tight.stop and not tight.resolved and "6 mm" in tight.reason


def test_no_proposals_when_regions_agree(models):
    rnd = plan_round(0, POS, EDGES, LABELS, {0: models[0], 1: models[2]}, SURVEY_F, SURVEY_A, NOISE_MM,
                     budget=6, min_spacing_mm=6.0, resolution_mm=4.0)
    assert rnd.resolved and rnd.proposed_mm == [] and "disagree" in rnd.reason


def test_stop_rule_on_edge_length():
    pos = np.array([[0.0, 0, 0], [3.0, 0, 0], [10.0, 0, 0]])
    edges = np.array([[0, 1], [1, 2]])
    assert boundaries_resolved(pos, edges, np.array([5.0, 0.0]), resolution_mm=4.0)[0]
    assert not boundaries_resolved(pos, edges, np.array([5.0, 5.0]), resolution_mm=4.0)[0]
    assert boundaries_resolved(pos, edges, np.array([1.0, 2.0]), resolution_mm=4.0)[0]


def test_propose_respects_spacing_budget_and_threshold():
    cand = np.array([[0.0, 0, 0], [1.0, 0, 0], [10.0, 0, 0], [20.0, 0, 0], [30.0, 0, 0]])
    scores = np.array([9.0, 8.0, 2.0, 7.0, np.inf])
    existing = np.array([[19.0, 0, 0]])
    idx = propose_points(cand, scores, existing, budget=5, min_spacing_mm=5.0, min_score=3.0)
    assert idx.tolist() == [4, 0]          # inf first; 1 too close to 0; 2 below threshold; 3 too close
    assert propose_points(cand, scores, existing, budget=1, min_spacing_mm=5.0).tolist() == [4]


def test_ambiguous_points_and_candidates():
    scores = {(0, 1): 10.0}
    post = np.array([[0.5, 0.5], [0.99, 0.01], [0.2, 0.8]])
    ps = point_scores(post, scores)
    assert np.isclose(ps[0], 10.0) and ps[1] < 0.3 and np.isclose(ps[2], 4.0)
    pos = np.array([[0.0, 0, 0], [10.0, 0, 0], [20.0, 0, 0]])
    edges = np.array([[0, 1], [1, 2]])
    es = edge_scores(edges, np.array([0, 0, 0]), scores)
    assert es.tolist() == [0.0, 0.0]
    cand, cs = candidate_points(pos, edges, es, ps)
    assert np.allclose(cand[:, 0], [5.0, 15.0]) and np.allclose(cs, [10.0, 4.0])
    surface = np.array([[5.0, 0, 1.0], [15.0, 0, 2.0]])
    cand, _ = candidate_points(pos, edges, es, ps, surface_points_mm=surface)
    assert np.allclose(cand, surface)


def test_averaged_noise_from_scan_statistics():
    rng = np.random.default_rng(0)
    scans = rng.normal(0, 0.08, (16, 256))
    _, count, std = average_profiles(scans)
    assert abs(averaged_noise_mm(std, count) - 0.02) < 0.003


def test_bisects_the_widest_unresolved_gaps_first(models):
    """Crossing edges of one pair of regions all score alike: the longest gaps are split first,
    and an edge already within resolution_mm is not split again."""
    pos = np.array([[0.0, 0, 0], [6.0, 0, 0], [0.0, 20, 0], [30.0, 20, 0], [0.0, 40, 0], [14.0, 40, 0]])
    edges = np.array([[0, 1], [2, 3], [4, 5], [0, 2], [2, 4], [1, 3], [3, 5]])
    labels = np.array([0, 1, 0, 1, 0, 1])
    rnd = plan_round(0, pos, edges, labels, {0: models[0], 1: models[1]}, SURVEY_F, SURVEY_A, NOISE_MM,
                     budget=2, min_spacing_mm=2.0, resolution_mm=8.0)
    assert np.allclose(rnd.proposed_mm, [[15.0, 20, 0], [7.0, 40, 0]])
    one = plan_round(0, pos, edges, labels, {0: models[0], 1: models[1]}, SURVEY_F, SURVEY_A, NOISE_MM,
                     budget=5, min_spacing_mm=2.0, resolution_mm=8.0)
    assert [3.0, 0.0, 0.0] not in one.proposed_mm           # the 6 mm edge is resolved


class _Dent:
    """A stand-in region model: a Gaussian dent of ``peak_mm`` (at the larger survey force,
    linear in force), and an ensemble spread of ``rel_spread`` x the profile."""

    def __init__(self, peak_mm: float, rel_spread: float) -> None:
        self.peak_mm, self.rel_spread = peak_mm, rel_spread

    def predict_batch_mm(self, force_n, angle_deg):
        f = np.asarray(force_n, dtype=float).reshape(-1, 1)
        return self.peak_mm * f / SURVEY_F.max() * np.exp(-(X_MM[None, :] / 8.0) ** 2)

    def predict_ensemble(self, force_n, angle_deg):
        mean = self.predict_batch_mm(force_n, angle_deg)
        return mean, self.rel_spread * mean


def test_an_order_of_magnitude_is_not_drowned_by_the_ensemble_spread():
    """A sponge 20x deeper than an elastomer, each model unsure of its depth by 40 % (two or
    three bootstrapped probe points): in millimetres the difference is 2.4 spreads, under the
    threshold; as a ratio of depths it is 5.3 spreads, far above."""
    from elastoprobe.controller.learning.densify import DEFAULT_THRESHOLD, model_distance, peak_ratio_score

    stiff, soft = _Dent(0.1, 0.4), _Dent(2.0, 0.4)
    diff, spread = model_distance(stiff, soft, SURVEY_F, SURVEY_A)
    assert diff / np.hypot(NOISE_MM, spread) < DEFAULT_THRESHOLD
    assert peak_ratio_score(stiff, soft, SURVEY_F, SURVEY_A, NOISE_MM) > 1.5 * DEFAULT_THRESHOLD
    assert pair_scores(np.array([0, 1]), {0: stiff, 1: soft}, SURVEY_F, SURVEY_A, NOISE_MM)[(0, 1)] > 5.0
    # One material, two regions: no disagreement either way.
    assert peak_ratio_score(_Dent(0.5, 0.3), _Dent(0.55, 0.3), SURVEY_F, SURVEY_A, NOISE_MM) < 1.0


def test_survey_scores_from_every_point_of_each_region():
    """The survey's own dents tell two regions apart (medians many standard errors apart)
    while the models may not; one material split in two scores low."""
    from elastoprobe.controller.learning.densify import survey_pair_scores

    rng = np.random.default_rng(4)
    labels = np.repeat([0, 1], 12)
    log_depth = np.where(labels[:, None] == 0, np.log(0.1), np.log(2.0)) + rng.normal(0, 0.15, (24, 2))
    rel = np.full((24, 2), 0.02)
    assert survey_pair_scores(log_depth, labels, rel)[(0, 1)] > 20.0
    same = np.log(0.5) + rng.normal(0, 0.15, (24, 2))
    assert survey_pair_scores(same, labels, rel)[(0, 1)] < 3.0


def test_a_point_its_region_explains_badly_is_probed_around():
    """One region, no boundary: resolved. A survey point flagged as a misfit (its dent beyond
    what its region explains): the round proposes the ring of its long edges."""
    labels = np.zeros(N * N, dtype=int)
    models = {0: _Dent(0.5, 0.1)}
    calm = plan_round(1, POS, EDGES, labels, models, SURVEY_F, SURVEY_A, NOISE_MM, budget=8,
                      min_spacing_mm=3.0, resolution_mm=6.0)
    assert calm.resolved and calm.proposed_mm == []
    odd = 4 * N + 4
    misfit = np.zeros(N * N)
    misfit[odd] = 1.8
    rnd = plan_round(1, POS, EDGES, labels, models, SURVEY_F, SURVEY_A, NOISE_MM, budget=8,
                     min_spacing_mm=3.0, resolution_mm=6.0, misfit=misfit)
    assert not rnd.resolved and rnd.extra["misfit_points"] == [odd]
    prop = np.asarray(rnd.proposed_mm)
    assert prop.shape == (4, 3)                                   # the four edges of a grid point
    assert np.allclose(np.linalg.norm(prop - POS[odd], axis=1), 5.0)
    assert rnd.extra["ring_around"] == []              # a misfit is not a material: no ring


def test_a_crossing_edge_is_split_where_the_level_crosses_midway():
    """A crossing edge whose stiff end dents a little deeper than its region (a probe straddling
    the seam): the seam is near that end, and the new point goes there, not to the midpoint."""
    pos = np.array([[0.0, 0, 0], [-20.0, 0, 0], [-30.0, 0, 0], [20.0, 0, 0], [30.0, 0, 0], [40.0, 0, 0]])
    edges = np.array([[0, 3], [1, 0], [2, 1], [3, 4], [4, 5]])
    labels = np.array([0, 0, 0, 1, 1, 1])
    # Levels (log depth): region 0 near log 0.1, region 1 near log 2.0; point 0 part way.
    levels = np.log(np.array([0.4, 0.1, 0.1, 2.0, 2.0, 2.0]))
    models = {0: _Dent(0.1, 0.1), 1: _Dent(2.0, 0.1)}
    plain = plan_round(1, pos, edges, labels, models, SURVEY_F, SURVEY_A, NOISE_MM, budget=1,
                       min_spacing_mm=2.0, resolution_mm=6.0)
    assert np.allclose(plain.proposed_mm, [[10.0, 0, 0]])
    toward = plan_round(1, pos, edges, labels, models, SURVEY_F, SURVEY_A, NOISE_MM, budget=1,
                        min_spacing_mm=2.0, resolution_mm=6.0, levels=levels)
    assert 0.0 < toward.proposed_mm[0][0] < 10.0


def test_a_crossing_edge_whose_crossing_lies_near_an_end_still_gets_a_probe():
    """A 10 mm crossing edge whose stiff end dents nearly as deep as the soft side (it straddles
    the seam): the level crosses midway near that end, and the false-position step, clipped to
    a fifth of the edge, puts the new probe 2 mm from it, inside the 3 mm spacing. The probe
    goes where the spacing allows (3 mm from that end), not nowhere: the seam along this edge
    is still unknown to within its 10 mm. (That end reads past the halfway toward the soft
    side, so its edge into its own region, x -10 to 0, is split too: only the crossing edge's
    probe, x > 0, is checked here.)"""
    pos = np.array([[0.0, 0, 0], [-10.0, 0, 0], [-20.0, 0, 0], [10.0, 0, 0], [20.0, 0, 0], [30.0, 0, 0]])
    edges = np.array([[0, 3], [1, 0], [2, 1], [3, 4], [4, 5]])
    labels = np.array([0, 0, 0, 1, 1, 1])
    levels = np.log(np.array([1.6, 0.1, 0.1, 2.0, 2.0, 2.0]))
    models = {0: _Dent(0.1, 0.1), 1: _Dent(2.0, 0.1)}
    assert np.isclose(_crossing_fraction(edges, labels, levels)[0], 0.2)
    rnd = plan_round(1, pos, edges, labels, models, SURVEY_F, SURVEY_A, NOISE_MM, budget=4,
                     min_spacing_mm=3.0, resolution_mm=6.0, levels=levels)
    assert np.allclose([p for p in rnd.proposed_mm if p[0] > 0.0], [[3.0, 0, 0]])
    wide = plan_round(1, pos, edges, labels, models, SURVEY_F, SURVEY_A, NOISE_MM, budget=4,
                      min_spacing_mm=1.0, resolution_mm=6.0, levels=levels)
    assert np.allclose([p for p in wide.proposed_mm if p[0] > 0.0], [[2.0, 0, 0]])


def test_an_edge_within_a_region_whose_end_reads_toward_its_neighbour_is_split():
    """A stiff inclusion (x 0-20, level log 0.1) in a soft matrix (log 2.0). The probe at x = 30
    is labelled soft (the clustering put it with its neighbours) but dents nearly as little as
    the stiff side (log 0.15, past the halfway toward it): its tip pressed mostly stiff
    material, and the seam lies between it and the soft probe at x = 40, along an edge
    whose ends share a label. That edge scores as a crossing edge (its midpoint, x = 35, is
    proposed); with the probe at x = 30 reading short of the halfway (log 1.5), it does not."""
    pos = np.array([[x, 0.0, 0.0] for x in (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0)])
    edges = np.array([[k, k + 1] for k in range(6)])
    labels = np.array([1, 1, 1, 0, 0, 0, 0])
    models = {0: _Dent(2.0, 0.1), 1: _Dent(0.1, 0.1)}
    kw = dict(budget=4, min_spacing_mm=2.0, resolution_mm=6.0)
    past = np.log(np.array([0.1, 0.1, 0.1, 0.15, 2.0, 2.0, 2.0]))
    rnd = plan_round(1, pos, edges, labels, models, SURVEY_F, SURVEY_A, NOISE_MM, levels=past, **kw)
    xs = sorted(p[0] for p in rnd.proposed_mm)
    assert 35.0 in xs and len(xs) == 2 and 20.0 < xs[0] < 30.0
    assert [3, 4] in rnd.disagreeing_edges
    short = np.log(np.array([0.1, 0.1, 0.1, 1.5, 2.0, 2.0, 2.0]))
    rnd = plan_round(1, pos, edges, labels, models, SURVEY_F, SURVEY_A, NOISE_MM, levels=short, **kw)
    assert len(rnd.proposed_mm) == 1 and 20.0 < rnd.proposed_mm[0][0] < 30.0
    assert rnd.disagreeing_edges == [[2, 3]]


def test_a_longer_border_is_split_before_an_equal_gap_at_a_corner(models):
    """Two crossing edges of equal length: with ``border`` the one whose cells share more
    surface (more area hangs on where that boundary is drawn) is split first."""
    pos = np.array([[0.0, 0, 0], [20.0, 0, 0], [0.0, 40, 0], [20.0, 40, 0], [-20.0, 20, 0], [40.0, 20, 0]])
    edges = np.array([[0, 1], [2, 3], [0, 2], [1, 3], [0, 4], [2, 4], [1, 5], [3, 5]])
    labels = np.array([0, 1, 0, 1, 0, 1])
    kw = dict(budget=1, min_spacing_mm=2.0, resolution_mm=8.0)
    first = plan_round(0, pos, edges, labels, {0: models[0], 1: models[1]}, SURVEY_F, SURVEY_A, NOISE_MM,
                       border=np.array([2.0, 30.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]), **kw)
    assert np.allclose(first.proposed_mm, [[10.0, 40, 0]])
    other = plan_round(0, pos, edges, labels, {0: models[0], 1: models[1]}, SURVEY_F, SURVEY_A, NOISE_MM,
                       border=np.array([30.0, 2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]), **kw)
    assert np.allclose(other.proposed_mm, [[10.0, 0, 0]])


def test_a_lone_probe_of_another_material_is_ringed_before_its_edges_are_split():
    """A small inclusion one survey probe landed on (a region of one point in a 10 mm grid):
    the round first rings it at a quarter of the survey spacing (2.5 mm; the midpoints of its
    edges, 5 mm out, mostly fall outside an inclusion that small), then splits edges. A lone
    point its neighbours' region does not disagree with gets no ring."""
    labels = np.zeros(N * N, dtype=int)
    lone = 4 * N + 4
    labels[lone] = 1
    rnd = plan_round(1, POS, EDGES, labels, {0: _Dent(0.1, 0.1), 1: _Dent(2.0, 0.1)}, SURVEY_F, SURVEY_A,
                     NOISE_MM, budget=8, min_spacing_mm=2.0, resolution_mm=6.0)
    assert rnd.extra["ring_around"] == [lone]
    prop = np.asarray(rnd.proposed_mm)
    r = np.linalg.norm(prop - POS[lone], axis=1)
    assert prop.shape == (8, 3)
    assert np.allclose(r[:6], 2.5) and np.allclose(r[6:], 5.0)
    angles = np.sort(np.degrees(np.arctan2(prop[:6, 1] - POS[lone, 1], prop[:6, 0] - POS[lone, 0])) % 360)
    assert np.allclose(np.diff(angles), 60.0)
    same = plan_round(1, POS, EDGES, labels, {0: _Dent(0.5, 0.1), 1: _Dent(0.52, 0.1)}, SURVEY_F, SURVEY_A,
                      NOISE_MM, budget=8, min_spacing_mm=2.0, resolution_mm=6.0)
    assert same.resolved and same.proposed_mm == []


def test_a_ring_follows_the_surface_and_skips_a_point_already_surrounded():
    """On a tilted plane the ring lies in the plane (snapped to the measured surface); a lone
    point whose edges are all within the resolution is already surrounded: no ring."""
    from elastoprobe.controller.learning.densify import ring_candidates

    tilt = np.radians(30.0)
    u, v = np.meshgrid(np.linspace(-40, 40, 161), np.linspace(-40, 40, 161))
    surface = np.column_stack([u.ravel() * np.cos(tilt), v.ravel(), u.ravel() * np.sin(tilt)])
    pos = np.array([[0.0, 0, 0], [20 * np.cos(tilt), 0, 20 * np.sin(tilt)], [0, 20.0, 0], [0, -20.0, 0]])
    edges = np.array([[0, 1], [0, 2], [0, 3]])
    ring, owner = ring_candidates(pos, edges, np.array([0]), min_spacing_mm=3.0, resolution_mm=6.0,
                                  surface_points_mm=surface)
    assert ring.shape == (6, 3) and np.all(owner == 0)
    normal = np.array([-np.sin(tilt), 0.0, np.cos(tilt)])
    assert np.all(np.abs((ring - pos[0]) @ normal) < 1e-6)
    assert np.allclose(np.linalg.norm(ring - pos[0], axis=1), 5.0, atol=0.3)
    close = pos * 0.25
    assert ring_candidates(close, edges, np.array([0]), 3.0, 6.0, surface)[0].shape == (0, 3)


def test_a_small_region_mostly_seam_points_is_split_next_to_them():
    """A soft strip (level log 2) of nine interior points (x = 0, 10, 20) and thirteen that an
    earlier round put along its seam (x = 30, 20-80 % of the way to the stiff level, log 0.2);
    the stiff side starts at x = 36. Read on all 22 points the soft level range spans the
    stiff one and every crossing edge would be split midway (x = 33); read on the interior,
    as the final map reads it, the seam points are placed between the levels and the new
    points go next to them (at most 40 % of the way; a fifth, the clip, from the seam points
    nearly halfway to the stiff level), where the seam is."""
    inner = [[x, y, 0.0] for x in (0.0, 10.0, 20.0) for y in (0.0, 12.0, 24.0)]
    seam = [[30.0, y, 0.0] for y in np.linspace(0.0, 24.0, 13)]
    stiff = [[x, y, 0.0] for x in (36.0, 46.0, 56.0) for y in (0.0, 6.0, 12.0, 18.0, 24.0)]
    pos = np.array(inner + seam + stiff)
    labels = np.array([0] * (len(inner) + len(seam)) + [1] * len(stiff))
    part = np.concatenate([np.zeros(len(inner)), np.linspace(0.2, 0.8, len(seam)), np.ones(len(stiff))])
    levels = np.log(2.0) + part * (np.log(0.2) - np.log(2.0))
    near = (np.abs(pos[:, None, 0] - pos[None, :, 0]) <= 10.0) & (np.abs(pos[:, None, 1] - pos[None, :, 1]) <= 12.0)
    i, j = np.nonzero(np.triu(near, k=1))
    edges = np.stack([i, j], axis=1)
    crossing = labels[edges[:, 0]] != labels[edges[:, 1]]
    assert crossing.any() and np.all(pos[edges[crossing, 0], 0] == 30.0)
    where = _crossing_fraction(edges, labels, levels)
    assert np.all((where[crossing] >= 0.2) & (where[crossing] < 0.4))
    assert np.allclose(where[crossing & (part[edges[:, 0]] > 0.5)], 0.2)
    assert np.allclose(where[~crossing], 0.5)


def test_a_seam_that_runs_out_toward_the_rim_band_is_followed_into_it():
    """A stiff inclusion (x <= 10, y 30-50) on the 10 mm grid's left side, where the survey
    stopped 3 mm short of a 12 mm rim band (x -15 to -3) that densify may still probe. The
    seam's ends beside the band (x = 0, y 20-60) each get one point a spacing out (x = -10),
    scored as their crossing edges; the map would otherwise draw the inclusion out to the rim.
    (0, 40), whose neighbours are all the inclusion's, has no seam to follow; ends farther in,
    and a round with no band, get none; a point already probed there is not proposed again."""
    labels = ((POS[:, 0] <= 10.0) & (POS[:, 1] >= 30.0) & (POS[:, 1] <= 50.0)).astype(int)
    bx, by = np.meshgrid(np.arange(-15.0, -2.5, 1.0), np.arange(-5.0, 95.5, 1.0))
    band = np.column_stack([bx.ravel(), by.ravel(), np.zeros(bx.size)])
    models = {0: _Dent(2.0, 0.1), 1: _Dent(0.1, 0.1)}
    rnd = plan_round(1, POS, EDGES, labels, models, SURVEY_F, SURVEY_A, NOISE_MM, budget=20,
                     min_spacing_mm=3.0, resolution_mm=6.0, band_points_mm=band)
    ends = sorted(int(k) for k in rnd.extra["rim_from"])
    assert ends == [k for k in range(N * N) if POS[k, 0] == 0.0 and POS[k, 1] in (20.0, 30.0, 50.0, 60.0)]
    prop = np.asarray(rnd.proposed_mm)
    in_band = prop[prop[:, 0] < -2.5]
    assert sorted(in_band[:, 1].tolist()) == [20.0, 30.0, 50.0, 60.0]
    assert np.allclose(in_band[:, 0], -10.0)
    assert "rim band" in rnd.reason and not rnd.resolved
    plain = plan_round(1, POS, EDGES, labels, models, SURVEY_F, SURVEY_A, NOISE_MM, budget=20,
                       min_spacing_mm=3.0, resolution_mm=6.0)
    assert plain.extra["rim_from"] == [] and np.all(np.asarray(plain.proposed_mm)[:, 0] >= 0.0)
    probed = np.vstack([POS, in_band])
    grown = np.concatenate([labels, np.zeros(len(in_band), dtype=int)])
    extra_edges = np.array([[int(np.flatnonzero((POS[:, 0] == 0.0) & (POS[:, 1] == y))[0]), N * N + k]
                            for k, y in enumerate(in_band[:, 1])])
    again = plan_round(2, probed, np.vstack([EDGES, extra_edges]), grown, models, SURVEY_F, SURVEY_A, NOISE_MM,
                       budget=20, min_spacing_mm=3.0, resolution_mm=6.0, band_points_mm=band)
    assert not any(p[0] < -2.5 and abs(p[0] + 10.0) < 5.0 for p in again.proposed_mm)


def test_a_seam_end_standing_in_the_rim_band_steps_on_away_from_the_survey_area():
    """Last round's rim points stand in a deep band (x -30 to -3; the survey's area x >= 0):
    the inclusion's two (-6, 30) and (-6, 50), reading it, and the matrix's (-6, 20) and
    (-6, 60). The band beyond them (to x = -30) is filled from them unless a round probes
    it. Each of the four seam ends steps its spacing (the median length of its edges: 10 mm
    in the middle, 8 mm at the ends of the row) away from the survey area, to x = -16 or
    -14, not toward its own nearest band point (itself, or one beside it); without the
    survey area a point standing on a band point has no way out and gets none."""
    labels = ((POS[:, 0] <= 10.0) & (POS[:, 1] >= 30.0) & (POS[:, 1] <= 50.0)).astype(int)
    bx, by = np.meshgrid(np.arange(-30.0, -2.5, 1.0), np.arange(-5.0, 95.5, 1.0))
    band = np.column_stack([bx.ravel(), by.ravel(), np.zeros(bx.size)])
    ax, ay = np.meshgrid(np.arange(0.0, 90.5, 1.0), np.arange(-5.0, 95.5, 1.0))
    area = np.column_stack([ax.ravel(), ay.ravel(), np.zeros(ax.size)])
    rows = np.arange(20.0, 60.5, 10.0)
    rim = np.column_stack([np.full(rows.size, -6.0), rows, np.zeros(rows.size)])
    probed = np.vstack([POS, rim])
    grown = np.concatenate([labels, ((rows >= 30.0) & (rows <= 50.0)).astype(int)])
    first = N * N
    inward = [[int(np.flatnonzero((POS[:, 0] == 0.0) & (POS[:, 1] == y))[0]), first + k] for k, y in enumerate(rows)]
    along = [[first + k, first + k + 1] for k in range(rows.size - 1)]
    edges = np.vstack([EDGES, inward, along])
    models = {0: _Dent(2.0, 0.1), 1: _Dent(0.1, 0.1)}
    kw = dict(budget=20, min_spacing_mm=3.0, resolution_mm=6.0, band_points_mm=band)
    rnd = plan_round(2, probed, edges, grown, models, SURVEY_F, SURVEY_A, NOISE_MM, survey_area_mm=area, **kw)
    assert sorted(int(k) for k in rnd.extra["rim_from"]) == [first, first + 1, first + 3, first + 4]
    prop = np.asarray(rnd.proposed_mm)
    out = prop[prop[:, 0] < -8.0]
    by_row = {float(y): float(x) for x, y in out[:, :2]}
    assert by_row == {20.0: -14.0, 30.0: -16.0, 50.0: -16.0, 60.0: -14.0}
    blind = plan_round(2, probed, edges, grown, models, SURVEY_F, SURVEY_A, NOISE_MM, **kw)
    assert blind.extra["rim_from"] == [] and not np.any(np.asarray(blind.proposed_mm)[:, 0] < -8.0)
