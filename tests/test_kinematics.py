"""Arm kinematics: IK against FK over all branches, reach and limits, moveL paths,
trapezoidal timing against closed forms and numerical integration, the Jacobian."""
import math

import numpy as np
import pytest

from elastoprobe.controller.core import kinematics as kin
from elastoprobe.controller.core.geometry import Pose, interpolate_pose, rotvec_to_matrix

TOOL = Pose(np.array([0.0, 0.0, 160.0]), np.eye(3))   # the sim cell's probe: 160 mm along flange z


def _same_pose(a: Pose, b: Pose, pos_mm: float = 1e-6, rot: float = 1e-9) -> bool:
    return (np.linalg.norm(a.position_mm - b.position_mm) < pos_mm
            and np.max(np.abs(a.rotation - b.rotation)) < rot)


def _wrapped_equal(q1: np.ndarray, q2: np.ndarray, tol: float = 1e-7) -> bool:
    d = np.angle(np.exp(1j * (np.asarray(q1) - np.asarray(q2))))
    return bool(np.max(np.abs(d)) < tol)


def test_published_zero_and_home_positions():
    m = kin.ur5e()
    # At zero joints the UR5e flange sits at (a2 + a3, -(d4 + d6), d1 - d5).
    assert np.allclose(kin.forward(m, np.zeros(6)).position_mm, [-817.2, -232.9, 62.8])
    home = kin.forward(m, np.radians([0.0, -90.0, 90.0, -90.0, -90.0, 0.0]))
    assert np.allclose(home.position_mm, [-392.2 - 99.7, -133.3, 162.5 + 425.0 - 99.6])
    # The flange points straight down at home.
    assert np.allclose(home.rotation[:, 2], [0.0, 0.0, -1.0], atol=1e-12)


def test_tcp_is_flange_composed_with_tool():
    m = kin.ur5e(TOOL)
    q = np.array([0.3, -1.1, 1.4, -0.6, 0.9, 0.2])
    f = kin.forward_flange(m, q)
    assert _same_pose(kin.forward(m, q), f.compose(TOOL))
    assert np.allclose(kin.forward(m, q).position_mm - f.position_mm, 160.0 * f.rotation[:, 2])


def test_ik_round_trip_all_branches_thousands():
    m = kin.ur5e(TOOL)
    rng = np.random.default_rng(42)
    branch_counts = []
    for _ in range(1500):
        q = rng.uniform(-math.pi, math.pi, 6)
        pose = kin.forward(m, q)
        sols = kin.inverse_all(m, pose, q)
        branch_counts.append(len(sols))
        assert sols, f"no solution for a reachable pose {q}"
        # Seeded with the true joints, the nearest solution is exactly them.
        assert np.allclose(sols[0], q, atol=1e-7)
        for s in sols:
            assert _same_pose(kin.forward(m, s), pose, pos_mm=1e-6, rot=1e-9)
            assert np.all(s >= m.joint_limits_rad[:, 0]) and np.all(s <= m.joint_limits_rad[:, 1])
        # Solutions are distinct configurations (different branches), not 2 pi copies.
        for i in range(len(sols)):
            for j in range(i + 1, len(sols)):
                assert not _wrapped_equal(sols[i], sols[j], 1e-6)
    counts = np.bincount(branch_counts, minlength=9)
    assert counts[8] > 0.5 * len(branch_counts)      # most random poses have all 8 branches
    assert set(np.nonzero(counts)[0]) <= {2, 4, 6, 8}


def test_each_branch_is_returned_when_seeded_with_it():
    m = kin.ur5e(TOOL)
    pose = kin.forward(m, np.array([0.4, -1.2, 1.3, -1.5, -1.2, 0.7]))
    sols = kin.inverse_all(m, pose)
    assert len(sols) == 8
    for s in sols:
        assert np.allclose(kin.inverse(m, pose, s), s, atol=1e-9)


def test_out_of_reach_poses_return_none():
    m = kin.ur5e()
    down = np.diag([1.0, -1.0, -1.0])                # flange z pointing down
    # Far beyond the ~850 mm reach.
    for r_mm in (1100.0, 1500.0):
        for az in np.linspace(0.0, 2.0 * math.pi, 7):
            assert kin.inverse(m, Pose(np.array([r_mm * math.cos(az), r_mm * math.sin(az), 300.0]), down)) is None
    # Inside the base column: the wrist centre closer to the base axis than d4.
    assert kin.inverse(m, Pose(np.array([0.0, 0.0, 400.0]), down)) is None
    assert kin.inverse(m, Pose(np.array([50.0, -40.0, 250.0]), down)) is None
    # Straight above the shoulder beyond the stretched arm.
    assert kin.inverse(m, Pose(np.array([0.0, -150.0, 162.5 + 817.2 + 150.0]), np.eye(3))) is None
    # Comfortably reachable, for contrast.
    assert kin.inverse(m, Pose(np.array([450.0, -100.0, 300.0]), down)) is not None


def test_tightened_joint_limits_exclude_solutions():
    base = kin.ur5e(TOOL)
    q = np.array([0.5, -1.3, 1.6, -1.8, -1.57, 0.3])
    pose = kin.forward(base, q)
    sols = kin.inverse_all(base, pose, q)
    elbow_values = {round(math.sin(s[2]), 6) > 0 for s in sols}
    assert elbow_values == {True, False}
    # Elbow limited to [0, pi]: only "elbow up" branches (theta3 > 0) remain.
    lim = np.tile([-2 * math.pi, 2 * math.pi], (6, 1))
    lim[2] = [0.0, math.pi]
    m = kin.ur5e(TOOL, lim)
    got = kin.inverse_all(m, pose, q)
    assert got and all(0.0 <= s[2] <= math.pi for s in got)
    assert len(got) == sum(1 for s in sols if math.sin(s[2]) > 0)
    # A wrist 3 window that no equivalent of the needed angle can reach.
    lim2 = np.tile([-2 * math.pi, 2 * math.pi], (6, 1))
    needed = {round(float(np.angle(np.exp(1j * s[5]))), 6) for s in sols}
    lo = max(needed) + 0.2
    lim2[5] = [lo, lo + 0.3]
    assert all(not (lo <= v + 2 * math.pi * k <= lo + 0.3) for v in needed for k in (-2, -1, 0, 1, 2))
    assert kin.inverse(kin.ur5e(TOOL, lim2), pose, q) is None
    # Every joint pinned far from any solution: nothing fits.
    lim3 = np.array([[q[i] + 0.5, q[i] + 0.6] for i in range(6)])
    assert kin.inverse(kin.ur5e(TOOL, lim3), pose, q) is None


def test_wraps_by_two_pi_to_stay_in_limits_and_near_the_seed():
    m = kin.ur5e(TOOL)
    q = np.array([5.5, -1.3, 1.6, -1.8, -1.57, -5.0])       # beyond +-pi, inside +-2 pi
    pose = kin.forward(m, q)
    assert np.allclose(kin.inverse(m, pose, q), q, atol=1e-7)
    # Base limited to [0, 2 pi]: the same pose near zero seed still uses 5.5 rad, not -0.78.
    lim = np.tile([-2 * math.pi, 2 * math.pi], (6, 1))
    lim[0] = [0.0, 2 * math.pi]
    got = kin.inverse(kin.ur5e(TOOL, lim), pose, np.zeros(6))
    assert got is not None and 0.0 <= got[0] <= 2 * math.pi


def test_jacobian_matches_finite_differences():
    m = kin.ur5e(TOOL)
    rng = np.random.default_rng(7)
    for _ in range(20):
        q = rng.uniform(-3, 3, 6)
        jac = kin.jacobian(m, q)
        p0 = kin.forward(m, q)
        h = 1e-6
        for i in range(6):
            dq = np.zeros(6)
            dq[i] = h
            p1 = kin.forward(m, q + dq)
            v = (p1.position_mm - p0.position_mm) / h
            w_skew = (p1.rotation @ p0.rotation.T - np.eye(3)) / h
            w = np.array([w_skew[2, 1], w_skew[0, 2], w_skew[1, 0]])
            assert np.allclose(jac[:3, i], v, atol=1e-3)
            assert np.allclose(jac[3:, i], w, atol=1e-5)


def test_manipulability_vanishes_at_singularities():
    m = kin.ur5e(TOOL)
    regular = kin.manipulability(m, np.array([0.2, -1.3, 1.6, -1.0, 0.8, 0.5]))
    wrist = kin.manipulability(m, np.array([0.2, -1.3, 1.6, -1.0, 0.0, 0.5]))
    elbow = kin.manipulability(m, np.array([0.2, -1.3, 0.0, -1.0, 0.8, 0.5]))
    assert regular > 1e-3 and wrist < 1e-9 and elbow < 1e-9


# ---------------------------------------------------------------------------------------
# moveL paths


def test_linear_path_follows_the_line_continuously():
    m = kin.ur5e(TOOL)
    q0 = np.radians([10.0, -100.0, 100.0, -90.0, -90.0, 0.0])
    start = kin.forward(m, q0)
    end = Pose(start.position_mm + np.array([120.0, -80.0, -60.0]), rotvec_to_matrix([0.2, -0.3, 0.1]) @ start.rotation)
    path = kin.linear_path_joints(m, start, end, q0)
    assert path is not None
    assert np.allclose(path[0], q0, atol=1e-7)
    fractions = kin.path_samples(start, end, 5.0, 5.0)
    assert len(path) == len(fractions) >= 30
    for f, q in zip(fractions, path):
        assert _same_pose(kin.forward(m, q), interpolate_pose(start, end, float(f)), 1e-6, 1e-8)
    assert np.max(np.abs(np.diff(path, axis=0))) < math.radians(10.0)


def _near_wrist_singular_path(m: kin.ArmModel, miss_deg: float) -> tuple[Pose, Pose, np.ndarray]:
    """A pure rotation about the TCP that swings the tool axis past the wrist
    singularity (theta5 = 0), missing it by ``miss_deg``."""
    q_mid = np.array([0.2, -1.3, 1.6, -1.0, 0.0, 0.5])
    p = kin.forward(m, q_mid)
    a = p.rotation[:, 2]
    c = np.cross(a, [0.0, 0.0, 1.0])
    c /= np.linalg.norm(c)
    c2 = np.cross(a, c)
    r_mid = rotvec_to_matrix(math.radians(miss_deg) * c2) @ p.rotation
    start = Pose(p.position_mm, rotvec_to_matrix(math.radians(-25.0) * c) @ r_mid)
    end = Pose(p.position_mm, rotvec_to_matrix(math.radians(25.0) * c) @ r_mid)
    return start, end, kin.inverse(m, start, q_mid)


@pytest.mark.parametrize("miss_deg", [0.0, 0.5, 1.0, 3.0, 5.0])
def test_linear_path_refuses_wrist_singularity(miss_deg):
    m = kin.ur5e(TOOL)
    start, end, q0 = _near_wrist_singular_path(m, miss_deg)
    assert q0 is not None and kin.inverse(m, end, q0) is not None   # both ends are fine on their own
    assert kin.linear_path_joints(m, start, end, q0) is None


@pytest.mark.parametrize("miss_deg", [1.0, 3.0])
def test_joint_step_bound_alone_catches_the_wrist_flip(miss_deg):
    """Without the singularity margins, the wrist's half-turn between two waypoints is
    what refuses the path."""
    m = kin.ur5e(TOOL)
    start, end, q0 = _near_wrist_singular_path(m, miss_deg)
    no_margins = dict(min_wrist_deg=0.0, min_elbow_deg=0.0, min_shoulder_mm=0.0)
    assert kin.linear_path_joints(m, start, end, q0, **no_margins) is None
    fine = kin.linear_path_joints(m, start, end, q0, step_mm=0.05, step_deg=0.05,
                                  max_joint_step_rad=math.pi, **no_margins)
    assert fine is not None
    # The wrist joints really do swing by about half a turn over the path.
    assert np.ptp(fine[:, 3]) > 2.0 or np.ptp(fine[:, 5]) > 2.0


def test_linear_path_accepts_the_same_swing_far_from_the_singularity():
    m = kin.ur5e(TOOL)
    start, end, q0 = _near_wrist_singular_path(m, 35.0)
    assert kin.linear_path_joints(m, start, end, q0) is not None


def test_linear_path_refuses_crossing_the_base_column():
    """Both ends reachable, but the straight line takes the wrist centre through the
    cylinder around the base axis where no solution exists."""
    m = kin.ur5e()
    down = np.diag([1.0, -1.0, -1.0])
    start = Pose(np.array([300.0, -133.3, 300.0]), down)
    end = Pose(np.array([-300.0, -133.3, 300.0]), down)
    q0 = kin.inverse(m, start)
    assert q0 is not None and kin.inverse(m, end) is not None
    assert kin.linear_path_joints(m, start, end, q0) is None


def test_linear_path_refuses_leaving_reach_and_limits():
    m = kin.ur5e(TOOL)
    q0 = np.radians([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])
    start = kin.forward(m, q0)
    far = Pose(start.position_mm + np.array([-900.0, 0.0, 0.0]), start.rotation)
    assert kin.linear_path_joints(m, start, far, q0) is None
    # A base joint limited to +-5 deg around the start cannot follow a sideways move.
    lim = np.tile([-2 * math.pi, 2 * math.pi], (6, 1))
    lim[0] = [-math.radians(5.0), math.radians(5.0)]
    tight = kin.ur5e(TOOL, lim)
    side = Pose(start.position_mm + np.array([0.0, 200.0, 0.0]), start.rotation)
    assert kin.linear_path_joints(m, start, side, q0) is not None
    assert kin.linear_path_joints(tight, start, side, q0) is None


# ---------------------------------------------------------------------------------------
# Timing


@pytest.mark.parametrize("distance,speed,accel", [(100.0, 150.0, 600.0), (10.0, 150.0, 600.0),
                                                  (37.5, 150.0, 600.0), (500.0, 250.0, 1200.0),
                                                  (1.0, 3.0, 0.5)])
def test_trapezoid_closed_forms_and_integration(distance, speed, accel):
    total = kin.trapezoid_duration_s(distance, speed, accel)
    if distance >= speed * speed / accel:
        expected = distance / speed + speed / accel                 # trapezoid
    else:
        expected = 2.0 * math.sqrt(distance / accel)                # triangle
    assert total == pytest.approx(expected, rel=1e-12)
    # Integrate the velocity numerically: it must reach the distance exactly at the end,
    # never exceed the speed, and never change faster than the acceleration.
    t = np.linspace(0.0, total, 20001)
    states = np.array([kin.trapezoid_state(distance, speed, accel, float(ti)) for ti in t])
    pos, vel = states[:, 0], states[:, 1]
    integral = np.concatenate([[0.0], np.cumsum((vel[1:] + vel[:-1]) / 2.0 * np.diff(t))])
    assert np.max(np.abs(integral - pos)) < 1e-6 * max(distance, 1.0)
    assert pos[-1] == pytest.approx(distance) and vel[-1] == pytest.approx(0.0, abs=1e-12)
    assert np.all(vel <= speed * (1 + 1e-12)) and np.all(vel >= -1e-12)
    assert np.max(np.abs(np.diff(vel) / np.diff(t))) <= accel * (1 + 1e-6)
    assert np.all(np.diff(pos) >= -1e-12)
    # Beyond the end it stays put; a negative distance mirrors.
    assert kin.trapezoid_state(distance, speed, accel, total + 5.0) == (pytest.approx(distance), 0.0)
    p_neg, v_neg = kin.trapezoid_state(-distance, speed, accel, total / 3.0)
    p_pos, v_pos = kin.trapezoid_state(distance, speed, accel, total / 3.0)
    assert (p_neg, v_neg) == (pytest.approx(-p_pos), pytest.approx(-v_pos))


def test_trapezoid_zero_distance():
    assert kin.trapezoid_duration_s(0.0, 100.0, 100.0) == 0.0
    assert kin.trapezoid_state(0.0, 100.0, 100.0, 1.0) == (0.0, 0.0)


def test_move_duration_translation_rotation_and_joint_limits():
    m = kin.ur5e(TOOL)
    q0 = np.radians([10.0, -100.0, 100.0, -90.0, -90.0, 0.0])
    start = kin.forward(m, q0)
    end = Pose(start.position_mm + np.array([100.0, 0.0, 0.0]), start.rotation)
    # Slow translation: the TCP limit governs, exactly the trapezoid.
    assert kin.move_duration_s(m, start, end, 150.0, 600.0, seed_joints_rad=q0) == pytest.approx(
        kin.trapezoid_duration_s(100.0, 150.0, 600.0), rel=1e-9)
    # Requests above the arm's TCP limits are clamped to them.
    assert kin.move_duration_s(m, start, end, 5000.0, 5000.0, seed_joints_rad=q0) >= \
        kin.trapezoid_duration_s(100.0, 1000.0, 5000.0) - 1e-12
    # Pure rotation of 30 deg at 20 deg/s, 40 deg/s^2.
    rot_end = Pose(start.position_mm, start.rotation @ rotvec_to_matrix([0.0, 0.0, math.radians(30.0)]))
    assert kin.move_duration_s(m, start, rot_end, 150.0, 600.0, 20.0, 40.0, seed_joints_rad=q0) == pytest.approx(
        kin.trapezoid_duration_s(30.0, 20.0, 40.0), rel=1e-6)
    # The same rotation at the default rotation equivalent (100 mm per rad).
    assert kin.move_duration_s(m, start, rot_end, 150.0, 600.0, seed_joints_rad=q0) == pytest.approx(
        kin.trapezoid_duration_s(math.radians(30.0) * 100.0, 150.0, 600.0), rel=1e-6)
    # Fast tool rotation: wrist 3 alone turns 1:1 with the tool and is capped at 180 deg/s.
    t_fast = kin.move_duration_s(m, start, rot_end, 1000.0, 5000.0, 720.0, 7200.0, seed_joints_rad=q0)
    assert t_fast == pytest.approx(kin.trapezoid_duration_s(math.radians(30.0), math.pi, math.radians(800.0)),
                                   rel=1e-3)
    with pytest.raises(ValueError):
        far = Pose(start.position_mm + np.array([-900.0, 0.0, 0.0]), start.rotation)
        kin.move_duration_s(m, start, far, 150.0, 600.0, seed_joints_rad=q0)
