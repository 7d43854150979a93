"""``elastoprobe train DIR``: refit a session's region models from its journal.

The models are fitted exactly as the session fits them (phases.fit_region: complete
targets, the same configuration and seeds) from the newest region map, and written to
DIR/models/retrained/<utc time>/; a manifest (DIR/models/retrained/manifest.json,
written last and atomically) switches ``predict`` to them. The session's own models
stay as they were. Works on a killed session too, once its regions are clustered.
"""
from __future__ import annotations

import datetime as _dt
from pathlib import Path
from typing import Any

from .core.atomic import atomic_write_json
from .core.config import load_session_inputs
from .core.errors import InputError
from .journal import Journal, newest_phase
from .phases import collect_region_steps, fit_region, region_train_config, registered_placement, scan_geometry
from .predict import MANIFEST, RETRAINED_DIR, newest_models_round


def retrain_session(session_dir: Path) -> list[str]:
    """Refit every region's model (see the module docstring); a line per region."""
    session_dir = Path(session_dir)
    j = Journal.open_readonly(session_dir)
    try:
        prov = j.provenance()
        inputs = load_session_inputs(prov["plan"]["path"], prov["cell"]["path"])
        seed = int(j.session()["seed"])
        _, rec = newest_phase(j, "regions")
        if rec is None:
            raise InputError("the session has no regions yet: nothing to train", path=str(session_dir))
        labels = dict(zip(rec.arrays["labelled_targets"].tolist(), rec.arrays["labels"].tolist()))
        n_regions = int(rec.outputs["n_regions"])
        models_round, models_outputs = newest_models_round(j)
        # The averaged scans' noise the session measured, as the run used it.
        noise = float((models_outputs or {}).get("noise_mm") or 0.0)
        # The scan geometry the session used: the cell's scanner mount, the object where it
        # was last registered or else where the cell file puts it.
        geometry = scan_geometry(inputs, inputs.cell.tool.tcp_to_scanner.pose(),
                                 registered_placement(j) or inputs.cell.object.base_to_object.pose())
        data = {region: collect_region_steps(j, labels, region, geometry) for region in range(n_regions)}
    finally:
        j.close()
    m = inputs.plan.model
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S%fZ")
    out_dir = session_dir / RETRAINED_DIR / stamp
    lines: list[str] = []
    regions: dict[str, dict[str, Any]] = {}
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        for region, steps in data.items():
            if len(steps) < 3:
                lines.append(f"region {region}: only {len(steps)} profiles, no model")
                continue
            cfg = region_train_config(m, seed, region, geometry.tip_radius_mm)
            model, info = fit_region(steps, cfg, geometry.tip_radius_mm, noise)
            path = model.save(out_dir / f"region{region}.npz")
            regions[str(region)] = {"path": str(path.relative_to(session_dir)), "model_hash": model.model_hash(),
                                    "n_profiles": len(steps), **info}
            lines.append(f"region {region}: {len(steps)} profiles -> {path} ({model.model_hash()[:12]}; "
                         f"mirror {'admitted' if info['mirror']['admitted'] else 'not admitted'})")
        atomic_write_json(session_dir / RETRAINED_DIR / MANIFEST,
                          {"trained_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                           "session_models_round": models_round, "regions": regions})
    except OSError as exc:
        raise InputError(f"cannot write the retrained models: {exc.strerror or exc}",
                         path=str(exc.filename or out_dir)) from exc
    return lines
