"""CPU cost of laser-only SLAM on the real logs end to end, its latency per keyframe and its
accuracy, optionally side by side with another revision of the code (issue 33's targets: MIT
CSAIL, the Intel bag and Freiburg 079 at least 40x faster than real time, the corridor 60x
with a p95 keyframe latency of 10 ms, peak memory under 500 MiB, relations error within 2 %).

Run: python experiments/bench_real_speed.py
       [--logs mit-csail freiburg-079 intel intel-bag corridor]
       [--backends isam2] [--max-scans N] [--compare REV] [--repeat N] [--profile | --split]
(``corridor``: the simulated corridor of seed 1, simulated first and not timed, fused sensors.)
Each run is a child process (``PYTHONPATH`` = the tree under test) that reads
``../shared/data/<log>``, runs :func:`fgslam.slam.runner.run_backends` with the scan-matching
defaults (``experiments/real_relations.py``'s "scan" mode: scan and wheel odometry, keyframes
by motion, loop closures on) and reports its process CPU time, its wall time, the CPU time
spent in loop-closure search (:meth:`fgslam.slam.loops.LoopCloser.try_close`), the loop
attempts and the accepted closures, the 95th percentile of the CPU time of the events that
completed a keyframe (``SlamPipeline.add``: the latency of an online run), and the relations
error of the every-scan trajectory where the log has relations (CARMEN logs: the benchmark's
method, :func:`fgslam.evaluation.dense.relations_error_chain`; the bag: interpolated). Before
the timed runs, each tree runs 40 scans untimed so that numba's kernels load from its disk
cache (``bench_kernels.py`` shows the cold and warm first calls). ``--compare REV`` checks REV
out into a temporary git worktree and runs it alternately with this tree (REV first), so that
both share the machine's load; on a shared machine compare CPU seconds, not wall seconds. The
real-time factor is log seconds / CPU seconds; the peak RSS is the child's whole process
(Python, numpy, GTSAM and the run). Prints one markdown row per run. ``--profile`` runs each
child under cProfile with the process-time clock (the profiler inflates Python-heavy parts:
read the shares; the table's CPU then includes it) and prints, after the table, where the CPU
went (:func:`split`). ``--split`` instead times the main stages with the process-time clock
around each call (no profiler, so the shares are those of a normal run; :func:`timers`) and
prints them after the table.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / ".." / "shared" / "data"
FILES = {
    "intel": "intel-corrected.log.gz",
    "freiburg-079": "freiburg-079-corrected.log.gz",
    "mit-csail": "mit-csail.clf",
    "intel-bag": "intel.orig.bag",
}
RELATIONS = {
    "intel": "intel-corrected.relations",
    "freiburg-079": "freiburg-079-corrected.relations",
    "mit-csail": "mit-csail.relations",
    "intel-bag": "intel.orig.relations",
}
SCAN = {"odometry": "both", "keyframes": "motion", "loop_closures": "on"}


def split(stats) -> dict:
    """Where the CPU of a profiled run went (s, cumulative): the loop-closure search, of it
    the matches and the local-map builds; the scan odometry; the front end without it; the
    SLAM step without the loop search, of it the backend's commit (iSAM2 update); the rest."""

    def cum(where: str, name: str, caller: tuple[str, str] | None = None) -> float:
        tot = 0.0
        for (f, _, n), (_, _, _, ct, callers) in stats.stats.items():
            if n != name or not f.endswith(where):
                continue
            if caller is None:
                tot += ct
            else:
                tot += sum(
                    v[3]
                    for (cf, _, cn), v in callers.items()
                    if cf.endswith(caller[0]) and cn in caller[1:]
                )
        return tot

    loops = "fgslam/slam/loops.py"
    sm = "fgslam/scanmatch/"
    out = {
        "total": cum("fgslam/slam/runner.py", "run_backends"),
        "loop_search": cum(loops, "try_close"),
        "loop_matches": cum(sm + "matcher.py", "match", (loops, "verify")),
        "loop_map_builds": cum(sm + "reference.py", "build", (loops, "verify", "reference")),
        "scan_odometry": cum("fgslam/slam/runner.py", "_select"),
        "front_end": cum("fgslam/frontend/pipeline.py", "process_scan"),
        "step": cum("fgslam/slam/step.py", "keyframe"),
        "commit": cum("fgslam/slam/graph.py", "commit", ("fgslam/slam/step.py", "keyframe")),
    }
    out["isam2_update"] = cum("~", "<built-in method gtsam.gtsam.update>")
    # the Python callbacks of the custom factors (lines, corners, calibrated odometry, own
    # time), wherever GTSAM calls them (iSAM2's linearisations, mostly)
    out["custom_factors"] = sum(
        v[3]
        for (f, _, n), v in stats.stats.items()
        if n == "error" and "/factors/" in f.replace("\\", "/")
    )
    out["front_end"] -= out["scan_odometry"]
    out["step"] -= out["loop_search"]
    out["rest"] = out["total"] - sum(out[k] for k in ("loop_search", "scan_odometry"))
    out["rest"] -= out["front_end"] + out["step"]
    return out


# (key, label): stages timed by ``--split``; an indented label is part of the row above it
SPLIT_ROWS = [
    ("total", "total"),
    ("front_end", "front end, every scan (FrontEnd.process_scan)"),
    ("scan_odometry", "- of it the scan odometry (ScanOdometry.add: a match per scan)"),
    ("step", "SLAM step, every keyframe (SlamStep.keyframe)"),
    ("loops", "- of it the loop-closure search (LoopCloser.try_close)"),
    ("commit", "- of it the backend's commit (iSAM2 update, estimate)"),
    ("match", "scan matches, anywhere (scanmatch.match)"),
    ("search", "- of it the correlative search"),
    ("icp", "- of it ICP (from each basin)"),
    ("build", "references built, anywhere (Reference.build)"),
]


def timers() -> dict:
    """Wrap the stages of :data:`SPLIT_ROWS` so that each call adds its process CPU time to
    the returned dict (seconds, and ``<key>_calls``)."""
    import functools

    from fgslam.frontend.pipeline import FrontEnd
    from fgslam.scanmatch import basins, matcher
    from fgslam.slam import keyframes, loops, step
    from fgslam.slam.graph import GraphBackend

    spent: dict = {}

    def timed(key, f):
        @functools.wraps(f)
        def g(*a, **kw):
            t0 = time.process_time()
            try:
                return f(*a, **kw)
            finally:
                spent[key] = spent.get(key, 0.0) + time.process_time() - t0
                spent[key + "_calls"] = spent.get(key + "_calls", 0) + 1

        return g

    for owner, name, key in [
        (FrontEnd, "process_scan", "front_end"),
        (keyframes.ScanOdometry, "add", "scan_odometry"),
        (step.SlamStep, "keyframe", "step"),
        (loops.LoopCloser, "try_close", "loops"),
        (GraphBackend, "commit", "commit"),
        (matcher, "_search", "search"),
    ]:
        setattr(owner, name, timed(key, getattr(owner, name)))
    # ICP runs from the best basin (matcher) and from the others (basins)
    matcher._icp = basins._icp = timed("icp", matcher._icp)
    build = timed("build", matcher.Reference.build.__func__)
    matcher.Reference.build = classmethod(build)
    match = timed("match", matcher.match)
    keyframes.match = loops.match = matcher.match = match
    return spent


def print_splits(runs: list[tuple[str, dict]]) -> None:
    """One column per ``--split`` run: CPU seconds (and calls) per stage."""

    def cell(key: str, r: dict) -> str:
        v = r["cpu_s"] if key == "total" else r["split"].get(key, 0.0)
        n = r["split"].get(key + "_calls")
        return f"{v:.1f}" + (f" ({n} calls)" if n else "")

    heads = [f"{r['log']} {r['backends']} {label}" for label, r in runs]
    columns("CPU (s), process clock around each call", heads, SPLIT_ROWS, runs, cell)


def columns(title: str, heads: list[str], rows: list, runs: list, cell) -> None:
    """A markdown table: a row per (key, name) of ``rows``, a column per run, ``cell(key,
    run)`` in each."""
    print()
    print(f"| {title} | " + " | ".join(heads) + " |")
    print("|---|" + "---|" * len(heads))
    for key, name in rows:
        print(f"| {name} | " + " | ".join(cell(key, r) for _, r in runs) + " |")


def child(
    log: str,
    backends: list[str],
    max_scans: int | None,
    profile: bool = False,
    split_: bool = False,
) -> dict:
    """One run in this process (the fgslam on ``sys.path``): its measurements."""
    from real_carmen import limited  # the same scan limit as the other real-log experiments

    import fgslam
    from fgslam.config import with_scanmatch
    from fgslam.io.formats import open_log
    from fgslam.slam import loops
    from fgslam.slam.runner import run_backends

    loop_cpu = [0.0]
    try_close = loops.LoopCloser.try_close

    def timed(self, *a, **kw):
        t0 = time.process_time()
        try:
            return try_close(self, *a, **kw)
        finally:
            loop_cpu[0] += time.process_time() - t0

    loops.LoopCloser.try_close = timed
    spent = timers() if split_ else {}
    # CPU of each event that completed a keyframe: an online run's latency per keyframe
    from fgslam.slam.runner import SlamPipeline

    latency: list[float] = []
    add = SlamPipeline.add

    def add_timed(self, ev):
        t0 = time.process_time()
        n = add(self, ev)
        if n:
            latency.append(time.process_time() - t0)
        return n

    SlamPipeline.add = add_timed

    sensors = "laser"
    if log == "corridor":  # the simulated corridor (seed 1), fused, the default pipeline
        from fgslam.config import load_config
        from fgslam.io.logfile import LogReader
        from fgslam.sim import simulate_to_log
        from fgslam.sim.world import load_world

        tmp = tempfile.TemporaryDirectory(prefix="bench_corridor_")  # removed when the run ends
        path = Path(tmp.name) / "corridor.log.gz"
        simulate_to_log(load_world("corridor"), load_config(), path, 1, None)
        reader, sensors = LogReader(path), "fused"
    else:
        reader = open_log(DATA / FILES[log])
    cfg = with_scanmatch(reader.config, SCAN)
    prof = cProfile.Profile(time.process_time) if profile else None
    c0, w0 = time.process_time(), time.perf_counter()
    if prof is not None:
        prof.enable()
    results = run_backends(limited(reader, max_scans), cfg, backends, sensors)
    if prof is not None:
        prof.disable()
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    res = results[0]
    rel = relations(log, res) if log in RELATIONS and max_scans is None else None
    where = {}
    if prof is not None:
        import pstats

        where = split(pstats.Stats(prof))
    return {
        "tree": str(Path(fgslam.__file__).resolve().parents[1]),
        "log": log,
        "backends": "+".join(backends),
        "log_s": res.log_duration,
        "cpu_s": cpu,
        "wall_s": wall,
        "loop_cpu_s": loop_cpu[0],
        "attempts": int(res.stats.get("loop_closures_tried", 0)),
        "accepted": sum(bool(c["accepted"]) for c in res.loop_closures),
        "keyframes": len(res.times),
        "maps_built": int(
            res.stats.get("loop_maps_built", res.stats.get("loop_closures_tried", 0))
        ),
        "profile": where,
        "p95_keyframe_ms": 1e3 * float(np.percentile(latency, 95)) if latency else float("nan"),
        "relations": rel,
        "split": spent,
        # peak resident memory of the whole child process (Linux: ru_maxrss in KiB)
        "max_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def relations(log: str, res) -> tuple[float, float]:
    """Relations error (translational m, rotational deg, means) of ``res``'s every-scan
    trajectory on ``log``."""
    from fgslam.evaluation import dense

    rel = dense.read_relations(DATA / RELATIONS[log])
    t, poses = res.every_scan
    if FILES[log].endswith(".bag"):
        m = dense.relations_error(rel, t, poses)
    else:
        from fgslam.io.readers.carmen import odometry_chain

        chain = odometry_chain(DATA / FILES[log])
        est, has = dense.estimate_at_scans(chain, t, poses)
        m = dense.relations_error_chain(rel, chain, est, has)
    return float(m["trans_mean"]), float(m["rot_mean_deg"])


def run_child(
    tree: Path,
    log: str,
    backends: list[str],
    max_scans: int | None,
    profile: bool = False,
    split_: bool = False,
) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    # this script (the same measurements on both trees) where the tree has the module
    # layout it imports (issue 32's); else the tree's own copy, which knows that layout
    script = Path(__file__).resolve()
    own = tree / "experiments" / Path(__file__).name
    if not (tree / "fgslam" / "io" / "formats.py").is_file() and own.is_file():
        script = own
    cmd = [sys.executable, str(script), "--child", "--logs", log]
    cmd += ["--backends", *backends]
    if max_scans is not None:
        cmd += ["--max-scans", str(max_scans)]
    if profile:
        cmd.append("--profile")
    if split_:
        cmd.append("--split")
    out = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def revision(tree: Path) -> str:
    git = ["git", "-C", str(tree), "rev-parse", "--short", "HEAD"]
    rev = subprocess.run(git, check=True, capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(
        ["git", "-C", str(tree), "status", "--porcelain", "--untracked-files=no"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    return rev + ("+" if dirty else "")


def row(label: str, r: dict) -> str:
    rt = r["log_s"] / r["cpu_s"] if r["cpu_s"] else float("nan")
    rel = "{:.4f} / {:.3f}".format(*r["relations"]) if r.get("relations") else "-"
    return (
        f"| {r['log']} | {r['backends']} | {label} | {r['log_s']:.0f} | {r['cpu_s']:.1f} | "
        f"{r['wall_s']:.1f} | {rt:.1f}x | {r['loop_cpu_s']:.1f} | {r['attempts']} | "
        f"{r['accepted']} | {r['keyframes']} | {r.get('max_rss_mib', float('nan')):.0f} | "
        f"{r.get('p95_keyframe_ms', float('nan')):.1f} | {rel} |"
    )


PROFILE_ROWS = [
    ("total", "total"),
    ("loop_search", "loop-closure search"),
    ("loop_matches", "- of it the matches"),
    ("loop_map_builds", "- of it the local-map builds"),
    ("loop_rest", "- the rest (marginals, poses, candidates, view checks)"),
    ("scan_odometry", "scan odometry (a match per scan, a reference per keyframe)"),
    ("front_end", "front end (features of the keyframes)"),
    ("step", "SLAM step without the loop search"),
    ("commit", "- of it the backend's commit (iSAM2 update)"),
    ("isam2_update", "iSAM2's update() calls, everywhere"),
    ("custom_factors", "custom factors' Python callbacks (nearly all within those)"),
    ("rest", "reading the log, the rest"),
]


def print_profiles(profiles: list[tuple[str, dict]]) -> None:
    """One column per profiled run: CPU seconds under the profiler."""

    def cell(key: str, r: dict) -> str:
        p = dict(r["profile"])
        p["loop_rest"] = p["loop_search"] - p["loop_matches"] - p["loop_map_builds"]
        out = f"{p[key]:.1f}"
        if key == "loop_search":
            out += f" ({r['attempts']} matches, {r['maps_built']} local maps built)"
        return out

    heads = [f"{r['log']} {label}" for label, r in profiles]
    columns("CPU under the profiler (s)", heads, PROFILE_ROWS, profiles, cell)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--logs", nargs="+", default=["mit-csail", "freiburg-079"], choices=[*FILES, "corridor"]
    )
    ap.add_argument("--backends", nargs="+", default=["isam2"])
    ap.add_argument("--max-scans", type=int, default=None)
    ap.add_argument("--compare", metavar="REV", help="also run this git revision, alternately")
    ap.add_argument("--repeat", type=int, default=1, help="runs of each tree per log")
    ap.add_argument("--profile", action="store_true", help="where the CPU goes (cProfile)")
    ap.add_argument(
        "--split", action="store_true", help="CPU per stage, timed around each call (no profiler)"
    )
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        out = child(args.logs[0], args.backends, args.max_scans, args.profile, args.split)
        print(json.dumps(out))
        return
    trees = [(revision(ROOT), ROOT)]
    with tempfile.TemporaryDirectory(prefix="bench_real_speed_") as tmp:
        if args.compare:
            other = Path(tmp) / "tree"
            subprocess.run(
                ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(other), args.compare],
                check=True,
                capture_output=True,
            )
            trees.insert(0, (revision(other), other))
            # the other tree's own script finds the logs beside it, as this one does
            if DATA.resolve().is_dir():
                (Path(tmp) / "shared").symlink_to(DATA.resolve().parent)
        try:
            print(
                "| log | backend | code | log (s) | CPU (s) | wall (s) | real time / CPU | "
                "loop search CPU (s) | loop attempts | accepted | keyframes | peak RSS (MiB) | "
                "p95 keyframe CPU (ms) | relations m / deg |"
            )
            print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
            profiles = []
            # numba compiles a kernel on its first call and caches it on disk beside the
            # code: a short untimed run per tree first, so that every timed run loads the
            # kernels from the cache as a user's second run does (bench_kernels.py shows the
            # cold and warm first calls)
            for _, tree in trees:
                run_child(tree, args.logs[0], args.backends, 40)
            for log in args.logs:
                for _ in range(args.repeat):
                    for label, tree in trees:
                        r = run_child(
                            tree, log, args.backends, args.max_scans, args.profile, args.split
                        )
                        print(row(label, r), flush=True)
                        profiles.append((label, r))
            if args.profile:
                print_profiles(profiles)
            if args.split:
                print_splits(profiles)
        finally:
            if args.compare:
                subprocess.run(
                    ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(other)],
                    check=False,
                    capture_output=True,
                )


if __name__ == "__main__":
    main()
