"""The plan rule (controller/planrule.py) and ``elastoprobe sim object``: a valid plan for any
object from its size alone, sensible on the shipped objects, bounded by the cell's limits."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller.cli import main
from elastoprobe.controller.core.config import DEFAULT_CELL, PlanSpec, load_cell, load_plan, load_session_inputs
from elastoprobe.controller.core.yamlio import dump_yaml_text
from elastoprobe.controller.cellfactory import load_object_model
from elastoprobe.controller.core.errors import InputError
from elastoprobe.controller.planrule import ObjectOutline, largest_force_n, outline_of, plan_for_object, reach_problems
from elastoprobe.sim.objects import load_object

ROOT = Path(__file__).resolve().parent.parent
OBJECTS = ROOT / "config" / "objects"
CELL, _ = load_cell(DEFAULT_CELL)


def valid(plan: dict, tmp_path: Path, name: str = "plan.yaml") -> PlanSpec:
    path = tmp_path / name
    path.write_text(dump_yaml_text(plan), encoding="utf-8")
    return load_plan(path)[0]


def shipped_plan(object_name: str) -> dict:
    outline = outline_of(load_object(OBJECTS / f"{object_name}.yaml").mesh)
    return plan_for_object(outline, CELL, object_name.replace("_", "-"), f"{OBJECTS / object_name}.yaml")


def test_the_rule_gives_the_shipped_objects_plans_like_their_own(tmp_path: Path) -> None:
    demo, user = shipped_plan("composite"), shipped_plan("user_object")
    # Forces: the shipped characterization exactly; the survey between the two shipped ones.
    for plan in (demo, user):
        assert plan["phases"]["characterize"]["forces_n"] == [2.0, 5.0, 9.0, 14.0, 20.0]
        assert plan["phases"]["survey"]["forces_n"] == [3.0, 9.0]
        assert plan["limits"]["max_force_n"] == 30.0
        valid(plan, tmp_path)
    # Units by footprint: the user object's 120 x 90 mm block gets about its shipped 24; the
    # 400 x 300 mm composite is capped at 120 (shipped: 80).
    assert 16 <= user["sampling"]["units"] <= 24 and demo["sampling"]["units"] == 120
    assert (demo["model"]["profile_span_mm"], user["model"]["profile_span_mm"]) == (80.0, 60.0)


def test_forces_follow_the_height_within_the_cells_limits(tmp_path: Path) -> None:
    assert largest_force_n(40.0, 45.0) == 20.0 and largest_force_n(140.0, 45.0) == 20.0
    assert largest_force_n(30.0, 45.0) == 11.5
    assert largest_force_n(15.0, 45.0) == 10.0          # never below ten tolerances' worth of force steps
    assert largest_force_n(40.0, 12.0) == 8.0           # the plan's limit (1.5 x) stays within the cell's
    outline = ObjectOutline(np.array([-100.0, -80.0, 0.0]), np.array([100.0, 80.0, 25.0]), 30_000.0)
    plan = plan_for_object(outline, CELL, "thin", "thin.yaml")
    assert plan["phases"]["characterize"]["forces_n"] == [1.0, 2.5, 4.5, 7.0, 10.0]
    assert plan["phases"]["survey"]["forces_n"] == [1.5, 4.5] and plan["limits"]["max_force_n"] == 15.0
    # The contact search ends above the table: half the height past the surface, not the cell's 30 mm.
    assert plan["limits"]["search_distance_mm"] == 12.0
    assert plan["sampling"]["units"] == 48
    dens = valid(plan, tmp_path).phases.densify
    # 2 x ceil(sqrt(342)): the 15 mm survey puts 342 units on 30,000 mm^2.
    assert dens.resolution_mm >= 2 * dens.min_spacing_mm and dens.points_per_round == 38


def test_an_object_that_does_not_fit_the_cell_is_named(tmp_path: Path) -> None:
    composite = outline_of(load_object(OBJECTS / "composite.yaml").mesh)
    assert reach_problems(composite, CELL) == []
    huge = ObjectOutline(np.array([-700.0, -200.0, 0.0]), np.array([700.0, 200.0, 50.0]), 500_000.0)
    assert any("cannot reach" in p for p in reach_problems(huge, CELL))
    # Workspace and keep-outs: the object loader's check on the mesh (what sim object runs too).
    plan = ROOT / "config" / "plans" / "demo.yaml"
    for x_mm, named in ((400.0, None), (900.0, "workspace"), (60.0, "robot_column")):
        text = DEFAULT_CELL.read_text(encoding="utf-8")
        text = text.replace("base_to_object: {position_mm: [400.0, 0.0, 0.0]}",
                            f"base_to_object: {{position_mm: [{x_mm}, 0.0, 0.0]}}")
        text = text.replace("file: ../objects/composite.yaml", f"file: {OBJECTS / 'composite.yaml'}")
        cell = tmp_path / f"cell_{x_mm:g}.yaml"
        cell.write_text(text, encoding="utf-8")
        inputs = load_session_inputs(plan, cell)
        if named is None:
            load_object_model(inputs)
            continue
        with pytest.raises(InputError, match=named):
            load_object_model(inputs)


def test_sim_object_writes_an_object_and_a_plan_that_run_as_they_are(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "obj"
    assert main(["sim", "object", "--seed", "1012", "--out", str(out), "--shape", "slab",
                 "--pattern", "two_inclusions", "--pairs", "near", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert (summary["shape"], summary["pattern"], len(summary["materials"])) == ("slab", "two_inclusions", 3)
    assert 2.7 <= summary["contrast"]["min"] <= 3.3
    inputs = load_session_inputs(out / "plan.yaml")
    assert inputs.object_file().resolve() == (out / "object.yaml").resolve()
    obj = load_object(out / "object.yaml")
    assert obj.region_names == [m["name"] for m in summary["materials"]]
    # The plan is the rule's for this object, and the object is valid at its largest force.
    rule = plan_for_object(outline_of(obj.mesh), CELL, summary["name"], "object.yaml")
    assert inputs.plan.sampling.units == rule["sampling"]["units"]
    assert obj.validity_report(max(inputs.plan.phases.characterize.forces_n), 5.0) == []
    # The same seed again: the same files.
    again = tmp_path / "again"
    assert main(["sim", "object", "--seed", "1012", "--out", str(again), "--shape", "slab",
                 "--pattern", "two_inclusions", "--pairs", "near"]) == 0
    for name in ("object.yaml", "object.ply"):
        assert (out / name).read_bytes() == (again / name).read_bytes()

    def body(path: Path) -> list[str]:         # the plan without its header (which names the folder)
        return [line for line in path.read_text(encoding="utf-8").splitlines() if not line.startswith("#")]
    assert body(out / "plan.yaml") == body(again / "plan.yaml")


@pytest.mark.parametrize("args, message", [
    (["--shape", "cube"], "unknown shape 'cube'"),
    (["--shape", "composite", "--pattern", "disc"], "composite takes one of the patterns box, plate"),
    (["--pairs", "close"], "pairs must be one of drawn, near, far"),
])
def test_sim_object_refuses_bad_choices_with_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture, args: list[str],
                                                     message: str) -> None:
    assert main(["sim", "object", "--seed", "3", "--out", str(tmp_path / "x"), *args]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()


def test_sim_object_into_a_file_is_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    target = tmp_path / "taken"
    target.write_text("not a folder", encoding="utf-8")
    assert main(["sim", "object", "--seed", "3", "--out", str(target)]) == 2
    assert "must be a folder" in capsys.readouterr().err and target.read_text(encoding="utf-8") == "not a folder"


def test_the_plan_text_reads_back_as_the_same_plan() -> None:
    from ruamel.yaml import YAML

    plan = shipped_plan("user_object")
    assert json.loads(json.dumps(YAML(typ="safe").load(dump_yaml_text(plan)))) == json.loads(json.dumps(plan))
