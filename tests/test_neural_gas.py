"""Neural gas: the minibatch form against the plain online oracle, quality against k-means,
and geometry awareness on a box-on-pillow cloud judged against the box's true edges."""
import numpy as np
import pytest
from scipy.spatial import cKDTree
from sklearn.cluster import KMeans

from elastoprobe.controller.learning.cloud import box_on_pillow_mesh, local_geometry, sample_mesh
from elastoprobe.controller.learning.neural_gas import (
    Schedule, assign, geometry_aware_inputs, initial_units, neighbour_count, quantization_error,
    reference_online_ng, sample_indices, train_neural_gas,
)


def test_reference_online_ng_matches_the_formula_by_hand():
    """The oracle itself: one sample, two units, ranks 0 and 1."""
    units = np.array([[0.0, 0.0], [3.0, 0.0]])
    x = np.array([[1.0, 0.0]])
    sched = Schedule(2.0, 2.0, 0.5, 0.5)  # constant lam = 2, eps = 0.5
    got = reference_online_ng(x, units, np.array([0]), sched)
    want = units + 0.5 * np.exp(-np.array([0.0, 1.0]) / 2.0)[:, None] * (x[0] - units)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-15)


def test_batch_one_without_cutoff_is_exactly_online_ng():
    rng = np.random.default_rng(3)
    feats = np.vstack([rng.normal(0, 1, (150, 3)), rng.normal(4, 0.5, (150, 3))])  # float64
    n_units, n_steps, seed = 12, 600, 5
    import torch

    threads = torch.get_num_threads()
    ours = train_neural_gas(feats, n_units, n_steps, batch_size=1, seed=seed, cutoff=None, n_threads=1)
    assert torch.get_num_threads() == threads  # restored
    ref = reference_online_ng(feats, initial_units(feats, n_units, seed), sample_indices(len(feats), n_steps, seed))
    assert not np.allclose(ref, initial_units(feats, n_units, seed))  # it did train
    np.testing.assert_allclose(ours.units, ref, rtol=0, atol=1e-9)


def test_batch_one_with_cutoff_is_close_to_online_ng():
    """The top-K cut drops terms below 1e-4 of the winner's: close, not exact."""
    rng = np.random.default_rng(4)
    feats = rng.uniform(0, 10, (400, 2))
    n_units, n_steps, seed = 40, 800, 1
    ours = train_neural_gas(feats, n_units, n_steps, batch_size=1, seed=seed, n_threads=1)
    ref = reference_online_ng(feats, initial_units(feats, n_units, seed), sample_indices(len(feats), n_steps, seed))
    err = np.abs(ours.units - ref).max()
    assert 0 < err < 1e-2


def test_neighbour_count_follows_lambda():
    assert neighbour_count(10.0, 1000) == 93  # ceil(10 ln 1e4)
    assert neighbour_count(0.01, 1000) == 1
    assert neighbour_count(10.0, 50) == 50
    assert neighbour_count(0.5, 50, cutoff=None) == 50


def test_minibatch_ng_quality_on_uniform_square_near_kmeans():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 100, (40_000, 2)).astype(np.float32)  # mm
    n_units = 64
    ng = train_neural_gas(pts, n_units, n_steps=300, batch_size=1024, seed=0, n_threads=1)
    random_qe = quantization_error(pts, initial_units(pts, n_units, 0))
    km = KMeans(n_units, n_init=3, random_state=0).fit(pts)  # the better of three k-means++ runs
    km_qe = quantization_error(pts, km.cluster_centers_)
    assert ng.quantization_error < 0.7 * random_qe
    assert ng.quantization_error <= 1.03 * km_qe
    # Uniform square: every unit wins a similar share (NG does not leave dead units).
    counts = np.bincount(assign(pts, ng.units), minlength=n_units)
    assert counts.min() > 0.4 * len(pts) / n_units
    assert ng.history[-1]["qe"] < ng.history[0]["qe"]


PILLOW_A, PILLOW_B, PILLOW_H, BOX_X, BOX_Y, BOX_TOP = 200.0, 150.0, 80.0, 75.0, 50.0, 140.0


def pillow_z(x, y):
    return PILLOW_H * np.sqrt(np.clip(1 - (x / PILLOW_A) ** 4, 0, None)) * np.sqrt(np.clip(1 - (y / PILLOW_B) ** 4, 0, None))


def box_edge_tree(step_mm: float = 0.2) -> cKDTree:
    """Dense samples of the box's twelve sharp edges: top rim, vertical corners, seam with the pillow."""
    parts = []
    for sign in (-1, 1):
        s = np.arange(-BOX_X, BOX_X + 1e-9, step_mm)
        y = np.full_like(s, sign * BOX_Y)
        parts += [np.c_[s, y, np.full_like(s, BOX_TOP)], np.c_[s, y, pillow_z(s, y)]]
        s = np.arange(-BOX_Y, BOX_Y + 1e-9, step_mm)
        x = np.full_like(s, sign * BOX_X)
        parts += [np.c_[x, s, np.full_like(s, BOX_TOP)], np.c_[x, s, pillow_z(x, s)]]
    for cx in (-BOX_X, BOX_X):
        for cy in (-BOX_Y, BOX_Y):
            z = np.arange(pillow_z(cx, cy), BOX_TOP, step_mm)
            parts.append(np.c_[np.full_like(z, cx), np.full_like(z, cy), z])
    return cKDTree(np.vstack(parts))


@pytest.fixture(scope="module")
def box_cloud():
    mesh = box_on_pillow_mesh((2 * PILLOW_A, 2 * PILLOW_B, PILLOW_H), (2 * BOX_X, 2 * BOX_Y, BOX_TOP - PILLOW_H))
    pts, _ = sample_mesh(mesh, 60_000, seed=2)
    pts += np.random.default_rng(0).normal(0, 0.05, pts.shape)
    normals, curv = local_geometry(pts, k=16)
    return pts, normals, curv


def test_geometry_aware_units_gather_at_edges(box_cloud):
    pts, normals, curv = box_cloud
    edges = box_edge_tree()
    band_mm = 10.0
    area_share = float(np.mean(edges.query(pts)[0] < band_mm))  # the band's share of the surface

    def share_near_edges(units):
        return float(np.mean(edges.query(units[:, :3])[0] < band_mm))

    plain = train_neural_gas(pts.astype(np.float32), 150, n_steps=120, batch_size=1024, seed=0, n_threads=1)
    feats, weights = geometry_aware_inputs(pts, normals, curv)
    aware = train_neural_gas(feats, 150, n_steps=120, batch_size=1024, seed=0,
                             sample_weights=weights, n_threads=1)
    plain_share, aware_share = share_near_edges(plain.units), share_near_edges(aware.units)
    # Plain NG follows density: about the band's share of the area. Geometry-aware: clearly more.
    assert plain_share < 1.6 * area_share
    assert aware_share > 1.5 * plain_share
