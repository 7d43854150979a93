"""Same seed, same bytes; a resumed run (same step keys) equals an uninterrupted one."""
from __future__ import annotations

import hashlib

import numpy as np

from elastoprobe.controller.core.devices import MotionState
from elastoprobe.controller.core.geometry import Pose

from test_sim_helpers import Log, burst, go_to, hold, make_cell, move, press, standoff_pose, wait

TOP = np.array([0.0, 0.0, 130.0])
UP = np.array([0.0, 0.0, 1.0])


def step_commands(cell, angle_deg: float) -> dict:
    """One probe as the controller issues it after begin_step; everything the devices returned."""
    log = Log()
    standoff, p, n, t = standoff_pose(cell, TOP, UP, angle_deg)
    go_to(cell, standoff, 250.0, log)
    hold(cell, 0.2, log)
    cell.ft.tare()
    tared_from = len(log.blocks)
    hold(cell, 0.05, log)
    ref, _ = burst(cell, 5, log)
    d = standoff.rotation[:, 2]
    assert wait(cell, cell.arm.seek_contact(d, 5.0, 0.4, 45.0), log) == MotionState.CONTACT
    scans = list(ref)
    for force in (4.0, 9.0):
        assert wait(cell, cell.arm.regulate_force(d, force, 10.0), log) == MotionState.DONE
        hold(cell, 1.0, log)
        got, _ = burst(cell, 8, log)
        scans += got
    pose = cell.arm.status().tcp_pose
    move(cell, Pose(pose.position_mm + n * 20.0, pose.rotation), 10.0, log)
    return {"blocks": log.blocks, "scans": scans, "poses": log.poses, "tared_from": tared_from}


def relative(result: dict, t0_s: float) -> dict:
    """The data with times relative to the begin_step instant (integer microseconds)."""
    ft = [(np.round((b.t_s - t0_s) * 1e6).astype(np.int64), b.force_n, b.torque_nm, b.status) for b in result["blocks"]]
    sc = [(int(round((s.exposure_t_s - t0_s) * 1e6)), s.x_mm, s.z_mm) for s in result["scans"]]
    return {"ft": ft, "scans": sc, "tared_from": result["tared_from"]}


def digest(rel: dict) -> str:
    h = hashlib.sha256()
    for t, f, tq, st in rel["ft"]:
        for arr in (t, f, tq, st):
            h.update(np.ascontiguousarray(arr).tobytes())
    for t, x, z in rel["scans"]:
        h.update(str(t).encode())
        h.update(x.tobytes())
        h.update(z.tobytes())
    return h.hexdigest()


def test_same_seed_gives_the_same_bytes_and_another_seed_does_not():
    def run(seed: int) -> str:
        cell = make_cell(seed=seed)
        cell.begin_step((seed, 3, 0))
        t0 = cell.clock.now_s()
        return digest(relative(step_commands(cell, 45.0), t0))

    a = run(21)
    assert run(21) == a
    assert run(22) != a


def test_resumed_step_equals_uninterrupted_at_any_absolute_time():
    seed, key = 5, (5, 42, 0)
    # Uninterrupted: a long history first (another probe, other step keys), then home.
    a = make_cell(seed=seed, start_s=812.34)
    a.begin_step((seed, 41, 0))
    press(a, TOP, UP, 75.0, 8.0, settle_s=1.0)
    pose = a.arm.status().tcp_pose
    move(a, Pose(pose.position_mm + UP * 30.0, pose.rotation), 20.0)
    move(a, Pose(np.array([*a.arm.status().tcp_pose.position_mm[:2], 400.0]), pose.rotation))
    move(a, a.home_pose())
    hold(a, 0.37)
    a.begin_step(key)
    t_a = a.clock.now_s()
    run_a = relative(step_commands(a, 45.0), t_a)

    # Resumed: a fresh process at another absolute time, same start pose, same key.
    b = make_cell(seed=seed, start_s=35.0)
    hold(b, 1.23)
    b.begin_step(key)
    t_b = b.clock.now_s()
    assert abs(t_a - t_b) > 700.0
    run_b = relative(step_commands(b, 45.0), t_b)

    assert len(run_a["ft"]) == len(run_b["ft"]) and len(run_a["scans"]) == len(run_b["scans"])
    k = run_a["tared_from"]
    assert k == run_b["tared_from"]
    # Before the step's tare the sensors differ only by their software bias (sensor state
    # from before the step: A was tared during its earlier probe, B never was).
    for (ta, fa, qa, sa), (tb, fb, qb, sb) in zip(run_a["ft"][:k], run_b["ft"][:k]):
        assert np.array_equal(ta, tb)
        offset = fa - fb
        assert np.allclose(offset, offset[0], atol=1e-9)
    # From the tare on: bit for bit.
    for (ta, fa, qa, sa), (tb, fb, qb, sb) in zip(run_a["ft"][k:], run_b["ft"][k:]):
        assert np.array_equal(ta, tb)
        assert fa.tobytes() == fb.tobytes() and qa.tobytes() == qb.tobytes() and sa.tobytes() == sb.tobytes()
    for (ta, xa, za), (tb, xb, zb) in zip(run_a["scans"], run_b["scans"]):
        assert ta == tb and xa.tobytes() == xb.tobytes() and za.tobytes() == zb.tobytes()
    tail = {"ft": run_a["ft"][k:], "scans": run_a["scans"]}
    assert digest(tail) == digest({"ft": run_b["ft"][k:], "scans": run_b["scans"]})


def test_permanent_dents_depend_on_the_max_force_and_are_restored():
    box_top = np.array([0.0, 0.0, 140.0])
    cell = make_cell(obj="composite", seed=2)
    press(cell, box_top, UP, 90.0, 40.0, settle_s=0.5)          # above the cardboard's yield (32 N)
    pose = cell.arm.status().tcp_pose
    move(cell, Pose(pose.position_mm + UP * 40.0, pose.rotation), 20.0)
    history = cell.press_history()
    assert len(history) == 1 and history[0][2] >= 39.0
    look, _, _, _ = standoff_pose(cell, box_top, UP, 90.0, standoff_mm=40.0)
    move(cell, look)
    dented = cell.scanner.profile(cell.world.snapshot_now(), noise=False)[1]

    fresh = make_cell(obj="composite", seed=2)
    go_to(fresh, look, 250.0)
    flat = fresh.scanner.profile(fresh.world.snapshot_now(), noise=False)[1]
    ok = np.isfinite(dented) & np.isfinite(flat)
    assert np.nanmax(np.abs(dented[ok] - flat[ok])) > 0.05       # the dent shows without contact

    resumed = make_cell(obj="composite", seed=2)
    resumed.restore_history(history)
    go_to(resumed, look, 250.0)
    again = resumed.scanner.profile(resumed.world.snapshot_now(), noise=False)[1]
    assert np.array_equal(np.isfinite(again), np.isfinite(dented))
    assert np.allclose(again[ok], dented[ok], atol=1e-9)

    # Pressing the same place to the same force again changes nothing.
    press(cell, box_top, UP, 90.0, 40.0, settle_s=0.5)
    pose = cell.arm.status().tcp_pose
    move(cell, Pose(pose.position_mm + UP * 40.0, pose.rotation), 20.0)
    move(cell, look)
    assert len(cell.press_history()) == 1
    after = cell.scanner.profile(cell.world.snapshot_now(), noise=False)[1]
    assert np.allclose(after[ok], dented[ok], atol=2e-3)
