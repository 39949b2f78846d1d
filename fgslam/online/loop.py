"""Online SLAM: events from the devices (:class:`fgslam.online.ports.DevicePorts`) into the
incremental pipeline (:class:`fgslam.slam.runner.SlamPipeline`) as they arrive.

:func:`run_online` is what ``fgslam online`` runs: it takes events from the ports' queue,
feeds them to the pipeline (iSAM2 by default: one update per keyframe), reports a status
line a few times per second, and stops on ``stop`` (Ctrl-C in the CLI) or at the end of the
data (nothing for ``idle_timeout`` s after data has been flowing); then it processes what is
still queued and returns the results, which ``fgslam.slam.outputs.write_outputs`` writes
like ``fgslam run``'s.

Order. The ports deliver events in arrival order: per device in time order, across devices
interleaved as the host's threads happened to run (a laser scan, stamped when its first byte
left the scanner, arrives after the sonar and odometry of its transmission time, 0.21 s at
38400 baud; a starved driver thread delivers seconds of events at once). The events are
merged by device time (:class:`fgslam.io.ordering.SourceMerger`, the merge a replay of the
recording applies), so that what the SLAM pipeline sees does not depend on the host's speed
or load: a host that cannot keep up lags (reported), it never drops or reorders data. Wall
time only decides when a device is silent (disconnected, or its driver waited
``silent_after`` s without data, counted in attentive time), and then the merge goes on
without it; what such a device delivers later is put back in order by the pipeline's reorder
buffer (``reorder_window`` s of log time) or, beyond it, counted.
"""

from __future__ import annotations

import math
import shlex
import shutil
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from devices.pty_emulator import Faults
from fgslam.config import RobotConfig
from fgslam.errors import UserError
from fgslam.events import Event, SonarReading
from fgslam.io.ordering import REORDER_WINDOW, SourceMerger
from fgslam.online.device_process import DeviceProcess
from fgslam.online.ports import LASER, ODOMETRY, DevicePorts, sonar_name, start_emulators
from fgslam.session import Session
from fgslam.session.localize import Localizer
from fgslam.slam.runner import SlamPipeline, SlamResult

STATUS_INTERVAL = 0.25  # wall s between status updates
SILENT_AFTER = 1.0  # s of a driver's attentive waiting without data: the merge goes on without it
HOST_GONE = 0.5  # wall s after every host closed its port: fgslam emulate stops
CHECKPOINT_EVERY = 5.0  # s of log time between the checkpoints of fgslam online's outputs


@dataclass
class OnlineResult:
    """What :func:`run_online` did: the SLAM result, why it stopped (``interrupted`` or
    ``end of data``), events taken per device, the largest lag of an event behind the
    clock when it was processed, of those released by the arrival of data (log s; not of
    those released by a silence, which waited ``silent_after`` for it, nor the end's flush),
    events that came after the merge had gone past
    them (``late``: the first events of a device after a silence, e.g. at the start; the
    pipeline's reorder buffer puts them back in order, or counts them as out of order
    beyond its window), silences declared per device, and the ports' final status."""

    result: SlamResult
    reason: str
    events: Counter = field(default_factory=Counter)
    max_lag: float = 0.0
    busy_seconds: float = 0.0
    wall_seconds: float = 0.0
    late: int = 0
    silences: Counter = field(default_factory=Counter)
    status: dict[str, dict[str, Any]] = field(default_factory=dict)


def source(ev: Event) -> str:
    """The device an event came from: laser, sonar<i>, odometry (else its type)."""
    if isinstance(ev, SonarReading):
        return sonar_name(ev.array)
    name = type(ev).__name__
    return {"LaserScan": LASER, "OdometryEvent": ODOMETRY}.get(name, name)


def run_online(
    ports: DevicePorts | DeviceProcess,
    cfg: RobotConfig,
    *,
    backend: str = "isam2",
    sensors: str = "fused",
    stop: threading.Event | None = None,
    idle_timeout: float = 5.0,
    on_status: Callable[[str], None] | None = None,
    status_interval: float = STATUS_INTERVAL,
    reorder_window: float = REORDER_WINDOW,
    silent_after: float = SILENT_AFTER,
    checkpoint: Callable[[SlamResult], None] | None = None,
    checkpoint_every: float = CHECKPOINT_EVERY,
    session: Session | None = None,
) -> OnlineResult:
    """Run the front end and ``backend`` on the events of started ``ports`` as they come;
    with a saved ``session``, localization on it instead (:class:`Localizer`; no
    checkpoints; the result a :class:`LocalizationResult`).

    Events are merged by device time (:class:`fgslam.io.ordering.SourceMerger`): an event goes
    on once every device has delivered one as late, so the order, and the map, do not depend
    on how fast the host is. A device is not waited for while it is disconnected or its
    driver has waited ``silent_after`` s (attentive time) without data, and only when every
    delivered event has been taken: a host that is behind lags, it does not skip a device.

    Stops when ``stop`` is set, or at the end of the data: every device silent for
    ``idle_timeout`` s (attentive) after data has been flowing, and nothing left to take.
    ``on_status`` receives a one-line status (:func:`status_line`) at most every
    ``status_interval`` wall s. ``checkpoint`` receives the estimate so far
    (:meth:`SlamPipeline.snapshot`) whenever ``checkpoint_every`` s of log time have been
    processed since the last one. A device that disconnects is reopened by its driver thread
    while the others go on. Raises RuntimeError if a device thread failed (a bug)."""
    stop = stop or threading.Event()
    if session is not None:
        pipe: SlamPipeline | Localizer = Localizer(session, cfg, count_idle=False)
        checkpoint = None
    else:
        pipe = SlamPipeline(
            cfg, [backend], sensors, reorder_window=reorder_window, count_idle=False
        )
    merger = SourceMerger(ports.names)
    clock = ports.clock
    counts: Counter = Counter()
    silences: Counter = Counter()
    max_lag = lag = 0.0
    t_wall = time.monotonic()
    flowing = False
    next_status = t_wall
    next_checkpoint = -math.inf
    reason = "interrupted"

    def take(evs: list[Event], streaming: bool = True) -> None:
        nonlocal lag, max_lag
        for ev in evs:
            lag = clock.now() - ev.t
            if streaming:
                max_lag = max(max_lag, lag)
            pipe.add(ev)

    while not stop.is_set():
        item = ports.poll(0.05)
        if isinstance(item, dict):  # a silence snapshot: everything delivered before is taken
            for n, q in item.items():
                if q > silent_after and n not in merger.silent:
                    silences[n] += 1
                    take(merger.set_silent(n), streaming=False)
                elif q <= silent_after and n in merger.silent:
                    take(merger.set_silent(n, False))  # streaming again: wait for it
            if flowing and min(item.values()) > idle_timeout:
                reason = "end of data"
                break
        elif item is not None:
            name = source(item)
            counts[name] += 1
            flowing = True
            take(merger.push(name, item))
        errors = ports.errors()
        if errors:
            raise RuntimeError(f"a device thread failed: {errors[0]!r}") from errors[0]
        if (
            checkpoint is not None
            and isinstance(pipe, SlamPipeline)
            and pipe.keyframes
            and pipe.last_t >= next_checkpoint
        ):
            if next_checkpoint > -math.inf:  # the first keyframe only starts the clock
                checkpoint(pipe.snapshot())
            next_checkpoint = pipe.last_t + checkpoint_every
        now = time.monotonic()
        if on_status is not None and now >= next_status:
            next_status = now + status_interval
            on_status(status_line(pipe, ports.status(), lag, not flowing))
    # what has arrived is processed, then the scans still waiting for their sonar window
    for ev in ports.drain():
        counts[source(ev)] += 1
        take(merger.push(source(ev), ev), streaming=False)
    take(merger.flush(), streaming=False)
    done = pipe.finish()
    res = done[0] if isinstance(done, list) else done
    res.stats.update({f"events_{k}": v for k, v in counts.items()})
    if merger.late:
        res.stats["events_late"] = merger.late
    status = ports.status()
    if on_status is not None:
        on_status(status_line(pipe, status, lag, not flowing))
    return OnlineResult(
        result=res,
        reason=reason,
        events=counts,
        max_lag=max_lag,
        busy_seconds=pipe.busy_seconds,
        wall_seconds=time.monotonic() - t_wall,
        late=merger.late,
        silences=silences,
        status=status,
    )


def device_summary(name: str, s: dict[str, Any]) -> str:
    """``name ok`` / ``name DOWN`` / ``name finished`` (closed at the end of the run), with
    its non-zero fault counters."""
    state = "ok" if s.get("connected") else "finished" if s.get("finished") else "DOWN"
    parts = [f"{name} {state}"]
    labels = (
        ("disconnects", "disc"),
        ("crc_errors", "crc"),
        ("dropped_frames", "drop"),
        ("discarded", "junk B"),
        ("rejected", "rej"),
    )
    notes = [f"{label} {s[k]}" for k, label in labels if s.get(k)]
    if notes:
        parts.append(f"({', '.join(notes)})")
    return " ".join(parts)


def status_line(pipe, status: dict[str, dict[str, Any]], lag: float, waiting: bool = False) -> str:
    """One line: the estimate (``pipe.status_text()``: a :class:`SlamPipeline`'s keyframes,
    pose, landmarks and latency, or a localizer's state and pose), how far the pipeline is
    behind the clock, and every device's state and fault counters."""
    devices = " | ".join(device_summary(n, s) for n, s in status.items())
    if waiting:
        return f"waiting for data | {devices}"
    return f"{pipe.status_text()} | lag {lag:4.1f} s | {devices}"


# ---------------------------------------------------------------------------------------------
# The commands (``fgslam emulate``, ``fgslam online``; their parsers are in fgslam.cli)


class StopSignal:
    """Turns the first SIGINT (Ctrl-C) or SIGTERM into ``event`` being set, so that a run
    stops between two events and writes its outputs; a second Ctrl-C raises
    KeyboardInterrupt. Installs nothing outside the main thread."""

    def __init__(self, message: str = "") -> None:
        self.event = threading.Event()
        self.message = message
        self._old: dict[int, Any] = {}

    def _handler(self, signum: int, _frame: Any) -> None:
        if self.event.is_set() and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.event.set()
        if self.message:
            print(f"\n{self.message}", file=sys.stderr, flush=True)

    def __enter__(self) -> StopSignal:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self._handler)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old.clear()


def parse_disconnect(spec: str) -> tuple[str, float, float]:
    """``DEVICE:AT:DOWN`` (e.g. ``odometry:20:2``) -> (device, run time s, down time s)."""
    parts = spec.split(":")
    try:
        if len(parts) != 3:
            raise ValueError
        name, at, down = parts[0], float(parts[1]), float(parts[2])
        if at < 0 or down <= 0:
            raise ValueError
    except ValueError:
        raise UserError(
            f"--disconnect {spec!r}: expected DEVICE:AT:DOWN, e.g. odometry:20:2 "
            "(unplugged at 20 s of the run for 2 s)"
        ) from None
    return name, at, down


def emulation_faults(
    cfg: RobotConfig,
    *,
    noise: float = 0.0,
    drop: float = 0.0,
    flip: float = 0.0,
    disconnects: list[str] | tuple[str, ...] = (),
    seed: int = 0,
) -> dict[str, Faults] | None:
    """Faults per device for :func:`fgslam.online.ports.start_emulators` (None: none at all)."""
    names = [LASER, *(sonar_name(i) for i in range(len(cfg.sonar.arrays))), ODOMETRY]
    for name, p in (("noise", noise), ("drop", drop), ("flip", flip)):
        if not 0.0 <= p <= 1.0:
            raise UserError(f"--{name} must be a probability in [0, 1], got {p}")
    plans: dict[str, list[tuple[float, float]]] = {n: [] for n in names}
    for spec in disconnects:
        name, at, down = parse_disconnect(spec)
        if name not in plans:
            raise UserError(f"--disconnect {spec!r}: unknown device; devices: {', '.join(names)}")
        plans[name].append((at, down))
    if not (noise or drop or flip or disconnects):
        return None
    return {
        n: Faults(
            seed=seed * 1000 + k,
            noise=noise,
            drop=drop,
            flip=flip,
            disconnects=tuple(sorted(plans[n])),
        )
        for k, n in enumerate(names)
    }


def online_command_line(ports: dict[str, Any], speed: float, out: str = "online-out") -> str:
    """The ``fgslam online`` command line for emulated ``ports`` (``Emulation.ports``)."""
    args = ["fgslam", "online", "--laser", ports["laser"]]
    for p in ports["sonar"]:
        args += ["--sonar", p]
    args += ["--odom", ports["odometry"]]
    if speed != 1.0:
        args += ["--speed", f"{speed:g}"]
    args += ["--out", out]
    return " ".join(shlex.quote(a) for a in args)


def emulate_main(
    cfg: RobotConfig,
    world_name: str,
    *,
    seed: int = 0,
    speed: float = 1.0,
    duration: float | None = None,
    link_dir: str | None = None,
    faults: dict[str, Faults] | None = None,
    stop: threading.Event | None = None,
    out: Any = None,
) -> int:
    """``fgslam emulate``: start the emulators, print their ports and the matching
    ``fgslam online`` command, play the run once every host streams, stop at its end, when
    every host has closed its port again (:data:`HOST_GONE` s after the last), or when
    ``stop`` is set."""
    from fgslam.sim.world import load_world

    out = out or sys.stdout
    if not speed > 0:
        raise UserError(f"--speed must be positive, got {speed}")
    if duration is not None and duration <= 0:
        raise UserError(f"--duration must be positive, got {duration}")
    world = load_world(world_name)
    stop = stop or threading.Event()
    try:
        emu = start_emulators(
            cfg,
            world,
            seed=seed,
            speed=speed,
            duration=duration,
            faults=faults,
            link_dir=link_dir,
            wait_timeout=math.inf,
        )
    except OSError as exc:
        raise UserError(f"cannot create the emulated ports: {exc}") from None
    try:
        ports = emu.ports
        print(
            f"emulating world '{world.name}', seed {seed}: {emu.run.duration:.1f} s of driving "
            f"at {speed:g}x real time",
            file=out,
        )
        print(f"  laser     {ports['laser']}  (SICK PLS)", file=out)
        for i, p in enumerate(ports["sonar"]):
            print(f"  {sonar_name(i):9s} {p}  (advanced sonar array {i})", file=out)
        print(f"  odometry  {ports['odometry']}  (odometry board)", file=out)
        print("the run starts once a host streams from every port; in another terminal:", file=out)
        print(f"  {online_command_line(ports, speed)}", file=out, flush=True)

        def hosts_gone() -> bool:  # every host that had opened its port closed it again
            return all(e.host_gone_for() > HOST_GONE for e in emu.emulators)

        while not stop.is_set() and not emu.started.wait(0.1):
            pass
        if emu.started.is_set():
            print("every host is streaming: run started", file=out, flush=True)
        gone = False
        while not stop.is_set() and not emu.wait(0.1):
            if hosts_gone():
                gone = True
                break
        if gone:
            print("every host closed its port: stopping", file=out, flush=True)
        elif emu.done and not stop.is_set():
            # let the last scheduled frames go out (a laser scan leaves after its stamp)
            stop.wait(max(0.5, emu.clock.wall(1.0)))
        if emu.playback.error is not None:
            raise RuntimeError("the emulator playback failed") from emu.playback.error
        finished = emu.done and emu.started.is_set()
    finally:
        emu.stop()
    st = emu.stats()
    frames = sum(s["frames_sent"] for s in st.values())
    lost = sum(s["frames_lost"] for s in st.values())
    overflow = sum(s["overflow_bytes"] for s in st.values())
    how = "run finished" if finished else "stopped"
    print(
        f"{how}: {frames} data frames sent, {lost} lost (unplugged or stalled), {overflow} "
        "bytes the host did not read; emulators stopped",
        file=out,
    )
    return 0


def open_ports(
    cfg: RobotConfig,
    *,
    laser: str | None,
    sonar: list[str],
    odometry: str | None,
    speed: float = 1.0,
    record: str | None = None,
    meta: dict[str, Any] | None = None,
) -> DeviceProcess:
    """The devices for the ``fgslam online`` options, driven in a process of their own
    (:class:`fgslam.online.device_process.DeviceProcess`: SLAM's load cannot delay their reads
    and timestamps), with clear errors for ports that do not exist."""
    if not speed > 0:
        raise UserError(f"--speed must be positive, got {speed}")
    given = [("--laser", laser), *(("--sonar", s) for s in sonar), ("--odom", odometry)]
    for opt, port in given:
        if port and not Path(port).exists():
            raise UserError(f"{opt} {port}: no such port")
    if not any(p for _, p in given):
        raise UserError("no device port given (--laser, --sonar, --odom)")
    if len(sonar) > len(cfg.sonar.arrays):
        raise UserError(
            f"{len(sonar)} sonar ports given, the configuration has "
            f"{len(cfg.sonar.arrays)} sonar arrays"
        )
    return DeviceProcess(
        cfg,
        laser=laser,
        sonar=sonar,
        odometry=odometry,
        speed=speed,
        record_dir=record,
        meta=meta,
    )


class StatusDisplay:
    """The live status line on a stream: rewritten in place on a terminal (at most every
    ``interval`` s), one line every ``log_interval`` s otherwise."""

    def __init__(self, stream: Any = None, interval: float = 0.25, log_interval: float = 5.0):
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.interval = interval if self.tty else log_interval
        self._next = 0.0
        self._shown = False
        self.last = ""

    def __call__(self, line: str) -> None:
        self.last = line
        now = time.monotonic()
        if now < self._next:
            return
        self._next = now + self.interval
        self._write(line)

    def _write(self, line: str) -> None:
        if self.tty:
            width = shutil.get_terminal_size((160, 20)).columns - 1
            self.stream.write("\r" + line[:width] + "\x1b[K")
            self._shown = True
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def close(self) -> None:
        """Show the last status (final counts) and end the line."""
        if self.last:
            self._write(self.last)
        if self.tty and self._shown:
            self.stream.write("\n")
            self.stream.flush()


def online_main(
    cfg: RobotConfig,
    *,
    laser: str | None,
    sonar: list[str],
    odometry: str | None,
    out: str,
    record: str | None = None,
    backend: str = "isam2",
    sensors: str = "fused",
    speed: float = 1.0,
    idle_timeout: float = 5.0,
    connect_timeout: float = 30.0,
    stop: threading.Event | None = None,
    status_stream: Any = None,
    meta: dict[str, Any] | None = None,
    session: Session | None = None,
) -> tuple[OnlineResult, dict[str, Any]]:
    """``fgslam online``: open the ports, run SLAM as data arrives until ``stop`` or the end
    of the data, write the outputs of ``fgslam run`` into ``out``; returns the run and its
    report. Meanwhile, every :data:`CHECKPOINT_EVERY` s of log time, the estimate so far is
    written there (trajectory.tum, map.json, report.json with ``checkpoint``; atomically),
    so that a run that is killed keeps its outputs up to the last checkpoint. With a saved
    ``session``: localization on it, and the outputs of ``fgslam localize``."""
    from fgslam.slam.outputs import write_outputs

    if idle_timeout <= 0:
        raise UserError(f"--idle-timeout must be positive, got {idle_timeout}")
    stop = stop or threading.Event()
    try:
        Path(out).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {out}: cannot create it ({exc.strerror or exc})") from None
    ports = open_ports(
        cfg,
        laser=laser,
        sonar=sonar,
        odometry=odometry,
        speed=speed,
        record=record,
        meta=meta,
    )
    display = StatusDisplay(status_stream)
    with ports:
        deadline = time.monotonic() + connect_timeout
        while not ports.wait_connected(0.1):
            if stop.is_set():
                break
            if time.monotonic() > deadline:
                status = ports.status()
                bad = [
                    f"{n} ({status[n]['last_error'] or 'no answer'})"
                    if n in status
                    else f"{n} (no answer)"
                    for n in ports.names
                    if not status.get(n, {}).get("connected")
                ]
                raise UserError(f"no answer after {connect_timeout:g} s from {'; '.join(bad)}")
        checkpoints = 0

        def save(res: SlamResult) -> None:  # atomic files: a killed run keeps the last one
            nonlocal checkpoints
            checkpoints += 1
            note = {"complete": False, "number": checkpoints, "log_time": res.times[-1]}
            write_outputs(res, out, extra={"checkpoint": note}, figure=False)

        try:
            run = run_online(
                ports,
                cfg,
                backend=backend,
                sensors=sensors,
                stop=stop,
                idle_timeout=idle_timeout,
                on_status=display,
                checkpoint=save,
                session=session,
            )
        finally:
            display.close()
    run.status = ports.status()  # after the drivers stopped: final counters
    if session is not None:
        from fgslam.session.outputs import write_localization

        return run, write_localization(session, run.result, out, {"online": True})
    rep = write_outputs(run.result, out)
    return run, rep
