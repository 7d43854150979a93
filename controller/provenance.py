"""What a session was run with: input files and their hashes, package versions, git revision.

``collect_provenance`` returns plain JSON-able data that the journal stores (one row
per top-level key). Everything except the plan and cell files is best effort: a
missing package, no git, or a git that hangs becomes ``None``, never an exception —
provenance must not stop a session from starting.
"""
from __future__ import annotations

import hashlib
import importlib.metadata
import os
import platform
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

from .core.calfile import believed_cell
from .core.config import load_cell
from .core.errors import InputError
from .core.inputfiles import MAX_MESH_BYTES, check_input_file, read_input_bytes

# Distributions whose versions change results (numerics, training, robot protocol, machine).
TRACKED_PACKAGES: tuple[str, ...] = (
    "elastoprobe", "numpy", "scipy", "torch", "ur-rtde", "transitions", "pydantic",
    "ruamel.yaml", "scikit-learn", "trimesh", "pyserial", "h5py",
)

_CHUNK = 1 << 20


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_text(text: str) -> str:
    """sha256 of ``text`` encoded as UTF-8 (equals :func:`sha256_file` of a UTF-8 file with that text)."""
    return sha256_bytes(text.encode("utf-8"))


def sha256_file(path: str | os.PathLike[str]) -> str:
    """Hex sha256 of a file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    check_input_file(path, MAX_MESH_BYTES)
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def _input_file(path: str | os.PathLike[str], what: str) -> dict[str, Any]:
    p = Path(path)
    try:
        data = read_input_bytes(p)
    except OSError as exc:
        raise InputError(f"cannot read the {what} file: {exc.strerror or exc}", path=str(p)) from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"the {what} file is not UTF-8 text (byte {exc.start})", path=str(p)) from None
    return {"path": str(p.resolve()), "text": text, "sha256": sha256_bytes(data), "size_bytes": len(data)}


def _optional_file(path: str | os.PathLike[str] | None) -> dict[str, Any] | None:
    if path is None:
        return None
    p = Path(path)
    try:
        return {"path": str(p.resolve()), "sha256": sha256_file(p), "size_bytes": p.stat().st_size}
    except OSError as exc:
        return {"path": str(p), "sha256": None, "error": exc.strerror or str(exc)}


def package_versions(names: tuple[str, ...] = TRACKED_PACKAGES) -> dict[str, str | None]:
    """Installed distribution versions (None when not installed); never imports the packages."""
    out: dict[str, str | None] = {}
    for name in names:
        try:
            out[name] = importlib.metadata.version(name)
        except Exception:   # noqa: BLE001 - any metadata problem means "unknown"
            out[name] = None
    return out


def git_revision(directory: str | os.PathLike[str] | None = None, timeout_s: float = 5.0) -> dict[str, Any] | None:
    """``{"revision": sha, "dirty": bool|None}`` of the repository holding ``directory``
    (default: this package's source), or None when there is none or git fails."""
    where = Path(directory) if directory is not None else Path(__file__).resolve().parent
    env = {**os.environ, "GIT_OPTIONAL_LOCKS": "0"}   # never take the index lock of a busy tree

    def run(*args: str) -> str | None:
        try:
            proc = subprocess.run(["git", "-C", str(where), *args], capture_output=True, text=True,
                                  timeout=timeout_s, env=env, stdin=subprocess.DEVNULL)
        except (OSError, subprocess.SubprocessError):
            return None
        return proc.stdout.strip() if proc.returncode == 0 else None

    rev = run("rev-parse", "HEAD")
    if not rev:
        return None
    status = run("status", "--porcelain", "--untracked-files=no")
    return {"revision": rev, "dirty": None if status is None else bool(status)}


def python_info() -> dict[str, Any]:
    return {"version": platform.python_version(), "implementation": platform.python_implementation(),
            "executable": sys.executable}


def calibration_entry(cell_path: str | os.PathLike[str],
                      calibration_path: str | os.PathLike[str] | None) -> dict[str, Any] | None:
    """The calibration file a session used: ``{path, sha256, size_bytes, applied_sections,
    problems}``, or None when the cell names none and needs none (a calibrated simulated
    cell). ``problems`` says why the controller's geometry may be off (missing, partial,
    stale or unreadable file; a miscalibrated simulated cell without one). Never raises."""
    entry = _optional_file(calibration_path)
    try:
        spec, _ = load_cell(cell_path)
        _, state = believed_cell(spec, cell_path)
    except Exception as exc:   # noqa: BLE001 - provenance must not stop a session
        if entry is None:
            return None
        extra: dict[str, Any] = {"applied_sections": None, "problems": [f"calibration not checked: {exc}"]}
    else:
        extra = {"applied_sections": list(state.applied), "problems": list(state.problems)}
    if entry is None and not extra["problems"]:
        return None
    return {**(entry or {"path": None, "sha256": None}), **extra}


def collect_provenance(plan_path: str | os.PathLike[str], cell_path: str | os.PathLike[str],
                       calibration_path: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """Provenance of a session about to start.

    Returns ``{"plan": {path, text, sha256, size_bytes}, "cell": {...}, "calibration":
    {path, sha256, size_bytes, applied_sections, problems} | None (:func:`calibration_entry`),
    "packages": {dist: version|None}, "python": {...},
    "platform": {...}, "git": {revision, dirty} | None}``. The plan and cell must be
    readable UTF-8 (InputError otherwise: they were validated just before); the rest
    never raises.
    """
    return {
        "plan": _input_file(plan_path, "plan"),
        "cell": _input_file(cell_path, "cell"),
        "calibration": calibration_entry(cell_path, calibration_path),
        "packages": package_versions(),
        "python": python_info(),
        "platform": {"system": platform.system(), "release": platform.release(),
                     "machine": platform.machine(), "host": socket.gethostname()},
        "git": git_revision(),
    }
