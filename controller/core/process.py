"""Child processes that must not outlive the controller (the hardware process, the UR link,
the loopback servers)."""
from __future__ import annotations

import ctypes
import signal
import sys

PR_SET_PDEATHSIG = 1        # <linux/prctl.h>


def set_parent_death_signal() -> None:
    """Linux: have the kernel SIGKILL this process when its parent dies, so an arm's driver
    never keeps running for a controller that was killed (-9). A no-op elsewhere."""
    if not sys.platform.startswith("linux"):
        return
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
