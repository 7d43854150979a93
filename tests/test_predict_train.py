"""``predict`` serves what ``train`` produced on a killed session, flags each sample's
support, and refuses (exit 2, no traceback) queries outside the trained ranges unless
``--extrapolate`` is given (issue 15, item 9 / build 6; issue 14, build 2)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller.export import export_hdf5, read_back
from test_session_util import TINY_PLAN, child_env, run_cli

pytestmark = [pytest.mark.timeout(900)]


@pytest.fixture(scope="module")
def killed_before_models(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, str]]:
    """The tiny session SIGKILLed just before its first models were saved: regions and
    characterization are in the journal, no models phase is."""
    root = tmp_path_factory.mktemp("predict")
    out = root / "session"
    env = child_env(root / "locks", crash_at="models:before_save")
    child = run_cli(["run", str(TINY_PLAN), "--out", str(out), "--seed", "1", "--quiet"], env)
    assert child.returncode == -9, child.stderr[-2000:]
    return out, child_env(root / "locks")


def test_train_on_a_killed_session_is_what_predict_serves(killed_before_models) -> None:
    out, env = killed_before_models
    before = run_cli(["predict", str(out), "--region", "0", "--force", "8", "--angle", "90"], env)
    assert before.returncode == 2 and "no trained models yet" in before.stderr and "Traceback" not in before.stderr
    trained = run_cli(["train", str(out)], env)
    assert trained.returncode == 0, trained.stderr[-2000:]
    manifest = json.loads((out / "models" / "retrained" / "manifest.json").read_text())
    assert manifest["session_models_round"] == -1 and set(manifest["regions"]) == {"0", "1"}
    for region in ("0", "1"):
        served = run_cli(["predict", str(out), "--region", region, "--force", "8", "--angle", "90", "--json"], env)
        assert served.returncode == 0, served.stderr[-2000:]
        doc = json.loads(served.stdout)
        assert doc["models"].startswith("retrained by `elastoprobe train`")
        assert not doc["extrapolated"]
        depth = np.array(doc["depth_mm"], dtype=float)
        assert np.all(np.isfinite(depth)) and len(doc["support"]) == depth.size
        assert set(doc["support"]) <= {"measured", "mirrored", "tip", "inferred", "unsupported"}
        assert "measured" in doc["support"]
        bounds = manifest["regions"][region]["depth_bounds_mm"]
        assert bounds[0] <= depth.min() and depth.max() <= bounds[1]


def test_out_of_range_queries_are_refused_or_flagged_on_request(killed_before_models) -> None:
    out, env = killed_before_models
    if not (out / "models" / "retrained" / "manifest.json").exists():
        assert run_cli(["train", str(out)], env).returncode == 0
    refused = run_cli(["predict", str(out), "--region", "1", "--force", "1000", "--angle", "90"], env)
    assert refused.returncode == 2
    assert "outside what the model was trained on" in refused.stderr and "--extrapolate" in refused.stderr
    assert "Traceback" not in refused.stderr and refused.stdout == ""
    angle = run_cli(["predict", str(out), "--region", "1", "--force", "8", "--angle", "20"], env)
    assert angle.returncode == 2 and "outside what the model was trained on" in angle.stderr
    flagged = run_cli(["predict", str(out), "--region", "1", "--force", "1000", "--angle", "90", "--extrapolate",
                       "--json"], env)
    assert flagged.returncode == 0, flagged.stderr[-2000:]
    doc = json.loads(flagged.stdout)
    assert doc["extrapolated"] and all(v is not None for v in doc["depth_mm"])
    text = run_cli(["predict", str(out), "--region", "1", "--force", "1000", "--angle", "90", "--extrapolate"], env)
    assert text.returncode == 0 and "EXTRAPOLATED" in text.stdout


def test_the_export_carries_what_predict_serves(killed_before_models, tmp_path: Path) -> None:
    out, env = killed_before_models
    if not (out / "models" / "retrained" / "manifest.json").exists():
        assert run_cli(["train", str(out)], env).returncode == 0
    back = read_back(export_hdf5(out, tmp_path / "export.h5"))
    assert set(back.retrained_models) == {0, 1}
    for model in back.retrained_models.values():
        codes = model["weights"]["support_codes"]
        assert codes.ndim == 3 and codes.shape[-1] == model["weights"]["x_mm"].size
        assert model["meta"]["serving"]["depth_max_mm"] > 0.0


def test_train_reads_the_placement_and_the_rounds_the_journal_last_recorded() -> None:
    """train maps old scans with the object where it was last registered (the journal's
    word, as a resumed session does), else where the cell file puts it; the newest round
    of a phase is the last of an unbroken count from 0."""
    from elastoprobe.controller.core.geometry import Pose
    from elastoprobe.controller.phases import registered_placement
    from elastoprobe.controller.journal import newest_phase

    class Journal:
        def __init__(self, placements: list[list[float]], rounds: int) -> None:
            self.placements, self.rounds = placements, rounds

        def events(self, kind: str) -> list[dict]:
            assert kind == "object_registered"
            return [{"record": {"base_to_object": p}} for p in self.placements]

        def phase(self, name: str, round_: int) -> object | None:
            return f"{name} {round_}" if round_ < self.rounds else None

    moved = [[100.0, 0.0, 0.0, 0.0, 0.0, 0.0], [120.0, 5.0, 0.0, 0.0, 0.0, 0.1]]
    assert registered_placement(Journal([], 0)) is None
    placed = registered_placement(Journal(moved, 0))
    assert isinstance(placed, Pose) and np.allclose(placed.to_list(), Pose.from_list(moved[-1]).to_list())
    assert newest_phase(Journal([], 3), "regions") == (2, "regions 2")
    assert newest_phase(Journal([], 0), "models") == (-1, None)
