"""Serving trained region models: ``predict`` and ``train`` (refit from the journal)."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import atomic_write_json
from .errors import InputError
from .journal import Journal
from .learning.models import RegionModel
from .provenance import sha256_file


# What `elastoprobe train` wrote: the refitted models and the ranges they were fitted on.
RETRAINED_MANIFEST = Path("models") / "retrained" / "manifest.json"


@dataclass(frozen=True)
class ServedModel:
    """One region's model file as ``predict`` serves it, with the ranges it was fitted on
    (``None`` for a session recorded before the ranges were: only the force is known)."""

    path: Path
    force_range_n: tuple[float, float] | None
    angle_range_deg: tuple[float, float] | None


def trained_ranges(measured_force_n: np.ndarray, commanded_force_n: np.ndarray,
                   angle_deg: np.ndarray) -> dict[str, list[float]]:
    """The force (N) and angle (deg) ranges a region's model was fitted on: the measured
    forces together with the commanded levels (a query at a commanded level is inside even
    where the force loop settled a little short of it)."""
    f = np.concatenate([np.asarray(measured_force_n, float).ravel(), np.asarray(commanded_force_n, float).ravel()])
    a = np.asarray(angle_deg, float).ravel()
    return {"force_range_n": [float(f.min()), float(f.max())], "angle_range_deg": [float(a.min()), float(a.max())]}


def _verified(session_dir: Path, region: str, info: dict[str, Any], recorder: str) -> ServedModel:
    """A model file is served only as ``recorder`` recorded it (sha256)."""
    path = Path(session_dir) / info["path"]
    if info.get("sha256") and (not path.is_file() or sha256_file(path) != info["sha256"]):
        raise InputError(f"the model file of region {region} is missing or changed since {recorder} recorded it "
                         f"(refit with: elastoprobe train {session_dir})", path=str(path))
    f, a = info.get("force_range_n"), info.get("angle_range_deg")
    return ServedModel(path, None if f is None else (float(f[0]), float(f[1])),
                       None if a is None else (float(a[0]), float(a[1])))


def served_models(session_dir: Path) -> tuple[str, dict[int, ServedModel]]:
    """(where they come from, region -> model) that ``predict`` serves: the models of the
    newest committed model phase, or those ``elastoprobe train`` refitted if it ran after
    that phase (or when the session never reached one, e.g. it was killed before)."""
    j = Journal.open_readonly(session_dir)
    try:
        rounds, rec = 0, None
        while (nxt := j.phase("models", rounds)) is not None:
            rec, rounds = nxt, rounds + 1
    finally:
        j.close()
    manifest_path = Path(session_dir) / RETRAINED_MANIFEST
    if manifest_path.is_file():
        try:
            manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
            after = int(manifest["model_rounds"])
            regions = dict(manifest["regions"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise InputError(f"unreadable ({exc}); refit with: elastoprobe train {session_dir}",
                             path=str(manifest_path)) from None
        if after >= rounds:
            return "retrained", {int(k): _verified(session_dir, k, v, "elastoprobe train")
                                 for k, v in regions.items()}
    if rec is None:
        raise InputError(f"the session has no trained models yet (fit them with: elastoprobe train {session_dir})",
                         path=str(session_dir))
    return f"round {rounds - 1}", {int(k): _verified(session_dir, k, v, "the session")
                                   for k, v in rec.outputs["regions"].items() if "path" in v}


def predict_profile(session_dir: Path, region: int, force_n: float, angle_deg: float, extrapolate: bool = False
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """(x_mm, depth_mm, ensemble std mm, what lies outside the fitted ranges) predicted by
    region ``region``'s model. A query outside the force (N) or angle (deg) range the model
    was fitted on is refused unless ``extrapolate``; then the list says what is outside."""
    if not 0.0 < angle_deg < 180.0:
        raise InputError(f"--angle {angle_deg}: the approach angle must be in (0, 180) degrees")
    if force_n < 0.0:
        raise InputError(f"--force {force_n}: the force must be >= 0 N")
    _, models = served_models(session_dir)
    if region not in models:
        raise InputError(f"--region {region}: the session has models for regions {sorted(models)}")
    served = models[region]
    model = RegionModel.load(served.path)
    force_range = served.force_range_n or model.force_range_n
    outside = []
    if not force_range[0] <= force_n <= force_range[1]:
        outside.append(f"--force {force_n:g} N is outside the {force_range[0]:.2f}-{force_range[1]:.2f} N "
                       f"region {region}'s model was fitted on")
    if served.angle_range_deg is not None and not served.angle_range_deg[0] <= angle_deg <= served.angle_range_deg[1]:
        lo, hi = served.angle_range_deg
        outside.append(f"--angle {angle_deg:g} deg is outside the {lo:g}-{hi:g} deg region {region}'s model "
                       f"was fitted on")
    if outside and not extrapolate:
        raise InputError("; ".join(outside) + " (pass --extrapolate to have the model answer anyway)")
    mean, std = model.predict_ensemble(force_n, angle_deg)
    return np.asarray(model.x_mm), np.asarray(mean).reshape(-1), np.asarray(std).reshape(-1), outside


def retrain_session(session_dir: Path) -> list[str]:
    """Refit every region's model from the journal into DIR/models/retrained/ (the session's
    committed models stay as they were) and write its manifest last: from then on
    ``predict`` serves these models, until the session commits a newer model phase.
    Returns a line per region."""
    from .evaluation import _inputs_of
    from .learning.models import TrainConfig, fit_region_model

    j = Journal.open_readonly(session_dir)
    try:
        inputs = _inputs_of(j)
        seed = int(j.session()["seed"])
        r, rec = 0, None
        while (nxt := j.phase("regions", r)) is not None:
            rec, r = nxt, r + 1
        if rec is None:
            raise InputError("the session has no regions yet", path=str(session_dir))
        labels = dict(zip(rec.arrays["labelled_targets"].tolist(), rec.arrays["labels"].tolist()))
        # The averaged scans' noise the session measured: the fit stops at it, as in the run.
        noise_mm, q = None, 0
        while (models_rec := j.phase("models", q)) is not None:
            noise_mm, q = models_rec.outputs.get("noise_mm", noise_mm), q + 1
        rows: dict[int, list] = {}
        for step in j.steps(statuses=["done"]):
            label = labels.get(step.plan.target_index)
            if label is None:
                continue
            res = j.step_result(step.step_id)
            rows.setdefault(label, []).append((float(np.linalg.norm(np.nanmean(res.scan_force_n, axis=0))),
                                               step.plan.angle_deg, res.profile_depth_mm, step.plan.target_index,
                                               step.plan.force_n))
    finally:
        j.close()
    m = inputs.plan.model
    x = np.linspace(-m.profile_span_mm / 2, m.profile_span_mm / 2, m.profile_samples)
    out = []
    retrained = Path(session_dir) / "models" / "retrained"
    retrained.mkdir(parents=True, exist_ok=True)
    regions: dict[str, dict[str, Any]] = {}
    for label, data in sorted(rows.items()):
        f, a, d, p, commanded = (np.array(v) for v in zip(*data))
        if len(f) < 3:          # as the session's model phase: too few profiles to fit
            out.append(f"region {label}: only {len(f)} profiles, no model")
            continue
        cfg = TrainConfig(hidden_units=m.hidden_units, ensemble=m.ensemble - 1,
                          epochs_per_stage=max(10, m.max_epochs // 5), seed=seed * 1000 + label)
        model = fit_region_model(f, a, d, x, point_ids=p, config=cfg, noise_mm=noise_mm)
        path = model.save(retrained / f"region{label}.npz")
        regions[str(label)] = {"path": str(Path(path).relative_to(session_dir)), "sha256": sha256_file(path),
                               "n_profiles": int(len(f)), **trained_ranges(f, commanded, a)}
        out.append(f"region {label}: {len(f)} profiles -> {path} ({model.model_hash()[:12]})")
    atomic_write_json(Path(session_dir) / RETRAINED_MANIFEST, {"model_rounds": q, "regions": regions})
    out.append(f"predict serves these models now (until the session fits newer ones): "
               f"{Path(session_dir) / RETRAINED_MANIFEST}")
    return out
