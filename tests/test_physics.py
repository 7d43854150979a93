"""Contact physics: Hertz against an independent integral, foam solver, asymmetry, mirror, creep."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy import integrate, special

from elastoprobe.sim.materials import Material
from elastoprobe.sim.physics import (Component, ContactModel, FoamResponse, HertzResponse, bounded_tip_shift_mm,
                                     hertz_contact_radius_mm, hertz_surface_depth_mm, solve_foam_obstacle)

OBJECTS = Path(__file__).resolve().parents[1] / "config" / "objects"
NINE = (10.0, 25.0, 45.0, 75.0, 90.0, 105.0, 135.0, 155.0, 170.0)
X_MM = np.linspace(-40.0, 40.0, 257)
UP, ALONG = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
RUBBER = Material(name="rubber", kind="elastic", E_mpa=10.0, nu=0.49, friction_mu=0.8)


def homogeneous_models(ball, composite, user_object):
    """(label, model factory(angle)) on homogeneous spots of every material."""
    return [
        ("rubber", lambda a: ball.contact_model(np.array([0.0, 0.0, 130.0]), UP, ALONG, a, 5.0)),
        ("cardboard", lambda a: composite.contact_model(np.array([0.0, 0.0, 140.0]), UP, ALONG, a, 5.0)),
        ("foam", lambda a: composite.contact_model(np.array([150.0, 0.0, 80.0]), UP, ALONG, a, 5.0)),
        ("elastomer", lambda a: user_object.contact_model(np.array([-25.0, 0.0, 40.0]), UP, ALONG, a, 5.0)),
        ("sponge", lambda a: user_object.contact_model(np.array([25.0, 0.0, 40.0]), UP, ALONG, a, 5.0)),
    ]


# ----------------------------------------------------------------------------- Hertz

def test_hertz_force_grows_as_depth_to_the_power_1_5_over_a_decade():
    model = ContactModel([Component(1.0, HertzResponse(RUBBER, 5.0, 5.0))], 90.0, RUBBER, 0)
    forces = np.geomspace(3.0, 30.0, 12)
    pushes = np.array([model.push_mm_at_force(f, math.inf) for f in forces])
    exponent = np.polyfit(np.log(pushes), np.log(forces), 1)[0]
    assert exponent == pytest.approx(1.5, abs=0.005)
    # And back: the force at each push is the force we started from.
    back = np.array([model.force_n_at_push(p, math.inf) for p in pushes])
    np.testing.assert_allclose(back, forces, rtol=1e-3)


def boussinesq_depth_mm(r_mm: float, force_n: float, radius_mm: float, e_mpa: float, nu: float) -> float:
    """Independent reference: integrate p(s) = p0 sqrt(1 - s^2/a^2) against the Boussinesq kernel
    (1 - nu^2) / (pi E |x - s|) numerically, in polar coordinates around the field point."""
    a = float(hertz_contact_radius_mm(force_n, radius_mm, e_mpa / (1 - nu * nu)))
    p0 = 3.0 * force_n / (2.0 * math.pi * a * a)
    nodes, weights = np.polynomial.legendre.leggauss(200)

    def chord(theta: float) -> float:
        # Points r e_x + rho (cos t, sin t) inside the circle: rho in [lo, hi].
        disc = a * a - (r_mm * math.sin(theta)) ** 2
        if disc <= 0:
            return 0.0
        root = math.sqrt(disc)
        lo, hi = max(-r_mm * math.cos(theta) - root, 0.0), -r_mm * math.cos(theta) + root
        if hi <= lo:
            return 0.0
        rho = 0.5 * (hi - lo) * nodes + 0.5 * (hi + lo)
        s2 = rho ** 2 + 2 * rho * r_mm * math.cos(theta) + r_mm ** 2
        pressure = p0 * np.sqrt(np.clip(1.0 - s2 / (a * a), 0.0, None))
        return 0.5 * (hi - lo) * float(np.dot(weights, pressure))   # dA / |x - s| = d rho d theta

    if r_mm < a:
        total, _ = integrate.quad(chord, 0.0, 2 * math.pi, limit=200)
    else:
        half = math.asin(a / r_mm)     # rays that reach the contact point back toward its centre
        total, _ = integrate.quad(chord, math.pi - half, math.pi + half, limit=200)
    return (1 - nu * nu) / (math.pi * e_mpa) * total


@pytest.mark.parametrize("r_over_a", [0.0, 0.4, 0.8, 0.99, 1.01, 1.5, 3.0, 8.0])
def test_hertz_depth_equals_the_integral_of_its_pressure_inside_and_outside(r_over_a):
    force_n, radius_mm, e_mpa, nu = 20.0, 5.0, 10.0, 0.49
    a = float(hertz_contact_radius_mm(force_n, radius_mm, e_mpa / (1 - nu * nu)))
    r = r_over_a * a
    model = float(hertz_surface_depth_mm(np.array([r]), force_n, radius_mm, e_mpa, nu)[0])
    reference = boussinesq_depth_mm(r, force_n, radius_mm, e_mpa, nu)
    assert model == pytest.approx(reference, rel=0.01)


# ----------------------------------------------------------------------------- asymmetry

@pytest.mark.parametrize("angle", [10.0, 25.0, 45.0, 75.0])
def test_mirror_angle_gives_the_mirrored_profile(ball, composite, user_object, angle):
    for name, factory in homogeneous_models(ball, composite, user_object):
        for force in (5.0, 20.0, 40.0):
            left = factory(angle).depth_profile_mm(X_MM, force)
            right = factory(180.0 - angle).depth_profile_mm(-X_MM, force)
            assert np.max(np.abs(left - right)) <= 0.01 * np.max(left), (name, force)


def centroid_mm(depth: np.ndarray) -> float:
    return float(np.sum(X_MM * depth) / np.sum(depth))


def test_rubber_dent_leans_toward_plus_t_and_further_with_the_tangential_force(ball):
    top = np.array([0.0, 0.0, 130.0])
    for angle in (10.0, 25.0, 45.0, 75.0):
        model = ball.contact_model(top, UP, ALONG, angle, 5.0)
        centroids = [centroid_mm(model.depth_profile_mm(X_MM, f)) for f in (5.0, 10.0, 20.0, 40.0)]
        assert centroids[0] > 0
        assert np.all(np.diff(centroids) > 0), (angle, centroids)
    # Same force, more tangential load (smaller angle): the centroid moves further right.
    at_20 = [centroid_mm(ball.contact_model(top, UP, ALONG, a, 5.0).depth_profile_mm(X_MM, 20.0))
             for a in (75.0, 45.0, 25.0, 10.0)]
    assert np.all(np.diff(at_20) > 0), at_20
    normal = ball.contact_model(top, UP, ALONG, 90.0, 5.0)
    assert abs(centroid_mm(normal.depth_profile_mm(X_MM, 20.0))) < 1e-9


def test_rubber_dent_bottom_follows_the_tip_shift_not_cerruti(ball):
    """For nu = 0.49 Cerruti's term is tiny: the bottom of the dent sits where the tip slid to."""
    fine = np.linspace(-10.0, 10.0, 2001)
    model = ball.contact_model(np.array([0.0, 0.0, 130.0]), UP, ALONG, 45.0, 5.0)
    bottoms = []
    for force in (5.0, 20.0, 40.0):
        bottom = fine[np.argmax(model.depth_profile_mm(fine, force))]
        assert bottom == pytest.approx(model.tip_shift_mm(force), abs=0.02)
        bottoms.append(bottom)
    assert bottoms[0] > 0.1 and np.all(np.diff(bottoms) > 0)


def test_tip_shift_sticks_then_slips_and_stays_bounded():
    g, nu, mu = RUBBER.shear_modulus_mpa, RUBBER.nu, RUBBER.friction_mu
    p, a = 20.0, 2.0
    q = np.linspace(0.0, 5 * mu * p, 200)
    shift = bounded_tip_shift_mm(q, np.full_like(q, p), np.full_like(q, a), g, nu, mu, 1.0)
    assert np.all(np.diff(shift) > 0)
    assert shift.max() < 1.0 * a
    # Small loads: Mindlin's initial stiffness 8 G a / (2 - nu).
    small = bounded_tip_shift_mm(np.array([0.01]), np.array([p]), np.array([a]), g, nu, mu, 1.0)[0]
    assert small == pytest.approx(0.01 * (2 - nu) / (8 * g * a), rel=0.01)
    assert bounded_tip_shift_mm(np.array([-5.0]), np.array([p]), np.array([a]), g, nu, mu, 1.0)[0] < 0


def test_slip_margin_and_shift_sign_follow_the_angle(ball):
    top = np.array([0.0, 0.0, 130.0])
    margins = {a: ball.contact_model(top, UP, ALONG, a, 5.0).slip_margin(20.0) for a in NINE}
    assert margins[90.0] == 0.0
    assert margins[10.0] > 1.0 > margins[75.0]               # 10 deg slides, 75 deg sticks
    for a in NINE:
        shift = ball.contact_model(top, UP, ALONG, a, 5.0).tip_shift_mm(20.0)
        assert np.sign(shift) == np.sign(round(math.cos(math.radians(a)), 12))


# ----------------------------------------------------------------------------- force, push, creep

def test_peak_depth_and_push_strictly_increase_with_force_for_every_material(ball, composite, user_object):
    forces = np.linspace(1.0, 40.0, 14)
    for name, factory in homogeneous_models(ball, composite, user_object):
        for angle in (10.0, 45.0, 90.0, 135.0):
            model = factory(angle)
            peaks = [model.depth_profile_mm(X_MM, f).max() for f in forces]
            pushes = [model.push_mm_at_force(f) for f in forces]
            assert np.all(np.diff(peaks) > 0), (name, angle)
            assert np.all(np.diff(pushes) > 0), (name, angle)
            assert model.force_n_at_push(0.0) == 0.0 and model.force_n_at_push(-1.0) == 0.0


def test_force_and_push_are_inverse_and_creep_relaxes(composite):
    model = composite.contact_model(np.array([150.0, 0.0, 80.0]), UP, ALONG, 75.0, 5.0)
    for hold in (0.0, 0.7, 3.0, math.inf):
        for force in (0.5, 5.0, 20.0, 45.0, 3000.0):          # also beyond the tables
            push = model.push_mm_at_force(force, hold)
            assert model.force_n_at_push(push, hold) == pytest.approx(force, rel=1e-6)
    relaxing = [model.force_n_at_push(10.0, h) for h in (0.0, 0.5, 1.0, 2.0, 3.0, 10.0)]
    assert np.all(np.diff(relaxing) < 0)
    # A 3 s settle (tau 1 s) leaves the dent within 1 % of its equilibrium.
    settled = model.depth_profile_mm(X_MM, 20.0, hold_s=3.0).max()
    final = model.depth_profile_mm(X_MM, 20.0).max()
    assert 0.99 * final < settled < final


# ----------------------------------------------------------------------------- foam solver

def test_foam_solver_matches_the_linear_pasternak_decay_outside_the_tip():
    """With no densification (m = 0) the layer outside the contact must follow A K0(r / lambda)."""
    k0, lam, r_tip = 0.0015, 15.0, 5.0
    r = (np.arange(1200) + 0.5) * 0.25
    w, load, contact = solve_foam_obstacle(8.0, r_tip, k0, k0 * lam * lam, 1e9, 0.0, r)
    outside = (r > contact + 2.0) & (r < 60.0)
    ref = special.k0(r[outside] / lam)
    amplitude = np.dot(w[outside], ref) / np.dot(ref, ref)
    np.testing.assert_allclose(w[outside], amplitude * ref, rtol=0.02)
    # Equilibrium: the tip's load equals what the springs carry (the far edge carries ~nothing).
    area = 2 * math.pi * r * 0.25
    assert load == pytest.approx(float(np.sum(area * k0 * w)), rel=0.02)


def test_foam_depths_are_plausible_and_within_densification(composite):
    model = composite.contact_model(np.array([150.0, 0.0, 80.0]), UP, ALONG, 90.0, 5.0)
    peaks = {f: model.depth_profile_mm(X_MM, f).max() for f in (20.0, 40.0)}
    assert 10.0 < peaks[20.0] < 20.0 and 15.0 < peaks[40.0] < 30.0
    foam = composite.materials[1]
    assert FoamResponse(foam, 5.0).validity_problems(40.0) == []


# ----------------------------------------------------------------------------- cardboard

@pytest.mark.parametrize("point", [(0.0, 0.0), (40.0, -30.0), (60.0, 0.0)])
def test_cardboard_makes_one_broad_bowl_without_a_local_cavity(composite, point):
    p = np.array([point[0], point[1], 140.0])
    for angle in (45.0, 90.0, 135.0):
        model = composite.contact_model(p, UP, ALONG, angle, 5.0)
        for force in (5.0, 20.0, 40.0):
            depth = model.depth_profile_mm(X_MM, force)
            peak = int(np.argmax(depth))
            slope = np.diff(depth)
            assert np.all(slope[:peak] >= -1e-12) and np.all(slope[peak:] <= 1e-12), (point, angle, force)
            if point == (0.0, 0.0):
                base = depth.min()
                wide = X_MM[depth - base > 0.1 * (depth.max() - base)]
                assert wide.max() - wide.min() > 50.0


def test_cardboard_is_stiffer_near_the_box_edges(composite):
    peaks = [composite.contact_model(np.array([x, 0.0, 140.0]), UP, ALONG, 90.0, 5.0).depth_profile_mm(X_MM, 20.0).max()
             for x in (0.0, 30.0, 50.0, 65.0)]
    assert np.all(np.diff(peaks) < 0)
