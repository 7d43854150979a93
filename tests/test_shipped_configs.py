"""Every shipped plan, cell and object file is valid (docs/design.md §1: shipped examples, all valid)."""
from __future__ import annotations

from pathlib import Path

import pytest

from elastoprobe.controller.core.config import load_cell, load_session_inputs
from elastoprobe.sim.objects import load_object

CONFIG = Path(__file__).resolve().parent.parent / "config"


@pytest.mark.parametrize("cell", sorted((CONFIG / "cells").glob("*.yaml")), ids=lambda p: p.name)
def test_cell_is_valid(cell: Path) -> None:
    spec, _ = load_cell(cell)
    assert spec.limits.max_force_n > 0


@pytest.mark.parametrize("plan", sorted((CONFIG / "plans").glob("*.yaml")), ids=lambda p: p.name)
def test_plan_is_valid_with_its_cell(plan: Path) -> None:
    inputs = load_session_inputs(plan)
    assert inputs.object_file().exists()


@pytest.mark.parametrize("obj", sorted((CONFIG / "objects").glob("*.yaml")), ids=lambda p: p.name)
def test_object_loads_and_is_valid_at_40_n(obj: Path) -> None:
    o = load_object(obj)
    assert o.validity_report(40.0, 5.0) == []
