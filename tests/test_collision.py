"""Motion validation: tool shapes against an object mesh, keep-out boxes and the
workspace, along whole paths; judged against exact distances computed independently."""
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from elastoprobe.controller.core.collision import (
    Box, SceneChecker, ToolShape, boxes_from_cell, sample_mesh_surface, shapes_from_cell,
)
from elastoprobe.controller.core.geometry import Pose, probe_tcp_pose, rotvec_to_matrix

DOWN = np.diag([1.0, -1.0, -1.0])           # tool z pointing down (-z of the base)
WORKSPACE = Box("workspace", np.array([-1000.0, -1000.0, -50.0]), np.array([1000.0, 1000.0, 1000.0]))
OBJ_MIN, OBJ_MAX = np.array([400.0, -50.0, 0.0]), np.array([500.0, 50.0, 80.0])


def probe(radius_mm: float = 4.0, length_mm: float = 140.0, gap_mm: float = 8.0) -> ToolShape:
    """The sim cell's probe: a cylinder from ``gap_mm`` behind the tip back along -z."""
    return ToolShape("probe", "cylinder", Pose(np.array([0.0, 0.0, -gap_mm - length_mm / 2]), np.eye(3)),
                     radius_mm=radius_mm, length_mm=length_mm)


def object_box() -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=OBJ_MAX - OBJ_MIN)
    mesh.apply_translation((OBJ_MIN + OBJ_MAX) / 2)
    return mesh


def exact_distance_to_object(shape: ToolShape, tcp: Pose, spacing_mm: float = 0.25) -> float:
    """Independent oracle: the shape's surface densely sampled, the box's exact SDF."""
    pts, _ = shape.surface_points_local(spacing_mm)
    base_pts = tcp.compose(shape.pose_in_tcp).apply(pts)
    return float(Box("o", OBJ_MIN, OBJ_MAX).signed_distance(base_pts).min())


def test_mesh_samples_cover_the_surface():
    mesh = object_box()
    spacing = 1.5
    pts, normals = sample_mesh_surface(mesh, spacing)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    probe_pts, _ = trimesh.sample.sample_surface(mesh, 5000, seed=1)
    from scipy.spatial import cKDTree
    d, _ = cKDTree(pts).query(probe_pts)
    assert d.max() <= spacing / math.sqrt(3) + 1e-9
    # Normals point outward: a step along them leaves the box.
    assert np.all(Box("o", OBJ_MIN, OBJ_MAX).signed_distance(pts + 0.5 * normals) > 0)


def test_shape_signed_distances_are_exact():
    cyl = ToolShape("c", "cylinder", Pose.identity(), radius_mm=5.0, length_mm=20.0)
    pts = np.array([[0, 0, 0], [8, 0, 0], [0, 0, 13], [8, 0, 14], [0, 3, 9]], float)
    assert np.allclose(cyl.signed_distance_local(pts), [-5.0, 3.0, 3.0, 5.0, -1.0])
    box = ToolShape("b", "box", Pose.identity(), size_mm=(10.0, 20.0, 30.0))
    assert np.allclose(box.signed_distance_local(np.array([[0, 0, 0], [8, 0, 0], [8, 14, 0]], float)),
                       [-5.0, 3.0, 5.0])
    # Cover spheres really cover: every surface point lies in some sphere.
    for shape in (cyl, box, ToolShape("f", "cylinder", Pose.identity(), radius_mm=45.0, length_mm=40.0)):
        centres, r = shape.cover_spheres_local()
        surf, _ = shape.surface_points_local(1.0)
        d = np.linalg.norm(surf[:, None, :] - centres[None], axis=2).min(axis=1)
        assert d.max() <= r + 1e-9


def test_probe_through_object_mid_path_with_clear_ends():
    checker = SceneChecker([probe()], object_box(), [], WORKSPACE, clearance_mm=2.0)
    # Tip 20 mm above the table, probe vertical: it sweeps sideways through the 80 mm tall box.
    start = Pose(np.array([300.0, 0.0, 20.0]), DOWN)
    end = Pose(np.array([600.0, 0.0, 20.0]), DOWN)
    assert checker.check_pose(start) == [] and checker.check_pose(end) == []
    hits = checker.check_path(start, end)
    assert {(c.shape, c.obstacle) for c in hits} == {("tcp", "object"), ("probe", "object")}
    hit = next(c for c in hits if c.shape == "probe")
    # Ground truth: the probe's side (radius 4) comes within 2 mm of the face x = 400
    # when the axis reaches x = 394: fraction (394 - 300) / 300.
    expected = (400.0 - 4.0 - 2.0 - 300.0) / 300.0
    tolerance = (2.0 + 0.87) / 300.0                     # one path step + the mesh sampling
    assert expected - tolerance <= hit.at_fraction <= expected + 1e-9
    assert "probe" in hit.message and hit.distance_mm < 2.0 + 0.87


def test_path_that_passes_by_is_clear():
    checker = SceneChecker([probe()], object_box(), [], WORKSPACE, clearance_mm=2.0)
    start = Pose(np.array([300.0, 60.0, 20.0]), DOWN)      # 10 mm beside the box's y = 50 face
    end = Pose(np.array([600.0, 60.0, 20.0]), DOWN)
    assert checker.check_path(start, end) == []
    closer = checker.check_path(Pose(np.array([300.0, 55.5, 20.0]), DOWN), Pose(np.array([600.0, 55.5, 20.0]), DOWN))
    assert [c.shape for c in closer] == ["probe"]           # 1.5 mm gap < 2 mm clearance


def test_decisions_against_exact_distances_random_poses():
    """Never misses a gap below the clearance; never flags one above clearance + sampling."""
    clearance = 2.0
    checker = SceneChecker([probe()], object_box(), [], WORKSPACE, clearance_mm=clearance)
    rng = np.random.default_rng(11)
    r_mesh = 1.5 / math.sqrt(3)
    decided = {"flagged": 0, "clear": 0}
    for _ in range(300):
        axis = rng.normal(size=3)
        rot = rotvec_to_matrix(axis / np.linalg.norm(axis) * rng.uniform(0, math.pi))
        tip = rng.uniform(OBJ_MIN - 40.0, OBJ_MAX + 40.0)
        tcp = Pose(tip, rot)
        shape = probe()
        truth = exact_distance_to_object(shape, tcp)
        got = [c for c in checker.check_pose(tcp, ignore_tip_mm=0.0) if c.shape == "probe" and c.obstacle == "object"]
        if truth < clearance - 0.3:
            assert got, f"missed a probe {truth:.2f} mm from the object"
            decided["flagged"] += 1
            if truth > 0.5:
                assert truth - 0.3 <= got[0].distance_mm <= truth + r_mesh + 0.3
        elif truth > clearance + r_mesh + 0.3:
            assert not got, f"flagged a probe {truth:.2f} mm away: {got[0].message}"
            decided["clear"] += 1
    assert decided["flagged"] > 30 and decided["clear"] > 30


def test_shape_wholly_inside_a_big_object_is_caught():
    big = trimesh.creation.box(extents=[600.0, 600.0, 600.0])
    big.apply_translation([0.0, 0.0, 300.0])
    small = ToolShape("pin", "cylinder", Pose(np.array([0.0, 0.0, -20.0]), np.eye(3)), radius_mm=3.0, length_mm=20.0)
    checker = SceneChecker([small], big, [], WORKSPACE, clearance_mm=2.0)
    hits = checker.check_pose(Pose(np.array([0.0, 0.0, 300.0]), DOWN), ignore_tip_mm=5.0)
    assert [(c.shape, c.obstacle) for c in hits] == [("pin", "object")]
    assert hits[0].distance_mm < -200.0 and "inside" in hits[0].message


def test_tip_allowance():
    checker = SceneChecker([probe()], object_box(), [], WORKSPACE, clearance_mm=2.0)
    top = OBJ_MAX[2]
    # Contact move: the tip centre goes from 30 mm above the top face to 10 mm into it,
    # so the probe cylinder (from 8 mm behind the tip) ends 2 mm deep.
    start = Pose(np.array([450.0, 0.0, top + 30.0]), DOWN)
    end = Pose(np.array([450.0, 0.0, top - 10.0]), DOWN)
    strict = checker.check_path(start, end)
    assert {c.shape for c in strict} == {"tcp", "probe"}
    # With the last 12 mm allowed to touch, it may.
    assert checker.check_path(start, end, ignore_tip_mm=12.0) == []
    # But pushing 30 mm in buries the probe beyond the allowance.
    deep = Pose(np.array([450.0, 0.0, top - 30.0]), DOWN)
    hits = checker.check_path(start, deep, ignore_tip_mm=12.0)
    assert [c.shape for c in hits] == ["probe"] and hits[0].distance_mm < 0
    # The allowance is a zone near the tool axis only: a wide shape near the tip still counts.
    skirt = ToolShape("skirt", "cylinder", Pose(np.array([0.0, 0.0, -3.0]), np.eye(3)), radius_mm=40.0,
                      length_mm=4.0)
    wide = SceneChecker([skirt], object_box(), [], WORKSPACE, clearance_mm=2.0)
    # Its underside 1.5 mm above the face: exempt near the axis, not at radius 20-40 mm.
    assert [c.shape for c in wide.check_pose(Pose(np.array([450.0, 0.0, top + 0.5]), DOWN), 12.0)] == ["skirt"]
    assert wide.check_pose(Pose(np.array([450.0, 0.0, top + 6.0]), DOWN), 12.0) == []


def test_keep_out_boxes_and_clearance():
    column = Box("robot_column", np.array([-120.0, -120.0, -10.0]), np.array([120.0, 120.0, 700.0]))
    checker = SceneChecker([probe()], None, [column], WORKSPACE, clearance_mm=2.0)
    # A sweep across the column at tip height 300: both ends clear, the middle is not.
    start = Pose(np.array([-300.0, 200.0, 300.0]), DOWN)
    end = Pose(np.array([300.0, -200.0, 300.0]), DOWN)
    assert checker.check_pose(start) == [] and checker.check_pose(end) == []
    hits = checker.check_path(start, end)
    assert {(c.shape, c.obstacle) for c in hits} == {("tcp", "robot_column"), ("probe", "robot_column")}
    assert all(0.0 < c.at_fraction < 1.0 for c in hits)
    # Clearance: the probe side 1.5 mm from the column's face is refused, 3 mm is fine.
    assert [c.obstacle for c in checker.check_pose(Pose(np.array([125.5, 0.0, 300.0]), DOWN))] == ["robot_column"]
    assert checker.check_pose(Pose(np.array([127.0, 0.0, 300.0]), DOWN)) == []
    # Above the column top the probe passes.
    assert checker.check_path(Pose(np.array([-300.0, 0.0, 800.0]), DOWN), Pose(np.array([300.0, 0.0, 800.0]), DOWN)) == []


def test_small_keep_out_inside_a_big_shape():
    flange = ToolShape("flange", "cylinder", Pose(np.array([0.0, 0.0, -185.0]), np.eye(3)), radius_mm=45.0,
                       length_mm=40.0)
    pebble = Box("pebble", np.array([-3.0, -3.0, 182.0]), np.array([3.0, 3.0, 188.0]))
    checker = SceneChecker([flange], None, [pebble], WORKSPACE, clearance_mm=2.0)
    assert [c.obstacle for c in checker.check_pose(Pose(np.array([0.0, 0.0, 0.0]), DOWN))] == ["pebble"]


def test_workspace_holds_the_tcp_and_every_shape():
    ws = Box("workspace", np.array([150.0, -400.0, -5.0]), np.array([850.0, 400.0, 700.0]))
    scanner = ToolShape("scanner", "box", Pose(np.array([150.0, 0.0, -120.0]),
                                               rotvec_to_matrix([0.0, math.radians(-51.34), 0.0])),
                        size_mm=(60.0, 80.0, 50.0))
    checker = SceneChecker([probe(), scanner], None, [], ws)
    assert checker.check_pose(Pose(np.array([450.0, 0.0, 200.0]), DOWN)) == []
    # TCP inside, but the tool reaching up past the top (tip at 600: probe up to 748 mm).
    hits = checker.check_pose(Pose(np.array([450.0, 0.0, 600.0]), DOWN))
    assert {(c.shape, c.obstacle) for c in hits} == {("probe", "workspace"), ("scanner", "workspace")}
    assert all(c.distance_mm < 0 for c in hits)
    # TCP itself outside.
    out = checker.check_pose(Pose(np.array([900.0, 0.0, 200.0]), DOWN))
    assert ("tcp", "workspace") in {(c.shape, c.obstacle) for c in out}
    # Along a path: leaving at the far end only.
    hits = checker.check_path(Pose(np.array([450.0, 0.0, 200.0]), DOWN), Pose(np.array([450.0, 0.0, 650.0]), DOWN))
    probe_hit = next(c for c in hits if c.shape == "probe")
    # The probe's top (148 mm above the tip) passes z = 700 when the tip is at 552.
    assert probe_hit.at_fraction == pytest.approx((552.0 - 200.0) / 450.0, abs=2.0 / 450.0 + 1e-9)


def test_rotation_sweeps_a_far_shape_through_an_obstacle():
    """A pure rotation about the TCP: the scanner, 190 mm from the tip, sweeps through a
    keep-out box that neither end pose touches."""
    scanner = ToolShape("scanner", "box", Pose(np.array([150.0, 0.0, -120.0]), np.eye(3)), size_mm=(60.0, 80.0, 50.0))
    tcp = np.array([450.0, 0.0, 100.0])
    start = Pose(tcp, DOWN)                                  # scanner centre at (600, 0, 220)
    end = Pose(tcp, rotvec_to_matrix([0.0, 0.0, math.pi * 0.9]) @ DOWN)
    mid = Pose(tcp, rotvec_to_matrix([0.0, 0.0, math.pi * 0.45]) @ DOWN)
    post = Box("post", *(lambda c: (c - 15.0, c + 15.0))(mid.compose(scanner.pose_in_tcp).position_mm))
    checker = SceneChecker([scanner], None, [post], WORKSPACE)
    assert checker.check_pose(start) == [] and checker.check_pose(end) == []
    hits = checker.check_path(start, end)
    assert [(c.shape, c.obstacle) for c in hits] == [("scanner", "post")]
    assert 0.2 < hits[0].at_fraction < 0.5


def test_sim_cell_shapes_and_boxes():
    from elastoprobe.controller.core.config import load_cell
    cell, _ = load_cell(Path(__file__).resolve().parents[1] / "config" / "cells" / "sim.yaml")
    shapes = shapes_from_cell(cell.tool)
    ws, keep_out = boxes_from_cell(cell.limits)
    assert {s.name for s in shapes} == {"probe", "ft_sensor", "scanner", "flange"}
    assert ws.name == "workspace" and [b.name for b in keep_out] == ["robot_column"]
    mesh = object_box()
    checker = SceneChecker(shapes, mesh, keep_out, ws)
    n, t = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    target = np.array([450.0, 0.0, OBJ_MAX[2]])
    # Steep angles on the flat top: approach to 30 mm standoff is clear, so is contact with allowance.
    for angle in (45.0, 75.0, 90.0, 105.0, 135.0):
        standoff = probe_tcp_pose(target, n, t, angle, offset_mm=30.0)
        contact = probe_tcp_pose(target, n, t, angle, offset_mm=-5.0)
        assert checker.check_path(standoff, contact, ignore_tip_mm=20.0) == [], angle
    # At 10 degrees on a flat face the probe body lies on the surface: refused, honestly.
    low = probe_tcp_pose(target, n, t, 10.0, offset_mm=0.0)
    assert any(c.shape == "probe" for c in checker.check_pose(low, ignore_tip_mm=20.0))


def test_a_path_that_starts_inside_a_keep_outs_clearance_may_leave_it_never_come_closer():
    """The probe side 1.5 mm from the column (inside the 2 mm clearance, not in the box), as a
    force loop or a fault's retract can leave it: moving away or straight up (along the
    face) is accepted, moving closer is refused, and the pose itself still is."""
    column = Box("robot_column", np.array([-120.0, -120.0, -10.0]), np.array([120.0, 120.0, 700.0]))
    checker = SceneChecker([probe()], None, [column], WORKSPACE, clearance_mm=2.0)
    here = Pose(np.array([125.5, 0.0, 300.0]), DOWN)
    assert [c.obstacle for c in checker.check_pose(here)] == ["robot_column"]
    away, up = Pose(np.array([160.0, 0.0, 300.0]), DOWN), Pose(np.array([125.5, 0.0, 400.0]), DOWN)
    assert checker.check_path(here, away, leaving=True) == []
    assert checker.check_path(here, up, leaving=True) == []                              # along the face
    assert [c.obstacle for c in checker.check_path(here, Pose(np.array([124.5, 0.0, 320.0]), DOWN), leaving=True)] \
        == ["robot_column"]                                                               # closer
    # Into the margin and out again farther along: refused where it comes closer.
    back = checker.check_path(here, Pose(np.array([124.0, 0.0, 600.0]), DOWN), leaving=True)
    assert back and back[0].at_fraction > 0.0
    # Planning from a pose the arm is not at keeps the clearance (the arm could not get there),
    # and from outside the clearance the rule is the clearance, as before.
    assert [c.obstacle for c in checker.check_path(here, away)] == ["robot_column"]
    assert [c.obstacle for c in checker.check_path(away, here, leaving=True)] == ["robot_column"]
