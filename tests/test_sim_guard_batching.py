"""The simulator's fast paths change no data: screened guard batches and the unbatched
per-sub-chunk guard give the same bytes and stop at the same virtual sample."""
from __future__ import annotations



from elastoprobe.controller.core.devices import MotionState

from test_sim_helpers import Log, burst, digest, hold, make_cell, press, wait

TOP = (0.0, 0.0, 130.0)
UP = (0.0, 0.0, 1.0)


def _force_limit_run(batch_us: int) -> tuple[str, object, int]:
    cell = make_cell(seed=7)
    cell.world.guard_batch_us = batch_us
    cell.begin_step((7, 1, 0))
    log = Log()
    d, _, _, _ = press(cell, TOP, UP, 60.0, 20.0, log=log, settle_s=1.5)
    scans, _ = burst(cell, 12, log)
    motion = cell.arm.regulate_force(d, 60.0, 100.0)      # the cell's limit is 45 N
    wait(cell, motion, log)
    hold(cell, 0.2, log)
    assert motion.state() == MotionState.TRIPPED
    return digest(log, scans), cell.arm.trip(), cell.world.stats["guard_blocks"]


def test_batched_guard_gives_the_same_bytes_and_the_same_trip_sample():
    batched, trip_b, calls_b = _force_limit_run(200_000)
    single, trip_s, calls_s = _force_limit_run(0)
    assert trip_b is not None and trip_s is not None and trip_b.kind == trip_s.kind == "force"
    assert trip_b.t_s == trip_s.t_s and trip_b.value == trip_s.value
    assert batched == single
    # The batching did happen (otherwise this test compares a path with itself).
    assert calls_b < calls_s / 3


def test_a_spike_after_a_long_batched_hold_stops_at_its_sample():
    def run(batch_us: int):
        cell = make_cell(seed=3)
        cell.world.guard_batch_us = batch_us
        cell.begin_step((3, 1, 0))
        press(cell, TOP, UP, 90.0, 5.0, settle_s=0.5)
        # 170 ms into a hold: screened samples are pending in the batch when the spike comes.
        cell.faults.inject("force_spike", delay_s=0.173)
        log = Log()
        hold(cell, 0.5, log)
        return cell.arm.trip(), digest(log, [])

    (trip_b, digest_b), (trip_s, digest_s) = run(200_000), run(0)
    assert trip_b is not None and trip_s is not None
    assert trip_b.kind == trip_s.kind and trip_b.t_s == trip_s.t_s
    assert digest_b == digest_s
