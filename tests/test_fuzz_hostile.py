"""Property tests over the hostile surfaces of issue #15: random mesh bytes, random journal
damage, random operator requests at random moments.

The contract each property states: exit 0, 2 or 3 as documented and never a traceback; a
mesh ``check`` accepts is safe to compute with; a journal a command calls sound is sound
(``verify`` finds nothing), and read-only commands never change a journal's bytes; a
pause or stop at any moment leaves a session that ``resume`` finishes exactly as an
uninterrupted one. Short by default (a handful of derandomized examples); the long runs
are marked slow.
"""
from __future__ import annotations

import hashlib
import os
import random
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from test_session_util import CLI, Outcome, child_env, outcome, run_cli, start_or_resume

from elastoprobe.controller.cli import main
from elastoprobe.controller.journal import Journal

REPO = Path(__file__).resolve().parent.parent
OBJECTS = REPO / "config" / "objects"
SIM_CELL = REPO / "config" / "cells" / "sim.yaml"
SEED = 2
SHORT = settings(max_examples=12, deadline=None, derandomize=True,
                 suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
LONG = settings(max_examples=300, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ----------------------------------------------------------------------------- meshes
PLY = (OBJECTS / "user_object.ply").read_bytes()
HEADER_END = PLY.index(b"end_header\n") + len(b"end_header\n")

patches = st.lists(st.tuples(st.integers(0, len(PLY) - 1), st.binary(min_size=1, max_size=64)),
                   min_size=1, max_size=6)
special_floats = st.sampled_from([np.nan, np.inf, -np.inf, 1e30, -1e30, 0.0, 1e-30, 3.4e38])


def _patched(data: bytes, edits: list[tuple[int, bytes]]) -> bytes:
    out = bytearray(data)
    for offset, chunk in edits:
        out[offset:offset + len(chunk)] = chunk
    return bytes(out)


def _mesh_case(tmp: Path, ply: bytes) -> Path:
    text = (OBJECTS / "user_object.yaml").read_text().replace("file: user_object.ply", "file: fuzz.ply")
    (tmp / "fuzz.ply").write_bytes(ply)
    (tmp / "obj.yaml").write_text(text)
    plan = (REPO / "config" / "plans" / "user_object.yaml").read_text()
    plan = plan.replace("cell: ../cells/sim.yaml", f"cell: {SIM_CELL}")
    plan = plan.replace("simulated_object: ../objects/user_object.yaml", f"simulated_object: {tmp / 'obj.yaml'}")
    (tmp / "plan.yaml").write_text(plan)
    return tmp / "plan.yaml"


def _assert_check_keeps_the_contract(tmp: Path, ply: bytes, capsys: pytest.CaptureFixture[str]) -> None:
    from elastoprobe.controller.core.config import load_session_inputs
    from elastoprobe.sim.objects import load_object

    plan = _mesh_case(tmp, ply)
    code = main(["check", str(plan)])              # an exception here fails the test
    err = capsys.readouterr().err
    assert code in (0, 2), (code, err)
    if code == 2:
        assert f"{tmp / 'obj.yaml'}:" in err or f"{plan}:" in err, err
        return
    # Accepted: the simulator computes with it without meeting a NaN or a degenerate face.
    inputs = load_session_inputs(plan)
    obj = load_object(inputs.object_file())
    lo, hi = obj.mesh.bounds
    pts = np.random.default_rng(0).uniform(lo - 5.0, hi + 5.0, size=(64, 3))
    closest, normals, labels = obj.closest_surface(pts)
    assert np.isfinite(closest).all() and np.isfinite(normals).all()
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    assert set(labels.tolist()) <= set(range(len(obj.region_names)))


@SHORT
@given(edits=patches)
def test_random_bytes_in_a_mesh_file(edits: list[tuple[int, bytes]], tmp_path_factory: pytest.TempPathFactory,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    _assert_check_keeps_the_contract(tmp_path_factory.mktemp("mesh"), _patched(PLY, edits), capsys)


@SHORT
@given(vertex=st.integers(0, 521), axis=st.integers(0, 2), value=special_floats,
       face=st.integers(0, 1039), corner=st.integers(0, 2), index=st.integers(-5, 600))
def test_special_values_in_the_vertex_and_face_blocks(vertex: int, axis: int, value: float, face: int, corner: int,
                                                      index: int, tmp_path_factory: pytest.TempPathFactory,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    m = trimesh.load(str(OBJECTS / "user_object.ply"), process=False)
    v, f = np.array(m.vertices), np.array(m.faces)
    v[vertex, axis] = value
    f[face, corner] = index
    colors = np.asarray(m.visual.face_colors)
    # Write the arrays raw (trimesh would refuse to export bad faces): same header, same layout.
    body = bytearray()
    for row in v.astype("<f4"):
        body += row.tobytes()
    for tri, col in zip(f.astype("<i4"), colors.astype(np.uint8)):
        body += bytes([3]) + tri.tobytes() + col.tobytes()
    _assert_check_keeps_the_contract(tmp_path_factory.mktemp("mesh"), PLY[:HEADER_END] + bytes(body), capsys)


@pytest.mark.slow
@LONG
@given(edits=patches)
def test_random_bytes_in_a_mesh_file_long(edits: list[tuple[int, bytes]], tmp_path_factory: pytest.TempPathFactory,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    _assert_check_keeps_the_contract(tmp_path_factory.mktemp("mesh"), _patched(PLY, edits), capsys)


# ----------------------------------------------------------------------------- journals
@pytest.fixture
def setup(tiny_session: dict) -> dict:
    return tiny_session


@pytest.fixture
def reference(tiny_session: dict) -> tuple[Path, Outcome, float]:
    """An uninterrupted finished session, its outcome and its wall time."""
    return tiny_session["finished"], tiny_session["outcome"], tiny_session["wall_s"]


damage = st.lists(st.tuples(st.floats(0.0, 1.0, exclude_max=True), st.integers(1, 400), st.integers(0, 2**32 - 1)),
                  min_size=1, max_size=3)


def _assert_damage_keeps_the_contract(reference: tuple[Path, Outcome, float], tmp: Path,
                                      hits: list[tuple[float, int, int]]) -> None:
    session = tmp / "s"
    shutil.copytree(reference[0], session)
    journal = session / "journal.sqlite"
    size = journal.stat().st_size
    with open(journal, "r+b") as f:
        for where, n, seed in hits:
            rng = random.Random(seed)
            f.seek(int(where * size))
            f.write(bytes(rng.randrange(256) for _ in range(n)))
    before = _sha(journal)
    status = run_cli(["status", str(session)], child_env(tmp / "locks"))
    assert status.returncode in (0, 2) and "Traceback" not in status.stderr, status.stderr[-3000:]
    if status.returncode == 0:
        # Called sound: then it is (the damage fell on free space or padding).
        with Journal.open_readonly(session) as j:
            assert j.verify() == []
    for args in (["report", str(session)], ["export", str(session), "--format", "hdf5", "--out", str(tmp / "x.h5")]):
        child = run_cli(args, child_env(tmp / "locks"))
        assert child.returncode in (0, 2) and "Traceback" not in child.stderr, (args, child.stderr[-3000:])
        assert child.returncode == status.returncode, (args, child.stderr[-2000:])
    assert _sha(journal) == before                 # read-only commands never write to it
    resumed = run_cli(["resume", str(session), "--quiet"], child_env(tmp / "locks"))
    assert "Traceback" not in resumed.stderr, resumed.stderr[-3000:]
    if status.returncode == 2:
        assert resumed.returncode == 2, resumed.stderr[-2000:]
        assert _sha(journal) == before             # refused: not one byte written
        salvaged = run_cli(["salvage", str(session), "--out", str(tmp / "new")], child_env(tmp / "locks"))
        assert salvaged.returncode in (0, 2) and "Traceback" not in salvaged.stderr, salvaged.stderr[-3000:]
        if salvaged.returncode == 0:
            with Journal.open_readonly(tmp / "new") as j:       # a salvaged journal is sound
                assert j.verify() == []
    else:
        assert resumed.returncode == 0, resumed.stderr[-2000:]
        with Journal.open_readonly(session) as j:
            assert j.session()["status"] == "done"  # a finished session stays finished


@settings(SHORT, max_examples=2)
@given(hits=damage)
def test_random_journal_damage(hits: list[tuple[float, int, int]], reference: tuple[Path, Outcome, float],
                               tmp_path_factory: pytest.TempPathFactory) -> None:
    _assert_damage_keeps_the_contract(reference, tmp_path_factory.mktemp("damage"), hits)


@pytest.mark.slow
@settings(LONG, max_examples=60)
@given(hits=damage)
def test_random_journal_damage_long(hits: list[tuple[float, int, int]], reference: tuple[Path, Outcome, float],
                                    tmp_path_factory: pytest.TempPathFactory) -> None:
    _assert_damage_keeps_the_contract(reference, tmp_path_factory.mktemp("damage"), hits)


# ----------------------------------------------------------------------------- signals
REQUESTS = ["SIGINT", "SIGTERM", "SIGINT twice", "stop", "pause"]


def _send(request: str, pid: int, session: Path, gap_s: float) -> None:
    if request == "SIGINT":
        os.kill(pid, signal.SIGINT)
    elif request == "SIGTERM":
        os.kill(pid, signal.SIGTERM)
    elif request == "SIGINT twice":
        os.kill(pid, signal.SIGINT)
        time.sleep(gap_s)
        os.kill(pid, signal.SIGINT)
    else:
        subprocess.run(CLI + [request, str(session)], capture_output=True, timeout=60)


def _assert_request_keeps_the_contract(setup: dict, reference: tuple[Path, Outcome, float], tmp: Path,
                                       fraction: float, request: str, gap_s: float) -> None:
    out = tmp / "s"
    proc = subprocess.Popen(CLI + ["run", str(setup["plan"]), "--out", str(out), "--seed", str(SEED), "--quiet"],
                            env=setup["env"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(fraction * reference[2])
    if proc.poll() is None and (out / "session.lock").exists():
        _send(request, proc.pid, out, gap_s)
    _, stderr = proc.communicate(timeout=600)
    assert "Traceback" not in stderr, stderr[-3000:]
    assert proc.returncode in (0, 3), (proc.returncode, stderr[-3000:])
    if proc.returncode == 3:
        with Journal.open_readonly(out) as j:
            s = j.session()
        assert s["status"] == "paused" and s["status_reason"], s
        for _ in range(3):                     # a finish_by or a fault may pause it again: resume on
            child = start_or_resume(setup["plan"], out, SEED, setup["env"])
            if child.returncode == 0:
                break
            assert child.returncode == 3, child.stderr[-3000:]
    got, ref = outcome(out), reference[1]
    assert got.status == "done" and got.problems == []
    # Resumed from its checkpoint, the session is the uninterrupted one.
    assert got.step_status == ref.step_status
    assert got.step_data == ref.step_data
    assert got.model_hashes == ref.model_hashes
    assert got.labels_sha256 == ref.labels_sha256


@settings(SHORT, max_examples=1)
@given(fraction=st.floats(0.05, 0.95), request=st.sampled_from(REQUESTS), gap_s=st.floats(0.0, 1.0))
@pytest.mark.timeout(1800)
def test_a_request_at_a_random_moment(fraction: float, request: str, gap_s: float, setup: dict,
                                      reference: tuple[Path, Outcome, float],
                                      tmp_path_factory: pytest.TempPathFactory) -> None:
    _assert_request_keeps_the_contract(setup, reference, tmp_path_factory.mktemp("signal"), fraction, request, gap_s)


@pytest.mark.slow
@settings(LONG, max_examples=30)
@given(fraction=st.floats(0.0, 1.0), request=st.sampled_from(REQUESTS), gap_s=st.floats(0.0, 2.0))
@pytest.mark.timeout(4 * 3600)
def test_a_request_at_a_random_moment_long(fraction: float, request: str, gap_s: float, setup: dict,
                                           reference: tuple[Path, Outcome, float],
                                           tmp_path_factory: pytest.TempPathFactory) -> None:
    _assert_request_keeps_the_contract(setup, reference, tmp_path_factory.mktemp("signal"), fraction, request, gap_s)
