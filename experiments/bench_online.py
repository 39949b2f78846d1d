"""Online runs over serial ports (issues 6, 17): how fast the emulators can play the corridor
run while the online pipeline (pty drivers in the device process -> merge by device time ->
front end -> iSAM2) keeps up; what happens when the host is loaded; and the CPU the online
run costs at the paper's 38400 baud in real time.

1. Speed sweep, on a short run (the first ``--duration`` s of the corridor run, seed 1), at
   each speed in ``--speeds``, in two set-ups: the emulators in the device process with the
   drivers (``DeviceProcess(emulation=...)``), and in a process of their own (``fgslam
   emulate``, as from the command line). "Keeps up" means: every data frame the emulators
   sent was received intact and processed (no CRC errors, dropped frames, discarded bytes,
   bytes the host failed to read, events dropped as out of order), the emulator played the
   run at the asked speed (within 5 %), and the SLAM pipeline was busy less than the wall
   time (it does not fall behind).
2. Loaded host: the same at ``--loaded-speed`` with busy processes on every core (2 per
   core): lag, events processed, and whether the map is the replay's bit for bit.
3. CPU at real time (speed 1, ``--cpu-duration`` s, emulators in a separate process): CPU
   time / wall time of the SLAM process and of the device and emulator processes.

Run: python experiments/bench_online.py [--duration 30] [--speeds 2,4,8,12,16,24,32]
[--loaded-speed 6] [--cpu-duration 60]. Prints markdown tables; writes nothing.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from fgslam.config import load_config
from fgslam.io.logfile import LogReader
from fgslam.online.device_process import DeviceProcess, EmulationSpec
from fgslam.online.loop import run_online
from fgslam.online.ports import replay_to_log
from fgslam.slam.runner import run_slam

CFG = load_config()
IDLE = 1.5  # s without data: end of the run
TICK = os.sysconf("SC_CLK_TCK")
EMULATE = [sys.executable, "-m", "fgslam.cli", "emulate"]


class Timed:
    """The device process, recording the wall time of the first and the last event."""

    def __init__(self, dev: DeviceProcess) -> None:
        self.dev = dev
        self.clock = dev.clock
        self.names = dev.names
        self.first = self.last = None
        self.odometry = 0

    def poll(self, timeout: float = 0.05):
        item = self.dev.poll(timeout)
        if item is not None and not isinstance(item, dict):
            now = time.monotonic()
            self.first = self.first or now
            self.last = now
            self.odometry += type(item).__name__ == "OdometryEvent"
        return item

    def drain(self):
        return self.dev.drain()

    def errors(self):
        return self.dev.errors()

    def status(self):
        return self.dev.status()


def proc_cpu(pid: int) -> float:
    """CPU seconds (user + system) of process ``pid`` so far, from /proc."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / TICK


def process_cpu(who: int = resource.RUSAGE_SELF) -> float:
    r = resource.getrusage(who)
    return r.ru_utime + r.ru_stime


def online(dev: DeviceProcess, raw: Path | None = None) -> dict[str, Any]:
    """Run SLAM online on the started device process until the data ends; measurements."""
    assert dev.wait_connected(60), dev.status()
    timed = Timed(dev)
    pid = dev._proc.pid  # private: a benchmark
    cpu0, wall0, dev0 = process_cpu(), time.monotonic(), proc_cpu(pid)
    run = run_online(timed, CFG, idle_timeout=IDLE)  # type: ignore[arg-type]
    wall = time.monotonic() - wall0 - IDLE
    dev_cpu = proc_cpu(pid) - dev0
    return {
        "run": run,
        "wall": wall,
        "cpu": process_cpu() - cpu0,
        "device_cpu": dev_cpu,
        "played": timed.odometry * CFG.odometry.sample_period,
        "span": (timed.last - timed.first) if timed.first else float("nan"),
    }


def with_device_process(
    speed: float, duration: float, seed: int, raw: Path | None = None
) -> dict[str, Any]:
    spec = EmulationSpec("corridor", seed=seed, duration=duration)
    dev = DeviceProcess(CFG, speed=speed, emulation=spec, record_dir=raw, world="corridor")
    with dev:
        m = online(dev)
    st = dev.emulation["stats"]
    m["run"].status = dev.status()
    m["sent"] = sum(s["frames_sent"] for s in st.values())
    m["overflow"] = sum(s["overflow_bytes"] for s in st.values())
    return m


def separate_process(speed: float, duration: float, seed: int) -> dict[str, Any]:
    links = Path(tempfile.mkdtemp(prefix="bench-online-"))
    cpu0 = process_cpu(resource.RUSAGE_CHILDREN)
    opts = ["--speed", f"{speed:g}", "--duration", f"{duration:g}", "--seed", str(seed)]
    emu = subprocess.Popen(
        [*EMULATE, *opts, "--link-dir", str(links)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 60
        while not (links / "odometry").exists():
            assert emu.poll() is None and time.monotonic() < deadline, emu.communicate()
            time.sleep(0.05)
        dev = DeviceProcess(
            CFG,
            laser=str(links / "laser"),
            sonar=[str(links / "sonar0"), str(links / "sonar1")],
            odometry=str(links / "odometry"),
            speed=speed,
        )
        with dev:
            m = online(dev)
        m["run"].status = dev.status()
        out, err = emu.communicate(timeout=60)
    finally:
        if emu.poll() is None:
            emu.kill()
            emu.communicate()
        shutil.rmtree(links, ignore_errors=True)
    m["emulator_cpu"] = process_cpu(resource.RUSAGE_CHILDREN) - cpu0 - m["device_cpu"]
    found = re.search(r"(\d+) data frames sent, (\d+) lost .*?, (\d+) bytes", out)
    assert found, (out, err)
    m["sent"], m["overflow"] = int(found[1]), int(found[3])
    return m


def verdict(m: dict[str, Any], speed: float) -> tuple[bool, dict[str, Any]]:
    run = m["run"]
    st = run.status
    received = sum(run.events.values())
    faults = sum(s["crc_errors"] + s.get("dropped_frames", 0) + s["discarded"] for s in st.values())
    achieved = m["played"] / m["span"] if m["span"] > 0 else float("nan")
    lat = np.array(run.result.latencies) * 1e3
    busy = run.busy_seconds / m["wall"]
    ok = (
        received == m["sent"]
        and faults == 0
        and m["overflow"] == 0
        and achieved >= 0.95 * speed
        and busy < 1.0
        and "events_out_of_order" not in run.result.stats
    )
    return ok, {
        "received": received,
        "sent": m["sent"],
        "faults": faults,
        "overflow": m["overflow"],
        "achieved": achieved,
        "lag": run.max_lag,
        "lat": lat,
        "busy": busy,
    }


def sweep(args) -> None:
    print(
        f"### Speed sweep: first {args.duration:g} s of the corridor run (seed {args.seed}), "
        "iSAM2 fused\n"
    )
    print(
        "| emulators | speed | frames received / sent | CRC + dropped + discarded | bytes "
        "not read | run played at | max lag (log s) | max lag (wall ms) | keyframe latency "
        "p50 / p95 / max (ms) | SLAM busy / wall | keeps up |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    best: dict[str, float] = {}
    modes = (("in the device process", with_device_process), ("own process", separate_process))
    for mode, fn in modes:
        for speed in args.speeds:
            m = fn(speed, args.duration, args.seed)
            ok, v = verdict(m, speed)
            if ok:
                best[mode] = max(best.get(mode, 0.0), speed)
            lat = v["lat"]
            print(
                f"| {mode} | {speed:g}x | {v['received']} / {v['sent']} | {v['faults']} | "
                f"{v['overflow']} | {v['achieved']:.1f}x | {v['lag']:.2f} | "
                f"{v['lag'] / speed * 1e3:.0f} | {np.median(lat):.1f} / "
                f"{np.percentile(lat, 95):.1f} / {lat.max():.0f} | "
                f"{v['busy']:.2f} | {'yes' if ok else 'no'} |",
                flush=True,
            )
    print()
    for mode, _ in modes:
        print(f"- highest speed that keeps up, emulators {mode}: {best.get(mode, 0):g}x")
    print()


def loaded(args) -> None:
    hogs = 2 * (os.cpu_count() or 1)
    speed = args.loaded_speed
    print(
        f"### Loaded host: {hogs} busy processes on {os.cpu_count()} cores, "
        f"{args.duration:g} s of the corridor run at {speed:g}x, emulators in the device "
        "process\n"
    )
    print(
        "| host | frames received / sent | events processed | dropped as out of order | "
        "max lag (log s) | SLAM busy / wall | equal to the replay |"
    )
    print("|---|---|---|---|---|---|---|")
    for label in ("quiet", "loaded"):
        raw = Path(tempfile.mkdtemp(prefix="bench-online-raw-"))
        procs = []
        if label == "loaded":
            procs = [
                subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(hogs)
            ]
        try:
            m = with_device_process(speed, args.duration, args.seed, raw / "raw")
        finally:
            for p in procs:
                p.kill()
                p.wait()
        run = m["run"]
        log = raw / "replayed.log.gz"
        replay_to_log(raw / "raw", log)
        with LogReader(log) as reader:
            ref = run_slam(reader, CFG, "isam2", "fused")
        same = np.array_equal(ref.poses, run.result.poses) and ref.means.keys() == (
            run.result.means.keys()
        )
        shutil.rmtree(raw, ignore_errors=True)
        print(
            f"| {label} | {sum(run.events.values())} / {m['sent']} | "
            f"{sum(run.events.values())} | {run.result.stats.get('events_out_of_order', 0)} | "
            f"{run.max_lag:.2f} | {run.busy_seconds / m['wall']:.2f} | "
            f"{'yes' if same else 'NO'} |",
            flush=True,
        )
    print()


def cpu(args) -> None:
    m = separate_process(1.0, args.cpu_duration, args.seed)
    ok, v = verdict(m, 1.0)
    wall = m["wall"]
    print(
        f"### CPU at real time: {args.cpu_duration:g} s of the corridor run, laser at "
        f"{CFG.laser.baud_rate} baud, emulators in a separate process\n"
    )
    print("| component | CPU s | CPU / wall |")
    print("|---|---|---|")
    rows = [
        ("SLAM process (merge, front end, iSAM2, status)", m["cpu"]),
        ("device process (4 drivers)", m["device_cpu"]),
        ("emulator process (start-up included)", m["emulator_cpu"]),
    ]
    for name, c in rows:
        print(f"| {name} | {c:.2f} | {100 * c / wall:.1f} % |")
    print(
        f"\n(wall {wall:.1f} s; {v['received']} / {v['sent']} frames; max lag "
        f"{v['lag']:.2f} s; keeps up: {'yes' if ok else 'no'}; busy time in the pipeline "
        f"{m['run'].busy_seconds:.2f} s)"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=30.0, help="run seconds per speed")
    ap.add_argument(
        "--speeds",
        type=lambda s: [float(x) for x in s.split(",")],
        default=[2.0, 4.0, 8.0, 12.0, 16.0, 24.0, 32.0],
    )
    ap.add_argument("--loaded-speed", type=float, default=6.0)
    ap.add_argument("--cpu-duration", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at start\n")
    sweep(args)
    loaded(args)
    cpu(args)
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end; {threading.active_count()} threads")


if __name__ == "__main__":
    main()
