"""Simulated objects: files, geometry queries, region blending, permanent dents, validity, bad input."""
from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

from elastoprobe.controller.core.errors import InputError
from elastoprobe.sim import objects as sim_objects
from elastoprobe.sim.objects import load_object

OBJECTS = Path(__file__).resolve().parents[1] / "config" / "objects"
X_MM = np.linspace(-40.0, 40.0, 257)
UP = np.array([0.0, 0.0, 1.0])


def test_shipped_objects_rest_on_the_table_and_name_their_regions(ball, composite, user_object):
    assert ball.region_names == ["rubber"]
    assert composite.region_names == ["cardboard", "foam"]
    assert user_object.region_names == ["elastomer", "sponge"]
    for obj in (ball, composite, user_object):
        assert obj.mesh.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-6)
        on_table = (obj.mesh.triangles[:, :, 2].max(axis=1) < 1e-3) & (obj.mesh.face_normals[:, 2] < -0.99)
        assert not np.any(on_table)
        assert [m.name for m in obj.materials] == obj.region_names


def test_validity_is_clean_at_the_plans_largest_force_and_not_at_an_absurd_one(ball, composite, user_object):
    for obj in (ball, composite, user_object):
        assert obj.validity_report(40.0, 5.0) == []
        problems = obj.validity_report(1000.0, 5.0)
        assert problems and all(isinstance(p, str) for p in problems)
    # Each composite region says what is wrong with it.
    text = "\n".join(composite.validity_report(1000.0, 5.0))
    assert "cardboard" in text and "foam" in text and "densification" in text


def test_closest_surface_is_exact_against_brute_force(composite):
    rng = np.random.default_rng(3)
    points = np.concatenate([composite.mesh.sample(150, seed=4) + rng.normal(0.0, 3.0, (150, 3)),
                             rng.uniform([-220, -170, 0], [220, 170, 160], (50, 3))])
    closest, normals, labels = composite.closest_surface(points)
    tris = composite.mesh.triangles
    for p, c in zip(points, closest):
        best = np.linalg.norm(trimesh.triangles.closest_point(tris, np.repeat(p[None], len(tris), 0)) - p, axis=1).min()
        assert np.linalg.norm(c - p) == pytest.approx(best, abs=1e-9)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)


def test_closest_surface_in_small_chunks_is_the_one_pass_answer(composite, monkeypatch):
    """Memory stays bounded on large queries: the candidates are measured a few at a time, and
    the answer is the one pass's, point for point (ties broken the same way)."""
    rng = np.random.default_rng(5)
    points = np.concatenate([composite.mesh.sample(2000, seed=6) + rng.normal(0.0, 2.0, (2000, 3)),
                             rng.uniform([-220, -170, 0], [220, 170, 160], (500, 3))])
    whole = composite.closest_surface(points)
    monkeypatch.setattr(sim_objects, "CLOSEST_CHUNK_PAIRS", 101)
    monkeypatch.setattr(sim_objects, "CLOSEST_CHUNK_POINTS", 7)
    for a, b in zip(whole, composite.closest_surface(points)):
        np.testing.assert_array_equal(a, b)


def test_ball_surface_is_the_true_sphere(ball):
    points = np.array([[0, 0, 200.0], [100, 0, 65.0], [10, 20, 70.0]])
    closest, normals, labels = ball.closest_surface(points)
    np.testing.assert_allclose(np.linalg.norm(closest - [0, 0, 65.0], axis=1), 65.0)
    np.testing.assert_allclose(normals, (closest - [0, 0, 65.0]) / 65.0)
    assert np.all(labels == 0)


def test_region_of_gives_the_true_material(composite, user_object):
    labels = composite.region_of(np.array([[0, 0, 141.0], [79, 0, 120.0], [150, 0, 81.0], [0, 140, 81.0]]))
    assert labels.tolist() == [0, 0, 1, 1]
    assert user_object.region_of(np.array([[-30, 0, 41.0], [30, 0, 41.0]])).tolist() == [0, 1]


def crossing(obj, path, force_n=20.0):
    """Peak depth along a path crossing a boundary, the claimed bound on its slope, and the slope."""
    peaks, diffs, comp_peaks = [], [], []
    for point, normal, t in path:
        model = obj.contact_model(point, normal, t, 90.0, 5.0)
        parts = model.component_profiles_mm(X_MM, force_n)
        peaks.append(model.depth_profile_mm(X_MM, force_n).max())
        diffs.append(np.max(np.abs(parts[0] - parts[-1])))
        comp_peaks.append([p.max() for p in parts] if len(parts) == 2 else [parts[0].max()] * 2)
    return np.array(peaks), np.array(diffs), np.array(comp_peaks)


def corner_path(step_mm: float):
    """Across the box's bottom edge: on the pillow toward the wall, then up the wall."""
    path, s_values = [], np.arange(-6.0, 6.0 + 1e-9, step_mm)
    for s in s_values:
        if s <= 0:
            path.append((np.array([80.0 - s, 10.0, 80.0]), UP, np.array([0.0, 1.0, 0.0])))
        else:
            path.append((np.array([80.0, 10.0, 80.0 + s]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])))
    return s_values, path


@pytest.mark.parametrize("which", ["composite", "user_object"])
def test_peak_depth_changes_across_a_boundary_within_the_stated_bound(which, composite, user_object):
    step = 0.1
    if which == "composite":
        obj = composite
        s_values, path = corner_path(step)
    else:
        obj = user_object
        s_values = np.arange(-6.0, 6.0 + 1e-9, step)
        path = [(np.array([s, 5.0, 40.0]), UP, np.array([1.0, 0.0, 0.0])) for s in s_values]
    peaks, diffs, comp_peaks = crossing(obj, path)
    slope = np.abs(np.diff(peaks)) / step
    # The docstring's bound: 1.5 / blend width * max |profile_A - profile_B| + the components' own slopes.
    intrinsic = np.max(np.abs(np.diff(comp_peaks, axis=0)), axis=1) / step
    bound = 1.5 / obj.blend_width_mm * np.maximum(diffs[1:], diffs[:-1]) + intrinsic
    assert np.all(slope <= bound * (1 + 1e-6) + 1e-9)
    # It does change (the two materials differ) and it is continuous (no jump at the boundary).
    assert abs(peaks[0] - peaks[-1]) > 1.0
    assert slope.max() < 1.5 / obj.blend_width_mm * diffs.max() * 1.05 + intrinsic.max()


def test_cardboard_keeps_a_dent_above_its_yield_force(composite):
    composite.reset_history()
    point = np.array([20.0, 10.0, 140.0])
    t = np.array([1.0, 0.0, 0.0])
    before = composite.true_profile_mm(point, UP, t, 20.0, 90.0, X_MM, 5.0)
    composite.add_permanent_dent(point, UP, 25.0)                     # below yield: nothing
    assert composite.contact_model(point, UP, t, 90.0, 5.0).depth_profile_mm(X_MM, 0.0).max() == 0.0
    composite.add_permanent_dent(point, UP, 45.0)
    residual = composite.contact_model(point, UP, t, 90.0, 5.0).depth_profile_mm(X_MM, 0.0)
    assert residual.max() == pytest.approx(0.02 * (45.0 - 32.0), rel=0.05)
    assert abs(X_MM[np.argmax(residual)]) < 0.5
    after = composite.true_profile_mm(point, UP, t, 20.0, 90.0, X_MM, 5.0)
    assert after.max() > before.max()                                 # crushed flutes: softer
    far = np.array([-50.0, -50.0, 140.0])
    assert composite.contact_model(far, UP, t, 90.0, 5.0).depth_profile_mm(X_MM, 0.0).max() < 1e-9
    composite.add_permanent_dent(np.array([150.0, 0.0, 80.0]), UP, 45.0)   # foam does not yield
    assert composite.contact_model(np.array([150.0, 0.0, 80.0]), UP, t, 90.0, 5.0).depth_profile_mm(X_MM, 0.0).max() == 0.0
    composite.reset_history()
    np.testing.assert_allclose(composite.true_profile_mm(point, UP, t, 20.0, 90.0, X_MM, 5.0), before)


def test_ground_truth_is_the_equilibrium_profile(ball):
    top, t = np.array([0.0, 0.0, 130.0]), np.array([0.0, 1.0, 0.0])
    truth = ball.true_profile_mm(top, UP, t, 20.0, 45.0, X_MM, 5.0)
    model = ball.contact_model(top, UP, t, 45.0, 5.0)
    np.testing.assert_allclose(truth, model.depth_profile_mm(X_MM, 20.0, hold_s=float("inf")))
    assert ball.contact_model(top, UP, t, 45.0, 5.0) is model                  # cached


# ----------------------------------------------------------------------------- bad files

BALL_OK = """\
name: ball
ball:
  radius_mm: 65.0
  material: rubber
materials:
  rubber:
    kind: elastic
    E_mpa: 10.0
    nu: 0.49
    friction_mu: 0.8
"""

BAD_CASES = [
    ("unknown key", BALL_OK.replace("    nu: 0.49\n", "    nu: 0.49\n    colour: red\n"), 10, 5, "unknown key"),
    ("negative modulus", BALL_OK.replace("E_mpa: 10.0", "E_mpa: -1.0"), 8, 12, "E_mpa"),
    ("string number", BALL_OK.replace("E_mpa: 10.0", "E_mpa: '10'"), 8, 12, "E_mpa"),
    ("unknown material", BALL_OK.replace("  material: rubber", "  material: steel"), 4, 13, "unknown material 'steel'"),
    ("wrong kind", BALL_OK.replace("kind: elastic", "kind: foam\n    thickness_mm: 50.0\n    decay_length_mm: 10.0\n"
                                   "    densification_strain: 0.7\n    densification_exponent: 1.5"), 4, 13, "must be 'elastic'"),
    ("two shapes", BALL_OK.replace("materials:", "mesh:\n  file: x.ply\nmaterials:"), 5, 1, "exactly one"),
    ("no shape", BALL_OK.replace("ball:\n  radius_mm: 65.0\n  material: rubber\n", ""), 1, 1, "exactly one"),
    ("unused material", BALL_OK + "  spare:\n    kind: elastic\n    E_mpa: 1.0\n    nu: 0.3\n    friction_mu: 0.5\n",
     11, 3, "not used"),
    ("foam without layer", BALL_OK.replace("kind: elastic", "kind: foam"), 7, 5, "thickness_mm"),
    ("bad name", BALL_OK.replace("name: ball", "name: Big Ball"), 1, 7, "name"),
    ("duplicate key", BALL_OK.replace("  radius_mm: 65.0\n", "  radius_mm: 65.0\n  radius_mm: 60.0\n"), 4, 3, "duplicate"),
]


@pytest.mark.parametrize("label,text,line,col,message", BAD_CASES, ids=[c[0] for c in BAD_CASES])
def test_bad_object_files_fail_at_their_line_and_column(tmp_path, label, text, line, col, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as info:
        load_object(path)
    first = str(info.value).splitlines()[0]
    assert re.match(rf"^{re.escape(str(path))}:{line}:{col}: ", first), first
    assert message in str(info.value)


def test_the_good_twin_of_the_bad_files_loads(tmp_path):
    path = tmp_path / "ok.yaml"
    path.write_text(BALL_OK)
    assert load_object(path).region_names == ["rubber"]


def test_mesh_object_errors_name_the_mesh_entry(tmp_path):
    text = (OBJECTS / "user_object.yaml").read_text()
    (tmp_path / "o.yaml").write_text(text.replace("file: user_object.ply", "file: missing.ply"))
    with pytest.raises(InputError, match=r"o\.yaml:12:9: mesh file .* does not exist"):
        load_object(tmp_path / "o.yaml")
    shutil.copy(OBJECTS / "user_object.ply", tmp_path / "user_object.ply")
    (tmp_path / "o.yaml").write_text(text.replace("face_color_rgb: [60, 60, 70]", "face_color_rgb: [61, 60, 70]"))
    with pytest.raises(InputError, match=r"o\.yaml:17:42: no face of the mesh has the colour \[61, 60, 70\] "
                                         r"\(material 'sponge'\); the mesh's colours: \[60, 60, 70\] on 520 faces"):
        load_object(tmp_path / "o.yaml")
