"""Fixtures shared by several test files: the shipped simulated objects (loaded once per module)."""
from __future__ import annotations

from pathlib import Path

import pytest

from elastoprobe.sim.objects import load_object

OBJECTS = Path(__file__).resolve().parents[1] / "config" / "objects"


@pytest.fixture(scope="module")
def ball():
    return load_object(OBJECTS / "rubber_ball.yaml")


@pytest.fixture(scope="module")
def composite():
    return load_object(OBJECTS / "composite.yaml")


@pytest.fixture(scope="module")
def user_object():
    return load_object(OBJECTS / "user_object.yaml")


@pytest.fixture(scope="session")
def tiny_session(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """One finished run of the tiny plan (tests/data/session/tiny.yaml, seed 2) through the CLI,
    shared by the tests that damage, interrupt or compare against it (they work on copies).

    Keys: ``plan``, ``cell`` (a private copy of the simulated cell), ``env`` (its own lock
    directory), ``seed``, ``finished`` (the session directory), ``outcome`` and ``wall_s``."""
    import time

    from test_session_util import child_env, copy_cell, outcome, plan_for, start_or_resume

    tmp = tmp_path_factory.mktemp("tiny")
    cell = copy_cell(Path(__file__).resolve().parents[1] / "config" / "cells" / "sim.yaml", tmp, "tiny-test-cell")
    setup = {"tmp": tmp, "cell": cell, "plan": plan_for(cell, tmp), "env": child_env(tmp / "locks"), "seed": 2}
    t0 = time.monotonic()
    child = start_or_resume(setup["plan"], tmp / "finished", setup["seed"], setup["env"])
    assert child.returncode == 0, child.stderr[-3000:]
    setup.update(finished=tmp / "finished", wall_s=time.monotonic() - t0, outcome=outcome(tmp / "finished"))
    return setup
