import numpy as np
import pytest

from elastoprobe.controller.core.geometry import Pose, probe_tcp_pose, rotvec_to_matrix, scan_direction
from elastoprobe.controller.learning.profiles import (
    ProfileGrid, average_profiles, denormalize, depth_scale_mm, mirror, mirror_angle_deg, normalize,
    profile_from_scans, resample_on_grid, scan_depths, scan_to_object_points, step_scan_points,
)

GRID = ProfileGrid(80.0, 256)
BASE_TO_OBJECT = Pose(np.array([400.0, -150.0, 80.0]), rotvec_to_matrix(np.array([0.1, -0.2, 0.7])))
# Scanner above and behind the tip on the tool's +x side, looking at it; its x-z plane is the
# tool x-z plane (a rotation about tool y), so the laser plane contains the probe axis and t.
_tilt = np.radians(-30.0)
TCP_TO_SCANNER = Pose(np.array([70.0, 0.0, -120.0]),
                      np.array([[np.cos(_tilt), 0, np.sin(_tilt)], [0, 1, 0], [-np.sin(_tilt), 0, np.cos(_tilt)]]))

P_OBJ = np.array([10.0, 20.0, 30.0])
N_OBJ = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
T_OBJ = scan_direction(N_OBJ, np.array([1.0, 0.0, 0.0]))


def dent_mm(x_mm: np.ndarray) -> np.ndarray:
    """A known asymmetric dent (mm, along -n)."""
    return 2.0 * np.exp(-((x_mm - 3.0) / 8.0) ** 2) + 0.3 * np.exp(-((x_mm + 15.0) / 5.0) ** 2)


def synth_scan(depth_fn, rng, noise_mm=0.0, angle_deg=75.0, jitter_mm=0.0, gap=None, dropout=0.0):
    """A scan (scanner x, z) of the surface p + x t - w(x) n seen from the TCP pose at this angle."""
    base_to_tcp = probe_tcp_pose(BASE_TO_OBJECT.apply(P_OBJ), BASE_TO_OBJECT.apply_vector(N_OBJ),
                                 BASE_TO_OBJECT.apply_vector(T_OBJ), angle_deg)
    if jitter_mm:
        base_to_tcp = Pose(base_to_tcp.position_mm + rng.normal(0, jitter_mm, 3),
                           base_to_tcp.rotation @ rotvec_to_matrix(rng.normal(0, 0.002, 3)))
    x = np.linspace(-50.0, 50.0, 300)
    q_obj = P_OBJ + x[:, None] * T_OBJ - depth_fn(x)[:, None] * N_OBJ
    object_to_scanner = BASE_TO_OBJECT.inverse().compose(base_to_tcp).compose(TCP_TO_SCANNER)
    # The synthetic tcp jitter tilts the laser plane slightly; keep the points where it cuts
    # the surface line (y ~ 0 is exact for the unjittered pose).
    q_sc = object_to_scanner.inverse().apply(q_obj)
    sx, sz = q_sc[:, 0].copy(), q_sc[:, 2].copy()
    sz += rng.normal(0.0, noise_mm, sz.shape)
    if gap is not None:
        sx[(x > gap[0]) & (x < gap[1])] = np.nan
    if dropout:
        sz[rng.random(sz.shape) < dropout] = np.nan
    return sx, sz, base_to_tcp


def object_points(depth_fn, rng, count, **kw):
    out = []
    for _ in range(count):
        sx, sz, pose = synth_scan(depth_fn, rng, **kw)
        out.append(scan_to_object_points(sx, sz, pose, TCP_TO_SCANNER, BASE_TO_OBJECT))
    return out


def test_grid_is_centred_and_fixed():
    x = GRID.x_mm
    assert x.shape == (256,) and x[0] == -40.0 and x[-1] == 40.0
    assert np.allclose(x, -x[::-1])


def test_known_surface_depth_reproduced_and_gap_left_nan():
    rng = np.random.default_rng(1)
    refs = object_points(lambda x: 0.0 * x, rng, 3, angle_deg=90.0)
    scans = object_points(dent_mm, rng, 10, angle_deg=75.0, gap=(5.0, 12.0), dropout=0.02)
    depth = profile_from_scans(scans, P_OBJ, N_OBJ, T_OBJ, GRID, refs)
    x = GRID.x_mm
    truth = dent_mm(x)
    in_gap = (x > 5.5) & (x < 11.5)
    seen = np.isfinite(depth)
    assert not seen[in_gap].any(), "a wide gap must stay NaN"
    assert seen[~((x > 4.5) & (x < 12.5))].all()
    assert np.max(np.abs(depth[seen] - truth[seen])) < 0.01


def test_points_survive_per_scan_pose_jitter():
    """Each scan is mapped through its own pose: jittered arm poses still give the same depth."""
    rng = np.random.default_rng(2)
    refs = object_points(lambda x: 0.0 * x, rng, 2, angle_deg=45.0, jitter_mm=0.0)
    scans = object_points(dent_mm, rng, 5, angle_deg=135.0, jitter_mm=0.3)
    d = scan_depths(scans, P_OBJ, N_OBJ, T_OBJ, GRID, refs)
    truth = dent_mm(GRID.x_mm)
    # A tilted laser plane samples a line slightly off the ideal one; the surface is
    # uniform across it here, so only in-plane errors would show.
    assert np.nanmax(np.abs(d - truth)) < 0.05


def test_averaged_noise_falls_as_one_over_sqrt_n():
    rng = np.random.default_rng(3)
    refs = object_points(lambda x: 0.0 * x, rng, 1, angle_deg=90.0)
    truth = dent_mm(GRID.x_mm)
    scans = object_points(dent_mm, rng, 256, angle_deg=90.0, noise_mm=0.05)
    d = scan_depths(scans, P_OBJ, N_OBJ, T_OBJ, GRID, refs)
    rms = {}
    for n in (4, 16, 64):
        errs = [average_profiles(d[i:i + n])[0] - truth for i in range(0, 256, n)]
        rms[n] = float(np.sqrt(np.nanmean(np.square(errs))))
    assert 1.6 < rms[4] / rms[16] < 2.5
    assert 1.6 < rms[16] / rms[64] < 2.5


def test_average_profiles_counts_and_std():
    d = np.array([[1.0, np.nan, 3.0], [3.0, np.nan, np.nan], [2.0, 5.0, np.nan]])
    mean, count, std = average_profiles(d)
    assert np.allclose(mean[[0, 2]], [2.0, 3.0]) and mean[1] == 5.0
    assert count.tolist() == [3, 1, 1]
    assert np.isclose(std[0], 1.0) and np.isnan(std[1]) and np.isnan(std[2])
    mean, count, _ = average_profiles(np.full((2, 4), np.nan))
    assert np.isnan(mean).all() and (count == 0).all()


def test_resample_does_not_extrapolate():
    grid = np.linspace(-10, 10, 21)
    out = resample_on_grid(np.array([-2.0, 0.0, 2.0]), np.array([1.0, 2.0, 3.0]), grid, max_gap_mm=5.0)
    assert np.isnan(out[grid < -2]).all() and np.isnan(out[grid > 2]).all()
    assert np.allclose(out[(grid >= -2) & (grid <= 2)], [1.0, 1.5, 2.0, 2.5, 3.0])


def test_step_scan_points_matches_single_mapping():
    rng = np.random.default_rng(4)
    sx, sz, pose = synth_scan(dent_mm, rng)
    xz = np.stack([np.column_stack([sx, sz])] * 2)
    poses = np.stack([pose.to_list()] * 2)
    pts = step_scan_points(xz, poses, TCP_TO_SCANNER, BASE_TO_OBJECT)
    one = scan_to_object_points(sx, sz, pose, TCP_TO_SCANNER, BASE_TO_OBJECT)
    assert np.allclose(pts[1], one)


def test_normalize_round_trip_and_mirror():
    d = np.array([[0.0, 1.0, 4.0], [np.nan, 2.0, 0.5]])
    s = depth_scale_mm(d)
    assert s == 4.0
    n = normalize(d, s)
    assert np.nanmax(n) == 1.0
    assert np.allclose(denormalize(n, s), d, equal_nan=True)
    with pytest.raises(ValueError):
        normalize(d, 0.0)
    x = GRID.x_mm
    p = dent_mm(x)
    m = mirror(p, x)
    assert np.allclose(m, dent_mm(-x))
    assert np.allclose(mirror(m, x), p)
    assert mirror_angle_deg(10.0) == 170.0
    # An asymmetric grid is mirrored by interpolation.
    xa = np.linspace(-20.0, 40.0, 121)
    ma = mirror(dent_mm(xa), xa)
    ok = np.isfinite(ma)
    assert ok.sum() > 60 and np.allclose(ma[ok], dent_mm(-xa[ok]), atol=1e-2)
