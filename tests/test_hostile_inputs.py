"""Hostile object files and meshes (issue #15, cases 1, 2, 3, 8 and the mesh warning of 9).

``check`` loads and validates everything ``run`` will load (cell, plan, object, mesh) with
the same messages; a bad object or mesh is exit 2 with ``path:line:col``, never a
traceback, and ``run`` refuses it before a session directory is made. An object that
does not fit the cell's workspace is refused at ``check`` and ``run``, and motion
validation itself is bounded whatever the path.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from elastoprobe.calibration import runner as calibration_runner
from elastoprobe.controller.cli import main
from elastoprobe.controller.core.atomic import atomic_write_bytes
from elastoprobe.controller.core.errors import DiskError

REPO = Path(__file__).resolve().parent.parent
OBJECTS = REPO / "config" / "objects"
SIM_CELL = REPO / "config" / "cells" / "sim.yaml"
CLI = [sys.executable, "-m", "elastoprobe.controller.cli"]


def _user_object(tmp: Path, edits: dict[str, str] | None = None, ply: bytes | None = None) -> Path:
    """A copy of the shipped user object (YAML + PLY) in ``tmp``, with line edits and other PLY bytes."""
    text = (OBJECTS / "user_object.yaml").read_text()
    for old, new in (edits or {}).items():
        assert old in text, old
        text = text.replace(old, new)
    (tmp / "obj.yaml").write_text(text)
    (tmp / "user_object.ply").write_bytes(ply if ply is not None else (OBJECTS / "user_object.ply").read_bytes())
    return tmp / "obj.yaml"


def _plan(tmp: Path, obj: Path, name: str = "plan.yaml") -> Path:
    text = (REPO / "config" / "plans" / "user_object.yaml").read_text()
    text = text.replace("cell: ../cells/sim.yaml", f"cell: {SIM_CELL}")
    text = text.replace("simulated_object: ../objects/user_object.yaml", f"simulated_object: {obj}")
    (tmp / name).write_text(text)
    return tmp / name


def _mesh_bytes(vertices: np.ndarray | None = None, faces: np.ndarray | None = None) -> bytes:
    """The shipped user mesh (binary PLY with face colours) with other vertices or faces."""
    m = trimesh.load(str(OBJECTS / "user_object.ply"), process=False)
    v = m.vertices if vertices is None else vertices
    f = m.faces if faces is None else faces
    colors = np.asarray(m.visual.face_colors)
    colors = colors[: len(f)] if len(f) <= len(colors) else np.vstack([colors, colors[: len(f) - len(colors)]])
    out = trimesh.Trimesh(v, f, face_colors=colors, process=False)
    return out.export(file_type="ply")


def _vertex_block_offset(data: bytes) -> int:
    return data.index(b"end_header\n") + len(b"end_header\n")


def _run_cli(args: list[str], timeout_s: float = 300.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(CLI + args, capture_output=True, text=True, timeout=timeout_s)


def _check_and_run_refuse(capsys: pytest.CaptureFixture[str], plan: Path, tmp: Path, where: str,
                          text: str) -> str:
    """``check`` and ``run`` both exit 2 with the same first line, naming ``where`` and ``text``;
    ``run`` leaves no session behind."""
    assert main(["check", str(plan)]) == 2
    err_check = capsys.readouterr().err
    out = tmp / "session"
    assert main(["run", str(plan), "--out", str(out), "--quiet"]) == 2
    err_run = capsys.readouterr().err
    for err in (err_check, err_run):
        assert "Traceback" not in err
        assert where in err, err
        assert text in err, err
    assert err_check.splitlines()[0] == err_run.splitlines()[0]
    assert not (out / "journal.sqlite").exists()
    return err_check


# ----------------------------------------------------------------------------- case 1
BROKEN_OBJECTS = {
    # label: (edits of user_object.yaml, PLY bytes or None, "file:line:col" suffix, message part)
    "missing mesh": ({"file: user_object.ply": "file: gone.ply"}, None, "obj.yaml:12:9", "does not exist"),
    "E_mpa zero": ({"E_mpa: 12.0": "E_mpa: 0.0"}, None, "obj.yaml:22:12", "greater than 0"),
    "E_mpa negative": ({"E_mpa: 12.0": "E_mpa: -3.0"}, None, "obj.yaml:22:12", "greater than 0"),
    "nu 0.5": ({"nu: 0.45": "nu: 0.5"}, None, "obj.yaml:23:9", "less than 0.5"),
    "unknown material": ({"{material: sponge,": "{material: spunge,"}, None, "obj.yaml:17:18",
                         "unknown material 'spunge'"),
    "corrupt PLY header": ({}, b"ply\nformat binary_little_endian 1.0\nelement vertex 12\x00\xff\n",
                           "obj.yaml:12:9", "cannot read mesh"),
}


@pytest.mark.parametrize("label", sorted(BROKEN_OBJECTS))
def test_case1_check_reads_the_object_as_run_does(label: str, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    edits, ply, where, text = BROKEN_OBJECTS[label]
    obj = _user_object(tmp_path, edits, ply)
    plan = _plan(tmp_path, obj)
    _check_and_run_refuse(capsys, plan, tmp_path, f"{tmp_path / where}: ", text)


# ----------------------------------------------------------------------------- case 2
def _nan_vertex() -> bytes:
    m = trimesh.load(str(OBJECTS / "user_object.ply"), process=False)
    v = np.array(m.vertices)
    v[7] = [np.nan, 0.0, 1.0]
    return _mesh_bytes(vertices=v)


def _random_vertex_block() -> bytes:
    data = bytearray((OBJECTS / "user_object.ply").read_bytes())
    start = _vertex_block_offset(bytes(data))
    rng = np.random.default_rng(15)
    data[start:start + 522 * 12] = rng.integers(0, 256, 522 * 12, dtype=np.uint8).tobytes()
    return bytes(data)


def _one_point() -> bytes:
    m = trimesh.load(str(OBJECTS / "user_object.ply"), process=False)
    return _mesh_bytes(vertices=np.tile(m.vertices[0], (len(m.vertices), 1)))


BAD_MESHES = {
    "NaN vertex": (_nan_vertex, "not finite"),
    "random vertex block": (_random_vertex_block, "mesh"),
    "all vertices in one point": (_one_point, "degenerate"),
}


@pytest.mark.parametrize("label", sorted(BAD_MESHES))
def test_case2_bad_mesh_data_is_refused_before_numpy_sees_it(label: str, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    make, text = BAD_MESHES[label]
    obj = _user_object(tmp_path, ply=make())
    plan = _plan(tmp_path, obj)
    _check_and_run_refuse(capsys, plan, tmp_path, f"{obj}:12:9: ", text)


@pytest.mark.timeout(600)
def test_case2_resume_with_a_mesh_broken_since_refuses_and_keeps_the_session(tmp_path: Path) -> None:
    from elastoprobe.controller.journal import Journal

    obj = _user_object(tmp_path)
    plan = _plan(tmp_path, obj)
    text = plan.read_text().replace("units: 24", "units: 0").replace("phases:", "targets:\n  - {point_mm: [30.0, 0.0, 40.0]}\nphases:")
    plan.write_text(text)
    out = tmp_path / "s"
    # A session that pauses at once (finish_by in the past), then the mesh is damaged.
    plan.write_text(plan.read_text() + "finish_by: '2000-01-01T00:00:00+00:00'\n")
    first = _run_cli(["run", str(plan), "--out", str(out), "--quiet"])
    assert first.returncode == 3, first.stderr[-2000:]
    (tmp_path / "user_object.ply").write_bytes(_nan_vertex())
    before = (out / "journal.sqlite").read_bytes()
    again = _run_cli(["resume", str(out), "--quiet"])
    assert again.returncode == 2, again.stderr[-2000:]
    assert "Traceback" not in again.stderr and "not finite" in again.stderr
    assert (out / "journal.sqlite").read_bytes() == before
    with Journal.open_readonly(out) as j:
        assert j.session()["status"] == "paused"


# ----------------------------------------------------------------------------- case 3
def test_case3_an_object_larger_than_the_workspace_is_refused_at_check(tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    obj = _user_object(tmp_path, {"scale_mm_per_unit: 1.0": "scale_mm_per_unit: 1000"})
    plan = _plan(tmp_path, obj)
    err = _check_and_run_refuse(capsys, plan, tmp_path, ": ", "does not fit the cell's workspace")
    assert "120000 x 90000 x 40000 mm" in err


def test_a_mesh_in_metres_is_refused_as_smaller_than_the_tip(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    obj = _user_object(tmp_path, {"scale_mm_per_unit: 1.0": "scale_mm_per_unit: 0.001"})
    _check_and_run_refuse(capsys, _plan(tmp_path, obj), tmp_path, ": ", "smaller than the probe's tip")


def test_an_object_placed_in_a_keep_out_box_is_refused_at_check(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    text = SIM_CELL.read_text().replace("base_to_object: {position_mm: [400.0, 0.0, 0.0]}",
                                        "base_to_object: {position_mm: [60.0, 0.0, 0.0]}")
    cell = tmp_path / "cell.yaml"
    cell.write_text(text.replace("../objects/composite.yaml", str(OBJECTS / "composite.yaml")))
    assert main(["check", str(REPO / "config" / "plans" / "demo.yaml"), "--cell", str(cell)]) == 2
    err = capsys.readouterr().err
    assert "keep-out box 'robot_column'" in err and "Traceback" not in err, err


@pytest.mark.timeout(900)
def test_case3_run_of_an_oversized_object_ends_with_a_reason(tmp_path: Path) -> None:
    obj = _user_object(tmp_path, {"scale_mm_per_unit: 1.0": "scale_mm_per_unit: 1000"})
    plan = _plan(tmp_path, obj)
    proc = _run_cli(["run", str(plan), "--out", str(tmp_path / "s"), "--quiet"], timeout_s=600)
    assert proc.returncode == 2 and "does not fit the cell's workspace" in proc.stderr, proc.stderr[-2000:]


def test_case3_motion_validation_is_bounded_for_any_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """A straight move 100 m long is refused by the workspace before any inverse kinematics,
    and the joint path of a move no arm can make is never sampled point by point."""
    from elastoprobe.controller.core import kinematics, validation
    from elastoprobe.controller.core.collision import SceneChecker, boxes_from_cell
    from elastoprobe.controller.core.config import load_session_inputs
    from elastoprobe.controller.core.errors import MotionRefused
    from elastoprobe.controller.core.geometry import probe_tcp_pose

    inputs = load_session_inputs(REPO / "config" / "plans" / "demo.yaml")
    model = validation.arm_model_for(inputs.cell)
    seed = np.radians(inputs.cell.robot.home_joints_deg)
    sampled: list[int] = []
    real = kinematics._valid_branches

    def counting(model, flange, hint):   # type: ignore[no-untyped-def]
        sampled.append(len(flange))
        return real(model, flange, hint)

    monkeypatch.setattr(kinematics, "_valid_branches", counting)
    down = np.array([0.0, 0.0, 1.0])
    a = probe_tcp_pose(np.array([400.0, -50_000.0, 300.0]), down, np.array([1.0, 0.0, 0.0]), 90.0)
    b = probe_tcp_pose(np.array([400.0, 50_000.0, 300.0]), down, np.array([1.0, 0.0, 0.0]), 90.0)
    assert kinematics.linear_path_joints(model, a, b, seed) is None
    assert max(sampled, default=0) <= 1000
    workspace, keep_out = boxes_from_cell(inputs.cell.limits)
    validator = validation.PathValidator(model, SceneChecker([], None, keep_out, workspace), seed, 10.0)
    sampled.clear()
    with pytest.raises(MotionRefused, match="workspace"):
        validator.validate_path(a, b)
    assert sampled == []


# ----------------------------------------------------------------------------- case 8
def test_case8_a_nul_byte_is_reported_at_its_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lines = SIM_CELL.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.startswith("  max_force_n:"))
    lines[k] = lines[k][:6] + "\x00" + lines[k][6:]
    cell = tmp_path / "cell.yaml"
    cell.write_text("\n".join(lines) + "\n")
    assert main(["check", str(REPO / "config" / "plans" / "demo.yaml"), "--cell", str(cell)]) == 2
    err = capsys.readouterr().err
    assert f"{cell}:{k + 1}:7: " in err, err
    assert "NUL" in err or "#x0000" in err


# ----------------------------------------------------------------------------- case 9 (meshes)
def _holed_mesh() -> tuple[bytes, np.ndarray]:
    """The user mesh with the faces around its top-most vertex removed: a hole in the top."""
    m = trimesh.load(str(OBJECTS / "user_object.ply"), process=False)
    top = int(np.argmax(m.vertices[:, 2]))
    keep = ~np.any(m.faces == top, axis=1)
    return _mesh_bytes(faces=m.faces[keep]), m.vertices[top]


def _non_manifold_mesh() -> bytes:
    """The user mesh with a fin: a third face on one of its edges."""
    m = trimesh.load(str(OBJECTS / "user_object.ply"), process=False)
    a, b = m.faces[0][:2]
    apex = len(m.vertices)
    v = np.vstack([m.vertices, m.vertices[a] + [0.0, 0.0, 15.0]])
    return _mesh_bytes(vertices=v, faces=np.vstack([m.faces, [[a, b, apex]]]))


def test_case9_holes_and_non_manifold_edges_are_a_warning_that_says_where(tmp_path: Path,
                                                                          capsys: pytest.CaptureFixture[str]) -> None:
    ply, top = _holed_mesh()
    plan = _plan(tmp_path, _user_object(tmp_path, ply=ply))
    assert main(["check", str(plan)]) == 0
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    assert "hole" in captured.err and "warning" in captured.err, captured.err
    assert f"{top[2]:.0f}" in captured.err          # where: the hole's place (mm) is named
    plan = _plan(tmp_path, _user_object(tmp_path, ply=_non_manifold_mesh()))
    assert main(["check", str(plan)]) == 0
    err = capsys.readouterr().err
    assert "non-manifold" in err and "warning" in err, err


def test_the_shipped_objects_give_no_mesh_warning(capsys: pytest.CaptureFixture[str]) -> None:
    for plan in ("demo.yaml", "rubber_ball.yaml", "user_object.yaml"):
        assert main(["check", str(REPO / "config" / "plans" / plan)]) == 0
        assert "warning" not in capsys.readouterr().err


def _special_files(tmp: Path) -> dict[str, Path]:
    fifo = tmp / "fifo.yaml"
    os.mkfifo(fifo)
    huge = tmp / "huge.yaml"
    with open(huge, "wb") as f:
        f.truncate(64 * 1024 * 1024 * 1024)         # sparse: 64 GiB that take no disk
    return {"device": Path("/dev/zero"), "pipe": fifo, "huge": huge}


@pytest.mark.timeout(120)
@pytest.mark.parametrize("special", ["device", "pipe", "huge"])
def test_a_device_a_pipe_or_a_huge_file_named_as_an_input_file_is_refused_without_reading_it(
        tmp_path: Path, special: str, capsys: pytest.CaptureFixture) -> None:
    """/dev/zero named as the cell was read until memory ran out; a pipe blocks its reader; a
    64 GiB file would be read whole. Plan, cell, object, mesh and calibration file: each
    refused at once, exit 2, named."""
    bad = _special_files(tmp_path)[special]
    obj = _user_object(tmp_path)
    plan = _plan(tmp_path, obj)
    cases = {"plan": (["check", str(bad)], str(bad)),
             "cell": (["check", str(plan), "--cell", str(bad)], str(bad))}
    obj_text = obj.read_text()
    mesh_obj = tmp_path / "mesh_obj.yaml"
    mesh_obj.write_text(obj_text.replace("file: user_object.ply", f"file: {bad}"))
    cases["mesh"] = (["check", str(_plan(tmp_path, mesh_obj, "mesh_plan.yaml"))], "mesh_obj.yaml:12:9")
    cell = tmp_path / "cell.yaml"
    cell.write_text((REPO / "config" / "cells" / "sim_miscalibrated.yaml").read_text()
                    .replace("calibration_file: sim_miscalibrated.calibration.json", f"calibration_file: {bad}")
                    .replace("file: ../objects/", f"file: {OBJECTS}/"))
    cases["calibration"] = (["check", str(plan), "--cell", str(cell)],
                            "more than the" if special == "huge" else "not a regular file")
    for what, (args, named) in cases.items():
        capsys.readouterr()
        code = main(args)
        err = capsys.readouterr().err
        if what == "calibration":        # a calibration problem is reported, the cell is still valid
            assert named in err + capsys.readouterr().out, (what, err)
            continue
        assert code == 2, (what, err)
        assert named in err and "Traceback" not in err, (what, err)
        assert ("more than the" if special == "huge" else "not a regular file") in err, (what, err)


def test_an_output_that_is_a_device_a_pipe_or_a_folder_is_refused_and_left_as_it_was(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Run as root, ``diagram --out /dev/full`` renamed a regular file over the device; the
    same path with ``/dev/null`` would have broken the machine. Outputs are written only
    over regular files."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    link = tmp_path / "to-null"
    link.symlink_to("/dev/null")
    folder = tmp_path / "folder"
    folder.mkdir()
    for target in (fifo, link, folder):
        with pytest.raises(SystemExit) as exc:
            main(["diagram", "--out", str(target)])
        assert exc.value.code == 2
        assert "is not a regular file" in capsys.readouterr().err
        with pytest.raises(DiskError, match="not a regular file"):
            atomic_write_bytes(target, b"x")
    assert fifo.is_fifo() and link.is_symlink() and Path("/dev/null").is_char_device() and folder.is_dir()
    assert not [p for p in tmp_path.iterdir() if p.name not in {"fifo", "to-null", "folder"}]   # no temporaries left


@pytest.mark.parametrize("argv", [
    ["run", str(REPO / "config" / "plans" / "demo.yaml"), "--out", ""],
    ["salvage", ".", "--out", " "],
    ["sim", "object", "--seed", "3", "--out", ""],
    ["export", ".", "--format", "hdf5", "--out", ""],
])
def test_an_empty_output_name_is_refused_not_read_as_the_default(
        argv: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    """``--out "$DIR"`` with DIR unset: ``run`` started a whole session in ./sessions/<date>-demo."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert "name is empty" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_a_damaged_calibration_file_is_bad_input_and_is_left_as_it_was(
        tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    """The calibration file is the user's: unreadable or damaged, it is exit 2 (not 1, a fault
    of the cell) before the arm moves (it was found only after every pose had been measured),
    and it is not overwritten."""
    def no_cell(*args: object, **kwargs: object) -> None:
        raise AssertionError("the cell was built: the arm would have moved")

    monkeypatch.setattr(calibration_runner, "calibration_cell", no_cell)
    damaged = tmp_path / "calibration.json"
    damaged.write_bytes(b'{"format": "elastoprobe-calibration", "sections": ')
    code = main(["calibrate", "tcp", "--cell", str(SIM_CELL), "--out", str(damaged)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"{damaged}: unreadable calibration file" in err and "Traceback" not in err
    assert damaged.read_bytes() == b'{"format": "elastoprobe-calibration", "sections": '


def test_check_says_when_the_budget_stops_the_plan_before_anything_is_probed(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """The finest sweep spacing (0.1 mm: a sweep at 5 mm/s) under a 3 minute budget: `check`
    said "valid" while `run` would spend the whole budget sweeping and probe nothing."""
    demo = REPO / "config" / "plans" / "demo.yaml"
    text = demo.read_text().replace("sweep_spacing_mm: 4.0", "sweep_spacing_mm: 0.1")
    text = text.replace("max_robot_hours: 4.0", "max_robot_hours: 0.05")
    text = text.replace("../cells/", f"{REPO}/config/cells/").replace("../objects/", f"{REPO}/config/objects/")
    plan = tmp_path / "slow_sweep.yaml"
    plan.write_text(text)
    assert main(["check", str(plan)]) == 0
    out = capsys.readouterr().out
    assert "warning: the plan needs about" in out and "nothing would be probed" in out, out
    assert main(["check", str(demo), "--json"]) == 0
    assert '"budget_warning": null' in capsys.readouterr().out


def test_a_binary_stl_of_the_wrong_length_is_named_for_what_it_is(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """trimesh retries it as ASCII, which wants an optional module: without that module the
    message named it ("No module named 'charset_normalizer'"), as if the user had to install
    something. With it or without it, the message is about the file."""
    obj = _user_object(tmp_path, edits={"file: user_object.ply": "file: broken.stl"})
    (tmp_path / "broken.stl").write_bytes(b"\0" * 80 + (4_000_000_000).to_bytes(4, "little") + b"\xee" * 50)
    assert main(["check", str(_plan(tmp_path, obj))]) == 2
    err = capsys.readouterr().err
    assert f"{obj}:12:9: broken.stl: " in err and "Traceback" not in err, err
    assert "module" not in err, err
    assert "Binary STL has incorrect length" in err or "holds no triangles" in err, err
