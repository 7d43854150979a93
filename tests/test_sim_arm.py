"""The simulated arm: refusals, timing, contact search, the force loop, protective and emergency stops."""
from __future__ import annotations

import numpy as np
import pytest

from elastoprobe.controller.core.devices import MotionState
from elastoprobe.controller.core.errors import MotionRefused
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.core.kinematics import trapezoid_state
from elastoprobe.sim.arm import trapezoid_u

from test_sim_helpers import Log, hold, make_cell, move, press, tick, wait

# The tolerance the force loop holds to, stated: every 10 ms mean of |F| within
# max(0.15 N, 1.5 % of the target) of the target over a 2 s hold.
HOLD_TOL_N = 0.15
HOLD_TOL_REL = 0.015


def test_refuses_unreachable_poses_and_limits():
    cell = make_cell()
    home = cell.arm.status().tcp_pose
    far = Pose(np.array([1500.0, 0.0, 300.0]), home.rotation)
    with pytest.raises(MotionRefused):
        cell.arm.move_linear(far, 100.0, 500.0)
    inside_base = Pose(np.array([0.0, 0.0, 200.0]), home.rotation)
    with pytest.raises(MotionRefused):
        cell.arm.move_linear(inside_base, 100.0, 500.0)
    near = Pose(home.position_mm + np.array([0.0, 0.0, -50.0]), home.rotation)
    with pytest.raises(MotionRefused):
        cell.arm.move_linear(near, 1500.0, 500.0)      # above the UR5e's 1000 mm/s
    with pytest.raises(MotionRefused):
        cell.arm.move_linear(near, 100.0, 9000.0)      # above its 5000 mm/s^2
    # Nothing moved, and the same move within limits is fine.
    assert cell.arm.status().tcp_pose.distance_to(home)[0] < 1e-9
    move(cell, near, 100.0)
    assert cell.arm.status().tcp_pose.distance_to(near)[0] < 1e-9


def test_refuses_a_path_through_the_base_even_with_reachable_ends():
    cell = make_cell()
    home = cell.arm.status().tcp_pose
    other_side = Pose(home.position_mm * np.array([-1.0, -1.0, 1.0]), home.rotation)
    assert cell.arm.inverse_kinematics(other_side) is not None
    with pytest.raises(MotionRefused):
        cell.arm.move_linear(other_side, 100.0, 500.0)


def test_vectorised_trapezoid_matches_kinematics():
    for dist, speed, accel in ((100.0, 150.0, 600.0), (5.0, 150.0, 600.0), (1.0, 0.3, 2.0)):
        ts = np.linspace(-0.1, dist / speed + speed / accel + 2.0, 400)
        u, v = trapezoid_u(ts, 0.0, dist, speed, accel)
        ref = np.array([trapezoid_state(dist, speed, accel, float(t)) for t in ts])
        assert np.allclose(u, ref[:, 0], atol=1e-9)
        assert np.allclose(v, ref[:, 1], atol=1e-9)


def test_move_takes_trapezoid_time_and_reports_progress():
    cell = make_cell()
    home = cell.arm.status().tcp_pose
    target = Pose(home.position_mm + np.array([0.0, 0.0, -100.0]), home.rotation)
    t0 = cell.clock.now_s()
    motion = cell.arm.move_linear(target, 100.0, 500.0)
    tick(cell, dt=0.5)
    assert motion.state() == MotionState.RUNNING and 0.2 < motion.progress() < 0.8
    assert cell.arm.status().is_moving
    assert wait(cell, motion) == MotionState.DONE
    expected_s = 100.0 / 100.0 + 100.0 / 500.0
    assert abs(cell.clock.now_s() - t0 - expected_s) < 0.011
    assert not cell.arm.status().is_moving


@pytest.mark.parametrize("speed_mm_s, distance_mm", [(10.0, 20.0), (1.0, 5.0), (0.3, 2.0)])
def test_seek_contact_in_free_air_ends_no_contact_after_the_distance(speed_mm_s: float, distance_mm: float) -> None:
    """It stops at its distance, not at the end of the controller's poll (10 ms later, beyond
    the line the arm validated: a protective stop)."""
    cell = make_cell()
    home = cell.arm.status().tcp_pose
    hold(cell, 0.1)
    cell.ft.tare()
    tick(cell, dt=0.0047)            # the search's end falls between two polls
    start = cell.arm.status().tcp_pose.position_mm
    oblique = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])   # positions round
    motion = cell.arm.seek_contact(oblique, speed_mm_s, 0.4, distance_mm)
    assert wait(cell, motion) == MotionState.NO_CONTACT
    hold(cell, 0.1)
    status = cell.arm.status()
    assert not status.protective_stop
    travelled = float(np.linalg.norm(status.tcp_pose.position_mm - start))
    # The distance, then the stop's deceleration: well within the travel of one 10 ms poll.
    assert distance_mm - 1e-6 < travelled < distance_mm + speed_mm_s * 0.005
    assert home.rotation.shape == (3, 3)


@pytest.mark.parametrize("obj, point, force_n", [("rubber_ball", (0.0, 0.0, 130.0), 10.0),
                                                  ("rubber_ball", (0.0, 0.0, 130.0), 20.0),
                                                  ("composite", (130.0, 0.0, 80.0), 10.0)])
def test_regulate_force_holds_within_tolerance_over_2_s(obj, point, force_n):
    cell = make_cell(obj)
    press(cell, point, (0.0, 0.0, 1.0), 90.0, force_n, settle_s=0.5)
    log = Log()
    push_before = cell.world.contact.push_mm
    hold(cell, 2.0, log)
    f = np.linalg.norm(log.forces(), axis=1)
    means = f[: f.size // 10 * 10].reshape(-1, 10).mean(axis=1)
    tol = max(HOLD_TOL_N, HOLD_TOL_REL * force_n)
    assert np.max(np.abs(means - force_n)) <= tol, (means.min(), means.max())
    if obj == "composite":
        # The foam creeps: holding the force needs the loop to keep pushing.
        assert cell.world.contact.push_mm > push_before + 0.01


def test_force_loop_state_resets_when_a_new_contact_begins():
    cell = make_cell()
    d, p, n, t = press(cell, (0.0, 0.0, 130.0), (0.0, 0.0, 1.0), 90.0, 5.0, settle_s=0.2)
    reg = cell.arm._regulator
    reg.integral = 123.0
    cell.arm._sim_contact_began()
    assert reg.integral == 0.0 and reg.last_force_n is None


def test_protective_stop_recovery_waits_5_s_and_never_clears_an_estop():
    cell = make_cell()
    cell.faults.inject("protective_stop")
    tick(cell)
    status = cell.arm.status()
    assert status.protective_stop and not status.program_running
    refused = cell.arm.move_linear(status.tcp_pose, 10.0, 100.0)
    assert refused.state() == MotionState.FAULT
    t0 = cell.clock.now_s()
    assert cell.arm.recover_protective_stop()
    assert cell.clock.now_s() - t0 >= 5.0 - 0.011
    assert not cell.arm.status().protective_stop and cell.arm.status().program_running

    cell.faults.inject("emergency_stop")
    tick(cell)
    assert cell.arm.status().emergency_stop
    assert not cell.arm.recover_protective_stop()
    hold(cell, 30.0)
    assert cell.arm.status().emergency_stop           # stays until an operator clears it
    cell.operator_clear_estop()
    assert not cell.arm.status().emergency_stop and not cell.arm.status().program_running
    assert cell.arm.recover_protective_stop()
    assert cell.arm.status().program_running
