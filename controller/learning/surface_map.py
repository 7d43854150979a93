"""Distances along the scanned surface, and the region map they give (docs/design.md §2 "region map
over the cloud", §7).

A probe labels one point; the rest of the cloud takes the label of the probed point it is
nearest to ALONG THE SURFACE, without crossing a concave crease. Why concave: where two
bodies meet (a box resting on a pillow, a lid on a pot) the surface folds inwards — the
"minima rule" of part segmentation (Hoffman & Richards, 1984: shapes divide into parts
at concave creases). A convex edge (the box's rim, a pillow's rounded edge) is the edge
of one body and is crossed freely. So the box's walls go with the box top, the pillow up
to the foot of the box's wall goes with the pillow, and on a smooth surface the boundary
falls midway between differently labelled probes (the geodesic Voronoi diagram), which
densification then refines.

1. The graph (:func:`build_graph`): the k nearest neighbours of every cloud point, plus
   its nearest neighbour in each quadrant of its tangent plane (a sweep samples lines:
   the k nearest alone stay on one line), plus bridges across unscanned bands of one face.
2. Folds: an edge climbs a fold when one end lies in front of the other's tangent plane
   (by more than sin 20° of its length); such edges are dropped. A point is on a fold
   when one of its 16 nearest neighbours lies in front of its tangent plane that way
   (:func:`concave_points`); the fold is a band a few points wide.
3. Cells (:func:`cells`): multi-source Dijkstra over the edge lengths with the fold points
   removed, so a path cannot sneak across a fold in small steps (PCA normals blend a
   fold over a few points, and a per-edge turn test alone is evaded in small turns).
4. The folds themselves, and faces no probe reached, are labelled afterwards
   (:func:`labels_from_seeds`): a fold point takes the label of the neighbouring face whose
   local plane it lies on (a point 0.7 mm up a wall belongs to the wall), an unreached
   face the label of the nearest labelled point along the graph (or in space).

The same cells give the probed points' surface neighbours: two probes are neighbours when
their cells touch (:func:`seed_neighbours`); across a fold they are not.

Frames and units: one frame for everything (the cloud's, i.e. the object frame), mm;
normals are outward unit vectors.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

DEFAULT_K = 8
QUADRANT_POOL = 32
MAX_GAP_MM = 20.0
CONCAVE_K = 16
CONCAVE_RISE = 0.34      # sin 20°
MIN_CHORD_MM = 1.5
_BRIDGE_ANGLE_DEG = 30.0
_MAX_BRIDGE_PASSES = 20
_MIN_BRIDGE_POINTS = 10
SEAM_SIDE = 0.45          # the most of the way to the other region a seed's level may count, its label standing
MIN_INTERIOR_SEEDS = 3    # a region's level is read on its interior seeds from this many on
SEAM_KERNEL = 0.75        # the seam's smoothing width (Gaussian sigma), in local seed spacings
SPACING_K = 6             # seeds whose nearest-seed distances give the local spacing
# How far (robust sigmas) from its region's median a seed still counts as pure when the
# final map draws a seam: 0, the seam is where the dent lies halfway between the two
# regions' medians (see seam_fractions for why, and docs/generated_objects.md, stop 33).
SEAM_EDGE_SIGMAS = 0.0
LOCAL_FIT_RIDGE = 0.1     # the seam fit's slope ridge, in (weights' sum x kernel width^2)
LOCAL_FIT_CHUNK = 20_000  # cloud points fitted at once (bounds the seed-to-point table)


@dataclass(frozen=True)
class SurfaceGraph:
    """A k-NN graph over cloud points: ``lengths`` (P,P) sparse symmetric edge lengths in mm,
    ``points_mm`` (P,3), ``concave`` (P,) True on a concave fold."""

    points_mm: np.ndarray
    lengths: csr_matrix
    concave: np.ndarray

    def __len__(self) -> int:
        return int(self.points_mm.shape[0])


def _neighbour_pairs(pts: np.ndarray, nrm: np.ndarray, k: int, pool: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Directed pairs (i, j, length mm): the k nearest neighbours of each point, plus the
    nearest of its ``pool`` nearest in each quadrant of its tangent plane.

    A scanner sweep samples densely along each line and a few mm between lines: the k
    nearest are then all on the point's own line and the graph falls apart into strips.
    The quadrant neighbours reach the lines on either side.
    """
    n = pts.shape[0]
    kk = min(max(k, pool) + 1, n)
    dist, idx = cKDTree(pts).query(pts, k=kk)
    dist, idx = dist[:, 1:], idx[:, 1:]
    near = np.zeros(dist.shape, dtype=bool)
    near[:, :min(k, kk - 1)] = True
    # A tangent basis per point (any, fixed rule): u ⟂ n from the axis least aligned with n.
    axis = np.eye(3)[np.argmin(np.abs(nrm), axis=1)]
    u = np.cross(nrm, axis)
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
    v = np.cross(nrm, u)
    off = pts[idx] - pts[:, None, :]
    quadrant = 2 * (np.einsum("nkc,nc->nk", off, u) >= 0) + (np.einsum("nkc,nc->nk", off, v) >= 0)
    for q in range(4):
        masked = np.where(quadrant == q, dist, np.inf)
        best = np.argmin(masked, axis=1)
        has = np.isfinite(masked[np.arange(n), best])
        near[np.flatnonzero(has), best[has]] = True
    i = np.repeat(np.arange(n), dist.shape[1]).reshape(dist.shape)[near]
    j, length = idx[near], dist[near]
    ok = np.isfinite(length) & (j < n) & (j != i)
    return i[ok], j[ok], np.maximum(length[ok], 1e-6)   # duplicates: a tiny positive length


def _bridge_gaps(pts: np.ndarray, nrm: np.ndarray, i: np.ndarray, j: np.ndarray, length: np.ndarray,
                 max_gap_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Join graph components across unscanned bands of one face.

    The sweep leaves bands without points (the probe's shadow on a box top, ~12 mm wide):
    the neighbours stop at the band and the face falls apart. Each point of a component
    is joined to its nearest point of another component when that point is within
    ``max_gap_mm`` and the chord runs along both tangent planes with the normals agreeing
    (same test as targets.surface_graph: never a jump down a step). Repeated until no
    component can be joined (bounded passes).
    """
    n = pts.shape[0]
    sin_max, cos_max = np.sin(np.radians(_BRIDGE_ANGLE_DEG)), np.cos(np.radians(_BRIDGE_ANGLE_DEG))
    for _ in range(_MAX_BRIDGE_PASSES):
        graph = csr_matrix((np.ones(i.size), (i, j)), shape=(n, n))
        n_comp, comp = connected_components(graph, directed=False)
        if n_comp < 2:
            break
        added_i, added_j, added_l = [], [], []
        sizes = np.bincount(comp)
        for c in np.argsort(sizes, kind="stable"):
            if sizes[c] < _MIN_BRIDGE_POINTS:
                continue        # specks (stray returns): the Euclidean fallback labels them
            inside = np.flatnonzero(comp == c)
            outside = np.flatnonzero(comp != c)
            if outside.size == 0:
                continue
            d, k = cKDTree(pts[outside]).query(pts[inside], distance_upper_bound=max_gap_mm)
            ok = np.isfinite(d)
            if not ok.any():
                continue
            a, b, d = inside[ok], outside[k[ok]], d[ok]
            chord = pts[b] - pts[a]
            along = ((np.abs(np.einsum("ij,ij->i", chord, nrm[a])) <= sin_max * d)
                     & (np.abs(np.einsum("ij,ij->i", chord, nrm[b])) <= sin_max * d)
                     & (np.einsum("ij,ij->i", nrm[a], nrm[b]) >= cos_max))
            if along.any():
                added_i.append(a[along])
                added_j.append(b[along])
                added_l.append(np.maximum(d[along], 1e-6))
                break       # recompute the components before joining more
        if not added_i:
            break
        i, j = np.concatenate([i, *added_i]), np.concatenate([j, *added_j])
        length = np.concatenate([length, *added_l])
    return i, j, length


def concave_points(points_mm: np.ndarray, normals: np.ndarray, k: int = CONCAVE_K,
                   rise: float = CONCAVE_RISE, min_chord_mm: float = MIN_CHORD_MM) -> np.ndarray:
    """(P,) True on a concave fold: one of the point's k nearest neighbours at least
    ``min_chord_mm`` away lies in front of its tangent plane by more than ``rise`` times
    its distance (sin 20°: a wall rising beside a floor). ``min_chord_mm`` keeps the
    scanner's depth noise (0.1 mm) from tilting chords between adjacent samples."""
    pts = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    nrm = np.asarray(normals, dtype=float).reshape(-1, 3)
    n = pts.shape[0]
    if n < 3:
        return np.zeros(n, dtype=bool)
    kk = min(k + 1, n)
    dist, idx = cKDTree(pts).query(pts, k=kk)
    off = pts[idx[:, 1:]] - pts[:, None, :]
    height = np.einsum("nkc,nc->nk", off, nrm)
    far = dist[:, 1:] >= min_chord_mm
    return np.any(far & (height > rise * dist[:, 1:]), axis=1)


def _concave_edges(pts: np.ndarray, nrm: np.ndarray, i: np.ndarray, j: np.ndarray, length: np.ndarray,
                   rise: float, min_chord_mm: float) -> np.ndarray:
    """(E,) True where either end of an edge lies in front of the other's tangent plane by
    more than ``rise`` times the edge length (the edge climbs a fold)."""
    chord = pts[j] - pts[i]
    up_i = np.einsum("ij,ij->i", chord, nrm[i])
    up_j = -np.einsum("ij,ij->i", chord, nrm[j])
    return (length >= min_chord_mm) & (np.maximum(up_i, up_j) > rise * length)


def build_graph(points_mm: np.ndarray, normals: np.ndarray, k: int = DEFAULT_K,
                quadrant_pool: int = QUADRANT_POOL, max_gap_mm: float = MAX_GAP_MM,
                rise: float = CONCAVE_RISE, min_chord_mm: float = MIN_CHORD_MM) -> SurfaceGraph:
    """The surface graph of a cloud (P,3) mm with outward unit normals (P,3); see the module
    docstring. Parts of one face split by an unscanned band up to ``max_gap_mm`` wide are joined."""
    pts = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    nrm = np.asarray(normals, dtype=float).reshape(-1, 3)
    n = pts.shape[0]
    if n < 2:
        return SurfaceGraph(pts, csr_matrix((n, n)), np.zeros(n, dtype=bool))
    i, j, length = _neighbour_pairs(pts, nrm, k, quadrant_pool)
    i, j, length = _bridge_gaps(pts, nrm, i, j, length, max_gap_mm)
    # Edges that climb a fold are not part of a face (kept out of the graph altogether:
    # the fold points are labelled by their planes, and faces join through the folds only
    # when no probe reached one).
    climb = _concave_edges(pts, nrm, i, j, length, rise, min_chord_mm)
    i, j, length = i[~climb], j[~climb], length[~climb]
    rows, cols = np.concatenate([i, j]), np.concatenate([j, i])
    ln = csr_matrix((np.concatenate([length, length]), (rows, cols)), shape=(n, n))
    mult = csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
    ln.data /= mult.data          # pairs found from both ends were summed
    return SurfaceGraph(pts, ln, concave_points(pts, nrm, rise=rise, min_chord_mm=min_chord_mm))


@dataclass(frozen=True)
class Cells:
    """Each cloud point's nearest seed along the surface without crossing a fold:
    ``source`` (P,) seed index (into the seeds passed; -1 on folds and on faces no seed
    reaches), ``distance_mm`` (P,)."""

    source: np.ndarray
    distance_mm: np.ndarray


def seed_nodes(graph: SurfaceGraph, seeds_mm: np.ndarray) -> np.ndarray:
    """Cloud point index (S,) nearest to each seed point (S,3) mm."""
    s = np.asarray(seeds_mm, dtype=float).reshape(-1, 3)
    if s.shape[0] == 0 or len(graph) == 0:
        return np.zeros(0, dtype=np.int64)
    return cKDTree(graph.points_mm).query(s)[1].astype(np.int64)


def _multi_source(lengths: csr_matrix, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance, index into ``nodes`` of the nearest source; -1 unreached). Two sources on one
    node: the first wins."""
    n = lengths.shape[0]
    first = np.sort(np.unique(nodes, return_index=True)[1])
    uniq = nodes[first]
    dist, _, src = dijkstra(lengths, directed=False, indices=uniq, return_predecessors=True, min_only=True)
    owner = np.full(n, -1, dtype=np.int64)
    owner[uniq] = first
    source = np.where(src >= 0, owner[np.maximum(src, 0)], -1)
    return dist, source


def _without(lengths: csr_matrix, blocked: np.ndarray) -> csr_matrix:
    """The graph with every edge touching a blocked node removed."""
    coo = lengths.tocoo()
    keep = ~(blocked[coo.row] | blocked[coo.col])
    return csr_matrix((coo.data[keep], (coo.row[keep], coo.col[keep])), shape=lengths.shape)


def cells(graph: SurfaceGraph, seeds_mm: np.ndarray) -> Cells:
    """Geodesic Voronoi cells of the seeds (S,3) mm on the graph with the folds removed (a
    seed on a fold keeps its own point)."""
    n = len(graph)
    nodes = seed_nodes(graph, seeds_mm)
    if nodes.size == 0:
        return Cells(np.full(n, -1, np.int64), np.full(n, np.inf))
    blocked = graph.concave.copy()
    blocked[nodes] = False
    dist, source = _multi_source(_without(graph.lengths, blocked), nodes)
    source[blocked] = -1
    dist[blocked] = np.inf
    return Cells(source, dist)


def labels_from_seeds(graph: SurfaceGraph, seeds_mm: np.ndarray, seed_labels: np.ndarray,
                      fit_radius_mm: float = 15.0, min_fit_points: int = 12,
                      seed_levels: np.ndarray | None = None,
                      dent_not_read: np.ndarray | None = None,
                      seed_peaks_mm: np.ndarray | None = None) -> np.ndarray:
    """Region label (P,) of every cloud point (see the module docstring, steps 3 and 4).

    ``seed_levels`` (S,): each seed's dent on a scale where a seed pressing two materials
    reads their weighted mean (the session passes the mean peak depth in mm over the survey
    forces, regions.mean_peak_mm); with them, the faces between seeds of two regions are
    split where the level interpolated along the surface crosses midway
    (:func:`_split_between`) instead of midway between the seeds.
    With levels and three regions or more, a band of seeds that only a seam between two other
    regions explains is first given to those two (:func:`transition_bands`).
    ``dent_not_read`` (S,) bool: seeds whose measurement does not support their label (the
    session passes regions.dent_falls_with_force). One that no seed of its own region
    neighbours on the surface labels no area: it alone would draw an island of its region,
    and the seeds around it share its cell instead. Beside its own region it stays (it
    claims nothing its neighbours do not).
    ``seed_peaks_mm`` (S,F): each seed's peak depth at each survey force (the session passes
    regions.peaks_mm). With them, a seed beside another region (not interior) whose level,
    the forces weighed as for that seam, reads past the halfway to that region counts where
    it puts it, across the seam from its label if need be (:func:`reads_other_side`);
    without, every seed stays on its own region's side. Also with them, a seed whose peaks
    read its own side at one force and the other's at another, three quarters of its
    neighbours in that other region, goes to it (:func:`defer_to_neighbours`) and counts at
    that region's own level; and each seam's levels weigh the forces by what they tell its
    two regions apart (:func:`_pair_levels`) instead of the plain mean ``seed_levels``.
    Each region's level on its seams is read on its interior seeds, or on the seeds deepest
    in it when it has too few of them (:func:`level_seeds`).
    """
    lab = np.asarray(seed_labels, dtype=np.int64).reshape(-1)
    n = len(graph)
    out = np.full(n, -1, dtype=np.int64)
    if lab.size == 0 or n == 0:
        return out
    c = cells(graph, seeds_mm)
    if dent_not_read is not None and np.any(dent_not_read):
        drop = np.asarray(dent_not_read, dtype=bool).reshape(-1) & ~_with_own_neighbour(lab, seed_neighbours(graph, c))
        if drop.any() and not drop.all():
            keep = ~drop
            return labels_from_seeds(graph, np.asarray(seeds_mm, dtype=float).reshape(-1, 3)[keep], lab[keep],
                                     fit_radius_mm, min_fit_points,
                                     None if seed_levels is None else np.asarray(seed_levels).reshape(-1)[keep],
                                     seed_peaks_mm=None if seed_peaks_mm is None else np.asarray(seed_peaks_mm)[keep])
    pairs = seed_neighbours(graph, c) if seed_levels is not None and np.unique(lab).size > 1 else []
    moved = np.zeros(lab.size, dtype=bool)
    if seed_peaks_mm is not None and len(pairs):
        deferred = defer_to_neighbours(seed_peaks_mm, lab, pairs)
        moved, lab = deferred != lab, deferred
    inner = interior_seeds(lab, pairs)
    if moved.any():
        # Its measurement contradicts itself: it says nothing of where the seam is, and
        # counts as its new region's own level (for the seam and the region's median).
        seed_levels = None if seed_levels is None else _at_region_level(seed_levels, lab, inner, moved)
        seed_peaks_mm = _at_region_level(seed_peaks_mm, lab, inner, moved)
    if seed_levels is not None and np.unique(lab).size > 2:
        banded = transition_bands(np.asarray(seed_levels, dtype=float).reshape(-1), lab, pairs, inner)
        if not np.array_equal(banded, lab):
            lab, inner = banded, interior_seeds(banded, pairs)
    reached = c.source >= 0
    out[reached] = lab[c.source[reached]]
    if seed_levels is not None and np.unique(lab).size > 1:
        out = _split_between(graph, seeds_mm, lab, np.asarray(seed_levels, dtype=float).reshape(-1), out, reached,
                             inner, seed_peaks_mm, level_seeds(seeds_mm, lab, inner))
    # Fold points: the label of the face whose plane they lie on.
    fold = np.flatnonzero(graph.concave & ~reached)
    if fold.size and reached.any():
        faces = np.flatnonzero(reached)
        tree = cKDTree(graph.points_mm[faces])
        for q, nb in zip(fold, tree.query_ball_point(graph.points_mm[fold], fit_radius_mm)):
            out[q] = _nearest_plane_label(graph.points_mm[q], graph.points_mm[faces[nb]], out[faces[nb]],
                                          min_fit_points)
    # Whatever is left (faces no seed reaches, folds without faces around): nearest labelled
    # point along the full graph, then (other components) the Euclidean nearest.
    left = out < 0
    if left.any() and (~left).any():
        done = np.flatnonzero(~left)
        _, src = _multi_source(graph.lengths, done)
        fill = left & (src >= 0)
        out[fill] = out[done[src[fill]]]
        left = out < 0
        if left.any():
            done = np.flatnonzero(~left)
            _, near = cKDTree(graph.points_mm[done]).query(graph.points_mm[left])
            out[left] = out[done[near]]
    return out


def transition_bands(levels: np.ndarray, seed_labels: np.ndarray, neighbour_pairs: list[tuple[int, int]],
                     interior: np.ndarray) -> np.ndarray:
    """Seed labels (S,) with the bands that only a seam between two other regions explains
    given to those two regions.

    Across a seam between A and C the dent passes through every level between theirs, so
    the probes densification lines up beside a high-contrast seam (hard rubber beside foam)
    read the level of any material B lying between the two, and cluster with B (unseen
    slab 1102: a line of hard-rubber probes 1.8 mm from a foam strip, reading 0.3 mm at
    2 N, joined the gel disc's region, 0.4 mm, and drew a gel band 180 mm long). The regions
    step relabels a region made only of such runs (regions._absorb_transition_bands); a run
    that is one piece of a real material's region is left to the map, here.

    A connected run of B's seeds (joined by surface neighbours of B) is such a band when
    none of them is interior (:func:`interior_seeds`), B has interior seeds elsewhere (its
    own body, which the run does not reach), and every seed of the run neighbours a region
    A whose level lies below both B's and the seed's and a region C whose level lies above
    both. Each seed of the band then goes to A or C by which side of the two regions' mid
    level (the mm halfway, as :func:`seam_fractions` draws the seam) it reads. A material
    really present as such a strip narrower than the probe spacing is lost with it; one
    wide enough to hold an interior seed is kept. Levels are each region's median, read
    on its interior seeds as in :func:`seam_fractions`. With fewer than three regions there
    is no third level to mistake, and nothing changes.
    """
    lev = np.asarray(levels, dtype=float).reshape(-1)
    lab = np.asarray(seed_labels, dtype=np.int64).reshape(-1).copy()
    inner = np.asarray(interior, dtype=bool).reshape(-1)
    regions = np.unique(lab)
    if regions.size < 3:
        return lab
    median = {int(r): float(np.median(v)) for r, v in zip(regions, _levels_read(lev, lab, inner, regions))}
    pairs = np.asarray(neighbour_pairs, dtype=np.int64).reshape(-1, 2)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    neighbours: list[set[int]] = [set() for _ in range(lab.size)]
    for i, j in pairs.tolist():
        neighbours[i].add(lab[j])
        neighbours[j].add(lab[i])
    goes_to = np.full(lab.size, -1, dtype=np.int64)
    for s in range(lab.size):
        b = int(lab[s])
        below = [r for r in neighbours[s] if median[r] < min(median[b], lev[s])]
        above = [r for r in neighbours[s] if median[r] > max(median[b], lev[s])]
        if below and above:
            a, c = min(below, key=median.get), max(above, key=median.get)
            goes_to[s] = a if lev[s] < 0.5 * (median[a] + median[c]) else c
    same = pairs[lab[pairs[:, 0]] == lab[pairs[:, 1]]]
    runs = coo_matrix((np.ones(len(same)), (same[:, 0], same[:, 1])), shape=(lab.size, lab.size))
    _, run_of = connected_components(runs, directed=False)
    out = lab.copy()
    for run in np.unique(run_of[goes_to >= 0]).tolist():
        members = np.flatnonzero(run_of == run)
        own_body = inner & (lab == lab[members[0]])
        if np.all(goes_to[members] >= 0) and not inner[members].any() and own_body.any():
            out[members] = goes_to[members]
    return out


def _with_own_neighbour(seed_labels: np.ndarray, neighbour_pairs: list[tuple[int, int]]) -> np.ndarray:
    """(S,) True for a seed with at least one surface neighbour of its own region."""
    lab = np.asarray(seed_labels, dtype=np.int64).reshape(-1)
    pairs = np.asarray(neighbour_pairs, dtype=np.int64).reshape(-1, 2)
    pairs = pairs[(pairs[:, 0] != pairs[:, 1]) & (lab[pairs[:, 0]] == lab[pairs[:, 1]])]
    out = np.zeros(lab.size, dtype=bool)
    out[pairs.ravel()] = True
    return out


def level_seeds(seeds_mm: np.ndarray, seed_labels: np.ndarray, interior: np.ndarray) -> np.ndarray:
    """(S,) True for the seeds each region's level is read on: its ``interior`` seeds when it
    has ``MIN_INTERIOR_SEEDS`` of them, else the deeper half of its seeds (at least
    ``MIN_INTERIOR_SEEDS``; all of them when it has no more), depth being the distance (mm,
    straight line) to the nearest seed of another region.

    A small inclusion has few seeds without a neighbour of another region, and the seeds
    densification lines up along its seam are most of its region: they press both
    materials, and a median read on all of them lies part way to the matrix (suite slab
    1012 seed 2's sponge disc, 20 mm across: 13 seeds, one interior, eight of them outside
    the disc; their median was the level of a seed on the seam, so every seed within a
    millimetre outside read as pure sponge and the disc was drawn up to 2.3 mm too large). The
    seeds deepest in the region press the least of another material. Half of them, not the
    three deepest: a stiff inclusion's peaks scatter by a third of its contrast with the
    matrix (hard rubber), and a median of three misplaces its level (docs/generated_objects.md,
    stop 42)."""
    pts = np.asarray(seeds_mm, dtype=float).reshape(-1, 3)
    lab = np.asarray(seed_labels, dtype=np.int64).reshape(-1)
    out = np.asarray(interior, dtype=bool).reshape(-1).copy()
    for r in np.unique(lab).tolist():
        members = np.flatnonzero(lab == r)
        if np.count_nonzero(out[members]) >= MIN_INTERIOR_SEEDS or members.size == lab.size:
            continue
        depth_mm = cKDTree(pts[lab != r]).query(pts[members])[0]
        deeper = max(MIN_INTERIOR_SEEDS, (members.size + 1) // 2)
        out[members[np.argsort(-depth_mm, kind="stable")[:deeper]]] = True
    return out


def interior_seeds(seed_labels: np.ndarray, neighbour_pairs: list[tuple[int, int]]) -> np.ndarray:
    """(S,) True for a seed with at least one surface neighbour (``neighbour_pairs``, from
    :func:`seed_neighbours`, or any (E,2) neighbour pairs), all of them of its own region."""
    lab = np.asarray(seed_labels, dtype=np.int64).reshape(-1)
    pairs = np.asarray(neighbour_pairs, dtype=np.int64).reshape(-1, 2)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]          # a seed is no neighbour of itself
    has = np.zeros(lab.size, dtype=bool)
    has[pairs.ravel()] = True
    border = np.zeros(lab.size, dtype=bool)
    crossing = pairs[lab[pairs[:, 0]] != lab[pairs[:, 1]]]
    border[crossing.ravel()] = True
    return has & ~border


def reads_other_side(peaks_mm: np.ndarray, seed_labels: np.ndarray, interior: np.ndarray | None,
                     members: np.ndarray, other: int) -> np.ndarray:
    """(M,) True for the seeds ``members`` (indices, all of one region A) whose level on the
    seam between A and region ``other`` (:func:`_pair_levels`: the peaks ``peaks_mm`` (S,F)
    weighted by what each survey force tells the two apart) lies past the halfway between
    the two regions' levels on that scale (each region read on the ``interior`` seeds as in
    :func:`seam_fractions`).

    Such a seed's tip pressed more of the other material than of its own: the clustering
    put it with A (on all its features and its neighbours), but its measurement says it
    stands across the seam. The weighted level, not the plain mean: a force at which the
    two differ by little and whose peaks scatter (hard rubber beside an elastomer 3x softer
    at the low force: generated slab 1303) is not evidence, and the weights count it as
    little as it tells (docs/generated_objects.md, stop 41: with the plain mean a level
    crossing by one noisy force moved matrix seeds onto a disc; holding every force to read
    past the halfway kept seeds 1-2 mm inside suite slab 1012 seed 2's hard-rubber ellipse
    on the elastomer's side by the low force's noise alone). Where the forces cannot be
    weighed (a region without spread at some force), every force must read past the
    halfway."""
    read = _read_pair(peaks_mm, seed_labels, interior, members, other)
    if read is None:
        return np.zeros(np.asarray(members).size, dtype=bool)
    values, rows_own, rows_other = read
    own, far = np.median(rows_own, axis=0), np.median(rows_other, axis=0)     # (F,)
    weight = _force_weights(rows_own, rows_other)
    if weight is None:
        return np.all(_beyond_halfway(values, own, far), axis=1)
    return _beyond_halfway(values @ weight, own @ weight, far @ weight)


def _past_halfway(peaks_mm: np.ndarray, seed_labels: np.ndarray, interior: np.ndarray | None,
                  members: np.ndarray, other: int) -> np.ndarray:
    """(M,F) True where seed ``members[m]``'s peak at force f lies past the halfway between its
    region's and region ``other``'s median peaks at that force (toward ``other``)."""
    read = _read_pair(peaks_mm, seed_labels, interior, members, other)
    if read is None:
        n_forces = np.asarray(peaks_mm).reshape(len(peaks_mm), -1).shape[1]
        return np.zeros((np.asarray(members).size, n_forces), dtype=bool)
    values, rows_own, rows_other = read
    return _beyond_halfway(values, np.median(rows_own, axis=0), np.median(rows_other, axis=0))


def _read_pair(peaks_mm: np.ndarray, seed_labels: np.ndarray, interior: np.ndarray | None, members: np.ndarray,
               other: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The peaks (M,F) of ``members`` (all of one region A), and the peaks A's and region
    ``other``'s levels are read on (:func:`_levels_read`); None without members or forces."""
    pk = np.asarray(peaks_mm, dtype=float)
    pk = pk.reshape(pk.shape[0], -1)
    lab = np.asarray(seed_labels, dtype=np.int64).reshape(-1)
    members = np.asarray(members, dtype=np.int64).reshape(-1)
    if members.size == 0 or pk.shape[1] == 0:
        return None
    inner = np.zeros(lab.size, dtype=bool) if interior is None else np.asarray(interior, dtype=bool).reshape(-1)
    rows_own, rows_other = _levels_read(pk, lab, inner, np.array([int(lab[members[0]]), int(other)]))
    return pk[members], rows_own, rows_other


def _beyond_halfway(values: np.ndarray, own: np.ndarray, far: np.ndarray) -> np.ndarray:
    """True where ``values`` lie past the halfway from ``own`` toward ``far`` (broadcast)."""
    toward = np.sign(far - own)
    return ((values - 0.5 * (own + far)) * toward > 0.0) & (toward != 0.0)


def defer_to_neighbours(peaks_mm: np.ndarray, seed_labels: np.ndarray,
                        neighbour_pairs: list[tuple[int, int]]) -> np.ndarray:
    """Seed labels (S,) with each seed whose survey peaks disagree about its side given to the
    region that at least three quarters of its surface neighbours hold.

    A seed of region A beside region B whose peak reads past the halfway toward B at some
    survey force and on A's side at another (:func:`_past_halfway`) has one measurement
    saying each; the clustering chose on all its features at once. Its neighbours are the
    other evidence: with three quarters of them in B it stands in B's body or in a pocket
    of it, not on a seam between the two, and it is a B seed one force read wrong (suite
    slab 1012 seed 2: a target 4 mm inside a hard-rubber ellipse read 0.012 mm at the low
    force, as the hard rubber does, and 0.053 mm at the high one, as the elastomer around
    does; labelled elastomer beside four hard-rubber neighbours of five, it cut a notch
    4 mm deep into the ellipse). Why three quarters: on a seam the neighbours split about
    evenly, and seam targets with one force read each way sit within a contact's width of
    the seam, where their levels are what places it (docs/generated_objects.md, stop 40:
    moved at a simple majority, 59 of 60 went to their true region and the maps still got
    worse where they were seam targets). A seed whose every peak reads its own side keeps its
    label whatever its neighbours (a small inclusion one probe found); one whose every peak
    reads B's is the crossing rule's (:func:`reads_other_side`). Decided for every seed at
    once on the labels given, so a relabelled seed moves no other. Interior seeds have no
    neighbour of another region and are never moved.
    """
    lab = np.asarray(seed_labels, dtype=np.int64).reshape(-1)
    pairs = np.asarray(neighbour_pairs, dtype=np.int64).reshape(-1, 2)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    out = lab.copy()
    if lab.size == 0 or pairs.size == 0 or np.unique(lab).size < 2:
        return out
    pairs = np.unique(np.sort(pairs, axis=1), axis=0)
    regions = np.unique(lab)
    k_of = np.full(int(regions.max()) + 1, -1, dtype=np.int64)
    k_of[regions] = np.arange(regions.size)
    count = np.zeros((lab.size, regions.size), dtype=np.int64)     # neighbours per region
    np.add.at(count, (pairs[:, 0], k_of[lab[pairs[:, 1]]]), 1)
    np.add.at(count, (pairs[:, 1], k_of[lab[pairs[:, 0]]]), 1)
    total = count.sum(axis=1)
    others = count.copy()
    others[np.arange(lab.size), k_of[lab]] = -1
    kb = np.argmax(others, axis=1)
    held = (total > 0) & (4 * others[np.arange(lab.size), kb] >= 3 * total)
    inner = interior_seeds(lab, pairs)
    for ra in regions.tolist():
        for kbv in np.unique(kb[held & (lab == ra)]).tolist():
            members = np.flatnonzero(held & (lab == ra) & (kb == kbv))
            past = _past_halfway(peaks_mm, lab, inner, members, int(regions[kbv]))
            out[members[past.any(axis=1) & ~past.all(axis=1)]] = regions[kbv]
    return out


def seam_fractions(levels: np.ndarray, labels: np.ndarray, a: np.ndarray, b: np.ndarray,
                   interior: np.ndarray | None = None, edge_sigmas: float = SEAM_EDGE_SIGMAS,
                   cross_a: np.ndarray | None = None, cross_b: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where seeds a (M,) and b (M,) (indices into ``levels``/``labels`` (N,)) stand on the way
    from a's region A to b's region B: (s_a (M,), s_b (M,), usable (M,) bool).

    s = (level - edge_A) / (edge_B - edge_A) clipped to [0, 1], with edge_A = A's median
    level + ``edge_sigmas`` robust sigmas (1.4826 MAD) toward B and edge_B likewise (the
    median and MAD, not percentiles: the seeds densification put on the seam belong to a
    region too, and are exactly the ones that must count).

    With ``edge_sigmas`` 0 (the final map's) s = 1/2 where the level lies halfway between
    the two medians. A tip straddling a seam presses both materials, and under the contact
    model (docs/design.md §8: the profiles of the two materials weighted by how much of the
    contact each takes, equal shares on the seam) its dent in mm is halfway between theirs
    exactly on the seam, so the seam is drawn there. Edges pulled toward each other by
    their regions' spreads move that crossing by half the difference of the spreads (in mm
    the softer material's is the larger, so the soft side grew); on log levels the midway
    is the geometric mean, nearer the stiff level, and soft inclusions grew, stiff ones
    shrank (docs/generated_objects.md, stops 29 and 33). ``edge_sigmas`` 3 counts a seed
    within its region's usual range as pure (0 or 1): densification's false-position
    placement reads it that way (densify._crossing_fraction).

    ``interior`` (N,) bool (:func:`interior_seeds`; the final map passes :func:`level_seeds`,
    which adds a small region's deeper seeds): a region's median and MAD come from these
    seeds when it has ``MIN_INTERIOR_SEEDS`` of them. A seed beside another region
    presses both materials; on a small inclusion densification makes such seeds most of
    its region (suite slab 1012's sponge disc: 16 of 30, whose levels reach the matrix's),
    and a range read on them overlaps the neighbour's, so no seam could be drawn through them.
    Not usable where the two ranges overlap (or a and b share a region). A seed stays on
    its own region's side, s_a <= ``SEAM_SIDE`` < 1/2 < 1 - ``SEAM_SIDE`` <= s_b (its level
    is one measurement; its label was decided with its neighbours), except the seeds that
    ``cross_a`` (M,) / ``cross_b`` (M,) mark: they count where their levels put them. The
    final map marks the seeds beside another region whose weighted level reads past the
    halfway (:func:`reads_other_side`); densification marks none (its false-position step
    interpolates between the two ends of an edge).
    """
    lev = np.asarray(levels, dtype=float).reshape(-1)
    lab = np.asarray(labels, dtype=np.int64).reshape(-1)
    a, b = np.asarray(a, dtype=np.int64).reshape(-1), np.asarray(b, dtype=np.int64).reshape(-1)
    regions = np.unique(lab)
    k_of = {int(r): k for k, r in enumerate(regions)}
    inner = np.zeros(lab.size, dtype=bool) if interior is None else np.asarray(interior, dtype=bool).reshape(-1)

    per = _levels_read(lev, lab, inner, regions)
    median = np.array([np.median(v) for v in per])
    sigma = np.array([_robust_spread(v) for v in per])
    low, high = median - edge_sigmas * sigma, median + edge_sigmas * sigma
    ka = np.array([k_of[int(v)] for v in lab[a]], dtype=np.int64)
    kb = np.array([k_of[int(v)] for v in lab[b]], dtype=np.int64)
    toward_b = median[kb] > median[ka]
    edge_a = np.where(toward_b, high[ka], low[ka])
    edge_b = np.where(toward_b, low[kb], high[kb])
    span = edge_b - edge_a
    usable = (span * (median[kb] - median[ka]) > 0.0) & (ka != kb)
    safe = np.where(usable, span, 1.0)
    side_a = SEAM_SIDE if cross_a is None else np.where(np.asarray(cross_a, dtype=bool), 1.0, SEAM_SIDE)
    side_b = SEAM_SIDE if cross_b is None else np.where(np.asarray(cross_b, dtype=bool), 1.0, SEAM_SIDE)
    s_a = np.where(usable, np.clip((lev[a] - edge_a) / safe, 0.0, side_a), 0.0)
    s_b = np.where(usable, np.clip((lev[b] - edge_a) / safe, 1.0 - side_b, 1.0), 1.0)
    return s_a, s_b, usable


def _at_region_level(values: np.ndarray, labels: np.ndarray, interior: np.ndarray, moved: np.ndarray
                     ) -> np.ndarray:
    """``values`` (S,) or (S,F) with each ``moved`` seed's row replaced by its region's median,
    read as :func:`_levels_read` reads it on the seeds not moved."""
    vals = np.array(values, dtype=float)
    flat = vals.reshape(vals.shape[0], -1)
    lab = np.asarray(labels, dtype=np.int64).reshape(-1)
    moved = np.asarray(moved, dtype=bool).reshape(-1)
    kept = np.where(moved, -1, lab)             # a moved seed is no member when the level is read
    for r in np.unique(lab[moved]).tolist():
        rows = _levels_read(flat, kept, np.asarray(interior, dtype=bool).reshape(-1), np.array([r]))[0]
        if rows.shape[0]:
            flat[moved & (lab == r)] = np.median(rows, axis=0)
    return flat.reshape(vals.shape)


def _pair_levels(peaks_mm: np.ndarray, labels: np.ndarray, interior: np.ndarray, a: int, b: int) -> np.ndarray:
    """(S,) each seed's level (mm) for the seam between regions ``a`` and ``b``: its peaks at
    the survey forces (``peaks_mm`` (S,F)) weighted by what each force tells the two apart.

    At force f a seed's seam fraction is (peak - m_a) / (m_b - m_a) (m: the regions' median
    peaks, read as :func:`_levels_read` reads them), with a variance of s_f^2 / d_f^2 (s_f^2:
    the two regions' mean squared robust spread (1.4826 MAD) at that force; d_f = m_b - m_a).
    The inverse-variance combination of the fractions weighs force f by d_f^2 / s_f^2, which
    is the level that weighs each peak by |d_f| / s_f^2. The plain mean of the peaks weighs
    each fraction by |d_f| alone: a force at which the two materials differ by a quarter of
    another's difference in mm, with peaks as noisy, counted a quarter as much instead of a
    sixteenth (suite slab 1012 seed 2's hard rubber beside the elastomer: 0.013 mm apart at
    the low force, 0.049 at the high one). The spread is measured, not assumed: weighing by
    d_f^2 alone (equal noise at every force) was tried and lost on 19 of 40 sessions
    (docs/generated_objects.md, stop 40). Without a spread at some force (regions of one
    seed), the plain mean."""
    pk = np.asarray(peaks_mm, dtype=float)
    pk = pk.reshape(pk.shape[0], -1)
    rows_a, rows_b = _levels_read(pk, np.asarray(labels, dtype=np.int64), interior, np.array([a, b]))
    weight = _force_weights(rows_a, rows_b)
    return pk.mean(axis=1) if weight is None else pk @ weight


def _force_weights(rows_a: np.ndarray, rows_b: np.ndarray) -> np.ndarray | None:
    """(F,) weights summing to 1 that :func:`_pair_levels` gives the survey forces, from the
    peaks (N,F) two regions' levels are read on: |d_f| / s_f^2 (d_f the difference of their
    median peaks, s_f^2 their mean squared robust spread). None when some force has no
    spread or no force tells them apart."""
    spread_sq = 0.5 * (_robust_spread(rows_a) ** 2 + _robust_spread(rows_b) ** 2)      # (F,)
    apart = np.abs(np.median(rows_b, axis=0) - np.median(rows_a, axis=0))
    if not np.all(spread_sq > 0.0) or not np.any(apart > 0.0):
        return None
    weight = apart / spread_sq
    return weight / weight.sum()


def _robust_spread(rows: np.ndarray) -> np.ndarray:
    """(F,) 1.4826 x the median absolute deviation of each column of ``rows`` (N,F)."""
    return 1.4826 * np.median(np.abs(rows - np.median(rows, axis=0)), axis=0)


def _levels_read(levels: np.ndarray, labels: np.ndarray, interior: np.ndarray, regions: np.ndarray
                 ) -> list[np.ndarray]:
    """Each region's seed levels that its level is read on: its interior seeds when it has
    ``MIN_INTERIOR_SEEDS`` of them, else all its seeds."""
    out = []
    for r in regions:
        members = labels == r
        own = members & interior
        out.append(levels[own if np.count_nonzero(own) >= MIN_INTERIOR_SEEDS else members])
    return out


def _split_between(graph: SurfaceGraph, seeds_mm: np.ndarray, seed_labels: np.ndarray, seed_levels: np.ndarray,
                   labels: np.ndarray, reached: np.ndarray, interior: np.ndarray | None = None,
                   seed_peaks_mm: np.ndarray | None = None, reading: np.ndarray | None = None) -> np.ndarray:
    """Draw the boundary between two regions where the seeds' levels, fitted locally over the
    surface, cross midway.

    A probe that straddles a seam presses both materials: its dent lies between theirs,
    and the seam passes within a contact's width of it. Each reached point p has its
    region A (the plain map's) and the nearest other region B along the surface. Every seed
    of A and B has a seam fraction (:func:`seam_fractions`: 0 at or beyond A's median
    level, 1 at or beyond B's, part way for a seed pressing both). p takes B when a locally
    linear fit of the fractions of the seeds around it (:func:`_local_linear_at`) exceeds
    1/2 at p; deep in A the seeds around read about 0 and nothing moves, and a point with
    no seed in reach keeps the plain map's label. The kernel width is ``SEAM_KERNEL`` x the local seed
    spacing (the median nearest-seed distance of the ``SPACING_K`` seeds nearest p), so
    several seeds on each side decide: the seam is a smooth curve through the part-way
    seeds, not the polygon of the cells of one pair of seeds (which follows each seed's
    position and one level's noise). A linear fit, not a weighted mean: a mean pulls the
    crossing toward the side with more seeds near p (the seeds densification put along a
    seam), a linear fit does not.

    ``interior`` (S,) bool: the seeds that never cross (:func:`interior_seeds`); ``reading``
    (S,) bool: the seeds each region's level is read on (:func:`level_seeds`; default
    ``interior``).
    """
    regions = np.unique(seed_labels)
    nodes = seed_nodes(graph, seeds_mm)
    blocked = graph.concave.copy()
    blocked[nodes] = False
    free = _without(graph.lengths, blocked)
    dist = np.full((regions.size, len(graph)), np.inf)
    for k, r in enumerate(regions):
        dist[k] = _multi_source(free, nodes[seed_labels == r])[0]
    out = labels.copy()
    # A: the region the plain map gave (ties stay as it broke them); B: the nearest other one.
    k_of = np.full(int(regions.max()) + 1, -1, dtype=np.int64)
    k_of[regions] = np.arange(regions.size)
    pts = np.flatnonzero(reached)
    ka = k_of[labels[pts]]
    others = dist[:, pts].copy()
    others[ka, np.arange(pts.size)] = np.inf
    kb = np.argmin(others, axis=0)
    seeds = np.asarray(seeds_mm, dtype=float).reshape(-1, 3)
    inner = np.zeros(seed_labels.size, dtype=bool) if interior is None else np.asarray(interior, dtype=bool)
    read_on = inner if reading is None else np.asarray(reading, dtype=bool)
    tree = cKDTree(seeds)
    nearest_seed_mm = tree.query(seeds, k=2)[0][:, 1] if len(seeds) > 1 else np.zeros(1)
    _, around = tree.query(graph.points_mm[pts], k=min(SPACING_K, len(seeds)))
    spacing_mm = np.median(nearest_seed_mm[np.asarray(around).reshape(pts.size, -1)], axis=1)
    h = SEAM_KERNEL * np.maximum(spacing_mm, 1e-3)      # coincident seeds: no zero width
    has_other = np.isfinite(others[kb, np.arange(pts.size)])
    for pair in np.unique(np.stack([ka[has_other], kb[has_other]], axis=1), axis=0):
        here = has_other & (ka == pair[0]) & (kb == pair[1])
        p, hp = pts[here], h[here]
        ra, rb = regions[pair[0]], regions[pair[1]]
        of_a, of_b = np.flatnonzero(seed_labels == ra), np.flatnonzero(seed_labels == rb)
        # Each seed's place on the way from A to B (its partner in the pair only names the
        # other region).
        cross_a = cross_b = None
        if seed_peaks_mm is not None:
            # Only beside another region: the seam passes there. Inside its region a seed
            # reading another material is a misfit (densify probes around it), not a seam.
            cross_a = reads_other_side(seed_peaks_mm, seed_labels, read_on, of_a, int(rb)) & ~inner[of_a]
            cross_b = reads_other_side(seed_peaks_mm, seed_labels, read_on, of_b, int(ra)) & ~inner[of_b]
        pair_levels = seed_levels if seed_peaks_mm is None else _pair_levels(seed_peaks_mm, seed_labels, read_on,
                                                                           int(ra), int(rb))
        s_a, _, usable = seam_fractions(pair_levels, seed_labels, of_a, np.full(of_a.size, of_b[0]), read_on,
                                        cross_a=cross_a)
        _, s_b, _ = seam_fractions(pair_levels, seed_labels, np.full(of_b.size, of_a[0]), of_b, read_on,
                                    cross_b=cross_b)
        if not usable.any():
            continue                       # the two levels overlap: the plain midway split
        members = np.concatenate([of_a, of_b])
        frac = np.concatenate([s_a, s_b])
        level, decided = _local_linear_at(graph.points_mm[p], hp, seeds[members], frac)
        out[p[decided]] = np.where(level[decided] > 0.5, rb, ra)
    return out


def _local_linear_at(points_mm: np.ndarray, width_mm: np.ndarray, seeds_mm: np.ndarray, values: np.ndarray,
                     ridge: float = LOCAL_FIT_RIDGE) -> tuple[np.ndarray, np.ndarray]:
    """The value at each point (P,3) of a linear function fitted to ``values`` (S,) at
    ``seeds_mm`` (S,3), weighted by a Gaussian of sigma ``width_mm`` (P,) around the point
    (seeds beyond 3 sigma left out): (value (P,), decided (P,) bool: some seed in reach).

    The slopes carry a ridge of ``ridge`` x the weights' sum x width^2: seeds on a surface
    say nothing about the slope along its normal (pinned to 0), nor across a single row of
    seeds (the fit is then the row's own); along the surface the data's own weight is
    about the sum x (width / 0.75)^2, so the ridge barely moves it. The value is clipped to
    the range of the values in reach: the fit interpolates, it does not extrapolate."""
    p = np.asarray(points_mm, dtype=float).reshape(-1, 3)
    h = np.asarray(width_mm, dtype=float).reshape(-1)
    value, decided = np.zeros(p.shape[0]), np.zeros(p.shape[0], dtype=bool)
    tree = cKDTree(seeds_mm)
    # In chunks: a seed-to-point table over a whole cloud (every point beside another region
    # is fitted) would grow with the cloud.
    for start in range(0, p.shape[0], LOCAL_FIT_CHUNK):
        part = slice(start, start + LOCAL_FIT_CHUNK)
        value[part], decided[part] = _local_linear_chunk(p[part], h[part], tree, seeds_mm, values, ridge)
    return value, decided


def _local_linear_chunk(p: np.ndarray, h: np.ndarray, tree: cKDTree, seeds_mm: np.ndarray, values: np.ndarray,
                        ridge: float) -> tuple[np.ndarray, np.ndarray]:
    near = cKDTree(p).sparse_distance_matrix(tree, 3.0 * float(h.max()), output_type="coo_matrix")
    keep = near.data <= 3.0 * h[near.row]
    row, col, d_mm = near.row[keep], near.col[keep], near.data[keep]
    w = np.exp(-0.5 * (d_mm / h[row]) ** 2)
    x = np.concatenate([np.ones((row.size, 1)), seeds_mm[col] - p[row]], axis=1)     # centred on the point
    n = p.shape[0]
    normal = np.zeros((n, 4, 4))
    rhs = np.zeros((n, 4))
    for i in range(4):
        rhs[:, i] = np.bincount(row, w * x[:, i] * values[col], minlength=n)
        for j in range(i, 4):
            normal[:, i, j] = normal[:, j, i] = np.bincount(row, w * x[:, i] * x[:, j], minlength=n)
    decided = normal[:, 0, 0] > 1e-9
    slope_ridge = ridge * normal[:, 0, 0] * h ** 2
    for i in range(1, 4):
        normal[:, i, i] += slope_ridge
    normal[~decided] = np.eye(4)
    value = np.linalg.solve(normal, rhs[..., None])[:, 0, 0]
    # Never beyond the values of the seeds in reach: past the last seeds (an object's rim) a
    # slope read between two of them would run on unchecked.
    low, high = np.full(n, np.inf), np.full(n, -np.inf)
    np.minimum.at(low, row, values[col])
    np.maximum.at(high, row, values[col])
    return np.where(decided, np.clip(value, low, high), value), decided


def _nearest_plane_label(point: np.ndarray, members: np.ndarray, labels: np.ndarray, min_points: int) -> int:
    """The label whose points' plane fit passes nearest to ``point`` (-1 if none has enough points)."""
    best, best_d = -1, np.inf
    for value in np.unique(labels):
        pts = members[labels == value]
        if pts.shape[0] < min_points:
            continue
        centre = pts.mean(axis=0)
        normal = np.linalg.eigh(np.cov((pts - centre).T))[1][:, 0]
        d = abs(float((point - centre) @ normal))
        if d < best_d:
            best, best_d = int(value), d
    return best


def seed_neighbours(graph: SurfaceGraph, c: Cells) -> list[tuple[int, int]]:
    """Pairs (a, b), a < b, of seeds whose cells touch (share a graph edge); cells meet only
    on a face, never across a fold."""
    coo = graph.lengths.tocoo()
    a, b = c.source[coo.row], c.source[coo.col]
    ok = (a >= 0) & (b >= 0) & (a != b)
    return sorted({(int(min(x, y)), int(max(x, y))) for x, y in zip(a[ok], b[ok])})


def shared_border(graph: SurfaceGraph, c: Cells, pairs: np.ndarray) -> np.ndarray:
    """(E,) how long the border between the cells of each pair of seeds (E,2) is, counted in
    graph edges joining the two cells (0 where they do not touch): with the pair's distance,
    the area whose label depends on where their boundary is drawn."""
    p = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    coo = graph.lengths.tocoo()
    a, b = c.source[coo.row], c.source[coo.col]
    ok = (a >= 0) & (b >= 0) & (a < b)
    n = max(int(c.source.max(initial=-1)) + 1, int(p.max(initial=-1)) + 1, 1)
    counts = np.bincount(a[ok] * n + b[ok], minlength=n * n)
    lo, hi = np.minimum(p[:, 0], p[:, 1]), np.maximum(p[:, 0], p[:, 1])
    return counts[lo * n + hi].astype(float)


def boundary_points(graph: SurfaceGraph, labels: np.ndarray) -> np.ndarray:
    """Indices of cloud points with a graph neighbour of another label (the map's boundary)."""
    lab = np.asarray(labels).reshape(-1)
    coo = graph.lengths.tocoo()
    return np.unique(coo.row[lab[coo.row] != lab[coo.col]])
