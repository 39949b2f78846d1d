"""SICK PLS (the LMS2xx telegram family) on a serial line: CRC, telegrams, a streaming
decoder, the B0 measured-values reply, and the driver.

Facts gathered from the public open-source drivers of this scanner family (sicktoolbox,
Player's sicklms200, MRPT's CSickLaserSerial). A telegram is
``STX ADDR LEN(u16 LE) CMD DATA... [STATUS] CRC(u16 LE)``; the host sends address 0x00, the
device answers with 0x80; LEN counts CMD + DATA (+ STATUS), at most 812. Before the reply to a
request the device sends one ACK (0x06) or NAK (0x15) byte. The line is 8E1 (11 bits a byte).

Time registration (docs/design.md, 3.4): the host cannot see when the PLS measured a scan, only when
the frame arrived. A frame is stamped with the log time of the read that completed it minus
the transmission, at the current line rate (``len * 11 / baud``), of the bytes read after it
in the same chunk and of the frame itself: the time its first byte left the scanner (at the
latest). The remaining delay, from the scan to the start of transmission, is not
observable; it is the configured ``laser.delay_min``..``delay_max`` that the front end takes
off (its mean) and turns into covariance (``laser.sigma_time``).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import serial

from devices.clock import Clock
from devices.driver import AttentiveTimer, DeviceError, Measurement, SerialDevice
from devices.framing import StreamDecoder
from devices.raw import RawRecorder

STX, ACK, NAK = 0x02, 0x06, 0x15
HOST_ADDRESS, DEVICE_ADDRESS = 0x00, 0x80
MAX_PAYLOAD = 812  # largest LEN
BITS_PER_BYTE = 11  # 8E1: start bit, 8 data bits, parity, stop bit
CMD_MODE, CMD_SCAN, CMD_STATUS, CMD_TYPE = 0x20, 0x30, 0x31, 0x3A
REPLY_MODE, REPLY_VALUES, REPLY_STATUS = 0xA0, 0xB0, 0xB1
REPLY_NOT_ACK = 0x92  # "not acknowledged" reply telegram
MODE_INSTALLATION, MODE_STREAM, MODE_REQUEST = 0x00, 0x24, 0x25
BAUD_MODES = {9600: 0x42, 19200: 0x41, 38400: 0x40, 500000: 0x48}
PLS_PASSWORD = b"SICK_PLS"
LMS_PASSWORD = b"SICK_LMS"
# special distance values (13-bit field); every value from 8183 up means "no usable return"
SPECIAL_DISTANCES = {
    8191: "invalid",
    8190: "dazzling",
    8189: "overflow",
    8187: "signal-to-noise too low",
    8183: "above maximum",
}
FIRST_SPECIAL = 8183
DISTANCE_MASK = 0x1FFF


def crc16(data: bytes | bytearray | memoryview) -> int:
    """The SICK telegram CRC (not a catalogue CRC-16): per byte, shift the register once
    (XOR 0x8005 if its top bit was set), then XOR ``previous_byte << 8 | byte``.
    ``crc16(b"123456789") == 0xA656``."""
    crc = 0
    prev = 0
    for b in data:
        if crc & 0x8000:
            crc = ((crc << 1) & 0xFFFF) ^ 0x8005
        else:
            crc = (crc << 1) & 0xFFFF
        crc ^= (prev << 8) | b
        prev = b
    return crc


def build_telegram(address: int, payload: bytes) -> bytes:
    """A complete telegram: STX, ``address``, LEN, ``payload`` (command byte, data and, in
    replies, the status byte) and the CRC."""
    if not 1 <= len(payload) <= MAX_PAYLOAD:
        raise ValueError(f"telegram payload must be 1..{MAX_PAYLOAD} bytes, got {len(payload)}")
    if not 0 <= address <= 0xFF:
        raise ValueError(f"address must be a byte, got {address}")
    body = bytes([STX, address]) + struct.pack("<H", len(payload)) + bytes(payload)
    return body + struct.pack("<H", crc16(body))


@dataclass(frozen=True)
class Telegram:
    """A decoded telegram whose CRC held."""

    address: int
    payload: bytes  # command, data, and in replies the status byte

    @property
    def command(self) -> int:
        return self.payload[0]

    @property
    def data(self) -> bytes:
        return self.payload[1:]

    def encode(self) -> bytes:
        return build_telegram(self.address, self.payload)


@dataclass(frozen=True)
class Control:
    """A lone ACK (0x06) or NAK (0x15) byte between telegrams."""

    code: int


class TelegramDecoder(StreamDecoder):
    """Streaming decoder of telegrams sent with ``address`` (0x80: device to host; 0x00 for
    an emulator decoding the host's requests). Resynchronises on ``02 <address>``, rejects
    LEN 0 or above 812, advances one byte after a CRC failure. With ``controls`` lone
    ACK/NAK bytes between telegrams are returned as :class:`Control` (and not counted as
    discarded)."""

    def __init__(self, address: int = DEVICE_ADDRESS, controls: bool = False) -> None:
        super().__init__(bytes([STX, address]), 4)
        self.controls = controls

    def _length(self, buf: bytearray, i: int) -> int:
        n = buf[i + 2] | buf[i + 3] << 8
        return n + 6 if 1 <= n <= MAX_PAYLOAD else 0

    def _valid(self, buf: bytearray, i: int, n: int) -> bool:
        return crc16(memoryview(buf)[i : i + n - 2]) == buf[i + n - 2] | buf[i + n - 1] << 8

    def _item(self, frame: bytes) -> Telegram:
        return Telegram(frame[1], frame[4:-2])

    def _skip(self, buf: bytearray, a: int, b: int, out: list[Any]) -> None:
        if not self.controls:
            self.stats.discarded += b - a
            return
        for k in range(a, b):
            if buf[k] in (ACK, NAK):
                out.append(Control(buf[k]))
            else:
                self.stats.discarded += 1


def mode_payload(mode: int, password: bytes = b"") -> bytes:
    """Payload of an operating-mode request ``20 <mode>`` (installation mode: + password)."""
    return bytes([CMD_MODE, mode]) + password


def baud_payload(baud: int) -> bytes:
    """Payload of the request to switch the line to ``baud``."""
    if baud not in BAUD_MODES:
        raise ValueError(f"the PLS runs at {sorted(BAUD_MODES)} baud, not {baud}")
    return mode_payload(BAUD_MODES[baud])


def transmission_time(n_bytes: int, baud: int) -> float:
    """Seconds that ``n_bytes`` take on an 8E1 line at ``baud``."""
    return n_bytes * BITS_PER_BYTE / baud


# ---------------------------------------------------------------------------------------------
# B0: measured values


@dataclass(frozen=True, eq=False)
class MeasuredValues:
    """A parsed B0 reply. ``distances`` are the 13-bit distance fields in units of
    ``1 / divisor`` m (100: cm, 1000: mm); ``flags`` the top 3 bits of each value."""

    distances: np.ndarray = field(repr=False)  # uint16
    flags: np.ndarray = field(repr=False)  # uint8
    divisor: int
    partial: bool
    partial_index: int
    status: int

    @property
    def severity(self) -> int:
        """Status bits 0-2: 0 no error, 1 info, 2 warning, 3 error, 4 fatal."""
        return self.status & 0x07

    @property
    def restart(self) -> bool:
        return bool(self.status & 0x20)

    @property
    def implausible(self) -> bool:
        return bool(self.status & 0x40)

    @property
    def pollution(self) -> bool:
        return bool(self.status & 0x80)

    def ranges(self) -> np.ndarray:
        """Ranges in m; NaN for every special value (>= 8183) and for 0."""
        d = self.distances
        r = d / float(self.divisor)
        r[(d >= FIRST_SPECIAL) | (d == 0)] = np.nan
        return r


def parse_b0(payload: bytes) -> MeasuredValues:
    """Parse a B0 payload ``B0 info(u16) N x value(u16) status``; ValueError if malformed.
    info bits 0-9: N; 11-12: partial scan index; 13: partial scan; 14-15: unit (0 cm, 1 mm)."""
    if len(payload) < 4 or payload[0] != REPLY_VALUES:
        raise ValueError("not a B0 reply")
    info = payload[1] | payload[2] << 8
    n = info & 0x3FF
    if len(payload) != 4 + 2 * n:
        raise ValueError(f"B0 reply announces {n} values but holds {(len(payload) - 4) / 2:g}")
    unit = info >> 14
    if unit > 1:
        raise ValueError(f"B0 reply has an unknown unit code {unit}")
    raw = np.frombuffer(payload, dtype="<u2", count=n, offset=3)
    return MeasuredValues(
        distances=(raw & DISTANCE_MASK).astype(np.uint16),
        flags=(raw >> 13).astype(np.uint8),
        divisor=1000 if unit == 1 else 100,
        partial=bool(info & 0x2000),
        partial_index=(info >> 11) & 0x3,
        status=payload[-1],
    )


def encode_b0(
    distances: Any,
    *,
    mm: bool = False,
    status: int = 0x10,
    flags: Any = None,
    partial_index: int | None = None,
) -> bytes:
    """A B0 payload from distance fields (cm, or mm with ``mm``; 8183..8191 special), with
    optional per-value flag bits (0..7) and a partial-scan index."""
    d = np.asarray(distances, dtype=np.int64)
    if d.ndim != 1 or d.size > 0x3FF or (d < 0).any() or (d > DISTANCE_MASK).any():
        raise ValueError("distances must be 1-D, at most 1023 values in 0..8191")
    v = d if flags is None else d | (np.asarray(flags, dtype=np.int64) << 13)
    info = d.size | (0x4000 if mm else 0)
    if partial_index is not None:
        info |= 0x2000 | (partial_index & 3) << 11
    return (
        bytes([REPLY_VALUES])
        + struct.pack("<H", info)
        + v.astype("<u2").tobytes()
        + bytes([status & 0xFF])
    )


@dataclass(frozen=True, eq=False)
class LaserFrame(Measurement):
    """One scan: ``t`` = log time its first byte left the scanner (read time minus the
    transmission time of it and of the bytes after it in the chunk), ``t_host`` = log time
    of the read that completed it; ``ranges`` in m, beam order of the scanner (first beam
    at -fov/2), NaN = no usable return."""

    t: float
    t_host: float
    ranges: np.ndarray = field(repr=False)
    values: MeasuredValues = field(repr=False)

    @property
    def ok(self) -> bool:
        """A complete scan without error status (severity < 3, not implausible)."""
        v = self.values
        return not v.partial and v.severity < 3 and not v.implausible


class SickReceiver:
    """Receiver (no I/O) of the host side: telegrams from the device, ACK/NAK bytes, and
    B0 replies turned into :class:`LaserFrame`. Counts: decoder counters, ``bad_frames``
    (B0 replies that do not parse; returned as plain telegrams)."""

    def __init__(self) -> None:
        self.decoder = TelegramDecoder(DEVICE_ADDRESS, controls=True)
        self.baud = 9600
        self.bad_frames = 0
        self.scans = 0

    def reset(self, baud: int) -> None:
        self.decoder.reset()
        self.baud = baud

    def set_baud(self, baud: int) -> None:
        self.decoder.reset()  # bytes at the old rate are garbage at the new one
        self.baud = baud

    def feed(self, t: float, data: bytes) -> list[Any]:
        """Decode a chunk read at log time ``t``. A scan is stamped with the time its first
        byte left the scanner: ``t`` less the transmission of the bytes that came after its
        last one in this chunk (a host that read late finds several scans in one chunk: they
        get their own times, not one) and less its own transmission."""
        out: list[Any] = []
        items = self.decoder.feed(data)
        tails = dict(self.decoder.frame_tails)
        for k, item in enumerate(items):
            if isinstance(item, Telegram) and item.command == REPLY_VALUES:
                try:
                    values = parse_b0(item.payload)
                except ValueError:
                    self.bad_frames += 1
                    out.append(item)
                    continue
                end = t - transmission_time(tails.get(k, 0), self.baud)
                tx = transmission_time(len(item.payload) + 6, self.baud)
                out.append(LaserFrame(end - tx, t, values.ranges(), values))
                self.scans += 1
            else:
                out.append(item)
        return out

    def counters(self) -> dict[str, int]:
        d = self.decoder.stats.as_dict()
        d.update(scans=self.scans, bad_frames=self.bad_frames)
        return d


class SickPLS(SerialDevice):
    """Driver of a SICK PLS (or LMS2xx) on a serial port (8E1).

    :meth:`open` finds the scanner's current line rate (trying the last known one, 9600 -
    the power-up rate - the target, then the others), logs in to installation mode and
    switches to ``baud`` if needed, then selects ``mode``: "stream" (continuous values,
    ``20 24``) or "request" (``20 25``; :meth:`read` then asks for one scan, ``30 01``, at a
    time). Every request waits ``ack_timeout`` s for ACK/NAK and ``reply_timeout`` s (plus
    the longest telegram's transmission time) for the reply, and is sent again up to
    ``retries`` times after a NAK or a timeout.
    """

    kind = "sick-pls"
    parity = serial.PARITY_EVEN
    PROBE_BAUDS = (9600, 38400, 19200, 500000)

    def __init__(
        self,
        port: str,
        *,
        baud: int = 38400,
        mode: str = "stream",
        password: bytes = PLS_PASSWORD,
        clock: Clock | None = None,
        recorder: RawRecorder | None = None,
        ack_timeout: float = 0.3,
        reply_timeout: float = 0.5,
        retries: int = 2,
    ) -> None:
        if baud not in BAUD_MODES:
            raise ValueError(f"the PLS runs at {sorted(BAUD_MODES)} baud, not {baud}")
        if mode not in ("stream", "request"):
            raise ValueError(f"mode must be 'stream' or 'request', got {mode!r}")
        super().__init__(port, SickReceiver(), clock=clock, recorder=recorder)
        self.baud = baud
        self.mode = mode
        self.password = password
        self.ack_timeout = ack_timeout
        self.reply_timeout = reply_timeout
        self.retries = retries
        self.known_baud: int | None = None  # the scanner's line rate when last seen

    # -- requests

    def request(
        self, payload: bytes, *, retries: int | None = None, ack_timeout: float | None = None
    ) -> Any:
        """Send a request and return its reply: a :class:`Telegram`, or a
        :class:`LaserFrame` for ``30 01``. DeviceError when it is refused (a 92 reply) or
        never answered."""
        retries = self.retries if retries is None else retries
        ack_timeout = self.ack_timeout if ack_timeout is None else ack_timeout
        want = payload[0] | 0x80
        telegram = build_telegram(HOST_ADDRESS, payload)
        for attempt in range(retries + 1):
            if attempt:
                self.link.retries += 1
            self._write(telegram)
            waited, limit = AttentiveTimer(), ack_timeout  # attentive: a busy host is not late
            nak = False
            while not nak:
                left = limit - waited.tick()
                if left <= 0:
                    self.link.timeouts += 1
                    break
                reply: Any = None
                for item in self._read_items(min(left, 0.05)):  # the whole chunk: keep data
                    if isinstance(item, Control):
                        if reply is not None or nak:
                            continue
                        if item.code == ACK:
                            limit = (
                                waited.elapsed
                                + self.reply_timeout
                                + transmission_time(MAX_PAYLOAD + 6, self.port_baud)
                            )
                        else:
                            self.link.naks += 1
                            nak = True
                    elif isinstance(item, LaserFrame):
                        if want == REPLY_VALUES and reply is None and not nak:
                            reply = item
                        else:
                            self._pending.append(item)
                    elif reply is None and not nak and item.command in (want, REPLY_NOT_ACK):
                        reply = item
                if isinstance(reply, LaserFrame):
                    self.data_arrived()
                    return reply
                if reply is not None and reply.command == REPLY_NOT_ACK:
                    self.link.naks += 1
                    raise DeviceError(f"{self.port}: scanner refused request {payload[:2].hex()}")
                if reply is not None:
                    return reply
        raise DeviceError(
            f"{self.port}: no reply to request {payload[:2].hex()} at {self.port_baud} baud "
            f"after {retries + 1} attempt(s)"
        )

    def _mode(self, payload: bytes, what: str) -> None:
        reply = self.request(payload)
        if len(reply.payload) < 2 or reply.payload[1] != 0:
            self.link.naks += 1
            raise DeviceError(f"{self.port}: scanner refused {what}")

    def login(self) -> None:
        """Enter installation mode (needed for a baud change)."""
        self._mode(mode_payload(MODE_INSTALLATION, self.password), "the installation password")

    def set_baud(self, baud: int) -> None:
        """Switch the line rate: the reply comes at the old rate, then both sides switch."""
        self._mode(baud_payload(baud), f"the change to {baud} baud")
        self._set_port_baud(baud)
        self.known_baud = baud
        self.status()  # both ends speak the new rate

    def set_mode(self, mode: str) -> None:
        """'stream' (continuous values) or 'request' (values on request)."""
        self._mode(mode_payload(MODE_STREAM if mode == "stream" else MODE_REQUEST), mode)
        self.mode = mode

    def status(self) -> Telegram:
        """The status reply (B1)."""
        return self.request(bytes([CMD_STATUS]))

    def request_scan(self) -> LaserFrame:
        """One scan on request (``30 01``)."""
        reply = self.request(bytes([CMD_SCAN, 0x01]))
        if not isinstance(reply, LaserFrame):
            raise DeviceError(f"{self.port}: malformed measured-values reply")
        return reply

    # -- device

    def _detect_baud(self) -> int:
        order = [self.known_baud, 9600, self.baud, *self.PROBE_BAUDS]
        bauds = list(dict.fromkeys(b for b in order if b is not None))
        self._open_port(bauds[0])
        for b in bauds:
            if b != self.port_baud:
                self._set_port_baud(b)
            try:
                self.request(bytes([CMD_STATUS]), retries=0)
                return b
            except DeviceError:
                continue
        raise DeviceError(f"{self.port}: no answer from a SICK scanner at {bauds} baud")

    def open(self) -> None:
        """Open the port, find the scanner's rate, log in and switch rate if needed, and
        select the mode. Raises DeviceError, SerialException or OSError."""
        try:
            self.known_baud = self._detect_baud()
            if self.known_baud != self.baud:
                self.login()
                self.set_baud(self.baud)
            self.set_mode(self.mode)
        except BaseException:
            self.close("open failed")
            raise
        self.link.opens += 1
        self.data_arrived()

    def read(self, timeout: float = 0.1) -> list[Measurement]:
        """Scans that arrived within ``timeout`` s (stream mode), or one requested scan."""
        if self.mode == "request" and not self._pending:
            return [self.request_scan()]
        return super().read(timeout)
