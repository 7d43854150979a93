"""Operator requests by signal (controller/signals.py): a computation ends at once, a deferred
block (a journal transaction, a contact) is never cut in two, each request interrupts once,
SIGINT twice is a stop."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from elastoprobe.controller.signals import REASSERT_S, OperatorFlags, OperatorInterrupt, deferred_interrupts


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


def test_two_sigints_during_one_long_c_call_are_a_stop(flags: OperatorFlags) -> None:
    """Python makes one handler call for signals that arrive while the main thread is inside
    one C call (a numpy or torch operation); a double SIGINT, 50 ms apart as ``elastoprobe
    stop`` sends it, must still be a stop. The long C call here is a blocking read(2) through
    ctypes, restarted after each signal (SA_RESTART), that ends when the sender writes."""
    import ctypes
    import time

    libc = ctypes.CDLL(None, use_errno=True)
    r, w = os.pipe()
    signal.siginterrupt(signal.SIGINT, False)       # restart the read: no return to Python between

    def press_twice_then_release() -> None:
        time.sleep(0.1)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        os.write(w, b"x")

    sender = threading.Thread(target=press_twice_then_release)
    try:
        sender.start()
        buf = ctypes.create_string_buffer(1)
        assert libc.read(r, buf, 1) == 1            # both signals land in here
        sender.join()
        assert flags.interrupts == 2 and flags.stop_now and flags.reason == "stopped by the operator"
    finally:
        os.close(r)
        os.close(w)


def test_a_sigint_and_a_sigterm_in_one_c_call_count_once_each(flags: OperatorFlags) -> None:
    """Two handler calls (one per signal number) drain one pipe: nothing is counted twice."""
    # Sent to the main thread itself: a signal sent to the process may be taken by another
    # thread that does not block it, and its handler would then run after the assert.
    main_thread = threading.main_thread().ident
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        signal.pthread_kill(main_thread, signal.SIGINT)
        signal.pthread_kill(main_thread, signal.SIGTERM)
    finally:
        # Both are delivered on unblocking; pthread_sigmask runs their handlers before it returns.
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    assert flags.requests == 2 and flags.interrupts == 1 and not flags.stop_now


def test_restore_gives_back_the_handlers_and_the_wakeup_fd() -> None:
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    r, w = os.pipe()
    os.set_blocking(w, False)
    previous = signal.set_wakeup_fd(w)
    try:
        outer = OperatorFlags().install()
        inner = OperatorFlags().install()     # the session inside the CLI's flags
        inner.restore()
        assert signal.getsignal(signal.SIGINT) == outer._on_signal
        outer.restore()
        assert {s: signal.getsignal(s) for s in before} == before
        assert signal.set_wakeup_fd(w) == w   # ours again, untouched
    finally:
        signal.set_wakeup_fd(previous)
        os.close(r)
        os.close(w)


def test_off_the_main_thread_install_takes_nothing_and_restore_is_harmless() -> None:
    import threading

    before = signal.getsignal(signal.SIGINT)
    errors: list[BaseException] = []

    def embedded() -> None:
        try:
            f = OperatorFlags().install()
            assert f._wakeup is None and not f._previous
            f.restore()
        except BaseException as exc:    # noqa: BLE001 - reported to the main thread
            errors.append(exc)

    t = threading.Thread(target=embedded)
    t.start()
    t.join()
    assert errors == [] and signal.getsignal(signal.SIGINT) is before


def test_an_interrupt_that_library_code_swallows_is_raised_again(flags: OperatorFlags) -> None:
    """trimesh imports its optional modules under ``except BaseException``: a SIGTERM during
    that import was swallowed, and ``check`` and ``evaluate`` ran on to exit 0."""
    swallowed, ticks = [], 0
    with pytest.raises(OperatorInterrupt):
        with flags.interruptible():
            try:
                _sigint()
            except BaseException as exc:      # what the library does
                swallowed.append(exc)
            while ticks < 2000:               # the rest of the computation: far longer than REASSERT_S
                time.sleep(0.01)
                ticks += 1
    assert len(swallowed) == 1 and isinstance(swallowed[0], OperatorInterrupt)
    assert ticks < 2000                       # raised again while it still ran, not only at its end
    assert not flags.stop_now                 # the same request, not a second one


def _sigint_swallowed() -> None:
    try:
        _sigint()
    except BaseException:                     # what trimesh's optional imports do
        pass


def test_a_swallowed_interrupt_is_raised_when_the_computation_ends(flags: OperatorFlags) -> None:
    with pytest.raises(OperatorInterrupt):
        with flags.interruptible():
            _sigint_swallowed()
    assert flags.requests == 1


def test_an_acknowledged_request_is_not_raised_again(flags: OperatorFlags) -> None:
    with flags.interruptible():
        try:
            _sigint()
        except OperatorInterrupt:
            flags.acknowledge()               # what a pausing session does
        time.sleep(3 * REASSERT_S)


_EARLY = """
import importlib.abc, os, signal, sys
class Hook(importlib.abc.MetaPathFinder):
    # the signal arrives while the command's modules are still being imported
    def find_spec(self, name, path, target=None):
        if name == {module!r}:
            os.kill(os.getpid(), signal.{signal})
        return None
sys.meta_path.insert(0, Hook())
from elastoprobe.controller.cli import main
sys.exit(main({argv!r}))
"""


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("command,code", [("check", 3), ("run", 1)])
def test_a_signal_before_the_command_took_the_signals_ends_it_cleanly(sig: str, command: str, code: int,
                                                                      tmp_path) -> None:
    """SIGINT in the first fraction of a second (the imports) was a KeyboardInterrupt traceback;
    SIGTERM there killed the process by the signal (exit -15)."""
    plan = Path(__file__).parent / "data" / "minimal_plan.yaml"
    argv = [command, str(plan)] + (["--out", str(tmp_path / "s"), "--quiet"] if command == "run" else [])
    script = _EARLY.format(module="elastoprobe.controller.journal", signal=sig, argv=argv)
    child = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert child.returncode == code, (child.returncode, child.stderr[-2000:])
    assert "Traceback" not in child.stderr
    assert f"elastoprobe {command}: interrupted before it started; nothing was written" in child.stderr
    assert not (tmp_path / "s").exists()


def test_a_signal_as_the_command_line_exits_keeps_its_exit_code(tmp_path) -> None:
    """SIGTERM at the moment ``status`` had printed everything and was exiting killed it by the
    signal (exit -15): the handler had been handed back to the default as main() returned."""
    out = tmp_path / "d.md"
    script = ("import os, signal, sys, time\n"
              "from elastoprobe.controller.cli import main\n"
              f"sys.argv = ['elastoprobe', 'diagram', '--out', {str(out)!r}]\n"
              "code = main()\n"
              "for sig in (signal.SIGTERM, signal.SIGINT):\n"
              "    os.kill(os.getpid(), sig)\n"
              "time.sleep(0.2)\n"
              "sys.exit(code)\n")
    child = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert child.returncode == 0, (child.returncode, child.stderr[-2000:])
    assert "Traceback" not in child.stderr and out.is_file()


def test_the_timer_it_borrows_is_given_back() -> None:
    """The process has one real-time timer (a test runner's timeout uses it): re-raising a
    swallowed interrupt borrows it and gives it back, with the time that was left."""
    signal.setitimer(signal.ITIMER_REAL, 100.0)
    flags = OperatorFlags().install()
    try:
        with pytest.raises(OperatorInterrupt):
            with flags.interruptible():
                _sigint_swallowed()
                time.sleep(3 * REASSERT_S)
        left, _ = signal.getitimer(signal.ITIMER_REAL)
        assert 90.0 < left <= 100.0
    finally:
        flags.restore()
    left, _ = signal.getitimer(signal.ITIMER_REAL)
    signal.setitimer(signal.ITIMER_REAL, 0.0)
    assert 90.0 < left <= 100.0
