"""A plan for any object from its size, by one rule (no per-object tuning).

``plan_for_object(outline_of(mesh), cell, ...)`` returns a plan (the YAML's dict) for an
object given only its mesh's extent and footprint and the cell's limits.
``elastoprobe sim object`` writes it beside each generated object, and the mapping
suite runs every object with it. Each setting and why (the same table, with the shipped
plans beside it, is in docs/generated_objects.md):

- **Forces.** A soft layer of height h pressed by the tip spreads its load over a patch
  whose size grows with h (the Winkler-Pasternak decay length of a layer is a fraction
  of its thickness), so the strain under the tip goes as F / (E h^2): the largest force
  is scaled as h^2 from the shipped user object's (20 N on its 40 mm block),
  ``F_max = 20 N x (h / 40 mm)^2``, clamped to [10 N, 20 N] (10 N: the smallest
  characterization force, a tenth of F_max, must be twice the force tolerance of 0.5 N;
  20 N: the shipped ceiling; heavier presses add no map information) and to the cell's
  ``max_force_n / 1.5`` (the plan's limit stays 1.5 x the largest commanded force, as in
  the shipped plans). Characterization at F_max x (0.1, 0.25, 0.45, 0.7, 1.0): exactly
  the shipped 2, 5, 9, 14, 20 N at 20 N. Survey at F_max x (0.15, 0.45): 3 and 9 N at
  20 N, between the shipped demo's 4/12 N and the user object's 2/6 N. Forces are
  rounded to 0.5 N.
- **Neural-gas units** in proportion to the footprint (the area of the convex hull of the
  mesh seen from above): one per 625 mm^2, i.e. a mean spacing of 25 mm, so any inclusion
  wider than 25 x sqrt(2) = 35 mm holds a survey target wherever it lies (on a square grid;
  the neural gas spreads its units about as evenly); smaller ones are densification's.
  Clamped to [16, 120]: 16 leaves a few survey points to each of up to four materials,
  120 caps the survey at 240 steps (about an hour of robot time).
- **Smallest inclusion** ``sampling.min_feature_mm`` = 15 mm: the requirement the suite
  states (docs/generated_objects.md, "The smallest feature the survey finds"): (nearly)
  every inclusion 15 mm across or larger holds a survey target. The session raises the units
  above until the targets' spacing over the probe-able top meets it
  (learning/survey_density.py: N = A (1.6 / 15 mm)^2, about one unit per 88 mm^2 against
  625 above); the budget is sized for that survey with the footprint standing in for the
  probe-able area (the top lies within it; the session's 5 mm squares can over-reach it by
  a little; on 1012 the session took 596 units, the footprint gives 615). This, not the
  footprint rule, sets the survey on every suite object; the footprint rule's units stay
  its floor (the session never lowers them).
- **Tilt** 30 degrees: what the sweep sees. The scanner looks 51.3 degrees off the probe
  axis, in the plane across the sweep's lines; a face sloping by t along the lines (base
  y) meets the laser at incidence acos(cos 51.3 cos t) from either heading, 57 degrees at
  t = 30: within what every library material returns light at (60-75 degrees) but the
  darkest foam's (55), so the surface the plan claims is about the surface its sweep can
  cover (a face sloping across the lines is seen by one heading at 51.3 - t).
- **Sweep**: profiles 3 mm apart (a point of the surface is then within 1.5 mm of a
  profile, inside the 2 mm that counts as covered, with 0.5 mm for the line's own sample
  spacing and noise), 40 mm above the top (the shipped plans').
- **Densify**: resolution 6 mm (an edge that short has located its piece of boundary to
  3 mm, the boundary goal), min spacing 3 mm (the least the plan schema allows with that
  resolution), 3 rounds (each halves the gaps: 25 -> 12.5 -> 6.25 mm), points per round
  2 x ceil(sqrt(survey units)) clamped to [8, 64] (a seam across the top crosses about
  sqrt(units) edges of the survey graph; each round finds about twice as many). The survey's
  units, not the footprint rule's: with the 15 mm survey the graph is finer, and on suite
  slab 1003 (four materials, two inclusions, 433 survey points) 79 edges disagreed after
  round 0; 16 points a round, the footprint rule's, left 66 of them longer than 6 mm after
  three rounds. Each point is one survey contact per survey force; at 64 (a survey of
  1024 units and up, the composite's) a round is about 16 robot minutes of contacts.
- **Contact search**: at most half the object's height past its nominal surface (at least
  5 mm; the cell's 30 mm on anything 60 mm or taller). The search must end above the
  table: on a 20 mm slab the cell's 30 mm would take the tip below the workspace's floor,
  and planning drops every such target (a 23 mm dome lost 38 of its 46). Half the height
  still reaches well past where a registered object's surface can be (millimetres off).
- **Model**: the profile span is 2/3 of the footprint's shorter side, rounded to 10 mm,
  in [40, 80] mm (80 mm on the composite and 60 mm on the user object, as shipped).
- **Budget**: the steps the phases can take with four materials, plus a quarter
  (retries, the densify rounds' survey), rounded up to 50; robot hours: 4 (shipped), or
  for a plan that needs more, its steps (plus the quarter) at 10 s each, rounded up to a
  whole hour (a survey step is about 7.6 s of robot time on the default cell: ``elastoprobe
  check`` gives 140 min for 553 two-force survey contacts on suite object 1012).
- Probing, angles, fault policy, edge clearance (three tip radii) and the scan direction
  (t along base y, keeping the wrist clear of the base) are the shipped plans'.

Frames and units: the object frame (mm, z up, table at z = 0); N; degrees.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull

from .core.config import CellSpec, ProbingSpec
from .core.geometry import NINE_ANGLES_DEG, Pose
from .core.kinematics import inverse
from .core.validation import arm_model_for
from .learning.survey_density import units_for_min_feature
from .probe import standoff_pose

REFERENCE_HEIGHT_MM = 40.0
REFERENCE_FORCE_N = 20.0
MIN_LARGEST_FORCE_N = 10.0
LIMIT_OVER_LARGEST = 1.5
CHARACTERIZE_FRACTIONS = (0.1, 0.25, 0.45, 0.7, 1.0)
SURVEY_FRACTIONS = (0.15, 0.45)
AREA_PER_UNIT_MM2 = 625.0
UNITS_RANGE = (16, 120)
MAX_TILT_DEG = 30.0
SWEEP_SPACING_MM = 3.0
SWEEP_HEIGHT_MM = 40.0
DENSIFY_RESOLUTION_MM = 6.0
DENSIFY_ROUNDS = 3
DENSIFY_POINTS_RANGE = (8, 64)
MAX_MATERIALS = 4
PROBING = ProbingSpec()          # the plan format's probing defaults, written out in full
MIN_SEARCH_MM = 5.0
MIN_FEATURE_MM = 15.0            # the suite's requirement: every inclusion this wide holds a survey target
BUDGET_HOURS = 4.0
BUDGET_S_PER_STEP = 10.0


@dataclass(frozen=True)
class ObjectOutline:
    """What the rule knows of an object: its bounding box (mm, object frame) and footprint area (mm^2)."""

    bounds_min_mm: np.ndarray
    bounds_max_mm: np.ndarray
    footprint_area_mm2: float

    @property
    def height_mm(self) -> float:
        return float(self.bounds_max_mm[2] - max(self.bounds_min_mm[2], 0.0))

    @property
    def size_mm(self) -> np.ndarray:
        return self.bounds_max_mm - self.bounds_min_mm


def outline_of(mesh: Any) -> ObjectOutline:
    """The outline of a mesh (a trimesh.Trimesh or anything with ``vertices`` (V,3) in mm)."""
    v = np.asarray(mesh.vertices, dtype=float)
    hull = ConvexHull(v[:, :2])
    return ObjectOutline(v.min(axis=0), v.max(axis=0), float(hull.volume))   # a 2-D hull's "volume" is its area


def _half(value: float) -> float:
    """To the nearest 0.5 (halves up)."""
    return math.floor(value * 2.0 + 0.5) / 2.0


def largest_force_n(height_mm: float, cell_max_force_n: float) -> float:
    """The largest force (N) for an object of this height (mm) on a cell with this limit (module docstring)."""
    scaled = REFERENCE_FORCE_N * (height_mm / REFERENCE_HEIGHT_MM) ** 2
    return _half(min(max(scaled, MIN_LARGEST_FORCE_N), REFERENCE_FORCE_N, cell_max_force_n / LIMIT_OVER_LARGEST))


def survey_forces_n(largest_n: float) -> list[float]:
    return [_half(largest_n * f) for f in SURVEY_FRACTIONS]


def characterize_forces_n(largest_n: float) -> list[float]:
    return [_half(largest_n * f) for f in CHARACTERIZE_FRACTIONS]


def forces_for_height(height_mm: float, cell: CellSpec) -> tuple[float, float]:
    """(the larger survey force, the largest force) in N: what a generated object's materials must suit."""
    largest = largest_force_n(height_mm, cell.limits.max_force_n)
    return survey_forces_n(largest)[-1], largest


def search_distance_mm(height_mm: float, cell_search_mm: float) -> float:
    """How far past the nominal surface the contact search may go (mm): half the object's height,
    at least 5 mm, at most the cell's (module docstring)."""
    return float(min(cell_search_mm, max(MIN_SEARCH_MM, math.floor(height_mm / 2.0))))


def units_for(outline: ObjectOutline) -> int:
    return int(np.clip(round(outline.footprint_area_mm2 / AREA_PER_UNIT_MM2), *UNITS_RANGE))


def plan_for_object(outline: ObjectOutline, cell: CellSpec, name: str, object_file: str,
                    cell_file: str | None = None, seed: int = 1) -> dict[str, Any]:
    """The plan (a dict in the plan file's layout) for an object of this outline on this cell.

    ``object_file`` is written as the plan's ``simulated_object`` and ``cell_file`` (None:
    the default simulated cell) as its ``cell``, both as given (relative to the plan).
    """
    largest = largest_force_n(outline.height_mm, cell.limits.max_force_n)
    survey = survey_forces_n(largest)
    characterize = characterize_forces_n(largest)
    units = units_for(outline)
    angles = [float(a) for a in NINE_ANGLES_DEG]
    survey_units = max(units, units_for_min_feature(outline.footprint_area_mm2, MIN_FEATURE_MM))
    points_per_round = int(np.clip(2 * math.ceil(math.sqrt(survey_units)), *DENSIFY_POINTS_RANGE))
    steps = (survey_units * len(survey) + MAX_MATERIALS * 2 * len(angles) * len(characterize)
             + DENSIFY_ROUNDS * points_per_round * len(survey))
    hours = max(BUDGET_HOURS, float(math.ceil(1.25 * steps * BUDGET_S_PER_STEP / 3600.0)))
    shorter = float(min(outline.size_mm[0], outline.size_mm[1]))
    plan: dict[str, Any] = {"name": name}
    if cell_file is not None:
        plan["cell"] = cell_file
    plan.update({
        "simulated_object": object_file,
        "seed": int(seed),
        "cloud": {"source": "scan", "sweep_spacing_mm": SWEEP_SPACING_MM, "sweep_height_mm": SWEEP_HEIGHT_MM},
        "sampling": {"units": units, "min_feature_mm": MIN_FEATURE_MM, "geometry_weight": 1.0,
                     "edge_clearance_mm": 3.0 * cell.tool.tip_radius_mm,
                     "max_tilt_deg": MAX_TILT_DEG, "reference_direction": [0.0, 1.0, 0.0]},
        "probing": {"scans_per_step": 30, "settle_s": PROBING.settle_s, "standoff_mm": PROBING.standoff_mm,
                    "force_rate_n_s": PROBING.force_rate_n_s, "force_tolerance_n": PROBING.force_tolerance_n},
        "phases": {
            "survey": {"angles_deg": [90.0], "forces_n": survey},
            "characterize": {"points_per_region": 2, "angles_deg": angles, "forces_n": characterize},
            "densify": {"rounds": DENSIFY_ROUNDS, "points_per_round": points_per_round,
                        "min_spacing_mm": DENSIFY_RESOLUTION_MM / 2.0, "resolution_mm": DENSIFY_RESOLUTION_MM},
        },
        "budget": {"max_steps": int(50 * math.ceil(1.25 * steps / 50)), "max_robot_hours": hours},
        "model": {"hidden_units": 45, "ensemble": 4, "max_epochs": 2000,
                  "profile_span_mm": float(np.clip(10 * round(shorter * 2.0 / 3.0 / 10), 40, 80)),
                  "profile_samples": 256},
        "limits": {"max_force_n": _half(min(LIMIT_OVER_LARGEST * largest, cell.limits.max_force_n)),
                   "search_distance_mm": search_distance_mm(outline.height_mm, cell.limits.search_distance_mm)},
        "fault_policy": {"default": {"action": "retry", "retries": 2},
                         "kinds": {"no_contact": {"action": "skip_target"}, "emergency_stop": {"action": "pause"}}},
    })
    return plan


def reach_problems(outline: ObjectOutline, cell: CellSpec) -> list[str]:
    """Where the arm cannot press the object's top along +z (empty: it can at its centre and
    corners; IK at the standoff). Whether the object lies inside the workspace and clear of the
    keep-outs is the object loader's check (cellfactory.load_object_model), on the mesh itself."""
    b2o = cell.object.base_to_object.pose()
    lo, hi = outline.bounds_min_mm, outline.bounds_max_mm
    problems = []
    model = arm_model_for(cell)
    seed = np.radians(np.asarray(cell.robot.home_joints_deg, dtype=float))
    up, t = b2o.apply_vector(np.array([0.0, 0.0, 1.0])), b2o.apply_vector(np.array([0.0, 1.0, 0.0]))
    top = [np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2]])]
    top += [np.array([x, y, hi[2]]) for x in (lo[0], hi[0]) for y in (lo[1], hi[1])]
    for p in top:
        pose: Pose = standoff_pose(b2o.apply(p), up, t, 90.0, cell.tool.tip_radius_mm, PROBING.standoff_mm)
        if inverse(model, pose, seed) is None:
            problems.append(f"the arm cannot reach above the object's top at {np.round(p, 1).tolist()} mm")
    return problems
