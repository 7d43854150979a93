"""Contact physics along one scanline (docs/design.md §8): what the probe feels and the dent it makes.

Local frame at a target point p: outward unit normal n, scan direction t in the
tangent plane, x (mm) the coordinate along t, depth w (mm) along -n, positive into
the object, relative to the undeformed surface. The probe at approach angle a
(deg, paper Fig. 5) pushes along d = cos(a) t - sin(a) n with force F (N), so the
normal load is P = F sin(a) and the tangential load Q = F cos(a) toward +t (a < 90).
Units: N, mm, MPa (= N/mm^2), s.

The pieces:

- :class:`HertzResponse` (elastic body): Hertz's full surface solution for P, the
  Cerruti term for Q (regularised so it is smooth through x = 0; it equals
  (1+nu)(1-2nu) Q / (2 pi E x) away from the contact), and the bounded Mindlin tip
  shift (:func:`bounded_tip_shift_mm`) that moves the whole dent along t.
- :class:`FoamResponse` (foam layer on the table): nonlinear Winkler-Pasternak,
  p = k(w) w - G lap(w), k(w) = (E/h) / (1 - w/(eps_D h))^m, solved as an obstacle
  problem under the spherical tip on a radial grid, tabulated once per material and
  tip radius; a Cerruti-like odd term attenuated over the decay length.
- :class:`PlateResponse` (cardboard): clamped circular plate bowl
  w = P/(16 pi D) [b^2 - r^2 + 2 r^2 ln(r/b)] plus a local Hertz dimple with the
  through-thickness modulus; the box's sink into the foam is a :class:`SupportSink`.
- :class:`ContactModel`: one target point and one angle; a weighted sum of the
  above (weights blend regions near a boundary), a rigid-body sink of the whole
  body, creep, and precomputed monotone force/push tables (np.interp: O(log n),
  no solving in the force loop).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Callable, Protocol, Sequence

import numpy as np
from scipy.linalg import solve_banded

from .materials import Material

# Validity thresholds of the models (the simulator's self-check, docs/design.md §8).
HERTZ_MAX_A_OVER_R = 0.5          # Hertz assumes a small contact: a/R beyond ~0.5 errs by > ~10 %
FOAM_MAX_DEPTH_OVER_DENSIFICATION = 0.6   # beyond, the densification law is only a curve fit
PLATE_MAX_DEFLECTION_OVER_THICKNESS = 0.5  # small-deflection plate theory (membrane effects beyond)
TABLE_MAX_FORCE_N = 2000.0        # force/push tables span 0 .. this; linear extrapolation beyond


# --------------------------------------------------------------------------- Hertz

def hertz_contact_radius_mm(normal_force_n: np.ndarray | float, radius_mm: float,
                            reduced_modulus_mpa: float) -> np.ndarray:
    """a = (3 P R / (4 E*))^(1/3) (mm) for a rigid sphere of radius R on an elastic body."""
    p = np.maximum(np.asarray(normal_force_n, dtype=float), 0.0)
    return np.cbrt(3.0 * p * radius_mm / (4.0 * reduced_modulus_mpa))


def hertz_surface_depth_mm(r_mm: np.ndarray, normal_force_n: float, radius_mm: float,
                           E_mpa: float, nu: float) -> np.ndarray:
    """Hertz's surface displacement w(r) (mm, into the body) inside and outside the contact.

    Inside (r <= a): w = delta - r^2 / (2R), delta = a^2 / R.
    Outside: w = (1 - nu^2) p0 / (2 a E) [(2a^2 - r^2) asin(a/r) + a r sqrt(1 - a^2/r^2)],
    p0 = 3P / (2 pi a^2). Both branches meet at r = a.
    """
    r = np.abs(np.asarray(r_mm, dtype=float))
    if normal_force_n <= 0.0:
        return np.zeros_like(r)
    e_star = E_mpa / (1.0 - nu * nu)
    a = float(hertz_contact_radius_mm(normal_force_n, radius_mm, e_star))
    delta = a * a / radius_mm
    p0 = 3.0 * normal_force_n / (2.0 * math.pi * a * a)
    out = np.empty_like(r)
    inside = r <= a
    out[inside] = delta - r[inside] ** 2 / (2.0 * radius_mm)
    ro = r[~inside]
    ratio = a / ro
    out[~inside] = (1.0 - nu * nu) * p0 / (2.0 * a * E_mpa) * (
        (2.0 * a * a - ro * ro) * np.arcsin(ratio) + a * ro * np.sqrt(1.0 - ratio * ratio))
    return out


def cerruti_depth_mm(x_mm: np.ndarray, tangential_force_n: float, E_mpa: float, nu: float,
                     core_mm: float) -> np.ndarray:
    """Normal surface displacement (mm, into the body) from a tangential load Q along +x.

    The surface sinks ahead of the load and rises behind it:
    (1+nu)(1-2nu) Q x / (2 pi E (x^2 + c^2)). Far from the contact (|x| >> c) this is
    Cerruti's point-load solution (1+nu)(1-2nu) Q sign(x) / (2 pi E |x|); the core c
    (the contact radius) regularises it smoothly through x = 0 (the form
    Q sign(x) / sqrt(x^2 + c^2) would have a step there that a distributed traction does not make).
    """
    x = np.asarray(x_mm, dtype=float)
    c2 = max(core_mm, 1e-6) ** 2
    return (1.0 + nu) * (1.0 - 2.0 * nu) * tangential_force_n * x / (2.0 * math.pi * E_mpa * (x * x + c2))


def bounded_tip_shift_mm(tangential_force_n: np.ndarray, normal_force_n: np.ndarray, contact_radius_mm: np.ndarray,
                         shear_modulus_mpa: float, nu: float, friction_mu: float,
                         plough_ratio: float) -> np.ndarray:
    """Tangential displacement of the tip along +t (mm), signed like Q.

    Sticking (Cattaneo-Mindlin, |Q| <= mu P): s = s* [1 - (1 - |Q|/(mu P))^(2/3)],
    s* = 3 mu P (2 - nu) / (16 G a). Beyond, gross slip resisted by ploughing:
    the extra load (|Q| - mu P) acts on the initial tangential stiffness 8 G a / (2 - nu).
    The tip sits in its own dent, so the total is bounded by ``plough_ratio * a``:
    s = s_max tanh(s_unbounded / s_max). Monotone in |Q| and in the force at a fixed angle.
    """
    q = np.asarray(tangential_force_n, dtype=float)
    p = np.asarray(normal_force_n, dtype=float)
    a = np.asarray(contact_radius_mm, dtype=float)
    q, p, a = np.broadcast_arrays(q, p, a)
    out = np.zeros(q.shape)
    ok = (p > 0) & (a > 0) & (np.abs(q) > 0)
    if not np.any(ok):
        return out
    qa, pa, aa = np.abs(q[ok]), p[ok], a[ok]
    mu_p = friction_mu * pa
    s_star = 3.0 * mu_p * (2.0 - nu) / (16.0 * shear_modulus_mpa * aa)
    ratio = np.minimum(qa / mu_p, 1.0)
    stick = s_star * (1.0 - (1.0 - ratio) ** (2.0 / 3.0))
    k_t = 8.0 * shear_modulus_mpa * aa / (2.0 - nu)
    unbounded = stick + np.maximum(qa - mu_p, 0.0) / k_t
    s_max = plough_ratio * aa
    out[ok] = np.sign(q[ok]) * s_max * np.tanh(unbounded / s_max)
    return out


# --------------------------------------------------------------------------- local responses

class LocalResponse(Protocol):
    """How one material answers a normal load P and a tangential load Q at the tip."""

    material: Material

    def approach_mm(self, normal_force_n: np.ndarray) -> np.ndarray:
        """Normal approach of the tip (mm) under P (vectorised, monotone)."""
        ...

    def contact_radius_mm(self, normal_force_n: np.ndarray) -> np.ndarray: ...

    def symmetric_depth_mm(self, r_mm: np.ndarray, normal_force_n: float) -> np.ndarray:
        """Axisymmetric part of the dent at distance r from the tip (mm)."""
        ...

    def odd_depth_mm(self, x_mm: np.ndarray, normal_force_n: float, tangential_force_n: float) -> np.ndarray:
        """Part of the dent that is odd in x, from the tangential load."""
        ...

    def tip_shift_mm(self, tangential_force_n: np.ndarray, normal_force_n: np.ndarray) -> np.ndarray: ...

    def validity_problems(self, normal_force_n: float) -> list[str]: ...


@dataclass(frozen=True)
class HertzResponse:
    """Elastic body under a rigid spherical tip; ``radius_mm`` is the effective radius R*
    (1/R* = 1/R_tip + 1/R_body), ``tip_radius_mm`` the tip's own (for the a/R check)."""

    material: Material
    radius_mm: float
    tip_radius_mm: float

    def contact_radius_mm(self, normal_force_n: np.ndarray) -> np.ndarray:
        return hertz_contact_radius_mm(normal_force_n, self.radius_mm, self.material.reduced_modulus_mpa)

    def approach_mm(self, normal_force_n: np.ndarray) -> np.ndarray:
        a = self.contact_radius_mm(normal_force_n)
        return a * a / self.radius_mm

    def symmetric_depth_mm(self, r_mm: np.ndarray, normal_force_n: float) -> np.ndarray:
        m = self.material
        return hertz_surface_depth_mm(r_mm, normal_force_n, self.radius_mm, m.E_mpa, m.nu)

    def odd_depth_mm(self, x_mm: np.ndarray, normal_force_n: float, tangential_force_n: float) -> np.ndarray:
        a = float(self.contact_radius_mm(normal_force_n))
        m = self.material
        return cerruti_depth_mm(x_mm, tangential_force_n, m.E_mpa, m.nu, a)

    def tip_shift_mm(self, tangential_force_n: np.ndarray, normal_force_n: np.ndarray) -> np.ndarray:
        m = self.material
        return bounded_tip_shift_mm(tangential_force_n, normal_force_n, self.contact_radius_mm(normal_force_n),
                                    m.shear_modulus_mpa, m.nu, m.friction_mu, m.plough_ratio)

    def validity_problems(self, normal_force_n: float) -> list[str]:
        a = float(self.contact_radius_mm(normal_force_n))
        ratio = a / self.radius_mm
        if ratio > HERTZ_MAX_A_OVER_R:
            return [f"{self.material.name}: Hertz contact radius a = {a:.2f} mm is {ratio:.2f} of the "
                    f"effective radius {self.radius_mm:.2f} mm at P = {normal_force_n:.1f} N "
                    f"(valid up to a/R = {HERTZ_MAX_A_OVER_R})"]
        return []


# --------------------------------------------------------------------------- foam

@dataclass(frozen=True)
class FoamTable:
    """Equilibria of a spherical tip pressed to depth w0 into a Winkler-Pasternak layer.

    ``tip_depth_mm`` (K,) increasing from 0; ``force_n`` (K,) the load at each depth;
    ``contact_radius_mm`` (K,); ``r_mm`` (N,) radial cell centres; ``depth_mm`` (K, N).
    """

    tip_depth_mm: np.ndarray
    force_n: np.ndarray
    contact_radius_mm: np.ndarray
    r_mm: np.ndarray
    depth_mm: np.ndarray


def _foam_stiffness(w_mm: np.ndarray, k0: float, wd_mm: float, m: float) -> tuple[np.ndarray, np.ndarray]:
    """k(w) w and its derivative d(k w)/dw for k = k0 / (1 - w/wd)^m (N/mm^3 * mm)."""
    s = np.clip(1.0 - w_mm / wd_mm, 1e-9, None)
    k = k0 / s ** m
    kw = k * w_mm
    dkw = k + k0 * m * w_mm / (wd_mm * s ** (m + 1.0))
    return kw, dkw


def solve_foam_obstacle(tip_depth_mm: float, tip_radius_mm: float, k0_n_mm3: float, shear_n_mm: float,
                        densification_depth_mm: float, exponent: float, r_mm: np.ndarray,
                        w_init: np.ndarray | None = None, max_iter: int = 80) -> tuple[np.ndarray, float, float]:
    """Equilibrium of the layer under a sphere whose lowest point is at depth ``tip_depth_mm``.

    Finite volumes on uniform radial cells (centres ``r_mm``, width dr), outer edge held at
    w = 0. Minimises sum A_i Phi(w_i) + 1/2 sum T_f (w_{i+1} - w_i)^2 with Phi' = k(w) w
    subject to w >= psi (the foam cannot rise through the tip: psi = w0 - (R - sqrt(R^2 - r^2))
    for r < R), by an active-set method with Newton steps on tridiagonal systems.
    Returns (w (N,), load P in N = sum of contact reactions, contact radius in mm).
    """
    n = r_mm.size
    dr = float(r_mm[1] - r_mm[0])
    faces = (np.arange(1, n + 1)) * dr                    # outer face of each cell
    area = 2.0 * math.pi * r_mm * dr
    trans = 2.0 * math.pi * faces * shear_n_mm / dr        # transmissibility of each outer face
    gap = np.full(n, np.inf)
    under = r_mm < tip_radius_mm
    gap[under] = tip_radius_mm - np.sqrt(tip_radius_mm ** 2 - r_mm[under] ** 2)
    psi = tip_depth_mm - gap                              # -inf beyond the tip
    w_cap = 0.995 * densification_depth_mm
    w = np.maximum(psi, 0.0) if w_init is None else np.maximum(w_init, psi)
    w = np.minimum(w, w_cap)
    active = psi > 0.0

    def gradient(wv: np.ndarray) -> np.ndarray:
        kw, _ = _foam_stiffness(wv, k0_n_mm3, densification_depth_mm, exponent)
        lap = trans * (wv - np.append(wv[1:], 0.0))               # flux out through the outer face
        lap[1:] += trans[:-1] * (wv[1:] - wv[:-1])                # flux out through the inner face
        return area * kw + lap

    for _ in range(max_iter):
        w[active] = psi[active]
        free = ~active
        for _newton in range(40):
            g = gradient(w)
            _, dkw = _foam_stiffness(w, k0_n_mm3, densification_depth_mm, exponent)
            diag = area * dkw + trans + np.concatenate([[0.0], trans[:-1]])
            off = -trans[:-1]
            # Fixed (active) cells: identity rows, zero coupling.
            diag = np.where(free, diag, 1.0)
            rhs = np.where(free, -g, 0.0)
            upper = np.where(free[:-1] & free[1:], off, 0.0)
            ab = np.zeros((3, n))
            ab[0, 1:] = upper
            ab[1] = diag
            ab[2, :-1] = upper
            step = solve_banded((1, 1), ab, rhs)
            # Damp so the iterate stays below the densification singularity.
            rising = step > 0
            scale = min(1.0, float(np.min(0.9 * (w_cap - w[rising]) / step[rising]))) if np.any(rising) else 1.0
            w = w + scale * step
            if float(np.max(np.abs(scale * step))) < 1e-10 * max(tip_depth_mm, 1.0):
                break
        g = gradient(w)
        release = active & (g < 0.0)                # the tip would have to pull: let go
        grab = ~active & (w < psi - 1e-12)          # the foam would pass through the tip
        if not np.any(release) and not np.any(grab):
            break
        active = (active & ~release) | grab
    g = gradient(w)
    load_n = float(np.sum(g[active])) if np.any(active) else 0.0
    contact_mm = float(r_mm[active].max() + dr / 2.0) if np.any(active) else 0.0
    return w, load_n, contact_mm


@lru_cache(maxsize=32)
def foam_table(material: Material, tip_radius_mm: float, samples: int = 64) -> FoamTable:
    """Tabulate :func:`solve_foam_obstacle` over tip depths up to 0.9 eps_D h (cached)."""
    h = material.thickness_mm
    k0 = material.E_mpa / h
    lam = material.decay_length_mm
    shear = k0 * lam * lam
    wd = material.densification_strain * h
    dr = min(0.25, tip_radius_mm / 12.0)
    r_max = max(10.0 * lam, 6.0 * tip_radius_mm, 80.0)
    r = (np.arange(int(math.ceil(r_max / dr))) + 0.5) * dr
    depths = 0.9 * wd * np.linspace(0.0, 1.0, samples) ** 1.5
    profiles = np.zeros((samples, r.size))
    loads = np.zeros(samples)
    radii = np.zeros(samples)
    w_prev = None
    for i, w0 in enumerate(depths[1:], start=1):
        w_prev, loads[i], radii[i] = solve_foam_obstacle(float(w0), tip_radius_mm, k0, shear, wd,
                                                         material.densification_exponent, r, w_prev)
        profiles[i] = w_prev
    loads = np.maximum.accumulate(loads)
    return FoamTable(depths, loads, radii, r, profiles)


@dataclass(frozen=True)
class FoamResponse:
    """Foam layer (see :func:`solve_foam_obstacle`); Cerruti-like odd term decaying over the
    Pasternak decay length; Mindlin tip shift with the foam's shear modulus, bounded by ploughing."""

    material: Material
    tip_radius_mm: float
    table: FoamTable = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "table", foam_table(self.material, self.tip_radius_mm))

    def approach_mm(self, normal_force_n: np.ndarray) -> np.ndarray:
        tb = self.table
        p = np.maximum(np.asarray(normal_force_n, dtype=float), 0.0)
        w = np.interp(p, tb.force_n, tb.tip_depth_mm)
        # Beyond the table (absurd forces): continue with the last compliance, still monotone.
        slope = (tb.tip_depth_mm[-1] - tb.tip_depth_mm[-2]) / max(tb.force_n[-1] - tb.force_n[-2], 1e-12)
        return np.where(p > tb.force_n[-1], tb.tip_depth_mm[-1] + slope * (p - tb.force_n[-1]), w)

    def contact_radius_mm(self, normal_force_n: np.ndarray) -> np.ndarray:
        tb = self.table
        w0 = self.approach_mm(normal_force_n)
        return np.interp(w0, tb.tip_depth_mm, tb.contact_radius_mm)

    def symmetric_depth_mm(self, r_mm: np.ndarray, normal_force_n: float) -> np.ndarray:
        tb = self.table
        w0 = float(self.approach_mm(normal_force_n))
        j = int(np.clip(np.searchsorted(tb.tip_depth_mm, w0) - 1, 0, tb.tip_depth_mm.size - 2))
        span = tb.tip_depth_mm[j + 1] - tb.tip_depth_mm[j]
        theta = (w0 - tb.tip_depth_mm[j]) / span
        row = (1.0 - theta) * tb.depth_mm[j] + theta * tb.depth_mm[j + 1]
        r = np.abs(np.asarray(r_mm, dtype=float))
        # The first cell centre is at dr/2; the tip's lowest point is w0 at r = 0.
        rr = np.concatenate([[0.0], tb.r_mm])
        ww = np.concatenate([[w0], row])
        return np.interp(r, rr, ww, right=0.0)

    def odd_depth_mm(self, x_mm: np.ndarray, normal_force_n: float, tangential_force_n: float) -> np.ndarray:
        m = self.material
        c = max(float(self.contact_radius_mm(normal_force_n)), 0.5 * self.tip_radius_mm)
        x = np.asarray(x_mm, dtype=float)
        return cerruti_depth_mm(x, tangential_force_n, m.E_mpa, m.nu, c) * np.exp(-np.abs(x) / m.decay_length_mm)

    def tip_shift_mm(self, tangential_force_n: np.ndarray, normal_force_n: np.ndarray) -> np.ndarray:
        m = self.material
        c = np.maximum(self.contact_radius_mm(normal_force_n), 0.2 * self.tip_radius_mm)
        return bounded_tip_shift_mm(tangential_force_n, normal_force_n, c, m.shear_modulus_mpa, m.nu,
                                    m.friction_mu, m.plough_ratio)

    def validity_problems(self, normal_force_n: float) -> list[str]:
        m = self.material
        w0 = float(self.approach_mm(normal_force_n))
        wd = m.densification_strain * m.thickness_mm
        if w0 > FOAM_MAX_DEPTH_OVER_DENSIFICATION * wd:
            return [f"{m.name}: foam depth {w0:.1f} mm is {w0 / wd:.2f} of the densification depth "
                    f"eps_D h = {wd:.1f} mm at P = {normal_force_n:.1f} N "
                    f"(valid up to {FOAM_MAX_DEPTH_OVER_DENSIFICATION})"]
        return []


# --------------------------------------------------------------------------- plate

def clamped_plate_depth_mm(r_mm: np.ndarray, normal_force_n: float, rigidity_n_mm: float,
                           span_radius_mm: float) -> np.ndarray:
    """Clamped circular plate under a central point load: w = P/(16 pi D) [b^2 - r^2 + 2 r^2 ln(r/b)]
    for r < b, 0 beyond (mm). D in N mm, b in mm."""
    r = np.abs(np.asarray(r_mm, dtype=float))
    b = span_radius_mm
    rr = np.minimum(r, b)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_term = np.where(rr > 0, 2.0 * rr * rr * np.log(rr / b), 0.0)
    return normal_force_n / (16.0 * math.pi * rigidity_n_mm) * (b * b - rr * rr + log_term)


@dataclass(frozen=True)
class PlateResponse:
    """Cardboard: a clamped plate of span radius ``span_radius_mm`` (the distance to the stiff
    box edges) plus a local Hertz dimple of the through-thickness modulus under the tip."""

    material: Material
    tip_radius_mm: float
    span_radius_mm: float

    @property
    def rigidity_n_mm(self) -> float:
        m = self.material
        return m.E_mpa * m.thickness_mm ** 3 / (12.0 * (1.0 - m.nu ** 2))

    def _local(self) -> HertzResponse:
        m = self.material
        local = Material(name=m.name, kind="elastic", E_mpa=m.local_E_mpa, nu=m.nu, friction_mu=m.friction_mu,
                         plough_ratio=m.plough_ratio)
        return HertzResponse(local, self.tip_radius_mm, self.tip_radius_mm)

    def bowl_depth_mm(self, normal_force_n: np.ndarray) -> np.ndarray:
        p = np.maximum(np.asarray(normal_force_n, dtype=float), 0.0)
        return p * self.span_radius_mm ** 2 / (16.0 * math.pi * self.rigidity_n_mm)

    def approach_mm(self, normal_force_n: np.ndarray) -> np.ndarray:
        return self.bowl_depth_mm(normal_force_n) + self._local().approach_mm(normal_force_n)

    def contact_radius_mm(self, normal_force_n: np.ndarray) -> np.ndarray:
        return self._local().contact_radius_mm(normal_force_n)

    def symmetric_depth_mm(self, r_mm: np.ndarray, normal_force_n: float) -> np.ndarray:
        bowl = clamped_plate_depth_mm(r_mm, normal_force_n, self.rigidity_n_mm, self.span_radius_mm)
        return bowl + self._local().symmetric_depth_mm(r_mm, normal_force_n)

    def odd_depth_mm(self, x_mm: np.ndarray, normal_force_n: float, tangential_force_n: float) -> np.ndarray:
        return self._local().odd_depth_mm(x_mm, normal_force_n, tangential_force_n)

    def tip_shift_mm(self, tangential_force_n: np.ndarray, normal_force_n: np.ndarray) -> np.ndarray:
        return self._local().tip_shift_mm(tangential_force_n, normal_force_n)

    def validity_problems(self, normal_force_n: float) -> list[str]:
        m = self.material
        problems = self._local().validity_problems(normal_force_n)
        w = float(self.bowl_depth_mm(normal_force_n))
        if w > PLATE_MAX_DEFLECTION_OVER_THICKNESS * m.thickness_mm:
            problems.append(f"{m.name}: plate deflection {w:.2f} mm is {w / m.thickness_mm:.2f} of its "
                            f"thickness {m.thickness_mm:.1f} mm at P = {normal_force_n:.1f} N (small-deflection "
                            f"theory valid up to {PLATE_MAX_DEFLECTION_OVER_THICKNESS})")
        return problems


# --------------------------------------------------------------------------- support and model

@dataclass(frozen=True)
class SupportSink:
    """Rigid-body translation of the whole body on what carries it (ball on the table, box on
    the pillow), along a fixed direction e (object frame).

    ``sink_mm(load_n)``: translation (mm) under the load component along e (vectorised, monotone).
    ``load_factor``: that load per newton of |F| (max(0, d . e)); ``push_factor`` (e . d) and
    ``depth_factor`` (e . -n): what 1 mm of sink adds to the push and to the depth along -n.
    """

    sink_mm: Callable[[np.ndarray], np.ndarray]
    load_factor: float
    push_factor: float
    depth_factor: float

    def push_mm(self, force_n: np.ndarray) -> np.ndarray:
        return self.push_factor * self.sink_mm(self.load_factor * np.asarray(force_n, dtype=float))

    def depth_mm(self, force_n: float) -> float:
        return float(self.depth_factor * self.sink_mm(np.asarray(self.load_factor * force_n)))


@dataclass(frozen=True)
class Component:
    """One material's share of a contact: ``weight`` in (0, 1], the sum over components is 1."""

    weight: float
    response: LocalResponse
    support: SupportSink | None = None


class ContactModel:
    """Local contact at one target point for one approach angle (pure, cheap, vectorised).

    ``material``/``region``: the region under the tip (largest weight). Near a region
    boundary the model is the weighted sum of the components' pushes and profiles
    (weights from :mod:`elastoprobe.sim.objects`). ``residual_mm(x)`` is a permanent
    dent already in the surface along this scanline (0 when there is none): it is part
    of every depth profile, at every force including 0.

    Creep: under a force held for ``hold_s`` the push and the dent reach the fraction
    c(hold) = 1 - beta exp(-hold / tau) of their equilibrium values; at a fixed push the
    force relaxes accordingly (force_n_at_push decreases with hold_s).
    """

    def __init__(self, components: Sequence[Component], angle_deg: float, material: Material, region: int,
                 residual_mm: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
        if not 0.0 < angle_deg < 180.0:
            raise ValueError(f"approach angle {angle_deg} deg must lie strictly between 0 and 180")
        total = sum(c.weight for c in components)
        if not components or abs(total - 1.0) > 1e-9:
            raise ValueError("component weights must sum to 1")
        self.components = tuple(components)
        self.material = material
        self.region = int(region)
        self.angle_deg = float(angle_deg)
        a = math.radians(angle_deg)
        cos_a = math.cos(a)
        self._cos = 0.0 if abs(cos_a) < 1e-12 else cos_a
        self._sin = math.sin(a)
        self._residual = residual_mm
        self._loads_key: tuple[float, float] | None = None
        self._loads: tuple[float, float, float, list[float]] | None = None
        self._creep_fraction = sum(c.weight * c.response.material.creep_fraction for c in components)
        self._creep_tau_s = sum(c.weight * c.response.material.creep_tau_s for c in components)
        force = np.concatenate([[0.0], np.geomspace(1e-4, TABLE_MAX_FORCE_N, 400)])
        push = self._equilibrium_push_mm(force)
        # Strictly increasing for np.interp in both directions (guards against round-off).
        push = np.maximum.accumulate(push) + np.arange(push.size) * 1e-12
        self._force_grid = force
        self._push_grid = push
        self._tail_slope = (push[-1] - push[-2]) / (force[-1] - force[-2])

    # -- loads
    def loads_n(self, force_n: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """(P, Q): normal load F sin(a) and tangential load F cos(a) along +t (N)."""
        f = np.asarray(force_n, dtype=float)
        return f * self._sin, f * self._cos

    def _equilibrium_push_mm(self, force_n: np.ndarray) -> np.ndarray:
        p, q = self.loads_n(force_n)
        push = np.zeros_like(force_n)
        for c in self.components:
            local = c.response.approach_mm(p) * self._sin + c.response.tip_shift_mm(q, p) * self._cos
            if c.support is not None:
                local = local + c.support.push_mm(force_n)
            push = push + c.weight * local
        return push

    def _creep(self, hold_s: float) -> float:
        if self._creep_fraction <= 0.0 or math.isinf(hold_s):
            return 1.0
        return 1.0 - self._creep_fraction * math.exp(-max(hold_s, 0.0) / self._creep_tau_s)

    def _force_at_equilibrium_push(self, push_mm: float) -> float:
        if push_mm <= 0.0:
            return 0.0
        if push_mm > self._push_grid[-1]:
            return float(self._force_grid[-1] + (push_mm - self._push_grid[-1]) / self._tail_slope)
        return float(np.interp(push_mm, self._push_grid, self._force_grid))

    def _equilibrium_push_at_force(self, force_n: float) -> float:
        if force_n <= 0.0:
            return 0.0
        if force_n > self._force_grid[-1]:
            return float(self._push_grid[-1] + (force_n - self._force_grid[-1]) * self._tail_slope)
        return float(np.interp(force_n, self._force_grid, self._push_grid))

    # -- public API
    def force_n_at_push(self, push_mm: float, hold_s: float = 0.0) -> float:
        """|F| (N) after the tip moved ``push_mm`` along d since first touch and stayed there ``hold_s``.
        0 for push <= 0; strictly increasing in push; decreasing in hold_s (relaxation)."""
        return self._force_at_equilibrium_push(push_mm / self._creep(hold_s))

    def push_mm_at_force(self, force_n: float, hold_s: float = 0.0) -> float:
        """Push (mm along d) at which the surface returns ``force_n`` after it was held ``hold_s``."""
        return self._equilibrium_push_at_force(force_n) * self._creep(hold_s)

    def effective_force_n(self, force_n: float, hold_s: float = math.inf) -> float:
        """The equilibrium force whose dent matches the (partly crept) dent under ``force_n``."""
        if math.isinf(hold_s):
            return float(force_n)
        return self._force_at_equilibrium_push(self._equilibrium_push_at_force(force_n) * self._creep(hold_s))

    def tip_shift_mm(self, force_n: float) -> float:
        """Tangential displacement of the tip along +t (mm): Mindlin stick, then bounded slip.
        Positive for angles under 90 deg, negative above, 0 at 90."""
        p, q = self.loads_n(force_n)
        return float(sum(c.weight * float(c.response.tip_shift_mm(q, p)) for c in self.components))

    def slip_margin(self, force_n: float) -> float:
        """Q / (mu P): above 1 the tip slides (gross slip, bounded by ploughing)."""
        p, q = self.loads_n(force_n)
        if float(p) <= 0.0:
            return 0.0
        return float(sum(c.weight * abs(float(q)) / (c.response.material.friction_mu * float(p))
                         for c in self.components))

    def depth_profile_mm(self, x_mm: np.ndarray, force_n: float, hold_s: float = math.inf) -> np.ndarray:
        """Depth (mm along -n, > 0 into the object, vs the undeformed surface) at p + x t.

        The whole dent, shifted along t by the tip shift; includes the body's sink and any
        permanent dent. ``hold_s`` < inf gives the partly crept dent under a held force.
        """
        x = np.asarray(x_mm, dtype=float)
        out = np.zeros_like(x)
        for c, part in zip(self.components, self.component_profiles_mm(x, force_n, hold_s)):
            out = out + c.weight * part
        if self._residual is not None:
            out = out + self._residual(x)
        return out

    def component_profiles_mm(self, x_mm: np.ndarray, force_n: float, hold_s: float = math.inf) -> list[np.ndarray]:
        """Each component's own (unweighted) dent, sharing the tip shift; without permanent dents.
        The profile is the weighted sum of these (plus the residual of permanent dents)."""
        x = np.asarray(x_mm, dtype=float)
        loads = self._dent_loads(force_n, hold_s)
        if loads is None:
            return [np.zeros_like(x) for _ in self.components]
        p, q, shift, sinks = loads
        xs = x - shift
        parts = []
        for c, sink in zip(self.components, sinks):
            part = c.response.symmetric_depth_mm(xs, p) + c.response.odd_depth_mm(xs, p, q)
            if c.support is not None:
                part = part + sink
            parts.append(part)
        return parts

    def _dent_loads(self, force_n: float, hold_s: float) -> tuple[float, float, float, list[float]] | None:
        """(P, Q, tip shift along t, each component's support sink) of the dent under ``force_n``
        held ``hold_s`` (None without a load), kept for the last arguments: a scanner profile
        asks for one dent at a few hundred points several times over (ray by ray, root find
        step by step), and these scalars are most of a call's cost."""
        key = (float(force_n), float(hold_s))
        if key != self._loads_key:
            f = self.effective_force_n(max(key[0], 0.0), key[1])
            loads = None
            if f > 0.0:
                p, q = self.loads_n(f)
                loads = (float(p), float(q), self.tip_shift_mm(f),
                         [c.support.depth_mm(f) if c.support is not None else 0.0 for c in self.components])
            self._loads_key, self._loads = key, loads
        return self._loads

    def validity_problems(self, force_n: float) -> list[str]:
        """What is out of its model's validity at |F| = ``force_n`` at this angle."""
        p = float(force_n) * self._sin
        problems: list[str] = []
        for c in self.components:
            problems.extend(c.response.validity_problems(p))
        return problems
