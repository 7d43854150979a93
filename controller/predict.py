"""Serving trained region models: which models a session serves, and ``predict``.

A session serves the models of its newest committed models phase, unless
``elastoprobe train DIR`` refitted them since (DIR/models/retrained/, with a manifest
naming the models round it saw): those serve until the session commits a newer models
phase. A session killed before its first models phase serves what ``train`` made.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from .core.errors import InputError
from .journal import Journal, newest_phase
from .learning.models import OutOfRange, RegionModel, ServedProfile

RETRAINED_DIR = Path("models") / "retrained"
MANIFEST = "manifest.json"


@dataclass(frozen=True)
class ServedModels:
    """The region model files a session serves and where they come from."""

    files: dict[int, Path]
    source: str                  # "models round N" or "retrained by `elastoprobe train` (...)"


def newest_models_round(j: Journal) -> tuple[int, dict | None]:
    """(round, outputs) of the newest committed models phase; (-1, None) if there is none."""
    round_, rec = newest_phase(j, "models")
    return round_, (rec.outputs if rec is not None else None)


def served_models(session_dir: Path) -> ServedModels:
    """The models ``predict`` serves for a session (see the module docstring)."""
    j = Journal.open_readonly(session_dir)
    try:
        round_, outputs = newest_models_round(j)
    finally:
        j.close()
    manifest = read_manifest(Path(session_dir))
    if manifest is not None and int(manifest.get("session_models_round", -1)) >= round_:
        files = {int(k): Path(session_dir) / v["path"] for k, v in manifest["regions"].items()}
        return ServedModels(files, f"retrained by `elastoprobe train` at {manifest.get('trained_utc', '?')}")
    if outputs is None:
        raise InputError("the session has no trained models yet (run `elastoprobe train` on it, or resume it)",
                         path=str(session_dir))
    files = {int(k): Path(session_dir) / v["path"] for k, v in outputs["regions"].items() if "path" in v}
    return ServedModels(files, f"models round {round_}")


def read_manifest(session_dir: Path) -> dict | None:
    """The retrained models' manifest, or None when there is none (or it cannot be read)."""
    path = Path(session_dir) / RETRAINED_DIR / MANIFEST
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and isinstance(data.get("regions"), dict) else None


def load_region_model(session_dir: Path, region: int) -> tuple[RegionModel, str]:
    """Region ``region``'s served model and where it comes from."""
    served = served_models(session_dir)
    if region not in served.files:
        raise InputError(f"--region {region}: the session has models for regions {sorted(served.files)}")
    try:
        return RegionModel.load(served.files[region]), served.source
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"cannot load the model of region {region}: {exc}", path=str(served.files[region])) from exc


def predict_profile(session_dir: Path, region: int, force_n: float, angle_deg: float,
                    extrapolate: bool = False) -> tuple[ServedProfile, str]:
    """The profile region ``region``'s model serves at (F, alpha), and the models' source.

    A query outside the forces and angles the model was trained on is refused (exit 2)
    unless ``extrapolate``; then it is served, clipped to the physical bounds, flagged.
    """
    if not 0.0 < angle_deg < 180.0:
        raise InputError(f"--angle {angle_deg}: the approach angle must be in (0, 180) degrees")
    if force_n < 0.0:
        raise InputError(f"--force {force_n}: the force must be >= 0 N")
    model, source = load_region_model(session_dir, region)
    try:
        return model.serve(force_n, angle_deg, extrapolate=extrapolate), source
    except OutOfRange as exc:
        raise InputError(f"region {region}: {exc}; pass --extrapolate to be served a flagged, bounded "
                         f"profile anyway") from exc
