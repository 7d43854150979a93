"""Laser line scanner on a serial line (pyserial: a tty, a pty, or ``socket://host:port``).

The protocol (docs/protocols.md) mixes ASCII and binary on one byte stream:
- commands: ASCII lines ending in "\\n"; replies: one ASCII line ("OK", "ERR <code> <text>",
  or a value), "DONE <k>" after a burst;
- profile frames, little-endian: sync A5 5A | length u32 (payload bytes) | payload |
  CRC-32 (IEEE, zlib) of length field + payload, u32. Payload: frame_counter u32,
  timestamp_us u64 (device clock), n u16, flags u16 (bit 0: an x array is present),
  x_scale, x_offset, z_scale, z_offset float32 (mm per count, mm), [x int16 x n],
  z int16 x n; -32768 = missing. Without bit 0, x_i = x_offset + x_scale * i.
ASCII is 7-bit and a frame starts with 0xA5, so the two never look alike. The parser
resynchronises after garbage: it scans for the sync bytes, checks the length bounds
before waiting for a body, checks the CRC, and on any failure moves on by one byte
(a corrupted length must not swallow the good frame after it).

Why no receive thread here (the F/T driver has one): exposure times come from the
device clock, so the moment bytes are read does not matter for timing, and the
controller polls ``read_scans`` every few ms during a burst; the OS buffer holds a
burst in the meantime. Device time is mapped onto the controller clock with the
offset of the ``TIME?`` exchange that had the shortest round trip (NTP-style, error
<= half that round trip), bounded by causality: no exposure after its frame arrived.
"""
from __future__ import annotations

import collections
import re
import struct
import zlib
from dataclasses import dataclass, replace

import numpy as np

from ..core.clock import Clock, RealClock
from ..core.devices import DeviceIdentity, Scan
from ..core.errors import DeviceError, DeviceTimeout, ProtocolError

SYNC = b"\xa5\x5a"
LENGTH = struct.Struct("<I")
CRC = struct.Struct("<I")
PAYLOAD_HEADER = struct.Struct("<IQHHffff")     # 32 bytes
MISSING = -32768
MAX_POINTS = 4096
FLAG_EXPLICIT_X = 0x0001
MIN_PAYLOAD = PAYLOAD_HEADER.size + 2                 # at least one z sample
MAX_PAYLOAD = PAYLOAD_HEADER.size + 4 * MAX_POINTS    # explicit x and z
MAX_LINE = 256
_TEXT_TOKENS = re.compile(rb"\n|[\x20-\x7e]+|\r+|[^\x20-\x7e\r\n]+")


@dataclass(frozen=True)
class Frame:
    """One decoded profile frame; ``x_mm``/``z_mm`` in the scanner frame, NaN = missing."""

    frame_counter: int
    timestamp_us: int
    x_mm: np.ndarray
    z_mm: np.ndarray
    size_bytes: int


def _decode_payload(payload: bytes, size_bytes: int) -> Frame:
    if len(payload) < PAYLOAD_HEADER.size:
        raise ProtocolError(f"frame payload of {len(payload)} bytes is shorter than its header")
    counter, ts_us, n, flags, xs, xo, zs, zo = PAYLOAD_HEADER.unpack_from(payload)
    if flags & ~FLAG_EXPLICIT_X:
        raise ProtocolError(f"unknown frame flags 0x{flags:04x}")
    if not 1 <= n <= MAX_POINTS:
        raise ProtocolError(f"frame with {n} samples (1..{MAX_POINTS})")
    explicit = bool(flags & FLAG_EXPLICIT_X)
    expected = PAYLOAD_HEADER.size + 2 * n * (2 if explicit else 1)
    if len(payload) != expected:
        raise ProtocolError(f"frame of {n} samples needs a {expected}-byte payload, got {len(payload)}")
    if not all(np.isfinite(v) for v in (xs, xo, zs, zo)):
        raise ProtocolError("non-finite scale or offset in a frame")
    body = np.frombuffer(payload, dtype="<i2", offset=PAYLOAD_HEADER.size)
    z_counts = body[n:] if explicit else body
    z_mm = np.where(z_counts == MISSING, np.nan, zo + zs * z_counts.astype(np.float64))
    if explicit:
        x_counts = body[:n]
        x_mm = np.where(x_counts == MISSING, np.nan, xo + xs * x_counts.astype(np.float64))
    else:
        x_mm = xo + xs * np.arange(n, dtype=np.float64)
    return Frame(int(counter), int(ts_us), x_mm, z_mm, size_bytes)


def decode_frame(data: bytes) -> Frame:
    """Decode exactly one complete frame; ``ProtocolError`` on any defect."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"frame must be bytes, not {type(data).__name__}")
    data = bytes(data)
    if len(data) < 6 or data[:2] != SYNC:
        raise ProtocolError("frame does not start with the sync bytes A5 5A")
    (length,) = LENGTH.unpack_from(data, 2)
    if not MIN_PAYLOAD <= length <= MAX_PAYLOAD:
        raise ProtocolError(f"frame length {length} outside {MIN_PAYLOAD}..{MAX_PAYLOAD}")
    if len(data) != 6 + length + 4:
        raise ProtocolError(f"frame is {len(data)} bytes, its header says {6 + length + 4}")
    (crc,) = CRC.unpack_from(data, 6 + length)
    if zlib.crc32(data[2:6 + length]) != crc:
        raise ProtocolError("frame CRC mismatch")
    return _decode_payload(data[6:6 + length], len(data))


@dataclass
class ParserCounters:
    frames: int = 0
    lines: int = 0
    bad_frames: int = 0          # sync + plausible length, but CRC or content wrong, or cut short
    garbage_bytes: int = 0       # bytes that were neither a frame nor part of a text line


class FrameParser:
    """Incremental, resynchronising parser of the scanner's byte stream.

    ``feed_events(data)`` returns frames and text lines (str) in stream order;
    ``feed(data)`` returns the frames and keeps the lines in ``self.lines``. Garbage is
    skipped and counted, never raised; the result does not depend on how the bytes are
    chunked. ``flush_partial`` gives up on a frame whose rest never came (truncated).
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._line = bytearray()
        self.lines: collections.deque[str] = collections.deque(maxlen=1024)
        self.counters = ParserCounters()

    @property
    def pending_bytes(self) -> int:
        return len(self._buf)

    def pending_ends_a_line(self) -> bool:
        """The bytes held for an incomplete frame end in "\\n": output went on after it."""
        return self._buf.endswith(b"\n")

    def feed(self, data: bytes) -> list[Frame]:
        frames = []
        for ev in self.feed_events(data):
            if isinstance(ev, Frame):
                frames.append(ev)
            else:
                self.lines.append(ev)
        return frames

    def feed_events(self, data: bytes) -> list[Frame | str]:
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise ProtocolError(f"parser input must be bytes, not {type(data).__name__}")
        self._buf += data
        return self._parse()

    def flush_partial(self) -> list[Frame | str]:
        """Treat a frame still waiting for bytes as truncated: count it, skip its sync."""
        if self._buf[:1] == SYNC[:1] and (len(self._buf) < 2 or self._buf[:2] == SYNC):
            if len(self._buf) >= 6 and self._plausible_length():
                self.counters.bad_frames += 1
            else:
                self.counters.garbage_bytes += 1
            del self._buf[:1]
            return self._parse(final=True)
        return []

    def _plausible_length(self) -> bool:
        (length,) = LENGTH.unpack_from(self._buf, 2)
        return MIN_PAYLOAD <= length <= MAX_PAYLOAD

    def _parse(self, final: bool = False) -> list[Frame | str]:
        events: list[Frame | str] = []
        buf = self._buf
        while buf:
            i = buf.find(SYNC)
            if i < 0:
                keep = 1 if (buf[-1] == SYNC[0] and not final) else 0
                self._text(bytes(buf[:len(buf) - keep]), events)
                del buf[:len(buf) - keep]
                break
            if i:
                self._text(bytes(buf[:i]), events)
                del buf[:i]
            if len(buf) < 6:
                break
            if not self._plausible_length():
                self._skip_sync_byte()
                continue
            (length,) = LENGTH.unpack_from(buf, 2)
            total = 6 + length + 4
            if len(buf) < total:
                break
            (crc,) = CRC.unpack_from(buf, 6 + length)
            if zlib.crc32(buf[2:6 + length]) != crc:
                self.counters.bad_frames += 1
                self._skip_sync_byte()
                continue
            try:
                frame = _decode_payload(bytes(buf[6:6 + length]), total)
            except ProtocolError:
                self.counters.bad_frames += 1
                self._skip_sync_byte()
                continue
            del buf[:total]
            if self._line:
                # A device never puts a frame inside a reply line: text before a frame is
                # debris (e.g. the tail of a corrupted frame), not the start of the next reply.
                self.counters.garbage_bytes += len(self._line)
                self._line.clear()
            self.counters.frames += 1
            events.append(frame)
        return events

    def _skip_sync_byte(self) -> None:
        # The 0xA5 was not a frame: it is garbage, and it breaks any text line in progress.
        self.counters.garbage_bytes += 1 + len(self._line)
        self._line.clear()
        del self._buf[:1]

    def _text(self, segment: bytes, events: list[Frame | str]) -> None:
        for m in _TEXT_TOKENS.finditer(segment):
            tok = m.group()
            if tok == b"\n":
                if self._line:
                    events.append(self._line.decode("ascii"))
                    self.counters.lines += 1
                    self._line.clear()
            elif tok[0] == 0x0D:
                continue                       # "\r\n" endings are accepted
            elif 0x20 <= tok[0] <= 0x7E:
                self._line += tok
                if len(self._line) > MAX_LINE:
                    self.counters.garbage_bytes += len(self._line)
                    self._line.clear()
            else:
                self.counters.garbage_bytes += len(tok) + len(self._line)
                self._line.clear()


class ShortBurst(DeviceError):
    """A burst ended (the device said DONE, or frames were bad) with fewer profiles than asked."""

    def __init__(self, requested: int, received: int, device_sent: int, bad_frames: int,
                 scans: list[Scan]) -> None:
        self.requested, self.received, self.device_sent = requested, received, device_sent
        self.bad_frames, self.scans = bad_frames, scans
        super().__init__(f"scanner burst short: {received} of {requested} profiles "
                         f"(device sent {device_sent}, {bad_frames} bad frames)")


class BurstTimeout(DeviceTimeout):
    """A burst did not complete before its deadline; ``scans`` holds what did arrive."""

    def __init__(self, message: str, scans: list[Scan]) -> None:
        self.scans = scans
        super().__init__(message)


@dataclass
class ScannerCounters:
    frames: int = 0
    bad_frames: int = 0
    garbage_bytes: int = 0
    short_bursts: int = 0
    timeouts: int = 0
    unexpected_lines: int = 0
    discarded_frames: int = 0


@dataclass
class _Burst:
    requested: int
    ok_event: int | None       # frames after this event number belong to the burst (None: no OK yet)
    deadline_s: float
    bad_frames_at_start: int
    received: int = 0
    done_count: int | None = None


class SerialLineScanner:
    """The line scanner over pyserial, implementing ``LineScanner``.

    ``url``: a device path (/dev/ttyUSB0, a pty) or any pyserial URL (socket://127.0.0.1:PORT).
    ``timeout_s``: deadline for a command reply, and the slack after a burst's nominal
    duration (count / rate) before ``read_scans`` raises ``BurstTimeout``.
    """

    _IDN = re.compile(r"([^,]+),([^,]+),([^,]+)")
    _INT = re.compile(r"(\d+)")
    _NUM = re.compile(r"(\d+(?:\.\d*)?)")

    def __init__(self, url: str, clock: Clock | None = None, timeout_s: float = 1.0, *,
                 baudrate: int = 921600, trigger_mode: str = "INT", rate_hz: float | None = None,
                 idle_flush_s: float = 0.05, raise_on_short: bool = True) -> None:
        import serial  # pyserial; imported here so the CLI does not pay for it

        self.url = url
        self.clock: Clock = clock or RealClock()
        self.timeout_s = float(timeout_s)
        self.idle_flush_s = idle_flush_s
        self.raise_on_short = raise_on_short
        self._serial_exc = serial.SerialException
        try:
            self._port = serial.serial_for_url(url, baudrate=baudrate, timeout=0, write_timeout=timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"scanner {url}: cannot open: {exc}") from exc
        self._parser = FrameParser()
        self._counters = ScannerCounters()
        self._event_no = 0
        self._lines: collections.deque[tuple[int, str]] = collections.deque(maxlen=256)
        self._ready: list[tuple[int, Scan]] = []     # (event number, scan)
        self._burst: _Burst | None = None
        self._last_bytes_s = self.clock.now_s()
        self._time_samples: collections.deque[tuple[float, float]] = collections.deque(maxlen=8)
        self._causal_offset_s = float("inf")
        try:
            self._command("STOP", re.compile("OK"))
            self._ready.clear()                       # anything streamed before STOP is stale
            model, serial_no, firmware = self._command("*IDN?", self._IDN).groups()
            self._points = int(self._command("PTS?", self._INT).group(1))
            self._command(f"TRIG:MODE {trigger_mode}", re.compile("OK"))
            if rate_hz is not None:
                self._command(f"RATE {rate_hz:g}", re.compile("OK"))
            self._rate_hz = float(self._command("RATE?", self._NUM).group(1))
            self.sync_clock()
        except BaseException:
            self._port.close()
            raise
        self._identity = DeviceIdentity("scanner", model.strip(), serial_no.strip(), firmware.strip(),
                                        extra={"url": url, "samples_per_profile": self._points,
                                               "trigger_mode": trigger_mode})

    # ------------------------------------------------------------------ LineScanner
    def identity(self) -> DeviceIdentity:
        return self._identity

    @property
    def samples_per_profile(self) -> int:
        return self._points

    @property
    def rate_hz(self) -> float:
        return self._rate_hz

    def start_burst(self, count: int) -> None:
        """Ask for ``count`` profiles at ``rate_hz``; they arrive through ``read_scans``.

        Profiles not yet read that the device sent before accepting the burst are
        dropped (counted in ``discarded_frames``): a burst delivers only its own.
        """
        if count < 1:
            raise ValueError("a burst needs at least one profile")
        self.sync_clock()
        self._pump()
        # The burst exists before the command is sent: the OK, the frames and even the
        # DONE may all arrive in the one read that finds the OK, and dispatch (in stream
        # order) must already know what they belong to.
        self._burst = _Burst(requested=int(count), ok_event=None,
                             deadline_s=self.clock.now_s() + count / self._rate_hz + self.timeout_s,
                             bad_frames_at_start=self._parser.counters.bad_frames)
        try:
            match_event = self._command(f"BURST {int(count)}", re.compile("OK"), want_event=True)
        except BaseException:
            self._burst = None
            raise
        # Frames from before the OK (a stream, an abandoned burst) belong to no burst.
        stale = sum(1 for event_no, _ in self._ready if event_no <= match_event)
        self._counters.discarded_frames += stale
        self._ready = [(event_no, scan) for event_no, scan in self._ready if event_no > match_event]

    def read_scans(self) -> list[Scan]:
        """Profiles completed since the previous call, oldest first.

        Raises ``ShortBurst`` when the device ends a burst early or frames of it were
        bad, and ``BurstTimeout`` (a ``DeviceTimeout``) when it misses the deadline;
        both carry the scans that did arrive.
        """
        self._pump()
        idle_s = self.clock.now_s() - self._last_bytes_s
        if self._parser.pending_bytes and (
                (idle_s >= self.idle_flush_s and self._parser.pending_ends_a_line())
                or idle_s >= 10 * self.idle_flush_s):
            # A frame waits for bytes that do not come while the device has moved on (a
            # reply line ended after it), or the line has been quiet for long: the device
            # writes whole frames, so this one was truncated. (Without the first
            # condition a frame caught mid-write by a slow writer would be thrown away.)
            self._dispatch(self._parser.flush_partial(), self.clock.now_s())
        out = [scan for _, scan in self._ready]
        self._ready = []
        burst = self._burst
        if burst is None:
            return out
        if burst.received >= burst.requested:
            self._burst = None
        elif burst.done_count is not None:
            self._burst = None
            self._counters.short_bursts += 1
            if self.raise_on_short:
                bad = self._parser.counters.bad_frames - burst.bad_frames_at_start
                raise ShortBurst(burst.requested, burst.received, burst.done_count, bad, out)
        elif self.clock.now_s() > burst.deadline_s:
            self._burst = None
            self._counters.timeouts += 1
            raise BurstTimeout(f"scanner {self.url}: burst got {burst.received} of {burst.requested} "
                               f"profiles by its deadline", out)
        return out

    # ------------------------------------------------------------------ extras
    def start_stream(self) -> None:
        """Continuous profiles at ``rate_hz`` until ``stop_stream``."""
        self._command("START", re.compile("OK"))

    def stop_stream(self) -> None:
        self._command("STOP", re.compile("OK"))
        self._burst = None

    def set_rate(self, rate_hz: float) -> None:
        self._command(f"RATE {rate_hz:g}", re.compile("OK"))
        self._rate_hz = float(self._command("RATE?", self._NUM).group(1))

    def sync_clock(self) -> None:
        """One ``TIME?`` exchange: offset = mid-point of the round trip - device time."""
        t0 = self.clock.now_s()
        device_us = int(self._command("TIME?", self._INT).group(1))
        t1 = self.clock.now_s()
        self._time_samples.append(((t1 - t0) / 2.0, (t0 + t1) / 2.0 - device_us * 1e-6))
        self._causal_offset_s = float("inf")

    @property
    def clock_offset_s(self) -> float:
        """Controller time minus device time (s), as used for exposure times."""
        _, offset = min(self._time_samples)
        return min(offset, self._causal_offset_s)

    @property
    def clock_offset_uncertainty_s(self) -> float:
        """Half the shortest round trip: the bound on the offset's error."""
        return min(self._time_samples)[0]

    def counters(self) -> ScannerCounters:
        c = replace(self._counters)
        c.bad_frames = self._parser.counters.bad_frames
        c.garbage_bytes = self._parser.counters.garbage_bytes
        return c

    def close(self) -> None:
        if self._port.is_open:
            try:
                self._port.write(b"STOP\n")
            except (self._serial_exc, OSError):
                pass
            self._port.close()

    def __enter__(self) -> "SerialLineScanner":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ internals
    def _write(self, text: str) -> None:
        try:
            self._port.write(text.encode("ascii") + b"\n")
        except (self._serial_exc, OSError) as exc:
            raise DeviceError(f"scanner {self.url}: write failed: {exc}") from exc

    def _command(self, text: str, reply: re.Pattern[str], want_event: bool = False):
        """Send one command and wait (bounded by ``timeout_s``) for the matching reply."""
        self._pump()
        self._lines.clear()
        self._write(text)
        deadline = self.clock.now_s() + self.timeout_s
        while True:
            while self._lines:
                event_no, line = self._lines.popleft()
                if line.startswith("ERR"):
                    raise DeviceError(f"scanner {self.url}: {text!r} -> {line}")
                m = reply.fullmatch(line)
                if m:
                    return event_no if want_event else m
                self._counters.unexpected_lines += 1
            if self.clock.now_s() > deadline:
                raise DeviceTimeout(f"scanner {self.url}: no reply to {text!r} within {self.timeout_s} s")
            if not self._pump():
                self.clock.sleep_s(0.0005)

    def _pump(self) -> int:
        """Read what the port has, parse it, dispatch frames and lines. Returns bytes read."""
        total = 0
        for _ in range(64):                      # bounded: at most 64 x 64 kB per call
            try:
                data = self._port.read(65536)
            except (self._serial_exc, OSError) as exc:
                raise DeviceError(f"scanner {self.url}: read failed: {exc}") from exc
            if not data:
                break
            total += len(data)
            now = self.clock.now_s()
            self._last_bytes_s = now
            self._dispatch(self._parser.feed_events(data), now)
        return total

    def _dispatch(self, events: list[Frame | str], arrival_s: float) -> None:
        for ev in events:
            self._event_no += 1
            burst = self._burst
            in_burst = burst is not None and burst.ok_event is not None
            if isinstance(ev, Frame):
                self._counters.frames += 1
                self._ready.append((self._event_no, self._to_scan(ev, arrival_s)))
                if in_burst:
                    burst.received += 1  # type: ignore[union-attr]
            elif ev.startswith("DONE"):
                m = re.fullmatch(r"DONE (\d+)", ev)
                if m and in_burst:
                    burst.done_count = int(m.group(1))  # type: ignore[union-attr]
            else:
                if burst is not None and burst.ok_event is None and ev == "OK":
                    burst.ok_event = self._event_no
                self._lines.append((self._event_no, ev))

    def _to_scan(self, frame: Frame, arrival_s: float) -> Scan:
        t_dev_s = frame.timestamp_us * 1e-6
        # Causality: the exposure happened before the frame was read.
        self._causal_offset_s = min(self._causal_offset_s, arrival_s - t_dev_s)
        return Scan(frame.frame_counter, t_dev_s + self.clock_offset_s, frame.x_mm, frame.z_mm)
