"""One list of the faults the controller sees: every kind the code raises or trips with is a
``FaultKind``, and a plan's ``fault_policy`` can name each of them but the operator's stop."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest
from elastoprobe.controller.core.config import FaultPolicySpec
from elastoprobe.controller.core.faultkinds import POLICY_FAULT_KINDS, FaultKind
from pydantic import ValidationError

ROOT = Path(__file__).resolve().parent.parent
RAISERS = {"ProbeFault", "_trip"}


def _kinds_in_source() -> dict[str, list[str]]:
    """Every string literal given as the kind (first argument) of ProbeFault(...) or a guard
    trip, and every trip kind in the guard's table, with where it is."""
    found: dict[str, list[str]] = {}
    for package in ("controller", "sim", "calibration"):
        for path in sorted((ROOT / package).rglob("*.py")):
            tree = ast.parse(path.read_text(), str(path))
            for node in ast.walk(tree):
                if isinstance(node, ast.Call) and node.args:
                    name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
                    first = node.args[0]
                    if name in RAISERS and isinstance(first, ast.Constant) and isinstance(first.value, str):
                        found.setdefault(first.value, []).append(f"{path.relative_to(ROOT)}:{node.lineno}")
            if path.name == "safety.py":
                for node in ast.walk(tree):
                    if (isinstance(node, ast.Tuple) and len(node.elts) == 5 and isinstance(node.elts[0], ast.Constant)
                            and isinstance(node.elts[0].value, str)):
                        found.setdefault(node.elts[0].value, []).append(f"{path.relative_to(ROOT)}:{node.lineno}")
    return found


def test_every_kind_the_code_raises_is_one_of_the_listed_fault_kinds() -> None:
    found = _kinds_in_source()
    assert {"device", "force", "stale", "force_not_held", "operator_stop"} <= set(found)   # the scan sees them
    unknown = {k: where for k, where in found.items() if k not in FaultKind.__members__.values()}
    assert not unknown, f"fault kinds not in FaultKind: {unknown}"


@pytest.mark.parametrize("kind", POLICY_FAULT_KINDS)
def test_a_plan_can_set_the_policy_of_every_kind(kind: str) -> None:
    policy = FaultPolicySpec(kinds={kind: {"action": "skip_target"}})
    assert policy.for_kind(kind).action == "skip_target"


def test_the_operator_stop_is_not_the_plans_to_decide() -> None:
    with pytest.raises(ValidationError, match="unknown fault kind 'operator_stop'"):
        FaultPolicySpec(kinds={"operator_stop": {"action": "retry"}})
