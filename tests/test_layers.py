"""The layers of docs/design.md §1 hold: import-linter's contracts in pyproject.toml, checked over
the source tree (core below the simulator and the drivers, the controller above them reaching
the simulator only through the cell registry, calibration under the CLI, no cycles)."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _source_tree(tmp_path: Path) -> Path:
    # The editable install maps elastoprobe.* onto three folders through an import hook that
    # grimp does not follow; a package of links to the same folders is what it can read.
    pkg = tmp_path / "elastoprobe"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    for name in ("controller", "sim", "calibration"):
        (pkg / name).symlink_to(ROOT / name, target_is_directory=True)
    return tmp_path


def _lint(tree: Path, config: Path) -> subprocess.CompletedProcess[str]:
    lint = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or shutil.which("lint-imports")
    if lint is None:
        pytest.fail("lint-imports is not installed (pip install -e '.[test]')")
    env = dict(os.environ, PYTHONPATH=str(tree))
    return subprocess.run([lint, "--config", str(config), "--no-cache"], cwd=tree, env=env,
                          capture_output=True, text=True, timeout=600)


def test_import_contracts_hold(tmp_path: Path) -> None:
    result = _lint(_source_tree(tmp_path), ROOT / "pyproject.toml")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "0 broken" in result.stdout


def test_a_wrong_way_import_breaks_a_contract(tmp_path: Path) -> None:
    """The check can fail: core importing the session is reported."""
    tree = _source_tree(tmp_path)
    core = tree / "elastoprobe" / "controller"
    # A copy of the tree with one bad import: links for everything, a real core folder.
    (tree / "elastoprobe" / "controller").unlink()
    shutil.copytree(ROOT / "controller", core, ignore=shutil.ignore_patterns("__pycache__"))
    geometry = core / "core" / "geometry.py"
    geometry.write_text(geometry.read_text() + "\nfrom elastoprobe.controller import session  # noqa\n")
    result = _lint(tree, ROOT / "pyproject.toml")
    assert result.returncode != 0
    assert "core imports nothing above it BROKEN" in result.stdout
