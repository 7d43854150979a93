"""The region map over the cloud: distances along the surface, folds, cells (learning/surface_map.py)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller.learning import evaluate as ev
from elastoprobe.controller.learning import surface_map as sm

ROOT = Path(__file__).resolve().parent.parent


def plane(nx: int, ny: int, spacing_mm: float, z_mm: float = 0.0, seed: int = 0, noise_mm: float = 0.0):
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(nx) * spacing_mm, np.arange(ny) * spacing_mm, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, z_mm)])
    pts[:, 2] += rng.normal(0.0, noise_mm, len(pts)) if noise_mm else 0.0
    return pts, np.tile([0.0, 0.0, 1.0], (len(pts), 1))


def test_two_seeds_on_a_flat_face_split_it_midway():
    pts, nrm = plane(41, 11, 2.0, noise_mm=0.05)
    g = sm.build_graph(pts, nrm)
    assert not g.concave.any()
    lab = sm.labels_from_seeds(g, np.array([[10.0, 10.0, 0.0], [70.0, 10.0, 0.0]]), np.array([3, 7]))
    assert set(np.unique(lab)) == {3, 7}
    assert np.all(lab[pts[:, 0] < 38.0] == 3) and np.all(lab[pts[:, 0] > 42.0] == 7)


def test_scan_lines_and_an_unscanned_band_stay_one_face():
    """A sweep samples densely along lines 4 mm apart and leaves a 12 mm band unseen: still one face."""
    x = np.arange(0.0, 100.0, 0.5)
    lines = [np.column_stack([x, np.full_like(x, y), np.zeros_like(x)]) for y in np.arange(0.0, 60.0, 4.0)]
    pts = np.concatenate(lines)
    pts = pts[(pts[:, 0] < 40.0) | (pts[:, 0] > 52.0)]
    nrm = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    g = sm.build_graph(pts, nrm)
    c = sm.cells(g, np.array([[5.0, 30.0, 0.0]]))
    assert np.all(c.source == 0)                     # every point reached from one seed


@pytest.fixture(scope="module")
def composite_surface():
    from bench import strategies as st
    from elastoprobe.controller.learning.cloud import sample_mesh
    from elastoprobe.sim.objects import load_object

    obj = load_object(ROOT / "config" / "objects" / "composite.yaml")
    pts, nrm = sample_mesh(obj.mesh, 30_000, seed=5)
    seen = st.seen_from_above(pts, nrm)
    return obj, pts[seen], nrm[seen]


def test_box_on_pillow_map_follows_the_fold_not_the_nearest_probe(composite_surface):
    """Two probes per body, labelled with the truth: the box's walls go with the box, the
    pillow up to the wall's foot with the pillow (the fold), against the truth."""
    obj, pts, nrm = composite_surface
    seeds = np.array([[0.0, 0.0, 140.0], [-40.0, 30.0, 140.0], [150.0, 0.0, 80.0], [-150.0, 60.0, 80.0]])
    seed_labels = obj.region_of(seeds)
    assert seed_labels.tolist() == [0, 0, 1, 1]
    g = sm.build_graph(pts, nrm)
    lab = sm.labels_from_seeds(g, seeds, seed_labels)
    truth = obj.region_of(pts)
    reach = nrm[:, 2] >= np.cos(np.radians(50.0))
    scores = ev.region_map_scores(lab[reach], truth[reach], None, pts[reach])
    assert scores["mislabelled_fraction"] < 0.005
    assert scores["boundary_mm_p90"] is not None and scores["boundary_mm_p90"] < 5.0
    assert np.mean(lab == truth) > 0.995              # walls included
    # The nearest probe in space gets the pillow beside the box wrong.
    from elastoprobe.controller.learning.regions import propagate_labels

    near = propagate_labels(seeds, seed_labels, pts[reach])
    assert np.mean(near != truth[reach]) > 10 * scores["mislabelled_fraction"]


def test_cells_do_not_touch_across_the_fold(composite_surface):
    obj, pts, nrm = composite_surface
    seeds = np.array([[60.0, 0.0, 140.0], [100.0, 0.0, 80.0], [100.0, 60.0, 80.0], [0.0, 0.0, 140.0]])
    g = sm.build_graph(pts, nrm)
    pairs = sm.seed_neighbours(g, sm.cells(g, seeds))
    assert (1, 2) in pairs and (0, 3) in pairs
    assert (0, 1) not in pairs and (0, 2) not in pairs


def test_a_seed_whose_dent_lies_between_two_regions_draws_the_seam_through_itself():
    """A flat face, a stiff and a soft material meeting along x = 33 mm. Seeds 20 mm apart
    (x = 0, 20, 40, ...): the plain map cuts midway, at x = 30. A seed at x = 32, 1 mm off
    the seam, presses both materials: its dent lies between theirs (labelled stiff, its
    level 40 % of the way to the soft one). With the seeds' levels, the boundary passes
    next to it (within 1 mm of the seam: the line fitted through the levels of x = 20, 32
    and 40 crosses midway there) instead of midway to the next soft seed; with pure levels
    the map is the plain one."""
    pts, nrm = plane(101, 41, 1.0)
    g = sm.build_graph(pts, nrm)
    xs = np.array([0.0, 20.0, 32.0, 40.0, 60.0, 80.0, 100.0])
    seeds = np.array([[x, y, 0.0] for x in xs for y in (0.0, 20.0, 40.0)])
    labels = (seeds[:, 0] > 33.0).astype(int)
    rng = np.random.default_rng(1)
    pure = np.where(labels == 1, np.log(2.0), np.log(0.2)) + rng.normal(0, 0.05, len(seeds))
    levels = pure.copy()
    levels[seeds[:, 0] == 32.0] = np.log(0.2) + 0.4 * (np.log(2.0) - np.log(0.2))
    truth = (pts[:, 0] > 33.0).astype(int)
    plain = sm.labels_from_seeds(g, seeds, labels)
    assert np.array_equal(sm.labels_from_seeds(g, seeds, labels, seed_levels=pure), plain)
    refined = sm.labels_from_seeds(g, seeds, labels, seed_levels=levels)
    err_plain, err_refined = np.mean(plain != truth), np.mean(refined != truth)
    assert err_plain > 0.01 and err_refined <= 0.5 * err_plain
    # On every row of the cloud the boundary lies within 1 mm of the seam (the plain map: at 36).
    for y in np.unique(pts[:, 1]):
        first_soft_mm = pts[(pts[:, 1] == y) & (refined == 1), 0].min()
        assert 33.0 <= first_soft_mm <= 34.0
    # Nothing moves on the far side of the seam seed, nor between other seeds.
    assert np.all(refined[pts[:, 0] < 31.5] == 0) and np.all(refined[pts[:, 0] > 36.0] == 1)


def test_a_small_region_mostly_seam_seeds_is_read_on_its_interior():
    """A soft strip x < 31.5 mm (level log 2) beside a stiff material (log 0.2). The soft
    region has nine interior seeds (x = 0, 10, 20) and thirteen that densification put along
    the seam at x = 30, 1.5 mm inside it, each pressing some of the stiff material (their
    levels 20-80 % of the way to the stiff one); the stiff side's first column is at x = 36.
    Read on all 22 seeds, the soft region's median and MAD span the stiff level, no seed can
    be placed between the two, and the map cuts midway between the columns (x = 33). Read
    on its interior, the soft level is the strip's own, and the boundary passes next to the
    seam seeds, on their side toward the stiff material."""
    pts, nrm = plane(101, 25, 1.0)
    g = sm.build_graph(pts, nrm)
    inner = [[x, y, 0.0] for x in (0.0, 10.0, 20.0) for y in (0.0, 12.0, 24.0)]
    seam = [[30.0, y, 0.0] for y in np.linspace(0.0, 24.0, 13)]
    stiff = [[x, y, 0.0] for x in (36.0, 46.0, 56.0, 66.0, 76.0, 86.0, 96.0) for y in (0.0, 6.0, 12.0, 18.0, 24.0)]
    seeds = np.array(inner + seam + stiff)
    labels = np.array([0] * (len(inner) + len(seam)) + [1] * len(stiff))
    soft_level, stiff_level = np.log(2.0), np.log(0.2)
    part = np.concatenate([np.zeros(len(inner)), np.linspace(0.2, 0.8, len(seam)), np.ones(len(stiff))])
    levels = soft_level + part * (stiff_level - soft_level)
    truth = (pts[:, 0] > 31.5).astype(int)
    interior = sm.interior_seeds(labels, sm.seed_neighbours(g, sm.cells(g, seeds)))
    assert not interior[seeds[:, 0] == 30.0].any() and not interior[seeds[:, 0] == 36.0].any()
    assert interior[seeds[:, 0] == 10.0].all() and interior[seeds[:, 0] == 66.0].all()
    a, b = np.flatnonzero(seeds[:, 0] == 30.0)[6:7], np.flatnonzero(seeds[:, 0] == 36.0)[2:3]
    # Read on all seeds, the ranges (3 sigmas, densification's reading) overlap.
    assert not sm.seam_fractions(levels, labels, a, b, edge_sigmas=3.0)[2].any()
    s_a, s_b, usable = sm.seam_fractions(levels, labels, a, b, interior)
    assert usable.all() and s_a[0] == pytest.approx(0.45) and s_b[0] == 1.0
    plain = sm.labels_from_seeds(g, seeds, labels)
    refined = sm.labels_from_seeds(g, seeds, labels, seed_levels=levels)
    assert np.mean(refined != truth) < 0.5 * np.mean(plain != truth)
    assert np.all(refined[pts[:, 0] < 29.5] == 0) and np.all(refined[pts[:, 0] > 33.5] == 1)


def _strip_with_a_column_across(column_peaks_mm: list[float], soft_mm: tuple[float, float] = (1.0, 2.0),
                                stiff_mm: tuple[float, float] = (0.1, 0.2),
                                scatter_mm: tuple[float, float] = (0.0, 0.0)):
    """A soft strip x < 31.5 mm (peaks ``soft_mm``, 1.0 / 2.0 mm, at two survey forces) beside
    a stiff material (``stiff_mm``, 0.1 / 0.2 mm); seeds at x = 0, 10, 20 and 29 (soft; the
    last 2.5 mm inside the seam) and 38 ... 98 (stiff), and a column at x = 34, 2.5 mm on the
    stiff side, that the clustering put with the soft strip, reading ``column_peaks_mm`` at
    the two forces. Each region's peaks scatter by -1, 0, +1 times ``scatter_mm`` in turn
    (a robust spread of 1.4826 x it)."""
    pts, nrm = plane(101, 25, 1.0)
    soft = [[x, y, 0.0] for x in (0.0, 10.0, 20.0, 29.0) for y in (0.0, 12.0, 24.0)]
    column = [[34.0, y, 0.0] for y in np.linspace(0.0, 24.0, 9)]
    stiff = [[x, y, 0.0] for x in np.arange(38.0, 99.0, 10.0) for y in (0.0, 12.0, 24.0)]
    seeds = np.array(soft + column + stiff)
    labels = np.array([0] * (len(soft) + len(column)) + [1] * len(stiff))

    def scattered(level_mm: tuple[float, float], n: int) -> np.ndarray:
        return np.asarray(level_mm) + np.outer(np.arange(n) % 3 - 1.0, scatter_mm)

    peaks = np.vstack([scattered(soft_mm, len(soft)), np.tile(column_peaks_mm, (len(column), 1)),
                       scattered(stiff_mm, len(stiff))])
    return pts, sm.build_graph(pts, nrm), seeds, labels, peaks


def test_a_seed_whose_every_peak_reads_the_other_material_counts_on_its_side():
    """The column on the stiff side reads 0.118 / 0.236 mm, 2 % of the way to the soft
    material (what the contact model gives 2.5 mm past a seam, docs/design.md §8): past the
    halfway (0.55 / 1.1 mm) at both forces. Held on the soft side (its label), the seam runs
    beyond it, past x = 34; counted where its peaks put it, the seam falls halfway between
    the column and the soft seeds at x = 29, on the true one (31.5)."""
    pts, g, seeds, labels, peaks = _strip_with_a_column_across([0.118, 0.236])
    cols = np.arange(len(seeds))
    column = np.flatnonzero(seeds[:, 0] == 34.0)
    assert np.array_equal(sm.reads_other_side(peaks, labels, None, column, 1), np.ones(column.size, bool))
    soft_seeds = cols[(labels == 0) & (seeds[:, 0] < 30.0)]
    assert not sm.reads_other_side(peaks, labels, None, soft_seeds, 1).any()
    levels = peaks.mean(axis=1)
    held = sm.labels_from_seeds(g, seeds, labels, seed_levels=levels)
    crossed = sm.labels_from_seeds(g, seeds, labels, seed_levels=levels, seed_peaks_mm=peaks)
    truth = (pts[:, 0] > 31.5).astype(int)
    on_row = pts[:, 1] == 12.0
    first_stiff_held = pts[on_row & (held == 1), 0].min()
    first_stiff_crossed = pts[on_row & (crossed == 1), 0].min()
    assert first_stiff_held > 34.0
    assert 31.0 <= first_stiff_crossed <= 32.0
    assert np.mean(crossed != truth) < 0.5 * np.mean(held != truth)


def test_a_seed_whose_mean_crosses_by_one_force_stays_on_its_side():
    """The column reads 0.118 mm at the first force (past the halfway) but 1.3 mm at the
    second (not past 1.1 mm): its mean level (0.71 mm) lies past the mean halfway, but the
    measurement disagrees with itself (a noisy force), so its label stands and the map is
    the one drawn without peaks."""
    pts, g, seeds, labels, peaks = _strip_with_a_column_across([0.118, 1.3])
    column = np.flatnonzero(seeds[:, 0] == 34.0)
    assert not sm.reads_other_side(peaks, labels, None, column, 1).any()
    levels = peaks.mean(axis=1)
    assert np.array_equal(sm.labels_from_seeds(g, seeds, labels, seed_levels=levels, seed_peaks_mm=peaks),
                          sm.labels_from_seeds(g, seeds, labels, seed_levels=levels))


# Two forces that tell the materials apart unequally: at the first they differ by 2.5 mm
# and scatter by 1.5 mm, at the second by 1.8 mm with a scatter of 0.07 mm.
_UNEQUAL = dict(soft_mm=(3.0, 2.0), stiff_mm=(0.5, 0.2), scatter_mm=(1.0, 0.05))


def test_a_seed_whose_telling_force_reads_the_other_material_counts_on_its_side():
    """The column reads the soft level at the noisy first force (3.2 mm) and the stiff one at
    the second (0.3 mm, 6 % of the way to the soft 2.0). Not every force read past the
    halfway, and neither did the plain mean (1.75 mm against a halfway of 1.43); weighed by
    what each force tells apart, the second decides, and the seam falls between the column
    and the soft seeds at x = 29, not beyond the column (suite slab 1012 seed 2: targets
    1-2 mm inside a hard-rubber ellipse whose low force reads like the elastomer)."""
    pts, g, seeds, labels, peaks = _strip_with_a_column_across([3.2, 0.3], **_UNEQUAL)
    column = np.flatnonzero(seeds[:, 0] == 34.0)
    interior = sm.interior_seeds(labels, sm.seed_neighbours(g, sm.cells(g, seeds)))
    assert not np.all(sm._past_halfway(peaks, labels, interior, column, 1), axis=1).any()
    assert sm.reads_other_side(peaks, labels, interior, column, 1).all()
    levels = peaks.mean(axis=1)
    mapped = sm.labels_from_seeds(g, seeds, labels, seed_levels=levels, seed_peaks_mm=peaks)
    on_row = pts[:, 1] == 12.0
    assert 30.0 <= pts[on_row & (mapped == 1), 0].min() <= 33.0
    held = sm.labels_from_seeds(g, seeds, labels, seed_levels=levels)
    assert pts[on_row & (held == 1), 0].min() > 34.0


def test_a_seed_whose_plain_mean_crosses_by_a_noisy_force_stays_on_its_side():
    """The column reads past the halfway at the noisy first force (0.4 mm, below the stiff
    0.5) and the soft level at the telling second (1.9 mm). Its plain mean (1.15 mm) lies
    past the plain halfway (1.43), its weighted level does not: it stays a soft seed."""
    pts, g, seeds, labels, peaks = _strip_with_a_column_across([0.4, 1.9], **_UNEQUAL)
    column = np.flatnonzero(seeds[:, 0] == 34.0)
    interior = sm.interior_seeds(labels, sm.seed_neighbours(g, sm.cells(g, seeds)))
    assert peaks[column[0]].mean() < 0.5 * (np.mean([3.0, 2.0]) + np.mean([0.5, 0.2]))
    assert not sm.reads_other_side(peaks, labels, interior, column, 1).any()


def test_interior_seeds_reading_the_other_material_draw_no_island():
    """Three soft seeds 2 mm apart in the middle of the strip (around x = 10, all their
    surface neighbours soft) read the stiff material at both forces: a misfit for
    densification, not a seam, so the map with peaks keeps the strip whole there. Counted
    where their levels put them they drew a stiff patch of about 95 mm^2 (unseen sheet 1308:
    a crossing seed drew a patch 18 mm from the seam)."""
    pts, g, seeds, labels, peaks = _strip_with_a_column_across([0.118, 0.236])
    seeds = np.vstack([seeds, [[12.0, 12.0, 0.0], [10.0, 14.0, 0.0]]])
    labels = np.concatenate([labels, [0, 0]])
    peaks = np.vstack([peaks, [[0.1, 0.2], [0.1, 0.2]]])
    patch = np.flatnonzero((np.abs(seeds[:, 0] - 11.0) <= 1.0) & (np.abs(seeds[:, 1] - 13.0) <= 1.0))
    peaks[patch] = [0.1, 0.2]
    interior = sm.interior_seeds(labels, sm.seed_neighbours(g, sm.cells(g, seeds)))
    assert patch.size == 3 and interior[patch].all()
    assert sm.reads_other_side(peaks, labels, interior, patch, 1).all()
    mapped = sm.labels_from_seeds(g, seeds, labels, seed_levels=peaks.mean(axis=1), seed_peaks_mm=peaks)
    assert np.all(mapped[pts[:, 0] <= 25.0] == 0)


def _strip_with_a_stray_seed(stray_peaks_mm: list[float]):
    """The strip of :func:`_strip_with_a_column_across` (its column read soft, on the soft
    side) and one more seed at (41, 12), 9.5 mm into the stiff material, that the clustering
    put with the soft strip, reading ``stray_peaks_mm`` at the two forces. Of its eight
    surface neighbours six are stiff (the two soft ones are column seeds). Also: the cloud
    points within 3 mm of it."""
    pts, g, seeds, labels, peaks = _strip_with_a_column_across([1.0, 2.0])
    seeds = np.vstack([seeds, [[41.0, 12.0, 0.0]]])
    labels = np.concatenate([labels, [0]])
    peaks = np.vstack([peaks, [stray_peaks_mm]])
    near_stray = np.hypot(pts[:, 0] - 41.0, pts[:, 1] - 12.0) < 3.0
    return pts, g, seeds, labels, peaks, near_stray


def test_a_seed_whose_peaks_disagree_goes_with_its_neighbours():
    """The stray seed reads the stiff material at the first force (0.1 mm) and the soft one at
    the second (2.0 mm): one force says each. Most of its neighbours are stiff, so it is a
    stiff seed one force read wrong. Held on its label it draws soft most of the 3 mm around
    it (suite slab 1012 seed 2: a notch 4 mm deep into a hard-rubber ellipse); deferred, it
    counts at the stiff material's own level and none of them is soft."""
    pts, g, seeds, labels, peaks, near_stray = _strip_with_a_stray_seed([0.1, 2.0])
    pairs = sm.seed_neighbours(g, sm.cells(g, seeds))
    deferred = sm.defer_to_neighbours(peaks, labels, pairs)
    assert deferred[-1] == 1
    assert np.array_equal(deferred[:-1], labels[:-1])
    levels = peaks.mean(axis=1)
    held = sm.labels_from_seeds(g, seeds, labels, seed_levels=levels)
    mapped = sm.labels_from_seeds(g, seeds, labels, seed_levels=levels, seed_peaks_mm=peaks)
    assert np.mean(held[near_stray] == 0) > 0.5
    assert not np.any(mapped[near_stray] == 0)


def test_a_seed_whose_every_peak_reads_its_own_material_keeps_its_island():
    """The stray seed reads the soft material at both forces: a small inclusion one probe
    found, whatever its neighbours say. It keeps its label and its area."""
    pts, g, seeds, labels, peaks, near_stray = _strip_with_a_stray_seed([1.0, 2.0])
    pairs = sm.seed_neighbours(g, sm.cells(g, seeds))
    assert np.array_equal(sm.defer_to_neighbours(peaks, labels, pairs), labels)
    mapped = sm.labels_from_seeds(g, seeds, labels, seed_levels=peaks.mean(axis=1), seed_peaks_mm=peaks)
    assert np.mean(mapped[near_stray] == 0) > 0.5


def test_a_seam_seed_whose_peaks_disagree_keeps_its_label_among_split_neighbours():
    """Seeds straddling the seam with one force read each way keep their labels when their
    neighbours do not mostly hold the other region: the column of
    :func:`_strip_with_a_column_across` reading 0.118 / 1.3 mm has soft and stiff
    neighbours, and column neighbours of its own label."""
    pts, g, seeds, labels, peaks = _strip_with_a_column_across([0.118, 1.3])
    pairs = sm.seed_neighbours(g, sm.cells(g, seeds))
    assert np.array_equal(sm.defer_to_neighbours(peaks, labels, pairs), labels)


def test_shared_border_counts_the_edges_between_two_cells():
    """Three seeds in a row on a flat strip: neighbours share a border as wide as the strip,
    the outer two none."""
    pts, nrm = plane(41, 11, 2.0)
    g = sm.build_graph(pts, nrm)
    seeds = np.array([[10.0, 10.0, 0.0], [40.0, 10.0, 0.0], [70.0, 10.0, 0.0]])
    border = sm.shared_border(g, sm.cells(g, seeds), np.array([[0, 1], [2, 1], [0, 2]]))
    assert border[2] == 0.0
    assert border[0] >= 11 and border[1] >= 11               # at least one edge per row of the strip
    assert abs(border[0] - border[1]) <= 0.25 * border[0]    # the same width on both sides


def _disc_session(spacing_mm: float, radius_mm: float = 12.0, blend_mm: float = 3.0, seed: int = 3):
    """A stiff plane (level log 0.2) with a soft disc (log 2) at (40, 40), radius ``radius_mm``;
    seeds on a jittered grid of ``spacing_mm``, each labelled by the material under its
    centre, its level blended linearly across ``blend_mm`` either side of the rim (a tip
    pressing both materials)."""
    pts, nrm = plane(81, 81, 1.0)
    rng = np.random.default_rng(seed)
    g1 = np.arange(spacing_mm / 2, 80.0, spacing_mm)
    gx, gy = np.meshgrid(g1, g1, indexing="ij")
    xy = np.column_stack([gx.ravel(), gy.ravel()]) + rng.uniform(-0.25, 0.25, (gx.size, 2)) * spacing_mm
    seeds = np.column_stack([xy, np.zeros(len(xy))])
    inside_mm = radius_mm - np.linalg.norm(xy - 40.0, axis=1)
    labels = (inside_mm > 0).astype(int)
    part = np.clip(0.5 + inside_mm / (2 * blend_mm), 0.0, 1.0)
    levels = np.log(0.2) + part * (np.log(2.0) - np.log(0.2))
    truth = (np.linalg.norm(pts[:, :2] - 40.0, axis=1) < radius_mm).astype(int)
    return pts, nrm, seeds, labels, levels, truth


def test_a_disc_seam_is_drawn_round_through_the_probes_that_straddle_it():
    """A 24 mm soft disc probed on a 6 mm grid (four to five probes across it): the plain map
    is the polygon of the probes' cells; with the levels the seam is a smooth curve through
    the probes that press both materials, and the disc comes out nearly whole."""
    pts, nrm, seeds, labels, levels, truth = _disc_session(6.0)
    g = sm.build_graph(pts, nrm)
    plain = sm.labels_from_seeds(g, seeds, labels)
    refined = sm.labels_from_seeds(g, seeds, labels, seed_levels=levels)

    def disc_iou(lab: np.ndarray) -> float:
        return float(np.sum((lab == 1) & (truth == 1)) / np.sum((lab == 1) | (truth == 1)))

    assert disc_iou(plain) < 0.85
    assert disc_iou(refined) > 0.9


def test_a_stiff_disc_keeps_its_size_when_the_seam_is_read_in_mm():
    """A stiff disc (radius 10 mm, dent 0.1 mm) in a soft plane (1.0 mm), probed on a jittered
    6 mm grid; a probe within 3 mm of the rim dents as the smoothstep-weighted mean of the
    two materials in mm (the simulator's contact model, docs/design.md §8), with 5 % noise.
    Drawn through the probes' mm levels the seam keeps the disc near its size; through
    their logarithms it runs where the dent is the geometric mean (0.32 mm, most of the way
    to the soft level in mm), inside the disc, and the disc shrinks (stops 29 and 33)."""
    pts, nrm = plane(81, 81, 1.0)
    g = sm.build_graph(pts, nrm)
    truth = np.linalg.norm(pts[:, :2] - 40.0, axis=1) < 10.0
    ratio_mm, ratio_log, iou_mm = [], [], []
    for seed in range(4):
        rng = np.random.default_rng(seed)
        g1 = np.arange(3.0, 80.0, 6.0)
        gx, gy = np.meshgrid(g1, g1, indexing="ij")
        xy = np.column_stack([gx.ravel(), gy.ravel()]) + rng.uniform(-1.5, 1.5, (gx.size, 2))
        seeds = np.column_stack([xy, np.zeros(len(xy))])
        inside_mm = 10.0 - np.linalg.norm(xy - 40.0, axis=1)
        labels = (inside_mm > 0).astype(int)
        u = np.clip(0.5 - np.abs(inside_mm) / 6.0, 0.0, 1.0)
        w_other = u * u * (3.0 - 2.0 * u)
        w_disc = np.where(inside_mm > 0, 1.0 - w_other, w_other)
        dent_mm = (0.1 * w_disc + 1.0 * (1.0 - w_disc)) * np.exp(rng.normal(0.0, 0.05, len(xy)))
        disc_mm = sm.labels_from_seeds(g, seeds, labels, seed_levels=dent_mm) == 1
        disc_log = sm.labels_from_seeds(g, seeds, labels, seed_levels=np.log(dent_mm)) == 1
        assert disc_mm.sum() > disc_log.sum()
        ratio_mm.append(disc_mm.sum() / truth.sum())
        ratio_log.append(disc_log.sum() / truth.sum())
        iou_mm.append(np.sum(disc_mm & truth) / np.sum(disc_mm | truth))
    assert 0.85 <= np.mean(ratio_mm) <= 1.1 and np.mean(ratio_log) < 0.85
    assert np.mean(iou_mm) >= 0.85


def test_a_lone_seed_whose_dent_was_not_read_labels_no_area():
    """A soft plane (region 0) on a 10 mm grid with a stiff inclusion of three neighbouring
    seeds (region 1) and, 40 mm away, one more seed labelled stiff whose dent fell as the
    force rose (a reading of the dent's tail, regions.dent_falls_with_force). The plain map
    (no levels) gives the lone seed its cell; flagged, it draws no island, and one flagged
    seed of the inclusion, beside its own region, keeps the inclusion as it was."""
    pts, nrm = plane(101, 61, 1.0)
    g = sm.build_graph(pts, nrm)
    seeds = np.array([[x, y, 0.0] for x in np.arange(0.0, 101.0, 10.0) for y in np.arange(0.0, 61.0, 10.0)])
    labels = np.zeros(len(seeds), dtype=int)
    inclusion = [int(np.flatnonzero((seeds[:, 0] == x) & (seeds[:, 1] == 30.0))[0]) for x in (20.0, 30.0)]
    inclusion.append(int(np.flatnonzero((seeds[:, 0] == 20.0) & (seeds[:, 1] == 40.0))[0]))
    lone = int(np.flatnonzero((seeds[:, 0] == 70.0) & (seeds[:, 1] == 30.0))[0])
    labels[inclusion + [lone]] = 1
    as_run = sm.labels_from_seeds(g, seeds, labels)
    not_read = np.zeros(len(seeds), dtype=bool)
    not_read[[lone, inclusion[0]]] = True
    flagged = sm.labels_from_seeds(g, seeds, labels, dent_not_read=not_read)
    near_lone = np.linalg.norm(pts[:, :2] - [70.0, 30.0], axis=1) < 4.5
    assert np.all(as_run[near_lone] == 1) and np.all(flagged[near_lone] == 0)
    away = np.linalg.norm(pts[:, :2] - [70.0, 30.0], axis=1) > 15.0
    assert np.array_equal(flagged[away], as_run[away]) and np.any(flagged[away] == 1)


def _hard_gel_foam(gel_columns_mm: tuple[float, ...]):
    """A hard plane (region 0, 0.016 mm) with a foam strip from x = 84 mm (region 2, 1.6 mm)
    and a gel disc of radius 12 mm at (30, 40) (region 1, 0.4 mm), seeds on a 6 mm grid;
    the seed columns at ``gel_columns_mm`` are labelled gel and read 0.3 mm."""
    pts, nrm = plane(121, 81, 1.0)
    seeds = np.array([[x, y, 0.0] for x in np.arange(0.0, 121.0, 6.0) for y in np.arange(4.0, 77.0, 6.0)])
    labels = np.where(seeds[:, 0] >= 84.0, 2, 0)
    levels = np.where(labels == 2, 1.6, 0.016)
    disc = np.linalg.norm(seeds[:, :2] - [30.0, 40.0], axis=1) <= 12.0
    labels[disc], levels[disc] = 1, 0.4
    column = np.isin(seeds[:, 0], gel_columns_mm)
    labels[column], levels[column] = 1, 0.3
    return pts, sm.build_graph(pts, nrm), seeds, labels, levels


def test_a_band_beside_a_seam_that_reads_a_third_material_goes_to_the_seams_two_sides():
    """Beside a seam between hard rubber and foam the dent passes through the gel's level: a
    line of probes 6 mm from the foam strip (x = 78 mm) reading 0.3 mm, labelled gel, drew a
    gel band along the strip (unseen slab 1102). With levels it is hard rubber (0.3 mm lies
    below the hard-foam midway), and the gel disc, which has interior seeds, stays."""
    pts, g, seeds, labels, levels = _hard_gel_foam((78.0,))
    plain = sm.labels_from_seeds(g, seeds, labels)
    mapped = sm.labels_from_seeds(g, seeds, labels, seed_levels=levels)
    band = (np.abs(pts[:, 0] - 78.0) <= 2.0) & (pts[:, 1] > 10.0) & (pts[:, 1] < 70.0)
    assert np.all(plain[band] == 1)
    assert not np.any(mapped[band] == 1) and np.all(mapped[band] == 0)
    in_disc = np.linalg.norm(pts[:, :2] - [30.0, 40.0], axis=1) < 8.0
    assert np.all(mapped[in_disc] == 1)
    assert np.all(mapped[pts[:, 0] > 90.0] == 2)


def test_a_strip_of_the_third_material_wide_enough_for_an_interior_seed_stays():
    """The same cell with three seed columns of gel (x = 66, 72, 78 mm) between the hard
    rubber and the foam: the middle column's seeds neighbour only gel, so the strip is a
    material of its own, and it stays gel."""
    pts, g, seeds, labels, levels = _hard_gel_foam((66.0, 72.0, 78.0))
    mapped = sm.labels_from_seeds(g, seeds, labels, seed_levels=levels)
    strip = (np.abs(pts[:, 0] - 72.0) <= 2.0) & (pts[:, 1] > 10.0) & (pts[:, 1] < 70.0)
    assert np.all(mapped[strip] == 1)
    pairs = sm.seed_neighbours(g, sm.cells(g, seeds))
    assert np.array_equal(sm.transition_bands(levels, labels, pairs, sm.interior_seeds(labels, pairs)), labels)


def test_the_seam_fit_interpolates_and_never_extrapolates():
    """Seeds in two rows (x = 0, 4, 8 mm) whose fractions rise to 0.45 at x = 8 (a probe by the
    rim of an object reading part way to another material): inside the rows the local fit
    follows the rise, beyond the last seeds it stays within the seeds' values (a line
    through them would pass 1/2 there and draw an island of the other region)."""
    seeds = np.array([[x, y, 0.0] for y in (0.0, 4.0) for x in (0.0, 4.0, 8.0)])
    values = np.array([0.0, 0.0, 0.45, 0.0, 0.0, 0.45])
    points = np.array([[4.0, 2.0, 0.0], [6.0, 2.0, 0.0], [12.0, 2.0, 0.0], [14.0, 2.0, 0.0]])
    value, decided = sm._local_linear_at(points, np.full(4, 3.0), seeds, values)
    assert decided.all()
    assert 0.0 < value[0] < value[1] < 0.45
    assert np.all(value[2:] <= 0.45 + 1e-12)


def test_a_seam_level_weighs_each_force_by_what_it_tells_apart():
    """Two regions 1.0 mm apart at both forces; the first force's peaks scatter ten times as
    much (0.2 against 0.02 mm robust spread). A seed reading A's level at the first force and
    B's at the second lies, by the inverse-variance weights, almost at B (the plain mean puts
    it halfway); with equal scatter at both forces, halfway again."""
    rng = np.random.default_rng(5)
    n = 41
    a = np.column_stack([rng.normal(0.0, 0.2, n), rng.normal(0.0, 0.02, n)]) + [1.0, 1.0]
    b = np.column_stack([rng.normal(0.0, 0.2, n), rng.normal(0.0, 0.02, n)]) + [2.0, 2.0]
    peaks = np.vstack([a, b, [[1.0, 2.0]]])
    labels = np.array([0] * n + [1] * n + [0])
    inner = np.ones(labels.size, dtype=bool)
    inner[-1] = False
    level = sm._pair_levels(peaks, labels, inner, 0, 1)[-1]
    assert peaks[-1].mean() == 1.5
    assert 1.95 < level <= 2.0
    even = peaks.copy()
    even[:2 * n, 1] = even[:2 * n, 0]          # the same scatter at both forces
    assert abs(sm._pair_levels(even, labels, inner, 0, 1)[-1] - 1.5) < 0.05


def _ring(radius_mm: float, n: int, phase: float = 0.0) -> list[list[float]]:
    t = phase + np.arange(n) * 2.0 * np.pi / n
    return [[40.0 + radius_mm * np.cos(a), 40.0 + radius_mm * np.sin(a), 0.0] for a in t]


def test_a_small_inclusion_mostly_seam_seeds_is_read_on_its_deepest_seeds():
    """A soft disc (radius 10 mm, dent 1.0 mm) in a stiff plane (0.1 mm); a probe within 3 mm of
    the rim dents as the smoothstep-weighted mean of the two (the simulator's contact model).
    The disc holds one probe at its centre, four 2 mm inside the rim and eight that
    densification put 0.8 mm outside it, which read a third of the way to the disc and were
    clustered with it: thirteen seeds, only the centre without a stiff neighbour. Read on all
    thirteen, the disc's level is about the outer ring's, every seed there reads as pure disc,
    and the disc grows past them (suite slab 1012 seed 2's sponge disc). Read on its deeper
    half (the seven seeds farthest from the stiff ones: the centre, the inner ring and two
    of the outer), it is the inner ring's, and the seam passes within the outer ring."""
    pts, nrm = plane(81, 81, 1.0)
    g = sm.build_graph(pts, nrm)
    disc = [[40.0, 40.0, 0.0]] + _ring(8.0, 4) + _ring(10.8, 8, np.pi / 8)
    matrix = _ring(14.0, 12) + [[x, y, 0.0] for x in np.arange(4.0, 80.0, 8.0) for y in np.arange(4.0, 80.0, 8.0)
                               if np.hypot(x - 40.0, y - 40.0) > 19.0]
    seeds = np.array(disc + matrix)
    labels = np.array([1] * len(disc) + [0] * len(matrix))
    inside_mm = 10.0 - np.linalg.norm(seeds[:, :2] - 40.0, axis=1)
    u = np.clip(0.5 - np.abs(inside_mm) / 6.0, 0.0, 1.0)
    w_other = u * u * (3.0 - 2.0 * u)
    w_disc = np.where(inside_mm > 0, 1.0 - w_other, w_other)
    dent_mm = (1.0 * w_disc + 0.1 * (1.0 - w_disc)) * np.exp(np.random.default_rng(4).normal(0.0, 0.03, len(seeds)))
    interior = sm.interior_seeds(labels, sm.seed_neighbours(g, sm.cells(g, seeds)))
    assert interior[: len(disc)].sum() < sm.MIN_INTERIOR_SEEDS
    deepest = sm.level_seeds(seeds, labels, interior)
    assert deepest[:5].all() and deepest[: len(disc)].sum() == (len(disc) + 1) // 2
    assert np.array_equal(deepest[len(disc):], interior[len(disc):])
    truth = np.linalg.norm(pts[:, :2] - 40.0, axis=1) < 10.0
    mapped = sm.labels_from_seeds(g, seeds, labels, seed_levels=dent_mm) == 1
    # The outer ring's seeds, 0.8 mm outside, stay on the plane's side of the seam.
    assert np.all(~mapped[np.linalg.norm(pts[:, :2] - 40.0, axis=1) > 11.0])
    assert np.sum(mapped & truth) / np.sum(mapped | truth) >= 0.8      # 0.85; read on all thirteen: 0.69
