import numpy as np
import pytest

from elastoprobe.controller.core.geometry import (
    NINE_ANGLES_DEG, Pose, interpolate_pose, matrix_to_rotvec, probe_axis, probe_tcp_pose,
    push_direction, rotvec_to_matrix, scan_direction,
)


def test_rotvec_round_trip_including_pi():
    rng = np.random.default_rng(0)
    for _ in range(500):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(0.0, np.pi)
        r = axis * angle
        m = rotvec_to_matrix(r)
        assert np.allclose(m @ m.T, np.eye(3), atol=1e-12)
        assert np.allclose(rotvec_to_matrix(matrix_to_rotvec(m)), m, atol=1e-8)
    m = rotvec_to_matrix(np.array([0.0, 0.0, np.pi]))
    assert np.allclose(rotvec_to_matrix(matrix_to_rotvec(m)), m, atol=1e-8)


def test_ur_pose_units_and_inverse():
    pose = Pose.from_ur([0.1, -0.2, 0.3, 0.1, 0.2, -0.3])
    assert np.allclose(pose.position_mm, [100.0, -200.0, 300.0])
    assert np.allclose(pose.to_ur(), [0.1, -0.2, 0.3, 0.1, 0.2, -0.3])
    ident = pose.compose(pose.inverse())
    assert np.allclose(ident.matrix(), np.eye(4), atol=1e-12)
    pts = np.array([[1.0, 2.0, 3.0], [-4.0, 0.0, 9.0]])
    assert np.allclose(pose.inverse().apply(pose.apply(pts)), pts)


def test_angle_convention_of_fig5():
    n = np.array([0.0, 0.0, 1.0])
    t = np.array([1.0, 0.0, 0.0])
    # 90 degrees pushes straight down, against the normal.
    assert np.allclose(push_direction(t, n, 90.0), [0.0, 0.0, -1.0], atol=1e-12)
    # Under 90 degrees the push has a +t component (the dent is deeper toward +t).
    assert push_direction(t, n, 10.0)[0] > 0.9
    assert push_direction(t, n, 170.0)[0] < -0.9
    # The probe body lies on the far left (-t) at small angles.
    assert probe_axis(t, n, 10.0)[0] < 0
    for a in NINE_ANGLES_DEG:
        pose = probe_tcp_pose(np.zeros(3), n, t, a, offset_mm=20.0)
        assert np.isclose(np.linalg.det(pose.rotation), 1.0)
        assert np.allclose(pose.rotation[:, 2], push_direction(t, n, a))
        # tool x stays in the (t, n) plane: the laser plane contains the probe axis and t
        assert abs(pose.rotation[1, 0]) < 1e-12
        # ... perpendicular to the probe, on the side away from the surface (scanner above)
        assert abs(np.dot(pose.rotation[:, 0], pose.rotation[:, 2])) < 1e-12
        assert np.dot(pose.rotation[:, 0], n) >= -1e-12
        assert np.allclose(pose.position_mm, 20.0 * probe_axis(t, n, a))


def test_scan_direction_is_tangent_and_stable():
    n = np.array([0.0, 0.6, 0.8])
    t = scan_direction(n, np.array([1.0, 0.0, 0.0]))
    assert abs(np.dot(t, n)) < 1e-12 and np.isclose(np.linalg.norm(t), 1.0)
    t2 = scan_direction(np.array([1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    assert abs(t2[0]) < 1e-12
    with pytest.raises(ValueError):
        scan_direction(np.zeros(3), np.array([1.0, 0.0, 0.0]))


def test_interpolate_pose_endpoints():
    a = Pose.from_ur([0, 0, 0, 0, 0, 0])
    b = Pose.from_ur([0.1, 0, 0, 0, 0, 1.0])
    assert np.allclose(interpolate_pose(a, b, 0.0).matrix(), a.matrix())
    assert np.allclose(interpolate_pose(a, b, 1.0).matrix(), b.matrix())
    mid = interpolate_pose(a, b, 0.5)
    assert np.allclose(matrix_to_rotvec(mid.rotation), [0, 0, 0.5])


def test_rotvec_of_a_nearly_orthogonal_matrix_near_pi():
    """Generated object 1003, target 46: a 90-degree probe on a flat top with the stored normal
    and scan direction (rounded to 9 digits, so the matrix is orthogonal only to ~4e-9) is a
    rotation 6e-6 rad short of pi. Its rotation vector must give back the same rotation: the
    trace-based angle gave 0.85 rad, the recorded scan poses were tilted 54 degrees, the
    scans fell 30 mm off the object and the placement check paused the session
    (a false object_moved)."""
    normal = np.array([0.00801757, 0.00801548, 0.99993573])
    t = np.array([-6.42670000e-05, 9.99967876e-01, -8.01521800e-03])
    pose = probe_tcp_pose(np.array([-56.79479, -63.281301, 26.7412]), normal, t, 90.0, offset_mm=15.0)
    assert abs(np.linalg.norm(matrix_to_rotvec(pose.rotation)) - np.pi) < 1e-4
    back = Pose.from_list(pose.to_list())
    assert np.abs(back.rotation - pose.rotation).max() < 1e-7
    assert np.abs(Pose.from_ur(pose.to_ur()).rotation - pose.rotation).max() < 1e-7


def test_rotvec_round_trip_of_perturbed_matrices_at_every_angle():
    """Matrices orthogonal only to ~1e-9 (sums of rounded inputs) round-trip to ~1e-9 at any
    angle, near 0 and within 1e-12..1e-2 rad of pi included."""
    rng = np.random.default_rng(3)
    for k in range(3000):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = (rng.uniform(0.0, np.pi), np.pi - 10 ** rng.uniform(-12, -2), 10 ** rng.uniform(-14, -3))[k % 3]
        m = rotvec_to_matrix(axis * angle) + rng.normal(size=(3, 3)) * 1e-9
        r = matrix_to_rotvec(m)
        assert np.linalg.norm(r) <= np.pi + 1e-9
        assert np.abs(rotvec_to_matrix(r) - m).max() < 2e-8, (angle, r)
