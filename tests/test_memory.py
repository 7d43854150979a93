"""Resident memory between contacts (controller/memory.py): what is freed goes back to the OS."""
from __future__ import annotations

import subprocess
import sys

import pytest

from elastoprobe.controller import memory
from elastoprobe.controller.memory import ContactCounter

# A child with a clean heap: contact-sized arrays held in reference cycles (as a fault's
# exception holds its frames), dropped; then the release. Prints RSS (MB) at the three moments.
_CHILD = """
import gc, numpy as np
from elastoprobe.controller.memory import release_freed_memory
def rss():
    for line in open('/proc/self/status'):
        if line.startswith('VmRSS'):
            return int(line.split()[1]) / 1024
gc.disable()
base = rss()
class Frame:
    pass
for _ in range(4000):
    a, b = Frame(), Frame()
    a.other, b.other = b, a
    a.data = np.random.rand(4000)     # 32 kB: heap, not mmap
    del a, b
held = rss()
release_freed_memory()
print(base, held, rss())
"""


def test_release_returns_arrays_held_by_dropped_cycles_to_the_os() -> None:
    out = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True, check=True, timeout=120)
    base, held, after = (float(x) for x in out.stdout.split())
    assert held - base > 80.0, (base, held)            # 4000 x 32 kB kept alive by their cycles
    assert after - base < 0.25 * (held - base), (base, held, after)


def test_the_heap_is_trimmed_after_every_contact_and_cycles_collected_every_so_many(
        monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[str] = []
    monkeypatch.setattr(memory, "release_freed_memory", lambda: calls.append("collect"))
    monkeypatch.setattr(memory, "trim_heap", lambda: calls.append("trim"))
    counter = ContactCounter(every=3)
    for _ in range(7):
        counter.contact_done()
    assert calls == ["trim", "trim", "collect", "trim", "trim", "collect", "trim"]
