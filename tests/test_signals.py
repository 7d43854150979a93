"""Operator requests by signal (controller/signals.py): a computation ends at once, a deferred
block (a journal transaction, a contact) is never cut in two, each request interrupts once,
SIGINT twice is a stop."""
from __future__ import annotations

import os
import signal

import pytest

from elastoprobe.controller.signals import OperatorFlags, OperatorInterrupt, deferred_interrupts


@pytest.fixture()
def flags():
    f = OperatorFlags().install()
    yield f
    f.restore()


def _sigint() -> None:
    os.kill(os.getpid(), signal.SIGINT)   # handled in this (the main) thread before kill() returns to Python


def test_a_request_ends_a_computation_at_once(flags: OperatorFlags) -> None:
    done = []
    with pytest.raises(OperatorInterrupt) as info:
        with flags.interruptible():
            _sigint()
            done.append("after")            # never reached: the handler raised in between
    assert done == [] and info.value.stop is False
    assert flags.reason == "pause requested by the operator"


def test_a_deferred_block_finishes_then_the_request_is_raised(flags: OperatorFlags) -> None:
    done = []
    with pytest.raises(OperatorInterrupt):
        with flags.interruptible():
            with deferred_interrupts():
                _sigint()
                done.append("inside")       # the block runs to its end
            done.append("after")            # raised where the block ended
    assert done == ["inside"]


def test_outside_a_computation_a_request_only_sets_flags(flags: OperatorFlags) -> None:
    _sigint()
    assert flags.pause_requested and not flags.stop_now
    _sigint()
    assert flags.stop_now and flags.reason == "stopped by the operator"


def test_each_request_interrupts_once(flags: OperatorFlags) -> None:
    with pytest.raises(OperatorInterrupt):
        with flags.interruptible():
            _sigint()
    flags.acknowledge()
    with flags.interruptible():              # the same request does not interrupt the saving
        pass
    with pytest.raises(OperatorInterrupt) as info:
        with flags.interruptible():
            _sigint()                        # a second one does, and it is a stop
    assert info.value.stop is True


def test_a_request_before_the_computation_interrupts_it_at_its_start(flags: OperatorFlags) -> None:
    os.kill(os.getpid(), signal.SIGTERM)
    with pytest.raises(OperatorInterrupt):
        with flags.interruptible():
            pytest.fail("the computation should not start")
