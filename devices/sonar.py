"""Advanced sonar array on a serial line: the SONAR data frame and the driver.

Data frame (type 0x41, ``docs/devices.md``), all little-endian::

    t_us (u32)  device time of the measurement cycle, us, wrapping
    pan (i16)   pan angle about the array's mount, 1e-4 rad
    n (u8)      number of echoes, then n times:
      kind (u8)      0 plane, 1 corner, 2 edge
      range (u16)    mm
      bearing (i16)  in the transducer frame (the mount rotated by the pan angle), 1e-4 rad

Ranges are quantised to 1 mm and angles to 1e-4 rad (0.006 deg), far below the sensor's
errors (2 % of range, 2 deg).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any, NamedTuple

from devices.driver import Measurement
from devices.frames import (
    DATA_SONAR,
    KIND_SONAR,
    SONAR_SYNC,
    Frame,
    FramedDevice,
    FramedReceiver,
)

KINDS = ("plane", "corner", "edge")
_HEAD = struct.Struct("<IhB")
_ECHO = struct.Struct("<BHh")
MAX_ECHOES = (255 - _HEAD.size) // _ECHO.size
ANGLE_UNIT = 1e-4  # rad
RANGE_UNIT = 1e-3  # m


class Echo(NamedTuple):
    """One classified echo: kind in ``KINDS``, range (m), bearing (rad, transducer frame)."""

    kind: str
    range: float
    bearing: float


def _i16(x: float, unit: float) -> int:
    return max(-32768, min(32767, round(x / unit)))


def encode_reading(t_us: int, pan: float, echoes: tuple | list) -> bytes:
    """The payload of a SONAR data frame: pan (rad) and echoes (kind, range m, bearing rad),
    quantised; ranges beyond 65.535 m saturate."""
    if len(echoes) > MAX_ECHOES:
        raise ValueError(f"at most {MAX_ECHOES} echoes per frame")
    parts = [_HEAD.pack(t_us & 0xFFFFFFFF, _i16(pan, ANGLE_UNIT), len(echoes))]
    for kind, r, b in echoes:
        mm = max(0, min(0xFFFF, round(r / RANGE_UNIT)))
        parts.append(_ECHO.pack(KINDS.index(kind), mm, _i16(b, ANGLE_UNIT)))
    return b"".join(parts)


def decode_reading(payload: bytes) -> tuple[int, float, tuple[Echo, ...]]:
    """(t_us, pan rad, echoes) of a SONAR data payload; ValueError if malformed."""
    if len(payload) < _HEAD.size:
        raise ValueError("short sonar payload")
    t_us, pan, n = _HEAD.unpack_from(payload)
    if len(payload) != _HEAD.size + n * _ECHO.size:
        raise ValueError(f"sonar payload announces {n} echoes, length {len(payload)}")
    echoes = []
    for k in range(n):
        kind, mm, b = _ECHO.unpack_from(payload, _HEAD.size + k * _ECHO.size)
        if kind >= len(KINDS):
            raise ValueError(f"unknown echo kind {kind}")
        echoes.append(Echo(KINDS[kind], mm / 1000.0, b / 10000.0))
    return t_us, pan / 10000.0, tuple(echoes)


@dataclass(frozen=True)
class SonarFrame(Measurement):
    """One measurement cycle of sonar array ``array`` (its index in the robot
    configuration): ``t`` log time of the cycle (device time mapped), ``t_host`` log time of
    the read that completed the frame, ``t_device`` the device's counter (us), ``seq`` the
    frame counter, ``pan`` (rad), ``echoes``."""

    t: float
    t_host: float
    t_device: int
    seq: int
    array: int
    pan: float
    echoes: tuple[Echo, ...]


class SonarReceiver(FramedReceiver):
    """Receiver (no I/O) of a sonar array's frames."""

    data_type = DATA_SONAR

    def __init__(self, array: int = 0, device_clock: bool = True) -> None:
        super().__init__(SONAR_SYNC, device_clock)
        self.array = array

    def recording_header(self) -> dict[str, Any]:
        return {"array": self.array, **super().recording_header()}

    def _measurement(self, frame: Frame, t: float) -> SonarFrame:
        t_us, pan, echoes = decode_reading(frame.payload)
        return SonarFrame(self.stamp(t_us, t), t, t_us, frame.seq, self.array, pan, echoes)


class SonarArray(FramedDevice):
    """Driver of one advanced sonar array; its readings are labelled with ``array``, the
    array's index in the robot configuration."""

    kind = "sonar"
    sync = SONAR_SYNC
    device_kind = KIND_SONAR

    def __init__(
        self, port: str, array: int = 0, *, device_clock: bool = True, **options: Any
    ) -> None:
        """``options``: :class:`devices.frames.FramedDevice`'s (baud, clock, recorder,
        reply_timeout, retries)."""
        super().__init__(port, SonarReceiver(array, device_clock), **options)
        self.array = array
