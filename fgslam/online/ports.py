"""Devices as event sources: the drivers on serial ports yield fgslam events, the emulators
are fed by the simulator, and raw recordings replay into the native log.

``devices`` never imports ``fgslam`` (docs/design.md, 1); this module is the bridge:

- :class:`DevicePorts` runs the SICK PLS, sonar array and odometry board drivers in one
  thread each (reopening a device that disconnects while the others go on), optionally
  records every byte into a raw directory, and delivers :mod:`fgslam.events` in arrival
  order from :meth:`DevicePorts.get`.
- :func:`start_emulators` puts the three kinds of devices on pseudo-terminals, fed by a
  simulated run of a world in real time or ``speed`` times faster; ``Emulation.ports``
  names their paths.
- :func:`replay` / :func:`replay_to_log` decode a raw directory through the same decoders.

Times: every event is in log time of the host :class:`devices.clock.Clock` (s, scaled by its
speed). Laser scans are stamped with the time their first byte left the scanner (read time
minus transmission time, ``devices.sick``); sonar readings and odometry samples with their
device time mapped to log time (``devices.clock.DeviceTime``). Docs: ``docs/devices.md``.
"""

from __future__ import annotations

import heapq
import json
import math
import queue
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from devices.clock import Clock
from devices.driver import DeviceRunner, Measurement, SerialDevice
from devices.emulators import OdometryEmulator, SickEmulator, SonarEmulator
from devices.odometry import OdometryBoard, OdometryFrame
from devices.playback import Playback
from devices.pty_emulator import Faults, PtyEmulator
from devices.raw import RawFormatError, RawRecorder, show
from devices.replay import ReplayFile
from devices.sick import FIRST_SPECIAL, LaserFrame, SickPLS
from devices.sonar import SonarArray, SonarFrame
from fgslam.config import RobotConfig, from_dict, load_config
from fgslam.errors import UserError
from fgslam.events import Event, LaserScan, OdometryEvent, SonarEcho, SonarReading, TruthPose
from fgslam.io.logwriter import LogWriter
from fgslam.io.ordering import merge_sources
from fgslam.sim.sensors import SimParams
from fgslam.sim.simulate import Run, events, plan_run
from fgslam.sim.world import World

SESSION_FILE = "session.json"
SESSION_FORMAT = "fgslam-raw-session"
SESSION_VERSION = 1
LASER, ODOMETRY = "laser", "odometry"
SNAPSHOT_INTERVAL = 0.1  # wall s: silence snapshots at least this often (DevicePorts.poll)


def sonar_name(i: int) -> str:
    """Device name of sonar array ``i`` (its index in the robot configuration)."""
    return f"sonar{i}"


# ---------------------------------------------------------------------------------------------
# Conversions


def laser_distances_cm(ranges: np.ndarray) -> np.ndarray:
    """PLS distance fields (cm) of ranges in m; no return (NaN, inf, <= 0) becomes 8183,
    "above maximum"."""
    r = np.asarray(ranges, dtype=float)
    ok = np.isfinite(r) & (r > 0)
    cm = np.full(r.shape, 8183, dtype=np.int64)
    cm[ok] = np.minimum(np.rint(r[ok] * 100.0), FIRST_SPECIAL - 1)
    return cm


def to_event(m: Measurement, cfg: RobotConfig) -> Event | None:
    """The fgslam event of a driver's measurement, or None when it cannot be used: a scan
    that is partial, has an error status or the wrong number of beams; a sonar reading of an
    array the configuration lacks; an odometry sample with an encoder fault. Laser ranges
    beyond ``laser.max_range`` become NaN (no return), as in the simulator."""
    if isinstance(m, LaserFrame):
        if not m.ok or m.ranges.size != cfg.laser.n_beams:
            return None
        r = np.array(m.ranges, dtype=float)
        with np.errstate(invalid="ignore"):
            r[r > cfg.laser.max_range] = np.nan
        return LaserScan(m.t, r)
    if isinstance(m, SonarFrame):
        if not 0 <= m.array < len(cfg.sonar.arrays):
            return None
        return SonarReading(m.t, m.array, m.pan, tuple(SonarEcho(*e) for e in m.echoes))
    if isinstance(m, OdometryFrame):
        if m.status & 0x03:
            return None
        return OdometryEvent(m.t, m.ticks_right, m.ticks_left)
    return None


# ---------------------------------------------------------------------------------------------
# Drivers


class DevicePorts:
    """The robot's devices on serial ports, as one stream of fgslam events.

    ``laser``, ``sonar`` (one port per array, in the configuration's order) and
    ``odometry`` are port paths (None / empty: device absent). Each device runs in its own
    thread (:class:`devices.driver.DeviceRunner`); a device that fails is reopened every
    ``reopen_interval`` s while the others go on, and one silent for ``silence_timeout`` s is
    reopened too. With ``record_dir`` every byte received is recorded there
    (``<name>.raw``, plus ``session.json`` with the configuration) for :func:`replay`.

    Use as a context manager, or :meth:`start` and :meth:`close`; read events with
    :meth:`get` or iterate :meth:`events`; :meth:`status` gives per-device counters.
    """

    def __init__(
        self,
        cfg: RobotConfig,
        *,
        laser: str | None = None,
        sonar: Iterable[str] = (),
        odometry: str | None = None,
        clock: Clock | None = None,
        record_dir: str | Path | None = None,
        laser_baud: int | None = None,
        laser_mode: str = "stream",
        silence_timeout: float = 3.0,
        reopen_interval: float = 0.5,
        world: str = "online",
        meta: dict[str, Any] | None = None,
    ) -> None:
        sonar = list(sonar)
        if len(sonar) > len(cfg.sonar.arrays):
            raise UserError(
                f"{len(sonar)} sonar ports given, the configuration has "
                f"{len(cfg.sonar.arrays)} sonar arrays"
            )
        self.cfg = cfg
        self.clock = clock or Clock()
        self.devices: dict[str, SerialDevice] = {}
        if laser:
            baud = laser_baud or cfg.laser.baud_rate
            try:
                self.devices[LASER] = SickPLS(laser, baud=baud, mode=laser_mode, clock=self.clock)
            except ValueError as exc:
                raise UserError(str(exc)) from None
        for i, port in enumerate(sonar):
            self.devices[sonar_name(i)] = SonarArray(port, i, clock=self.clock)
        if odometry:
            self.devices[ODOMETRY] = OdometryBoard(odometry, clock=self.clock)
        if not self.devices:
            raise UserError("no device port given")
        self.record_dir = Path(record_dir) if record_dir is not None else None
        self._recorders: list[RawRecorder] = []
        if self.record_dir is not None:
            self._start_recording(world, meta or {})
        self.rejected = dict.fromkeys(self.devices, 0)
        self.received = dict.fromkeys(self.devices, 0)
        self._queue: queue.Queue[Event] = queue.Queue()
        self._runners = {
            name: DeviceRunner(
                dev,
                self._sink(name),
                reopen_interval=reopen_interval,
                silence_timeout=silence_timeout,
                name=f"fgslam-{name}",
            )
            for name, dev in self.devices.items()
        }
        self._started = False
        self._next_snapshot = 0.0

    @classmethod
    def for_emulation(cls, cfg: RobotConfig, emu: Emulation, **kw: Any) -> DevicePorts:
        """Ports of emulated devices (:func:`start_emulators`), sharing the emulation's clock
        as drivers in the same process must; ``kw`` as for the constructor."""
        return cls(
            cfg,
            laser=emu.ports["laser"],
            sonar=emu.ports["sonar"],
            odometry=emu.ports["odometry"],
            clock=emu.clock,
            **kw,
        )

    def _start_recording(self, world: str, meta: dict[str, Any]) -> None:
        assert self.record_dir is not None
        try:
            self.record_dir.mkdir(parents=True, exist_ok=True)
            session = {
                "format": SESSION_FORMAT,
                "version": SESSION_VERSION,
                "world": world,
                "clock_speed": self.clock.speed,
                "config": self.cfg.to_dict(),
                "devices": {n: d.recording_header() for n, d in self.devices.items()},
                "meta": meta,
            }
            (self.record_dir / SESSION_FILE).write_text(json.dumps(session, indent=1) + "\n")
            for name, dev in self.devices.items():
                rec = RawRecorder(self.record_dir / f"{name}.raw", dev.recording_header())
                dev.recorder = rec
                self._recorders.append(rec)
        except OSError as exc:
            raise UserError(f"cannot record into {self.record_dir}: {exc}") from None

    def _sink(self, name: str) -> Callable[[Measurement], None]:
        cfg, q = self.cfg, self._queue

        def sink(m: Measurement) -> None:
            self.received[name] += 1
            ev = to_event(m, cfg)
            if ev is None:
                self.rejected[name] += 1
            else:
                q.put(ev)

        return sink

    def start(self) -> DevicePorts:
        if not self._started:
            self._started = True
            for r in self._runners.values():
                r.start()
        return self

    def wait_connected(self, timeout: float = 10.0) -> bool:
        """Wait until every device is open and configured (or ``timeout`` s passed)."""
        deadline = time.monotonic() + timeout
        return all(
            r.connected.wait(max(0.0, deadline - time.monotonic())) for r in self._runners.values()
        )

    def get(self, timeout: float | None = None) -> Event | None:
        """The next event, waiting up to ``timeout`` s (None: forever); None if none came."""
        try:
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def poll(self, timeout: float = 0.05) -> Event | dict[str, float]:
        """The next event (waiting up to ``timeout`` s), or - when none is waiting, and at
        least every :data:`SNAPSHOT_INTERVAL` s - a *silence snapshot*: ``{device:
        silence(device)}`` taken with the queue empty, so that every event delivered before
        it has been returned before it."""
        now = time.monotonic()
        if now >= self._next_snapshot and self._queue.empty():
            self._next_snapshot = now + SNAPSHOT_INTERVAL
            return self.silences()
        ev = self.get(timeout)
        if ev is None:
            self._next_snapshot = time.monotonic() + SNAPSHOT_INTERVAL
            return self.silences()
        return ev

    def drain(self) -> list[Event]:
        """The events delivered and not yet taken, without waiting."""
        out = []
        while (ev := self.get(timeout=0)) is not None:
            out.append(ev)
        return out

    def silences(self) -> dict[str, float]:
        """:meth:`silence` of every device."""
        return {n: self.silence(n) for n in self.devices}

    def events(self, idle_timeout: float | None = None) -> Iterator[Event]:
        """Events as they arrive; ends after ``idle_timeout`` s without any (None: never)."""
        while True:
            ev = self.get(idle_timeout)
            if ev is None:
                return
            yield ev

    @property
    def names(self) -> list[str]:
        """The devices' names (laser, sonar<i>, odometry), the sources of the events."""
        return list(self.devices)

    def silence(self, name: str) -> float:
        """How long device ``name`` has been silent, s: while connected, its driver's
        attentive waiting since the last measurement (:class:`devices.driver.AttentiveTimer`:
        time the host was too busy to read does not count); while not, the wall time since
        it was lost (or since the start, for one that never answered)."""
        runner = self._runners[name]
        if not runner.connected.is_set():
            return time.monotonic() - runner.down_since
        return self.devices[name].seconds_since_data()

    def status(self) -> dict[str, dict[str, Any]]:
        """Per device: connected, counters (opens, disconnects, timeouts, naks, retries,
        bytes_in, frames, crc_errors, discarded, dropped_frames, ...), received and rejected
        measurements, last error, log times of the disconnects."""
        out = {}
        for name, dev in self.devices.items():
            d: dict[str, Any] = {"connected": self._runners[name].connected.is_set()}
            d.update(dev.counters())
            d.update(received=self.received[name], rejected=self.rejected[name])
            d["last_error"] = dev.last_error
            d["disconnect_times"] = list(self._runners[name].disconnect_times)
            out[name] = d
        return out

    def errors(self) -> list[BaseException]:
        """Fatal errors of the device threads (bugs), if any."""
        return [r.error for r in self._runners.values() if r.error is not None]

    def close(self) -> None:
        """Stop every device thread, close the ports and the recordings."""
        for r in self._runners.values():
            r.stop()
        for rec in self._recorders:
            rec.close()
        self._recorders.clear()

    def __enter__(self) -> DevicePorts:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------------------------------
# Emulators


@dataclass
class Emulation:
    """Emulated devices fed by a simulated run (see :func:`start_emulators`).

    ``truth`` collects the run's true poses in log time as they are played; ``sent`` (with
    ``keep_sent``) the simulated events handed to the emulators, in simulation time; the
    run's time 0 is log time ``start_time`` (known once ``started`` is set).
    """

    clock: Clock
    laser: SickEmulator
    sonars: list[SonarEmulator]
    odometry: OdometryEmulator
    playback: Playback
    run: Run
    truth: list[TruthPose] = field(default_factory=list)
    sent: list[Event] | None = None

    @property
    def emulators(self) -> list[PtyEmulator]:
        return [self.laser, *self.sonars, self.odometry]

    @property
    def ports(self) -> dict[str, Any]:
        """{'laser': path, 'sonar': [path per array], 'odometry': path}."""
        return {
            "laser": self.laser.port,
            "sonar": [s.port for s in self.sonars],
            "odometry": self.odometry.port,
        }

    @property
    def started(self) -> threading.Event:
        return self.playback.started

    @property
    def start_time(self) -> float:
        return self.playback.offset

    @property
    def done(self) -> bool:
        return self.playback.done.is_set()

    def ready(self) -> bool:
        """Every emulator has a host that started its data stream."""
        return all(e.ready for e in self.emulators)

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the whole run has been played (True) or ``timeout`` s passed."""
        return self.playback.done.wait(timeout)

    def stop(self) -> None:
        """Stop the playback and the emulators (closing their ptys)."""
        self.playback.stop()
        for e in reversed(self.emulators):  # the laser's owns a temporary link directory
            e.stop()

    def stats(self) -> dict[str, dict[str, int]]:
        out = {LASER: self.laser.stats.as_dict(), ODOMETRY: self.odometry.stats.as_dict()}
        out[LASER].update(scans_skipped=self.laser.scans_skipped)
        for i, s in enumerate(self.sonars):
            out[sonar_name(i)] = s.stats.as_dict()
        return out

    def __enter__(self) -> Emulation:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def start_emulators(
    cfg: RobotConfig,
    world: World,
    *,
    seed: int = 0,
    speed: float = 1.0,
    duration: float | None = None,
    params: SimParams | None = None,
    faults: Faults | dict[str, Faults] | None = None,
    link_dir: str | Path | None = None,
    wait_for_hosts: bool = True,
    wait_timeout: float = 60.0,
    keep_sent: bool = False,
    clock: Clock | None = None,
    lead: float = 10.0,
) -> Emulation:
    """Emulate the robot's devices on pseudo-terminals, fed by a simulated run of ``world``
    (``fgslam.sim``: the planned run and the sensor models) at ``speed`` times real time.

    The ports are symlinks ``<link_dir>/laser``, ``sonar0``, ``sonar1``, ..., ``odometry``
    (a temporary directory by default). ``faults``: one :class:`devices.pty_emulator.Faults`
    for every device (each gets its own seed) or a dict by device name. With
    ``wait_for_hosts`` the run starts once every device's host is streaming (at most
    ``wait_timeout`` wall s). Drivers in the same process should share ``Emulation.clock``.
    The first ``lead`` s of the simulation (inf: the whole run) are computed before this
    returns and the rest ahead of the playback in a thread of its own, so that the devices
    keep their times on a busy host (:class:`devices.playback.Playback`).
    """
    clock = clock or Clock(speed)
    run = plan_run(world, cfg, seed, params, duration)

    def faults_for(name: str, k: int) -> Faults:
        if isinstance(faults, dict):
            return faults.get(name, Faults())
        if faults is None:
            return Faults()
        return replace(faults, seed=faults.seed * 7919 + k)

    link = Path(link_dir) if link_dir is not None else None
    if link is not None:
        link.mkdir(parents=True, exist_ok=True)
    emus: list[PtyEmulator] = []
    try:
        laser = SickEmulator(LASER, clock=clock, faults=faults_for(LASER, 0), link_dir=link)
        emus.append(laser)
        if link is None:
            link = laser.link_dir
        sonars = []
        for i in range(len(cfg.sonar.arrays)):
            name = sonar_name(i)
            s = SonarEmulator(
                name,
                device_id=i,
                period=1.0 / cfg.sonar.cycle_rate,
                clock=clock,
                faults=faults_for(name, i + 1),
                link_dir=link,
            )
            sonars.append(s)
            emus.append(s)
        odo = OdometryEmulator(
            ODOMETRY,
            period=cfg.odometry.sample_period,
            clock=clock,
            faults=faults_for(ODOMETRY, 99),
            link_dir=link,
        )
        emus.append(odo)
    except BaseException:
        for e in emus:
            e.stop()
        raise
    sent: list[Event] | None = [] if keep_sent else None
    emulation = Emulation(clock, laser, sonars, odo, None, run, [], sent)  # type: ignore[arg-type]
    named = {e.name: e for e in emus}
    schedule = _schedule(world, cfg, run, params, emulation, named, faults_for)
    emulation.playback = Playback(
        clock,
        schedule,
        wait_for=emulation.ready if wait_for_hosts else None,
        wait_timeout=wait_timeout,
        lead=lead,
    )
    emulation.playback.start()  # computes the lead before the emulators answer anyone
    for e in emus:
        e.start()
    return emulation


def _schedule(
    world: World,
    cfg: RobotConfig,
    run: Run,
    params: SimParams | None,
    emu: Emulation,
    named: dict[str, PtyEmulator],
    faults_for: Callable[[str, int], Faults],
) -> Iterator[tuple[float, Callable[[float], Any]]]:
    """(run time, action(log time)) for every simulated event and planned disconnect."""

    def sim() -> Iterator[tuple[float, int, Callable[[float], Any]]]:
        for k, ev in enumerate(events(world, cfg, run, params)):
            if emu.sent is not None and not isinstance(ev, TruthPose):
                emu.sent.append(ev)
            yield ev.t, k, _action(ev, emu)

    plans = []
    for k, name in enumerate(named):
        for at, down in faults_for(name, k).disconnects:
            plans.append((float(at), -1 - len(plans), _disconnect(named[name], float(down))))
    plans.sort(key=lambda p: p[:2])
    for t, _, action in heapq.merge(sim(), plans, key=lambda p: p[:2]):
        yield t, action


def _disconnect(e: PtyEmulator, down: float) -> Callable[[float], Any]:
    return lambda _t: e.disconnect(down)


def _action(ev: Event, emu: Emulation) -> Callable[[float], Any]:
    if isinstance(ev, OdometryEvent):
        return lambda t: emu.odometry.offer_sample(t, ev.ticks_right, ev.ticks_left, ev.t)
    if isinstance(ev, SonarReading):
        echoes = [(e.kind, e.range, e.bearing) for e in ev.echoes]
        return lambda t: emu.sonars[ev.array].offer_reading(t, ev.pan, echoes, ev.t)
    if isinstance(ev, LaserScan):
        cm = laser_distances_cm(ev.ranges)
        return lambda t: emu.laser.offer_scan(t, cm)
    assert isinstance(ev, TruthPose)
    return lambda t: emu.truth.append(TruthPose(t, ev.x, ev.y, ev.theta))


# ---------------------------------------------------------------------------------------------
# Replay


def read_session(raw_dir: str | Path) -> dict[str, Any]:
    """The ``session.json`` of a raw directory ({} if there is none); UserError if bad: not
    JSON, not a session, or a ``world`` that is not one line of text, a ``clock_speed`` that
    is not a positive finite number, a ``meta`` that is not an object of finite values (the
    ``config`` is checked by :func:`session_config`)."""
    path = Path(raw_dir) / SESSION_FILE
    if not Path(raw_dir).is_dir():
        raise UserError(f"{raw_dir}: not a directory")
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text("utf-8"))
    except RecursionError:
        raise UserError(f"{path}: cannot read session file (nested too deeply)") from None
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: cannot read session file ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != SESSION_FORMAT:
        raise UserError(f"{path}: not an fgslam raw session file")
    world = data.get("world", "online")
    if not isinstance(world, str) or "\n" in world or "\r" in world:
        raise UserError(f"{path}: world must be one line of text, got {show(world)}")
    speed = data.get("clock_speed", 1.0)
    if isinstance(speed, bool) or not isinstance(speed, int | float) or not 0 < speed < math.inf:
        raise UserError(f"{path}: clock_speed must be a positive number, got {show(speed)}")
    meta = data.get("meta") or {}
    try:
        if not isinstance(meta, dict):
            raise ValueError("not an object")
        json.dumps(meta, allow_nan=False)
    except ValueError as exc:
        raise UserError(f"{path}: meta must be an object of finite values ({exc})") from None
    return data


def session_config(raw_dir: str | Path) -> RobotConfig | None:
    """The robot configuration recorded with a raw directory, if any."""
    data = read_session(raw_dir).get("config")
    if data is None:
        return None
    return from_dict(data, source=f"{Path(raw_dir) / SESSION_FILE} (config)")


@dataclass
class ReplayResult:
    """What :func:`replay_to_log` wrote: events per kind, measurements rejected, and per
    raw file its receiver counters and damage (truncated last record, skipped bytes)."""

    events: int = 0
    by_kind: dict[str, int] = field(default_factory=dict)
    rejected: int = 0
    files: dict[str, dict[str, Any]] = field(default_factory=dict)


def _raw_names(raw_dir: str | Path) -> list[str]:
    names = sorted(p.stem for p in Path(raw_dir).glob("*.raw"))
    if not names:
        raise UserError(f"{raw_dir}: no raw recordings (*.raw) in it")
    return names


def replay(
    raw_dir: str | Path, cfg: RobotConfig | None = None, result: ReplayResult | None = None
) -> Iterator[Event]:
    """The fgslam events of a raw directory, decoded by the drivers' receivers and merged by
    device time (:func:`fgslam.io.ordering.merge_sources`, the merge the online run applies):
    the same every time, and the same order as the online run that made the recording.
    ``cfg`` defaults to the recorded configuration (else the default one). ``result``, if
    given, is filled in as events go (counts, and per file its counters and damage at the
    end)."""
    if cfg is None:
        cfg = session_config(raw_dir) or load_config()
    result = result if result is not None else ReplayResult()
    names = _raw_names(raw_dir)
    try:
        opened = {name: ReplayFile(Path(raw_dir) / f"{name}.raw") for name in names}
    except RawFormatError as exc:
        raise UserError(str(exc)) from None

    def decoded(rf: ReplayFile) -> Iterator[Event]:
        for m in rf:
            ev = to_event(m, cfg)
            if ev is None:
                result.rejected += 1
            else:
                yield ev

    try:
        for ev in merge_sources({name: decoded(rf) for name, rf in opened.items()}):
            result.events += 1
            kind = type(ev).__name__
            result.by_kind[kind] = result.by_kind.get(kind, 0) + 1
            yield ev
    except RawFormatError as exc:
        raise UserError(str(exc)) from None
    for name, rf in opened.items():
        info: dict[str, Any] = dict(rf.receiver.counters())
        info.update(truncated=rf.reader.truncated, skipped_bytes=rf.reader.skipped_bytes)
        result.files[name] = info


def replay_to_log(
    raw_dir: str | Path,
    out: str | Path,
    cfg: RobotConfig | None = None,
    progress: Callable[[float], None] | None = None,
) -> ReplayResult:
    """Decode a raw directory into a native log at ``out`` (``.gz`` compressed); replaying
    the same directory twice gives byte-identical logs. ``progress`` gets each event's time
    since the first event."""
    session = read_session(raw_dir)
    if cfg is None:
        cfg = session_config(raw_dir) or load_config()
    meta = {"source": "raw replay", "clock_speed": session.get("clock_speed", 1.0)}
    meta.update(session.get("meta") or {})
    result = ReplayResult()
    first = math.nan
    with LogWriter(out, cfg, str(session.get("world", "online")), meta) as log:
        for ev in replay(raw_dir, cfg, result):
            log.write(ev)
            if progress is not None:
                first = ev.t if math.isnan(first) else first
                progress(ev.t - first)
    return result
