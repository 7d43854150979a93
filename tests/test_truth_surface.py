"""Scoring region maps on the object's true surface: the sampler (sim/truth_surface.py) and the
scorer (controller/learning/evaluate.py: carry_labels, truth_surface_scores) on synthetic maps."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from elastoprobe.controller.learning.evaluate import carry_labels, truth_surface_scores
from elastoprobe.sim.materials import Material
from elastoprobe.sim.objects import MeshObject, load_object
from elastoprobe.sim.truth_surface import top_surface

ROOT = Path(__file__).resolve().parent.parent
FOAM = Material(name="foam", kind="foam", E_mpa=0.1, nu=0.25, friction_mu=0.7, thickness_mm=30.0,
                decay_length_mm=6.0, densification_strain=0.7, densification_exponent=1.5)
RUBBER = Material(name="rubber", kind="elastic", E_mpa=10.0, nu=0.49, friction_mu=0.8)
SIDE_MM = 100.0


def two_halves_block() -> MeshObject:
    """A 100 x 100 x 30 mm block (no bottom), painted in two halves at x = 0 on the top."""
    box = trimesh.creation.box(extents=[SIDE_MM, SIDE_MM, 30.0])
    box.apply_translation([0.0, 0.0, 15.0])
    mesh = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=5.0), process=False)
    mesh.update_faces(mesh.face_normals[:, 2] > -0.99)
    mesh.remove_unreferenced_vertices()
    labels = (mesh.triangles_center[:, 0] >= 0.0).astype(int)
    return MeshObject("halves", mesh, labels, ["rubber", "foam"], [RUBBER, FOAM])


def flat_cloud(spacing_mm: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A dense scan of the block's top (points on a grid offset from the samples', normals up)."""
    g = np.arange(-SIDE_MM / 2 + 0.25, SIDE_MM / 2, spacing_mm)
    x, y = np.meshgrid(g, g, indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 30.0)])
    return pts, np.tile([0.0, 0.0, 1.0], (len(pts), 1))


def score(top, cloud_pts, cloud_nrm, cloud_labels):  # noqa: ANN001, ANN201
    return truth_surface_scores(top.points_mm, top.normals, top.labels, top.area_mm2, cloud_pts, cloud_nrm,
                                cloud_labels, top.spacing_mm)


def test_the_sampler_takes_the_top_seen_from_above_with_its_area_and_paint() -> None:
    obj = two_halves_block()
    top = top_surface(obj, max_tilt_deg=30.0)
    assert len(top) == 100 * 100 and top.total_area_mm2 == pytest.approx(SIDE_MM ** 2)
    assert np.all(top.points_mm[:, 2] == pytest.approx(30.0)) and np.all(top.normals[:, 2] == pytest.approx(1.0))
    # Samples at cell centres (whole mm + 0.5): never on the seam, half on each side.
    assert np.array_equal(top.labels, (top.points_mm[:, 0] > 0).astype(int))
    assert np.count_nonzero(top.labels) == 5000
    # Coarser grids: the same surface, the same area.
    assert top_surface(obj, 30.0, spacing_mm=2.0).total_area_mm2 == pytest.approx(SIDE_MM ** 2)


def test_the_sampler_weighs_slopes_by_their_area_and_drops_what_is_steeper_or_hidden() -> None:
    ball = load_object(ROOT / "config" / "objects" / "rubber_ball.yaml")
    for tilt in (30.0, 60.0):
        cap = top_surface(ball, tilt)
        # A spherical cap within the tilt: 2 pi R^2 (1 - cos tilt), the normals analytic.
        assert cap.total_area_mm2 == pytest.approx(2 * np.pi * 65.0 ** 2 * (1 - np.cos(np.radians(tilt))), rel=0.01)
        assert np.degrees(np.arccos(cap.normals[:, 2].min())) <= tilt
    composite = load_object(ROOT / "config" / "objects" / "composite.yaml")
    top = top_surface(composite, 50.0)
    # The box's top (160 x 160 mm) and the pillow around it; the pillow under the box is hidden.
    assert np.sum(top.area_mm2[top.labels == 0]) == pytest.approx(160.0 * 160.0, rel=1e-3)
    under_box = (np.abs(top.points_mm[:, 0]) < 79) & (np.abs(top.points_mm[:, 1]) < 79)
    assert np.all(top.labels[under_box] == 0) and np.all(top.points_mm[under_box, 2] == pytest.approx(140.0))


def test_a_perfect_map_scores_no_error_full_iou_and_full_coverage() -> None:
    top = top_surface(two_halves_block(), 30.0)
    pts, nrm = flat_cloud()
    s = score(top, pts, nrm, np.where(pts[:, 0] >= 0.0, 7, 3))
    assert s["mislabelled_fraction"] == 0.0 and s["worst_region_iou"] == 1.0
    assert s["boundary_mm_mean"] == 0.0 and s["boundary_mm_p90"] == 0.0
    assert s["coverage"] == 1.0 and s["uncovered_area_mm2"] == 0.0
    assert s["matching"] == {3: 0, 7: 1}


@pytest.mark.parametrize("shift_mm", [3.0, 8.0])
def test_a_map_shifted_by_d_scores_a_boundary_d_away_and_the_strip_between_as_error(shift_mm: float) -> None:
    top = top_surface(two_halves_block(), 30.0)
    pts, nrm = flat_cloud()
    s = score(top, pts, nrm, (pts[:, 0] >= shift_mm).astype(int))
    assert s["boundary_mm_mean"] == pytest.approx(shift_mm, abs=0.6)
    assert s["mislabelled_fraction"] == pytest.approx(shift_mm / SIDE_MM, abs=0.011)
    # The shrunk half: its true area minus the strip, over its true area.
    assert s["worst_region_iou"] == pytest.approx((50 - shift_mm) / 50, abs=0.011)
    assert s["coverage"] == 1.0


def test_coverage_of_a_cloud_missing_a_band_is_that_bands_area_fraction() -> None:
    top = top_surface(two_halves_block(), 30.0)
    pts, nrm = flat_cloud()
    band_mm = 20.0
    # Cloud points are removed 2 mm further on each side: the surface farther than 2 mm
    # from the cloud is the band itself.
    gone = (pts[:, 1] > 10.0 - 2.0) & (pts[:, 1] < 10.0 + band_mm + 2.0)
    s = score(top, pts[~gone], nrm[~gone], (pts[~gone, 0] >= 0.0).astype(int))
    assert 1.0 - s["coverage"] == pytest.approx(band_mm / SIDE_MM, abs=0.011)
    # The band still gets a map (labels carried from the nearest scanned point) and is scored.
    assert s["mislabelled_fraction"] == 0.0 and s["error_uncovered"] == 0.0


def test_labels_come_from_the_same_face_not_from_a_wall_beside_it() -> None:
    top_pts = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    up = np.tile([0.0, 0.0, 1.0], (2, 1))
    # A wall's foot 0.5 mm away (label 1, facing sideways) and the top's own scan 4 mm away (label 0).
    cloud = np.array([[0.5, 0.0, 0.2], [0.0, 4.0, 0.0], [10.0, 3.0, 0.0]])
    cloud_n = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    labels, dist = carry_labels(top_pts, up, cloud, cloud_n, np.array([1, 0, 0]))
    assert labels.tolist() == [0, 0] and dist == pytest.approx([4.0, 3.0])
    # Nothing facing that way at all: the nearest point, whatever it faces.
    labels, dist = carry_labels(top_pts[:1], up[:1], cloud[:1], cloud_n[:1], np.array([1]))
    assert labels.tolist() == [1] and dist[0] == pytest.approx(np.hypot(0.5, 0.2))


def test_a_missed_region_scores_its_area_as_error_and_iou_zero() -> None:
    top = top_surface(two_halves_block(), 30.0)
    pts, nrm = flat_cloud()
    s = score(top, pts, nrm, np.zeros(len(pts), int))
    assert s["mislabelled_fraction"] == pytest.approx(0.5) and s["worst_region_iou"] == 0.0
    assert s["boundary_mm_mean"] is None


def test_a_boundary_drawn_where_the_materials_meet_off_the_top_is_measured_from_the_seam() -> None:
    composite = load_object(ROOT / "config" / "objects" / "composite.yaml")
    top = top_surface(composite, 50.0)
    pillow = top.labels == 1
    # A scan of the true top, labelled right except for a 3 mm band of pillow along the box's
    # foot on one side (x just above 80 mm), labelled as the box.
    cloud_labels = top.labels.copy()
    band = pillow & (top.points_mm[:, 0] > 80.0) & (top.points_mm[:, 0] < 83.0) & (np.abs(top.points_mm[:, 1]) < 80)
    cloud_labels[band] = 0
    s = truth_surface_scores(top.points_mm, top.normals, top.labels, top.area_mm2, top.points_mm, top.normals,
                             cloud_labels, top.spacing_mm,
                             seam_distance_mm=lambda p: composite.boundary_distance_mm(p)[0])
    # The drawn boundary runs 3 mm out from the foot (and along the band's ends): about 3 mm away.
    assert 2.0 <= s["boundary_mm_mean"] <= 4.0 and s["boundary_mm_p90"] <= 4.5
    assert s["mislabelled_fraction"] == pytest.approx(float(top.area_mm2[band].sum() / top.total_area_mm2))
    perfect = truth_surface_scores(top.points_mm, top.normals, top.labels, top.area_mm2, top.points_mm, top.normals,
                                   top.labels, top.spacing_mm,
                                   seam_distance_mm=lambda p: composite.boundary_distance_mm(p)[0])
    assert perfect["boundary_mm_mean"] == 0.0 and perfect["mislabelled_fraction"] == 0.0


def test_an_unscanned_band_beside_a_step_takes_its_labels_along_its_own_face() -> None:
    composite = load_object(ROOT / "config" / "objects" / "composite.yaml")
    top = top_surface(composite, 50.0)
    # The scanner's shadow: no cloud on the pillow within 85 mm of the box's wall at x = -80,
    # where the box's top edge (60 mm up) is nearer in space than the pillow beyond the band.
    shadow = (top.labels == 1) & (top.points_mm[:, 0] > -165.0) & (top.points_mm[:, 0] < -80.0) \
        & (np.abs(top.points_mm[:, 1]) < 100.0)
    seen = ~shadow
    s = truth_surface_scores(top.points_mm, top.normals, top.labels, top.area_mm2, top.points_mm[seen],
                             top.normals[seen], top.labels[seen], top.spacing_mm)
    assert s["mislabelled_fraction"] == 0.0
    assert 1.0 - s["coverage"] == pytest.approx(float(top.area_mm2[shadow].sum() - 2 * 2 * 150) / top.total_area_mm2,
                                                abs=0.003)
    # Nearest in space alone would have given the band's side by the wall to the box.
    nearest, _ = carry_labels(top.points_mm[shadow], top.normals[shadow], top.points_mm[seen], top.normals[seen],
                              top.labels[seen])
    assert np.any(nearest == 0)
