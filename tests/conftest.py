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


# Files whose tests open the real transports on loopback (ur-rtde's fixed ports, the Net F/T
# UDP ports, pseudo-terminals behind the served cell). Under pytest-xdist they run in one
# group, on one worker, one at a time: two at once would collide on the fixed ports.
_LOOPBACK_FILES = frozenset({
    "test_explicit_targets.py", "test_forceloop.py", "test_hardware.py", "test_line_scanner.py",
    "test_loopback_calibrate.py", "test_loopback_faults.py", "test_loopback_forceloop.py",
    "test_loopback_operator_stop.py", "test_loopback_rig.py", "test_loopback_run.py",
    "test_loopback_vs_inprocess.py", "test_netft.py", "test_ur_emulator.py", "test_ur_link.py",
})


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # Only the loopback tests are grouped: test by test is how two workers balance best
    # (one group per file measured 761 s against 632 s, the files' sizes being uneven).
    for item in items:
        if item.path.name in _LOOPBACK_FILES or item.get_closest_marker("loopback") is not None:
            item.add_marker(pytest.mark.xdist_group("loopback"))
