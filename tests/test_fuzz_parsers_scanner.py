"""Fuzzing the scanner frame decoder and stream parser: 10,000 inputs; only ProtocolError
may escape, and the parse does not depend on how the bytes are chunked."""
from __future__ import annotations

import struct
import zlib

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from elastoprobe.controller.core.errors import ProtocolError
from elastoprobe.controller.drivers.line_scanner import MAX_POINTS, SYNC, FrameParser, decode_frame

pytestmark = pytest.mark.timeout(240)
# Hypothesis itself costs ~1 ms per example: one property per file keeps each file fast.
MANY = settings(max_examples=10_000, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def frame_like(kind: int, blob: bytes) -> bytes:
    """Random bytes, or random payloads behind a real header with a correct CRC (then n,
    flags and scales are whatever the blob says)."""
    if kind == 0:
        return blob
    payload = blob[:120] if kind == 1 else (blob + bytes(32))[:32] + blob[32:]
    length = struct.pack("<I", len(payload))
    return SYNC + length + payload + struct.pack("<I", zlib.crc32(length + payload))


@MANY
@given(st.integers(0, 2), st.binary(max_size=300), st.integers(1, 7))
def test_frame_decoder_and_parser_raise_only_protocol_error(kind: int, blob: bytes, chunk: int):
    data = frame_like(kind, blob)
    try:
        frame = decode_frame(data)
    except ProtocolError:
        pass
    else:
        n = frame.z_mm.shape[0]
        assert 1 <= n <= MAX_POINTS and frame.x_mm.shape == (n,)
    whole = FrameParser()
    frames = whole.feed(data) + [ev for ev in whole.flush_partial() if not isinstance(ev, str)]
    # Chunking does not change the result.
    pieces = FrameParser()
    got = []
    for i in range(0, len(data), chunk):
        got += pieces.feed(data[i:i + chunk])
    got += [ev for ev in pieces.flush_partial() if not isinstance(ev, str)]
    assert [f.frame_counter for f in got] == [f.frame_counter for f in frames]
    assert pieces.counters == whole.counters
