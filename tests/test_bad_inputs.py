"""The bad-input corpus: every broken plan or cell exits 2 with path:line:col, and no traceback."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from elastoprobe.controller.cli import main

HERE = Path(__file__).parent
BAD = HERE / "data" / "bad"
DEMO = HERE.parent / "config" / "plans" / "demo.yaml"

# file -> (line, col, part of the message)
PLANS = {
    "alias_bomb.yaml": (1, 12, "alias bomb"),
    "angle_180.yaml": (4, 22, "less than 180"),
    "angles_empty.yaml": (4, 17, "at least 1 item"),
    "angle_string.yaml": (4, 18, "valid number"),
    "angle_zero.yaml": (4, 18, "greater than 0"),
    "bad_name_chars.yaml": (1, 7, "pattern"),
    "binary_garbage.yaml": (1, 1, "YAML syntax"),
    "cell_name_blank.yaml": (2, 7, "the file name is empty"),
    "custom_tag.yaml": (2, 7, "'!fancy' is not allowed"),
    "duplicate_key_nested.yaml": (4, 3, "duplicate key 'settle_s'"),
    "duplicate_key_top.yaml": (3, 1, "duplicate key 'seed'"),
    "empty.yaml": (1, 1, "file is empty"),
    "fault_action_unknown.yaml": (3, 21, "'retry', 'skip_target', 'pause' or 'abort'"),
    "fault_policy_unknown_kind.yaml": (4, 5, "unknown fault kind 'gremlins'"),
    "finish_by_garbage.yaml": (2, 12, "ISO 8601"),
    "force_above_cell_limit.yaml": (6, 26, "exceeds the limit max_force_n = 45.0 N"),
    "force_negative.yaml": (4, 21, "greater than 0"),
    "forces_empty.yaml": (4, 15, "at least 1 item"),
    "force_not_increasing.yaml": (4, 15, "strictly increasing"),
    "limit_looser_than_cell.yaml": (5, 16, "looser than the cell's 45.0"),
    "merge_key.yaml": (4, 3, "merge keys"),
    "min_contrast_below_one.yaml": (4, 19, "greater than or equal to 1"),
    "min_feature_too_small.yaml": (3, 19, "greater than or equal to 5"),
    "min_feature_without_units.yaml": (4, 19, "units is 0 (explicit targets only)"),
    "missing_name.yaml": (1, 1, "missing required key 'name'"),
    "nan_value.yaml": (3, 13, "NaN and infinity are not allowed"),
    "nested_block_deep.yaml": (66, 65, "nested more than 64 levels deep"),
    "nested_flow_deep.yaml": (2, 71, "nested more than 64 levels deep"),
    "non_utf8.yaml": (1, 10, "not valid UTF-8"),
    "only_comments.yaml": (1, 1, "file is empty"),
    "python_tag.yaml": (1, 7, "python/object/apply:os.system' is not allowed"),
    "reference_direction_steep.yaml": (4, 24, "26.6 deg from vertical, within max_tilt_deg = 50"),
    "reference_direction_zero.yaml": (3, 24, "the zero vector"),
    "scans_too_many.yaml": (3, 19, "less than or equal to 200"),
    "scans_zero.yaml": (3, 19, "greater than or equal to 1"),
    "seed_negative.yaml": (2, 7, "greater than or equal to 0"),
    "simulated_object_empty.yaml": (2, 19, "the file name is empty"),
    "sweep_spacing_tiny.yaml": (3, 21, "greater than or equal to 0.1"),
    "syntax_bad_indent.yaml": (2, 7, "mapping values are not allowed"),
    "syntax_tab.yaml": (2, 1, "'\\t'"),
    "syntax_unclosed_list.yaml": (5, 1, "expected ',' or ']'"),
    "target_in_keep_out.yaml": (5, 15, "inside keep-out box 'robot_column'"),
    "target_outside_workspace.yaml": (5, 15, "outside the cell workspace"),
    "top_level_list.yaml": (1, 1, "should be an object"),
    "units_below_four.yaml": (3, 10, "0 (explicit targets only) or at least 4"),
    "units_zero_without_targets.yaml": (5, 10, "the plan has no targets: list"),
    "unknown_nested_key.yaml": (3, 3, "unknown key 'scans_per_stepp'"),
    "unknown_top_key.yaml": (2, 1, "unknown key 'forcez'"),
    "wrong_type_bool_word.yaml": (5, 14, "valid number"),
    "wrong_type_list_for_map.yaml": (2, 10, "should be an object"),
    "wrong_type_quoted_number.yaml": (2, 7, "valid integer"),
    "wrong_type_string_for_number.yaml": (3, 13, "valid number"),
}

CELLS = {
    "cell_fault_without_when.yaml": (65, 7, "exactly one of step, rate_per_100_steps or rate_per_100_faults"),
    "cell_home_joint_out_of_range.yaml": (9, 55, "less than or equal to 360"),
    "cell_home_outside_joint_limits.yaml": (9, 20, "joint 6 at 120 deg lies outside its limits [-90, 90]"),
    "cell_missing_limits.yaml": (4, 1, "missing required key 'limits'"),
    "cell_object_missing.yaml": (38, 9, "does not exist"),
    "cell_tip_radius_zero.yaml": (11, 18, "greater than 0"),
    "cell_unknown_kind.yaml": (5, 7, "'simulated', 'ur' or 'loopback'"),
    "cell_workspace_inverted.yaml": (54, 14, "min_mm must be below max_mm"),
}


def _expect(capsys: pytest.CaptureFixture[str], argv: list[str], path: Path, line: int, col: int, text: str) -> None:
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    assert f"{path}:{line}:{col}: " in err, err
    assert text in err, err


def test_corpus_is_large_enough() -> None:
    assert len(PLANS) + len(CELLS) >= 30
    on_disk = {p.name for p in BAD.iterdir()}
    assert on_disk == set(PLANS) | set(CELLS), on_disk ^ (set(PLANS) | set(CELLS))


@pytest.mark.parametrize("name", sorted(PLANS))
def test_bad_plan(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    line, col, text = PLANS[name]
    path = BAD / name
    _expect(capsys, ["check", str(path)], path, line, col, text)


@pytest.mark.parametrize("name", sorted(CELLS))
def test_bad_cell(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    line, col, text = CELLS[name]
    path = BAD / name
    plan = HERE / "data" / "minimal_plan.yaml" if name == "cell_object_missing.yaml" else DEMO
    _expect(capsys, ["check", str(plan), "--cell", str(path)], path, line, col, text)


def test_bad_cli_arguments_exit_2_without_traceback() -> None:
    for argv in (["check"], ["nonsense-command"], ["check", str(DEMO), "--bogus"]):
        proc = subprocess.run([sys.executable, "-m", "elastoprobe.controller.cli", *argv],
                              capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2, (argv, proc.stderr)
        assert "Traceback" not in proc.stderr


def test_missing_plan_file(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(BAD / "does_not_exist.yaml")]) == 2
    assert "no such file" in capsys.readouterr().err
