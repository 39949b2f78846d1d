"""What every driver shares: the serial port (pyserial), recording, statistics, and a thread
that keeps a device running (reopening it after a disconnect).

A driver is a :class:`SerialDevice` around a *receiver*: a pure object (no I/O) that turns
timestamped byte chunks into frames. The driver records every chunk it reads, and every port
event that changes how bytes are decoded (open, baud change), before handing it to the
receiver; replaying a recording through a fresh receiver therefore gives the same frames, with
the same timestamps, as the live run (:mod:`devices.replay`).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any, Protocol

import serial

from devices.clock import Clock
from devices.raw import RawRecorder

READ_SLICE = 0.05  # s, longest single blocking read (bounds the reaction to stop requests)

try:  # pyserial lets termios errors through on some ports; they are port errors
    import termios

    _PORT_ERRORS: tuple[type[BaseException], ...] = (termios.error,)
except ImportError:  # pragma: no cover - not POSIX
    _PORT_ERRORS = ()


def is_pseudo_terminal(port: str) -> bool:
    """Whether ``port`` (possibly a symlink) is a pseudo-terminal, which has no parity."""
    return os.path.realpath(port).startswith("/dev/pts/")


class AttentiveTimer:
    """Seconds a thread spent waiting for a device, counted in steps of at most ``cap`` s.

    A driver thread waits in short reads (:data:`READ_SLICE`); between two :meth:`tick`
    calls it may also have been stopped by the host (CPU load, another thread holding the
    GIL), and that time says nothing about the device. Each step counts at most ``cap``, so
    a device is declared silent, or a reply overdue, after that much *attentive* waiting:
    the margin grows by itself when the host is behind. Not thread safe (one owner).
    """

    def __init__(self, cap: float = 4 * READ_SLICE) -> None:
        self.cap = cap
        self.reset()

    def reset(self) -> None:
        """Start counting from zero now."""
        self.elapsed = 0.0
        self._last = time.monotonic()

    def tick(self) -> float:
        """Add the time since the last tick (at most ``cap``); returns the total, s."""
        now = time.monotonic()
        self.elapsed += min(max(now - self._last, 0.0), self.cap)
        self._last = now
        return self.elapsed


class DeviceError(Exception):
    """The device does not answer as its protocol says (no reply, refused command, wrong
    device). Port errors are ``serial.SerialException`` or ``OSError``."""


class Measurement:
    """Base of the data frames drivers deliver (laser scans, sonar readings, odometry)."""

    t: float  # log time of the measurement, s (best estimate)
    t_host: float  # log time of the read that completed the frame, s


class Receiver(Protocol):
    """Turns byte chunks into frames: measurements (subclasses of :class:`Measurement`) and
    protocol replies. ``reset`` starts afresh (the port was opened at ``baud``)."""

    def reset(self, baud: int) -> None: ...

    def set_baud(self, baud: int) -> None: ...

    def feed(self, t: float, data: bytes) -> list[Any]: ...

    def counters(self) -> dict[str, int]: ...


@dataclass
class LinkStats:
    """Counters of a driver's link (beyond its decoder's)."""

    opens: int = 0  # successful opens (connect and configure)
    disconnects: int = 0  # losses of a configured device (port error or silence)
    timeouts: int = 0  # requests that got no reply in time
    naks: int = 0  # requests the device refused (NAK) or answered with an error
    retries: int = 0  # requests sent again


class SerialDevice:
    """A device on a serial port. Subclasses implement :meth:`open` (open the port and
    configure the device) and may override :meth:`read`.

    ``clock`` stamps every read (log time, s); ``recorder``, if given, receives every byte.
    """

    kind = "device"
    parity = serial.PARITY_NONE

    def __init__(
        self,
        port: str,
        receiver: Receiver,
        *,
        clock: Clock | None = None,
        recorder: RawRecorder | None = None,
    ) -> None:
        self.port = port
        self.receiver = receiver
        self.clock = clock or Clock()
        self.recorder = recorder
        self.link = LinkStats()
        self.last_error = ""
        self.port_baud = 0
        self._ser: serial.Serial | None = None
        self._pending: list[Measurement] = []
        self._quiet = AttentiveTimer()  # attentive waiting since the last measurement

    def recording_header(self) -> dict[str, Any]:
        """Header of this device's raw recording: what replay needs to decode it."""
        return {"device": self.kind, "port": self.port}

    # -- port

    @property
    def is_open(self) -> bool:
        return self._ser is not None

    def _open_port(self, baud: int) -> None:
        """Open the port at ``baud``, 8 data bits, the device's parity, 1 stop bit; drop
        whatever the port buffered before."""
        self.close()
        # a pty cannot do parity (some kernels reject it): there it is emulated logically
        parity = serial.PARITY_NONE if is_pseudo_terminal(self.port) else self.parity
        try:
            ser = serial.Serial(
                self.port,
                baud,
                bytesize=serial.EIGHTBITS,
                parity=parity,
                stopbits=serial.STOPBITS_ONE,
                timeout=READ_SLICE,
                write_timeout=2.0,
            )
        except _PORT_ERRORS as exc:
            raise serial.SerialException(f"cannot configure {self.port}: {exc}") from None
        ser.reset_input_buffer()
        self._ser = ser
        self.port_baud = baud
        t = self.clock.now()
        if self.recorder is not None:
            self.recorder.marker(t, "open", baud=baud, port=self.port)
        self.receiver.reset(baud)
        self._quiet.reset()

    def _set_port_baud(self, baud: int) -> None:
        """Change the host side's line rate."""
        assert self._ser is not None
        try:
            self._ser.baudrate = baud
        except _PORT_ERRORS as exc:
            raise serial.SerialException(f"cannot set {baud} baud on {self.port}: {exc}") from None
        self.port_baud = baud
        if self.recorder is not None:
            self.recorder.marker(self.clock.now(), "baud", baud=baud)
        self.receiver.set_baud(baud)

    def _write(self, data: bytes) -> None:
        if self._ser is None:
            raise DeviceError(f"{self.port}: not open")
        if self.recorder is not None:
            self.recorder.sent(self.clock.now(), data)
        self._ser.write(data)

    def _read_items(self, timeout: float) -> list[Any]:
        """Wait up to ``timeout`` s (attentive, see :class:`AttentiveTimer`) for bytes;
        record and decode what arrived."""
        ser = self._ser
        if ser is None:
            raise DeviceError(f"{self.port}: not open")
        waited = AttentiveTimer()
        while True:
            data = ser.read(1)
            if data:
                waiting = ser.in_waiting
                if waiting:
                    data += ser.read(waiting)
                break
            if waited.tick() >= timeout:
                return []
        t = self.clock.now()
        if self.recorder is not None:
            self.recorder.received(t, data)
        return self.receiver.feed(t, data)

    def close(self, reason: str = "closed") -> None:
        """Close the port (safe to call at any time)."""
        ser, self._ser = self._ser, None
        if ser is None:
            return
        if self.recorder is not None:
            self.recorder.marker(self.clock.now(), "close", reason=reason)
        try:
            ser.close()
        except (serial.SerialException, OSError):
            pass

    # -- measurements

    def open(self) -> None:
        """Open the port and bring the device into streaming; DeviceError if it does not
        answer, SerialException/OSError if the port cannot be opened."""
        raise NotImplementedError

    def read(self, timeout: float = 0.1) -> list[Measurement]:
        """Measurements completed within ``timeout`` s (possibly none)."""
        out, self._pending = self._pending, []
        if not out:
            out = [x for x in self._read_items(timeout) if _is_data(x)]
        if out:
            self._quiet.reset()
        else:
            self._quiet.tick()
        return out

    def data_arrived(self) -> None:
        """A measurement came (restarts the count of :meth:`seconds_since_data`)."""
        self._quiet.reset()

    def drain(self) -> list[Measurement]:
        """Measurements decoded but not yet returned by :meth:`read` (e.g. those that came
        in while a request failed): the runner delivers them before reopening, so nothing
        decoded - nothing a replay of the recording would give - is lost."""
        out, self._pending = self._pending, []
        return out

    def seconds_since_data(self) -> float:
        """Seconds this driver has been waiting, attentively (:class:`AttentiveTimer`),
        since the last measurement or the port's opening: the device's silence, not the
        host's."""
        return self._quiet.elapsed

    def counters(self) -> dict[str, int]:
        """All counters: link (opens, disconnects, timeouts, naks, retries) and receiver
        (bytes_in, frames, crc_errors, discarded, dropped_frames, bad_frames, ...)."""
        d = {f.name: getattr(self.link, f.name) for f in fields(self.link)}
        d.update(self.receiver.counters())
        return d

    def __enter__(self) -> SerialDevice:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _is_data(item: Any) -> bool:
    return isinstance(item, Measurement)


class DeviceRunner:
    """Keeps one device running in a thread: opens it (retrying every ``reopen_interval``
    s), reads, and passes each measurement to ``sink``; on a port error, or when no
    measurement came for ``silence_timeout`` s of attentive waiting (a device that stopped
    answering, not a host too busy to read it: :class:`AttentiveTimer`), it closes and
    reopens. ``stop()`` ends the thread and closes the port."""

    def __init__(
        self,
        device: SerialDevice,
        sink: Callable[[Measurement], None],
        *,
        reopen_interval: float = 0.5,
        silence_timeout: float = 3.0,
        name: str | None = None,
    ) -> None:
        self.device = device
        self.sink = sink
        self.reopen_interval = reopen_interval
        self.silence_timeout = silence_timeout
        self.connected = threading.Event()
        self.disconnect_times: list[float] = []  # log time of each loss of the device
        self.down_since = time.monotonic()  # wall time it was last lost (or created)
        self.error: BaseException | None = None  # an exception from the sink, fatal
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name=name or f"fgslam-{device.kind}", daemon=True
        )

    def start(self) -> DeviceRunner:
        self.down_since = time.monotonic()
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def _run(self) -> None:
        dev = self.device
        try:
            while not self._stop.is_set():
                try:
                    if not dev.is_open:
                        dev.open()
                        self.connected.set()
                    for m in dev.read(0.1):
                        self.sink(m)
                    if dev.seconds_since_data() > self.silence_timeout:
                        raise DeviceError(f"no data for {self.silence_timeout:g} s")
                except (DeviceError, serial.SerialException, OSError, *_PORT_ERRORS) as exc:
                    dev.last_error = f"{type(exc).__name__}: {exc}"
                    if self.connected.is_set():
                        dev.link.disconnects += 1
                        self.disconnect_times.append(dev.clock.now())
                        self.down_since = time.monotonic()
                        self.connected.clear()
                    for m in dev.drain():
                        self.sink(m)
                    dev.close(reason=dev.last_error)
                    self._stop.wait(self.reopen_interval)
            for m in dev.drain():
                self.sink(m)
        except BaseException as exc:  # a bug or a failing sink: keep it for the owner
            self.error = exc
        finally:
            self.connected.clear()
            dev.close(reason="stopped")
