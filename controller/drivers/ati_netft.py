"""ATI Net F/T driver: RDT streaming over UDP, calibration info over TCP.

Wire formats (network byte order; docs/protocols.md has the full notes):
- RDT request (UDP, default port 49152), 8 bytes ``>HHI``: header 0x1234, command
  (0 stop, 2 real-time streaming, 3 buffered streaming, 0x42 set software bias on the
  device — no reply), sample count (0 = until stopped).
- RDT record, 36 bytes ``>III6i``: rdt_sequence (1 for the first record of a request,
  uint32, wraps to 0), ft_sequence (device's internal sample counter), status
  (0 = healthy), Fx Fy Fz Tx Ty Tz in counts. Buffered mode packs several records in
  one datagram.
- READCALINFO (TCP 49151): 20-byte request whose first byte is 1, 24-byte reply
  ``>HBBII6H``: header 0x1234, force unit code, torque unit code, counts per force
  unit, counts per torque unit, six 16-bit scale factors (unused by RDT).

Sign and frame: the counts are the load the environment applies to the tool side of
the sensor, in the sensor frame; that is ``WrenchBlock``'s convention, so no sign is
changed here (pressing the probe into an object gives a negative Fz when the sensor's
+z points along the probe).

Why a background receive thread (and not a non-blocking drain in ``read_block``):
- every record is time-stamped when it arrives, not when the controller gets round to
  reading, so ``last_sample_age_s`` means "the device went quiet", not "the reader was busy";
- the kernel's UDP buffer (about 200 kB, ~280 datagrams at 1 kHz) would overflow — and
  silently lose data — whenever the controller stalls for a few hundred ms (journal
  fsync, a long plan step); the thread keeps draining it into a bounded queue.
Sample times come from the sequence numbers on a timebase anchored to the arrival
times (lower envelope), so records that arrive together in a buffered datagram or
after a scheduling hiccup still get evenly spaced times; the force-rate limit in the
safety path divides by these differences.
"""
from __future__ import annotations

import collections
import select
import socket
import struct
import threading
from dataclasses import dataclass, field, replace

import numpy as np

from ..core.clock import Clock, RealClock
from ..core.devices import DeviceIdentity, WrenchBlock
from ..core.errors import DeviceError, DeviceTimeout, ProtocolError

RDT_HEADER = 0x1234
CMD_STOP = 0x0000
CMD_START_REALTIME = 0x0002
CMD_START_BUFFERED = 0x0003
CMD_SET_BIAS = 0x0042
READCALINFO = 1

RDT_REQUEST = struct.Struct(">HHI")
RDT_RECORD = struct.Struct(">III6i")
CALINFO_REPLY = struct.Struct(">HBBII6H")
CALINFO_REQUEST_SIZE = 20
MAX_UDP_PAYLOAD = 65507
UINT32 = 1 << 32
HALF_UINT32 = 1 << 31

# ATI unit codes -> SI factor (N per unit, N*m per unit).
FORCE_UNIT_TO_N: dict[int, tuple[str, float]] = {
    1: ("lbf", 4.4482216152605),
    2: ("N", 1.0),
    3: ("klbf", 4448.2216152605),
    4: ("kN", 1000.0),
    5: ("kgf", 9.80665),
    6: ("gf", 0.00980665),
}
TORQUE_UNIT_TO_NM: dict[int, tuple[str, float]] = {
    1: ("lbf-in", 0.1129848290276167),
    2: ("lbf-ft", 1.3558179483314004),
    3: ("N-m", 1.0),
    4: ("N-mm", 0.001),
    5: ("kgf-cm", 0.0980665),
    6: ("kN-m", 1000.0),
}


# A tare needs a live stream: the newest record arrived at most this long ago (s). The tare
# is taken at rest in free air, so samples this old still describe the unloaded sensor.
TARE_STALE_S = 0.5


@dataclass(frozen=True)
class RdtRecord:
    """One RDT record as it came off the wire (counts, not physical units)."""

    rdt_sequence: int
    ft_sequence: int
    status: int
    counts: tuple[int, int, int, int, int, int]   # Fx Fy Fz Tx Ty Tz


@dataclass(frozen=True)
class CalInfo:
    """The device's calibration scaling, read over TCP (never assumed)."""

    force_units: int
    torque_units: int
    counts_per_force: int
    counts_per_torque: int
    scale_factors: tuple[int, ...]

    @property
    def newtons_per_count(self) -> float:
        return FORCE_UNIT_TO_N[self.force_units][1] / self.counts_per_force

    @property
    def newton_meters_per_count(self) -> float:
        return TORQUE_UNIT_TO_NM[self.torque_units][1] / self.counts_per_torque

    @property
    def unit_names(self) -> tuple[str, str]:
        return FORCE_UNIT_TO_N[self.force_units][0], TORQUE_UNIT_TO_NM[self.torque_units][0]


def build_rdt_request(command: int, sample_count: int = 0) -> bytes:
    """The 8-byte RDT request datagram."""
    if not 0 <= command <= 0xFFFF or not 0 <= sample_count < UINT32:
        raise ValueError(f"bad RDT request: command={command} count={sample_count}")
    return RDT_REQUEST.pack(RDT_HEADER, command, sample_count)


def build_calinfo_request() -> bytes:
    """READCALINFO: first byte 1, 19 reserved zero bytes."""
    return bytes([READCALINFO]) + bytes(CALINFO_REQUEST_SIZE - 1)


def parse_rdt_datagram(data: bytes) -> list[RdtRecord]:
    """Split one RDT datagram into records; ``ProtocolError`` if it is not a whole
    number (>= 1) of 36-byte records."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"RDT datagram must be bytes, not {type(data).__name__}")
    size = len(data)
    if size == 0 or size % RDT_RECORD.size or size > MAX_UDP_PAYLOAD:
        raise ProtocolError(f"RDT datagram of {size} bytes is not a whole number of "
                            f"{RDT_RECORD.size}-byte records")
    out = []
    for fields in RDT_RECORD.iter_unpack(bytes(data)):
        out.append(RdtRecord(fields[0], fields[1], fields[2], tuple(fields[3:9])))  # type: ignore[arg-type]
    return out


def parse_calinfo(data: bytes) -> CalInfo:
    """Decode the 24-byte READCALINFO reply; ``ProtocolError`` on any defect."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"calibration reply must be bytes, not {type(data).__name__}")
    if len(data) != CALINFO_REPLY.size:
        raise ProtocolError(f"calibration reply is {len(data)} bytes, expected {CALINFO_REPLY.size}")
    header, fu, tu, cpf, cpt, *scales = CALINFO_REPLY.unpack(bytes(data))
    if header != RDT_HEADER:
        raise ProtocolError(f"calibration reply header 0x{header:04x}, expected 0x{RDT_HEADER:04x}")
    if fu not in FORCE_UNIT_TO_N:
        raise ProtocolError(f"unknown force unit code {fu}")
    if tu not in TORQUE_UNIT_TO_NM:
        raise ProtocolError(f"unknown torque unit code {tu}")
    if cpf == 0 or cpt == 0:
        raise ProtocolError(f"zero counts per unit (cpf={cpf}, cpt={cpt})")
    return CalInfo(fu, tu, cpf, cpt, tuple(scales))


def read_calinfo(host: str, port: int = 49151, timeout_s: float = 2.0) -> CalInfo:
    """Ask the device for its counts per unit over TCP (one request, one reply)."""
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as sock:
            sock.sendall(build_calinfo_request())
            buf = b""
            while len(buf) < CALINFO_REPLY.size:
                chunk = sock.recv(CALINFO_REPLY.size - len(buf))
                if not chunk:
                    raise ProtocolError(f"calibration reply cut short after {len(buf)} bytes")
                buf += chunk
    except socket.timeout as exc:
        raise DeviceTimeout(f"Net F/T {host}:{port} did not send its calibration within {timeout_s} s") from exc
    except OSError as exc:
        raise DeviceError(f"Net F/T {host}:{port}: calibration request failed: {exc}") from exc
    return parse_calinfo(buf)


@dataclass
class NetFTCounters:
    """Record accounting since the client was opened.

    Within one stream, every sequence number between the first and the newest is
    exactly one of: delivered (``received``), never arrived (``lost``), or arrived
    after a newer one and dropped (``reordered``). ``duplicated`` counts extra copies.
    """

    received: int = 0
    lost: int = 0
    reordered: int = 0
    duplicated: int = 0
    bad_datagrams: int = 0
    overflowed: int = 0        # delivered records dropped because nobody read them
    resyncs: int = 0           # the device restarted its sequence under us
    reanchors: int = 0         # timebase re-anchored (stall, or rate_hz not the device's)
    longest_gap_s: float = 0.0  # longest silence between two datagrams of one stream (s)


class SequenceTracker:
    """Unwraps uint32 rdt_sequence numbers and decides which records to deliver.

    Delivers only records newer than every record delivered so far (order preserved,
    no duplicates); a late record that fills a gap is dropped and moves one count from
    ``lost`` to ``reordered``. Records far behind (more than ``window``) come from a
    device that restarted its sequence: after ``resync_after`` of them in a row the
    tracker follows the new sequence.
    """

    def __init__(self, counters: NetFTCounters, window: int = 8192, resync_after: int = 8) -> None:
        self.c = counters
        self.window = window
        self.resync_after = resync_after
        self.head: int | None = None        # unwrapped sequence of the newest delivered record
        self.first: int | None = None       # oldest sequence number of this stream seen so far
        self._raw_head = 0
        self._next_base: int | None = None  # unwrapped value given to the first record of a stream
        self._seen: set[int] = set()
        self._seen_order: collections.deque[int] = collections.deque()
        self._far_run = 0

    def new_stream(self) -> None:
        """A fresh request was sent: its first record continues right after ``head``."""
        self._next_base = None if self.head is None else self.head + 1
        self.head = None
        self.first = None
        self._seen.clear()
        self._seen_order.clear()
        self._far_run = 0

    def _remember(self, seq: int) -> None:
        self._seen.add(seq)
        self._seen_order.append(seq)
        while self._seen_order and self._seen_order[0] < seq - self.window:
            self._seen.discard(self._seen_order.popleft())

    def accept(self, raw_seq: int) -> int | None:
        """The unwrapped sequence number to deliver, or None to drop the record."""
        if self.head is None:
            self.head = raw_seq if self._next_base is None else self._next_base
            self.first = self.head
            self._raw_head = raw_seq
            self._remember(self.head)
            self.c.received += 1
            return self.head
        ahead = (raw_seq - self._raw_head) % UINT32
        if 0 < ahead < HALF_UINT32:
            self._far_run = 0
            self.c.lost += ahead - 1
            self.head += ahead
            self._raw_head = raw_seq
            self._remember(self.head)
            self.c.received += 1
            return self.head
        behind = (self._raw_head - raw_seq) % UINT32
        if behind <= self.window:
            self._far_run = 0
            seq = self.head - behind
            if seq in self._seen:
                self.c.duplicated += 1
                return None
            self._remember(seq)
            self.c.reordered += 1
            assert self.first is not None
            if seq < self.first:
                # Older than the first record of the stream: the span grows backwards.
                self.c.lost += self.first - seq - 1
                self.first = seq
            else:
                self.c.lost -= 1       # it was counted lost when the head skipped it
            return None
        # Far behind: a stray old datagram, or a device that restarted its stream.
        self._far_run += 1
        if self._far_run >= self.resync_after:
            self.c.resyncs += 1
            base = self.head + 1
            self.new_stream()
            self._next_base = base
            return self.accept(raw_seq)
        return None


class _Timebase:
    """Sample time = anchor + seq / rate, anchored to the earliest-arriving records.

    ``anchor`` follows the lower envelope of (arrival - seq/rate): transport delay only
    ever makes a record late, never early. It creeps up at no more than ``creep`` s/s
    (device crystal vs nominal rate: 200 ppm covers ordinary oscillators), and jumps when a record arrives more than ``max_lag_s`` after its
    predicted time (a stalled stream restarting). Times never exceed the arrival time
    and never go backwards.
    """

    def __init__(self, rate_hz: float, max_lag_s: float = 0.02, creep: float = 2e-4) -> None:
        self.period_s = 1.0 / rate_hz
        self.max_lag_s = max_lag_s
        self.creep = creep
        self.anchor_s: float | None = None
        self._anchor_arrival_s = 0.0
        self.last_t_s = -np.inf
        self.reanchors = 0

    def stamp(self, seq: int, arrival_s: float) -> float:
        candidate = arrival_s - seq * self.period_s
        if self.anchor_s is None:
            self.anchor_s = candidate
        else:
            allowed = self.anchor_s + self.creep * max(0.0, arrival_s - self._anchor_arrival_s)
            if candidate < allowed:
                self.anchor_s = candidate
            elif candidate - allowed > self.max_lag_s:
                self.anchor_s = candidate
                self.reanchors += 1
            else:
                self.anchor_s = min(candidate, allowed)
        self._anchor_arrival_s = arrival_s
        t_s = min(self.anchor_s + seq * self.period_s, arrival_s)
        t_s = max(t_s, self.last_t_s)
        self.last_t_s = t_s
        return t_s


@dataclass
class _Pending:
    t_s: list[float] = field(default_factory=list)
    seq: list[int] = field(default_factory=list)
    counts: list[tuple[int, ...]] = field(default_factory=list)
    status: list[int] = field(default_factory=list)


class NetFTClient:
    """ATI Net F/T over RDT, implementing ``ForceTorqueSensor``.

    ``host``: the sensor's address; ``rate_hz``: the RDT output rate configured on the
    device (not readable over RDT; used for the sample timebase). Forces in N and
    torques in N*m in the sensor frame, with the software bias (``tare``) removed.
    The client owns the stream: the socket is connected to (host, rdt_port), so the
    kernel drops datagrams from anyone else. Use as a context manager or call close().
    """

    def __init__(self, host: str, rdt_port: int = 49152, calinfo_port: int = 49151, *,
                 clock: Clock | None = None, rate_hz: float = 1000.0, buffered: bool = False,
                 serial: str = "unknown", firmware: str = "unknown", model: str = "ATI Net F/T",
                 timeout_s: float = 2.0, max_pending_s: float = 60.0,
                 tare_window_s: float = 0.1, autostart: bool = True, receive_thread: bool = True) -> None:
        if rate_hz <= 0:
            raise ValueError("rate_hz must be > 0")
        self.host = host
        self.rdt_port = rdt_port
        self.calinfo_port = calinfo_port
        self.clock: Clock = clock or RealClock()
        self._rate_hz = float(rate_hz)
        self.buffered = buffered
        self.timeout_s = timeout_s
        self.tare_window_s = tare_window_s
        self.cal = read_calinfo(host, calinfo_port, timeout_s)
        self._identity = DeviceIdentity(
            kind="ft", model=model, serial=serial, firmware=firmware,
            extra={"host": host, "rdt_port": rdt_port, "counts_per_force": self.cal.counts_per_force,
                   "counts_per_torque": self.cal.counts_per_torque,
                   "force_units": self.cal.unit_names[0], "torque_units": self.cal.unit_names[1]})
        self._scale = np.array([self.cal.newtons_per_count] * 3 + [self.cal.newton_meters_per_count] * 3)
        self._bias = np.zeros(6)
        self._lock = threading.Lock()
        self._counters = NetFTCounters()
        self._tracker = SequenceTracker(self._counters)
        self._timebase = _Timebase(rate_hz)
        self._pending = _Pending()
        self._max_pending = max(1, int(max_pending_s * rate_hz))
        self._recent: collections.deque[tuple[float, tuple[int, ...]]] = collections.deque(
            maxlen=max(16, int(2.0 * rate_hz)))
        self._last_arrival_s: float | None = None
        self._stream_arrival_s: float | None = None   # newest arrival of the current stream
        self._streaming = False
        self._stop_event = threading.Event()
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
            self._sock.connect((host, rdt_port))
            self._sock.settimeout(0.05)   # bounds how long close() waits for the thread
        except OSError as exc:
            self._sock.close()
            raise DeviceError(f"Net F/T {host}:{rdt_port}: {exc}") from exc
        # Without a receive thread the owner calls receive() itself (the hardware process's
        # safety thread does: the check runs in the thread that read the datagram, no hop).
        self._thread: threading.Thread | None = None
        self._poller: select.poll | None = None
        if not receive_thread:
            # A non-blocking socket and a poll object: receive() waits in poll() only for the
            # first datagram, then drains without a wait (a socket timeout would poll first).
            self._sock.setblocking(False)
            self._poller = select.poll()
            self._poller.register(self._sock, select.POLLIN)
        else:
            self._thread = threading.Thread(target=self._receive_loop, name=f"netft-rx-{host}", daemon=True)
            self._thread.start()
        if autostart:
            self.start()

    # ------------------------------------------------------------------ protocol
    def identity(self) -> DeviceIdentity:
        return self._identity

    @property
    def rate_hz(self) -> float:
        return self._rate_hz

    def start(self, sample_count: int = 0) -> None:
        """Ask for streaming (real-time, or buffered if ``buffered``); 0 = until stop()."""
        with self._lock:
            self._tracker.new_stream()
            self._timebase = _Timebase(self._rate_hz)
            self._stream_arrival_s = None
            self._streaming = True
        self._send(build_rdt_request(CMD_START_BUFFERED if self.buffered else CMD_START_REALTIME,
                                     sample_count))

    def stop(self) -> None:
        """Ask the device to stop streaming; records still in flight are discarded (they
        belong to no stream once stopped)."""
        with self._lock:
            self._streaming = False
        self._send(build_rdt_request(CMD_STOP))

    def device_bias(self) -> None:
        """Command 0x42: the device zeroes its own output (no reply). Clears the software bias."""
        self._send(build_rdt_request(CMD_SET_BIAS))
        with self._lock:
            self._bias[:] = 0.0

    def tare(self) -> None:
        """Software bias: the mean of the newest ``tare_window_s`` of samples becomes zero.

        Kept on the client (not sent as 0x42) so the raw counts stay meaningful and the
        bias is journaled with the data; raises ``DeviceTimeout`` when no record arrived
        in the last ``TARE_STALE_S`` (the stream has stopped). The window is on the
        samples' own timebase, ending at the newest sample (the timebase stamps samples
        from their sequence counter at the nominal rate, not from the arrival clock), so
        a delivery pause shorter than ``TARE_STALE_S`` does not fail the tare.
        """
        now_s = self.clock.now_s()
        with self._lock:
            fresh = self._last_arrival_s is not None and now_s - self._last_arrival_s <= max(TARE_STALE_S,
                                                                                         self.tare_window_s)
            newest_s = self._recent[-1][0] if self._recent else None
            rows = [] if not fresh or newest_s is None else \
                [c for (t, c) in self._recent if t >= newest_s - self.tare_window_s]
            if not rows:
                raise DeviceTimeout(f"Net F/T {self.host}: no sample arrived in the last "
                                    f"{max(TARE_STALE_S, self.tare_window_s)} s to tare on")
            self._bias = np.mean(np.asarray(rows, dtype=np.float64), axis=0) * self._scale

    def bias(self) -> np.ndarray:
        """The software bias (6,) subtracted from every sample: N, N, N, N*m, N*m, N*m."""
        with self._lock:
            return self._bias.copy()

    def read_block(self) -> WrenchBlock:
        """Every record delivered since the previous call, oldest first."""
        with self._lock:
            pending, self._pending = self._pending, _Pending()
            bias = self._bias.copy()
        if not pending.seq:
            return WrenchBlock.empty()
        wrench = np.asarray(pending.counts, dtype=np.float64) * self._scale - bias
        return WrenchBlock(np.asarray(pending.t_s, dtype=np.float64), np.asarray(pending.seq, dtype=np.int64),
                           wrench[:, :3], wrench[:, 3:], np.asarray(pending.status, dtype=np.uint32))

    def last_sample_age_s(self) -> float:
        """Seconds since the newest record arrived (inf before the first one)."""
        with self._lock:
            last = self._last_arrival_s
        return float("inf") if last is None else self.clock.now_s() - last

    def counters(self) -> NetFTCounters:
        with self._lock:
            c = replace(self._counters)
            c.reanchors = self._timebase.reanchors + self._counters.reanchors
        return c

    def close(self) -> None:
        """Stop the stream, end the receive thread, close the socket. Idempotent."""
        if self._stop_event.is_set():
            return
        try:
            self.stop()
        except DeviceError:
            pass
        self._stop_event.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._sock.close()

    def __enter__(self) -> "NetFTClient":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ internals
    def _send(self, data: bytes) -> None:
        try:
            self._sock.send(data)
        except OSError as exc:
            raise DeviceError(f"Net F/T {self.host}:{self.rdt_port}: send failed: {exc}") from exc

    def receive(self, timeout_s: float) -> int:
        """Read the datagrams that have arrived, waiting up to ``timeout_s`` for the first;
        returns how many datagrams were read (0 on timeout). For a client built with
        ``receive_thread=False`` (one thread must do all the receiving)."""
        if self._poller is None:
            raise RuntimeError("this NetFTClient has its own receive thread")
        if not self._poller.poll(max(0.0, float(timeout_s)) * 1e3):
            return 0
        got = 0
        while got < 256:                  # bounded: a flood cannot keep the caller here
            try:
                data = self._sock.recv(MAX_UDP_PAYLOAD + 1)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                # ICMP port unreachable (device not up yet): staleness tells the controller;
                # wait out the timeout so a caller's loop does not spin.
                if not got:
                    self._stop_event.wait(timeout_s)
                break
            self._accept_datagram(data, self.clock.now_s())
            got += 1
        return got

    def _accept_datagram(self, data: bytes, arrival_s: float) -> None:
        try:
            records = parse_rdt_datagram(data)
        except ProtocolError:
            with self._lock:
                self._counters.bad_datagrams += 1
            return
        self._ingest(records, arrival_s)

    def _receive_loop(self) -> None:
        while not self._stop_event.is_set():
            try:
                data = self._sock.recv(MAX_UDP_PAYLOAD + 1)
            except socket.timeout:
                continue
            except OSError:
                # ICMP port unreachable (device not up yet) surfaces here on a connected
                # UDP socket; keep listening — staleness tells the controller.
                if self._stop_event.wait(0.01):
                    return
                continue
            self._accept_datagram(data, self.clock.now_s())

    def _ingest(self, records: list[RdtRecord], arrival_s: float) -> None:
        with self._lock:
            if not self._streaming:
                return            # stray records after stop(): not part of any stream
            if self._stream_arrival_s is not None:
                self._counters.longest_gap_s = max(self._counters.longest_gap_s, arrival_s - self._stream_arrival_s)
            self._stream_arrival_s = arrival_s
            for rec in records:
                seq = self._tracker.accept(rec.rdt_sequence)
                if seq is None:
                    continue
                t_s = self._timebase.stamp(seq, arrival_s)
                p = self._pending
                p.t_s.append(t_s)
                p.seq.append(seq)
                p.counts.append(rec.counts)
                p.status.append(rec.status)
                self._recent.append((t_s, rec.counts))
                self._last_arrival_s = arrival_s
            overflow = len(self._pending.seq) - self._max_pending
            if overflow > 0:
                p = self._pending
                del p.t_s[:overflow], p.seq[:overflow], p.counts[:overflow], p.status[:overflow]
                self._counters.overflowed += overflow
