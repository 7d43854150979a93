"""Materials of simulated objects: mechanical parameters, creep, and how the scanner sees them.

A :class:`Material` is plain, frozen data (hashable, so the physics can cache
tables per material). Units are in the field names: MPa (= N/mm^2), mm, N, s,
degrees. The YAML form (``materials:`` in ``config/objects/*.yaml``) is
:class:`MaterialSpec`; :func:`material_from_spec` turns one into the other.

Kinds (docs/design.md §8, physics in :mod:`elastoprobe.sim.physics`):

- ``elastic``: a linear elastic body (rubber): Hertz + Cerruti + Mindlin.
  ``E_mpa``, ``nu``, ``friction_mu``; ``body_radius_mm`` is the body's own curvature
  at the contact (0 = flat; the ball object supplies its radius).
- ``foam``: a layer of thickness ``thickness_mm`` on the table, nonlinear
  Winkler-Pasternak: k(w) = (E/h) / (1 - w/(eps_D h))^m with ``densification_strain``
  (eps_D) and ``densification_exponent`` (m); shear layer G = k0 * ``decay_length_mm``^2.
- ``plate_on_foam``: a thin plate (cardboard) of bending modulus ``E_mpa`` and
  thickness ``thickness_mm``; ``local_E_mpa`` is the through-thickness (crush)
  modulus of the local dimple under the tip; ``plate_radius_mm`` is the clamped
  span used when the object geometry does not give one; above ``yield_force_n``
  (normal load) it keeps a permanent dent of ``dent_mm_per_n`` per newton above yield.

Creep (standard linear solid, every kind): under a held force the indentation
grows as ``1 - creep_fraction * exp(-t / creep_tau_s)`` of its equilibrium value.

Optical (the scanner engineer's inputs): ``scanner_noise_mm`` per-sample sigma,
``noise_corr_floor_mm`` the correlated floor that averaging cannot remove,
``dropout_prob`` the base fraction of missing samples (dark fabric: high),
``steep_incidence_deg`` the incidence beyond which samples are lost.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from pydantic import Field, model_validator

from elastoprobe.controller.core.yamlio import Spec

KINDS = ("elastic", "foam", "plate_on_foam")


@dataclass(frozen=True)
class Material:
    """One material; see the module docstring for the meaning of each field."""

    name: str
    kind: str
    E_mpa: float
    nu: float
    friction_mu: float
    thickness_mm: float = 0.0
    plough_ratio: float = 1.0             # gross slip of the tip is bounded by plough_ratio * contact radius
    body_radius_mm: float = 0.0           # elastic: curvature radius of the body (0 = flat)
    decay_length_mm: float = 0.0          # foam: Pasternak decay length sqrt(G/k0) at small depth
    densification_strain: float = 0.0     # foam: eps_D
    densification_exponent: float = 0.0   # foam: m
    local_E_mpa: float = 0.0              # plate: through-thickness modulus of the local dimple
    plate_radius_mm: float = 0.0          # plate: default clamped span radius b
    yield_force_n: float | None = None    # plate: normal load above which a permanent dent remains
    dent_mm_per_n: float = 0.0            # plate: residual dent depth per newton above yield
    creep_fraction: float = 0.0
    creep_tau_s: float = 1.0
    scanner_noise_mm: float = 0.02
    noise_corr_floor_mm: float = 0.004
    dropout_prob: float = 0.01
    steep_incidence_deg: float = 75.0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"material kind {self.kind!r} is not one of {KINDS}")

    @property
    def shear_modulus_mpa(self) -> float:
        """G = E / (2 (1 + nu)) (MPa)."""
        return self.E_mpa / (2.0 * (1.0 + self.nu))

    @property
    def reduced_modulus_mpa(self) -> float:
        """E* = E / (1 - nu^2) against a rigid tip (MPa)."""
        return self.E_mpa / (1.0 - self.nu * self.nu)

    def creep_factor(self, hold_s: float) -> float:
        """Fraction of the equilibrium indentation reached after holding a force for ``hold_s``."""
        if self.creep_fraction <= 0.0 or math.isinf(hold_s):
            return 1.0
        return 1.0 - self.creep_fraction * math.exp(-max(hold_s, 0.0) / self.creep_tau_s)


class OpticalSpec(Spec):
    """How the laser line scanner sees a material."""

    scanner_noise_mm: float = Field(0.02, ge=0, le=5)
    noise_corr_floor_mm: float = Field(0.004, ge=0, le=5)
    dropout_prob: float = Field(0.01, ge=0, lt=1)
    steep_incidence_deg: float = Field(75.0, gt=0, le=90)


class MaterialSpec(Spec):
    """One entry of ``materials:`` in an object file (units in the key names)."""

    kind: Literal["elastic", "foam", "plate_on_foam"]
    E_mpa: float = Field(gt=0, le=1e5)
    nu: float = Field(ge=0, lt=0.5)
    friction_mu: float = Field(gt=0, le=3)
    thickness_mm: float = Field(0.0, ge=0, le=2000)
    plough_ratio: float = Field(1.0, gt=0, le=10)
    body_radius_mm: float = Field(0.0, ge=0)
    decay_length_mm: float = Field(0.0, ge=0, le=500)
    densification_strain: float = Field(0.0, ge=0, le=1)
    densification_exponent: float = Field(0.0, ge=0, le=10)
    local_E_mpa: float = Field(0.0, ge=0, le=1e5)
    plate_radius_mm: float = Field(0.0, ge=0, le=2000)
    yield_force_n: float | None = Field(None, gt=0)
    dent_mm_per_n: float = Field(0.0, ge=0, le=1)
    creep_fraction: float = Field(0.0, ge=0, lt=1)
    creep_tau_s: float = Field(1.0, gt=0, le=3600)
    optical: OpticalSpec = OpticalSpec()

    @model_validator(mode="after")
    def _kind_needs(self) -> "MaterialSpec":
        if self.kind == "foam":
            if self.thickness_mm <= 0 or self.decay_length_mm <= 0:
                raise ValueError("a foam needs thickness_mm > 0 and decay_length_mm > 0")
            if not (0 < self.densification_strain <= 1) or self.densification_exponent <= 0:
                raise ValueError("a foam needs 0 < densification_strain <= 1 and densification_exponent > 0")
        if self.kind == "plate_on_foam":
            if self.thickness_mm <= 0 or self.local_E_mpa <= 0:
                raise ValueError("a plate_on_foam needs thickness_mm > 0 and local_E_mpa > 0")
        return self


def material_from_spec(name: str, spec: MaterialSpec) -> Material:
    """The frozen :class:`Material` of a validated YAML entry."""
    fields = spec.model_dump(exclude={"optical"})
    return Material(name=name, **fields, **spec.optical.model_dump())
