"""Probe targets from units, judged against the true box-on-pillow surface and its edges."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from elastoprobe.controller.learning.cloud import box_on_pillow_mesh, local_geometry, sample_mesh
from elastoprobe.controller.learning.profiles import MAX_FACE_SLOPE
from elastoprobe.controller.learning.targets import (TargetRules, _Surface, border_scan_frames, face_runs_mm,
                                                     make_targets, probeable, probeable_and_rim_band, scan_frames,
                                                     surface_graph)

from test_neural_gas import BOX_TOP, BOX_X, BOX_Y, PILLOW_A, PILLOW_B, PILLOW_H, box_edge_tree

RULES = TargetRules(tip_radius_mm=2.5, edge_clearance_radii=3.0, max_tilt_deg=60.0)


@pytest.fixture(scope="module")
def scene():
    mesh = box_on_pillow_mesh((2 * PILLOW_A, 2 * PILLOW_B, PILLOW_H), (2 * BOX_X, 2 * BOX_Y, BOX_TOP - PILLOW_H))
    truth_pts, truth_nrm = sample_mesh(mesh, 1_000_000, seed=9)  # dense ground truth
    pts, _ = sample_mesh(mesh, 80_000, seed=1)
    rng = np.random.default_rng(0)
    pts += rng.normal(0, 0.05, pts.shape)
    normals, curv = local_geometry(pts, k=16)
    edges = box_edge_tree()
    # Units: some anywhere just off the surface, some right on the box's sharp edges.
    anywhere = pts[rng.choice(len(pts), 250, replace=False)] + rng.normal(0, 1.0, (250, 3))
    edge_pts = edges.data[rng.choice(len(edges.data), 40, replace=False)]
    units = np.vstack([anywhere, edge_pts])
    targets = make_targets(units, pts, normals, curv, RULES, reference_dir=np.array([1.0, 0.0, 0.0]))
    return dict(truth=cKDTree(truth_pts), truth_nrm=truth_nrm, pts=pts, normals=normals, curv=curv,
                edges=edges, units=units, n_edge_units=len(edge_pts), targets=targets)


def test_targets_lie_on_the_surface_with_outward_unit_normals(scene):
    tg = scene["targets"]
    assert len(tg) > 100
    dist, idx = scene["truth"].query(tg.points_mm)
    true_n = scene["truth_nrm"][idx]
    off_plane_mm = np.abs(np.einsum("ij,ij->i", tg.points_mm - scene["truth"].data[idx], true_n))
    # The rim of the faceted pillow (5 mm facets, steep) is the worst place for a local plane.
    assert dist.max() < 2.0 and np.median(off_plane_mm) < 0.05 and off_plane_mm.max() < 0.5
    np.testing.assert_allclose(np.linalg.norm(tg.normals, axis=1), 1.0, atol=1e-9)
    assert np.einsum("ij,ij->i", tg.normals, true_n).min() > 0.97


def test_no_target_within_the_edge_clearance_and_none_too_steep(scene):
    tg = scene["targets"]
    edge_dist_mm, _ = scene["edges"].query(tg.points_mm)
    assert edge_dist_mm.min() >= RULES.clearance_mm
    assert np.all(tg.normals[:, 2] >= np.cos(np.radians(RULES.max_tilt_deg)) - 1e-9)
    spacing, _ = cKDTree(tg.points_mm).query(tg.points_mm, k=2)
    assert spacing[:, 1].min() >= RULES.spacing_mm


def test_edge_units_move_beside_the_edge(scene):
    tg = scene["targets"]
    first_edge_unit = len(scene["units"]) - scene["n_edge_units"]
    from_edge = tg.source_unit >= first_edge_unit
    assert np.all(tg.edge_flag[from_edge])
    assert from_edge.sum() >= 0.4 * scene["n_edge_units"]  # the rest merged or too steep (vertical corners)
    moved_mm = np.linalg.norm(tg.points_mm[from_edge] - scene["units"][tg.source_unit[from_edge]], axis=1)
    assert np.all(moved_mm >= RULES.clearance_mm - 0.5) and np.all(moved_mm <= RULES.shift_mm + 0.5)
    # Units far from the box edges on the gentle part of the pillow (its steep, faceted rim
    # has creases of its own) are not flagged.
    src = scene["units"][tg.source_unit]
    gentle = (np.abs(src[:, 0]) < 0.8 * PILLOW_A) & (np.abs(src[:, 1]) < 0.8 * PILLOW_B)
    far = gentle & (scene["edges"].query(src)[0] > 2 * RULES.shift_mm)
    assert far.sum() > 50
    assert not tg.edge_flag[far].any()


def test_scan_frames_lie_in_the_tangent_plane(scene):
    tg = scene["targets"]
    np.testing.assert_allclose(np.linalg.norm(tg.t, axis=1), 1.0, atol=1e-9)
    assert np.abs(np.einsum("ij,ij->i", tg.t, tg.normals)).max() < 1e-9
    assert np.all(tg.t[:, 0] > 0)  # the +x reference projected, never flipped
    per_target = scan_frames(tg.normals, np.tile([0.0, 1.0, 0.0], (len(tg), 1)))
    assert np.all(per_target[:, 1] > 0)


def test_surface_graph_does_not_step_off_the_box(scene):
    tg = scene["targets"]
    pairs = surface_graph(tg.points_mm, tg.normals, k=20, cloud_mm=scene["pts"])
    assert len(pairs) > len(tg)
    on_top = tg.points_mm[:, 2] > BOX_TOP - 1.0
    assert on_top.sum() >= 3
    assert not any(on_top[i] != on_top[j] for i, j in pairs)
    assert sum(on_top[i] and on_top[j] for i, j in pairs) >= on_top.sum() - 1
    # Without the tangency and gap tests a plain k-NN graph would cross (the check can fail).
    plain = surface_graph(tg.points_mm, tg.normals, k=20, max_angle_deg=90.0)
    assert any(on_top[i] != on_top[j] for i, j in plain)


def test_sparse_and_border_units_are_dropped():
    rng = np.random.default_rng(2)
    dense = np.c_[rng.uniform(0, 100, (20_000, 2)), rng.normal(0, 0.02, 20_000)]
    sparse = np.c_[rng.uniform(150, 250, (40, 2)), np.zeros(40)]
    cloud = np.vstack([dense, sparse])
    normals, curv = local_geometry(cloud, k=16, viewpoint_mm=np.array([0.0, 0.0, 1000.0]))
    units = np.array([[50.0, 50.0, 1.0], [0.5, 50.0, 0.0], [200.0, 200.0, 0.0]])
    tg = make_targets(units, cloud, normals, curv, RULES)
    assert tg.source_unit.tolist() == [0]
    np.testing.assert_allclose(tg.points_mm[0, :2], [50.0, 50.0], atol=0.5)
    assert abs(tg.points_mm[0, 2]) < 0.1  # projected onto the surface, not left 1 mm above


@pytest.mark.parametrize("noise_mm", [0.015, 0.03])
def test_a_target_on_a_line_raster_gets_the_surface_normal_not_one_across_the_line(noise_mm):
    """A laser-line raster of a tilted plane: profiles densely sampled (0.3 mm) 4 mm apart,
    every line scanned in both headings (at the same place). The ``plane_k`` nearest neighbours of any point lie on
    its own profile: a plane fit to them alone gave a normal across the line (the loopback
    plan's ball target got (0, -1, 0), a horizontal 90 deg probe, refused)."""
    from elastoprobe.controller.core.geometry import rotvec_to_matrix
    from elastoprobe.controller.learning.cloud import curvature, estimate_normals

    rng = np.random.default_rng(11)
    xs, ys = np.arange(-40.0, 40.0, 0.3), np.arange(-40.0, 40.0, 4.0)
    gx, gy = np.meshgrid(xs, ys)
    flat = np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]
    flat = np.vstack([flat, flat])                                     # both headings on the same line
    flat[:, 2] += rng.normal(0.0, noise_mm, len(flat))
    normal = np.array([0.2, 0.15, 1.0]) / np.linalg.norm([0.2, 0.15, 1.0])
    axis = np.cross([0.0, 0.0, 1.0], normal)
    rot = rotvec_to_matrix(axis / np.linalg.norm(axis) * np.arccos(normal[2]))
    pts = flat @ rot.T + np.array([0.0, 0.0, 100.0])
    nrm = estimate_normals(pts, k=16, viewpoint_mm=pts.mean(axis=0) + normal * 1000.0)
    units = pts[rng.choice(len(pts), 30, replace=False)] + normal * 0.5
    rules = TargetRules(tip_radius_mm=5.0, edge_clearance_radii=1.0, max_tilt_deg=25.0)
    found = make_targets(units, pts, nrm, curvature(pts, k=16), rules=rules, reference_dir=np.array([0.0, 1.0, 0.0]))
    inner = np.all(np.abs(found.points_mm[:, :2]) < 30.0, axis=1)     # away from the raster's border
    assert inner.sum() >= 3
    cos = np.asarray(found.normals)[inner] @ normal
    assert np.min(cos) > np.cos(np.radians(5.0)), np.degrees(np.arccos(np.clip(cos, -1, 1)))


# --------------------------------------------------------------------------- scan lines at a border
# The judgement at the cells' scale (phases._scan_frames_on_face): 5 mm tip, profile span 80 mm.
HALF_SPAN_MM, WINDOW_MM, STRIP_MM, BIN_MM, GAP_MM = 40.0, 15.0, 5.0, 1.0, 5.0


def _frames(cloud, points, reference):
    points = np.asarray(points, float)
    up = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    return border_scan_frames(cloud, points, up, np.asarray(reference, float), HALF_SPAN_MM, WINDOW_MM, STRIP_MM,
                              BIN_MM, MAX_FACE_SLOPE, GAP_MM)


def test_a_scan_line_that_would_cross_a_rim_turns_along_it(scene):
    """On the box top (x in +-75, y in +-50), a line along x from 10 mm inside the x-rim would
    leave the face 10 mm out, inside the dent's window; along y it stays on for the
    half-span: the line turns. Near the y-rim the rule's line already runs along it; in the
    middle both stay on; 25 mm from the rim the rule's line holds the window and is kept; at
    a corner neither gains more than the strip, so the rule holds."""
    top = BOX_TOP
    t = _frames(scene["pts"], [[0, 0, top], [65, 0, top], [-66, 5, top], [0, 42, top], [65, 42, top],
                               [50, 0, top]], [1, 0, 0])
    along_x = np.abs(t[:, 0]) > 0.999
    along_y = np.abs(t[:, 1]) > 0.999
    assert along_x[0] and along_y[1] and along_y[2] and along_x[3] and along_x[4] and along_x[5]
    np.testing.assert_allclose(t @ [0.0, 0.0, 1.0], 0.0, atol=1e-9)


def test_a_scan_line_at_the_foot_of_a_wall_turns_along_the_wall(scene):
    """On the pillow 10 mm from the box's wall the line along x would climb the wall (a step
    steeper than the measurement's face limit); along the wall it stays on the pillow."""
    cloud = scene["pts"]
    runs = face_runs_mm(cloud, np.array([[-85.0, 0.0, PILLOW_H]]), np.array([[0.0, 0.0, 1.0]]),
                        np.array([[1.0, 0.0, 0.0]]), HALF_SPAN_MM, STRIP_MM, BIN_MM, MAX_FACE_SLOPE, GAP_MM)
    assert 7.0 <= runs[0, 0] <= 11.0 and runs[0, 1] == HALF_SPAN_MM
    t = _frames(cloud, [[-85.0, 0.0, PILLOW_H]], [1, 0, 0])
    assert abs(t[0, 1]) > 0.999


def test_a_face_run_ends_where_the_cloud_ends():
    """A top whose wall the sweep did not see (a flat patch, lines 3 mm apart along x): the run
    across the lines ends at the last line, the run along them at the patch's end; a hole
    narrower than the gap allowance (one missing line) does not end it."""
    xs, ys = np.arange(-100.0, 100.0, 0.3), np.arange(-80.0, 80.01, 3.0)
    ys = ys[np.abs(ys - 10.0) > 1.0]                   # one sweep line missing (y = 10)
    gx, gy = np.meshgrid(xs, ys)
    cloud = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, 30.0)])
    pts = np.array([[0.0, 0.0, 30.0], [0.0, 70.0, 30.0], [85.0, 0.0, 30.0]])
    up = np.tile([0.0, 0.0, 1.0], (3, 1))
    along_y = face_runs_mm(cloud, pts, up, np.tile([0.0, 1.0, 0.0], (3, 1)), HALF_SPAN_MM, STRIP_MM, BIN_MM,
                           MAX_FACE_SLOPE, GAP_MM)
    along_x = face_runs_mm(cloud, pts, up, np.tile([1.0, 0.0, 0.0], (3, 1)), HALF_SPAN_MM, STRIP_MM, BIN_MM,
                           MAX_FACE_SLOPE, GAP_MM)
    np.testing.assert_allclose(along_y[0], [HALF_SPAN_MM, HALF_SPAN_MM])
    np.testing.assert_allclose(along_y[1], [9.0, HALF_SPAN_MM], atol=BIN_MM)
    np.testing.assert_allclose(along_x[2], [14.7, HALF_SPAN_MM], atol=BIN_MM)
    t = _frames(cloud, pts, [0, 1, 0])
    assert abs(t[0, 1]) > 0.999 and abs(t[1, 0]) > 0.999 and abs(t[2, 1]) > 0.999


def _floor_and_plate(noise_mm: float, seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A floor (z = 0) with a 10 mm plate on it for x >= 0, sampled from above at 0.5 mm
    with the plate's side unseen (a scanner above barely sees it), and a shallow hollow in
    the floor centred at x = -60 (40 mm across, 2 mm deep: the sag of a 100 mm sphere, wider
    than any tip); flat normals and zero curvature, so no sharp-edge test can stand in for
    the tip test."""
    g = np.arange(-120.0, 40.0, 0.5)
    gx, gy = np.meshgrid(g, np.arange(-30.0, 30.01, 0.5))
    x, y = gx.ravel(), gy.ravel()
    rho2 = (x + 60.0) ** 2 + y ** 2
    hollow = np.where(rho2 < 20.0 ** 2, -(400.0 - rho2) / 200.0, 0.0)     # sag of a 100 mm sphere, <= 2 mm
    z = np.where(x >= 0.0, 10.0, hollow) + np.random.default_rng(seed).normal(0.0, noise_mm, x.size)
    cloud = np.column_stack([x, y, z])
    normals = np.tile([0.0, 0.0, 1.0], (len(cloud), 1))
    return cloud, normals, np.zeros(len(cloud))


@pytest.mark.parametrize("noise_mm", [0.0, 0.12])
def test_the_tip_does_not_fit_at_the_foot_of_a_wall(noise_mm):
    """Within one tip radius of the plate's foot the ball would meet the plate first: not
    probe-able, although the plate's side is not in the cloud; beyond it, on the plate's top,
    in the wide hollow and on the flat floor it fits. The noise is the library's noisiest
    scanner (foam, 0.12 mm)."""
    rules = TargetRules(tip_radius_mm=5.0, edge_clearance_radii=3.0, max_tilt_deg=60.0)
    cloud, normals, curv = _floor_and_plate(noise_mm)
    ok = probeable(cloud, normals, curv, rules)
    inner = np.abs(cloud[:, 1]) < 20.0                  # away from the patch's open borders
    foot = inner & (cloud[:, 0] < 0.0) & (cloud[:, 0] > -rules.tip_radius_mm + 0.25)
    beside = inner & (cloud[:, 0] < -rules.tip_radius_mm - 0.25) & (cloud[:, 0] > -100.0)
    top = inner & (cloud[:, 0] >= 0.0) & (cloud[:, 0] < 30.0)
    assert not ok[foot].any()
    assert ok[beside].mean() > 0.999 and ok[top].mean() > 0.999


def test_a_unit_at_the_foot_of_a_wall_moves_off_it():
    """The unit marks where to look: its target moves to the nearest point where the tip
    fits, one tip radius out from the plate's side, and is flagged as moved."""
    rules = TargetRules(tip_radius_mm=5.0, edge_clearance_radii=3.0, max_tilt_deg=60.0)
    cloud, normals, curv = _floor_and_plate(0.05)
    found = make_targets(np.array([[-2.0, 0.0, 0.0], [-40.0, 0.0, 0.0]]), cloud, normals, curv, rules)
    assert len(found) == 2
    assert -rules.tip_radius_mm - 1.0 <= found.points_mm[0, 0] <= -rules.tip_radius_mm + 0.01
    assert found.edge_flag.tolist() == [True, False]


@pytest.mark.parametrize("tilt_deg", [30.0, 59.0])
def test_the_tip_fits_on_a_tilted_face(tilt_deg):
    """A plane tilted up to the tilt limit never rises into the ball resting on it."""
    g = np.arange(-40.0, 40.0, 0.5)
    gx, gy = np.meshgrid(g, g)
    a = np.radians(tilt_deg)
    cloud = np.column_stack([gx.ravel(), gy.ravel(), gx.ravel() * np.tan(a)])
    cloud[:, 2] += np.random.default_rng(1).normal(0.0, 0.05, len(cloud))
    normals = np.tile([-np.sin(a), 0.0, np.cos(a)], (len(cloud), 1))
    surf = _Surface(cloud, normals, np.zeros(len(cloud)), TargetRules(tip_radius_mm=5.0), np.array([0.0, 0.0, 1.0]))
    inner = np.flatnonzero(np.all(np.abs(cloud[:, :2]) < 25.0, axis=1))
    assert surf.tip_fits(inner).all()


@pytest.mark.parametrize("groove_radius_mm, fits", [(20.0, True), (6.0, True), (4.0, False)])
def test_the_tip_fits_in_a_groove_only_if_the_groove_is_wider_than_the_tip(groove_radius_mm, fits):
    """A round-bottomed groove along y: a 5 mm ball reaches the bottom of one whose radius is
    larger than the ball's, and meets the flanks of a narrower one first."""
    g = np.arange(-15.0, 15.0, 0.4)
    gx, gy = np.meshgrid(g, g)
    x, r = gx.ravel(), groove_radius_mm
    z = np.where(np.abs(x) < r, r - np.sqrt(np.maximum(r * r - x * x, 0.0)), r)
    cloud = np.column_stack([x, gy.ravel(), z])
    normals = np.tile([0.0, 0.0, 1.0], (len(cloud), 1))
    surf = _Surface(cloud, normals, np.zeros(len(cloud)), TargetRules(tip_radius_mm=5.0), np.array([0.0, 0.0, 1.0]))
    bottom = np.flatnonzero((np.abs(x) < 0.2) & (np.abs(cloud[:, 1]) < 2.0))
    assert surf.tip_fits(bottom).all() == fits and surf.tip_fits(bottom).any() == fits


def test_the_rim_band_lies_between_the_band_clearance_and_the_survey_clearance(scene):
    """Densify's rim band (targets.probeable_and_rim_band) on the box-on-pillow: the survey's
    part is exactly ``probeable``; the band lies off it, nearer the box's sharp edges than the
    survey clearance allows but no nearer than the band's clearance; with the band clearance
    at the survey's it is empty."""
    pts, normals, curv = scene["pts"], scene["normals"], scene["curv"]
    survey, band = probeable_and_rim_band(pts, normals, curv, RULES, band_clearance_mm=RULES.tip_radius_mm)
    np.testing.assert_array_equal(survey, probeable(pts, normals, curv, RULES))
    assert band.sum() > 1000 and not np.any(band & survey)
    # The band also runs along the pillow's rim; the box's edges are the ones the truth has.
    edge_dist_mm, _ = scene["edges"].query(pts[band])
    by_box = edge_dist_mm[edge_dist_mm < 20.0]
    survey_dist_mm, _ = scene["edges"].query(pts[survey])
    assert by_box.size > 1000 and by_box.min() >= RULES.tip_radius_mm
    assert np.median(by_box) < survey_dist_mm.min()
    assert not probeable_and_rim_band(pts, normals, curv, RULES, band_clearance_mm=RULES.clearance_mm)[1].any()
