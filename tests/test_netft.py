"""ATI Net F/T driver against the simulated device over real UDP/TCP on 127.0.0.1.

The server logs every record it put on the wire (in wire order) and every record it
dropped; the client's accounting is judged against an oracle computed from that log.
"""
from __future__ import annotations

import socket
import struct
import time
from typing import Callable

import numpy as np
import pytest

from elastoprobe.controller.drivers.ati_netft import (
    CalInfo, NetFTClient, NetFTCounters, RDT_RECORD, SequenceTracker, build_rdt_request,
    parse_calinfo, parse_rdt_datagram, read_calinfo)
from elastoprobe.controller.core.devices import ForceTorqueSensor
from elastoprobe.controller.core.errors import DeviceTimeout, ProtocolError
from elastoprobe.sim.servers.netft_server import (
    NetFTFaults, NetFTServer, constant_source, ramp_source)

# Real transports on loopback, timed: never beside other tests (the default run's second part).
pytestmark = [pytest.mark.timeout(60), pytest.mark.loopback]
CPF = 1_000_000
CPT = 1_000_000


def wait_until(cond: Callable[[], bool], limit_s: float = 10.0) -> bool:
    """Poll ``cond`` until true or ``limit_s`` passed (bounded)."""
    end = time.monotonic() + limit_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.005)
    return cond()


@pytest.fixture
def make_server(request: pytest.FixtureRequest):
    servers: list[NetFTServer] = []

    def factory(**kw) -> NetFTServer:
        kw.setdefault("source", ramp_source(CPF))
        srv = NetFTServer(max_lifetime_s=50.0, **kw).start()
        servers.append(srv)
        return srv

    yield factory
    for srv in servers:
        srv.stop()


@pytest.fixture
def make_client(request: pytest.FixtureRequest):
    clients: list[NetFTClient] = []

    def factory(srv: NetFTServer, **kw) -> NetFTClient:
        c = NetFTClient("127.0.0.1", srv.rdt_port, srv.calinfo_port, rate_hz=srv.rate_hz, **kw)
        clients.append(c)
        return c

    yield factory
    for c in clients:
        c.close()


def wait_more(client: NetFTClient, k: int) -> None:
    """Wait until ``k`` more records have been delivered."""
    target = client.counters().received + k
    assert wait_until(lambda: client.counters().received >= target)


def collect_finite(srv: NetFTServer, client: NetFTClient, n: int) -> "object":
    """Ask for exactly ``n`` records and gather every delivered record."""
    client.start(sample_count=n)
    assert wait_until(lambda: srv.log.requests and not srv.streaming and len(srv.log.transmitted) +
                      len(srv.log.dropped) >= n)
    # The stream has ended on the device; wait for the last datagrams to be read.
    assert wait_until(lambda: client.last_sample_age_s() > 0.2)
    return client.read_block()


def oracle(transmitted: list[int]) -> dict[str, object]:
    """What a correct client delivers from records arriving in ``transmitted`` order."""
    delivered, seen = [], set()
    late = dup = 0
    best = None
    for s in transmitted:
        if s in seen:
            dup += 1
            continue
        seen.add(s)
        if best is None or s > best:
            delivered.append(s)
            best = s
        else:
            late += 1
    return {"delivered": delivered, "late": late, "dup": dup}


# ---------------------------------------------------------------- calibration over TCP
def test_calinfo_is_read_from_the_device_and_scales_the_counts(make_server, make_client):
    cpf, cpt = 1_234_567, 7_654_321
    src = constant_source([1.0, -2.0, 3.0], [0.1, 0.2, -0.3], cpf, cpt)
    srv = make_server(source=src, counts_per_force=cpf, counts_per_torque=cpt, force_units=1,
                      torque_units=2)
    cal = read_calinfo("127.0.0.1", srv.calinfo_port)
    assert (cal.counts_per_force, cal.counts_per_torque, cal.unit_names) == (cpf, cpt, ("lbf", "lbf-ft"))
    client = make_client(srv, autostart=False)
    assert client.identity().extra["counts_per_force"] == cpf
    block = collect_finite(srv, client, 50)
    assert len(block) == 50
    # counts = value x cpf; the client converts lbf -> N and lbf-ft -> N*m.
    np.testing.assert_allclose(block.force_n, np.tile([1.0, -2.0, 3.0], (50, 1)) * 4.4482216152605, rtol=1e-6)
    np.testing.assert_allclose(block.torque_nm, np.tile([0.1, 0.2, -0.3], (50, 1)) * 1.3558179483314004,
                               rtol=1e-5)


def test_calinfo_silent_device_times_out(make_server):
    srv = make_server(faults=NetFTFaults(calinfo_silent=True))
    with pytest.raises(DeviceTimeout):
        read_calinfo("127.0.0.1", srv.calinfo_port, timeout_s=0.3)
    assert srv.log.calinfo_requests == 1


# ---------------------------------------------------------------- clean stream
@pytest.mark.parametrize("buffered", [False, True])
def test_clean_stream_delivers_every_record_in_order(make_server, make_client, buffered):
    srv = make_server(rate_hz=1000.0, records_per_datagram=10)
    client = make_client(srv, autostart=False, buffered=buffered)
    assert isinstance(client, ForceTorqueSensor)
    block = collect_finite(srv, client, 800)
    assert len(block) == 800
    np.testing.assert_array_equal(block.seq, np.arange(1, 801))
    # The ramp puts the sample index in Fx: order and identity of every record.
    np.testing.assert_array_equal(np.rint(block.force_n[:, 0] * CPF), np.arange(800))
    np.testing.assert_allclose(block.force_n[:, 2], -5.0)
    c = client.counters()
    assert (c.received, c.lost, c.reordered, c.duplicated, c.bad_datagrams) == (800, 0, 0, 0, 0)
    # Times come from the sequence: spaced at 1/rate (the anchor may creep 200 ppm), never
    # backwards, whatever the arrival jitter -- also for the ten records that share one
    # buffered datagram (arrival stamps would give them all the same time).
    assert np.all(np.diff(block.t_s) >= 0)
    assert np.median(np.diff(block.t_s)) == pytest.approx(1e-3, rel=2.5e-4)
    assert client.read_block().t_s.size == 0        # nothing twice


@pytest.mark.parametrize("buffered", [False, True])
def test_loss_reordering_duplicates_are_accounted_against_the_wire_log(make_server, make_client, buffered):
    faults = NetFTFaults(loss_fraction=0.05, reorder_fraction=0.08, duplicate_fraction=0.06)
    srv = make_server(rate_hz=2000.0, records_per_datagram=4, faults=faults, seed=7)
    client = make_client(srv, autostart=False, buffered=buffered)
    n = 3000
    block = collect_finite(srv, client, n)
    expect = oracle(srv.log.transmitted)
    assert expect["late"] > 10 and expect["dup"] > 10 and len(srv.log.dropped) > 10   # faults did happen
    np.testing.assert_array_equal(block.seq, np.asarray(expect["delivered"], dtype=np.int64))
    assert np.all(np.diff(block.seq) > 0)                       # order preserved, no duplicates
    np.testing.assert_array_equal(np.rint(block.force_n[:, 0] * CPF), block.seq - 1)   # the right payload
    c = client.counters()
    assert c.received == len(block)
    assert c.duplicated == expect["dup"]
    assert c.reordered == expect["late"]
    # Every sequence number in the span is exactly one of delivered / lost / late.
    lo, hi = min(srv.log.transmitted), max(srv.log.transmitted)
    assert c.received + c.lost + c.reordered == hi - lo + 1
    never_arrived = set(range(lo, hi + 1)) - set(srv.log.transmitted)
    assert c.lost == len(never_arrived)


def test_sequence_wraparound_on_the_wire(make_server, make_client):
    first = (1 << 32) - 150
    srv = make_server(rate_hz=2000.0, first_rdt_sequence=first,
                      faults=NetFTFaults(loss_fraction=0.03), seed=3)
    client = make_client(srv, autostart=False)
    block = collect_finite(srv, client, 400)
    assert np.all(np.diff(block.seq) > 0)
    assert block.seq[0] == first and block.seq[-1] > (1 << 32)     # unwrapped past 2^32
    def unwrap(s: int) -> int:
        return s if s >= first else s + (1 << 32)

    sent = [unwrap(s) for s in srv.log.transmitted]
    np.testing.assert_array_equal(block.seq, np.asarray(sent, dtype=np.int64))
    dropped_inside = [s for s in map(unwrap, srv.log.dropped) if s < block.seq[-1]]
    assert len(dropped_inside) > 0
    assert client.counters().lost == len(dropped_inside)


# ---------------------------------------------------------------- stale, frozen, status
def test_stalled_stream_is_stale_then_resumes_without_loss(make_server, make_client):
    faults = NetFTFaults()
    srv = make_server(rate_hz=1000.0, faults=faults)
    client = make_client(srv)
    assert wait_until(lambda: client.counters().received > 100)
    faults.stalled = True
    before = client.read_block()
    assert wait_until(lambda: client.last_sample_age_s() > 0.3)
    stalled = client.read_block()
    faults.stalled = False
    assert wait_until(lambda: client.last_sample_age_s() < 0.05)
    assert wait_until(lambda: client.counters().received > len(before) + len(stalled) + 100)
    after = client.read_block()
    seq = np.concatenate([before.seq, stalled.seq, after.seq])
    np.testing.assert_array_equal(seq, np.arange(seq[0], seq[0] + seq.size))   # a stall is not loss
    t = np.concatenate([before.t_s, stalled.t_s, after.t_s])
    assert np.max(np.diff(t)) > 0.25      # the timebase shows the pause instead of hiding it
    assert client.counters().lost == 0 and client.counters().reanchors >= 1
    assert client.counters().longest_gap_s > 0.25     # the client saw the silence ...
    assert srv.log.longest_late_s < 0.1                # ... that the server was told to make


def test_a_starved_server_logs_how_late_it_sent_and_catches_up(make_server, make_client):
    """The server's thread held up (here: its sample source blocks 0.2 s once) is not an
    injected fault: the log says how late the records went out, and the client's longest
    gap shows the same silence; the burst that follows loses nothing."""
    ramp = ramp_source(CPF)
    calls = {"n": 0}

    def slow_once(n: int):
        calls["n"] += 1
        if calls["n"] == 300:
            time.sleep(0.2)
        return ramp(n)

    srv = make_server(source=slow_once, rate_hz=1000.0)
    client = make_client(srv)
    assert wait_until(lambda: calls["n"] > 320 and client.counters().received > 600)
    assert srv.log.longest_late_s > 0.15
    assert client.counters().longest_gap_s > 0.15
    assert client.counters().lost == 0


def test_frozen_values_and_status_bits_pass_through(make_server, make_client):
    faults = NetFTFaults()
    srv = make_server(rate_hz=1000.0, faults=faults)
    client = make_client(srv)
    assert wait_until(lambda: client.counters().received > 50)
    faults.frozen, faults.status_bits = True, 0x80010000
    time.sleep(0.05)
    client.read_block()
    wait_more(client, 200)
    block = client.read_block()
    assert len(block) > 20
    assert np.all(block.status == 0x80010000)
    assert np.ptp(block.force_n[:, 0]) == 0.0            # values frozen ...
    assert np.all(np.diff(block.seq) == 1)               # ... while the sequence runs on


# ---------------------------------------------------------------- bias
def test_software_tare_and_device_bias(make_server, make_client):
    src = constant_source([2.0, -1.0, 4.0], [0.05, 0.0, 0.01], CPF, CPT, noise_counts=2000.0, seed=1)
    srv = make_server(source=src, rate_hz=1000.0)
    client = make_client(srv, tare_window_s=0.2)
    assert wait_until(lambda: client.counters().received > 300)
    client.tare()
    np.testing.assert_allclose(client.bias()[:3], [2.0, -1.0, 4.0], atol=0.003)   # noise 2 mN / sqrt(200)
    client.read_block()
    wait_more(client, 500)
    block = client.read_block()
    np.testing.assert_allclose(block.force_n.mean(axis=0), 0.0, atol=0.003)
    # Device bias: the server zeroes its own output; the client drops its software bias.
    client.device_bias()
    assert wait_until(lambda: srv.log.bias_commands == 1)
    assert np.all(client.bias() == 0.0)
    time.sleep(0.05)
    client.read_block()
    wait_more(client, 500)
    block = client.read_block()
    np.testing.assert_allclose(block.force_n.mean(axis=0), 0.0, atol=0.01)


def test_tare_without_data_raises(make_server, make_client):
    srv = make_server(faults=NetFTFaults(stalled=True))
    client = make_client(srv)
    with pytest.raises(DeviceTimeout):
        client.tare()


# ---------------------------------------------------------------- ownership, bad datagrams, close
def test_newest_requester_owns_the_stream_and_strangers_are_ignored(make_server, make_client):
    srv = make_server(rate_hz=1000.0)
    first = make_client(srv)
    assert wait_until(lambda: first.counters().received > 50)
    # A stranger sends well-formed records straight at the client's port: not from the device.
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        before = first.counters().received
        stranger.sendto(RDT_RECORD.pack(10**6, 0, 0, 1, 2, 3, 4, 5, 6), first._sock.getsockname())
        second = make_client(srv)
        assert wait_until(lambda: second.counters().received > 50)
        assert wait_until(lambda: first.last_sample_age_s() > 0.2)
        late = first.read_block()
        assert not np.any(late.seq >= 10**6)
        assert first.counters().bad_datagrams == 0
        assert first.counters().received >= before
    finally:
        stranger.close()


def test_bad_datagrams_are_counted_and_the_stream_goes_on(make_server):
    # The calibration comes from the simulator; the RDT "device" is a raw socket here.
    srv = make_server()
    fake = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    fake.bind(("127.0.0.1", 0))
    fake.settimeout(5.0)
    client = NetFTClient("127.0.0.1", fake.getsockname()[1], srv.calinfo_port, rate_hz=1000.0)
    try:
        request, addr = fake.recvfrom(64)
        assert request == build_rdt_request(2, 0)
        fake.sendto(b"\x00" * 35, addr)
        fake.sendto(b"", addr)
        fake.sendto(RDT_RECORD.pack(1, 0, 0, 1, 2, 3, 4, 5, 6) * 2, addr)        # duplicate inside
        fake.sendto(RDT_RECORD.pack(3, 0, 0, 1, 2, 3, 4, 5, 6), addr)
        assert wait_until(lambda: client.counters().received == 2)
        c = client.counters()
        assert (c.bad_datagrams, c.duplicated, c.lost) == (2, 1, 1)
        np.testing.assert_array_equal(client.read_block().seq, [1, 3])
    finally:
        client.close()
        fake.close()


def test_close_ends_the_thread_and_stops_the_stream(make_server):
    srv = make_server()
    client = NetFTClient("127.0.0.1", srv.rdt_port, srv.calinfo_port)
    assert wait_until(lambda: client.counters().received > 10)
    client.close()
    client.close()
    assert not client._thread.is_alive()
    assert wait_until(lambda: not srv.streaming)
    assert srv.log.requests[-1] == (0, 0)


# ---------------------------------------------------------------- pure parsers / tracker
def test_parsers_reject_bad_sizes_and_headers():
    rec = RDT_RECORD.pack(5, 6, 7, -1, -2, -3, 4, 5, 6)
    (r,) = parse_rdt_datagram(rec)
    assert (r.rdt_sequence, r.ft_sequence, r.status, r.counts) == (5, 6, 7, (-1, -2, -3, 4, 5, 6))
    assert len(parse_rdt_datagram(rec * 3)) == 3
    for bad in (b"", rec[:-1], rec + b"\x00"):
        with pytest.raises(ProtocolError):
            parse_rdt_datagram(bad)
    good = struct.pack(">HBBII6H", 0x1234, 2, 3, 10, 20, 1, 1, 1, 1, 1, 1)
    assert parse_calinfo(good) == CalInfo(2, 3, 10, 20, (1,) * 6)
    for bad in (good[:-1], b"\x12\x35" + good[2:], good[:2] + b"\x09" + good[3:],
                struct.pack(">HBBII6H", 0x1234, 2, 3, 0, 20, *([1] * 6))):
        with pytest.raises(ProtocolError):
            parse_calinfo(bad)


def test_tracker_wraps_loses_reorders_and_resyncs():
    c = NetFTCounters()
    t = SequenceTracker(c, window=100, resync_after=3)
    top = (1 << 32) - 2
    got = [t.accept(s) for s in (top, top + 1, 1, 0, 0, 3)]   # wrap, lost 2^32 (=0) arrives late
    assert got == [top, top + 1, (1 << 32) + 1, None, None, (1 << 32) + 3]
    assert (c.received, c.lost, c.reordered, c.duplicated) == (4, 1, 1, 1)   # 2 never came
    # The device restarts at 1: after three far-behind records the tracker follows it.
    c3 = NetFTCounters()
    t3 = SequenceTracker(c3, window=100, resync_after=3)
    assert [t3.accept(s) for s in (1000, 1001, 1, 2, 3, 4)] == [1000, 1001, None, None, 1002, 1003]
    assert c3.resyncs == 1
    # A late record older than the first of a stream extends the span backwards.
    c2 = NetFTCounters()
    t2 = SequenceTracker(c2)
    assert [t2.accept(s) for s in (5, 2, 6, 3)] == [5, None, 6, None]
    assert (c2.received, c2.lost, c2.reordered) == (2, 1, 2)     # 4 never came: 2..6 all accounted


# ---------------------------------------------------------------- receiving in the caller's thread
def test_receive_in_caller_thread_delivers_every_record_and_times_out_quietly(make_server, make_client):
    """receive_thread=False (the hardware process's safety thread reads the socket itself):
    the same records, in order, and receive() returns 0 after its timeout when nothing comes."""
    srv = make_server(rate_hz=1000.0, records_per_datagram=1)
    client = make_client(srv, autostart=False, receive_thread=False)
    assert client.receive(0.01) == 0                       # not streaming yet
    client.start(sample_count=300)
    got = 0
    end = time.monotonic() + 10.0
    while got < 300 and time.monotonic() < end:
        got += client.receive(0.05)
    block = client.read_block()
    assert len(block) == 300 and got == 300
    np.testing.assert_array_equal(block.seq, np.arange(1, 301))
    np.testing.assert_array_equal(np.rint(block.force_n[:, 0] * CPF), np.arange(300))
    t0 = time.monotonic()
    assert client.receive(0.05) == 0                       # the finite stream ended
    assert time.monotonic() - t0 >= 0.04                   # it waited instead of spinning
    with pytest.raises(RuntimeError):
        make_client(srv, autostart=False).receive(0.01)    # a threaded client refuses
