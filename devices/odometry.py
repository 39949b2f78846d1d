"""Odometry board on a serial line: the ODOMETRY data frame and the driver.

Data frame (type 0x40, ``docs/devices.md``), one per encoder sample, little-endian::

    t_us (u32)   device time at the end of the sample, us, wrapping
    right (i16)  encoder tick increment of the right wheel over the sample
    left (i16)   same, left wheel
    status (u8)  bit 0: right encoder fault, bit 1: left encoder fault,
                 bit 2: an increment saturated at the i16 limits
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

from devices.driver import Measurement
from devices.frames import (
    DATA_ODOMETRY,
    KIND_ODOMETRY,
    ODOMETRY_SYNC,
    Frame,
    FramedDevice,
    FramedReceiver,
)

_SAMPLE = struct.Struct("<IhhB")
FAULT_RIGHT, FAULT_LEFT, SATURATED = 0x01, 0x02, 0x04


def encode_sample(t_us: int, right: int, left: int, status: int = 0) -> bytes:
    """The payload of an ODOMETRY data frame; increments beyond i16 saturate (status bit 2)."""
    r, l = max(-32768, min(32767, right)), max(-32768, min(32767, left))
    if (r, l) != (right, left):
        status |= SATURATED
    return _SAMPLE.pack(t_us & 0xFFFFFFFF, r, l, status)


def decode_sample(payload: bytes) -> tuple[int, int, int, int]:
    """(t_us, right, left, status) of an ODOMETRY data payload; ValueError if malformed."""
    if len(payload) != _SAMPLE.size:
        raise ValueError("bad odometry payload length")
    return _SAMPLE.unpack(payload)


@dataclass(frozen=True)
class OdometryFrame(Measurement):
    """One encoder sample: tick increments over the sample ending at ``t`` (device time
    mapped to log time); ``t_host`` log time of the read, ``t_device`` the board's counter
    (us), ``seq`` the frame counter, ``status`` fault bits."""

    t: float
    t_host: float
    t_device: int
    seq: int
    ticks_right: int
    ticks_left: int
    status: int


class OdometryReceiver(FramedReceiver):
    """Receiver (no I/O) of the odometry board's frames."""

    data_type = DATA_ODOMETRY

    def __init__(self, device_clock: bool = True) -> None:
        super().__init__(ODOMETRY_SYNC, device_clock)

    def _measurement(self, frame: Frame, t: float) -> OdometryFrame:
        t_us, r, l, status = decode_sample(frame.payload)
        return OdometryFrame(self.stamp(t_us, t), t, t_us, frame.seq, r, l, status)


class OdometryBoard(FramedDevice):
    """Driver of the odometry board."""

    kind = "odometry"
    sync = ODOMETRY_SYNC
    device_kind = KIND_ODOMETRY

    def __init__(self, port: str, *, device_clock: bool = True, **options: Any) -> None:
        """``options``: :class:`devices.frames.FramedDevice`'s (baud, clock, recorder,
        reply_timeout, retries)."""
        super().__init__(port, OdometryReceiver(device_clock), **options)
