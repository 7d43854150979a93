"""Calibration solvers against known synthetic truths, with sensor-like noise; degenerate sets refused."""
from __future__ import annotations

import numpy as np
import pytest

from elastoprobe.calibration.ft_payload import GravityCompensator, PayloadModel, gravity_in_sensor, solve_payload
from elastoprobe.calibration.scanner_sphere import SphereProfile, fit_circle, solve_scanner_sphere
from elastoprobe.calibration.tcp_pivot import solve_pivot, solve_sphere_touches
from elastoprobe.controller.core.devices import WrenchBlock
from elastoprobe.controller.core.errors import CalibrationError
from elastoprobe.controller.core.geometry import Pose, rotvec_to_matrix


def random_rotation(rng: np.random.Generator, max_deg: float = 180.0) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return rotvec_to_matrix(axis * np.radians(rng.uniform(0, max_deg)))


DOWN = np.diag([1.0, -1.0, -1.0])     # tool z pointing down


def tilted(rng: np.random.Generator, tilt_deg: float) -> np.ndarray:
    """A down-pointing tool, turned about the vertical and tilted by up to ``tilt_deg``."""
    heading = rotvec_to_matrix(np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)]))
    axis = np.array([*rng.normal(size=2), 0.0])
    axis /= np.linalg.norm(axis)
    return rotvec_to_matrix(axis * np.radians(rng.uniform(0, tilt_deg))) @ heading @ DOWN


# ----------------------------------------------------------------------------- F/T payload
def ft_data(rng, rotations, mass=0.65, com_mm=(10.0, -3.0, 40.0), noise_n=0.04 / np.sqrt(500),
            noise_nm=0.002 / np.sqrt(500)):
    bias_f, bias_t = rng.normal(0, 1.5, 3), rng.normal(0, 0.05, 3)
    g = gravity_in_sensor(rotations)
    w = mass * g
    f = bias_f + w + rng.normal(0, noise_n, w.shape)
    t = bias_t + np.cross(np.asarray(com_mm) / 1000.0, w) + rng.normal(0, noise_nm, w.shape)
    return f, t, bias_f, bias_t


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_payload_recovers_mass_and_com(seed: int) -> None:
    rng = np.random.default_rng(seed)
    rots = np.stack([tilted(rng, 90.0) for _ in range(12)])
    f, t, bias_f, bias_t = ft_data(rng, rots)
    fit = solve_payload(rots, f, t)
    assert abs(fit.mass_kg - 0.65) / 0.65 < 0.005
    assert np.linalg.norm(fit.com_sensor_mm - np.array([10.0, -3.0, 40.0])) < 0.5
    assert np.allclose(fit.bias_force_n, bias_f, atol=0.02)
    assert fit.force_report.condition_number < 30
    assert fit.force_report.rms < 0.01


def test_payload_refuses_close_orientations_and_too_few() -> None:
    rng = np.random.default_rng(3)
    close = np.stack([tilted(rng, 4.0) for _ in range(10)])
    f, t, *_ = ft_data(rng, close)
    with pytest.raises(CalibrationError, match="cone|condition"):
        solve_payload(close, f, t)
    few = np.stack([tilted(rng, 90.0) for _ in range(5)])
    f, t, *_ = ft_data(rng, few)
    with pytest.raises(CalibrationError, match="at least 6"):
        solve_payload(few, f, t)


def test_payload_refuses_contact_during_measurement() -> None:
    rng = np.random.default_rng(4)
    rots = np.stack([tilted(rng, 90.0) for _ in range(10)])
    f, t, *_ = ft_data(rng, rots)
    f[3] += np.array([0.0, 0.0, -3.0])      # the tip leaned on something at one pose
    with pytest.raises(CalibrationError, match="residual"):
        solve_payload(rots, f, t)


def test_gravity_compensation_leaves_only_contact() -> None:
    rng = np.random.default_rng(5)
    payload = PayloadModel(0.65, np.array([10.0, 0.0, 40.0]), np.array([1.0, -2.0, 0.5]), np.array([0.01, 0.0, 0.02]))
    tcp_to_sensor = Pose(np.array([0.0, 0.0, -160.0]), np.eye(3))
    comp = GravityCompensator(payload, tcp_to_sensor)
    r_tcp = np.stack([tilted(rng, 80.0) for _ in range(20)])
    f_g, t_g = payload.gravity_wrench(r_tcp)
    contact = np.tile([0.0, 0.0, -2.0], (20, 1))
    block = WrenchBlock(np.arange(20) * 1e-3, np.arange(20), contact + f_g + payload.bias_force_n,
                        t_g + payload.bias_torque_nm, np.zeros(20, np.uint32))
    out = comp.compensate(block, r_tcp)
    assert np.allclose(out.force_n, contact, atol=1e-9)
    assert np.allclose(out.torque_nm, 0.0, atol=1e-9)
    # A stream tared at one orientation: only the change of weight since the tare is removed.
    tare = r_tcp[0]
    f0, t0 = payload.gravity_wrench(tare)
    tared = WrenchBlock(block.t_s, block.seq, contact + f_g - f0, t_g - t0, block.status)
    out2 = comp.compensate(tared, r_tcp, tare_r_base_tcp=tare)
    assert np.allclose(out2.force_n, contact, atol=1e-9)


# ----------------------------------------------------------------------------- tip
def test_pivot_recovers_tip_and_refuses_single_axis() -> None:
    rng = np.random.default_rng(6)
    tip = np.array([1.2, -0.8, 161.5])
    pivot = np.array([450.0, 20.0, 30.0])
    rots = np.stack([tilted(rng, 35.0) for _ in range(15)])
    trans = pivot - np.einsum("nij,j->ni", rots, tip) + rng.normal(0, 0.05, (15, 3))
    fit = solve_pivot(rots, trans)
    assert np.linalg.norm(fit.tip_mm - tip) < 0.2
    assert np.linalg.norm(fit.fixed_point_base_mm - pivot) < 0.2
    # Turning about the tool axis only: the tip's component along it is free.
    spin = np.stack([DOWN @ rotvec_to_matrix(np.array([0.0, 0.0, a])) for a in np.linspace(0, 3, 10)])
    trans = pivot - np.einsum("nij,j->ni", spin, tip)
    with pytest.raises(CalibrationError, match="degenerate"):
        solve_pivot(spin, trans)


def sphere_touches(rng, tip, centre, rho, n, lean_deg, aim_offset_mm=3.0):
    rots, trans, dirs = [], [], []
    for _ in range(n):
        r = tilted(rng, 40.0)
        d = r[:, 2]
        # Approach direction: the probe axis leaned by up to lean_deg, still going down.
        axis = np.cross(d, rng.normal(size=3))
        axis /= np.linalg.norm(axis)
        e = rotvec_to_matrix(axis * np.radians(rng.uniform(0, lean_deg))) @ d
        # Touch where the tip centre reaches distance rho from the centre along -e from a random offset line.
        off = rng.normal(0, aim_offset_mm, 3)
        off -= (off @ e) * e
        start = centre + off - e * (rho + 20.0)
        # |start + s e - centre| = rho
        b = (start - centre) @ e
        s = -b - np.sqrt(b * b - ((start - centre) @ (start - centre) - rho * rho))
        tip_base = start + s * e
        rots.append(r)
        trans.append(tip_base - r @ tip)
        dirs.append(e)
    return np.stack(rots), np.stack(trans), np.stack(dirs)


def test_sphere_touches_recover_tip() -> None:
    rng = np.random.default_rng(7)
    tip = np.array([1.5, -1.0, 0.9])
    centre = np.array([450.0, 0.0, 25.0])
    rho = 30.0
    rots, trans, dirs = sphere_touches(rng, tip, centre, rho, 24, 55.0)
    trans = trans + rng.normal(0, 0.01, trans.shape)
    fit = solve_sphere_touches(rots, trans, dirs, rho)
    assert np.linalg.norm(fit.tip_mm - tip) < 0.1
    assert np.linalg.norm(fit.fixed_point_base_mm - centre) < 0.1


def test_sphere_touches_along_the_axis_are_refused() -> None:
    rng = np.random.default_rng(8)
    tip = np.array([1.5, -1.0, 0.9])
    # Every touch along the probe axis, aimed at the centre: the contact normal is the same in the
    # tool frame each time, so the tip's lateral offset never changes a touch distance.
    rots, trans, dirs = sphere_touches(rng, tip, np.array([450.0, 0.0, 25.0]), 30.0, 24, 0.0, aim_offset_mm=0.0)
    with pytest.raises(CalibrationError, match="not observable"):
        solve_sphere_touches(rots, trans, dirs, 30.0)


# ----------------------------------------------------------------------------- scanner
def test_fit_circle_exact() -> None:
    a = np.linspace(0.3, 2.0, 50)
    pts = np.column_stack([3.0 + 12.0 * np.cos(a), -170.0 + 12.0 * np.sin(a)])
    c, r = fit_circle(pts)
    assert np.allclose(c, [3.0, -170.0], atol=1e-6) and abs(r - 12.0) < 1e-6


def sphere_profiles(rng, mount, centre, radius, n, tilt_deg, noise_mm=0.015, samples=256):
    profiles = []
    for _ in range(n):
        r_tcp = tilted(rng, tilt_deg)
        y_off = rng.choice([-1.0, 1.0]) * rng.uniform(5.0, 18.0)
        p_s = np.array([rng.uniform(-15, 15), y_off, rng.uniform(170, 210)])
        t_tcp = centre - r_tcp @ mount.apply(p_s)
        pose = Pose(t_tcp, r_tcp)
        scanner = pose.compose(mount)
        c_s = scanner.inverse().apply(centre)
        rc = np.sqrt(radius**2 - c_s[1] ** 2)
        # Rays of a fan from the scanner origin: hit the circle's near side, else the table (a line).
        ang = np.linspace(-np.radians(20), np.radians(20), samples)
        dirs = np.column_stack([np.sin(ang), np.cos(ang)])
        cc = c_s[[0, 2]]
        b = dirs @ cc
        disc = b * b - (cc @ cc - rc * rc)
        s = np.where(disc > 0, b - np.sqrt(np.maximum(disc, 0)), np.nan)
        xz = dirs * s[:, None]
        # Table points where the circle is missed: a line well below the sphere's centre.
        table_s = (cc[1] + rc + 5.0) / dirs[:, 1]
        xz = np.where(np.isfinite(xz), xz, dirs * table_s[:, None])
        xz[:, 1] += rng.normal(0, noise_mm, samples)
        drop = rng.random(samples) < 0.05
        xz[drop] = np.nan
        profiles.append(SphereProfile(pose, xz))
    return profiles


def test_scanner_sphere_recovers_mount() -> None:
    rng = np.random.default_rng(9)
    nominal = Pose(np.array([150.0, 0.0, -120.0]), rotvec_to_matrix(np.radians([0.0, -51.34, 0.0])))
    turn = Pose(np.array([2.0, -1.5, 1.8]), rotvec_to_matrix(np.radians(2.0) * np.array([0.6, 0.0, 0.8])))
    true = nominal.compose(turn)
    centre = np.array([450.0, 30.0, 25.0])
    profiles = sphere_profiles(rng, true, centre, 25.0, 40, 35.0)
    fit = solve_scanner_sphere(profiles, 25.0, nominal)
    d_mm, d_deg = fit.tcp_to_scanner.distance_to(true)
    assert d_mm < 0.3 and d_deg < 0.1, (d_mm, d_deg)
    assert np.linalg.norm(fit.sphere_centre_base_mm - centre) < 0.3
    base_mm, base_deg = nominal.distance_to(true)
    assert base_mm > 2.0 and base_deg > 1.9       # the nominal really was off


def test_scanner_refuses_pure_translations_and_few_profiles() -> None:
    rng = np.random.default_rng(10)
    nominal = Pose(np.array([150.0, 0.0, -120.0]), rotvec_to_matrix(np.radians([0.0, -51.34, 0.0])))
    centre = np.array([450.0, 30.0, 25.0])
    flat = sphere_profiles(rng, nominal, centre, 25.0, 30, 0.0)
    same = [SphereProfile(Pose(p.tcp_pose.position_mm, flat[0].tcp_pose.rotation), p.xz_mm) for p in flat]
    with pytest.raises(CalibrationError, match="span only"):
        solve_scanner_sphere(same, 25.0, nominal)
    few = sphere_profiles(rng, nominal, centre, 25.0, 5, 30.0)
    with pytest.raises(CalibrationError, match="at least 8"):
        solve_scanner_sphere(few, 25.0, nominal)
