"""Online SLAM (issue 6): the incremental pipeline, and emulators -> pty drivers ->
:func:`fgslam.online.loop.run_online` compared with ``fgslam run`` on the log of the same run;
Ctrl-C, a device disconnect, the ``fgslam emulate`` / ``fgslam online`` commands.

Emulated runs are short (25-40 s of the corridor run) at 3x real time, one on a machine
loaded by busy processes, one faster than the host can follow; every wait is generous and
the assertions are on content, not on timing (issue 17)."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections import Counter

import numpy as np
import pytest
from devices_helpers import cpu_hogs, wait_until

from devices.pty_emulator import Faults
from devices.replay import ReplayFile
from fgslam.config import load_config
from fgslam.events import LaserScan, OdometryEvent, SonarReading, TruthPose
from fgslam.io.logfile import LogReader
from fgslam.online.device_process import DeviceProcess, EmulationSpec
from fgslam.online.loop import online_main, run_online, source
from fgslam.online.ports import laser_distances_cm, replay, replay_to_log, start_emulators
from fgslam.sim import simulate_to_log
from fgslam.sim.scenes import room_events
from fgslam.sim.world import load_world
from fgslam.slam.runner import SlamPipeline, run_backends, run_slam

CFG = load_config()
SPEED = 3.0
SEED, DURATION = 1, 40.0
FGSLAM = [sys.executable, "-m", "fgslam.cli"]


# ------------------------------------------------------------------ the incremental pipeline


def _kill(*procs: subprocess.Popen | None) -> None:
    """Kill and reap the processes still running (None: never started)."""
    for p in procs:
        if p is not None and p.poll() is None:
            p.kill()
            p.communicate()


def _same_results(a, b) -> None:
    assert a.backend == b.backend
    np.testing.assert_array_equal(a.times, b.times)
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.filtered, b.filtered)
    assert a.means.keys() == b.means.keys()
    for k in a.means:
        np.testing.assert_array_equal(a.means[k], b.means[k])
    assert {k: v.kind for k, v in a.landmarks.items()} == {
        k: v.kind for k, v in b.landmarks.items()
    }


def test_pipeline_event_by_event_equals_run_backends():
    evs, cfg, _ = room_events(0, 20.0)
    ref = run_backends(list(evs), cfg, ["ekf", "isam2"], "fused")
    pipe = SlamPipeline(cfg, ["ekf", "isam2"], "fused")
    assert pipe.pose() is None and pipe.last_latency() is None and pipe.keyframes == 0
    n = 0
    for ev in evs:
        k = pipe.add(ev)
        n += k
        if k:
            assert pipe.keyframes == n and pipe.pose().shape == (3,)
            assert pipe.last_latency("ekf") > 0 and pipe.last_latency("isam2") > 0
    res = pipe.finish()
    assert pipe.finish() is res  # idempotent
    counts = pipe.landmark_counts("isam2")
    for a, b in zip(ref, res, strict=True):
        _same_results(a, b)
    isam = res[1]
    assert counts == dict(Counter(lm.kind for lm in isam.landmarks.values()))
    assert len(isam.times) == pipe.keyframes > n - 5  # the last scans come out at finish
    with pytest.raises(RuntimeError):
        pipe.add(evs[-1])


def test_reorder_buffer_puts_late_events_back_within_its_window():
    evs, cfg, _ = room_events(0, 20.0)
    evs = list(evs)
    # every laser scan arrives 0.5 s late (as a scan stamped at its first byte does)
    late = sorted(
        evs, key=lambda e: e.t + (0.5 if isinstance(e, LaserScan) else 0.0), reverse=False
    )
    assert late != evs
    a = run_backends(evs, cfg, ["isam2"])[0]
    b = run_backends(late, cfg, ["isam2"])[0]
    _same_results(a, b)
    assert b.stats["events_reordered"] > 0 and "events_out_of_order" not in b.stats
    # with no window, every late scan is dropped
    pipe = SlamPipeline(cfg, ["isam2"], reorder_window=0.0)
    for ev in late:
        pipe.add(ev)
    dropped = pipe.finish()[0].stats["events_out_of_order"]
    assert dropped >= 0.9 * sum(isinstance(e, LaserScan) for e in evs)


# ------------------------------------------------------------------ end to end
# The emulators and the drivers run in a device process (fgslam.online.device_process), SLAM in
# this one, as ``fgslam online`` runs them: SLAM's load cannot delay the drivers' reads.


def online(raw, *, speed=SPEED, duration=DURATION, seed=SEED, faults=None, **kw):
    """An emulated run of the corridor, SLAM online with iSAM2 until the end of the data;
    returns the run and the emulation's final state (stats per device, start time)."""
    spec = EmulationSpec("corridor", seed=seed, duration=duration, faults=faults)
    dev = DeviceProcess(CFG, speed=speed, record_dir=raw, world="corridor", emulation=spec, **kw)
    with dev:
        run = run_online(dev, CFG, idle_timeout=1.5, on_status=kw.pop("on_status", None))
    run.status = dev.status()  # final counters
    assert dev.emulation["done"] and dev.emulation["error"] is None, dev.emulation
    return run, dev.emulation


@pytest.fixture(scope="module")
def online_run(tmp_path_factory):
    """40 s of the corridor run (seed 1) emulated at 3x, SLAM online with iSAM2; ends at
    the end of the data (the emulators stay up, silent)."""
    raw = tmp_path_factory.mktemp("online") / "raw"
    lines: list[str] = []
    spec = EmulationSpec("corridor", seed=SEED, duration=DURATION)
    dev = DeviceProcess(CFG, speed=SPEED, record_dir=raw, world="corridor", emulation=spec)
    with dev:
        run = run_online(dev, CFG, idle_timeout=1.5, on_status=lines.append)
    run.status = dev.status()
    return run, dev.emulation, raw, lines


def landmark_points(res) -> dict[str, np.ndarray]:
    """A position per landmark, by kind: corner vertices, points, and line segment
    midpoints (the normal point moved along the line to the middle of its extent)."""
    out: dict[str, list] = {"line": [], "corner": [], "point": []}
    for lid, lm in res.landmarks.items():
        m = res.means[lid]
        if lm.kind == "line":
            a, d = m[0], m[1]
            s = 0.0 if lm.extent is None else float(np.mean(lm.extent))
            out["line"].append((d * np.cos(a) - s * np.sin(a), d * np.sin(a) + s * np.cos(a)))
        else:
            out[lm.kind].append((m[0], m[1]))
    return {k: np.array(v).reshape(-1, 2) for k, v in out.items()}


def assert_everything_arrived(run, emulation, duration) -> None:
    """Every frame sent arrived intact and was processed; a device was lost only outside the
    run (silent after the end of the data while the host was still working), never during
    it."""
    start, end = emulation["start_time"], emulation["start_time"] + duration
    for name, s in run.status.items():
        assert s["crc_errors"] == s.get("dropped_frames", 0) == s["discarded"] == 0, name
        assert run.events[name] == emulation["stats"][name]["frames_sent"] > 0, name
        assert s["disconnects"] <= s["opens"] <= 1 + s["disconnects"], name
        during = [t for t in s["disconnect_times"] if start <= t <= end]
        assert not during, (name, during, start, end)
    # a device's first event after a silence (the start) may come after the merge went on:
    # the pipeline's reorder buffer puts it back; nothing is dropped
    assert run.late <= 4 and "events_out_of_order" not in run.result.stats
    assert run.result.stats["events_laser"] == run.events["laser"]
    assert len(run.result.every_scan[0]) == run.events["laser"]  # a pose at every scan


def assert_equals_replay(run, raw, tmp_path) -> None:
    """The recording replays into exactly the events the online run took (the same
    decoders, the same stamps) in the same merge by device time: ``fgslam run`` on the
    replayed log gives the same map and trajectory, to the last bit."""
    log = tmp_path / "replayed.log.gz"
    rep = replay_to_log(raw, log)
    assert rep.events == sum(run.events.values())
    with LogReader(log) as reader:
        ref = run_slam(reader, CFG, "isam2", "fused")
    assert "events_out_of_order" not in ref.stats
    _same_results(ref, run.result)


def test_online_run_keeps_up_and_reports_status(online_run):
    run, emulation, _, lines = online_run
    assert run.reason == "end of data"
    assert_everything_arrived(run, emulation, DURATION)
    assert any("lines" in ln and "laser ok" in ln and "kf " in ln for ln in lines)


def test_online_equals_fgslam_run_on_the_replayed_recording(online_run, tmp_path):
    run, _, raw, _ = online_run
    assert_equals_replay(run, raw, tmp_path)


def restamped(sim_events, online_events, start_time):
    """The simulator's events stamped as the host stamped them in the online run (the run's
    time 0 is log time ``start_time``), in time order: the simulation as the host saw its
    clocks. Each device's events are paired in order, their content checked (odometry ticks,
    sonar pans and echo counts, laser distance fields); a simulated event the emulated run
    did not send (its last moments) is left out. The stamps are what depends on the host's
    load (the laser's carries the read latency, the device-clock filter starts from the
    first reads'), not the chain from device to map, which is what this compares."""
    by_source: dict[str, list] = {}
    for e in online_events:
        by_source.setdefault(source(e), []).append(e)
    taken: dict[str, int] = {}
    out = []
    for e in sim_events:
        name = source(e)
        k = taken.get(name, 0)
        got = by_source.get(name, [])
        if k >= len(got):
            continue
        o = got[k]
        taken[name] = k + 1
        if isinstance(e, LaserScan):
            assert np.array_equal(laser_distances_cm(e.ranges), laser_distances_cm(o.ranges))
            e = LaserScan(o.t - start_time, e.ranges)
        elif isinstance(e, OdometryEvent):
            assert (e.ticks_right, e.ticks_left) == (o.ticks_right, o.ticks_left)
            e = OdometryEvent(o.t - start_time, e.ticks_right, e.ticks_left)
        else:
            assert abs(e.pan - o.pan) <= 5e-5 + 1e-12 and len(e.echoes) == len(o.echoes)
            e = SonarReading(o.t - start_time, e.array, e.pan, e.echoes)
        out.append(e)
    assert all(taken.get(n, 0) == len(v) for n, v in by_source.items())  # all paired
    return sorted(out, key=lambda e: e.t)


def test_online_matches_fgslam_run_on_the_simulated_log(online_run, tmp_path):
    """``fgslam run`` on the simulator's log of the same seed and duration, its events
    stamped as the host stamped them online (:func:`restamped`: on a loaded host a laser
    stamp carries seconds of read latency, and that is the host's, not the chain's). Not
    equal: sonar readings are quantised to 1 mm / 1e-4 rad and laser ranges to 1 cm. Both
    runs start at the origin (the truth is left out). Observed over 40 s (seeds 1 and 5,
    before the restamping, on a quiet host): final pose 1-6 mm and 0.03 deg apart; the same
    line and point counts, corners 6 vs 6-8 (a corner near the gate is sometimes ambiguous,
    sometimes new); nearest-neighbour landmark distances median 2-5 mm, max 2.3 cm.
    Tolerances, several times that: final pose within 5 cm and 0.5 deg; landmark counts by
    kind within 3; median nearest-neighbour distance below 2 cm and 80 % of the landmarks
    within 10 cm (an association decided differently moves a segment's extent)."""
    run, emulation, raw, _ = online_run
    log = tmp_path / "sim.log"
    simulate_to_log(load_world("corridor"), CFG, log, SEED, DURATION)
    with LogReader(log) as reader:
        sim = [e for e in reader if not isinstance(e, TruthPose)]
    evs = restamped(sim, replay(raw), emulation["start_time"])
    assert sum(isinstance(e, LaserScan) for e in evs) == run.events["laser"]
    ref = run_slam(evs, CFG)
    res = run.result
    assert abs(len(ref.times) - len(res.times)) <= 1
    d = ref.poses[-1] - res.poses[-1]
    dth = np.degrees(np.arctan2(np.sin(d[2]), np.cos(d[2])))
    assert np.hypot(d[0], d[1]) < 0.05 and abs(dth) < 0.5, d
    a, b = landmark_points(ref), landmark_points(res)
    dists = []
    for kind in a:
        assert abs(len(a[kind]) - len(b[kind])) <= 3, (kind, len(a[kind]), len(b[kind]))
        for p in b[kind]:
            if len(a[kind]):
                dists.append(np.min(np.hypot(*(a[kind] - p).T)))
    assert len(dists) >= 6
    assert np.median(dists) < 0.02 and np.mean(np.array(dists) < 0.10) >= 0.8, dists


def test_online_equals_replay_with_every_core_loaded(tmp_path):
    """Busy processes on every core (twice as many as cores) while the devices stream at
    6x: the host falls behind, and the map is still the replay's, bit for bit, with every
    frame processed and no device declared lost during the run."""
    raw = tmp_path / "raw"
    with cpu_hogs(per_core=2):
        run, emulation = online(raw, speed=6.0, duration=25.0, seed=2)
    assert run.reason == "end of data"
    assert_everything_arrived(run, emulation, 25.0)
    assert_equals_replay(run, raw, tmp_path)


def test_online_lags_then_catches_up_when_the_host_cannot_follow(tmp_path):
    """The devices stream at 20x, faster than SLAM follows on the machines this runs on
    (about 10x for the fused corridor): the run lags (reported as ``max_lag``), every event
    is processed at the end, and the result is the replay's."""
    raw = tmp_path / "raw"
    run, emulation = online(raw, speed=20.0, duration=30.0, seed=3)
    assert run.reason == "end of data" and run.max_lag > 0
    assert_everything_arrived(run, emulation, 30.0)
    assert_equals_replay(run, raw, tmp_path)


def test_disconnect_mid_run_reconnects_and_records_everything(tmp_path):
    """The odometry cable is pulled at 8 s for 1 s and the sonar 0 line is noisy: the run
    completes, the status shows the reconnect, and the recording holds every frame the
    drivers received (replayed events = events the online run took, per device)."""
    faults = {
        "odometry": Faults(seed=3, disconnects=((8.0, 1.0),)),
        "sonar0": Faults(seed=4, noise=0.2),
    }
    raw = tmp_path / "raw"
    run, emulation = online(raw, duration=25.0, seed=2, faults=faults, reopen_interval=0.1)
    sent = emulation["stats"]
    st = run.status
    assert run.reason == "end of data" and len(run.result.every_scan[0]) > 50
    assert st["odometry"]["disconnects"] >= 1 and st["odometry"]["opens"] >= 2
    assert st["sonar0"]["discarded"] > 0
    start, end = emulation["start_time"], emulation["start_time"] + 25.0
    assert not [t for t in st["laser"]["disconnect_times"] if start <= t <= end]
    replayed = Counter(source(e) for e in replay(raw))
    assert replayed == run.events
    for name in ("laser", "sonar0", "sonar1"):
        assert run.events[name] == sent[name]["frames_sent"], name
    assert sent["odometry"]["frames_lost"] > 50  # ~1 s at 100 Hz not sent while unplugged
    # lost on the line, not on the host: the board's sample clock of the frames recorded
    # has one gap, over the unplugged second (frames in the pty when the cable was pulled,
    # and those written into the new pty before the driver reopened it, widen it by as much
    # as the host lagged: no bound on that on a loaded host), and no other
    period = round(CFG.odometry.sample_period * 1e6)
    clock = np.array([f.t_device for f in ReplayFile(raw / "odometry.raw")], dtype=np.int64)
    steps = np.diff(clock)
    gaps = np.flatnonzero(steps != period)
    assert len(gaps) == 1, steps[gaps]
    g0, g1 = clock[gaps[0]] - clock[0], clock[gaps[0] + 1] - clock[0]
    assert g0 <= 8.0e6 and g1 >= 9.0e6 - 2 * period, (g0, g1)
    lost = sent["odometry"]["frames_sent"] - run.events["odometry"]
    assert lost >= 0 and lost == steps[gaps[0]] // period - 1 - sent["odometry"]["frames_lost"]


def test_stop_writes_the_outputs(tmp_path):
    """What Ctrl-C does in ``fgslam online`` (the stop event), on its own clock as in a
    separate process: the run stops mid-way and the outputs of ``fgslam run`` are written."""
    emu = start_emulators(CFG, load_world("corridor"), seed=3, speed=SPEED, duration=60.0)
    stop = threading.Event()

    def stopper() -> None:  # after 12 s of the run (60 scans), however fast that went
        emu.started.wait(60)
        while emu.laser.stats.frames_sent < 60 and not emu.done:
            time.sleep(0.05)
        stop.set()

    th = threading.Thread(target=stopper, daemon=True)
    th.start()
    try:
        run, rep = online_main(
            CFG,
            laser=emu.ports["laser"],
            sonar=emu.ports["sonar"],
            odometry=emu.ports["odometry"],
            out=str(tmp_path / "out"),
            speed=SPEED,
            stop=stop,
            status_stream=io.StringIO(),
        )
        finished = emu.done
    finally:
        emu.stop()
        th.join(5)
    assert run.reason == "interrupted" and not finished
    assert rep["poses"] == len(run.result.times) and 20 < rep["scans_placed"]
    assert 5.0 < rep["log_duration_s"] < 30.0
    for name in ("trajectory.tum", "map.json", "report.json", "map.png"):
        assert (tmp_path / "out" / name).stat().st_size > 0


# ------------------------------------------------------------------ the commands


def test_emulate_and_online_commands_with_ctrl_c(tmp_path):
    """``fgslam emulate`` in one process, ``fgslam online`` in another (as in two
    terminals); Ctrl-C (SIGINT) stops the online run, which writes its outputs, then the
    emulator."""
    links, out, raw = tmp_path / "links", tmp_path / "out", tmp_path / "raw"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    emulate = ["emulate", "--duration", "120", "--seed", "4", "--speed", f"{SPEED:g}"]
    emu = subprocess.Popen(
        [*FGSLAM, *emulate, "--link-dir", str(links)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    online = None
    try:
        assert wait_until(lambda: (links / "odometry").exists(), timeout=60)
        printed = emu.stdout.readline() + "".join(emu.stdout.readline() for _ in range(6))
        cmd = next(ln.split() for ln in printed.splitlines() if "fgslam online" in ln)
        assert cmd[cmd.index("--speed") + 1] == f"{SPEED:g}"
        assert cmd[cmd.index("--laser") + 1] == str(links / "laser")
        online = subprocess.Popen(
            [*FGSLAM, *cmd[1 : cmd.index("--out")], "--out", str(out), "--record", str(raw)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )

        def flowing() -> bool:  # ~10 s of the run recorded
            p = raw / "odometry.raw"
            return p.exists() and p.stat().st_size > 17 * 100 * 10

        assert wait_until(flowing, timeout=90), online.poll()
        online.send_signal(signal.SIGINT)
        o_out, o_err = online.communicate(timeout=90)
        assert online.returncode == 0, o_err
        assert "stopped (interrupted)" in o_out and "isam2/fused" in o_out
        assert "laser ok" in o_err and "Traceback" not in o_err
        for name in ("trajectory.tum", "map.json", "report.json", "map.png"):
            assert (out / name).stat().st_size > 0
        e_out, e_err = emu.communicate(timeout=60)  # its host is gone: it stops by itself
        assert emu.returncode == 0, e_err
        assert "run started" in e_out and "every host closed its port" in e_out
        assert "stopped:" in e_out and not (links / "laser").exists()
    finally:
        _kill(online, emu)


def test_killed_online_run_keeps_its_last_checkpoint(tmp_path):
    """``fgslam online`` killed with SIGKILL (nothing can run at exit): its outputs of the
    last checkpoint are there, whole (written atomically), and say they are a checkpoint;
    the emulator then sees its host gone and stops by itself."""
    links, out = tmp_path / "links", tmp_path / "out"
    emulate = ["emulate", "--duration", "600", "--seed", "5", "--speed", "3"]
    emu = subprocess.Popen(
        [*FGSLAM, *emulate, "--link-dir", str(links)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    online = None
    try:
        assert wait_until(lambda: (links / "odometry").exists(), timeout=60)
        ports = ["--laser", str(links / "laser"), "--odom", str(links / "odometry")]
        ports += ["--sonar", str(links / "sonar0"), "--sonar", str(links / "sonar1")]
        online = subprocess.Popen(
            [*FGSLAM, "online", *ports, "--speed", "3", "--out", str(out)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )

        def checkpoints() -> int:
            try:
                rep = json.loads((out / "report.json").read_text())
            except (OSError, ValueError):
                return 0
            return rep.get("checkpoint", {}).get("number", 0)

        assert wait_until(lambda: checkpoints() >= 2, timeout=120), online.poll()
        online.kill()  # SIGKILL
        online.wait(30)
        rep = json.loads((out / "report.json").read_text())
        assert rep["checkpoint"]["complete"] is False and rep["scans_placed"] > 10
        traj = (out / "trajectory.tum").read_text().splitlines()
        assert len(traj) == rep["poses"]
        assert json.loads((out / "map.json").read_text())["landmarks"]
        assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary left
        e_out, e_err = emu.communicate(timeout=120)  # the host is gone: it stops
        assert emu.returncode == 0 and "every host closed its port" in e_out, e_err
    finally:
        _kill(online, emu)


def test_emulate_stops_on_ctrl_c_before_any_host(tmp_path):
    links = tmp_path / "links"
    emu = subprocess.Popen(
        [*FGSLAM, "emulate", "--duration", "600", "--link-dir", str(links)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert wait_until(lambda: (links / "odometry").exists(), timeout=60)
        emu.send_signal(signal.SIGINT)
        e_out, e_err = emu.communicate(timeout=60)
        assert emu.returncode == 0, e_err
        assert "stopped:" in e_out and "Traceback" not in e_err
        assert not (links / "laser").exists()
    finally:
        _kill(emu)


def test_emulate_stops_when_its_host_is_gone(tmp_path):
    """A host streams from every port of ``fgslam emulate`` (a 600 s run in real time) and
    then closes them: the emulator notices and ends, writing its summary."""
    links = tmp_path / "links"
    emulate = ["emulate", "--duration", "600", "--seed", "4", "--link-dir", str(links)]
    emu = subprocess.Popen(
        [*FGSLAM, *emulate], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert wait_until(lambda: (links / "odometry").exists(), timeout=60)
        ports = {"laser": str(links / "laser"), "odometry": str(links / "odometry")}
        sonar = [str(links / "sonar0"), str(links / "sonar1")]
        with DeviceProcess(CFG, **ports, sonar=sonar) as dev:
            assert dev.wait_connected(60)
            got = 0
            deadline = time.monotonic() + 60
            while got < 20 and time.monotonic() < deadline:  # the run is playing
                got += isinstance(dev.poll(0.1), OdometryEvent)
            assert got >= 20
        out, err = emu.communicate(timeout=120)  # the run itself would take 600 s
        assert emu.returncode == 0, err
        assert "every host closed its port" in out and "stopped:" in out, out
    finally:
        _kill(emu)


@pytest.mark.parametrize(
    "argv, msg",
    [
        (["online", "--laser", "/dev/no-such-port", "--out", "o"], "no such port"),
        (["online", "--out", "o"], "no device port given"),
        (["online", "--odom", os.devnull, "--out", "o", "--connect-timeout", "0.5"], "odometry"),
        (["online", "--odom", os.devnull, "--out", "o", "--speed", "0"], "--speed"),
        (["emulate", "--disconnect", "odometry:5"], "DEVICE:AT:DOWN"),
        (["emulate", "--disconnect", "wheel:5:1"], "unknown device"),
        (["emulate", "--speed", "-2"], "--speed"),
        (["emulate", "--noise", "2"], "--noise"),
    ],
)
def test_command_errors_are_one_line(one_line_error, argv, msg):
    one_line_error(argv, msg)
