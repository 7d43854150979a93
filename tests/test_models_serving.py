"""What a region model may serve: its trained ranges, physical bounds and per-sample support."""
from __future__ import annotations

import json

import numpy as np
import pytest

from elastoprobe.controller.learning.models import (
    OutOfRange, RegionModel, ServingLimits, TrainConfig, fit_region_model,
)
from elastoprobe.controller.learning.profiles import ProfileGrid

X = ProfileGrid(80.0, 128).x_mm


def _model(limits: ServingLimits | None) -> RegionModel:
    f = np.repeat([2.0, 10.0, 20.0], 3)
    a = np.tile([45.0, 90.0, 135.0], 3)
    depth = np.stack([0.2 * fi ** 0.7 * np.exp(-((X - 0.05 * (90 - ai)) / 6.0) ** 2) for fi, ai in zip(f, a)])
    model = fit_region_model(f, a, depth, X, config=TrainConfig(ensemble=2, stages=1, epochs_per_stage=200, seed=1,
                                                                basis_spacing_mm=1.0))
    return model if limits is None else model.with_limits(limits)


def _limits(lo: float = -0.05, hi: float = 1.0) -> ServingLimits:
    codes = np.zeros((3, 3, X.size), dtype=np.int8)
    codes[0, :, : X.size // 2] = 3          # 45 deg: the trailing half inferred
    codes[2, :, X.size // 2:] = 3           # 135 deg: the other half
    codes[:, 2, X.size // 2] = 2            # the tip at 20 N
    return ServingLimits((2.0, 20.0), (45.0, 135.0), lo, hi, np.array([2.0, 10.0, 20.0]),
                         np.array([45.0, 90.0, 135.0]), codes)


@pytest.fixture(scope="module")
def served_model() -> RegionModel:
    return _model(_limits())


def test_queries_outside_the_trained_ranges_are_refused_unless_asked_for(served_model: RegionModel) -> None:
    for f, a in ((25.0, 90.0), (1.0, 90.0), (10.0, 30.0), (10.0, 150.0)):
        with pytest.raises(OutOfRange, match="outside what the model was trained on"):
            served_model.serve(f, a)
    profile = served_model.serve(25.0, 90.0, extrapolate=True)
    assert profile.extrapolated and np.all(np.isfinite(profile.depth_mm))
    inside = served_model.serve(10.0, 90.0)
    assert not inside.extrapolated


def test_served_depths_are_clipped_to_the_bounds_and_flagged() -> None:
    tight = _model(_limits(lo=0.0, hi=0.3))
    raw = tight.raw_batch_mm(np.array([20.0]), np.array([90.0]))[0]
    assert raw.max() > 0.3                                  # the net itself goes deeper
    profile = tight.serve(20.0, 90.0)
    assert profile.depth_mm.max() <= 0.3 and profile.depth_mm.min() >= 0.0
    assert np.array_equal(profile.clipped, (raw > 0.3) | (raw < 0.0))
    # Every serving path applies the same bounds.
    assert tight.predict_mm(20.0, 90.0).max() <= 0.3
    assert tight.predict_members_mm(np.array([20.0]), np.array([90.0])).max() <= 0.3


def test_support_is_the_weakest_of_the_bracketing_trained_cells(served_model: RegionModel) -> None:
    at_90 = served_model.serve(10.0, 90.0).support
    assert np.all(at_90 == 0)                               # an exact trained angle: its own cell
    between = served_model.serve(10.0, 60.0).support       # between 45 and 90 deg
    assert np.all(between[: X.size // 2] == 3) and np.all(between[X.size // 2:] == 0)
    near_top = served_model.serve(15.0, 90.0).support       # between 10 and 20 N
    assert near_top[X.size // 2] == 2


def test_limits_are_saved_hashed_and_loaded(tmp_path, served_model: RegionModel) -> None:
    path = served_model.save(tmp_path / "region0")
    back = RegionModel.load(path)
    assert back.model_hash() == served_model.model_hash()
    assert back.limits is not None and back.limits.force_range_n == (2.0, 20.0)
    assert np.array_equal(back.limits.support_codes, served_model.limits.support_codes)   # type: ignore[union-attr]
    meta = json.loads((tmp_path / "region0.json").read_text())
    assert meta["serving"]["depth_max_mm"] == 1.0
    # Other bounds are another model.
    assert served_model.with_limits(_limits(hi=2.0)).model_hash() != served_model.model_hash()


def test_a_model_file_from_before_the_limits_still_loads_and_serves(tmp_path) -> None:
    plain = _model(None)
    plain.save(tmp_path / "old")
    back = RegionModel.load(tmp_path / "old")
    assert back.limits is None
    profile = back.serve(30.0, 10.0)                        # nothing to refuse against
    assert np.all(profile.support == -1) and not profile.extrapolated
    assert np.array_equal(profile.depth_mm, plain.raw_batch_mm(np.array([30.0]), np.array([10.0]))[0])
