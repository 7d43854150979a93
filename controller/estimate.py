"""Robot-time estimate of a plan before anything moves (``elastoprobe check``).

The estimate follows the executor's sequence per contact (travel, tare,
reference scans, contact search, per force level ramp + settle + scans, unload,
retract) with the plan's speeds, so it is comparable with the robot time a
simulated run reports.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .core.config import SessionInputs, effective_motion_limits
from .learning import cloud as cl
from .learning import survey_density as sd
from .learning import targets as tg

MESH_POINTS_PER_MM2 = 0.5      # a nominal cloud of the mesh: ~40 points within the targets' 5 mm density radius
MAX_MESH_POINTS = 200_000


def trapezoid_s(distance_mm: float, speed_mm_s: float, accel_mm_s2: float) -> float:
    """Duration (s) of a rest-to-rest move with a trapezoidal speed profile."""
    d = abs(distance_mm)
    if d == 0:
        return 0.0
    ramp_mm = speed_mm_s * speed_mm_s / accel_mm_s2
    if d <= ramp_mm:
        return 2.0 * float(np.sqrt(d / accel_mm_s2))
    return d / speed_mm_s + speed_mm_s / accel_mm_s2


@dataclass(frozen=True)
class Estimate:
    contacts: int
    steps: int
    robot_s: float                      # what the budget lets run
    per_phase_s: dict[str, float]
    budget_s: float = float("inf")      # the plan's max_robot_hours
    survey_targets: int = 0             # neural-gas units + explicit targets, each pressed at the survey angles

    def hours(self) -> float:
        return self.robot_s / 3600.0

    def budget_warning(self) -> str | None:
        """Said when the plan's budget stops it before its phases are done: which phases would
        not run (or not finish); None when the whole plan fits."""
        needed_s = sum(self.per_phase_s.values())
        if needed_s <= self.budget_s:
            return None
        elapsed_s, cut = 0.0, []
        for name, phase_s in self.per_phase_s.items():
            if elapsed_s + phase_s > self.budget_s:
                cut.append(name if elapsed_s >= self.budget_s else f"{name} (partly)")
            elapsed_s += phase_s
        return (f"the plan needs about {needed_s / 3600:.1f} robot h but budget.max_robot_hours stops it at "
                f"{self.budget_s / 3600:.2f} h: {', '.join(cut)} would not run"
                + ("; nothing would be probed" if cut and cut[0].startswith("cloud") else ""))


def contact_time_s(inputs: SessionInputs, forces_n: list[float], travel_mm: float) -> float:
    """Robot time of one contact at one angle through ``forces_n`` (s)."""
    plan = inputs.plan
    m = effective_motion_limits(inputs)
    pr = plan.probing
    clearance_mm = 60.0
    t = trapezoid_s(travel_mm, m["free_speed_mm_s"], m["free_accel_mm_s2"])
    t += 2 * trapezoid_s(clearance_mm, m["free_speed_mm_s"], m["free_accel_mm_s2"])
    t += 0.25                                                # tare in free air
    rate_hz = inputs.cell.scanner.rate_hz
    t += 10 / rate_hz                                        # reference scans
    t += pr.standoff_mm / m["contact_speed_mm_s"]            # contact search
    previous = 0.0
    for f in forces_n:
        t += abs(f - previous) / pr.force_rate_n_s + pr.settle_s + pr.scans_per_step / rate_hz
        previous = f
    t += (pr.standoff_mm + 5.0) / (2.0 * m["contact_speed_mm_s"])   # unload along the normal
    return t


def survey_units(inputs: SessionInputs, mesh: object | None) -> int:
    """The neural-gas units the session will train: the plan's ``sampling.units``, raised for
    ``sampling.min_feature_mm`` by the rule the session applies to its scanned cloud
    (learning.survey_density), here applied to a nominal cloud of the object's mesh (object
    frame, mm; area-uniform samples with the faces' normals): the same probe-able test (tilt,
    edge clearance, density), so the count is the session's to within what the scan misses
    (shadows make the scanned probe-able area smaller, never larger). ``mesh`` None: the plan's."""
    sampling = inputs.plan.sampling
    if sampling.min_feature_mm is None or sampling.units == 0 or mesh is None:
        return sampling.units
    area = float(getattr(mesh, "area"))
    pts, nrm = cl.sample_mesh(mesh, int(min(MAX_MESH_POINTS, max(1000.0, area * MESH_POINTS_PER_MM2))), seed=0)
    rules = tg.rules_for_plan(inputs.cell.tool.tip_radius_mm, sampling.edge_clearance_mm, sampling.max_tilt_deg,
                              sampling.min_feature_mm)
    where = tg.probeable(pts, nrm, cl.curvature(pts, k=16), rules)
    return sd.survey_units(sampling.units, sampling.min_feature_mm, pts[where])


def estimate_plan(inputs: SessionInputs, expected_regions: int = 2, mean_travel_mm: float = 80.0,
                  n_units: int | None = None) -> Estimate:
    """Estimate contacts, force steps and robot time of the whole plan; ``n_units``: the survey's
    neural-gas units (:func:`survey_units`; None: the plan's ``sampling.units``)."""
    plan = inputs.plan
    ph = plan.phases
    per: dict[str, float] = {}
    contacts = steps = 0
    # Cloud sweep: raster lines over the object at the scanner's rate.
    per["cloud"] = 0.0
    if plan.cloud.source == "scan":
        per["cloud"] = 400.0 / (plan.cloud.sweep_spacing_mm * inputs.cell.scanner.rate_hz) * 4 + 20.0
    n_survey = (plan.sampling.units if n_units is None else n_units) + len(plan.targets)
    per["survey"] = n_survey * len(ph.survey.angles_deg) * contact_time_s(inputs, ph.survey.forces_n, mean_travel_mm)
    contacts += n_survey * len(ph.survey.angles_deg)
    steps += n_survey * len(ph.survey.angles_deg) * len(ph.survey.forces_n)
    n_char = expected_regions * ph.characterize.points_per_region * len(ph.characterize.angles_deg)
    per["characterize"] = n_char * contact_time_s(inputs, ph.characterize.forces_n, 30.0)
    contacts += n_char
    steps += n_char * len(ph.characterize.forces_n)
    n_dens = ph.densify.rounds * ph.densify.points_per_round * len(ph.survey.angles_deg)
    per["densify"] = n_dens * contact_time_s(inputs, ph.survey.forces_n, mean_travel_mm)
    contacts += n_dens
    steps += n_dens * len(ph.survey.forces_n)
    steps = min(steps, plan.budget.max_steps)
    total = min(sum(per.values()), plan.budget.max_robot_hours * 3600.0)
    return Estimate(contacts=contacts, steps=steps, robot_s=total, per_phase_s=per,
                    budget_s=plan.budget.max_robot_hours * 3600.0, survey_targets=n_survey)
