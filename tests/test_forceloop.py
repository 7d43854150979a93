"""The force loop (controller/core/forceloop.py) on the scripted arm, without the physics simulator:
contact search, force regulation on springs from foam-soft to rubber-stiff with a robot's
command delay, the first crossing stopping the arm, and a latched trip that lets an unloading
motion through and stops anything else. Plus the gains' home, the cell file (validated with
positions), and the simulated arm running this loop and no other."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller.core.clock import VirtualClock
from elastoprobe.controller.core.config import load_cell
from elastoprobe.controller.core.devices import MotionState, Trip
from elastoprobe.controller.core.errors import InputError
from elastoprobe.controller.core.forceloop import ForceLoopGains, ForceSupervisor, SupervisedMotion, Verdict
from elastoprobe.controller.core.geometry import Pose
from elastoprobe.controller.core.safety import SafetyLimits
from elastoprobe.controller.drivers.real_cell import hardware_config
from elastoprobe.controller.drivers.scripted import ScriptedArm

from test_sim_helpers import make_cell, press

ROOT = Path(__file__).resolve().parent.parent
LIMITS = SafetyLimits(max_force_n=45.0, max_torque_nm=4.0, max_lateral_force_n=45.0, max_force_rate_n_s=1500.0,
                      ft_stale_ms=30.0, ft_frozen_ms=60.0, slip_mm=6.0)
DOWN = np.array([0.0, 0.0, -1.0])
SURFACE_Z_MM = 0.0


def spring(stiffness_n_mm: float, surface_z_mm: float = SURFACE_Z_MM):
    """A flat surface at z = surface_z_mm pushing back with ``stiffness_n_mm`` (force up, on the tool)."""
    def force_of(p: np.ndarray) -> np.ndarray:
        return np.array([0.0, 0.0, stiffness_n_mm * max(surface_z_mm - p[2], 0.0)])
    return force_of


def arm_on(force_of, start_z_mm: float = 5.0, limits: SafetyLimits = LIMITS, **kwargs) -> tuple[ScriptedArm, VirtualClock]:
    clock = VirtualClock()
    arm = ScriptedArm(clock, force_of, limits=limits, start_mm=np.array([0.0, 0.0, start_z_mm]), **kwargs)
    return arm, clock


def wait(clock: VirtualClock, motion, timeout_s: float = 20.0, poll_s: float = 0.01) -> MotionState:
    end = clock.now_s() + timeout_s
    while motion.state() == MotionState.RUNNING and clock.now_s() < end:
        clock.sleep_s(poll_s)
    return motion.state()


def pressed(stiffness_n_mm: float, force_n: float, **kwargs) -> tuple[ScriptedArm, VirtualClock]:
    arm, clock = arm_on(spring(stiffness_n_mm), **kwargs)
    assert wait(clock, arm.seek_contact(DOWN, 5.0, 0.4, 20.0)) == MotionState.CONTACT
    assert wait(clock, arm.regulate_force(DOWN, force_n, 10.0)) == MotionState.DONE
    return arm, clock


# ----------------------------------------------------------------------------- contact search
def test_contact_search_stops_at_the_threshold_sample() -> None:
    arm, clock = arm_on(spring(5.0), start_z_mm=5.0)
    motion = arm.seek_contact(DOWN, 5.0, 0.4, 20.0)
    assert wait(clock, motion) == MotionState.CONTACT
    # The stop went out at the sample that reached 0.4 N (0.08 mm into a 5 N/mm surface):
    # stopping from 5 mm/s at 2500 mm/s^2 adds 0.005 mm, one sample 0.005 mm more.
    stops = [t for t, kind, _ in arm.commands if kind == "stop"]
    assert len(stops) == 1
    clock.sleep_s(0.1)
    depth = SURFACE_Z_MM - arm.position_mm[2]
    assert 0.08 - 1e-9 <= depth <= 0.08 + 0.011, depth
    assert arm.supervisor.counts.contacts == 1


def test_contact_search_without_a_surface_ends_no_contact_after_its_distance() -> None:
    arm, clock = arm_on(spring(5.0, surface_z_mm=-100.0), start_z_mm=5.0)
    motion = arm.seek_contact(DOWN, 5.0, 0.4, 12.0)
    assert wait(clock, motion) == MotionState.NO_CONTACT
    clock.sleep_s(0.1)
    travelled = 5.0 - arm.position_mm[2]
    # The distance is checked every control tick (2 ms here): at most one tick's travel beyond.
    assert 12.0 <= travelled <= 12.0 + 5.0 * 0.002 + 0.02, travelled
    assert arm.supervisor.counts.no_contacts == 1


# ----------------------------------------------------------------------------- regulation
@pytest.mark.parametrize("stiffness_n_mm", [0.5, 5.0, 60.0])
@pytest.mark.parametrize("delay_s", [0.0, 0.006])
def test_regulation_reaches_and_holds_the_force_on_soft_and_stiff_springs(stiffness_n_mm: float,
                                                                          delay_s: float) -> None:
    """Foam-soft to rubber-stiff, with no command delay and with a robot's (6 ms: an RTDE
    cycle, the link and the controller): DONE, then held within the loop's tolerance, and the
    ramp overshoots by no more than that tolerance."""
    gains = ForceLoopGains()
    force_n = 12.0
    arm, clock = arm_on(spring(stiffness_n_mm), command_delay_s=delay_s, noise_n=0.04, seed=3)
    assert wait(clock, arm.seek_contact(DOWN, 5.0, 0.4, 20.0)) == MotionState.CONTACT
    arm.ft.read_block()
    motion = arm.regulate_force(DOWN, force_n, 10.0)
    assert wait(clock, motion, timeout_s=10.0) == MotionState.DONE
    ramp = arm.ft.read_block()
    clock.sleep_s(2.0)
    held = arm.ft.read_block()
    f_ramp = np.convolve(ramp.force_magnitude_n(), np.ones(10) / 10, mode="valid")
    f_held = held.force_magnitude_n().reshape(-1, 10).mean(axis=1)      # the loop's own 10 ms reading
    tol = gains.tolerance_n_at(force_n)
    assert f_ramp.max() - force_n <= tol, (f_ramp.max(), stiffness_n_mm, delay_s)
    assert np.abs(f_held - force_n).max() <= 3 * tol, (f_held.min(), f_held.max())
    assert abs(f_held.mean() - force_n) <= tol
    assert motion.state() == MotionState.DONE and arm.supervisor.regulation is not None   # still holding
    assert arm.supervisor.counts.updates >= 200


def test_regulation_updates_come_once_per_period_from_the_cell_gains() -> None:
    gains = ForceLoopGains(period_s=0.02)
    arm, clock = arm_on(spring(5.0), gains=gains)
    assert wait(clock, arm.seek_contact(DOWN, 5.0, 0.4, 20.0)) == MotionState.CONTACT
    t0 = clock.now_s()
    arm.regulate_force(DOWN, 5.0, 10.0)
    clock.sleep_s(1.0)
    sent = np.array([t for t, kind, _ in arm.commands if kind == "speed_linear" and t >= t0])
    # On schedule from the regulation's start (the first update at the next control tick).
    assert sent[0] - t0 <= arm.tick_s + 1e-9
    assert sent.size in (50, 51)
    np.testing.assert_allclose(np.diff(sent[1:]), 0.02, atol=1e-9)


def test_regulation_holds_still_while_the_ft_stream_stalls() -> None:
    """A stall shorter than the guard's stale limit: once the newest sample is two loop periods
    old the loop commands no speed (no pushing on an old force), then carries on."""
    limits = SafetyLimits(**{**LIMITS.__dict__, "ft_stale_ms": 100.0})
    arm, clock = arm_on(spring(20.0), limits=limits)
    assert wait(clock, arm.seek_contact(DOWN, 5.0, 0.4, 20.0)) == MotionState.CONTACT
    motion = arm.regulate_force(DOWN, 10.0, 10.0)
    clock.sleep_s(0.3)
    t_stall = clock.now_s()
    arm.stall_ft(0.08)
    clock.sleep_s(0.08)
    during = [(t, np.asarray(v)) for t, kind, v in arm.commands if kind == "speed_linear" and t > t_stall]
    assert during and all(not v.any() for t, v in during if t > t_stall + 0.02 + 1e-9)
    assert arm.supervisor.counts.stale_holds >= 5
    assert arm.trip() is None
    assert wait(clock, motion) == MotionState.DONE


@pytest.mark.parametrize("stiffness_n_mm", [60.0, 200.0])
def test_the_next_force_level_starts_from_the_contact_s_stiffness(stiffness_n_mm: float) -> None:
    """A probe's force levels (1, 2.5, 4.5, 7, 10 N) on one contact, hard-rubber stiff, with a
    robot's command delay. Each level used to start from the 2 N/mm guess: 30-100x too soft,
    its feed-forward alone drove 5 mm/s into the surface, the probe bounced off it and came
    back at top speed (5-15 N over every target, a force-rate trip at 200 N/mm). From the
    second level on the loop starts from the estimate the first one measured. (The first
    level starts over its target here: the contact search's stop, 6 ms late at 5 mm/s.)"""
    gains = ForceLoopGains()
    arm, clock = arm_on(spring(stiffness_n_mm), command_delay_s=0.006, noise_n=0.04, seed=3)
    assert wait(clock, arm.seek_contact(DOWN, 5.0, 0.4, 20.0)) == MotionState.CONTACT
    levels_n = (1.0, 2.5, 4.5, 7.0, 10.0)
    for k, force_n in enumerate(levels_n):
        arm.ft.read_block()
        motion = arm.regulate_force(DOWN, force_n, 10.0)
        assert wait(clock, motion, timeout_s=10.0) == MotionState.DONE
        reg = arm.supervisor.regulation
        assert reg is not None and reg.stiffness_measured
        assert stiffness_n_mm / 3 <= reg.stiffness_n_mm <= stiffness_n_mm * 3, reg.stiffness_n_mm
        f_ramp = np.convolve(arm.ft.read_block().force_magnitude_n(), np.ones(10) / 10, mode="valid")
        if k > 0:
            assert f_ramp.max() - force_n <= 2 * gains.tolerance_n_at(force_n), (force_n, f_ramp.max())
            assert f_ramp.min() >= 0.8 * levels_n[k - 1], "the probe left the surface"
        clock.sleep_s(0.5)
    assert arm.trip() is None


@pytest.mark.parametrize("stiffness_n_mm", [0.5, 20.0, 60.0, 200.0])
def test_the_first_level_starts_from_the_touch_when_it_is_stiffer_than_the_guess(stiffness_n_mm: float) -> None:
    """The contact search's force rise, from half its threshold to the threshold at its speed,
    measures the touch (sampled at 1 kHz: a 200 N/mm surface rises 1 N per sample and reads
    about half that). The first regulation starts from it when it is stiffer than the guess;
    a softer touch leaves the guess, which errs on the careful side there."""
    gains = ForceLoopGains()
    arm, clock = arm_on(spring(stiffness_n_mm), command_delay_s=0.006, noise_n=0.04, seed=3)
    assert wait(clock, arm.seek_contact(DOWN, 5.0, 0.4, 20.0)) == MotionState.CONTACT
    arm.regulate_force(DOWN, 2.0, 10.0)
    reg = arm.supervisor.regulation
    assert reg is not None
    if stiffness_n_mm > gains.initial_stiffness_n_mm:
        assert reg.stiffness_measured and stiffness_n_mm / 3 <= reg.stiffness_n_mm <= 2 * stiffness_n_mm
    else:
        assert not reg.stiffness_measured and reg.stiffness_n_mm == gains.initial_stiffness_n_mm


def test_a_regulation_carries_the_estimate_only_on_the_same_push() -> None:
    """The estimate goes on to a regulation that directly follows along the same push; after a
    move, a contact search, or along another direction it starts from the guess again. The
    first pair whose force change the noise cannot make replaces the guess; smaller ones
    blend into it."""
    gains = ForceLoopGains()
    sup = ForceSupervisor(gains, LIMITS)
    reg = sup.begin_regulation(DOWN, 5.0, 10.0, 0.0, 0.5) and sup.regulation
    assert reg is not None and not reg.stiffness_measured
    reg.update(0.00, 0.50, 0.0)
    reg.update(0.01, 0.55, 0.005)                # 0.05 N: noise could make it, blended
    assert not reg.stiffness_measured and gains.initial_stiffness_n_mm < reg.stiffness_n_mm < 3.0
    reg.update(0.02, 1.55, 0.015)                # 1 N over 0.01 mm: 100 N/mm, taken whole
    assert reg.stiffness_measured and reg.stiffness_n_mm == pytest.approx(100.0)
    sup.begin_regulation(DOWN, 7.0, 10.0, 0.1, 5.0)
    assert sup.regulation.stiffness_measured and sup.regulation.stiffness_n_mm == pytest.approx(100.0)
    sup.begin_regulation(np.array([0.0, 0.6, -0.8]), 7.0, 10.0, 0.2, 5.0)
    assert sup.regulation.stiffness_n_mm == gains.initial_stiffness_n_mm
    sup.regulation.stiffness_n_mm, sup.regulation.stiffness_measured = 100.0, True
    sup.begin_move(np.zeros(3), np.array([0.0, 0.0, 10.0]))
    sup.begin_regulation(np.array([0.0, 0.6, -0.8]), 7.0, 10.0, 0.3, 5.0)
    assert sup.regulation.stiffness_n_mm == gains.initial_stiffness_n_mm and not sup.regulation.stiffness_measured
    sup.regulation.stiffness_n_mm, sup.regulation.stiffness_measured = 100.0, True
    sup.begin_seek(DOWN, 5.0, 0.4, 10.0, np.zeros(3))
    sup.begin_regulation(DOWN, 7.0, 10.0, 0.4, 5.0)
    assert sup.regulation.stiffness_n_mm == gains.initial_stiffness_n_mm
    # A touch measured by a search goes to the regulation after it along its push only.
    sup.begin_seek(DOWN, 5.0, 0.4, 10.0, np.zeros(3))
    sup.seek_samples(np.array([0.100, 0.101, 0.102]), np.array([0.05, 0.15, 0.45]))
    sup.contact()
    sup.begin_regulation(np.array([0.0, 0.6, -0.8]), 7.0, 10.0, 0.5, 0.45)
    assert sup.regulation.stiffness_n_mm == gains.initial_stiffness_n_mm
    sup.begin_seek(DOWN, 5.0, 0.4, 10.0, np.zeros(3))
    sup.seek_samples(np.array([0.100, 0.101, 0.102]), np.array([0.05, 0.15, 0.45]))
    sup.contact()
    sup.begin_regulation(DOWN, 7.0, 10.0, 0.6, 0.45)
    assert sup.regulation.stiffness_measured and sup.regulation.stiffness_n_mm == pytest.approx(60.0)

# ----------------------------------------------------------------------------- trips and unloading
def _tripped_at_limit(max_force_n: float = 15.0) -> tuple[ScriptedArm, VirtualClock]:
    """A ramp to 25 N through a 15 N limit on a 20 N/mm spring, with a robot's 6 ms command
    delay: the arm stops a little beyond the limit and stays there."""
    limits = SafetyLimits(**{**LIMITS.__dict__, "max_force_n": max_force_n})
    arm, clock = arm_on(spring(20.0), limits=limits, command_delay_s=0.006)
    assert wait(clock, arm.seek_contact(DOWN, 5.0, 0.4, 20.0)) == MotionState.CONTACT
    motion = arm.regulate_force(DOWN, 25.0, 50.0)
    assert wait(clock, motion) == MotionState.TRIPPED
    return arm, clock


def test_the_first_crossing_stops_the_arm_at_its_sample() -> None:
    arm, clock = _tripped_at_limit()
    trip = arm.trip()
    assert trip is not None and trip.kind == "force"
    # The stop was sent at the crossing sample's instant, and no speed command after it.
    stop_t = [t for t, kind, _ in arm.commands if kind == "stop" and t >= trip.t_s - 1e-9]
    assert stop_t and abs(stop_t[0] - trip.t_s) < 1e-9
    assert not [t for t, kind, _ in arm.commands if kind == "speed_linear" and t > trip.t_s]
    assert arm.supervisor.latch is not None and arm.supervisor.counts.trips == 1


def test_a_force_trip_lets_its_own_retract_through() -> None:
    arm, clock = _tripped_at_limit()
    clock.sleep_s(0.05)
    assert arm.ft.read_block().force_magnitude_n()[-1] > 15.0          # still above the limit
    up = Pose(arm.position_mm + np.array([0.0, 0.0, 10.0]), np.eye(3))
    motion = arm.move_linear(up, 5.0, 500.0)
    assert wait(clock, motion) == MotionState.DONE
    assert arm.supervisor.counts.let_through > 0
    assert arm.rearm()                                                   # unloaded: below the hysteresis
    assert arm.supervisor.latch is None


def test_a_motion_into_the_contact_after_a_trip_is_stopped_again() -> None:
    arm, clock = _tripped_at_limit()
    down = Pose(arm.position_mm + np.array([0.0, 0.0, -5.0]), np.eye(3))
    motion = arm.move_linear(down, 5.0, 500.0)
    assert wait(clock, motion) == MotionState.TRIPPED
    sideways = Pose(arm.position_mm + np.array([10.0, 0.0, 0.0]), np.eye(3))
    assert wait(clock, arm.move_linear(sideways, 5.0, 500.0)) == MotionState.TRIPPED
    assert arm.supervisor.counts.let_through == 0


def test_a_retract_whose_force_rises_is_stopped() -> None:
    """Away from the contact, but the force goes on rising (something pulls the probe): more
    than 10 % above the latched peak, the guard stops it."""
    limits = SafetyLimits(**{**LIMITS.__dict__, "max_force_n": 15.0})

    snag = {"from_z_mm": None}

    def force_of(p: np.ndarray) -> np.ndarray:
        below = max(SURFACE_Z_MM - p[2], 0.0)
        # Once caught, the probe is pulled back harder the farther it goes (40 N/mm).
        pulled = 0.0 if snag["from_z_mm"] is None else max(p[2] - snag["from_z_mm"], 0.0) * 40.0
        return np.array([0.0, 0.0, 20.0 * below + pulled])

    arm, clock = arm_on(force_of, limits=limits, command_delay_s=0.006)
    assert wait(clock, arm.seek_contact(DOWN, 5.0, 0.4, 20.0)) == MotionState.CONTACT
    assert wait(clock, arm.regulate_force(DOWN, 25.0, 50.0)) == MotionState.TRIPPED
    snag["from_z_mm"] = float(arm.position_mm[2])
    arm.ft.read_block()
    peak = arm.supervisor.latch.peak_force_n
    up = Pose(arm.position_mm + np.array([0.0, 0.0, 10.0]), np.eye(3))
    assert wait(clock, arm.move_linear(up, 5.0, 500.0)) == MotionState.TRIPPED
    # Stopped at the first sample past 10 % above the peak: the stop then takes the robot's
    # 6 ms delay and its deceleration, at 5 mm/s into 40 N/mm (0.2 N per ms, 1.2 N + 0.2 N).
    f = arm.ft.read_block().force_magnitude_n()
    over = np.flatnonzero(f > 1.1 * max(peak, 15.0))
    assert over.size and f.max() <= 1.1 * max(peak, 15.0) + 1.6, (peak, f.max())


def test_the_verdict_needs_a_known_contact_for_force_kinds() -> None:
    """A force trip with no known contact (a move, before any contact search): nothing says a
    motion unloads it, so the supervisor stops it."""
    sup = ForceSupervisor(ForceLoopGains(), LIMITS)
    sup.begin_move(np.zeros(3), np.array([10.0, 0.0, 0.0]))
    trip = Trip("force", 1.0, 50.0, 45.0, "force 50 N exceeds 45 N")
    assert sup.verdict(trip, 50.0) == Verdict.STOP
    sup.tripped(trip, 50.0, np.array([-50.0, 0.0, 0.0]))
    assert sup.latch is not None and sup.latch.away_base is None       # no contact search yet
    sup.begin_move(np.zeros(3), np.array([-10.0, 0.0, 0.0]))
    assert sup.verdict(trip, 48.0) == Verdict.STOP
    motion = sup.motion
    assert isinstance(motion, SupervisedMotion)
    motion.finish(MotionState.STOPPED)
    assert sup.verdict(trip, 48.0) == Verdict.IGNORE                   # nothing moves: nothing to stop


# ----------------------------------------------------------------------------- the cell file
def _cell_with(tmp_path: Path, block: str) -> Path:
    """The shipped simulated cell with its ``force_loop:`` section replaced by ``block``."""
    text = (ROOT / "config" / "cells" / "sim.yaml").read_text()
    text = text[:text.index("force_loop:\n")] + text[text.index("simulation:\n"):]
    text = text.replace("object:\n  file: ../objects/composite.yaml",
                        f"object:\n  file: {ROOT / 'config' / 'objects' / 'composite.yaml'}")
    path = tmp_path / "cell.yaml"
    path.write_text(text.rstrip("\n") + "\n" + block)
    return path


def test_the_gains_come_from_the_cell_file(tmp_path: Path) -> None:
    cell, _ = load_cell(_cell_with(tmp_path, "force_loop:\n  gain: 0.25\n  period_ms: 12\n"))
    gains = cell.force_loop.gains()
    assert gains.gain == 0.25 and gains.period_s == pytest.approx(0.012)
    shipped, _ = load_cell(ROOT / "config" / "cells" / "loopback.yaml")
    sim, _ = load_cell(ROOT / "config" / "cells" / "sim.yaml")
    assert shipped.force_loop.gains() == sim.force_loop.gains()


@pytest.mark.parametrize("block, line, col, words", [
    ("force_loop:\n  gain: 1.5\n", 2, 9, "less than 1"),
    ("force_loop:\n  period_ms: 0\n", 2, 14, "greater than or equal to 1"),
    ("force_loop:\n  force_window: 40\n", 2, 17, "longer than the loop period"),
    ("force_loop:\n  gian: 0.3\n", 2, 3, "gian"),
])
def test_bad_gains_are_refused_with_their_position(tmp_path: Path, block: str, line: int, col: int, words: str) -> None:
    path = _cell_with(tmp_path, block)
    n_lines = len(path.read_text().splitlines()) - block.count("\n")
    with pytest.raises(InputError) as info:
        load_cell(path)
    err = info.value
    assert err.path == str(path) and err.line == n_lines + line and err.col == col, err.format()
    assert words in err.format()


# ----------------------------------------------------------------------------- one loop
def test_the_simulated_arm_runs_this_loop_with_the_cell_gains() -> None:
    """The in-process cell's contact search and regulation are the supervisor's: its counters
    move, its identity (code hash and gains) is what the arm reports, and it is the identity
    the real cell's hardware process is configured with from the same cell file."""
    cell = make_cell()
    sup = cell.arm.supervisor
    assert isinstance(sup, ForceSupervisor)
    press(cell, (0.0, 0.0, 130.0), (0.0, 0.0, 1.0), 90.0, 5.0, settle_s=0.3)
    assert sup.counts.seeks == 1 and sup.counts.contacts == 1 and sup.counts.regulations == 1
    assert sup.counts.updates >= 30 and sup.counts.settled == 1
    assert cell.arm.identity().extra["force_loop"] == sup.identity()
    spec, _ = load_cell(ROOT / "config" / "cells" / "loopback.yaml")
    cfg = hardware_config(spec, spec.limits.safety())
    assert ForceSupervisor(cfg.force_loop, cfg.limits).identity() == sup.identity()
