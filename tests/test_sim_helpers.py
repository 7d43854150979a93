"""Helpers for the simulated-cell tests (drive a SimCell through its device interfaces), and
tests of the keyed random streams they rely on."""
from __future__ import annotations

import hashlib
from dataclasses import replace
from pathlib import Path

import numpy as np

from elastoprobe.controller.core.config import load_cell
from elastoprobe.controller.core.devices import MotionState
from elastoprobe.controller.core.errors import MotionRefused
from elastoprobe.controller.core.geometry import Pose, probe_tcp_pose, scan_direction
from elastoprobe.sim.cell import SimCell, params_from_cell
from elastoprobe.sim.world import PagedNormal, keyed_rng

ROOT = Path(__file__).resolve().parent.parent
HOME_DEG = (180.0, -90.0, 90.0, -90.0, -90.0, 0.0)   # the base turned toward +x, where the objects sit


class Fence:
    """A path validator that refuses every straight path ending beyond x = ``max_x_mm``
    (base frame), and records what it checked."""

    def __init__(self, max_x_mm: float) -> None:
        self.max_x_mm = max_x_mm
        self.checked: list[tuple[Pose, Pose, bool]] = []

    def validate_path(self, start: Pose, end: Pose, contact_allowed: bool = False) -> None:
        self.checked.append((start, end, contact_allowed))
        if end.position_mm[0] > self.max_x_mm:
            raise MotionRefused(f"beyond the fence at x = {self.max_x_mm} mm")


def composite_targets_plan(name: str, *, characterize: str, densify: str, budget: str, targets: str,
                           tail: str = "") -> str:
    """The text of a plan on the simulated cell (config/cells/sim.yaml) and the shipped
    composite that presses exactly ``targets`` (YAML list items, one per line), surveyed at
    90 deg with 4 and 12 N. ``characterize``, ``densify`` and ``budget``: YAML flow mappings;
    ``tail``: more top-level keys."""
    return f"""
name: {name}
cell: {ROOT / 'config' / 'cells' / 'sim.yaml'}
simulated_object: {ROOT / 'config' / 'objects' / 'composite.yaml'}
seed: 1
cloud: {{source: scan, sweep_spacing_mm: 6.0, sweep_height_mm: 40.0, max_points: 20000}}
sampling:
  units: 0
  edge_clearance_mm: 15.0
  max_tilt_deg: 50.0
  reference_direction: [0.0, 1.0, 0.0]
probing: {{scans_per_step: 5, settle_s: 0.5, standoff_mm: 15.0, force_rate_n_s: 20.0, force_tolerance_n: 0.5}}
phases:
  survey: {{angles_deg: [90], forces_n: [4.0, 12.0]}}
  characterize: {characterize}
  densify: {densify}
budget: {budget}
targets:
{targets}
model: {{hidden_units: 45, ensemble: 2, max_epochs: 100, profile_span_mm: 80.0, profile_samples: 64}}
{tail}"""


def make_cell(obj: str = "rubber_ball", seed: int = 1, base_x_mm: float = 450.0, start_s: float = 0.0,
              scanner: dict | None = None, ft: dict | None = None, faults=None, object_path: Path | None = None,
              **overrides) -> SimCell:
    """A simulated cell (config/cells/sim.yaml) with a shipped object by name, or the object
    file at ``object_path``."""
    spec, _ = load_cell(ROOT / "config" / "cells" / "sim.yaml")
    params = params_from_cell(spec, object_path or ROOT / "config" / "objects" / f"{obj}.yaml", seed=seed)
    params.home_joints_deg = HOME_DEG
    params.base_to_object = Pose(np.array([base_x_mm, 0.0, 0.0]), np.eye(3))
    params.start_time_s = start_s
    if scanner:
        params.scanner = replace(params.scanner, **scanner)
    if ft:
        params.ft = replace(params.ft, **ft)
    if faults is not None:
        params.faults = list(faults)
    for k, v in overrides.items():
        setattr(params, k, v)
    return SimCell(params)


class Log:
    """What a controller records while it polls: F/T blocks and TCP poses."""

    def __init__(self) -> None:
        self.blocks = []
        self.pose_t = []
        self.poses = []

    def forces(self) -> np.ndarray:
        return np.concatenate([b.force_n for b in self.blocks]) if self.blocks else np.zeros((0, 3))

    def times(self) -> np.ndarray:
        return np.concatenate([b.t_s for b in self.blocks]) if self.blocks else np.zeros(0)


def tick(cell: SimCell, log: Log | None = None, dt: float = 0.01) -> None:
    cell.clock.sleep_s(dt)
    block = cell.ft.read_block()
    status = cell.arm.status()
    if log is not None:
        if len(block):
            log.blocks.append(block)
        log.pose_t.append(status.t_s)
        log.poses.append(status.tcp_pose)


def wait(cell: SimCell, motion, log: Log | None = None, timeout_s: float = 60.0) -> MotionState:
    end = cell.clock.now_s() + timeout_s
    while motion.state() == MotionState.RUNNING and cell.clock.now_s() < end:
        tick(cell, log)
    return motion.state()


def hold(cell: SimCell, duration_s: float, log: Log | None = None) -> None:
    end = cell.clock.now_s() + duration_s
    while cell.clock.now_s() < end - 1e-9:
        tick(cell, log)


def burst(cell: SimCell, count: int, log: Log | None = None) -> tuple[list, list[Pose]]:
    """Scans and the TCP pose at each exposure (from the poses logged while polling)."""
    log = log if log is not None else Log()
    cell.scanner.read_scans()
    cell.scanner.start_burst(count)
    scans = []
    end = cell.clock.now_s() + count / cell.scanner.rate_hz * 3 + 1.0
    while len(scans) < count and cell.clock.now_s() < end:
        tick(cell, log)
        scans.extend(cell.scanner.read_scans())
    poses = []
    t = np.asarray(log.pose_t)
    for sc in scans:
        j = int(np.argmin(np.abs(t - sc.exposure_t_s)))
        poses.append(log.poses[j])
    return scans, poses


def move(cell: SimCell, pose: Pose, speed: float = 150.0, log: Log | None = None) -> None:
    state = wait(cell, cell.arm.move_linear(pose, speed, 600.0), log)
    assert state == MotionState.DONE, state


def standoff_pose(cell: SimCell, p_obj: np.ndarray, n_obj: np.ndarray, angle_deg: float,
                  t_obj: np.ndarray | None = None, standoff_mm: float = 15.0) -> tuple[Pose, np.ndarray, np.ndarray, np.ndarray]:
    """Standoff TCP pose aiming the tip centre at p + R n (the sphere then touches at p)."""
    b2o = cell.base_to_object
    p, n = b2o.apply(p_obj), b2o.apply_vector(n_obj)
    t = b2o.apply_vector(t_obj) if t_obj is not None else scan_direction(n, np.array([1.0, 0.0, 0.0]))
    r = cell.params.tip_radius_mm
    return probe_tcp_pose(p + r * n, n, t, angle_deg, offset_mm=standoff_mm), p, n, t


def go_to(cell: SimCell, pose: Pose, travel_z_mm: float, log: Log | None = None) -> None:
    here = cell.arm.status().tcp_pose
    if here.position_mm[2] < travel_z_mm - 1.0:
        move(cell, Pose(np.array([*here.position_mm[:2], travel_z_mm]), here.rotation), log=log)
    move(cell, Pose(np.array([*pose.position_mm[:2], max(travel_z_mm, pose.position_mm[2])]), pose.rotation), log=log)
    move(cell, pose, log=log)


def press(cell: SimCell, p_obj, n_obj, angle_deg: float, force_n: float, travel_z_mm: float = 250.0,
          log: Log | None = None, settle_s: float = 3.0, t_obj=None):
    """Standoff, tare, seek contact and regulate to ``force_n``; returns (d, p, n, t) in the base frame."""
    standoff, p, n, t = standoff_pose(cell, np.asarray(p_obj, float), np.asarray(n_obj, float), angle_deg, t_obj)
    go_to(cell, standoff, travel_z_mm, log)
    hold(cell, 0.2, log)
    cell.ft.tare()
    hold(cell, 0.05, log)
    d = standoff.rotation[:, 2]
    assert wait(cell, cell.arm.seek_contact(d, 5.0, 0.4, 45.0), log) == MotionState.CONTACT
    assert wait(cell, cell.arm.regulate_force(d, force_n, 10.0), log) == MotionState.DONE
    hold(cell, settle_s, log)
    return d, p, n, t


def scan_points_obj(cell: SimCell, scans, poses) -> np.ndarray:
    """Scans mapped through the TCP pose at exposure into the object frame (M,3), NaN dropped."""
    out = []
    to_obj = cell.base_to_object.inverse()
    for sc, pose in zip(scans, poses):
        ok = np.isfinite(sc.z_mm)
        local = np.column_stack([sc.x_mm[ok], np.zeros(int(ok.sum())), sc.z_mm[ok]])
        out.append(to_obj.compose(pose).compose(cell.tcp_to_scanner).apply(local))
    return np.vstack(out) if out else np.zeros((0, 3))


def depth_profile(cell: SimCell, ref_pts_obj: np.ndarray, pts_obj: np.ndarray, p_obj: np.ndarray, n_obj: np.ndarray,
                  t_obj: np.ndarray, grid_mm: np.ndarray) -> np.ndarray:
    """Depth along -n (mm) of the loaded surface below the reference, resampled on x along t."""
    def height(pts):
        rel = pts - p_obj
        x, h = rel @ t_obj, rel @ n_obj
        order = np.argsort(x)
        x, h = x[order], h[order]
        # Bin onto the grid (mean per bin), NaN where no sample fell.
        edges = np.concatenate([grid_mm - np.diff(grid_mm)[0] / 2, [grid_mm[-1] + np.diff(grid_mm)[0] / 2]])
        idx = np.digitize(x, edges) - 1
        out = np.full(grid_mm.shape, np.nan)
        for k in range(grid_mm.size):
            sel = idx == k
            if sel.any():
                out[k] = h[sel].mean()
        return out
    return height(ref_pts_obj) - height(pts_obj)


# ------------------------------------------------------------------ tests of the keyed streams

def test_keyed_rng_depends_on_every_key_element():
    base = keyed_rng(1, 2, 3, 4).random(4)
    assert np.array_equal(base, keyed_rng(1, 2, 3, 4).random(4))
    for key in ((0, 2, 3, 4), (1, 0, 3, 4), (1, 2, 0, 4), (1, 2, 3, 0)):
        assert not np.array_equal(base, keyed_rng(*key).random(4))


def test_paged_normal_is_independent_of_grouping():
    a, b = PagedNormal(6, page_rows=64), PagedNormal(6, page_rows=64)
    a.reset(keyed_rng(5, 1, 0, 1))
    b.reset(keyed_rng(5, 1, 0, 1))
    whole = a.take(0, 300)
    parts = []
    i = 0
    for n in (1, 7, 56, 64, 100, 72):
        parts.append(b.take(i, n))
        i += n
    assert np.array_equal(whole, np.concatenate(parts))
    # Re-reading the current page (a sub-chunk cut short) gives the same rows.
    assert np.array_equal(b.take(290, 10), whole[290:300])


def digest(log: Log, scans) -> str:
    """SHA-256 of every F/T block and every scan (exposure time, x and z): same bytes, same digest."""
    h = hashlib.sha256()
    for b in log.blocks:
        for arr in (b.t_s, b.seq, b.force_n, b.torque_nm, b.status):
            h.update(np.ascontiguousarray(arr).tobytes())
    for sc in scans:
        h.update(repr(sc.exposure_t_s).encode())
        h.update(sc.x_mm.tobytes())
        h.update(sc.z_mm.tobytes())
    return h.hexdigest()
