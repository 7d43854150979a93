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


def estimate_plan(inputs: SessionInputs, expected_regions: int = 2, mean_travel_mm: float = 80.0) -> Estimate:
    """Estimate contacts, force steps and robot time of the whole plan."""
    plan = inputs.plan
    ph = plan.phases
    per: dict[str, float] = {}
    contacts = steps = 0
    # Cloud sweep: raster lines over the object at the scanner's rate.
    per["cloud"] = 0.0
    if plan.cloud.source == "scan":
        per["cloud"] = 400.0 / (plan.cloud.sweep_spacing_mm * inputs.cell.scanner.rate_hz) * 4 + 20.0
    n_survey = plan.sampling.units + len(plan.targets)
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
                    budget_s=plan.budget.max_robot_hours * 3600.0)
