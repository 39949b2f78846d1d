"""Online runs over serial ports (issue 6): how fast the emulators can play the corridor run
while the online pipeline (pty drivers -> reorder buffer -> front end -> iSAM2) keeps up,
and the CPU the online run costs at the paper's 38400 baud in real time.

1. Speed sweep, on a short run (the first ``--duration`` s of the corridor run, seed 1), at
   each speed in ``--speeds``, in two set-ups: the emulators in the same process as the
   host (``start_emulators``, one clock), and in a separate process (``fgslam emulate``, as
   from the command line). "Keeps up" means: every data frame the emulators sent was
   received intact (no CRC errors, dropped frames or discarded bytes, no bytes the host
   failed to read), the emulator played the run at the asked speed (within 5 %), and no
   event lagged the host clock by more than the reorder window when it was processed (so
   none could be dropped as out of order).
2. CPU at real time (speed 1, ``--cpu-duration`` s, emulators in a separate process): CPU
   time / wall time of the host process, of each driver thread and of the main thread
   (front end + iSAM2 + status), and of the emulator process.

Run: python experiments/bench_online.py [--duration 30] [--speeds 2,4,8,12,16,24,32]
[--cpu-duration 60]. Prints markdown tables; writes nothing.
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
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from fgslam.config import load_config
from fgslam.online import REORDER_WINDOW, run_online
from fgslam.ports import DevicePorts, start_emulators
from fgslam.sim.world import load_world

CFG = load_config()
IDLE = 1.5  # s without data: end of the run
TICK = os.sysconf("SC_CLK_TCK")
EMULATE = [sys.executable, "-m", "fgslam.cli", "emulate"]


class Timed:
    """The ports, recording the wall time of the first and the last event taken."""

    def __init__(self, ports: DevicePorts) -> None:
        self.ports = ports
        self.clock = ports.clock
        self.first = self.last = None
        self.odometry = 0

    def get(self, timeout: float | None = None):
        ev = self.ports.get(timeout)
        if ev is not None:
            now = time.monotonic()
            self.first = self.first or now
            self.last = now
            self.odometry += type(ev).__name__ == "OdometryEvent"
        return ev

    def errors(self):
        return self.ports.errors()

    def status(self):
        return self.ports.status()


def thread_cpu(native_id: int | None) -> float:
    """CPU seconds (user + system) of one thread of this process, from /proc."""
    if native_id is None:
        return float("nan")
    try:
        fields = Path(f"/proc/self/task/{native_id}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / TICK


def process_cpu(who: int = resource.RUSAGE_SELF) -> float:
    r = resource.getrusage(who)
    return r.ru_utime + r.ru_stime


def online(ports: DevicePorts, after: Callable[[], None] | None = None) -> dict[str, Any]:
    """Run SLAM online on started ``ports`` until the data ends; measurements."""
    assert ports.wait_connected(60), ports.status()
    timed = Timed(ports)
    cpu0, wall0, main0 = process_cpu(), time.monotonic(), time.thread_time()
    threads = {n: r._thread for n, r in ports._runners.items()}  # private: a benchmark
    thr0 = {n: thread_cpu(t.native_id) for n, t in threads.items()}
    run = run_online(timed, CFG, idle_timeout=IDLE)  # type: ignore[arg-type]
    wall = time.monotonic() - wall0 - IDLE
    out = {
        "run": run,
        "wall": wall,
        "cpu": process_cpu() - cpu0,
        "main": time.thread_time() - main0,
        "threads": {n: thread_cpu(t.native_id) - thr0[n] for n, t in threads.items()},
        "played": timed.odometry * CFG.odometry.sample_period,
        "span": (timed.last - timed.first) if timed.first else float("nan"),
    }
    if after is not None:
        after()
    return out


def in_process(speed: float, duration: float, seed: int) -> dict[str, Any]:
    emu = start_emulators(CFG, load_world("corridor"), seed=seed, speed=speed, duration=duration)
    try:
        with DevicePorts.for_emulation(CFG, emu) as ports:
            m = online(ports)
        st = emu.stats()
    finally:
        emu.stop()
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
        from devices.clock import Clock

        with DevicePorts(
            CFG,
            laser=str(links / "laser"),
            sonar=[str(links / "sonar0"), str(links / "sonar1")],
            odometry=str(links / "odometry"),
            clock=Clock(speed),
        ) as ports:
            m = online(ports)
        out, err = emu.communicate(timeout=60)
    finally:
        if emu.poll() is None:
            emu.kill()
            emu.communicate()
        shutil.rmtree(links, ignore_errors=True)
    m["emulator_cpu"] = process_cpu(resource.RUSAGE_CHILDREN) - cpu0
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
    ok = (
        received == m["sent"]
        and faults == 0
        and m["overflow"] == 0
        and achieved >= 0.95 * speed
        and run.max_lag < REORDER_WINDOW
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
    }


def sweep(args) -> None:
    print(
        f"### Speed sweep: first {args.duration:g} s of the corridor run (seed {args.seed}), "
        "iSAM2 fused\n"
    )
    print(
        "| emulators | speed | frames received / sent | CRC + dropped + discarded | bytes "
        "not read | run played at | max lag (log s) | max lag (wall ms) | keyframe latency "
        "p50 / p95 / max (ms) | host CPU / wall | keeps up |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    best: dict[str, float] = {}
    for mode, fn in (("same process", in_process), ("separate process", separate_process)):
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
                f"{m['cpu'] / m['wall']:.2f} | {'yes' if ok else 'no'} |",
                flush=True,
            )
    print()
    for mode in ("same process", "separate process"):
        print(f"- highest speed that keeps up, emulators in the {mode}: {best.get(mode, 0):g}x")
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
    rows = [("host process, all", m["cpu"])]
    rows += [(f"driver thread {n}", c) for n, c in m["threads"].items()]
    rows += [("main thread (front end, iSAM2, status)", m["main"])]
    rows += [("emulator process (start-up included)", m["emulator_cpu"])]
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
    ap.add_argument("--cpu-duration", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at start\n")
    sweep(args)
    cpu(args)
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end; {threading.active_count()} threads")


if __name__ == "__main__":
    main()
