"""Cloud acquisition on the simulated cell: the sweep's strips, lines refused by motion
validation planned again (validated before the arm moves), the surface left unseen filled
and reported."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from elastoprobe.controller import phases
from elastoprobe.controller.acquire import SweepSettings, acquire_cloud, line_footprint_mm, sweep_lines
from elastoprobe.controller.cellfactory import ground_truth_for
from elastoprobe.controller.cli import main
from elastoprobe.controller.core.collision import Box, SceneChecker, boxes_from_cell, shapes_from_cell
from elastoprobe.controller.core.config import load_cell, load_session_inputs
from elastoprobe.controller.core.geometry import Pose, probe_tcp_pose
from elastoprobe.controller.core.kinematics import ur5e
from elastoprobe.controller.core.validation import PathValidator
from elastoprobe.controller.coverage import seen_mask, top_surface
from elastoprobe.controller.journal import Journal
from elastoprobe.controller.learning.evaluate import truth_surface_scores
from elastoprobe.controller.machine import SessionMachine
from elastoprobe.controller.probe import ProbeExecutor, ProbeSettings
from elastoprobe.controller.session import EXIT_PAUSED, Session
from elastoprobe.controller.status import snapshot
from elastoprobe.sim.objects import SimObject, load_object

from test_sim_helpers import go_to, make_cell

ROOT = Path(__file__).resolve().parent.parent
SPEC, _ = load_cell(ROOT / "config" / "cells" / "sim.yaml")
HEIGHT_MM = 40.0
BALL_TOP_MM = 130.0           # the rubber ball's top (object frame), the ball at base x = 450 mm


def footprint(depth_mm: float = HEIGHT_MM) -> tuple[float, float]:
    return line_footprint_mm(SPEC.tool.tcp_to_scanner.pose(), SPEC.scanner.field_of_view_deg,
                             SPEC.scanner.max_range_mm, depth_mm, shapes_from_cell(SPEC.tool), SPEC.tool.tip_radius_mm)


class Recorder:
    """The arm's commanded moves (every straight leg the executor sent)."""

    def __init__(self, cell) -> None:
        self.legs: list[tuple[Pose, Pose]] = []
        arm, send = cell.arm, cell.arm.move_linear

        def move_linear(target: Pose, speed: float, accel: float):
            self.legs.append((arm.status().tcp_pose, target))
            return send(target, speed, accel)

        arm.move_linear = move_linear


def flat_slab(size_mm: float = 300.0, height_mm: float = 50.0) -> SimObject:
    """A homogeneous elastomer slab on the table (a flat top: its mesh is exact)."""
    mesh = trimesh.creation.box(extents=(size_mm, size_mm, height_mm))
    mesh.apply_translation([0.0, 0.0, height_mm / 2.0])
    material = load_object(ROOT / "config" / "objects" / "user_object.yaml").materials[0]
    return SimObject("slab", mesh, np.zeros(len(mesh.faces), dtype=int), [material.name], [material])


def sweep_ball(keep_out: list[Box], settings: SweepSettings | None = None, obj: SimObject | None = None):
    """Sweep the rubber ball (or ``obj``) with a validator that knows the cell's boxes plus
    ``keep_out``; returns (result, the commanded legs, the checker)."""
    cell = make_cell() if obj is None else make_cell(object=obj)
    mesh_base = cell.world.obj.mesh.copy()
    mesh_base.apply_transform(cell.base_to_object.matrix())
    workspace, boxes = boxes_from_cell(SPEC.limits)
    checker = SceneChecker(shapes_from_cell(SPEC.tool), mesh_base, boxes + keep_out, workspace)
    validator = PathValidator(ur5e(SPEC.tool.flange_to_tcp.pose()), checker, cell.arm.status().joints_rad, 0.0)
    probe = ProbeSettings(scans_per_step=10, settle_s=1.0, standoff_mm=15.0, force_rate_n_s=10.0,
                          force_tolerance_n=0.5, contact_force_n=0.4, contact_speed_mm_s=5.0, free_speed_mm_s=150.0,
                          free_accel_mm_s2=600.0, search_distance_mm=30.0, tip_radius_mm=SPEC.tool.tip_radius_mm)
    top_z = float(cell.world.obj.mesh.bounds[1, 2])
    ex = ProbeExecutor(cell, SessionMachine(initial="planning"), probe, validator, object_top_z_mm=top_z)
    recorder = Recorder(cell)
    settings = settings or SweepSettings(4.0, HEIGHT_MM, footprint(), max_tilt_deg=35.0)
    return acquire_cloud(ex, cell.world.obj.mesh, settings), recorder.legs, checker


def assert_never_entered(legs: list[tuple[Pose, Pose]], checker: SceneChecker) -> None:
    for start, end in legs:
        hits = checker.check_path(start, end)
        assert not hits, hits[0].message


def test_footprint_is_what_the_simulated_scanner_sees_of_a_level_surface():
    # A slab 40 mm below the tip: the controller's footprint (from the cell file: mount, field
    # of view, range, the tool's shapes hiding the line beyond the tip) must lie inside what
    # the simulated scanner returns, or neighbouring lines would leave bands between them.
    cell = make_cell(object=flat_slab(400.0), scanner={"noise_scale": 0.0})
    pose = probe_tcp_pose(np.array([450.0, 0.0, 50.0 + HEIGHT_MM]), np.array([0.0, 0.0, 1.0]),
                          np.array([1.0, 0.0, 0.0]), 90.0)
    go_to(cell, pose, 150.0)
    x, z = cell.scanner.profile(cell.world.snapshot_now(), noise=False)
    ok = np.isfinite(z)
    in_tool = cell.tcp_to_scanner.apply(np.column_stack([x[ok], np.zeros(int(ok.sum())), z[ok]]))
    lo, hi = footprint()
    print(f"footprint {lo:.1f}..{hi:.1f} mm; the scanner returns {in_tool[:, 0].min():.1f}..{in_tool[:, 0].max():.1f}")
    assert hi - lo > 60.0
    assert in_tool[:, 0].min() <= lo + 0.5 and in_tool[:, 0].max() >= hi - 0.5
    # Deeper surfaces show a wider line: the raster is planned on the narrowest, the top.
    lo_deep, hi_deep = footprint(2.0 * HEIGHT_MM)
    assert hi_deep - lo_deep > hi - lo


def test_raster_lines_lie_at_most_a_strip_apart_in_both_headings():
    lines = sweep_lines(np.array([385.0, -65.0, 0.0]), np.array([515.0, 65.0, 130.0]), 170.0, 82.0, 40.0)
    for heading in (-1, 1):
        xs = np.sort([ln.across_mm for ln in lines if ln.heading == heading])
        assert xs[0] == pytest.approx(345.0) and xs[-1] == pytest.approx(555.0)
        assert np.max(np.diff(xs)) <= 82.0 + 1e-9
    assert all(min(ln.from_mm, ln.to_mm) == pytest.approx(-105.0) for ln in lines)


def test_a_line_blocked_by_a_keep_out_is_scanned_shifted_and_nothing_is_left_unseen():
    # A bracket hanging beside the ball, in the way of the probe on one raster line over the
    # ball (both headings) and of nothing else: skipping those lines would leave a band.
    lo, hi = footprint()
    ball = make_cell().world.obj.mesh.bounds + [[450.0, 0.0, 0.0]]
    xs = [ln.across_mm for ln in sweep_lines(ball[0], ball[1], BALL_TOP_MM + HEIGHT_MM, 0.9 * (hi - lo))]
    x = min(xs, key=lambda v: abs(v - 470.0))
    bracket = Box("bracket", np.array([x - 8.0, 85.0, 150.0]), np.array([x + 8.0, 100.0, 175.0]))
    result, legs, checker = sweep_ball([bracket])
    replanned = [r for r in result.replanned if r.startswith(f"line at x={x:.0f} mm")]
    assert len(replanned) == 2 and all("bracket" in r and "shifted" in r for r in replanned), result.replanned
    assert result.refused == []
    assert_never_entered(legs, checker)
    assert result.unseen_mm2 < 0.005 * result.top_mm2, result.unseen_where


def test_a_line_blocked_along_part_of_its_length_is_scanned_in_pieces():
    # A beam across every line's far end (all x, y 80..100 mm): no shift or turn of a line
    # clears it, the part of each line short of it does.
    beam = Box("beam", np.array([250.0, 80.0, 150.0]), np.array([650.0, 100.0, 175.0]))
    result, legs, checker = sweep_ball([beam])
    assert result.replanned and all("piece" in r and "beam" in r for r in result.replanned), result.replanned
    assert_never_entered(legs, checker)
    # The ball reaches y = 65 mm: the pieces end short of the beam and still cover it.
    assert result.unseen_mm2 < 0.005 * result.top_mm2, result.unseen_where


def test_bands_the_raster_misses_get_lines_of_their_own():
    # A raster planned for a line half again as wide as the scanner's leaves bands between its
    # lines; the fill pass finds them on the slab's top and scans them.
    lo, hi = footprint()
    wide = SweepSettings(4.0, HEIGHT_MM, (lo - 0.25 * (hi - lo), hi + 0.25 * (hi - lo)), max_tilt_deg=20.0)
    result, _, _ = sweep_ball([], wide, flat_slab())
    assert result.fill_lines >= 2
    assert result.unseen_mm2 < 0.005 * result.top_mm2, result.unseen_where


def test_profiles_further_apart_than_twice_the_seen_distance_leave_no_unseen_surface():
    # Profiles 8 mm apart along the line: a point midway between two is 4 mm from both. The
    # surface between them was scanned, and a fill line (at the same spacing) would not see it
    # any closer: it is neither unseen nor worth lines of its own.
    sparse = SweepSettings(8.0, HEIGHT_MM, footprint(), max_tilt_deg=20.0)
    assert sparse.seen_within_mm == pytest.approx(4.5)
    result, _, _ = sweep_ball([], sparse, flat_slab())
    assert result.fill_lines == 0
    assert result.unseen_mm2 < 0.005 * result.top_mm2, result.unseen_where
    assert result.outputs()["seen_within_mm"] == pytest.approx(4.5)


def test_unseen_area_is_what_the_sweep_saw_before_the_cloud_is_thinned():
    # max_points thins the cloud the session keeps; the surface the sweep saw is not unseen
    # for that (3000 of the slab's points leave most of it without one within 2 mm).
    thin = SweepSettings(4.0, HEIGHT_MM, footprint(), max_tilt_deg=20.0, max_points=3000)
    result, _, _ = sweep_ball([], thin, flat_slab())
    assert len(result.points_mm) == 3000
    assert result.unseen_mm2 < 0.005 * result.top_mm2, result.unseen_where


def test_top_surface_is_what_is_seen_from_above_within_the_tilt():
    composite = load_object(ROOT / "config" / "objects" / "composite.yaml").mesh
    top = top_surface(composite, 1.0, 20.0)
    # The box top (160 x 160) and the pillow's top (400 x 300, its rounded rim of radius 25 mm
    # within 20 deg of level) less what the box stands on: the pillow's faces under the box
    # are not top surface.
    rim = 25.0 * (1.0 - np.sin(np.radians(20.0)))
    assert top.total_mm2 == pytest.approx((400.0 - 2 * rim) * (300.0 - 2 * rim), rel=0.01)
    assert not np.any((np.abs(top.points_mm[:, :2]) < 79.0).all(axis=1) & (top.points_mm[:, 2] < 100.0))
    tilted = trimesh.creation.box(extents=(100.0, 100.0, 10.0))
    tilted.apply_transform(trimesh.transformations.rotation_matrix(np.radians(15.0), [1.0, 0.0, 0.0]))
    assert top_surface(tilted, 0.5, 20.0).total_mm2 == pytest.approx(100.0 * 100.0, rel=0.005)
    assert top_surface(tilted, 0.5, 10.0).total_mm2 == 0.0
    pts = top.points_mm
    assert seen_mask(pts, pts + [0.0, 0.0, 1.9]).all() and not seen_mask(pts, pts + [0.0, 0.0, 2.1]).any()


def _pause_after_the_cloud(monkeypatch: pytest.MonkeyPatch, session: Session) -> None:
    """The operator asks for a pause as the cloud phase ends (a request before the run would
    pause the sweep itself, before the cloud is committed)."""
    sweep = phases.phase_cloud

    def cloud_then_pause(ctx: phases.PhaseContext) -> phases.Plan:
        yield from sweep(ctx)
        session.flags.pause_requested = True

    monkeypatch.setattr(phases, "phase_cloud", cloud_then_pause)


def test_session_journals_and_reports_the_unseen_area(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    # The user object on the default cell: one raster line has the scanner in the robot's
    # column and is planned again. Paused after the cloud phase: it is committed.
    inputs = load_session_inputs(ROOT / "config" / "plans" / "user_object.yaml")
    session = Session(inputs, tmp_path / "s", seed=1)
    _pause_after_the_cloud(monkeypatch, session)
    assert session.run() == EXIT_PAUSED
    with Journal.open_readonly(tmp_path / "s") as j:
        sweep = j.phase("cloud", 0).outputs["sweep"]
    assert sweep["lines_refused"] == [] and any("robot_column" in r for r in sweep["lines_replanned"])
    assert sweep["top_surface_mm2"] > 8000.0 and sweep["unseen_mm2"] < 0.01 * sweep["top_surface_mm2"]
    assert sweep["coverage"] == pytest.approx(1.0 - sweep["unseen_mm2"] / sweep["top_surface_mm2"], abs=1e-4)
    log = (tmp_path / "s" / "log.jsonl").read_text()
    assert '"sweep_line_replanned"' in log and '"sweep_unseen"' in log
    cloud = snapshot(tmp_path / "s")["cloud"]
    assert cloud["coverage"] == sweep["coverage"] and cloud["lines_replanned"] == len(sweep["lines_replanned"])


@pytest.mark.parametrize("object_seed", [1006, 1007])
def test_a_generated_object_is_covered_on_its_true_surface(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                           object_seed: int):
    # Objects nobody tuned for (the suite's domes 1006 and 1007, docs/generated_objects.md)
    # with the plan the rule gives them: the raster line nearest the robot's column has the
    # scanner in the column and is planned again (skipped, with lines a scanner's width and
    # more apart, the cloud covered 85 % of 1006's top); the cloud then covers the true top
    # within the plan's tilt, scored as evaluate scores it (>= 98 %: issue 16's goal). 1007's
    # rim meets the table at about 25 degrees, inside the tilt: the table removal dropped
    # its lowest 2 mm, a band all round (92.5 %), while the sweep reported 100 %; the
    # journal's figure is now that of the cloud kept.
    assert main(["sim", "object", "--seed", str(object_seed), "--out", str(tmp_path / "obj")]) == 0
    inputs = load_session_inputs(tmp_path / "obj" / "plan.yaml")
    session = Session(inputs, tmp_path / "s", seed=1)
    _pause_after_the_cloud(monkeypatch, session)
    assert session.run() == EXIT_PAUSED
    with Journal.open_readonly(tmp_path / "s") as j:
        cloud = j.phase("cloud", 0)
    sweep = cloud.outputs["sweep"]
    assert sweep["lines_refused"] == [] and any("robot_column" in r for r in sweep["lines_replanned"])
    top = ground_truth_for(inputs, 1).top_surface(inputs.plan.sampling.max_tilt_deg)
    pts, nrm = cloud.arrays["points_mm"].astype(float), cloud.arrays["normals"].astype(float)
    scores = truth_surface_scores(top.points_mm, top.normals, top.labels, top.area_mm2, pts, nrm,
                                  np.zeros(len(pts), dtype=int), top.spacing_mm)
    print(f"coverage {scores['coverage']:.4f} of {scores['area_mm2']:.0f} mm^2; sweep: {sweep['coverage']}")
    assert scores["coverage"] >= 0.98
    assert sweep["coverage"] == pytest.approx(scores["coverage"], abs=0.01)
