"""F/T bias and payload: mass and centre of mass from static readings at spread orientations.

Model (sensor frame, the ``WrenchBlock`` convention: the load ON the tool):

    F_i = F0 + m g_i            g_i = R_i^T g   (R_i = base <- sensor, g = (0, 0, -9.80665) m/s^2)
    T_i = T0 + c x (m g_i)      c: centre of mass in the sensor frame (m inside, mm outside)

Both are linear: first [I  g_i][F0; m] = F_i, then with w_i = m g_i,
[I  -K(w_i)][T0; c] = T_i (K(w) c = w x c). F0 and T0 absorb the sensor bias and any
software tare, so the stream may have been tared once before the data were taken
(not between poses). The orientations must turn gravity through a wide cone in the
sensor frame, or mass and bias (and the centre of mass along gravity) cannot be told
apart: the column-scaled condition number of both designs is checked.

:class:`GravityCompensator` removes the payload's weight from a stream, given the
TCP orientation of each block (and, for a tared stream, the orientation at the tare).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from elastoprobe.controller.core.devices import WrenchBlock
from elastoprobe.controller.core.errors import CalibrationError
from elastoprobe.controller.core.geometry import Pose

from .common import (FitReport, axis_spread, data_sha256, residual_stats,
                     scaled_condition_number, skew_batch)

GRAVITY_BASE_M_S2 = np.array([0.0, 0.0, -9.80665])
MIN_ORIENTATIONS = 6


@dataclass(frozen=True)
class PayloadFit:
    """Solved payload: mass (kg), centre of mass (sensor frame, mm), bias (N, N m) and the fit quality."""

    mass_kg: float
    com_sensor_mm: np.ndarray
    bias_force_n: np.ndarray
    bias_torque_nm: np.ndarray
    force_report: FitReport
    torque_report: FitReport
    data_sha256: str

    def com_tcp_mm(self, tcp_to_sensor: Pose) -> np.ndarray:
        """The centre of mass in the TCP frame (mm)."""
        return tcp_to_sensor.apply(self.com_sensor_mm)


def gravity_in_sensor(r_base_sensor: np.ndarray, gravity_base_m_s2: np.ndarray = GRAVITY_BASE_M_S2) -> np.ndarray:
    """Gravity (m/s^2) in the sensor frame for rotations (3,3) or (N,3,3) base <- sensor."""
    r = np.asarray(r_base_sensor, dtype=float)
    return gravity_base_m_s2 @ r if r.ndim == 2 else np.einsum("nij,i->nj", r, gravity_base_m_s2)


def solve_payload(r_base_sensor: np.ndarray, force_n: np.ndarray, torque_nm: np.ndarray,
                  max_condition: float = 30.0, max_force_rms_n: float = 0.3,
                  max_torque_rms_nm: float = 0.03, min_gravity_spread: float = 0.2) -> PayloadFit:
    """Least-squares bias, mass and centre of mass from N static readings.

    ``r_base_sensor`` (N,3,3) sensor orientations; ``force_n``, ``torque_nm`` (N,3) the
    mean readings (sensor frame) held still at each. Refuses (CalibrationError) fewer
    than 6 orientations, gravity directions that do not span a wide cone (second
    singular value of the centred directions below ``min_gravity_spread``), a scaled
    condition number above ``max_condition``, a negative mass, or residuals above the
    given RMS (contact, motion or a loose payload during the measurement).
    """
    r = np.asarray(r_base_sensor, dtype=float)
    f = np.asarray(force_n, dtype=float)
    t = np.asarray(torque_nm, dtype=float)
    n = r.shape[0]
    if n < MIN_ORIENTATIONS:
        raise CalibrationError(f"F/T payload: {n} orientations, at least {MIN_ORIENTATIONS} are needed")
    if f.shape != (n, 3) or t.shape != (n, 3):
        raise CalibrationError("F/T payload: force and torque must be (N,3) like the N rotations")
    g = gravity_in_sensor(r)
    spread = axis_spread(g)
    if spread[1] < min_gravity_spread:
        raise CalibrationError(f"F/T payload: the orientations turn gravity through too narrow a cone in the "
                               f"sensor frame (spread {spread[1]:.3f} < {min_gravity_spread}); tilt the tool "
                               f"about at least two different axes")
    # Forces: 3 rows per orientation, unknowns F0 (3) and m.
    a_f = np.zeros((3 * n, 4))
    a_f[:, :3] = np.tile(np.eye(3), (n, 1))
    a_f[:, 3] = g.ravel()
    cond_f = scaled_condition_number(a_f)
    if not np.isfinite(cond_f) or cond_f > max_condition:
        raise CalibrationError(f"F/T payload: mass and bias are not separable with these orientations "
                               f"(condition number {cond_f:.3g} > {max_condition:g})")
    x_f, *_ = np.linalg.lstsq(a_f, f.ravel(), rcond=None)
    bias_f, mass = x_f[:3], float(x_f[3])
    if mass <= 0.0:
        raise CalibrationError(f"F/T payload: the fitted mass is {mass:.4f} kg (not positive): wrong gravity "
                               f"sign, wrong sensor frame or no payload")
    res_f = (f.ravel() - a_f @ x_f).reshape(n, 3)
    # Torques: unknowns T0 (3) and c (3, metres), with w_i = m g_i.
    w = mass * g
    a_t = np.zeros((3 * n, 6))
    a_t[:, :3] = np.tile(np.eye(3), (n, 1))
    a_t[:, 3:] = -skew_batch(w).reshape(3 * n, 3)
    cond_t = scaled_condition_number(a_t)
    if not np.isfinite(cond_t) or cond_t > max_condition:
        raise CalibrationError(f"F/T payload: the centre of mass is not observable with these orientations "
                               f"(condition number {cond_t:.3g} > {max_condition:g})")
    x_t, *_ = np.linalg.lstsq(a_t, t.ravel(), rcond=None)
    res_t = (t.ravel() - a_t @ x_t).reshape(n, 3)
    rms_f, max_f = residual_stats(res_f)
    rms_t, max_t = residual_stats(res_t)
    if rms_f > max_force_rms_n:
        raise CalibrationError(f"F/T payload: force residual RMS {rms_f:.3f} N > {max_force_rms_n} N "
                               f"(contact, motion or a loose payload while measuring?)")
    if rms_t > max_torque_rms_nm:
        raise CalibrationError(f"F/T payload: torque residual RMS {rms_t:.4f} N m > {max_torque_rms_nm} N m "
                               f"(contact, motion or a loose payload while measuring?)")
    spread_extra = {"gravity_spread": spread}
    return PayloadFit(
        mass_kg=mass, com_sensor_mm=x_t[3:] * 1000.0, bias_force_n=bias_f, bias_torque_nm=x_t[:3],
        force_report=FitReport(n, rms_f, max_f, "N", cond_f, spread_extra),
        torque_report=FitReport(n, rms_t, max_t, "N m", cond_t, {}),
        data_sha256=data_sha256(r, f, t))


@dataclass(frozen=True)
class PayloadModel:
    """What gravity compensation needs: mass (kg), centre of mass (sensor frame, mm), bias."""

    mass_kg: float
    com_sensor_mm: np.ndarray
    bias_force_n: np.ndarray = field(default_factory=lambda: np.zeros(3))
    bias_torque_nm: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @staticmethod
    def from_fit(fit: PayloadFit) -> "PayloadModel":
        return PayloadModel(fit.mass_kg, fit.com_sensor_mm, fit.bias_force_n, fit.bias_torque_nm)

    def gravity_wrench(self, r_base_sensor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Payload weight (force N, torque N m about the sensor origin) in the sensor frame."""
        w = self.mass_kg * np.atleast_2d(gravity_in_sensor(r_base_sensor))
        c_m = np.asarray(self.com_sensor_mm, dtype=float) / 1000.0
        return w, np.cross(c_m, w)


class GravityCompensator:
    """Removes the payload's weight (and, for an untared stream, the bias) from F/T blocks.

    ``tcp_to_sensor`` fixes the sensor's orientation on the tool, so callers give TCP
    rotations (base <- tcp), what the arm reports.
    """

    def __init__(self, payload: PayloadModel, tcp_to_sensor: Pose) -> None:
        self.payload = payload
        self._r_tcp_sensor = tcp_to_sensor.rotation

    def sensor_rotation(self, r_base_tcp: np.ndarray) -> np.ndarray:
        r = np.asarray(r_base_tcp, dtype=float)
        return r @ self._r_tcp_sensor

    def compensate(self, block: WrenchBlock, r_base_tcp: np.ndarray,
                   tare_r_base_tcp: np.ndarray | None = None) -> WrenchBlock:
        """The block with the payload's weight removed: only contact loads remain.

        ``r_base_tcp``: (3,3) for the whole block or (N,3,3) per sample. If the stream
        was tared (software bias) at orientation ``tare_r_base_tcp``, the tare already
        removed the bias and the weight at that orientation: only the change of weight
        since is subtracted. Otherwise the fitted bias and the full weight are.
        """
        if not len(block):
            return block
        f_g, t_g = self.payload.gravity_wrench(self.sensor_rotation(r_base_tcp))
        if tare_r_base_tcp is not None:
            f0, t0 = self.payload.gravity_wrench(self.sensor_rotation(tare_r_base_tcp))
        else:
            f0 = -np.asarray(self.payload.bias_force_n)[None, :]
            t0 = -np.asarray(self.payload.bias_torque_nm)[None, :]
        return WrenchBlock(block.t_s, block.seq, block.force_n - (f_g - f0), block.torque_nm - (t_g - t0),
                           block.status)
