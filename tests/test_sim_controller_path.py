"""The controller's own probe executor and cloud sweep drive the simulated cell end to end."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller.core.config import load_session_inputs
from elastoprobe.controller.core.errors import MotionRefused
from elastoprobe.controller.core.geometry import Pose, probe_tcp_pose, rotvec_to_matrix
from elastoprobe.controller.core.validation import build_validator
from elastoprobe.controller.machine import SessionMachine
from elastoprobe.controller.probe import ForceLevel, ProbeExecutor, ProbeSettings, ProbeTarget
from elastoprobe.controller.toolhead import WRIST_TURN_LEG_RAD, MotionSettings, Toolhead

from test_sim_helpers import ROOT, Fence, make_cell


class _NoValidation:
    def validate_path(self, start: Pose, end: Pose, contact_allowed: bool = False) -> None:
        return None


def _executor(cell) -> ProbeExecutor:
    settings = ProbeSettings(scans_per_step=10, settle_s=1.0, standoff_mm=15.0, force_rate_n_s=10.0,
                             force_tolerance_n=0.5, contact_force_n=0.4, contact_speed_mm_s=5.0,
                             free_speed_mm_s=150.0, free_accel_mm_s2=600.0, search_distance_mm=30.0,
                             tip_radius_mm=cell.params.tip_radius_mm)
    return ProbeExecutor(cell, SessionMachine(initial="planning"), settings, _NoValidation(), object_top_z_mm=130.0)


def test_probe_executor_runs_force_levels_on_the_sim():
    cell = make_cell()
    ex = _executor(cell)
    steps = []
    target = ProbeTarget(0, np.array([0.0, 0.0, 130.0]), np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    ex.probe(target, 90.0, [ForceLevel(1, 3.0), ForceLevel(2, 8.0)], steps.append)
    assert [s.step_id for s in steps] == [1, 2]
    for step, force in zip(steps, (3.0, 8.0)):
        assert step.scans_xz_mm.shape == (10, 256, 2)
        assert abs(step.force_magnitude_n() - force) < 0.2
        assert np.isfinite(step.scans_xz_mm[..., 1]).mean() > 0.2
        # The measured force direction: the probe pushes down into the ball top.
        assert step.measured_direction()[2] < -0.99
    assert cell.arm.trip() is None and cell.world.contact is None
    assert ex.contact_normal_base is None            # unloaded: no probe in flight


def test_an_unload_the_limits_cut_short_is_reported_with_the_refusal():
    """The unload backs out standoff + 5 mm along the normal; where the limits allow less, the
    arm stops short and the executor says how far it went and why (the session logs it as
    ``unload_shortened``). A whole unload reports nothing."""
    normal = np.array([0.3, 0.0, 1.0]) / np.hypot(0.3, 1.0)
    target = ProbeTarget(0, np.array([0.0, 0.0, 130.0]), normal, np.array([0.0, 1.0, 0.0]))
    for fence_after_mm, expect_short in ((1e9, False), (12.0, True)):
        cell = make_cell()
        ex = _executor(cell)
        shortened: list[dict] = []
        ex.on_unload_shortened = shortened.append

        def fence_once_loaded(step) -> None:
            # Once the last level is scanned the fence closes in: 20 mm along the normal is
            # beyond it, 10 mm is not (the approach itself was free).
            x_mm = float(ex.toolhead.pose().position_mm[0])
            ex.validator = Fence(x_mm + normal[0] * fence_after_mm)

        ex.probe(target, 90.0, [ForceLevel(1, 3.0)], fence_once_loaded)
        assert cell.arm.trip() is None and cell.world.contact is None
        if not expect_short:
            assert shortened == []
            continue
        assert len(shortened) == 1
        record = shortened[0]
        assert record["asked_mm"] == pytest.approx(20.0)            # standoff 15 + 5
        assert record["moved_mm"] == pytest.approx(10.0)             # halved once
        assert "fence" in record["refused"]


@pytest.mark.parametrize("angle_deg", [90.0, 170.0])
def test_force_levels_on_hard_rubber_stay_near_their_targets(tmp_path: Path, angle_deg: float):
    """The ball made of the generated objects' stiffest rubber (60 MPa, ~100 N/mm under the
    tip): a probe's five levels, as the characterize phase runs them. Each level used to
    start the loop from its 2 N/mm guess: 5-15 N over every target after the first, and a
    force-rate trip at 4.5-7 N that cost the target (33 trips on one generated slab), and the
    first level 1-4 N over its 1 N. The first level now starts from the touch's stiffness
    (the contact search's force rise), each later one from where the previous one's ended."""
    text = (ROOT / "config" / "objects" / "rubber_ball.yaml").read_text()
    assert "E_mpa: 10.0" in text
    obj = tmp_path / "hard_ball.yaml"
    obj.write_text(text.replace("E_mpa: 10.0", "E_mpa: 60.0"))
    cell = make_cell(object_path=obj)
    ex = _executor(cell)
    records, steps = [], []
    ex.on_regulated = records.append
    target = ProbeTarget(0, np.array([0.0, 0.0, 130.0]), np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    levels_n = (1.0, 2.5, 4.5, 7.0, 10.0)
    ex.probe(target, angle_deg, [ForceLevel(k + 1, f) for k, f in enumerate(levels_n)], steps.append)
    assert len(steps) == 5 and cell.arm.trip() is None
    gains = cell.arm.supervisor.gains
    for record in records:
        assert record["overshoot_n"] <= 2 * gains.tolerance_n_at(record["target_n"]), record


def test_a_fault_s_retract_uses_the_probe_s_normal_only_within_its_reach():
    """The normal of the probe in flight is handed to the toolhead's retract while the arm is
    within standoff + search + tip radius of its point; farther (moved by hand since) it is
    straight up. Either way the retract forgets it."""
    cell = make_cell()
    ex = _executor(cell)
    given = []
    ex.toolhead.safe_retract = lambda direction=None: given.append(direction)
    here = ex.toolhead.pose().position_mm
    normal = np.array([0.0, np.sin(0.2), np.cos(0.2)])
    reach_mm = ex.s.standoff_mm + ex.s.search_mm + ex.s.tip_radius_mm
    for offset_mm, expected in ((reach_mm - 1.0, normal), (reach_mm + 1.0, None)):
        ex.contact_normal_base = normal
        ex.contact_point_base_mm = here + np.array([offset_mm, 0.0, 0.0])
        ex.safe_retract()
        assert (given[-1] is None) == (expected is None)
        if expected is not None:
            np.testing.assert_array_equal(given[-1], expected)
        assert ex.contact_normal_base is None and ex.contact_point_base_mm is None
    ex.safe_retract()                                # nothing in flight: straight up
    assert given[-1] is None


def test_scan_while_moving_gives_profiles_along_the_sweep():
    cell = make_cell()
    ex = _executor(cell)
    down = probe_tcp_pose(np.array([400.0, -80.0, 170.0]), np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), 90.0)
    end = Pose(np.array([400.0, 80.0, 170.0]), down.rotation)   # tip 40 mm above the ball top
    scans, poses = ex.scan_while_moving(down, end, 150.0)
    assert len(scans) >= int(160.0 / 150.0 * cell.scanner.rate_hz)
    ys = poses[:, 1]
    assert np.all(np.diff(ys) >= -1e-9) and ys[-1] - ys[0] > 100.0
    assert sum(np.isfinite(s.z_mm).sum() for s in scans) > 1000


# Recorded after a target's 105 degree probe on generated slab 1002 and sheet 1009 (seed 1):
# the arm's joints (rad), the travel height, and the 135 degree standoff (mm, rotation vector).
WOUND_BY_THE_COLUMN = {
    "slab 1002, 339 deg": ([2.790507, -2.001782, 2.57705, -2.233654, -1.801466, 5.922116], 92.22,
                           [281.743, -13.608, 47.994], [1.769966, -1.770955, 0.718709]),
    "sheet 1009, 357 deg": ([3.092978, -2.082879, 2.646783, -2.263116, -1.856804, 6.23284], 89.12,
                            [257.469, 58.647, 35.753], [1.727317, -1.814671, 0.866098]),
}


@pytest.mark.parametrize("case", sorted(WOUND_BY_THE_COLUMN))
def test_a_wound_wrist_that_cannot_unwind_by_the_column_unwinds_farther_out(case: str):
    """After the 105 degree probe of a target ~120 mm in front of the robot, the last wrist
    joint stood at 339 (1002) or 357 deg (1009). The 135 degree approach needs it past its
    360 deg limit; unwinding in place turned the scanner into the robot's column on the
    second 120 deg leg; so every route was refused, and the target lost its 135, 155 and 170
    degree steps (28 such refusals on 7 of 12 suite objects). The arm now turns back what
    the column allows where it is, moves out from the robot with the tool as it then is,
    finishes the full turn there and goes on (at 357 deg even the move out needs the first
    leg: the joint turns a few degrees as the arm reaches out)."""
    joints_rad, travel_z_mm, standoff_mm, standoff_rotvec = WOUND_BY_THE_COLUMN[case]
    cell = make_cell(base_x_mm=700.0, home_joints_deg=tuple(np.degrees(joints_rad)))
    # The session's validator on the shipped simulated cell (its tool, keep-outs, workspace);
    # no object: the recorded routes run above it.
    validator = build_validator(load_session_inputs(ROOT / "config" / "plans" / "user_object.yaml"), cell, None)
    settings = MotionSettings(contact_force_n=0.4, contact_speed_mm_s=5.0, free_speed_mm_s=150.0,
                              free_accel_mm_s2=600.0)
    head = Toolhead(cell, settings, validator, travel_z_mm=travel_z_mm)
    here = head.pose()
    standoff_135 = Pose(np.array(standoff_mm), rotvec_to_matrix(np.array(standoff_rotvec)))
    with pytest.raises(MotionRefused, match="keep-out box 'robot_column'"):
        for a, b in head._wrist_turn_legs(here, -3, WRIST_TURN_LEG_RAD)[0]:
            validator.validate_path(a, b)
    validator.seed_joints = cell.arm.status().joints_rad
    head.travel_to(standoff_135)
    d_mm, d_deg = head.pose().distance_to(standoff_135)
    assert d_mm < 0.01 and d_deg < 0.01
    assert abs(cell.arm.status().joints_rad[5]) <= np.pi
