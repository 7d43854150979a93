"""Serial line scanner driver against the simulated scanner through a real pty (and once
over socket://). The server logs what it sent (frame counters, true exposure times,
injected faults); the driver is judged against that log and the profile source."""
from __future__ import annotations

import os
import time

import numpy as np
import pytest

from elastoprobe.controller.core.clock import RealClock
from elastoprobe.controller.core.devices import LineScanner, Scan
from elastoprobe.controller.drivers.line_scanner import (
    BurstTimeout, SerialLineScanner, ShortBurst)
from elastoprobe.controller.core.errors import DeviceError, DeviceTimeout
from elastoprobe.sim.servers.scanner_serial import ScannerFaults, ScannerPtyServer

# Real transports on loopback, timed: never beside other tests (the default run's second part).
pytestmark = [pytest.mark.timeout(60), pytest.mark.loopback]
N = 256
Z_SCALE = 0.002
DEVICE_OFFSET_S = 1234.5


def truth_z(counter: int, t_s: float) -> np.ndarray:
    """A dent whose depth depends on the frame, with a moving band of missing samples."""
    x = np.linspace(-30.0, 30.0, N)
    z = 120.0 + 2.0 * np.exp(-(x / 6.0) ** 2) + 0.01 * counter
    z[(counter * 7) % 200:(counter * 7) % 200 + 12] = np.nan
    z[-1] = np.nan
    return z


@pytest.fixture
def make_scanner():
    made: list[tuple[ScannerPtyServer, SerialLineScanner | None]] = []

    def factory(faults: ScannerFaults | None = None, timeout_s: float = 1.0, **kw):
        srv = ScannerPtyServer(truth_z, n_points=N, z_scale_mm=Z_SCALE, rate_hz=kw.pop("rate_hz", 200.0),
                               device_clock_offset_s=DEVICE_OFFSET_S, faults=faults,
                               max_lifetime_s=50.0, **kw).start()
        made.append((srv, None))
        client = SerialLineScanner(srv.url, RealClock(), timeout_s=timeout_s)
        made[-1] = (srv, client)
        return srv, client

    yield factory
    for srv, client in made:
        if client is not None:
            client.close()
        srv.stop()


def collect(client: SerialLineScanner, n: int, limit_s: float = 10.0) -> list[Scan]:
    """Start a burst of ``n`` and gather it (bounded); exceptions propagate."""
    client.read_scans()
    client.start_burst(n)
    scans: list[Scan] = []
    end = time.monotonic() + limit_s
    while len(scans) < n and time.monotonic() < end:
        scans += client.read_scans()
        time.sleep(0.002)
    return scans


def expect_exception(client: SerialLineScanner, n: int, exc_type: type[Exception],
                     limit_s: float = 10.0) -> tuple[Exception, list[Scan]]:
    """Start a burst that must fail with ``exc_type``; returns it and every scan seen."""
    client.read_scans()
    client.start_burst(n)
    scans: list[Scan] = []
    end = time.monotonic() + limit_s
    while time.monotonic() < end:
        try:
            scans += client.read_scans()
        except exc_type as exc:
            scans += getattr(exc, "scans", [])
            return exc, scans
        time.sleep(0.002)
    raise AssertionError(f"no {exc_type.__name__} within {limit_s} s; got {len(scans)} scans")


def check_scan_against_truth(scan: Scan) -> None:
    truth = truth_z(scan.frame_counter, 0.0)
    np.testing.assert_array_equal(np.isnan(scan.z_mm), np.isnan(truth))          # NaNs preserved
    ok = ~np.isnan(truth)
    assert np.max(np.abs(scan.z_mm[ok] - truth[ok])) <= Z_SCALE / 2 + 1e-9       # quantisation only
    np.testing.assert_allclose(scan.x_mm, np.linspace(-30.0, 30.0, N), atol=1e-5)


# ---------------------------------------------------------------- identify, bursts, time
def test_identify_through_a_real_pty(make_scanner):
    srv, client = make_scanner()
    assert srv.port_path is not None and srv.port_path.startswith("/dev/")
    fd = os.open(srv.port_path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        assert os.isatty(fd)
    finally:
        os.close(fd)
    assert isinstance(client, LineScanner)
    ident = client.identity()
    assert (ident.kind, ident.model, ident.serial, ident.firmware) == ("scanner", "ELS-256", "SIM00042", "1.0.0")
    assert client.samples_per_profile == N and client.rate_hz == 200.0
    assert srv.log.commands[:2] == ["STOP", "*IDN?"]


def test_burst_of_n_with_nans_and_exposure_times(make_scanner):
    srv, client = make_scanner()
    scans = collect(client, 25)
    assert len(scans) == 25
    assert [s.frame_counter for s in scans] == [f.frame_counter for f in srv.log.frames]
    for scan in scans:
        check_scan_against_truth(scan)
    # Device clock (offset by 1234.5 s) mapped onto ours within the round-trip bound.
    true_t = np.array([f.exposure_monotonic_s for f in srv.log.frames])
    err = np.array([s.exposure_t_s for s in scans]) - true_t
    assert np.max(np.abs(err)) <= client.clock_offset_uncertainty_s + 2e-5
    assert client.clock_offset_s == pytest.approx(-DEVICE_OFFSET_S, abs=0.05)
    np.testing.assert_allclose(np.diff([s.exposure_t_s for s in scans]), 1 / 200.0, atol=2e-6)
    c = client.counters()
    assert (c.frames, c.bad_frames, c.garbage_bytes, c.short_bursts) == (25, 0, 0, 0)
    assert srv.log.bursts == [(25, 25)]


def test_explicit_x_frames_decode_the_same(make_scanner):
    _, client = make_scanner(explicit_x=True)
    scans = collect(client, 5)
    assert len(scans) == 5
    for scan in scans:
        check_scan_against_truth(scan)


def test_set_rate_and_refusal(make_scanner):
    srv, client = make_scanner()
    client.set_rate(500.0)
    assert client.rate_hz == 500.0 and srv.rate_hz == 500.0
    with pytest.raises(DeviceError, match="ERR 2"):
        client.set_rate(0.0)
    scans = collect(client, 10)
    np.testing.assert_allclose(np.diff([s.exposure_t_s for s in scans]), 1 / 500.0, atol=2e-6)


# ---------------------------------------------------------------- faults
def test_corrupted_frame_is_skipped_and_counted(make_scanner):
    srv, client = make_scanner(ScannerFaults(corrupt_crc={3}))
    exc, scans = expect_exception(client, 10, ShortBurst)
    bad = [f.frame_counter for f in srv.log.frames if f.fault == "crc"]
    assert len(bad) == 1
    assert [s.frame_counter for s in scans] == [f.frame_counter for f in srv.log.frames if f.fault != "crc"]
    assert (exc.requested, exc.received, exc.device_sent, exc.bad_frames) == (10, 9, 10, 1)
    assert client.counters().bad_frames == 1 and client.counters().short_bursts == 1
    for scan in scans:
        check_scan_against_truth(scan)
    # The next burst is clean again.
    srv.faults.corrupt_crc = set()
    assert len(collect(client, 6)) == 6


def test_truncated_frame_followed_by_a_good_one(make_scanner):
    srv, client = make_scanner(ScannerFaults(truncate={4}))
    exc, scans = expect_exception(client, 10, ShortBurst)
    sent_whole = [f.frame_counter for f in srv.log.frames if f.fault != "truncated"]
    assert [s.frame_counter for s in scans] == sent_whole          # frame 5 onwards recovered
    assert exc.received == 9 and client.counters().bad_frames >= 1


def test_truncated_last_frame_is_flushed_when_the_line_goes_quiet(make_scanner):
    srv, client = make_scanner(ScannerFaults(truncate={7}))
    exc, scans = expect_exception(client, 8, ShortBurst)
    assert [s.frame_counter for s in scans] == [f.frame_counter for f in srv.log.frames[:7]]
    assert exc.device_sent == 8 and client.counters().bad_frames >= 1


def test_garbage_between_frames_is_skipped(make_scanner):
    srv, client = make_scanner(ScannerFaults(garbage_before={0, 4, 9}, garbage_bytes=200), seed=11)
    scans = collect(client, 12)
    assert [s.frame_counter for s in scans] == [f.frame_counter for f in srv.log.frames]
    assert client.counters().garbage_bytes > 0
    assert client.counters().short_bursts == 0


def test_short_burst_is_reported(make_scanner):
    srv, client = make_scanner(ScannerFaults(short_burst_by=3))
    exc, scans = expect_exception(client, 10, ShortBurst)
    assert (exc.requested, exc.received, exc.device_sent, exc.bad_frames) == (10, 7, 7, 0)
    assert len(scans) == 7 and srv.log.bursts == [(10, 7)]


def test_silent_scanner_times_out_within_the_bound(make_scanner):
    srv, client = make_scanner(timeout_s=0.5)
    srv.faults.silent = True
    clock = client.clock
    t0 = clock.now_s()
    with pytest.raises(DeviceTimeout):
        client.start_burst(5)
    waited_s = clock.now_s() - t0
    assert 0.5 <= waited_s < 0.5 + 2.0       # it waited its deadline, and no longer than that bound


def test_scanner_going_silent_mid_burst_raises_burst_timeout(make_scanner):
    srv, client = make_scanner(ScannerFaults(silent_after_frames=4), timeout_s=0.3)
    exc, scans = expect_exception(client, 10, BurstTimeout)
    assert isinstance(exc, DeviceTimeout)
    assert len(scans) == 4 and client.counters().timeouts == 1
    assert "4 of 10" in str(exc)


def test_socket_url_variant(make_scanner):
    srv, client = make_scanner(ScannerFaults(garbage_before={2}), transport="tcp")
    assert client.url.startswith("socket://127.0.0.1:")
    assert client.identity().serial == "SIM00042"
    scans = collect(client, 8)
    assert [s.frame_counter for s in scans] == [f.frame_counter for f in srv.log.frames]
    for scan in scans:
        check_scan_against_truth(scan)
    true_t = np.array([f.exposure_monotonic_s for f in srv.log.frames])
    err = np.array([s.exposure_t_s for s in scans]) - true_t
    assert np.max(np.abs(err)) <= client.clock_offset_uncertainty_s + 2e-5


def test_stream_frames_before_a_burst_are_not_counted_in_it(make_scanner):
    srv, client = make_scanner()
    client.start_stream()
    time.sleep(0.05)
    before = client.read_scans()
    scans = collect(client, 5)          # BURST while streaming: the device restarts as a burst
    assert [s.frame_counter for s in scans] == [f.frame_counter for f in srv.log.frames[-5:]]
    assert [f.position for f in srv.log.frames[-5:]] == [0, 1, 2, 3, 4]
    assert len(before) >= 1
    assert client.counters().frames >= len(before) + client.counters().discarded_frames + 5


def test_burst_arriving_with_its_ok_in_one_read(make_scanner, monkeypatch):
    # A slow reader: the OK, the whole burst and its DONE arrive in the read that finds the OK.
    srv, client = make_scanner(ScannerFaults(short_burst_by=2), rate_hz=1000.0)
    write = client._write

    def write_then_stall(text: str) -> None:
        write(text)
        if text.startswith("BURST"):
            time.sleep(0.1)

    monkeypatch.setattr(client, "_write", write_then_stall)
    exc, scans = expect_exception(client, 6, ShortBurst)
    assert (exc.requested, exc.received, exc.device_sent) == (6, 4, 4)
    assert [s.frame_counter for s in scans] == [f.frame_counter for f in srv.log.frames]
    srv.faults.short_burst_by = 0
    assert len(collect(client, 6)) == 6
    assert client.counters().timeouts == 0


def test_printable_debris_before_frames_does_not_stick_to_the_next_reply():
    from elastoprobe.controller.drivers.line_scanner import FrameParser
    from elastoprobe.sim.servers.scanner_serial import encode_frame

    frame = encode_frame(1, 2, np.array([1.0, 2.0]), x_scale=1.0, x_offset=0.0, z_scale=0.01, z_offset=0.0)
    parser = FrameParser()
    events = parser.feed_events(b"\xff?x" + frame + b"DONE 3\n")
    assert [e if isinstance(e, str) else e.frame_counter for e in events] == [1, "DONE 3"]
    assert parser.counters.garbage_bytes == 3


def test_a_frame_rendered_late_is_stamped_when_it_was_rendered():
    """A source that says when its profile is true (a simulated world renders only its
    present): every 3rd frame is rendered 30 ms after its schedule; the frame carries that
    instant, and the client maps it onto the controller clock within its bound."""
    rendered: dict[int, float] = {}

    def late_source(counter: int, device_t_s: float) -> tuple[np.ndarray, float]:
        if counter % 3 == 0:
            time.sleep(0.03)                  # the render is held up (a busy world)
        actual = max(time.monotonic(), device_t_s - DEVICE_OFFSET_S)
        rendered[counter] = actual
        return truth_z(counter, device_t_s), actual + DEVICE_OFFSET_S

    srv = ScannerPtyServer(late_source, n_points=N, z_scale_mm=Z_SCALE, rate_hz=100.0,
                           device_clock_offset_s=DEVICE_OFFSET_S, max_lifetime_s=30.0).start()
    client = SerialLineScanner(srv.url, RealClock(), timeout_s=1.0)
    try:
        scans = collect(client, 9)
        assert len(scans) == 9
        for scan, frame in zip(scans, srv.log.frames):
            assert frame.exposure_monotonic_s == pytest.approx(rendered[scan.frame_counter], abs=1e-6)
            assert abs(scan.exposure_t_s - rendered[scan.frame_counter]) <= client.clock_offset_uncertainty_s + 2e-5
    finally:
        client.close()
        srv.stop()
