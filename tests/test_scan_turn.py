"""A survey line turned at a border feeds the regions' features only: the models learn from
steps along the plan's scan rule, and a turned target is never characterized (docs/design.md
§3, "at a border the line turns")."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from elastoprobe.controller import phases
from elastoprobe.controller.core.geometry import follows_scan_rule, scan_direction
from elastoprobe.controller.journal import StepPlan
from elastoprobe.controller.learning.profiles import ProfileGrid
from elastoprobe.controller.probe import ProbeTarget

UP = np.array([0.0, 0.0, 1.0])
RULE = np.array([0.0, 1.0, 0.0])      # the plan's reference direction: t = +y on a level top
TURNED = np.cross(UP, RULE)           # a quarter turn about the normal: t = -x
GRID = ProfileGrid(span_mm=80.0, samples=16)


def test_only_the_rules_own_direction_follows_it() -> None:
    tilted = np.array([0.0, 0.3, 0.954])
    assert follows_scan_rule(UP, RULE, RULE)
    assert follows_scan_rule(tilted, scan_direction(tilted, RULE), RULE)
    assert not follows_scan_rule(UP, TURNED, RULE)
    assert not follows_scan_rule(UP, -TURNED, RULE)
    assert not follows_scan_rule(UP, -RULE, RULE)     # a mirrored line: its angles mean 180 - a


class _Journal:
    """The two calls collect_region_steps makes, over steps held in memory."""

    def __init__(self, plans: list[StepPlan]) -> None:
        self.plans = plans

    def steps(self, statuses=None, phase=None):
        return [SimpleNamespace(step_id=p.step_id, plan=p) for p in self.plans]

    def step_result(self, step_id: int):
        depth = np.full(GRID.samples, 0.1 * (step_id + 1))
        return SimpleNamespace(profile_depth_mm=depth, summary={}, reference_pose=None,
                               scan_force_n=np.tile([0.0, 0.0, 4.0], (3, 1)))


def _plan(step_id: int, target: int, t: np.ndarray, angle_deg: float = 90.0) -> StepPlan:
    return StepPlan(step_id, target, np.array([10.0 * target, 0.0, 30.0]), UP, t, angle_deg, 4.0, step_id)


def test_steps_of_a_turned_line_are_left_out_of_the_region_models_data() -> None:
    journal = _Journal([_plan(0, 0, RULE), _plan(1, 1, TURNED), _plan(2, 1, -TURNED, 45.0), _plan(3, 2, RULE)])
    geometry = phases.ScanGeometry(GRID, None, None, 5.0, tuple(RULE))
    steps = phases.collect_region_steps(journal, {0: 0, 1: 0, 2: 0}, 0, geometry)
    assert steps.point_ids.tolist() == [0, 2]
    np.testing.assert_allclose(steps.depth_mm[:, 0], [0.1, 0.4])


def test_a_turned_target_is_not_characterized(monkeypatch: pytest.MonkeyPatch) -> None:
    """Region 0's most interior target was turned at a border (in this toy, turned targets are
    the ones far from region 1): the choice passes it over for the next one."""
    points = np.array([[-80.0, 0.0, 30.0], [-60.0, 0.0, 30.0], [-20.0, 0.0, 30.0], [40.0, 0.0, 30.0]])
    ts = [TURNED, RULE, RULE, RULE]
    targets = {i: ProbeTarget(i, points[i], UP, ts[i]) for i in range(4)}
    plan = SimpleNamespace(sampling=SimpleNamespace(reference_direction=tuple(RULE)),
                           phases=SimpleNamespace(characterize=SimpleNamespace(points_per_region=1,
                                                                               angles_deg=[45.0, 90.0, 135.0])))
    ctx = SimpleNamespace(journal=_Journal([]), inputs=SimpleNamespace(plan=plan), targets=targets, edge_flag={},
                          log=lambda *a, **k: None)
    monkeypatch.setattr(phases, "_clear_angles", lambda ctx, target, angles: list(angles))
    chosen, _ = phases._characterize_choice(ctx, {0: 0, 1: 0, 2: 0, 3: 1}, 2, points, [0, 1, 2, 3])
    assert chosen == [1, 3]
