"""Resident memory of a long session: hand freed memory back to the OS between contacts.

An overnight session allocates and frees a contact's worth of arrays (F/T blocks, scanner
bursts, the dent's profiles) thousands of times, and a fault's exception keeps its frames
(and their arrays) alive in reference cycles until a full garbage collection. glibc keeps
freed heap pages for reuse, so without help the process's resident size ratchets up between
the moments something large is released: a faulted 3.3-robot-hour survey in one process
(docs/soak.md, memory) rose 417 -> 440 MB between re-registrations and fell back to 424 MB
at each. What stays resident should be what is live.
"""
from __future__ import annotations

import ctypes
import gc

# Contacts between two releases: a release costs a full collection and a heap walk (tens of
# ms with torch loaded) against a contact's several robot seconds; every 20 contacts is
# ~0.1 % of the wall time, and the heap cannot drift far between two.
CONTACTS_PER_RELEASE = 20


def release_freed_memory() -> None:
    """Collect reference cycles, then return free heap pages to the OS (glibc's
    ``malloc_trim``). No-op for the second part where the C library has no such call."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


class ContactCounter:
    """Calls :func:`release_freed_memory` after every ``every`` contacts."""

    def __init__(self, every: int = CONTACTS_PER_RELEASE) -> None:
        self.every = every
        self._since = 0

    def contact_done(self) -> None:
        self._since += 1
        if self._since >= self.every:
            self._since = 0
            release_freed_memory()
