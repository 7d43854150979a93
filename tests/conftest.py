"""Fixtures shared by several test files (the shipped simulated objects, loaded once per module;
one finished tiny session per run) and how the tests are spread over two workers."""
from __future__ import annotations

import fcntl
import json
import os
import re
import sys
import time
from pathlib import Path
from typing import Iterator

import pytest

from elastoprobe.sim.objects import load_object
from elastoprobe.sim.servers.loopback import LoopbackServers
from elastoprobe.sim.servers.netft_server import NetFTServer
from elastoprobe.sim.servers.scanner_serial import ScannerPtyServer
from elastoprobe.sim.servers.ur_emulator import UREmulator

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


@pytest.fixture(scope="session", autouse=True)
def _own_cell_locks(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Cell locks in this run's (this worker's) own directory, for in-process sessions and the
    CLI children that inherit it: under the machine-wide default two workers' sessions on one
    shipped cell (or another test run's) would refuse each other. Tests that name their own
    lock directory still do."""
    patch = pytest.MonkeyPatch()
    patch.setenv("ELASTOPROBE_LOCK_DIR", str(tmp_path_factory.mktemp("cell-locks")))
    yield
    patch.undo()


@pytest.fixture(scope="session")
def tiny_session(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """One finished run of the tiny plan (tests/data/session/tiny.yaml, seed 2) through the CLI,
    shared by the tests that damage, interrupt or compare against it (they work on copies).

    Built once per test run: under pytest-xdist the first worker to ask runs it while the
    others wait on a file lock, then every worker reads the same finished directory.

    Its plan is the tiny plan with a ``notify`` command on finish and pause that appends each
    payload to ``notify_inbox`` (every run of the plan does, killed and resumed ones too).

    Keys: ``plan``, ``cell`` (a private copy of the simulated cell), ``env`` (this worker's own
    lock directory, so two workers' sessions on the cell never meet each other's cell lock),
    ``tmp`` (this worker's directory for sessions written beside the finished one), ``seed``,
    ``finished`` (the session directory: never written to), ``outcome``, ``wall_s`` and
    ``notify_inbox``."""
    from test_session_util import child_env, copy_cell, outcome, plan_for, start_or_resume

    own = tmp_path_factory.mktemp("tiny")
    # The run's base directory is shared by its xdist workers (each has a subdirectory).
    base = tmp_path_factory.getbasetemp()
    shared = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "tiny-shared"
    shared.mkdir(exist_ok=True)
    with open(shared / "build.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        built = shared / "built.json"
        if not built.exists():
            cell = copy_cell(Path(__file__).resolve().parents[1] / "config" / "cells" / "sim.yaml", shared,
                             "tiny-test-cell")
            plan = plan_for(cell, shared)
            # The operator's notify command, on finish and pause, appends each payload to one
            # file (tests/test_session_notify.py reads the finished run's).
            hook = f"import sys; open({str(shared / 'notify.jsonl')!r}, 'a').write(sys.stdin.read() + '\\n')"
            plan.write_text(plan.read_text() + f"notify:\n  command: [{json.dumps(sys.executable)}, -c, "
                                               f"{json.dumps(hook)}]\n  on: [finish, pause]\n")
            t0 = time.monotonic()
            child = start_or_resume(plan, shared / "finished", 2, child_env(shared / "locks"))
            assert child.returncode == 0, child.stderr[-3000:]
            built.write_text(json.dumps({"plan": str(plan), "cell": str(cell), "seed": 2,
                                         "wall_s": time.monotonic() - t0}))
        record = json.loads(built.read_text())
    return {"tmp": own, "cell": Path(record["cell"]), "plan": Path(record["plan"]), "seed": record["seed"],
            "env": child_env(own / "locks"), "finished": shared / "finished", "wall_s": record["wall_s"],
            "outcome": outcome(shared / "finished"), "notify_inbox": shared / "notify.jsonl"}


# ----------------------------------------------------------------------------- two workers
# The default run (README) is two pytest runs: everything but the loopback tests on two
# pytest-xdist workers, then the loopback tests alone. Tests that open the real transports
# on loopback (ur-rtde against the emulator, Net F/T over UDP, the scanner's pty) are timing
# sensitive and use fixed ports: they need the machine to themselves.
_LOOPBACK_SERVERS = (UREmulator, NetFTServer, ScannerPtyServer, LoopbackServers)


@pytest.fixture(autouse=True)
def _loopback_servers_need_the_marker(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """A test that starts a loopback server must be marked ``loopback``: unmarked, it would
    run beside a CPU-bound test on the other worker. A marked one fails on a worker."""
    if request.node.get_closest_marker("loopback") is not None:
        if os.environ.get("PYTEST_XDIST_WORKER"):
            pytest.fail("a loopback test on an xdist worker: loopback tests run alone, after the others "
                        "(README: -m 'not loopback' with -n 2, then -m loopback without -n)", pytrace=False)
        return

    def refuse(self: object, *args: object, **kwargs: object) -> None:
        raise AssertionError(f"{request.node.nodeid} starts a {type(self).__name__} on loopback: "
                             f"mark it @pytest.mark.loopback (it must not run beside other tests)")

    for server in _LOOPBACK_SERVERS:
        monkeypatch.setattr(server, "start", refuse)


# A module that builds something once for its tests (a module- or class-scoped fixture: a
# session run, a suite) sends all its tests to one worker, else each worker would build it.
# The rest are spread test by test, the largest groups first. (xdist's own --dist loadgroup
# does not group on pytest 9.2: pytest-dev/pytest-xdist#1386.)
_BUILDS_ONCE = re.compile(r"@pytest\.fixture\(\s*scope=[\"'](?:module|class|package)[\"']")


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object:
    from xdist.scheduler import LoadScopeScheduling

    once: dict[str, bool] = {}

    def builds_once(module: str) -> bool:
        if module not in once:
            path = config.rootpath / module
            once[module] = path.suffix == ".py" and path.exists() and bool(_BUILDS_ONCE.search(path.read_text()))
        return once[module]

    class ByModuleWhereItBuildsOnce(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            module = nodeid.split("::", 1)[0]
            return module if builds_once(module) else nodeid

    return ByModuleWhereItBuildsOnce(config, log)
