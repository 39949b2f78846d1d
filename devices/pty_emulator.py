"""The pseudo-terminal machinery every device emulator shares (:class:`PtyEmulator`), the
faults it injects (:class:`Faults`) and what it counts (:class:`EmulatorStats`).

Each emulator owns a pty and publishes its slave under a stable path, a symlink
``<link_dir>/<name>`` (like a udev ``/dev/serial/by-id`` link): a disconnect closes the pty
and removes the link, a reconnect creates a new pty and points the link at it, so a driver
reopens the same path. One thread per emulator answers the host's commands and writes the
scheduled output at its due log time (:class:`devices.clock.Clock`, possibly accelerated).

A pty ignores parity and line rate, so both are emulated logically: the emulator reads the
rate the host set on the port (the pty's termios, visible from the master) and, when it
differs from the device's rate, garbles what it sends and ignores what it receives, as a UART
at the wrong rate would. Faults (:class:`Faults`) are drawn from a seeded generator.

The devices themselves are in :mod:`devices.emulators`.
"""

from __future__ import annotations

import contextlib
import heapq
import math
import os
import random
import select
import shutil
import tempfile
import termios
import threading
import time
import tty
from dataclasses import dataclass, field, fields
from pathlib import Path

from devices.clock import Clock

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
