"""Fuzzing the ATI RDT and READCALINFO parsers: 10,000 inputs; only ProtocolError may escape."""
from __future__ import annotations

import random
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from elastoprobe.controller.drivers.ati_netft import (
    CALINFO_REPLY, RDT_RECORD, parse_calinfo, parse_rdt_datagram)
from elastoprobe.controller.core.errors import ProtocolError

pytestmark = pytest.mark.timeout(240)
# Hypothesis itself costs ~1 ms per example: one property per file keeps each file fast.
MANY = settings(max_examples=10_000, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# ---------------------------------------------------------------- ATI RDT / calinfo
# Few hypothesis draws per example (a kind, a seed, a blob), the structure built from the
# seed: generation then costs little and 10,000 examples stay fast.
def rdt_like(kind: int, seed: int, blob: bytes) -> bytes:
    """Random bytes, often near the valid sizes and with real headers in them."""
    rng = random.Random(seed)
    if kind == 0:
        return blob
    cut = rng.randint(-3, 3)
    if kind == 1:
        recs = b"".join(RDT_RECORD.pack(rng.getrandbits(32), rng.getrandbits(32), rng.getrandbits(32),
                                        *(rng.getrandbits(32) - 2**31 for _ in range(6)))
                        for _ in range(rng.randint(1, 6)))
    elif kind == 2:
        recs = struct.pack(">HBBII", rng.choice([0x1234, 0x3412, 0]), rng.choice([0, 1, 2, 6, 7, 255]),
                           rng.choice([0, 1, 3, 6, 7, 255]), rng.choice([0, 1, rng.getrandbits(32)]),
                           rng.choice([0, 1, rng.getrandbits(32)])) + (blob + bytes(12))[:12]
    else:
        return (blob + bytes(24))[:24]
    return recs[:len(recs) + cut] if cut < 0 else recs + bytes(cut)


@MANY
@given(st.integers(0, 3), st.integers(0, 2**32), st.binary(max_size=200))
def test_rdt_and_calinfo_parsers_raise_only_protocol_error(kind: int, seed: int, blob: bytes):
    data = rdt_like(kind, seed, blob)
    try:
        records = parse_rdt_datagram(data)
    except ProtocolError:
        assert len(data) == 0 or len(data) % RDT_RECORD.size != 0
    else:
        assert len(data) > 0 and len(records) == len(data) // RDT_RECORD.size
        for rec, fields in zip(records, RDT_RECORD.iter_unpack(data)):
            assert (rec.rdt_sequence, rec.ft_sequence, rec.status) == fields[:3]
            assert rec.counts == fields[3:]
    try:
        cal = parse_calinfo(data)
    except ProtocolError:
        pass
    else:
        assert len(data) == CALINFO_REPLY.size and data[:2] == b"\x12\x34"
        assert cal.counts_per_force > 0 and cal.counts_per_torque > 0
        assert np.isfinite(cal.newtons_per_count) and np.isfinite(cal.newton_meters_per_count)
