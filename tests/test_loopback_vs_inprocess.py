"""Issue #5, "Done when" (and issue #17's one force loop): the loopback plan on the real drivers (ur_rtde 1.6.5, Net F/T over
UDP, the scanner over a socket, the world served in real time) and the same plan, seed and
cell file on the in-process simulated cell (``--dry-run``) agree step by step: the held force
and the dent under the tip within 3 sigma/sqrt(N) (sigma: per-scan standard deviation within
the step, pooled over the two runs; N: scans per step). bench/loopback_vs_inprocess.py does
the work and documents the quantities; these tests run it on their own 127.0.0.x.

The shipped loopback plan gives its probe point, so both runs press the same place (a plan
whose neural gas places the targets from each run's own cloud pressed points 1-6 mm apart, or
even a different number of them).

The bound is 2.12 standard errors of the difference, so two runs of one system exceed it on
3.4 % of steps by chance; a test that wanted every step inside would fail a perfect system
about a quarter of the time with 16 comparisons. The tests instead ask how likely the
number of exceedances is between identical systems (``p_value``, binomial) and fail below
P_MIN: at most 2 of 8 steps may exceed per quantity (0.2 % false alarms).

- Without the scanner's burst-correlated noise (a diagnostic copy of the object with
  ``noise_corr_floor_mm: 0``), the literal bound holds: this judges the transports and drivers.
- With the shipped noise the literal bound is NOT met for depth, between in-process runs
  either (seeds 2-7 vs 1 on the same point: 3-6 of 8 depth steps within, z up to 8; with the
  floor off 7-8 of 8): every profile of a burst shares one smooth error and the reference burst
  another, which move the step mean without showing in the within-step sigma. Declared (xfail).
- With the shipped noise, the loopback run differs from the in-process one by no more than
  in-process runs differ from each other (3 sqrt(2) sd, sd of the step mean over in-process
  seeds 1-7: its real standard error).

Real time (about a minute per loopback run, about 10 s per in-process run), so slow; fixed
ur_rtde ports, so loopback.
"""
from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
REFERENCE_SEEDS = (2, 3, 4, 5, 6, 7)
P_MIN = 0.005


def _compare_module():
    from bench import loopback_vs_inprocess

    return loopback_vs_inprocess


def _run_pair(base: Path, host: str, corr_floor_mm: float | None, reference_seeds: tuple[int, ...]) -> dict:
    cmp = _compare_module()
    plan, cell = cmp.prepare_configs(base, host, ROOT / "config" / "plans" / "loopback.yaml",
                                     ROOT / "config" / "cells" / "loopback.yaml", corr_floor_mm)
    lb = cmp.run_session(plan, cell, base / "loopback", 1, False, 900.0)
    ip = cmp.run_session(plan, cell, base / "in_process", 1, True, 900.0)
    assert lb["exit_code"] == 0, lb["stderr_tail"]
    assert ip["exit_code"] == 0, ip["stderr_tail"]
    refs = []
    for seed in reference_seeds:
        run = cmp.run_session(plan, cell, base / f"in_process_seed{seed}", seed, True, 900.0)
        assert run["exit_code"] == 0, (seed, run["stderr_tail"])
        refs.append(base / f"in_process_seed{seed}")
    result = cmp.compare_sessions(base / "loopback", base / "in_process")
    if refs:
        cmp.add_reference(result, base / "in_process", refs)
    # Survey at 90 deg and characterization at 45, 90 and 135 deg, two forces each: all done.
    assert result["steps_loopback"] == result["steps_in_process"] == result["steps_compared"] == 8
    # One force loop: both runs journaled the same supervisor (code hash and gains), and each
    # reports how its force levels went.
    loops = result["force_loop"]
    assert loops["same_supervisor"], (loops["loopback"]["identity"], loops["in_process"]["identity"])
    for side in ("loopback", "in_process"):
        assert loops[side]["levels"] == 8
        assert loops[side]["overshoot_n"]["n"] == 8 and loops[side]["held_error_n"]["n"] == 8
    for row in result["steps"]:
        assert row["target_offset_mm"] == 0.0, row
        # A step whose scans all read one F/T sample (a time-mapping fault) has zero spread:
        # the comparison would be meaningless, so it is a failure in itself.
        assert row["force"]["sigma_lb"] > 0 and row["force"]["sigma_ip"] > 0, row
    return result


@pytest.fixture(scope="module")
def compared(tmp_path_factory: pytest.TempPathFactory) -> dict:
    return _run_pair(tmp_path_factory.mktemp("loopback_vs_inprocess"), "127.0.0.193", None, REFERENCE_SEEDS)


@pytest.fixture(scope="module")
def compared_without_burst_noise(tmp_path_factory: pytest.TempPathFactory) -> dict:
    return _run_pair(tmp_path_factory.mktemp("loopback_vs_inprocess_no_burst_noise"), "127.0.0.194", 0.0, ())


def _unlikely(summary: dict) -> list[tuple[str, dict]]:
    return [(q, s) for q, s in summary.items() if s["p_value"] < P_MIN]


@pytest.mark.slow
@pytest.mark.loopback
@pytest.mark.timeout(1800)
def test_without_burst_noise_loopback_steps_agree_within_3_sigma_over_sqrt_n(compared_without_burst_noise: dict) -> None:
    result = compared_without_burst_noise
    assert not _unlikely(result["literal_exceedances"]), (result["literal_exceedances"], result["steps"])


@pytest.mark.slow
@pytest.mark.loopback
@pytest.mark.timeout(1800)
def test_loopback_steps_differ_from_in_process_no_more_than_in_process_runs_do(compared: dict) -> None:
    assert not _unlikely(compared["between_runs_exceedances"]), (compared["between_runs_exceedances"],
                                                                 compared["steps"])


@pytest.mark.slow
@pytest.mark.loopback
@pytest.mark.timeout(1800)
@pytest.mark.xfail(strict=False, reason="known gap (issue 5): with the scanner's burst-correlated noise the literal "
                   "3 sigma/sqrt(N) bound understates a step's depth error; two in-process runs on the same point miss "
                   "it too (3-6 of 8 depth steps within); see the module docstring")
def test_loopback_steps_agree_with_the_in_process_cell_within_3_sigma_over_sqrt_n(compared: dict) -> None:
    assert not _unlikely(compared["literal_exceedances"]), (compared["literal_exceedances"], compared["steps"])
