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

# Contacts between two full releases: a full garbage collection costs ~0.1 s with torch
# loaded (~200k objects), against a contact's several robot seconds; a heap trim costs
# ~0-4 ms and runs after every contact, so what the allocator keeps never builds up.
CONTACTS_PER_COLLECTION = 20


def _libc() -> ctypes.CDLL | None:
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return None


_LIBC = _libc()


def trim_heap() -> None:
    """Return free heap pages to the OS (glibc's ``malloc_trim``); no-op without glibc."""
    if _LIBC is not None and hasattr(_LIBC, "malloc_trim"):
        _LIBC.malloc_trim(0)


def release_freed_memory() -> None:
    """Collect reference cycles, then trim the heap."""
    gc.collect()
    trim_heap()


class ContactCounter:
    """Between contacts: trim the heap after each, collect cycles too after every ``every``."""

    def __init__(self, every: int = CONTACTS_PER_COLLECTION) -> None:
        self.every = every
        self._since = 0

    def contact_done(self) -> None:
        self._since += 1
        if self._since >= self.every:
            self._since = 0
            release_freed_memory()
        else:
            trim_heap()
