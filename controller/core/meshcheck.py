"""Checks of a user's object mesh before anything is computed from it.

A mesh file is data from outside: a NaN, a face that points at a vertex that is not
there, or a triangle with no area reaches numpy and scipy as a traceback deep inside
planning or the simulated physics. :func:`read_mesh` reads a PLY/STL/OBJ into a
``trimesh.Trimesh`` and refuses what cannot be used (``ValueError`` with a message for
the user; the caller names the file); :func:`mesh_findings` then says what is wrong
with a readable mesh: errors (nothing usable) and warnings with where (mm, the mesh's
frame) — holes and non-manifold edges, which a closed surface scanned from above
tolerates but the user should know of. :func:`drop_degenerate_faces` removes faces
without area (their normal has no direction).

Used by the simulator's object loader and by the real cell's object mesh alike, so
``check`` and ``run`` say the same thing about the same file.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from .inputfiles import MAX_MESH_BYTES, check_input_file

# A face is degenerate when its area is below this fraction of the squared size of the
# mesh (its bounding-box diagonal): at 1e-9, a 100 mm object's faces need 1e-5 mm^2,
# far below any real facet, far above float64's rounding of a cross product.
DEGENERATE_AREA_FRACTION = 1e-9
# An open rim lying on the table (its lowest slice) is the open bottom of an object
# resting there, not a hole: the scanner and the probe never see it.
TABLE_RIM_MM = 0.5
MAX_PLACES = 3


@dataclass
class MeshFindings:
    """What :func:`mesh_findings` found: ``errors`` (the mesh cannot be used) and ``warnings``."""

    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def read_mesh(path: str | Path) -> trimesh.Trimesh:
    """A mesh file as one ``Trimesh`` (no processing); ``ValueError`` when it holds no usable
    triangles: unreadable, no faces, non-finite coordinates, faces naming missing vertices."""
    try:
        check_input_file(path, MAX_MESH_BYTES)
    except OSError as exc:
        raise ValueError(f"cannot read mesh: {exc.strerror or exc}") from None
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:     # noqa: BLE001 - trimesh raises many types for bad files
        # A fallback reader that needs an optional module (a binary STL of the wrong length
        # is retried as ASCII, which wants charset_normalizer) hides the file's own problem.
        # Then the first error of the chain is the one about the file.
        if isinstance(exc, ImportError):
            while isinstance(exc.__context__, Exception):
                exc = exc.__context__
        raise ValueError(f"cannot read mesh: {type(exc).__name__}: {exc}") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ValueError("the mesh file holds no triangles")
    vertices = np.asarray(loaded.vertices, dtype=float)
    faces = np.asarray(loaded.faces)
    bad = ~np.all(np.isfinite(vertices), axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{int(bad.sum())} vertices have coordinates that are not finite numbers "
                         f"(NaN or infinity), the first is vertex {first}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        k = int(np.flatnonzero((faces < 0).any(axis=1) | (faces >= len(vertices)).any(axis=1))[0])
        raise ValueError(f"face {k} refers to vertex {faces[k].tolist()}, but the mesh has only "
                         f"{len(vertices)} vertices (a damaged file?)")
    return loaded


def degenerate_faces(mesh: trimesh.Trimesh) -> np.ndarray:
    """Mask of faces whose area is negligible against the mesh's size (no normal direction)."""
    tri = np.asarray(mesh.triangles, dtype=float)
    cross = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    diag = float(np.linalg.norm(np.ptp(np.asarray(mesh.vertices, dtype=float), axis=0)))
    return cross <= 2.0 * DEGENERATE_AREA_FRACTION * diag * diag


def drop_degenerate_faces(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, np.ndarray]:
    """``(mesh without its degenerate faces, mask of the faces kept)``."""
    keep = ~degenerate_faces(mesh)
    out = mesh.copy()
    out.update_faces(keep)
    out.remove_unreferenced_vertices()
    return out, keep


def _places(points_mm: list[np.ndarray]) -> str:
    shown = ", ".join(f"({p[0]:.0f}, {p[1]:.0f}, {p[2]:.0f}) mm" for p in points_mm[:MAX_PLACES])
    more = len(points_mm) - MAX_PLACES
    return shown + (f" and {more} more" if more > 0 else "")


def mesh_findings(mesh: trimesh.Trimesh) -> MeshFindings:
    """Errors and warnings of a read mesh (mm, object frame, z up: the object rests on the
    table at its lowest point)."""
    found = MeshFindings()
    vertices = np.asarray(mesh.vertices, dtype=float)
    degenerate = degenerate_faces(mesh)
    if degenerate.all():
        found.errors.append(f"the mesh has no area: all {len(degenerate)} faces are degenerate "
                            f"(their corners coincide or lie on one line)")
        return found
    if degenerate.any():
        centres = [np.asarray(mesh.triangles[i]).mean(axis=0) for i in np.flatnonzero(degenerate)]
        found.warnings.append(f"{int(degenerate.sum())} degenerate faces (no area) are left out, at "
                              f"{_places(centres)}")
    faces = np.asarray(mesh.faces)[~degenerate]
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    non_manifold = unique[counts > 2]
    if len(non_manifold):
        mids = [vertices[e].mean(axis=0) for e in non_manifold]
        found.warnings.append(f"{len(non_manifold)} non-manifold edges (shared by more than two faces) at "
                              f"{_places(mids)}: the simulated contact and the collision checks may see "
                              f"a wrong side there")
    open_edges = unique[counts == 1]
    if len(open_edges):
        on_table = np.all(vertices[open_edges][:, :, 2] <= vertices[:, 2].min() + TABLE_RIM_MM, axis=1)
        open_edges = open_edges[~on_table]
    if len(open_edges):
        holes = _loops(open_edges)
        where = [vertices[np.unique(h)].mean(axis=0) for h in holes]
        sizes = [float(np.ptp(vertices[np.unique(h)], axis=0).max()) for h in holes]
        found.warnings.append(
            f"{len(holes)} holes in the surface (open edges off the table): "
            + _places(where) + f" (largest {max(sizes):.0f} mm across): the scanner sees through a hole "
            f"and the probe can be planned into one")
    return found


def _loops(edges: np.ndarray) -> list[np.ndarray]:
    """The open edges (E, 2) grouped into connected rims, largest first."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nodes, inverse = np.unique(edges, return_inverse=True)
    inverse = inverse.reshape(-1, 2)
    graph = coo_matrix((np.ones(len(edges)), (inverse[:, 0], inverse[:, 1])), shape=(len(nodes), len(nodes)))
    _, label = connected_components(graph, directed=False)
    edge_label = label[inverse[:, 0]]
    groups = [edges[edge_label == k] for k in np.unique(edge_label)]
    return sorted(groups, key=len, reverse=True)


def bounds_problem(vertices_base_mm: np.ndarray, workspace_min_mm: np.ndarray,
                   workspace_max_mm: np.ndarray) -> str | None:
    """Why an object (vertices in the base frame, mm) does not fit in a workspace box, or None."""
    lo, hi = vertices_base_mm.min(axis=0), vertices_base_mm.max(axis=0)
    w_lo, w_hi = np.asarray(workspace_min_mm, float), np.asarray(workspace_max_mm, float)
    if np.all(lo >= w_lo) and np.all(hi <= w_hi):
        return None
    size = hi - lo
    axes = "xyz"
    out = [f"{axes[i]} {lo[i]:.0f}..{hi[i]:.0f} mm" for i in range(3) if lo[i] < w_lo[i] or hi[i] > w_hi[i]]
    room = ", ".join(f"{axes[i]} {w_lo[i]:.0f}..{w_hi[i]:.0f}" for i in range(3))
    return (f"the object ({size[0]:.0f} x {size[1]:.0f} x {size[2]:.0f} mm) does not fit the cell's workspace: "
            f"it reaches {', '.join(out)} in the base frame, the workspace is {room} mm")
