"""Whether a survey profile saw its own dent (learning/contact.py saw_its_dent)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller.learning import contact as ct
from elastoprobe.sim.generate import FAMILIES
from elastoprobe.sim.materials import MaterialSpec, material_from_spec
from elastoprobe.sim.physics import Component, ContactModel, FoamResponse, HertzResponse

DATA = Path(__file__).parent / "data" / "regions"
X = np.linspace(-15.0, 15.0, 121)
R = 5.0
SHADOW_MM = 4.0            # the tool hides the line this far from the tip on the cell
SURVEY_FORCES_N = (1.5, 4.5)


def _normal_dent(family: str, modulus_mpa: float, force_n: float) -> tuple[np.ndarray, float]:
    """The simulator's dent (mm, on X) of one family's material at one modulus, and its tip depth."""
    fam = FAMILIES[family]
    spec = fam.spec(modulus_mpa, 30.0, np.random.default_rng(0), plate_radius_mm=60.0)
    material = material_from_spec(family, MaterialSpec(**spec))
    response = FoamResponse(material, R) if material.kind == "foam" else HertzResponse(material, R, R)
    model = ContactModel([Component(1.0, response)], 90.0, material, 0)
    depth = model.depth_profile_mm(X, force_n)
    return depth, float(np.interp(0.0, X, depth))


def _seen(depth_mm: np.ndarray, noise_mm: float, rng: np.random.Generator) -> np.ndarray:
    return np.where(np.abs(X) > SHADOW_MM, depth_mm + rng.normal(0.0, noise_mm, X.shape), np.nan)


@pytest.mark.parametrize("family", ["foam", "sponge", "gel", "elastomer", "hard_rubber"])
def test_every_family_s_dent_is_seen_beyond_the_tool_s_shadow(family: str) -> None:
    """At both ends of each generated family's modulus range and both survey forces, the
    simulator's own dent, seen only beyond the tool's shadow with an averaged profile's
    noise, counts as seen."""
    rng = np.random.default_rng(1)
    for modulus in FAMILIES[family].modulus_mpa:
        for force in SURVEY_FORCES_N:
            depth, tip = _normal_dent(family, modulus, force)
            assert ct.saw_its_dent(X, _seen(depth, 0.01, rng), 0.0, tip, R, 0.01), (family, modulus, force)


def test_a_motionless_surface_under_a_deep_push_did_not_see_the_dent() -> None:
    """The table past a low rim: the tip went 2 mm into a sponge, every seen sample reads
    0 within the noise. A stiff material's push, whose dent Hertz puts below the noise
    beyond the shadow, is not refuted by the same reading."""
    rng = np.random.default_rng(2)
    soft, tip_soft = _normal_dent("sponge", 0.25, 4.5)
    assert tip_soft > 1.0
    still = _seen(np.zeros_like(X), 0.003, rng)
    assert not ct.saw_its_dent(X, still, 0.0, tip_soft, R, 0.003)
    stiff, tip_stiff = _normal_dent("hard_rubber", 60.0, 1.5)
    assert tip_stiff < 0.1
    assert ct.saw_its_dent(X, still, 0.0, tip_stiff, R, 0.003)
    # Recorded on unseen block 7633 (hard rubber, 3 N): the tip went 0.054 mm in and the
    # scanner's correlated floor put every seen sample 0.012-0.022 mm below zero, more than
    # 3 standard errors (0.0039 mm). Hertz's share there is within the noise: no refutation.
    offset = np.where(np.abs(X) > 2.8, -0.0123 - 0.003 * np.abs(np.sin(X)), np.nan)
    assert ct.saw_its_dent(X, offset, 0.0, 0.054, R, 0.0039)
    # Nothing to judge by: no tip depth, or nothing seen.
    assert ct.saw_its_dent(X, still, 0.0, float("nan"), R, 0.003)
    assert ct.saw_its_dent(X, np.full_like(X, np.nan), 0.0, tip_soft, R, 0.003)


def test_recorded_dome_survey_refutes_exactly_the_rim_steps_that_read_the_table() -> None:
    """Every 90-degree survey step of generated dome 1007 (seed 1, 802 steps, sponge and gel):
    those whose seen samples all read under 0.01 mm while the tip went over 1 mm deep (the
    line ran past the rim onto the table: 14 steps at 4.5 N on sponge, 2 mm above the
    table) are refuted, and no other step is. They had clustered with the stiffer gel
    and drawn a false gel band along the rim (worst IoU 0.499, boundary mean 19.9 mm)."""
    d = np.load(DATA / "dome_rim_1007.npz")
    depth = d["depth_mm"].astype(float)
    seen = np.array([ct.saw_its_dent(d["x_mm"], depth[k], float(d["tip_x_mm"][k]), float(d["tip_depth_mm"][k]),
                                     float(d["tip_radius_mm"]), float(d["noise_mm"])) for k in range(depth.shape[0])])
    table = (np.nanmax(np.abs(depth), axis=1) < 0.01) & (d["tip_depth_mm"] > 1.0)
    assert table.sum() == 14
    np.testing.assert_array_equal(~seen, table)
    assert set(d["material"][table]) == {"sponge"} and (d["point_mm"][table][:, 2] < 2.5).all()
