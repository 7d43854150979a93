"""Fuzzing frame recovery: 10,000 streams of valid frames (from the simulator's encoder,
written apart from the decoder), some mutated, with garbage around them."""
from __future__ import annotations

import random

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from elastoprobe.controller.drivers.line_scanner import SYNC, FrameParser, decode_frame
from elastoprobe.sim.servers.scanner_serial import encode_frame

pytestmark = pytest.mark.timeout(240)
# Hypothesis itself costs ~1 ms per example: one property per file keeps each file fast.
MANY = settings(max_examples=10_000, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# ---------------------------------------------------------------- scanner frames
def valid_frame(counter: int, n: int, seed: int, explicit: bool) -> bytes:
    rng = np.random.default_rng(seed)
    z = 100.0 + rng.normal(0, 5, n)
    z[rng.random(n) < 0.1] = np.nan
    x = np.linspace(-20, 20, n) if explicit else None
    return encode_frame(counter, 10_000 + counter, z, x_scale=0.01, x_offset=0.0, z_scale=0.01,
                        z_offset=100.0, x_mm=x)


def mutated_stream(seed: int) -> tuple[list[bytes], bytes, set[int]]:
    """Valid frames, some mutated (bit flips, truncation), with garbage around them.

    Returns the original frames, the stream, and the indexes left intact."""
    rng = random.Random(seed)
    frames = [valid_frame(k, rng.randint(1, 40), rng.getrandbits(32), rng.random() < 0.5)
              for k in range(rng.randint(1, 4))]
    stream = b""
    intact = set()
    for k, fr in enumerate(frames):
        stream += rng.randbytes(rng.randint(0, 40))
        if rng.random() < 0.5:    # things that look like a start: text, sync, a sync with a huge length
            stream += rng.choice([b"OK\n", SYNC, b"\xa5", SYNC + b"\xff\xff\xff\xff", SYNC + b"\x40\x00\x00\x00"])
        action = rng.choice(["keep", "keep", "flip", "truncate"])
        if action == "flip":
            b = bytearray(fr)
            for _ in range(rng.randint(1, 3)):
                b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
            fr = bytes(b)
            if fr == frames[k]:
                intact.add(k)
        elif action == "truncate":
            fr = fr[:rng.randrange(len(fr))]
        else:
            intact.add(k)
        stream += fr
    stream += rng.randbytes(rng.randint(0, 40))
    return frames, stream, intact


@MANY
@given(st.integers(0, 2**64), st.integers(1, 64))
def test_valid_frames_are_recovered_after_garbage_and_mutations(seed: int, chunk: int):
    frames, stream, intact = mutated_stream(seed)
    parser = FrameParser()
    got = []
    for i in range(0, len(stream), chunk):
        got += parser.feed(stream[i:i + chunk])
    for _ in range(len(stream) + 1):       # the line went quiet: give up pending frames, bounded
        if not parser.pending_bytes:
            break
        got += [ev for ev in parser.flush_partial() if not isinstance(ev, str)]
    originals = {decode_frame(fr).frame_counter: decode_frame(fr) for fr in frames}
    # Nothing corrupted gets through: every frame returned is an original, bit for bit.
    for f in got:
        ref = originals[f.frame_counter]
        assert f.timestamp_us == ref.timestamp_us
        np.testing.assert_array_equal(f.z_mm, ref.z_mm)
        np.testing.assert_array_equal(f.x_mm, ref.x_mm)
    # Every intact frame is recovered, in order, whatever came before it.
    counters = [f.frame_counter for f in got]
    assert [c for c in counters if c in intact] == sorted(intact)
    assert set(counters) >= intact
    assert len(counters) == len(set(counters))
