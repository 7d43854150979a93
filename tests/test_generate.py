"""Generated objects (sim/generate.py): deterministic, loadable, painted finely enough, valid
physics, plausible contrasts, fitting the default cell; the fixed suite covers every shape
and pattern."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller.cellfactory import placement_problem
from elastoprobe.controller.core.config import DEFAULT_CELL, load_cell
from elastoprobe.controller.planrule import forces_for_height, outline_of, reach_problems
from elastoprobe.sim import generate as gen
from elastoprobe.sim.objects import load_object

CELL, _ = load_cell(DEFAULT_CELL)


def rule_forces(height_mm: float) -> tuple[float, float]:
    return forces_for_height(height_mm, CELL)


@pytest.fixture(scope="module")
def suite_objects() -> list[gen.GeneratedObject]:
    return [gen.generate(e.seed, e.shape, e.pattern, e.pairs, forces=rule_forces) for e in gen.suite()]


def test_the_suite_covers_every_shape_and_pattern_with_fixed_seeds() -> None:
    entries = gen.suite()
    assert len(entries) == 12 and [e.seed for e in entries] == list(range(1001, 1013))
    assert {e.shape for e in entries} == set(gen.SHAPES)
    assert {e.pattern for e in entries} == set(gen.SURFACE_PATTERNS) | set(gen.COMPOSITE_PATTERNS)
    assert sum(e.pairs == "near" for e in entries) >= 3
    more = gen.suite(14)
    assert more[:12] == entries and (more[12].seed, more[12].shape) == (1101, entries[0].shape)
    assert entries[3].cli_args() == ["--seed", "1004", "--shape", "block", "--pattern", "strip", "--pairs", "near"]


def test_a_seed_gives_the_same_object_and_another_seed_another() -> None:
    a = gen.generate(7, forces=rule_forces)
    b = gen.generate(7, forces=rule_forces)
    assert (a.shape, a.pattern, a.materials.specs) == (b.shape, b.pattern, b.materials.specs)
    assert np.array_equal(a.painted.vertices, b.painted.vertices) and np.array_equal(a.painted.faces, b.painted.faces)
    assert np.array_equal(a.painted.labels, b.painted.labels)
    c = gen.generate(8, a.shape.kind, a.pattern.kind, forces=rule_forces)
    assert c.shape != a.shape


def test_every_suite_object_loads_with_its_paint_valid_physics_and_contrast(
        suite_objects: list[gen.GeneratedObject], tmp_path: Path) -> None:
    for obj in suite_objects:
        path = gen.write_object(obj, tmp_path / obj.name)
        loaded = load_object(path)
        n = len(obj.materials.names)
        assert loaded.region_names == obj.materials.names and len(loaded.region_names) == n
        # The PLY's colours give back every face's material (the table's faces are not in it).
        counts = np.bincount(loaded.face_labels, minlength=n)
        assert np.array_equal(counts, np.bincount(obj.painted.labels, minlength=n))
        assert np.all(counts > 0)
        assert float(loaded.mesh.vertices[:, 2].min()) == pytest.approx(0.0, abs=1e-4)
        # Inside the simulator's validity at the plan's largest force (what the session checks).
        assert loaded.validity_report(obj.forces_n[1], 5.0) == [], obj.name
        # The paint renders every seam within 1 mm with faces of about a millimetre along it.
        err = gen.seam_render_error_mm(obj.painted)
        assert err["from_seam_mm"] <= 1.0 and err["to_mesh_mm"] <= 1.0, (obj.name, err)
        assert err["face_mm"] <= 2.5, (obj.name, err)
        # Contrast in survey dent: a near pair about 3x, every other pair at least 3.5x.
        c = obj.materials.contrast()
        for i, j, ratio in c["pairs"]:
            if obj.materials.near_pair == (i, j):
                assert 2.7 <= ratio <= 3.3, (obj.name, c)
            else:
                assert ratio >= 3.45, (obj.name, c)
        # Fits the default cell: reachable, inside the workspace and clear of the keep-outs.
        assert reach_problems(outline_of(obj.mesh()), CELL) == [], obj.name
        assert placement_problem(obj.mesh().vertices, CELL) is None, obj.name


def test_near_and_far_pairs_are_honoured(suite_objects: list[gen.GeneratedObject]) -> None:
    for entry, obj in zip(gen.suite(), suite_objects):
        if entry.pairs == "near":
            assert obj.materials.near_pair == (0, 1)
        if entry.pairs == "far":
            assert obj.materials.near_pair is None


def test_materials_span_the_library_and_composites_carry_a_stiff_part(
        suite_objects: list[gen.GeneratedObject]) -> None:
    families = {f for obj in suite_objects for f in obj.materials.families}
    assert families >= {"foam", "sponge", "gel", "elastomer", "hard_rubber"}
    for obj in suite_objects:
        if obj.shape.kind == "composite":
            assert obj.materials.families[0] in gen.SOFT_FAMILIES
            assert obj.materials.families[1] in gen.TOP_PART_FAMILIES
        for spec in obj.materials.specs:
            if spec["kind"] == "foam":
                # The layer under the probe: its thickness is the object's height there.
                assert 10.0 <= spec["thickness_mm"] <= obj.shape.max_height_mm + 1e-6


@pytest.mark.parametrize("shape", ["slab", "block", "dome", "sheet"])
def test_every_shape_takes_the_curved_patterns_with_the_seams_rendered(shape: str) -> None:
    for k, pattern in enumerate(("ring", "wavy_seam", "two_inclusions", "curved_seam")):
        drawn = gen.draw_shape(shape, np.random.default_rng([k, 1]), pattern)
        painted_pattern = gen.draw_pattern(pattern, drawn, np.random.default_rng([k, 2]))
        painted = gen.build_mesh(drawn, painted_pattern)
        assert len(np.unique(painted.labels)) == painted_pattern.n_materials, (shape, pattern)
        err = gen.seam_render_error_mm(painted)
        assert err["from_seam_mm"] <= 1.0 and err["to_mesh_mm"] <= 1.0, (shape, pattern, err)


def test_unknown_or_mismatched_shape_and_pattern_are_refused() -> None:
    with pytest.raises(ValueError, match="unknown shape"):
        gen.generate(1, "cube")
    with pytest.raises(ValueError, match="composite takes one of the patterns box, plate"):
        gen.generate(1, "composite", "disc")
    with pytest.raises(ValueError, match="slab takes one of the patterns"):
        gen.generate(1, "slab", "box")
    with pytest.raises(ValueError, match="pairs"):
        gen.generate(1, pairs="close")


def test_a_small_block_drawn_for_two_inclusions_is_drawn_again_not_a_traceback() -> None:
    # Seed 3001 draws a block 138 x 120 mm for two inclusions and a strip: no room for both
    # 15 mm apart, and `elastoprobe sim object --seed 3001` ended in a traceback. The shape
    # is drawn again; a seed whose first shape fits keeps it.
    obj = gen.generate(3001, forces=rule_forces)
    assert obj.shape.kind == "block" and obj.pattern.kind == "two_inclusions_and_strip"
    assert len(obj.pattern.features) == 3
    again = gen.generate(3067, "block", "two_inclusions", forces=rule_forces)
    assert len(again.pattern.features) == 2
    first = gen.draw_shape("slab", np.random.default_rng([3002, 1]), "disc")
    assert gen.generate(3002, "slab", "disc", forces=rule_forces).shape == first


@pytest.mark.parametrize("exponent", [6.0, 8.0, 10.0])
def test_every_ring_chord_is_an_edge_of_the_top_so_the_mesh_has_no_hole_at_a_corner(exponent: float) -> None:
    # Seed 1803's slab lost one face at a rounded corner ("not closed above the table: 3 bad
    # edges"): beside a seam's crossing point the ring's chord was 1.28 mm, a seam row point
    # 0.7 mm inside along the ray from the centre lay 0.59 mm from its midpoint, and the
    # ghost ring outside took that chord's place. Here: rings with crossings inserted as the
    # generator does and rows at its insets; before the fix 5 of these 30 rings had a hole.
    fp = gen.Footprint(120.0, 80.0, exponent)
    dense = fp.boundary(0.05)
    for seed in range(10):
        picked = dense[np.sort(np.random.default_rng(seed).choice(len(dense), 40, replace=False))]
        crossings = picked[np.r_[True, np.linalg.norm(np.diff(picked, axis=0), axis=1) > 2.0]]
        ring = gen._ring_with(fp, fp.boundary(gen.RING_STEP_MM), crossings)
        rows = [gen._resample(fp.inset_points(ring, inset), 0.8, True) for inset in (0.7, 0.75, 0.9, 1.2)]
        _, faces = gen._top_faces(fp, ring, rows)
        edges = np.sort(np.vstack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        uniq, counts = np.unique(edges, axis=0, return_counts=True)
        found = {(int(a), int(b)): int(c) for (a, b), c in zip(uniq, counts)}
        n = len(ring)
        chords = {(min(i, (i + 1) % n), max(i, (i + 1) % n)) for i in range(n)}
        assert [c for c in chords if found.get(c) != 1] == [], (exponent, seed)
        assert all(c == 2 for e, c in found.items() if e not in chords), (exponent, seed)


def test_seed_1803_generates_a_closed_mesh() -> None:
    # What `bench/mapping_suite.py --objects 108` asks for; it ended in a traceback.
    obj = gen.generate(1803, "slab", "two_inclusions_and_strip", "far", forces=rule_forces)
    gen._check_closed_above_table(obj.painted.vertices, obj.painted.faces)
    assert len(np.unique(obj.painted.labels)) == obj.pattern.n_materials
