"""Point clouds: loading, table removal, normals and curvature, ICP and mesh registration,
judged against known geometry and known transforms."""
import numpy as np
import pytest
import trimesh

from elastoprobe.controller.core.errors import InputError
from elastoprobe.controller.core.geometry import Pose, rotvec_to_matrix
from elastoprobe.controller.learning.cloud import (
    box_on_pillow_mesh, cloud_hash, curvature, estimate_normals, icp, load_cloud, local_geometry,
    register_mesh_to_cloud, remove_table, sample_mesh,
)

TRUE_POSE = Pose(np.array([8.0, -5.0, 3.0]), rotvec_to_matrix(np.radians(4.0) * np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])))


def rms_pose_error_mm(estimate: Pose, truth: Pose, points: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((estimate.apply(points) - truth.apply(points)) ** 2, axis=1))))


@pytest.fixture(scope="module")
def mesh():
    # Off-centre box: the object has no symmetry that would make the pose ambiguous.
    return box_on_pillow_mesh(box_centre_mm=(40.0, 20.0))


def noisy_samples(mesh, n, seed, noise_mm=0.1):
    pts, nrm = sample_mesh(mesh, n, seed)
    return pts + np.random.default_rng(seed).normal(0, noise_mm, pts.shape), nrm


def test_icp_recovers_a_known_rigid_transform(mesh):
    source, _ = noisy_samples(mesh, 20_000, seed=1)
    target, _ = noisy_samples(mesh, 60_000, seed=2)  # different samples: no point-to-point twins
    target = TRUE_POSE.apply(target)
    target_normals = estimate_normals(target, k=16)
    pose, rms_mm, iterations = icp(source, target, None, max_iter=60, target_normals=target_normals)
    assert rms_pose_error_mm(pose, TRUE_POSE, source) < 0.5
    assert rms_mm < 0.5 and 1 < iterations <= 60
    # The same without normals (point-to-point) still gets close.
    pose_pp, _, _ = icp(source, target, None, max_iter=80)
    assert rms_pose_error_mm(pose_pp, TRUE_POSE, source) < 1.5


LARGE_TURN = Pose(np.array([100.0, -50.0, 20.0]), rotvec_to_matrix(np.radians(170.0) * np.array([0.1, 0.05, 1.0])
                                                                  / np.linalg.norm([0.1, 0.05, 1.0])))


@pytest.mark.parametrize("truth", [TRUE_POSE, LARGE_TURN], ids=["small", "half_turn"])
def test_register_mesh_to_cloud_without_init(mesh, truth):
    """A half turn is beyond plain ICP's reach: the PCA-axis starts find it."""
    cloud, _ = noisy_samples(mesh, 40_000, seed=3)
    cloud = truth.apply(cloud)
    pose, rms_mm = register_mesh_to_cloud(mesh, cloud, init=None, seed=0)
    assert rms_pose_error_mm(pose, truth, np.asarray(mesh.vertices)) < 0.5
    assert rms_mm < 0.5


def test_icp_with_outliers_is_trimmed(mesh):
    source, _ = noisy_samples(mesh, 20_000, seed=4)
    target, _ = noisy_samples(mesh, 60_000, seed=5)
    rng = np.random.default_rng(0)
    clutter = rng.uniform([-300, -300, 0], [300, 300, 200], (3_000, 3))  # points of another object
    source = np.vstack([source, clutter])
    target = TRUE_POSE.apply(target)
    pose, _, _ = icp(source, target, None, target_normals=estimate_normals(target), trim_fraction=0.2)
    assert rms_pose_error_mm(pose, TRUE_POSE, source[:20_000]) < 0.5


def test_remove_table_keeps_the_object_and_drops_the_plane(mesh):
    obj, _ = noisy_samples(mesh, 40_000, seed=6, noise_mm=0.2)
    rng = np.random.default_rng(1)
    table = np.c_[rng.uniform(-450, 450, (60_000, 2)), rng.normal(0, 0.2, 60_000)]
    table = table[~((np.abs(table[:, 0]) < 200) & (np.abs(table[:, 1]) < 150))]  # under the pillow: hidden
    tilt = Pose(np.array([0.0, 0.0, -30.0]), rotvec_to_matrix(np.radians([3.0, -2.0, 20.0])))
    scene = tilt.apply(np.vstack([obj, table]))
    is_obj = np.r_[np.ones(len(obj), bool), np.zeros(len(table), bool)]
    height_mm = np.r_[obj[:, 2], table[:, 2]]  # above the table, in the untilted frame
    kept, (normal, offset_mm) = remove_table(scene, distance_threshold_mm=1.5, seed=0)
    true_normal = tilt.rotation[:, 2]
    assert np.degrees(np.arccos(np.clip(normal @ true_normal, -1, 1))) < 0.5
    assert abs(offset_mm - true_normal @ tilt.position_mm) < 0.3
    kept_set = {tuple(p) for p in np.round(kept, 6)}
    in_kept = np.array([tuple(p) in kept_set for p in np.round(scene, 6)])
    assert in_kept[~is_obj].mean() < 0.002  # table gone
    assert in_kept[is_obj & (height_mm > 3.0)].mean() > 0.995  # object kept
    # With an up hint it finds the same plane and orients it the same way.
    _, (normal_up, _) = remove_table(scene, 1.5, seed=1, up=np.array([0.0, 0.0, 1.0]))
    assert normal_up @ true_normal > 0.9999


def test_normals_outward_and_curvature_on_known_shapes():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    pts, _ = sample_mesh(sphere, 20_000, seed=0)
    normals, curv = local_geometry(pts, k=16)
    radial = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    assert np.min(np.einsum("ij,ij->i", normals, radial)) > 0.98
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(0, 100, (5_000, 2)), np.zeros(5_000)]
    toward = estimate_normals(plane, viewpoint_mm=np.array([50.0, 50.0, -500.0]))
    assert np.all(toward[:, 2] < -0.999)  # toward a viewpoint below
    flat_curv = curvature(plane)
    box = trimesh.creation.box(extents=[60.0, 60.0, 60.0])
    bpts, _ = sample_mesh(box, 30_000, seed=1)
    bcurv = curvature(bpts)
    on_edge = np.sum(np.abs(bpts) > 28.5, axis=1) >= 2  # within 1.5 mm of two faces
    mid_face = np.sum(np.abs(bpts) < 20.0, axis=1) == 2
    assert flat_curv.max() < 1e-6 and np.median(curv) < 2e-3
    assert np.median(bcurv[on_edge]) > 20 * max(np.median(bcurv[mid_face]), 1e-6)
    assert np.median(bcurv[on_edge]) > 0.02


def test_load_cloud_formats(tmp_path, mesh):
    for suffix in ("stl", "ply", "obj"):
        path = tmp_path / f"object.{suffix}"
        mesh.export(path)
        pts, nrm = load_cloud(path, n_samples=5_000, seed=3)
        assert pts.shape == (5_000, 3) and nrm.shape == (5_000, 3)
        assert np.all(pts.min(axis=0) >= mesh.bounds[0] - 1e-6) and np.all(pts.max(axis=0) <= mesh.bounds[1] + 1e-6)
        again, _ = load_cloud(path, n_samples=5_000, seed=3)
        np.testing.assert_array_equal(pts, again)  # seeded sampling
    xyz = tmp_path / "cloud.xyz"
    data = np.c_[np.arange(12.0).reshape(4, 3), np.tile([0.0, 0.0, 2.0], (4, 1))]
    np.savetxt(xyz, data)
    pts, nrm = load_cloud(xyz)
    np.testing.assert_allclose(pts, data[:, :3])
    np.testing.assert_allclose(nrm, np.tile([0.0, 0.0, 1.0], (4, 1)))
    cloud_ply = tmp_path / "cloud.ply"
    trimesh.PointCloud(data[:, :3]).export(cloud_ply)
    pts, nrm = load_cloud(cloud_ply)
    np.testing.assert_allclose(pts, data[:, :3])
    assert nrm is None
    for encoding in ("ascii", "binary_little_endian"):
        with_normals = tmp_path / f"normals_{encoding}.ply"
        write_ply_with_normals(with_normals, data[:, :3], data[:, 3:], encoding)
        pts, nrm = load_cloud(with_normals)
        np.testing.assert_allclose(pts, data[:, :3])
        np.testing.assert_allclose(nrm, np.tile([0.0, 0.0, 1.0], (4, 1)))
    bad = tmp_path / "bad.xyz"
    bad.write_text("1 2\n3 4\n")
    with pytest.raises(InputError, match="bad.xyz"):
        load_cloud(bad)
    with pytest.raises(InputError):
        load_cloud(tmp_path / "missing.ply")


def write_ply_with_normals(path, pts, nrm, encoding):
    header = (f"ply\nformat {encoding} 1.0\nelement vertex {len(pts)}\n"
              + "".join(f"property float {k}\n" for k in ("x", "y", "z", "nx", "ny", "nz")) + "end_header\n")
    rows = np.hstack([pts, nrm]).astype("<f4")
    with open(path, "wb") as f:
        f.write(header.encode())
        if encoding == "ascii":
            f.write("".join(" ".join(map(str, r)) + "\n" for r in rows).encode())
        else:
            f.write(rows.tobytes())


def test_cloud_hash_is_stable_and_sensitive():
    pts = np.random.default_rng(0).normal(0, 50, (1000, 3))
    h = cloud_hash(pts)
    assert h == cloud_hash(pts.astype(np.float32)) == cloud_hash(pts.copy())
    assert len(h) == 64
    moved = pts.copy()
    moved[10, 2] += 0.01
    assert cloud_hash(moved) != h


def raster_scan_of_plane(normal: np.ndarray, noise_mm: float, seed: int) -> np.ndarray:
    """A laser-line raster of a plane as the demo's sweep makes it: profiles 0.55 mm apart
    along x, lines 4 mm apart along y, every line scanned twice (both sweep headings land
    on the same y when the scanner is calibrated), depth noise along the plane's normal."""
    rng = np.random.default_rng(seed)
    xs, ys = np.arange(-60.0, 60.0, 0.55), np.arange(-60.0, 60.0, 4.0)
    gx, gy = np.meshgrid(xs, ys)
    flat = np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]
    flat = np.vstack([flat, flat])                      # both headings
    flat[:, 2] += rng.normal(0.0, noise_mm, len(flat))
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, normal)
    if np.linalg.norm(axis) < 1e-12:
        return flat
    angle = np.arccos(np.clip(z @ normal, -1.0, 1.0))
    return flat @ rotvec_to_matrix(axis / np.linalg.norm(axis) * angle).T


@pytest.mark.parametrize("normal", [np.array([0.0, 0.0, 1.0]),
                                    np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])])
@pytest.mark.parametrize("noise_mm", [0.03, 0.12])
def test_normals_of_a_raster_scan_whose_neighbourhoods_are_single_lines(normal, noise_mm):
    # The 16 nearest neighbours of a point lie on its own profile line (and its twin
    # from the other heading): a line, whose PCA "normal" is any direction across it —
    # the demo's calibrated cell got (0, -1, 0) on 74 % of the box top, which then
    # counted as an unprobeable wall. Such a neighbourhood must be widened until it
    # spans the surface.
    pts = raster_scan_of_plane(normal, noise_mm, seed=5)
    normals = estimate_normals(pts, k=16, viewpoint_mm=normal * 1000.0)
    cos = np.einsum("ij,j->i", normals, normal)
    assert np.min(cos) > 0.99, f"{np.mean(cos < 0.99):.1%} of the normals off by more than 8 deg"
    curv = curvature(pts, k=16)
    assert np.percentile(curv, 99) < 0.01        # a plane: flat wherever the neighbourhood spans it


def swept_dome_on_table(noise_mm: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A raster scan (profiles 3 mm apart along y, 0.5 mm samples along x) of a table with a
    spherical cap on it whose rim meets the table at 25 degrees (radius 100 mm): the points
    (N, 3) mm with noise, and which of them lie on the cap."""
    rim_mm, slope_deg = 100.0, 25.0
    sphere_r = rim_mm / np.sin(np.radians(slope_deg))
    x, y = np.meshgrid(np.arange(-160.0, 160.0, 0.5), np.arange(-160.0, 160.0, 3.0))
    x, y = x.ravel(), y.ravel()
    r2 = x ** 2 + y ** 2
    z = np.where(r2 < rim_mm ** 2, np.sqrt(np.maximum(sphere_r ** 2 - r2, 0.0)) - sphere_r * np.cos(np.radians(slope_deg)), 0.0)
    z = z + np.random.default_rng(seed).normal(0.0, noise_mm, z.shape)
    return np.column_stack([x, y, z]), r2 < rim_mm ** 2


@pytest.mark.parametrize("noise_mm", [0.01, 0.08])
def test_table_removal_keeps_the_foot_of_a_face_sloping_onto_the_table(noise_mm):
    # The suite's dome 1007 lost the band of its top within 2 mm of the table (4 mm wide at
    # 25 degrees, 7.5 % of the top surface, never seen by the map). What the object reaches
    # down to stays; the table, and its lone high readings away from the object, go.
    from elastoprobe.controller.phases import remove_table_below

    pts, on_cap = swept_dome_on_table(noise_mm, seed=3)
    spikes = np.flatnonzero(~on_cap & (np.hypot(pts[:, 0], pts[:, 1]) > 130.0))[::997]
    pts[spikes, 2] += 1.0                       # scattered returns 1 mm above the table
    kept, (normal, offset) = remove_table_below(pts, seed=1, link_mm=4.5)
    assert normal[2] > 0.999 and abs(offset) < 0.2
    kept_set = {tuple(p) for p in np.round(kept, 6)}
    is_kept = np.array([tuple(p) in kept_set for p in np.round(pts, 6)])
    # Every cap point clear of the table's scatter (its floor at about 6 sigma, and 4 sigma of
    # its own noise) is kept: the foot band too.
    assert is_kept[on_cap & (pts[:, 2] > 10.0 * noise_mm)].all()
    assert np.count_nonzero(is_kept & on_cap & (pts[:, 2] < 2.0)) > 1000
    # Nothing of the table: neither its spikes nor its readings around the rim.
    assert not is_kept[spikes].any()
    assert np.count_nonzero(is_kept & ~on_cap) == 0
