"""The device drivers (and, for tests and trials, their emulators) in a process of their own.

Why: SLAM holds Python's GIL for long stretches (GTSAM's Python factors, numpy). Driver
threads in the same process then read late, and a laser scan - stamped with the time of the
read that completed it - is stamped late by as much: on a loaded host, seconds of log time at
6x emulation, enough to shred the map. In their own process the drivers wake when their bytes
arrive, whatever SLAM is doing, and the stamps no longer depend on the SLAM process's load.

:class:`DeviceProcess` has the interface :func:`fgslam.online.loop.run_online` uses of
:class:`fgslam.online.ports.DevicePorts` (``names``, ``clock``, ``poll``, ``drain``, ``status``,
``errors``, ``wait_connected``, context manager). The child sends, in one ordered pipe, the
events in each device's order and the silence snapshots of :meth:`DevicePorts.poll`, so the
snapshots keep their meaning (every event delivered before a snapshot comes before it), plus
status messages. Log time is shared: both processes' clocks have one origin on the machine's
monotonic clock.
"""

from __future__ import annotations

import contextlib
import math
import os
import queue
import signal
import subprocess
import sys
import threading
import time
import traceback
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from devices.clock import Clock
from devices.pty_emulator import Faults
from fgslam.config import RobotConfig
from fgslam.errors import UserError
from fgslam.events import Event

STATUS_INTERVAL = 0.1  # wall s between status messages of the child
BATCH = 256  # events per message at most
DEVICE_NICE = -10  # the device process's priority where the system allows it (raise_priority)


@dataclass(frozen=True)
class EmulationSpec:
    """Emulated devices to start in the device process (``fgslam.online.ports.start_emulators``):
    the simulated run of ``world`` with ``seed`` for ``duration`` s (None: the whole run),
    with ``faults`` by device name; the playback starts once ``lead`` s of the run are
    computed (inf: all, so that the emulators keep time on a loaded host)."""

    world: str
    seed: int = 0
    duration: float | None = None
    faults: dict[str, Faults] | None = None
    lead: float = math.inf


@dataclass(frozen=True)
class _Spec:
    cfg: RobotConfig
    speed: float
    origin: float
    laser: str | None
    sonar: tuple[str, ...]
    odometry: str | None
    record_dir: str | None
    laser_baud: int | None
    laser_mode: str
    silence_timeout: float
    reopen_interval: float
    world: str
    meta: dict[str, Any] | None
    emulation: EmulationSpec | None


def _child(conn: Any, spec: _Spec, stop: threading.Event) -> None:
    """The device process: drivers (and emulators), events and snapshots into ``conn``."""
    from fgslam.online.ports import DevicePorts, start_emulators

    def send(msg: tuple) -> None:
        conn.send(msg)  # BrokenPipeError: the parent is gone, and so are we

    clock = Clock(spec.speed, origin=spec.origin)
    emu = None
    try:
        try:
            if spec.emulation is not None:
                from fgslam.sim.world import load_world

                e = spec.emulation
                emu = start_emulators(
                    spec.cfg,
                    load_world(e.world),
                    seed=e.seed,
                    speed=spec.speed,
                    duration=e.duration,
                    faults=e.faults,
                    clock=clock,
                    lead=e.lead,
                )
                ports_of = emu.ports
                laser, sonar, odometry = ports_of["laser"], ports_of["sonar"], ports_of["odometry"]
            else:
                laser, sonar, odometry = spec.laser, list(spec.sonar), spec.odometry
            ports = DevicePorts(
                spec.cfg,
                laser=laser,
                sonar=sonar,
                odometry=odometry,
                clock=clock,
                record_dir=spec.record_dir,
                laser_baud=spec.laser_baud,
                laser_mode=spec.laser_mode,
                silence_timeout=spec.silence_timeout,
                reopen_interval=spec.reopen_interval,
                world=spec.world,
                meta=spec.meta,
            )
        except UserError as exc:
            send(("error", "user", str(exc)))
            return
        ports.start()

        def emu_state() -> dict[str, Any]:
            if emu is None:
                return {}
            return {
                "done": emu.done,
                "start_time": emu.start_time,
                "error": repr(emu.playback.error) if emu.playback.error else None,
            }

        send(("ready", ports.names))
        last_connected: dict[str, bool] = {}
        next_status = 0.0
        batch: list[Event] = []
        while not stop.is_set():
            item = ports.poll(0.05)
            if isinstance(item, dict):
                if batch:
                    send(("events", batch))
                    batch = []
                send(("silence", item))
            else:
                batch.append(item)
                if len(batch) >= BATCH:
                    send(("events", batch))
                    batch = []
            now = time.monotonic()
            if now >= next_status:
                next_status = now + STATUS_INTERVAL
                if batch:
                    send(("events", batch))
                    batch = []
                errors = [repr(x) for x in ports.errors()]
                status = ports.status()
                last_connected = {n: d["connected"] for n, d in status.items()}
                send(("status", status, errors, emu_state()))
        last_connected = {n: d["connected"] for n, d in ports.status().items()}
        ports.close()
        batch += ports.drain()
        if batch:
            send(("events", batch))
        emu_info = emu_state()
        if emu is not None:
            emu_info["stats"] = emu.stats()
        final = ports.status()
        for name, d in final.items():  # closed by us at the end, not lost
            d["finished"] = last_connected.get(name, False)
        send(("final", final, [repr(x) for x in ports.errors()], emu_info))
    except (BrokenPipeError, EOFError, OSError) as exc:
        if isinstance(exc, BrokenPipeError | EOFError):
            return  # the parent is gone
        with contextlib.suppress(OSError):
            send(("error", "bug", traceback.format_exc()))
    except BaseException:
        with contextlib.suppress(OSError):
            send(("error", "bug", traceback.format_exc()))
    finally:
        if emu is not None:
            emu.stop()
        with contextlib.suppress(OSError):
            conn.close()


class DeviceProcess:
    """The robot's devices (or an emulation of them) driven in a child process.

    Arguments as for :class:`fgslam.online.ports.DevicePorts` (``speed`` instead of a clock), or
    ``emulation`` to start emulated devices in the child and drive those. :meth:`start`
    raises UserError for what the drivers refuse (a port that is missing, ...).
    After :meth:`close`, :attr:`emulation` holds the emulation's final state (``done``,
    ``start_time``, ``error``, ``stats`` per device) and :meth:`status` the final counters.
    """

    def __init__(
        self,
        cfg: RobotConfig,
        *,
        laser: str | None = None,
        sonar: list[str] | tuple[str, ...] = (),
        odometry: str | None = None,
        speed: float = 1.0,
        record_dir: str | Path | None = None,
        laser_baud: int | None = None,
        laser_mode: str = "stream",
        silence_timeout: float = 3.0,
        reopen_interval: float = 0.5,
        world: str = "online",
        meta: dict[str, Any] | None = None,
        emulation: EmulationSpec | None = None,
        start_timeout: float = 120.0,
    ) -> None:
        if not speed > 0:
            raise UserError(f"--speed must be positive, got {speed}")
        self.clock = Clock(speed)
        self._spec = _Spec(
            cfg,
            float(speed),
            self.clock.origin,
            laser,
            tuple(sonar),
            odometry,
            None if record_dir is None else str(record_dir),
            laser_baud,
            laser_mode,
            silence_timeout,
            reopen_interval,
            world,
            meta,
            emulation,
        )
        self.start_timeout = start_timeout
        self.names: list[str] = []
        self.emulation: dict[str, Any] = {}
        self._items: queue.Queue[Event | dict[str, float]] = queue.Queue()
        self._status: dict[str, dict[str, Any]] = {}
        self._errors: list[str] = []
        self._ready = threading.Event()
        self._connected = threading.Event()
        self._final = threading.Event()
        self._startup_error: tuple[str, str] | None = None
        self._proc: subprocess.Popen | None = None
        self._reader: threading.Thread | None = None
        self._closed = False

    # -- life cycle

    def start(self) -> DeviceProcess:
        if self._proc is not None:
            return self
        # a fresh interpreter running this module (not multiprocessing's spawn, which
        # re-imports the caller's main script), with a message pipe and a control pipe
        r_msg, w_msg = os.pipe()
        r_ctl, w_ctl = os.pipe()
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-m", "fgslam.online.device_process", str(w_msg), str(r_ctl)],
                pass_fds=(w_msg, r_ctl),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
            )
        finally:
            os.close(w_msg)
            os.close(r_ctl)
        self._conn = Connection(r_msg, writable=False)
        self._ctl = Connection(w_ctl, readable=False)
        self._ctl.send(self._spec)
        self._reader = threading.Thread(target=self._read, name="fgslam-devices-pipe", daemon=True)
        self._reader.start()
        deadline = time.monotonic() + self.start_timeout
        while not self._ready.wait(0.1):
            if self._startup_error is not None or not self._reader.is_alive():
                break
            if time.monotonic() > deadline:
                self.close()
                raise RuntimeError("the device process did not start")
        if self._startup_error is not None:
            kind, msg = self._startup_error
            self.close()
            if kind == "user":
                raise UserError(msg)
            raise RuntimeError(f"the device process failed:\n{msg}")
        if not self._ready.is_set():
            self.close()
            raise RuntimeError("the device process ended before it was ready")
        return self

    def _read(self) -> None:
        try:
            while True:
                msg = self._conn.recv()
                tag = msg[0]
                if tag == "events":
                    for ev in msg[1]:
                        self._items.put(ev)
                elif tag == "silence":
                    self._items.put(msg[1])
                elif tag in ("status", "final"):
                    self._status, errors = msg[1], msg[2]
                    self._errors = list(errors)
                    self.emulation = msg[3]
                    if self._status and all(s.get("connected") for s in self._status.values()):
                        self._connected.set()
                    if tag == "final":
                        self._final.set()
                        return
                elif tag == "ready":
                    self.names = list(msg[1])
                    self._ready.set()
                elif tag == "error":
                    if not self._ready.is_set():
                        self._startup_error = (msg[1], msg[2])
                    else:
                        self._errors.append(msg[2])
                    return
        except (EOFError, OSError):
            if not self._final.is_set() and self._ready.is_set():
                self._errors.append("the device process ended unexpectedly")

    def close(self, timeout: float = 10.0) -> None:
        """Stop the drivers (and emulators), wait for their final counters."""
        if self._proc is None or self._closed:
            return
        self._closed = True
        with contextlib.suppress(OSError):
            self._ctl.send("stop")
            self._ctl.close()
        if self._reader is not None:
            self._reader.join(timeout)
        try:
            self._proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(timeout)
        with contextlib.suppress(OSError):
            self._conn.close()

    def __enter__(self) -> DeviceProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- what run_online uses

    def poll(self, timeout: float = 0.05) -> Event | dict[str, float] | None:
        """The next event or silence snapshot (see :meth:`DevicePorts.poll`), None if
        nothing came within ``timeout`` s."""
        try:
            return self._items.get(timeout=timeout)
        except queue.Empty:
            return None

    def drain(self) -> list[Event]:
        """The events received and not yet taken, without waiting."""
        out = []
        while True:
            try:
                item = self._items.get_nowait()
            except queue.Empty:
                return out
            if not isinstance(item, dict):
                out.append(item)

    def wait_connected(self, timeout: float = 10.0) -> bool:
        """Wait until every device is open and configured (or ``timeout`` s passed)."""
        return self._connected.wait(timeout)

    def status(self) -> dict[str, dict[str, Any]]:
        """Per device counters, as :meth:`DevicePorts.status` (the latest the child sent)."""
        return self._status

    def errors(self) -> list[BaseException]:
        """Fatal errors of the device process (bugs), if any."""
        return [RuntimeError(e) for e in self._errors]


def raise_priority(nice: int = DEVICE_NICE) -> int:
    """Lower this process's nice value to ``nice`` where allowed (root, or CAP_SYS_NICE), as
    robots run their drivers: a driver woken by its bytes then runs before batch work, and
    its timestamps keep to milliseconds on a loaded host. Returns the nice value in force
    (unchanged where not allowed)."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except (PermissionError, OSError):
        pass
    return os.getpriority(os.PRIO_PROCESS, 0)


def _main(argv: list[str]) -> None:
    """Entry of the device process: ``python -m fgslam.online.device_process MSG_FD CTL_FD``. The
    control pipe brings the spec, then "stop" - or end of file when the parent is gone
    (even killed), which stops the drivers and closes the recording too."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    raise_priority()
    conn = Connection(int(argv[0]), readable=False)
    ctl = Connection(int(argv[1]), writable=False)
    spec = ctl.recv()
    stop = threading.Event()

    def watch() -> None:
        with contextlib.suppress(EOFError, OSError):
            ctl.recv()
        stop.set()

    threading.Thread(target=watch, name="fgslam-devices-control", daemon=True).start()
    _child(conn, spec, stop)


if __name__ == "__main__":
    _main(sys.argv[1:])
