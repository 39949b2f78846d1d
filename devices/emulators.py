"""Device emulators on pseudo-terminals, byte for byte in each device's protocol: the SICK
PLS (:class:`SickEmulator`), an advanced sonar array (:class:`SonarEmulator`) and the
odometry board (:class:`OdometryEmulator`). The pty, its link, the thread, the output
scheduling and the faults they share are :class:`devices.pty_emulator.PtyEmulator`; the
thread that feeds them measurements at their times is :class:`devices.playback.Playback`.

Emulators take plain numbers (no fgslam types): ``fgslam.online.ports.start_emulators`` feeds them
from the simulator.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

from devices import frames as fr
from devices import sick
from devices.odometry import encode_sample
from devices.pty_emulator import PtyEmulator
from devices.sonar import encode_reading


class SickEmulator(PtyEmulator):
    """A SICK PLS: powers up at 9600 baud with values on request; answers status (31), type
    (3A), installation login (20 00 + password), mode changes (20 24 stream, 20 25 request)
    and baud changes (20 40/41/42/48, only in installation mode; the reply goes out at the
    old rate, then the device switches). A request with a bad CRC gets a NAK, an unknown one
    ACK + a 92 reply.

    :meth:`offer_scan` hands it a scan whose first byte is due at log time ``t``: when
    streaming, it is written so that its last byte leaves at ``t`` (or, when the line is
    still busy with the previous scan, the moment it is free) + its transmission time at
    the current rate. The simulator's scan times already follow the configured line rate
    (with a jittering delay), so a scan is skipped only when the line would still be busy
    with the previous one for more than half a frame: at a lower rate than the configured
    one (at 9600 baud about one scan in four fits). A single-scan request (30 01) is
    answered with the next scan offered.
    """

    kind = "sick-pls"

    def __init__(
        self,
        name: str = "laser",
        *,
        password: bytes = sick.PLS_PASSWORD,
        status: int = 0x10,
        **options: Any,
    ) -> None:
        """``options``: :class:`devices.pty_emulator.PtyEmulator`'s (clock, faults,
        link_dir, check_baud)."""
        self.password = password
        self.status_byte = status
        self._decoder = sick.TelegramDecoder(sick.HOST_ADDRESS)
        self._power_on()
        self.scans_offered = 0
        self.scans_skipped = 0
        super().__init__(name, baud=9600, **options)

    def _power_on(self) -> None:
        self.baud = 9600
        self.streaming = False
        self.installation = False
        self._requests = 0
        self._line_free = -math.inf
        self._decoder.reset()

    @property
    def ready(self) -> bool:
        return self.connected and self.streaming

    def offer_scan(self, t: float, distances: Any, status: int | None = None) -> None:
        """A scan (distance fields in cm, 8183..8191 special) whose first byte is due at
        log time ``t``."""
        with self._lock:
            self.scans_offered += 1
            if not (self.streaming or self._requests):
                return
            st = self.status_byte if status is None else status
            payload = sick.encode_b0(distances, status=st)
            telegram = sick.build_telegram(sick.DEVICE_ADDRESS, payload)
            tx = sick.transmission_time(len(telegram), self.baud)
            if self._requests:
                self._requests -= 1
            elif t < self._line_free - tx / 2:
                self.scans_skipped += 1
                return
            # a line sends one byte after the other: a scan due while the previous one is
            # still going out starts when the line is free
            start = max(t, self._line_free)
            self._line_free = start + tx
            self.send(telegram, start + tx, frame=True)

    def _reply(self, payload: bytes) -> None:
        self.send(bytes([sick.ACK]) + sick.build_telegram(sick.DEVICE_ADDRESS, payload))

    def _on_bytes(self, data: bytes) -> None:
        before = self._decoder.stats.crc_errors
        for tel in self._decoder.feed(data):
            self._handle(tel)
        for _ in range(self._decoder.stats.crc_errors - before):
            self.stats.bad_commands += 1
            self.send(bytes([sick.NAK]))

    def _handle(self, tel: sick.Telegram) -> None:
        what = self._take_command()
        if what == "ignore":
            return
        if what == "refuse":
            self.send(bytes([sick.NAK]))
            return
        cmd, data, st = tel.command, tel.data, self.status_byte
        if cmd == sick.CMD_MODE and data:
            mode = data[0]
            ok = True
            new_baud = None
            if mode == sick.MODE_INSTALLATION:
                ok = data[1:] == self.password
                self.installation = self.installation or ok
            elif mode in (sick.MODE_STREAM, sick.MODE_REQUEST):
                self.streaming = mode == sick.MODE_STREAM
                self.installation = False
            elif mode in sick.BAUD_MODES.values() and len(data) == 1:
                ok = self.installation
                if ok:
                    new_baud = next(b for b, m in sick.BAUD_MODES.items() if m == mode)
            else:
                ok = False
            self._reply(bytes([sick.REPLY_MODE, 0 if ok else 1, st]))
            if new_baud is not None:
                self.baud = new_baud  # the reply above is queued at the old rate
                self._line_free = -math.inf
        elif cmd == sick.CMD_SCAN and data == b"\x01":
            self.send(bytes([sick.ACK]))
            self._requests += 1
        elif cmd == sick.CMD_STATUS and not data:
            self._reply(bytes([sick.REPLY_STATUS]) + b"PLS emulated " + bytes([st]))
        elif cmd == sick.CMD_TYPE and not data:
            self._reply(bytes([sick.CMD_TYPE | 0x80]) + b"PLS101-312" + bytes([st]))
        else:
            self.stats.bad_commands += 1
            self._reply(bytes([sick.REPLY_NOT_ACK, st]))

    def _on_reconnect(self, power_cycle: bool) -> None:
        if power_cycle:
            self._power_on()
        self._decoder.reset()


class FramedEmulator(PtyEmulator):
    """Base of the sonar and odometry emulators: answers INFO, START, STOP; numbers its
    data frames; streams only after START."""

    sync = b""
    device_kind = 0
    data_type = 0

    def __init__(
        self,
        name: str,
        *,
        device_id: int = 0,
        period: float = 0.01,
        baud: int = fr.DEFAULT_BAUD,
        **options: Any,
    ) -> None:
        """``options``: :class:`devices.pty_emulator.PtyEmulator`'s (clock, faults,
        link_dir, check_baud)."""
        self.device_id = device_id
        self.period = period
        self.started = False
        self.seq = 0
        self._decoder = fr.FrameDecoder(self.sync)
        super().__init__(name, baud=baud, **options)

    @property
    def ready(self) -> bool:
        return self.connected and self.started

    def _on_bytes(self, data: bytes) -> None:
        before = self._decoder.stats.crc_errors
        for f in self._decoder.feed(data):
            what = self._take_command()
            if what == "ignore":
                continue
            if what == "refuse" or f.type not in (fr.CMD_INFO, fr.CMD_START, fr.CMD_STOP):
                self.stats.bad_commands += 1
                code = fr.ERR_BAD_PAYLOAD if what == "refuse" else fr.ERR_UNKNOWN_COMMAND
                self.send(fr.build_frame(self.sync, fr.TYPE_ERROR, f.seq, bytes([f.type, code])))
                continue
            if f.type == fr.CMD_INFO:
                info = fr.DeviceInfo(
                    fr.PROTOCOL_VERSION, self.device_kind, self.device_id, self.period
                )
                payload = info.encode()
            else:
                self.started = f.type == fr.CMD_START
                payload = b"\x00"
            self.send(fr.build_frame(self.sync, f.type | fr.REPLY_BIT, f.seq, payload))
        self.stats.bad_commands += self._decoder.stats.crc_errors - before

    def _on_reconnect(self, power_cycle: bool) -> None:
        if power_cycle:
            self.started = False
            self.seq = 0
        self._decoder.reset()

    def _data(
        self, t: float, device_time: float | None, encode: Callable[..., bytes], *values: Any
    ) -> None:
        """A data frame sent at log time ``t``, its payload ``encode(t_us, *values)`` with
        ``t_us`` the device's clock at ``device_time`` s (default ``t``), in us."""
        payload = encode(round((t if device_time is None else device_time) * 1e6), *values)
        with self._lock:
            if not self.started:
                return
            frame = fr.build_frame(self.sync, self.data_type, self.seq, payload)
            self.seq = (self.seq + 1) & 0xFFFF
            self.send(frame, t, frame=True)


class SonarEmulator(FramedEmulator):
    """An advanced sonar array; :meth:`offer_reading` hands it one measurement cycle."""

    kind = "sonar"
    sync = fr.SONAR_SYNC
    device_kind = fr.KIND_SONAR
    data_type = fr.DATA_SONAR

    def offer_reading(
        self,
        t: float,
        pan: float,
        echoes: Iterable[tuple[str, float, float]],
        device_time: float | None = None,
    ) -> None:
        """Cycle sent at log time ``t``, measured at ``device_time`` s of the device's clock
        (default ``t``): pan (rad), echoes (kind, range m, bearing rad)."""
        self._data(t, device_time, encode_reading, pan, list(echoes))


class OdometryEmulator(FramedEmulator):
    """The odometry board; :meth:`offer_sample` hands it one encoder sample."""

    kind = "odometry"
    sync = fr.ODOMETRY_SYNC
    device_kind = fr.KIND_ODOMETRY
    data_type = fr.DATA_ODOMETRY

    def offer_sample(
        self, t: float, right: int, left: int, device_time: float | None = None
    ) -> None:
        """Sample sent at log time ``t``, ending at ``device_time`` s of the board's clock
        (default ``t``): tick increments of the right and left wheels."""
        self._data(t, device_time, encode_sample, right, left)
