"""The framed binary protocol of the advanced sonar arrays and the odometry board
(specified in ``docs/devices.md``)::

    SYNC (2) | LEN (u8) | TYPE (u8) | SEQ (u16 LE) | PAYLOAD (LEN bytes) | CRC (u16 LE)

CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, not reflected; check value 0x29B1) over every
byte from SYNC through the payload. SYNC is ``AA 53`` ("S") for a sonar array and ``AA 4F``
("O") for the odometry board, so that a swapped cable is noticed. Data frames carry the
device's own frame counter in SEQ (gaps are dropped frames); a reply carries the SEQ of the
command it answers.

This module holds the framing, the commands every device answers (INFO, START, STOP), the
receiver base that counts sequence gaps and maps device time to log time, and the driver base.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass
from typing import Any

from devices.clock import Clock, DeviceTime
from devices.driver import AttentiveTimer, DeviceError, Measurement, SerialDevice
from devices.framing import StreamDecoder
from devices.raw import RawRecorder

SONAR_SYNC = b"\xaaS"
ODOMETRY_SYNC = b"\xaaO"
HEADER = struct.Struct("<2sBBH")  # sync, len, type, seq
HEADER_LEN = HEADER.size  # 6
OVERHEAD = HEADER_LEN + 2
MAX_PAYLOAD = 255
PROTOCOL_VERSION = 1
DEFAULT_BAUD = 115200

# frame types: commands (host to device) < 0x40, data 0x40-0x7F, replies = command | 0x80
CMD_INFO, CMD_START, CMD_STOP = 0x01, 0x02, 0x03
REPLY_BIT = 0x80
TYPE_ERROR = 0xFF  # payload: command type, error code
ERR_UNKNOWN_COMMAND, ERR_BAD_PAYLOAD = 1, 2
DATA_ODOMETRY, DATA_SONAR = 0x40, 0x41
KIND_ODOMETRY, KIND_SONAR = 1, 2
KIND_NAMES = {KIND_ODOMETRY: "odometry board", KIND_SONAR: "sonar array"}
_INFO = struct.Struct("<BBBI")  # version, kind, device id, period (us)


def crc16_ccitt(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE: ``crc16_ccitt(b"123456789") == 0x29B1``."""
    return binascii.crc_hqx(data, 0xFFFF)


def build_frame(sync: bytes, ftype: int, seq: int, payload: bytes = b"") -> bytes:
    """A complete frame."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload longer than {MAX_PAYLOAD} bytes")
    body = HEADER.pack(sync, len(payload), ftype & 0xFF, seq & 0xFFFF) + bytes(payload)
    return body + struct.pack("<H", crc16_ccitt(body))


@dataclass(frozen=True)
class Frame:
    """A decoded frame whose CRC held."""

    type: int
    seq: int
    payload: bytes

    def encode(self, sync: bytes) -> bytes:
        return build_frame(sync, self.type, self.seq, self.payload)


class FrameDecoder(StreamDecoder):
    """Streaming decoder of frames starting with ``sync``."""

    def __init__(self, sync: bytes) -> None:
        super().__init__(sync, HEADER_LEN)

    def _length(self, buf: bytearray, i: int) -> int:
        return OVERHEAD + buf[i + 2]

    def _valid(self, buf: bytearray, i: int, n: int) -> bool:
        crc = crc16_ccitt(memoryview(buf)[i : i + n - 2])
        return crc == buf[i + n - 2] | buf[i + n - 1] << 8

    def _item(self, frame: bytes) -> Frame:
        _, _, ftype, seq = HEADER.unpack_from(frame)
        return Frame(ftype, seq, frame[HEADER_LEN:-2])


@dataclass(frozen=True)
class DeviceInfo:
    """The INFO reply: protocol version, device kind, device id (a sonar array's index),
    and the nominal period of its data frames (s)."""

    version: int
    kind: int
    device_id: int
    period: float

    def encode(self) -> bytes:
        return _INFO.pack(self.version, self.kind, self.device_id, round(self.period * 1e6))

    @classmethod
    def decode(cls, payload: bytes) -> DeviceInfo:
        if len(payload) != _INFO.size:
            raise ValueError("bad INFO payload")
        v, k, i, p = _INFO.unpack(payload)
        return cls(v, k, i, p * 1e-6)


class FramedReceiver:
    """Receiver (no I/O) base: decodes frames, turns data frames of ``data_type`` into
    measurements with :meth:`_measurement`, passes other frames (replies) through.

    Counts ``dropped_frames`` (gaps in the data frames' SEQ), ``duplicates`` (a repeated
    SEQ, ignored) and ``bad_frames`` (data frames whose payload does not parse). With
    ``device_clock`` a measurement's time is its device time mapped to log time
    (:class:`devices.clock.DeviceTime`); otherwise the host stamp.
    """

    data_type = -1

    def __init__(self, sync: bytes, device_clock: bool = True) -> None:
        self.decoder = FrameDecoder(sync)
        self.device_clock = device_clock
        self.time = DeviceTime()
        self.last_seq: int | None = None
        self.dropped_frames = 0
        self.duplicates = 0
        self.bad_frames = 0
        self.measurements = 0

    def reset(self, baud: int) -> None:
        self.decoder.reset()
        self.last_seq = None  # frames lost while disconnected are not counted as gaps

    def set_baud(self, baud: int) -> None:
        self.decoder.reset()

    def stamp(self, device_us: int, t_host: float) -> float:
        return self.time.map(device_us, t_host) if self.device_clock else t_host

    def recording_header(self) -> dict[str, Any]:
        """What replay needs of this receiver to decode a recording the same way."""
        return {"device_clock": self.device_clock}

    def _measurement(self, frame: Frame, t: float) -> Measurement:
        raise NotImplementedError

    def feed(self, t: float, data: bytes) -> list[Any]:
        out: list[Any] = []
        for frame in self.decoder.feed(data):
            if frame.type != self.data_type:
                out.append(frame)
                continue
            if self.last_seq is not None:
                gap = (frame.seq - self.last_seq - 1) & 0xFFFF
                if gap == 0xFFFF:
                    self.duplicates += 1
                    continue
                if gap < 0x8000:  # else the counter restarted: resynchronise silently
                    self.dropped_frames += gap
            self.last_seq = frame.seq
            try:
                m = self._measurement(frame, t)
            except (ValueError, struct.error):
                self.bad_frames += 1
                continue
            self.measurements += 1
            out.append(m)
        return out

    def counters(self) -> dict[str, int]:
        d = self.decoder.stats.as_dict()
        d.update(
            measurements=self.measurements,
            dropped_frames=self.dropped_frames,
            duplicates=self.duplicates,
            bad_frames=self.bad_frames,
            clock_restarts=self.time.restarts,
        )
        return d


class FramedDevice(SerialDevice):
    """Driver base of a framed-protocol device: :meth:`open` opens the port (8N1 at
    ``baud``), asks INFO (checking the device kind), and sends START. Commands wait
    ``reply_timeout`` s and are sent again up to ``retries`` times. The devices pass their
    receiver and these options on."""

    sync = b""
    device_kind = 0

    def __init__(
        self,
        port: str,
        receiver: FramedReceiver,
        *,
        baud: int = DEFAULT_BAUD,
        clock: Clock | None = None,
        recorder: RawRecorder | None = None,
        reply_timeout: float = 0.3,
        retries: int = 2,
    ) -> None:
        super().__init__(port, receiver, clock=clock, recorder=recorder)
        self.baud = baud
        self.reply_timeout = reply_timeout
        self.retries = retries
        self.info: DeviceInfo | None = None
        self._seq = 0

    def recording_header(self) -> dict[str, Any]:
        """The port's header and the receiver's (:meth:`FramedReceiver.recording_header`)."""
        return {**super().recording_header(), **self.receiver.recording_header()}

    def command(self, ctype: int, payload: bytes = b"", retries: int | None = None) -> Frame:
        """Send a command and return its reply frame; DeviceError on an error reply or when
        no reply comes."""
        retries = self.retries if retries is None else retries
        self._seq = (self._seq + 1) & 0xFFFF
        seq = self._seq
        frame = build_frame(self.sync, ctype, seq, payload)
        for attempt in range(retries + 1):
            if attempt:
                self.link.retries += 1
            self._write(frame)
            waited = AttentiveTimer()  # attentive: a busy host is not a late device
            while (left := self.reply_timeout - waited.tick()) > 0:
                reply = None
                for item in self._read_items(min(left, 0.05)):  # the whole chunk: keep data
                    if isinstance(item, Measurement):
                        self._pending.append(item)
                    elif reply is None and item.seq == seq:
                        if item.type in (ctype | REPLY_BIT, TYPE_ERROR):
                            reply = item
                if reply is not None and reply.type == TYPE_ERROR:
                    self.link.naks += 1
                    raise DeviceError(f"{self.port}: device refused command 0x{ctype:02x}")
                if reply is not None:
                    return reply
            self.link.timeouts += 1
        raise DeviceError(f"{self.port}: no reply to command 0x{ctype:02x}")

    def open(self) -> None:
        """Open the port, check the device kind (INFO) and start the data stream."""
        try:
            self._open_port(self.baud)
            info = DeviceInfo.decode(self.command(CMD_INFO).payload)
            if info.kind != self.device_kind:
                raise DeviceError(
                    f"{self.port}: answers as a {KIND_NAMES.get(info.kind, 'unknown device')}"
                    f", expected a {KIND_NAMES[self.device_kind]}"
                )
            self.info = info
            self.command(CMD_START)
        except ValueError as exc:
            self.close("open failed")
            raise DeviceError(f"{self.port}: bad INFO reply ({exc})") from None
        except BaseException:
            self.close("open failed")
            raise
        self.link.opens += 1
        self.data_arrived()
