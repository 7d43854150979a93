"""A simulated ATI Net F/T on loopback: RDT over UDP, READCALINFO over TCP.

It encodes the wire formats itself (not through the driver's helpers), so a format
mistake on either side shows up in the loopback tests instead of cancelling out.

Behaviour follows the device: the newest requester owns the stream; command 2 streams
one record per datagram, command 3 ``records_per_datagram`` per datagram; rdt_sequence
restarts at ``first_rdt_sequence`` (1 on a real device) for every request and wraps at
2^32; ft_sequence runs on from power-up; 0x42 zeroes the output at the current load.
Samples are paced on the wall clock at ``rate_hz`` (a starved thread catches up in a
burst, as the device's own buffer would); the thread ends by itself after
``max_lifetime_s``.

Faults (``NetFTFaults``, change them at any time): datagram loss, reordering (a
datagram held back behind the next one), duplicates, a stalled stream (nothing is
sampled or sent while set), frozen values (the counts stop changing, sequence runs on),
status error bits OR-ed into every record, a silent calibration port.
"""
from __future__ import annotations

import random
import selectors
import socket
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

_REQUEST = struct.Struct(">HHI")
_RECORD = struct.Struct(">III6i")
_CALINFO = struct.Struct(">HBBII6H")
_HEADER = 0x1234

# (n) -> (counts (n, 6) int, status (n,) uint32)
WrenchSource = Callable[[int], tuple[np.ndarray, np.ndarray]]


@dataclass
class NetFTFaults:
    loss_fraction: float = 0.0        # datagrams never sent
    reorder_fraction: float = 0.0     # datagrams sent after the next one
    duplicate_fraction: float = 0.0   # datagrams sent twice in a row
    stalled: bool = False             # stream paused: nothing sampled, nothing sent
    frozen: bool = False              # counts repeat the last sent values
    status_bits: int = 0              # OR-ed into every record's status word
    calinfo_silent: bool = False      # READCALINFO requests get no answer


@dataclass
class NetFTServerLog:
    """What went on the wire, for tests to judge the client against."""

    transmitted: list[int] = field(default_factory=list)   # rdt_sequence per record, wire order
    dropped: list[int] = field(default_factory=list)       # rdt_sequence of records never sent
    requests: list[tuple[int, int]] = field(default_factory=list)   # (command, count)
    bias_commands: int = 0
    calinfo_requests: int = 0
    bad_requests: int = 0
    # How far behind its sampling instant a record was sent, at worst (s): the server's own
    # thread starved of CPU (the device itself never is), not a fault it was told to inject.
    longest_late_s: float = 0.0


def ramp_source(counts_per_force: int) -> WrenchSource:
    """Fx counts = the sample index x 1 (so delivery order is visible), others fixed."""
    state = {"k": 0}

    def source(n: int) -> tuple[np.ndarray, np.ndarray]:
        k0 = state["k"]
        state["k"] += n
        counts = np.zeros((n, 6), dtype=np.int64)
        counts[:, 0] = np.arange(k0, k0 + n)
        counts[:, 2] = -5 * counts_per_force   # a steady -5 N push along z
        return counts, np.zeros(n, dtype=np.uint32)

    return source


def constant_source(force_n: np.ndarray, torque_nm: np.ndarray, counts_per_force: int,
                    counts_per_torque: int, noise_counts: float = 0.0, seed: int = 0) -> WrenchSource:
    """A constant wrench (N, N*m) with optional Gaussian noise in counts."""
    rng = np.random.default_rng(seed)
    base = np.concatenate([np.asarray(force_n, float) * counts_per_force,
                           np.asarray(torque_nm, float) * counts_per_torque])

    def source(n: int) -> tuple[np.ndarray, np.ndarray]:
        counts = base + (rng.normal(0.0, noise_counts, (n, 6)) if noise_counts > 0 else 0.0)
        return np.rint(np.broadcast_to(counts, (n, 6))).astype(np.int64), np.zeros(n, dtype=np.uint32)

    return source


class NetFTServer:
    """Serves RDT on ``rdt_port`` and READCALINFO on ``calinfo_port`` (0 = ephemeral;
    the bound ports are then in ``.rdt_port`` / ``.calinfo_port``)."""

    def __init__(self, host: str = "127.0.0.1", rdt_port: int = 0, calinfo_port: int = 0, *,
                 source: WrenchSource, rate_hz: float = 1000.0, records_per_datagram: int = 10,
                 counts_per_force: int = 1_000_000, counts_per_torque: int = 1_000_000,
                 force_units: int = 2, torque_units: int = 3, first_rdt_sequence: int = 1,
                 faults: NetFTFaults | None = None, seed: int = 0, max_lifetime_s: float = 120.0) -> None:
        if not host.startswith("127."):
            raise ValueError("the simulated Net F/T serves loopback addresses only")
        self.host = host
        self.source = source
        self.rate_hz = float(rate_hz)
        self.records_per_datagram = int(records_per_datagram)
        self.counts_per_force = counts_per_force
        self.counts_per_torque = counts_per_torque
        self.force_units = force_units
        self.torque_units = torque_units
        self.first_rdt_sequence = first_rdt_sequence % (1 << 32)
        self.faults = faults or NetFTFaults()
        self.log = NetFTServerLog()
        self.max_lifetime_s = max_lifetime_s
        self._rng = random.Random(seed)
        self._udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._udp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._udp.bind((host, rdt_port))
        self._udp.setblocking(False)
        self._tcp = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._tcp.bind((host, calinfo_port))
        self._tcp.listen(4)
        self._tcp.setblocking(False)
        self.rdt_port = self._udp.getsockname()[1]
        self.calinfo_port = self._tcp.getsockname()[1]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="netft-server", daemon=True)
        # stream state (server thread only)
        self._client: tuple[str, int] | None = None
        self._mode = 0
        self._remaining: int | None = None
        self._rdt_seq = self.first_rdt_sequence
        self._ft_seq = 0
        self._emitted = 0
        self._t0 = 0.0
        self._device_bias = np.zeros(6, dtype=np.int64)
        self._last_counts = np.zeros(6, dtype=np.int64)
        self._last_raw = np.zeros(6, dtype=np.int64)
        self._queue: list[tuple[int, ...]] = []      # records waiting for a full buffered datagram
        self._held: bytes | None = None
        self._held_seqs: list[int] = []
        self._conns: dict[socket.socket, bytearray] = {}

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "NetFTServer":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        for conn in list(self._conns):
            conn.close()
        self._udp.close()
        self._tcp.close()

    def __enter__(self) -> "NetFTServer":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def streaming(self) -> bool:
        return self._mode in (2, 3)

    # ------------------------------------------------------------------ loop
    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self._udp, selectors.EVENT_READ, "udp")
        sel.register(self._tcp, selectors.EVENT_READ, "accept")
        deadline = time.monotonic() + self.max_lifetime_s
        try:
            while not self._stop.is_set() and time.monotonic() < deadline:
                for key, _ in sel.select(timeout=0.0005 if self.streaming else 0.01):
                    if key.data == "udp":
                        self._on_udp()
                    elif key.data == "accept":
                        self._on_accept(sel)
                    else:
                        self._on_tcp(sel, key.fileobj)  # type: ignore[arg-type]
                self._emit_due()
        finally:
            sel.close()
            self._mode = 0

    def _on_udp(self) -> None:
        while True:
            try:
                data, addr = self._udp.recvfrom(2048)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            if len(data) != _REQUEST.size:
                self.log.bad_requests += 1
                continue
            header, command, count = _REQUEST.unpack(data)
            if header != _HEADER:
                self.log.bad_requests += 1
                continue
            self.log.requests.append((command, count))
            if command == 0:
                self._flush_held()
                self._mode = 0
            elif command in (2, 3):
                self._flush_held()
                self._client = addr           # the newest requester owns the stream
                self._mode = command
                self._remaining = count or None
                self._rdt_seq = self.first_rdt_sequence
                self._emitted = 0
                self._queue = []
                self._t0 = time.monotonic()
            elif command == 0x42:
                self.log.bias_commands += 1
                # The device zeroes its output at the load it measures now.
                self._device_bias = self._last_raw.copy()
            else:
                self.log.bad_requests += 1

    def _on_accept(self, sel: selectors.BaseSelector) -> None:
        try:
            conn, _ = self._tcp.accept()
        except OSError:
            return
        conn.setblocking(False)
        self._conns[conn] = bytearray()
        sel.register(conn, selectors.EVENT_READ, "conn")

    def _on_tcp(self, sel: selectors.BaseSelector, conn: socket.socket) -> None:
        try:
            chunk = conn.recv(256)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            chunk = b""
        if not chunk:
            sel.unregister(conn)
            conn.close()
            self._conns.pop(conn, None)
            return
        buf = self._conns[conn]
        buf += chunk
        while len(buf) >= 20:
            command = buf[0]
            del buf[:20]
            if command == 1:
                self.log.calinfo_requests += 1
                if not self.faults.calinfo_silent:
                    reply = _CALINFO.pack(_HEADER, self.force_units, self.torque_units,
                                          self.counts_per_force, self.counts_per_torque, *([1] * 6))
                    try:
                        conn.sendall(reply)
                    except OSError:
                        pass

    # ------------------------------------------------------------------ stream
    def _sample_raw(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        counts, status = self.source(n)
        counts = np.asarray(counts, dtype=np.int64).reshape(n, 6)
        status = np.asarray(status, dtype=np.int64).reshape(n)
        return counts, status

    def _emit_due(self) -> None:
        if not self.streaming or self._client is None:
            return
        now = time.monotonic()
        if self.faults.stalled:
            # Re-base the schedule so the stream resumes without a catch-up burst.
            self._t0 = now - self._emitted / self.rate_hz
            return
        due = int((now - self._t0) * self.rate_hz) - self._emitted
        if self._remaining is not None:
            due = min(due, self._remaining)
        if due <= 0:
            return
        # The oldest due record was sampled at t0 + emitted/rate; it goes out now.
        late_s = now - (self._t0 + (self._emitted + 1) / self.rate_hz)
        self.log.longest_late_s = max(self.log.longest_late_s, late_s)
        counts, status = self._sample_raw(due)
        self._last_raw = counts[-1].copy()
        counts = counts - self._device_bias
        if self.faults.frozen:
            counts = np.broadcast_to(self._last_counts, counts.shape)
        status = (status | self.faults.status_bits) & 0xFFFFFFFF
        counts = np.clip(counts, -(1 << 31), (1 << 31) - 1)
        self._last_counts = np.array(counts[-1], dtype=np.int64)
        for i in range(due):
            self._queue.append((self._rdt_seq, self._ft_seq & 0xFFFFFFFF, int(status[i]),
                                *(int(v) for v in counts[i])))
            self._rdt_seq = (self._rdt_seq + 1) % (1 << 32)
            self._ft_seq += 1
        self._emitted += due
        if self._remaining is not None:
            self._remaining -= due
        per = 1 if self._mode == 2 else self.records_per_datagram
        finished = self._remaining == 0
        while len(self._queue) >= per or (finished and self._queue):
            records, self._queue = self._queue[:per], self._queue[per:]
            self._send_datagram(records)
        if finished:
            self._flush_held()
            self._mode = 0

    def _send_datagram(self, records: list[tuple[int, ...]]) -> None:
        data = b"".join(_RECORD.pack(*r) for r in records)
        seqs = [r[0] for r in records]
        f = self.faults
        if self._rng.random() < f.loss_fraction:
            self.log.dropped.extend(seqs)
            return
        if self._held is None and self._rng.random() < f.reorder_fraction:
            self._held, self._held_seqs = data, seqs
            return
        copies = 2 if self._rng.random() < f.duplicate_fraction else 1
        for _ in range(copies):
            self._sendto(data, seqs)
        self._flush_held()

    def _flush_held(self) -> None:
        if self._held is not None:
            self._sendto(self._held, self._held_seqs)
            self._held, self._held_seqs = None, []

    def _sendto(self, data: bytes, seqs: list[int]) -> None:
        if self._client is None:
            return
        try:
            self._udp.sendto(data, self._client)
        except OSError:
            self.log.dropped.extend(seqs)     # e.g. client gone: count as lost on the wire
            return
        self.log.transmitted.extend(seqs)
