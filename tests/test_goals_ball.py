"""Issue 3's rubber-ball goals on a full simulated session of config/plans/rubber_ball.yaml
(slow: a few minutes of wall time), judged against the simulator's ground truth."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from test_goals_composite import assert_whole_profile_goals

ROOT = Path(__file__).resolve().parent.parent
pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800)]


@pytest.fixture(scope="module")
def ball_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from elastoprobe.controller.cli import main

    out = tmp_path_factory.mktemp("ball") / "session"
    assert main(["run", str(ROOT / "config" / "plans" / "rubber_ball.yaml"), "--out", str(out), "--seed", "1"]) == 0
    return out


def test_homogeneous_ball_is_one_region_and_meets_the_profile_goals(ball_session: Path) -> None:
    from elastoprobe.controller.evaluation import evaluate_session

    ev = evaluate_session(ball_session)
    assert ev["regions_found"] == 1
    goal = max(1.5 * ev["noise_floor_mm"], 0.03 * ev["peak_depth_mm"])
    assert ev["profile_rmse_mm"]["held_out_angles"] <= goal
    assert_whole_profile_goals(ev)


def _between(session_dir: Path) -> dict:
    """unseen_force_between on the final model, over the evaluation's region of interest
    (truth-free part: |x| beyond the tip, seen by the scanner on that side in at least half
    of the characterization profiles, deeper than 5 % of the upper force's peak)."""
    from elastoprobe.controller.evaluation import _inputs_of
    from elastoprobe.controller.journal import Journal
    from elastoprobe.controller.learning.evaluate import roi_mask, unseen_force_between
    from elastoprobe.controller.learning.models import RegionModel

    j = Journal.open_readonly(session_dir)
    try:
        inputs = _inputs_of(j)
        final = j.phase("final", 0)
        models = j.phase("models", int(final.outputs["model_round"]))
        done = [r for r in j.steps(statuses=["done"]) if r.phase == "regions"]
        seen: dict[bool, np.ndarray] = {}
        count: dict[bool, int] = {}
        for rec in done:
            key = rec.plan.angle_deg <= 90.0
            seen[key] = seen.get(key, 0) + np.isfinite(j.step_result(rec.step_id).profile_depth_mm)
            count[key] = count.get(key, 0) + 1
    finally:
        j.close()
    model = RegionModel.load(session_dir / models.outputs["regions"]["0"]["path"])
    x = model.x_mm
    radius = inputs.cell.tool.tip_radius_mm

    def roi(force_n: float, angle_deg: float, upper: np.ndarray) -> np.ndarray:
        key = angle_deg <= 90.0
        return roi_mask(upper[None])[0] & (np.abs(x) > radius) & (seen[key] >= 0.5 * count[key])

    ch = inputs.plan.phases.characterize
    return unseen_force_between(model, np.array(ch.forces_n), np.array(ch.angles_deg), roi=roi)


def test_unseen_force_lies_between_the_trained_forces_at_every_roi_sample(ball_session: Path) -> None:
    # Issue 3: at every trained angle, the profile at each midpoint of adjacent trained
    # forces lies between theirs at every ROI sample (no tolerance). Training penalises
    # non-monotone behaviour in force (models.py); the served bounds (issue 14) lie far
    # outside these profiles, so clipping plays no part here.
    res = _between(ball_session)
    assert res["cases"] == 4 * 9
    assert res["fraction"] == 1.0, res["failed_cases"]

