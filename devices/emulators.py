"""Device emulators on pseudo-terminals, byte for byte in each device's protocol, and the
playback thread that feeds them measurements at their times.

Each emulator owns a pty and publishes its slave under a stable path, a symlink
``<link_dir>/<name>`` (like a udev ``/dev/serial/by-id`` link): a disconnect closes the pty
and removes the link, a reconnect creates a new pty and points the link at it, so a driver
reopens the same path. One thread per emulator answers the host's commands and writes the
scheduled output at its due log time (:class:`devices.clock.Clock`, possibly accelerated).

A pty ignores parity and line rate, so both are emulated logically: the emulator reads the
rate the host set on the port (the pty's termios, visible from the master) and, when it
differs from the device's rate, garbles what it sends and ignores what it receives, as a UART
at the wrong rate would. Faults (:class:`Faults`) are drawn from a seeded generator.

Emulators take plain numbers (no fgslam types): ``fgslam.online.ports.start_emulators`` feeds them
from the simulator.
"""

from __future__ import annotations

import contextlib
import heapq
import math
import os
import queue
import random
import select
import shutil
import tempfile
import termios
import threading
import time
import tty
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from devices import frames as fr
from devices import sick
from devices.clock import Clock
from devices.odometry import encode_sample
from devices.sonar import encode_reading

_BAUD_CODES = {
    getattr(termios, f"B{b}"): b
    for b in (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000)
    if hasattr(termios, f"B{b}")
}
IMMEDIATE = -math.inf  # due time of replies: before any scheduled output


@dataclass(frozen=True)
class Faults:
    """Faults an emulator injects into what it sends (drawn per frame from ``seed``).

    ``noise``: probability of 1-16 random bytes before a frame; ``drop``: of losing 1-8
    consecutive bytes of it; ``flip``: of one flipped bit in it; ``delay``: of the line
    stalling ``delay_s`` s (log time) before it. ``disconnects``: (log time, down time)
    pairs at which the cable is pulled (scheduled by the playback); ``power_cycle``: a
    reconnect also resets the device (SICK: 9600 baud, values on request). ``nak``: the
    first n commands are refused (SICK: NAK byte; framed devices: error reply); ``mute``:
    the first n commands are ignored.
    """

    seed: int = 0
    noise: float = 0.0
    drop: float = 0.0
    flip: float = 0.0
    delay: float = 0.0
    delay_s: float = 0.1
    disconnects: tuple[tuple[float, float], ...] = ()
    power_cycle: bool = False
    nak: int = 0
    mute: int = 0


@dataclass
class EmulatorStats:
    """What an emulator did: frames and bytes written, commands handled, faults injected,
    frames lost (unplugged, stalled or host not reading), garbled writes (rate mismatch)."""

    frames_sent: int = 0
    bytes_sent: int = 0
    commands: int = 0
    bad_commands: int = 0
    frames_lost: int = 0
    noise_bytes: int = 0
    dropped_bytes: int = 0
    flipped_bits: int = 0
    stalls: int = 0
    disconnects: int = 0
    garbled: int = 0
    overflow_bytes: int = 0

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(order=True)
class _Out:
    due: float
    n: int
    data: bytes = field(compare=False)
    baud: int = field(compare=False)
    frame: bool = field(compare=False)  # a data frame (faults apply) or a reply


class PtyEmulator:
    """Base of the emulators: the pty, the symlink, the thread, output scheduling, faults."""

    kind = "device"

    def __init__(
        self,
        name: str,
        *,
        baud: int,
        clock: Clock | None = None,
        faults: Faults | None = None,
        link_dir: str | os.PathLike[str] | None = None,
        check_baud: bool = True,
    ) -> None:
        self.name = name
        self.baud = baud
        self.clock = clock or Clock()
        self.faults = faults or Faults()
        self.check_baud = check_baud
        self.stats = EmulatorStats()
        self._rng = random.Random(self.faults.seed)
        self._tmp = None if link_dir is not None else tempfile.mkdtemp(prefix="fgslam-emu-")
        self.link_dir = Path(link_dir if link_dir is not None else self._tmp)  # type: ignore[arg-type]
        self.port = str(self.link_dir / name)
        self._lock = threading.RLock()
        self._queue: list[_Out] = []
        self._n = 0
        self._wake_r, self._wake_w = os.pipe()
        self._stop = threading.Event()
        self._master = self._slave = -1
        self.connected = False
        self._host_seen = False  # a host has opened the port
        self._host_open = False  # a host holds it open now
        self.host_gone_since = time.monotonic()  # wall time the host closed it (or start)
        self._down_until: float | None = None
        self._stall_until = -math.inf
        self._stalled = -1
        self._mute_until = -math.inf
        self._ignore = self.faults.mute
        self._refuse = self.faults.nak
        self._plug()
        self._thread = threading.Thread(target=self._run, name=f"emulator-{name}", daemon=True)

    # -- public

    def start(self) -> PtyEmulator:
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread, close the pty, remove the link (and a temporary link dir)."""
        self._stop.set()
        self._wake()
        if self._thread.is_alive():
            self._thread.join(5.0)
        with self._lock:
            self._unplug()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._wake_r = self._wake_w = -1
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)

    def disconnect(self, down: float) -> None:
        """Pull the cable for ``down`` s of log time (the pty is closed and its link removed;
        then a new pty appears under the same link)."""
        with self._lock:
            if self.connected:
                self._unplug()
                self.stats.disconnects += 1
            self._down_until = self.clock.now() + down
        self._wake()

    def stall(self, duration: float) -> None:
        """Stop answering and sending for ``duration`` s of log time (output is lost)."""
        with self._lock:
            self._mute_until = self.clock.now() + duration

    def refuse_next(self, n: int) -> None:
        """Refuse the next ``n`` commands (SICK: NAK)."""
        with self._lock:
            self._refuse += n

    def ignore_next(self, n: int) -> None:
        """Ignore the next ``n`` commands (the host times out)."""
        with self._lock:
            self._ignore += n

    @property
    def ready(self) -> bool:
        """Whether a host has connected and started the data stream."""
        raise NotImplementedError

    def host_gone_for(self) -> float:
        """Wall seconds since a host that had opened the port closed it (0 while one holds
        it open, or before any did)."""
        if self._host_open or not self._host_seen:
            return 0.0
        return time.monotonic() - self.host_gone_since

    def _check_host(self) -> bool:
        """Whether a host holds the port open (the master hangs up when none does)."""
        if not self.connected:
            return False
        try:
            p = select.poll()
            p.register(self._master, select.POLLHUP)
            hup = any(ev & select.POLLHUP for _, ev in p.poll(0))
        except (OSError, ValueError):
            return False
        if not hup and not self._host_open:
            self._host_seen = self._host_open = True
        elif hup and self._host_open:
            self._host_open = False
            self.host_gone_since = time.monotonic()
        return not hup

    def send(self, data: bytes, due: float = IMMEDIATE, frame: bool = False) -> None:
        """Queue bytes to write at log time ``due`` (at the device's current rate)."""
        with self._lock:
            self._n += 1
            heapq.heappush(self._queue, _Out(due, self._n, bytes(data), self.baud, frame))
        self._wake()

    # -- device hooks

    def _on_bytes(self, data: bytes) -> None:
        """Bytes from the host (called with the lock held)."""

    def _on_reconnect(self, power_cycle: bool) -> None:
        """The cable is back (called with the lock held)."""

    def _take_command(self) -> str:
        """Fault injection for one command: 'ignore', 'refuse' or 'ok'."""
        self.stats.commands += 1
        if self._ignore > 0:
            self._ignore -= 1
            return "ignore"
        if self._refuse > 0:
            self._refuse -= 1
            return "refuse"
        return "ok"

    # -- pty

    def _plug(self) -> None:
        m, s = os.openpty()
        tty.setraw(s)
        os.set_blocking(m, False)
        name = os.ttyname(s)
        # the slave is the host's alone: with no host holding it the master hangs up, so
        # the emulator sees a host go (the pty and its buffer live on with the master)
        os.close(s)
        self._master, self._slave = m, -1
        tmp = self.link_dir / f".{self.name}.{os.getpid()}.tmp"
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        os.symlink(name, tmp)
        os.replace(tmp, self.port)
        self.connected = True
        self._host_seen = self._host_open = False
        self.host_gone_since = time.monotonic()

    def _unplug(self) -> None:
        if not self.connected:
            return
        self.connected = False
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.port)
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._master = self._slave = -1
        self.stats.frames_lost += sum(1 for o in self._queue if o.frame)
        self._queue.clear()

    def _wake(self) -> None:
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")

    def host_baud(self) -> int | None:
        """The line rate the host set on its end of the pty (None if unknown)."""
        try:
            return _BAUD_CODES.get(termios.tcgetattr(self._master)[5])
        except (termios.error, OSError):
            return None

    def _rate_ok(self, baud: int) -> bool:
        if not self.check_baud:
            return True
        host = self.host_baud()
        return host is None or host == baud

    # -- thread

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                now = self.clock.now()
                if self._down_until is not None and now >= self._down_until:
                    self._down_until = None
                    self._plug()
                    self._on_reconnect(self.faults.power_cycle)
                timeout = 0.1
                if self._queue:
                    due = max(self._queue[0].due, self._stall_until)
                    timeout = min(timeout, self.clock.wall(due - now))
                if self._down_until is not None:
                    timeout = min(timeout, self.clock.wall(self._down_until - now))
                host = self._check_host()
                if not host:
                    timeout = min(timeout, 0.02)  # a hung-up master is always readable
                fds = [self._wake_r] + ([self._master] if host else [])
            try:
                ready, _, _ = select.select(fds, [], [], max(0.0, timeout))
            except (OSError, ValueError):
                continue  # a descriptor was closed by disconnect()
            if self._wake_r in ready:
                with contextlib.suppress(OSError):
                    os.read(self._wake_r, 4096)
            with self._lock:
                if self.connected and self._master in ready:
                    try:
                        data = os.read(self._master, 4096)
                    except (BlockingIOError, OSError):
                        data = b""
                    if data and self.clock.now() >= self._mute_until:
                        if self._rate_ok(self.baud):
                            self._on_bytes(data)
                        else:
                            self.stats.garbled += 1
                self._flush()

    def _flush(self) -> None:
        """Write every output that is due (lock held)."""
        while self._queue:
            now = self.clock.now()
            head = self._queue[0]
            if head.due > now or self._stall_until > now:
                return
            f, rng = self.faults, self._rng
            if head.frame and f.delay and self._stalled != head.n and rng.random() < f.delay:
                self._stalled = head.n
                self._stall_until = now + f.delay_s
                self.stats.stalls += 1
                continue
            heapq.heappop(self._queue)
            if not self.connected or now < self._mute_until:
                self.stats.frames_lost += head.frame
                continue
            data = head.data
            if head.frame:
                data = self._inject(data)
            if not self._rate_ok(head.baud):
                data = bytes(rng.getrandbits(8) for _ in data)
                self.stats.garbled += 1
            self._write(data)
            self.stats.frames_sent += head.frame

    def _inject(self, data: bytes) -> bytes:
        f, rng = self.faults, self._rng
        if f.drop and rng.random() < f.drop and len(data) > 1:
            k = rng.randint(1, min(8, len(data) - 1))
            i = rng.randrange(len(data) - k + 1)
            data = data[:i] + data[i + k :]
            self.stats.dropped_bytes += k
        if f.flip and rng.random() < f.flip:
            b = bytearray(data)
            i = rng.randrange(len(b) * 8)
            b[i // 8] ^= 1 << (i % 8)
            data = bytes(b)
            self.stats.flipped_bits += 1
        if f.noise and rng.random() < f.noise:
            k = rng.randint(1, 16)
            data = bytes(rng.getrandbits(8) for _ in range(k)) + data
            self.stats.noise_bytes += k
        return data

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        deadline = time.monotonic() + 1.0  # then the host is not reading: bytes are lost
        while view:
            try:
                n = os.write(self._master, view)
                self.stats.bytes_sent += n
                view = view[n:]
            except BlockingIOError:
                if time.monotonic() > deadline or self._stop.is_set():
                    self.stats.overflow_bytes += len(view)
                    return
                select.select([], [self._master], [], 0.01)
            except OSError:
                self.stats.overflow_bytes += len(view)
                return


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
        clock: Clock | None = None,
        faults: Faults | None = None,
        link_dir: str | os.PathLike[str] | None = None,
        password: bytes = sick.PLS_PASSWORD,
        check_baud: bool = True,
        status: int = 0x10,
    ) -> None:
        self.password = password
        self.status_byte = status
        self._decoder = sick.TelegramDecoder(sick.HOST_ADDRESS)
        self._power_on()
        self.scans_offered = 0
        self.scans_skipped = 0
        super().__init__(
            name, baud=9600, clock=clock, faults=faults, link_dir=link_dir, check_baud=check_baud
        )

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
        clock: Clock | None = None,
        faults: Faults | None = None,
        link_dir: str | os.PathLike[str] | None = None,
        check_baud: bool = True,
    ) -> None:
        self.device_id = device_id
        self.period = period
        self.started = False
        self.seq = 0
        self._decoder = fr.FrameDecoder(self.sync)
        super().__init__(
            name, baud=baud, clock=clock, faults=faults, link_dir=link_dir, check_baud=check_baud
        )

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

    def _data(self, t: float, payload: bytes) -> None:
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
        dt = t if device_time is None else device_time
        self._data(t, encode_reading(round(dt * 1e6), pan, list(echoes)))


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
        dt = t if device_time is None else device_time
        self._data(t, encode_sample(round(dt * 1e6), right, left))


class Playback:
    """Runs a time-ordered ``schedule`` of (run time, action) pairs in a thread: each action
    is called with the log time it is due at, ``offset + run time``.

    ``offset`` is the log time at which the run starts: with ``wait_for`` the playback first
    waits (up to ``wait_timeout`` wall s) until ``wait_for()`` is true - e.g. until every
    emulator's host is streaming - so that nothing of the run is sent before the drivers
    listen. Actions that fall behind run at once (the run then lags real time rather than
    skipping data).

    The schedule is computed ahead (a simulation is costly: ray casting, sonar echoes): its
    first ``lead`` s of run time (inf: all of it) in :meth:`start`, before any host can be
    waiting for data, the rest by a thread of its own, so that a busy host delays the start
    rather than the data: emulated devices keep their time as real ones do.
    """

    def __init__(
        self,
        clock: Clock,
        schedule: Iterable[tuple[float, Callable[[float], Any]]],
        *,
        wait_for: Callable[[], bool] | None = None,
        wait_timeout: float = 30.0,
        lead: float = 0.0,
        name: str = "emulator-playback",
    ) -> None:
        self.clock = clock
        self.schedule = schedule
        self.wait_for = wait_for
        self.wait_timeout = wait_timeout
        self.lead = lead
        self.offset = math.nan
        self.done = threading.Event()
        self.started = threading.Event()
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._ahead: queue.Queue[tuple[float, Callable[[float], Any]] | None] = queue.Queue()
        self._computed = -math.inf  # run time of the last action computed
        self._all_computed = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._producer = threading.Thread(target=self._produce, name=f"{name}-ahead", daemon=True)

    def _fill(self, until: float) -> bool:
        """Compute the schedule up to run time ``until``; False once it is exhausted."""
        for item in self._items:
            self._ahead.put(item)
            self._computed = item[0]
            if self._computed >= until or self._stop.is_set():
                return True
        self._ahead.put(None)
        self._all_computed.set()
        return False

    def _produce(self) -> None:
        try:
            if not self._all_computed.is_set():
                self._fill(math.inf)
        except BaseException as exc:
            self.error = exc
            self._ahead.put(None)
            self._all_computed.set()

    def start(self) -> Playback:
        self._items = iter(self.schedule)
        self._fill(self.lead)
        self._producer.start()
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def _run(self) -> None:
        try:
            if self.wait_for is not None:
                deadline = time.monotonic() + self.wait_timeout
                while not self.wait_for() and time.monotonic() < deadline:
                    if self._stop.wait(0.02):
                        return
            self.offset = self.clock.now()
            self.started.set()
            while (item := self._ahead.get()) is not None:
                t, action = item
                due = self.offset + t
                if not self.clock.sleep_until(due, self._stop):
                    return
                action(due)
        except BaseException as exc:
            self.error = exc
        finally:
            self.done.set()
