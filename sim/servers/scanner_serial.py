"""A simulated line scanner speaking the serial protocol of docs/protocols.md.

It sits on a pseudo-terminal (``os.openpty``, slave set raw; the client opens
``.port_path``) or on a loopback TCP port (``.url`` = ``socket://127.0.0.1:PORT``).
Frames are encoded here, independently of the driver's decoder, so a format mistake
shows up in the tests. Exposures are paced on the wall clock at the set rate; the
device clock is ``time.monotonic() + device_clock_offset_s`` and every frame sent is
logged with its true exposure time, for tests to judge the driver's time mapping.

Faults (``ScannerFaults``, indexes are frame positions within the current burst or
stream): garbage bytes before a frame, a frame with a corrupted CRC, a truncated
frame, a short burst (fewer frames, then "DONE k"), a device that goes silent (at
once, or after some frames of a burst). One thread, bounded lifetime, ``stop()``.
"""
from __future__ import annotations

import os
import random
import re
import select
import socket
import struct
import threading
import time
import tty
import zlib
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

_HEADER = struct.Struct("<IQHHffff")
_SYNC = b"\xa5\x5a"
_MISSING = -32768

# (frame_counter, device time in s) -> z in mm (N,), NaN = missing
# (frame_counter, device time s) -> z (mm) on the fixed x grid, or (z, device time s of the
# instant the profile shows) when rendering can lag the schedule (a simulated world), or
# (x, z, that time) for a device that reports each sample's own x (sent as explicit x).
ProfileSource = Callable[[int, float], "np.ndarray | tuple[np.ndarray, float]"]


def encode_frame(frame_counter: int, timestamp_us: int, z_mm: np.ndarray, *, x_scale: float,
                 x_offset: float, z_scale: float, z_offset: float,
                 x_mm: np.ndarray | None = None) -> bytes:
    """One profile frame. NaN, or a depth that does not fit in int16, is sent as missing."""

    def quantize(values: np.ndarray, scale: float, offset: float) -> np.ndarray:
        with np.errstate(invalid="ignore"):
            q = np.rint((np.asarray(values, dtype=np.float64) - offset) / scale)
        bad = ~np.isfinite(q) | (q < -32767) | (q > 32767)
        return np.where(bad, _MISSING, np.nan_to_num(q)).astype("<i2")

    n = int(np.asarray(z_mm).shape[0])
    flags = 0
    body = b""
    if x_mm is not None:
        flags |= 1
        body += quantize(x_mm, x_scale, x_offset).tobytes()
    body += quantize(z_mm, z_scale, z_offset).tobytes()
    payload = _HEADER.pack(frame_counter & 0xFFFFFFFF, timestamp_us & 0xFFFFFFFFFFFFFFFF, n, flags,
                           x_scale, x_offset, z_scale, z_offset) + body
    length = struct.pack("<I", len(payload))
    return _SYNC + length + payload + struct.pack("<I", zlib.crc32(length + payload))


@dataclass
class ScannerFaults:
    garbage_before: set[int] = field(default_factory=set)   # frame positions preceded by garbage
    garbage_bytes: int = 48
    corrupt_crc: set[int] = field(default_factory=set)      # frames whose CRC is wrong
    truncate: set[int] = field(default_factory=set)         # frames cut to their first half
    short_burst_by: int = 0                                  # bursts send this many fewer frames
    silent: bool = False                                     # answers nothing, sends nothing
    silent_after_frames: int | None = None                   # go silent after this many frames


@dataclass
class SentFrame:
    frame_counter: int
    position: int              # index within the burst / stream
    exposure_monotonic_s: float
    fault: str                 # "", "garbage", "crc", "truncated"


@dataclass
class ScannerLog:
    commands: list[str] = field(default_factory=list)
    frames: list[SentFrame] = field(default_factory=list)
    bursts: list[tuple[int, int]] = field(default_factory=list)   # (requested, sent)


class ScannerPtyServer:
    """The simulated scanner. ``transport``: "pty" (default) or "tcp"."""

    def __init__(self, profile_source: ProfileSource, *, n_points: int = 256, x_span_mm: float = 60.0,
                 z_scale_mm: float = 0.002, z_offset_mm: float = 120.0, rate_hz: float = 200.0,
                 model: str = "ELS-256", serial: str = "SIM00042", firmware: str = "1.0.0",
                 transport: str = "pty", host: str = "127.0.0.1", port: int = 0,
                 device_clock_offset_s: float = 0.0, explicit_x: bool = False,
                 native_x_resolution_mm: float = 0.005,
                 faults: ScannerFaults | None = None, seed: int = 0, max_lifetime_s: float = 120.0) -> None:
        if transport not in ("pty", "tcp"):
            raise ValueError("transport is 'pty' or 'tcp'")
        if transport == "tcp" and not host.startswith("127."):
            raise ValueError("the simulated scanner serves loopback addresses only")
        self.profile_source = profile_source
        self.n_points = n_points
        self.x_scale = x_span_mm / (n_points - 1)
        self.x_offset = -x_span_mm / 2.0
        self.z_scale = z_scale_mm
        self.z_offset = z_offset_mm
        self.rate_hz = float(rate_hz)
        self.idn = f"{model},{serial},{firmware}"
        self.transport = transport
        self.device_clock_offset_s = device_clock_offset_s
        self.explicit_x = explicit_x
        # Explicit x of a source's own samples (3-tuples): int16 at this step, centred on 0.
        self.native_x_scale = float(native_x_resolution_mm)
        self.faults = faults or ScannerFaults()
        self.log = ScannerLog()
        self.max_lifetime_s = max_lifetime_s
        self.trigger_mode = "INT"
        self._rng = random.Random(seed)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"scanner-{transport}", daemon=True)
        self._counter = 0
        self._inbuf = bytearray()
        self._remaining: int | None = None     # frames left in the burst; None = no burst/stream
        self._streaming = False
        self._position = 0
        self._burst_sent = 0
        self._next_exposure = 0.0
        self._fd: int | None = None            # pty master
        self._listener: socket.socket | None = None
        self._conn: socket.socket | None = None
        if transport == "pty":
            master, slave = os.openpty()
            tty.setraw(slave)
            os.set_blocking(master, False)
            self._fd, self._slave = master, slave      # the slave stays open: no EIO on the master
            self.port_path = os.ttyname(slave)
            self.url = self.port_path
        else:
            self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listener.bind((host, port))
            self._listener.listen(1)
            self._listener.setblocking(False)
            self.port = self._listener.getsockname()[1]
            self.port_path = None
            self.url = f"socket://{host}:{self.port}"

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "ScannerPtyServer":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        if self._fd is not None:
            os.close(self._fd)
            os.close(self._slave)
            self._fd = None
        if self._conn is not None:
            self._conn.close()
        if self._listener is not None:
            self._listener.close()

    def __enter__(self) -> "ScannerPtyServer":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def device_time_us(self, monotonic_s: float | None = None) -> int:
        t = time.monotonic() if monotonic_s is None else monotonic_s
        return int(round((t + self.device_clock_offset_s) * 1e6))

    # ------------------------------------------------------------------ loop
    def _run(self) -> None:
        deadline = time.monotonic() + self.max_lifetime_s
        while not self._stop.is_set() and time.monotonic() < deadline:
            self._accept()
            wait = 0.01
            if self._active():
                wait = max(0.0, min(wait, self._next_exposure + 0.001 - time.monotonic()))
            data = self._read(wait)
            if data:
                self._inbuf += data
                while b"\n" in self._inbuf:
                    line, _, rest = bytes(self._inbuf).partition(b"\n")
                    self._inbuf = bytearray(rest)
                    self._on_command(line.decode("ascii", "replace").strip())
                if len(self._inbuf) > 1024:          # no newline in 1 kB: not a command
                    self._inbuf.clear()
            self._emit_due()

    def _active(self) -> bool:
        return self._streaming or (self._remaining is not None and self._remaining > 0)

    def _link_fd(self) -> int | None:
        if self._fd is not None:
            return self._fd
        return self._conn.fileno() if self._conn is not None else None

    def _accept(self) -> None:
        if self._listener is None or self._conn is not None:
            return
        try:
            conn, _ = self._listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._conn = conn

    def _drop_conn(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        self._streaming, self._remaining = False, None

    def _read(self, wait_s: float) -> bytes:
        fd = self._link_fd()
        if fd is None:
            self._stop.wait(wait_s)
            return b""
        ready, _, _ = select.select([fd], [], [], wait_s)
        if not ready:
            return b""
        try:
            data = os.read(fd, 4096) if self._fd is not None else self._conn.recv(4096)  # type: ignore[union-attr]
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:
            data = b""
        if not data and self._conn is not None:
            self._drop_conn()                     # client went away; wait for the next one
        return data

    def _write(self, data: bytes) -> None:
        """Write all of ``data``; gives up when stopping or after 2 s of back-pressure."""
        view = memoryview(data)
        give_up = time.monotonic() + 2.0
        while view and not self._stop.is_set() and time.monotonic() < give_up:
            fd = self._link_fd()
            if fd is None:
                return
            _, ready, _ = select.select([], [fd], [], 0.01)
            if not ready:
                continue
            try:
                n = os.write(fd, view) if self._fd is not None else self._conn.send(view)  # type: ignore[union-attr]
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                self._drop_conn()
                return
            view = view[n:]

    def _reply(self, text: str) -> None:
        if not self.faults.silent:
            self._write(text.encode("ascii") + b"\n")

    # ------------------------------------------------------------------ commands
    def _on_command(self, line: str) -> None:
        if not line:
            return
        self.log.commands.append(line)
        if self.faults.silent:
            return
        cmd, _, arg = line.partition(" ")
        cmd = cmd.upper()
        if cmd == "*IDN?":
            self._reply(self.idn)
        elif cmd == "PTS?":
            self._reply(str(self.n_points))
        elif cmd == "TIME?":
            self._reply(str(self.device_time_us()))
        elif cmd == "RATE?":
            self._reply(f"{self.rate_hz:g}")
        elif cmd == "RATE":
            try:
                hz = float(arg)
            except ValueError:
                hz = -1.0
            if 1.0 <= hz <= 10000.0:
                self.rate_hz = hz
                self._reply("OK")
            else:
                self._reply("ERR 2 rate out of range 1..10000")
        elif cmd == "TRIG:MODE?":
            self._reply(self.trigger_mode)
        elif cmd == "TRIG:MODE":
            if arg.strip().upper() in ("INT", "EXT", "SW"):
                self.trigger_mode = arg.strip().upper()
                self._reply("OK")
            else:
                self._reply("ERR 3 trigger mode is INT, EXT or SW")
        elif cmd == "START":
            self._reply("OK")
            self._begin(None)
        elif cmd == "STOP":
            self._streaming, self._remaining = False, None
            self._reply("OK")
        elif cmd == "BURST":
            if re.fullmatch(r"\d{1,6}", arg.strip()) and 1 <= int(arg) <= 100000:
                self._reply("OK")
                self._begin(int(arg))
            else:
                self._reply("ERR 4 burst count 1..100000")
        elif cmd == "TRG":
            if self.trigger_mode == "SW":
                self._reply("OK")
                self._begin(1)
            else:
                self._reply("ERR 5 TRG needs TRIG:MODE SW")
        else:
            self._reply("ERR 1 unknown command")

    def _begin(self, count: int | None) -> None:
        """A burst of ``count`` frames, or a stream (None); the first exposure is now."""
        self._streaming = count is None
        self._remaining = None if count is None else max(0, count - self.faults.short_burst_by)
        self._requested = count
        self._position = 0
        self._burst_sent = 0
        self._next_exposure = time.monotonic()
        if count is not None and self._remaining == 0:
            self._finish_burst()

    def _finish_burst(self) -> None:
        self.log.bursts.append((self._requested or 0, self._burst_sent))
        self._remaining = None
        self._reply(f"DONE {self._burst_sent}")

    # ------------------------------------------------------------------ frames
    def _emit_due(self) -> None:
        # Bounded per loop turn so commands (STOP) are still served during a long burst.
        for _ in range(64):
            if not self._active() or time.monotonic() < self._next_exposure + 0.001:
                return
            f = self.faults
            if f.silent_after_frames is not None and self._position >= f.silent_after_frames:
                f.silent = True
            if f.silent:
                return
            exposure = self._next_exposure
            self._send_frame(exposure)
            self._next_exposure = exposure + 1.0 / self.rate_hz
            if self._remaining is not None:
                self._remaining -= 1
                if self._remaining == 0:
                    self._finish_burst()

    def _send_frame(self, exposure_s: float) -> None:
        counter, pos = self._counter, self._position
        result = self.profile_source(counter, exposure_s + self.device_clock_offset_s)
        x_native = None
        if isinstance(result, tuple):
            # The source says when (device clock, s) the profile it rendered was true: a
            # frame rendered late is stamped with that instant, not with its schedule.
            if len(result) == 3:
                x_native, result, actual_device_s = result
            else:
                result, actual_device_s = result
            exposure_s = max(exposure_s, float(actual_device_s) - self.device_clock_offset_s)
        z = np.asarray(result, dtype=float)
        x_scale, x_offset = self.x_scale, self.x_offset
        if x_native is not None:
            x = np.asarray(x_native, dtype=float)
            x_scale, x_offset = self.native_x_scale, 0.0
        else:
            x = self.x_offset + self.x_scale * np.arange(self.n_points) if self.explicit_x else None
        data = encode_frame(counter, self.device_time_us(exposure_s), z, x_scale=x_scale,
                            x_offset=x_offset, z_scale=self.z_scale, z_offset=self.z_offset, x_mm=x)
        fault = ""
        f = self.faults
        if pos in f.garbage_before:
            junk = bytes(self._rng.randrange(256) for _ in range(f.garbage_bytes))
            self._write(junk)
            fault = "garbage"
        if pos in f.corrupt_crc:
            data = data[:-1] + bytes([data[-1] ^ 0xFF])
            fault = "crc"
        if pos in f.truncate:
            data = data[:len(data) // 2]
            fault = "truncated"
        # Logged before the write: a test may read the frame before this thread runs again.
        self.log.frames.append(SentFrame(counter, pos, exposure_s, fault))
        self._write(data)
        self._counter += 1
        self._position += 1
        self._burst_sent += 1
