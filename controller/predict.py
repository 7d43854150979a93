"""Serving trained region models: ``predict`` and ``train`` (refit from the journal)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import InputError
from .journal import Journal
from .learning.models import RegionModel
from .provenance import sha256_file


def latest_models(session_dir: Path) -> tuple[int, dict[int, Path]]:
    """(model round, region -> model file) of the newest committed model phase."""
    j = Journal.open_readonly(session_dir)
    try:
        r, rec = 0, None
        while (nxt := j.phase("models", r)) is not None:
            rec, r = nxt, r + 1
    finally:
        j.close()
    if rec is None:
        raise InputError("the session has no trained models yet", path=str(session_dir))
    files = {int(k): Path(session_dir) / v["path"] for k, v in rec.outputs["regions"].items() if "path" in v}
    for k, v in rec.outputs["regions"].items():     # a model file is served only as it was recorded
        if "path" in v and v.get("sha256") and (not files[int(k)].is_file() or sha256_file(files[int(k)]) != v["sha256"]):
            raise InputError(f"the model file of region {k} is missing or changed since the session recorded it "
                             f"(refit with: elastoprobe train {session_dir})", path=str(files[int(k)]))
    return r - 1, files


def predict_profile(session_dir: Path, region: int, force_n: float, angle_deg: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x_mm, depth_mm, ensemble std mm) predicted by region ``region``'s model."""
    if not 0.0 < angle_deg < 180.0:
        raise InputError(f"--angle {angle_deg}: the approach angle must be in (0, 180) degrees")
    if force_n < 0.0:
        raise InputError(f"--force {force_n}: the force must be >= 0 N")
    _, files = latest_models(session_dir)
    if region not in files:
        raise InputError(f"--region {region}: the session has models for regions {sorted(files)}")
    model = RegionModel.load(files[region])
    mean, std = model.predict_ensemble(force_n, angle_deg)
    return np.asarray(model.x_mm), np.asarray(mean).reshape(-1), np.asarray(std).reshape(-1)


def retrain_session(session_dir: Path) -> list[str]:
    """Refit every region's model from the journal into DIR/models/retrained/ (the session's
    committed models stay as they were); returns a line per region."""
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
                                               step.plan.angle_deg, res.profile_depth_mm, step.plan.target_index))
    finally:
        j.close()
    m = inputs.plan.model
    x = np.linspace(-m.profile_span_mm / 2, m.profile_span_mm / 2, m.profile_samples)
    out = []
    (Path(session_dir) / "models" / "retrained").mkdir(parents=True, exist_ok=True)
    for label, data in sorted(rows.items()):
        f, a, d, p = (np.array(v) for v in zip(*data))
        cfg = TrainConfig(hidden_units=m.hidden_units, ensemble=m.ensemble - 1,
                          epochs_per_stage=max(10, m.max_epochs // 5), seed=seed * 1000 + label)
        model = fit_region_model(f, a, d, x, point_ids=p, config=cfg, noise_mm=noise_mm)
        path = model.save(Path(session_dir) / "models" / "retrained" / f"region{label}.npz")
        out.append(f"region {label}: {len(f)} profiles -> {path} ({model.model_hash()[:12]})")
    return out
