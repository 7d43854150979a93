"""CI runs the README's test command word for word, and its two parts (two workers, then the
loopback tests alone) together run exactly the default selection, each test once."""
from __future__ import annotations

import itertools
import re
import shlex
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _readme_test_command() -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    block = re.search(r"Run the tests:\n\n```\n(.+?)\n```", text)
    assert block is not None, "README.md has no 'Run the tests:' command block"
    return block.group(1)


def _pytest_parts(command: str) -> list[tuple[str, bool]]:
    """(``-m`` expression, runs on workers) of each ``python -m pytest`` part of an ``&&`` chain."""
    parts = []
    for part in command.split("&&"):
        words = shlex.split(part)
        if words[:3] == ["python", "-m", "pytest"]:
            args = words[3:]
            assert "-m" in args, f"a pytest part without its own selection: {part!r}"
            parts.append((args[args.index("-m") + 1], "-n" in args))
    return parts


def _selects(expression: str, marks: dict[str, bool]) -> bool:
    assert re.fullmatch(r"[\w\s()]+", expression), expression     # names, and/or/not, brackets
    return bool(eval(expression, {"__builtins__": {}}, dict(marks)))  # noqa: S307 — checked above


def test_ci_runs_the_readme_test_command() -> None:
    command = _readme_test_command()
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()
    assert command in ci, "the README's test command is not a line of .ci/run"


def test_the_two_parts_run_the_default_selection_each_test_once() -> None:
    parts = _pytest_parts(_readme_test_command())
    assert [workers for _, workers in parts] == [True, False]
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["pytest"]["ini_options"]
    default = shlex.split(config["addopts"])
    default = default[default.index("-m") + 1]
    names = sorted({m.split(":")[0] for m in config["markers"]})
    assert {"slow", "soak", "loopback"} <= set(names)
    for values in itertools.product((False, True), repeat=len(names)):
        marks = dict(zip(names, values))
        chosen = [_selects(p, marks) for p, _ in parts]
        assert sum(chosen) == int(_selects(default, marks)), (marks, parts, default)
        # The loopback tests never run beside others: only in the part without workers.
        if marks["loopback"] and any(chosen):
            assert chosen == [False, True], (marks, parts)
