"""Checks of a user's mesh (controller/core/meshcheck.py): what cannot be used is refused with a
reason, what can be used but should be known is a warning that says where (mm)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from elastoprobe.controller.core.meshcheck import (bounds_problem, degenerate_faces, drop_degenerate_faces,
                                              mesh_findings, read_mesh)


def _box() -> trimesh.Trimesh:
    """A closed 100 x 60 x 40 mm box resting on the table (z from 0)."""
    m = trimesh.creation.box(extents=(100.0, 60.0, 40.0))
    m.apply_translation([0.0, 0.0, 20.0])
    return m


def test_a_closed_mesh_has_nothing_to_say() -> None:
    found = mesh_findings(_box())
    assert found.errors == [] and found.warnings == []


def test_an_open_bottom_on_the_table_is_not_a_hole_but_an_open_top_is() -> None:
    box = _box()
    down = box.face_normals[:, 2] < -0.99
    open_bottom = trimesh.Trimesh(box.vertices, box.faces[~down], process=False)
    assert mesh_findings(open_bottom).warnings == []
    up = box.face_normals[:, 2] > 0.99
    open_top = trimesh.Trimesh(box.vertices, box.faces[~up], process=False)
    warnings = mesh_findings(open_top).warnings
    assert len(warnings) == 1 and "1 holes" in warnings[0]
    assert "(0, 0, 40) mm" in warnings[0] and "largest 100 mm across" in warnings[0]


def test_non_manifold_edges_and_degenerate_faces_are_warned_with_where() -> None:
    box = _box()
    a, b = box.faces[0][:2]
    v = np.vstack([box.vertices, box.vertices[a] + [0.0, 0.0, 30.0], box.vertices[b]])
    fin = [a, b, len(box.vertices)]
    sliver = [a, a, len(box.vertices) + 1]          # two corners in one point: no area
    mesh = trimesh.Trimesh(v, np.vstack([box.faces, fin, sliver]), process=False)
    found = mesh_findings(mesh)
    assert found.errors == []
    text = " ".join(found.warnings)
    assert "1 non-manifold edges" in text and "1 degenerate faces" in text
    cleaned, kept = drop_degenerate_faces(mesh)
    assert kept.sum() == len(mesh.faces) - 1 and not degenerate_faces(cleaned).any()


def test_a_mesh_without_area_is_an_error() -> None:
    box = _box()
    flat = trimesh.Trimesh(np.tile(box.vertices[:1], (len(box.vertices), 1)), box.faces, process=False)
    assert "all 12 faces are degenerate" in mesh_findings(flat).errors[0]


def test_unreadable_and_broken_files_are_refused(tmp_path: Path) -> None:
    (tmp_path / "junk.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    with pytest.raises(ValueError, match="cannot read mesh|no triangles"):
        read_mesh(tmp_path / "junk.ply")
    box = _box()
    v = np.array(box.vertices)
    v[3, 1] = np.inf
    trimesh.Trimesh(v, box.faces, process=False).export(tmp_path / "inf.ply")
    with pytest.raises(ValueError, match="not finite numbers .* vertex 3"):
        read_mesh(tmp_path / "inf.ply")


def test_bounds_against_a_workspace() -> None:
    v = _box().vertices + [400.0, 0.0, 0.0]
    assert bounds_problem(v, np.array([-300.0, -600.0, -5.0]), np.array([1000.0, 600.0, 800.0])) is None
    problem = bounds_problem(v * 100.0, np.array([-300.0, -600.0, -5.0]), np.array([1000.0, 600.0, 800.0]))
    assert problem is not None and "10000 x 6000 x 4000 mm" in problem and "x 35000..45000 mm" in problem
