"""Every real log, run to the end as a new user would (issue 31, item 5).

Run: python experiments/real_corpus.py [--data DIR] [--out DIR] [--logs NAME ...]
       [--backends isam2 ekf] [--timeout S] [--workers 1]

The (log, backend) runs are a sweep on a local Dask cluster (fgslam.sweep; one worker by
default, so that the wall times are undisturbed): with ``--out``, a run stopped and started
again runs only what is missing.

Each log in the data folder (default ``../shared/data`` beside the project) goes through the
command line exactly as a user types it, with default options: a ROS bag first through
``fgslam convert``, then ``fgslam run LOG --backend B --sensors laser`` for iSAM2 and the
EKF (none of these logs has sonar, so there is no fused run), and, where the benchmark has
relations for the log, ``fgslam evaluate`` with them (every-scan logs: the run's dense
trajectory; corrected logs, which keep one scan in a few: the keyframes bridged by the log's
own odometry, the benchmark's method). Victoria Park (point landmarks, given association) is run by
``experiments/real_victoria_park.py`` instead. Prints one markdown table: log, backend,
scans placed, records skipped, finished (exit status, partial or not, every output
written), wall time and real-time factor, relations error where relations exist, else ATE
against the log's reference poses, and the warnings the run printed.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

from fgslam.sweep import sweep_function

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
OUTPUTS = ("trajectory.tum", "map.json", "report.json", "map.png")
# log file -> relations file of the benchmark (on the log's own clock), and whether the log
# keeps every scan (a dense trajectory is scored) or a subset (keyframes + odometry records)
RELATIONS = {
    "intel-corrected.log.gz": ("intel-corrected.relations", False),
    "freiburg-079-corrected.log.gz": ("freiburg-079-corrected.relations", False),
    "mit-csail.clf": ("mit-csail.relations", True),
    "intel.orig.bag": ("intel.orig.relations", True),
}
SKIP = {"victoria_park.txt"}  # point landmarks: experiments/real_victoria_park.py


def fgslam(*args: str, timeout: float) -> tuple[int, str, float]:
    """Run ``fgslam ARGS`` as a user would; (exit status, stderr, wall seconds)."""
    t0 = time.perf_counter()
    try:
        p = subprocess.run(
            [sys.executable, "-m", "fgslam.cli", *args],
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )
        return p.returncode, p.stderr + p.stdout, time.perf_counter() - t0
    except subprocess.TimeoutExpired:
        return -1, f"timed out after {timeout:.0f} s", time.perf_counter() - t0


def logs(data: Path, names: list[str] | None) -> list[Path]:
    out = []
    for p in sorted(data.iterdir()):
        if p.name in SKIP or p.suffix == ".relations" or p.name.endswith(".md"):
            continue
        if names and not any(n in p.name for n in names):
            continue
        out.append(p)
    return out


def warnings_of(text: str) -> list[str]:
    lines = [ln.strip() for ln in text.splitlines()]
    return [ln for ln in lines if "warning" in ln.lower() or "error" in ln.lower()]


def one_run(log: Path, run_log: Path, backend: str, sensors: str, out: Path, args) -> dict:
    rc, text, wall = fgslam(
        "run", str(run_log), "--backend", backend, "--sensors", sensors, "--out", str(out),
        timeout=args.timeout,
    )  # fmt: skip
    row = {"log": log.name, "backend": f"{backend}/{sensors}", "exit": rc, "wall": wall}
    row["warnings"] = warnings_of(text)
    row["outputs"] = all((out / f).exists() for f in OUTPUTS)
    rep = {}
    if (out / "report.json").exists():
        rep = json.loads((out / "report.json").read_text())
    row["partial"] = bool(rep.get("partial"))
    row["scans"] = rep.get("scans_placed")
    row["skipped"] = (rep.get("reader") or {}).get("skipped_by_reason", {})
    row["duration"] = rep.get("log_duration_s")
    if rep.get("ate"):
        row["ate"] = rep["ate"]["rmse"]
    rel = RELATIONS.get(log.name)
    if rel is not None and rc == 0:
        rel_file, dense = rel
        ev = ["evaluate", str(out), "--relations", str(log.parent / rel_file)]
        if not dense:
            ev += ["--odometry-log", str(log)]
        ev += ["--out", str(out / "relations.json")]
        erc, etext, _ = fgslam(*ev, timeout=args.timeout)
        if erc == 0 and (out / "relations.json").exists():
            r = json.loads((out / "relations.json").read_text())
            r = r.get("relations", r)
            row["relations"] = (r["trans_mean"], r["rot_mean_deg"])
        else:
            row["warnings"].append(f"evaluate failed: {etext.strip()[:120]}")
    return row


def _cell_row(opts: dict, settings: dict) -> dict:
    """One (log, backend) cell of the sweep: the bag converted first (once; kept in the work
    folder), then :func:`one_run`."""
    log = Path(settings["log"])
    work = Path(opts["work"])
    args = argparse.Namespace(timeout=opts["timeout"])
    run_log = log
    if log.suffix == ".bag":  # a bag goes through convert first, as the issue says
        run_log = work / (log.stem + ".log.gz")
        if not run_log.exists():
            rc, text, _ = fgslam("convert", str(log), "--out", str(run_log), timeout=args.timeout)
            if rc != 0:
                return {"log": log.name, "backend": "convert", "exit": rc, "wall": 0.0,
                        "warnings": warnings_of(text), "outputs": False, "partial": False,
                        "scans": None, "skipped": {}, "duration": None}  # fmt: skip
    backend = settings["backend"]
    out = work / f"{log.name}.{backend}.laser"
    return one_run(log, run_log, backend, "laser", out, args)


def table(rows: list[dict]) -> str:
    head = (
        "| log | backend | scans placed | records skipped | finished | wall s | x real time "
        "| relations m / deg | ATE m (reference) | warnings |\n"
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"
    )
    out = [head]
    for r in rows:
        done = "yes" if r["exit"] == 0 and not r["partial"] and r["outputs"] else "NO"
        if r["exit"] != 0 or r["partial"]:
            done += f" (exit {r['exit']}{', partial' if r['partial'] else ''})"
        if not r["outputs"]:
            done += " (outputs missing)"
        rt = f"{r['duration'] / r['wall']:.1f}" if r.get("duration") and r["wall"] else "-"
        rel = "{:.3f} / {:.2f}".format(*r["relations"]) if r.get("relations") else "-"
        ate = f"{r['ate']:.3f}" if r.get("ate") is not None and not r.get("relations") else "-"
        sk = sum(r["skipped"].values()) if r["skipped"] else 0
        warn = "; ".join(w[:90] for w in r["warnings"][:3]) or "-"
        if len(r["warnings"]) > 3:
            warn += f" (+{len(r['warnings']) - 3})"
        out.append(
            f"| {r['log']} | {r['backend']} | {r['scans'] or '-'} | {sk} | {done} "
            f"| {r['wall']:.0f} | {rt} | {rel} | {ate} | {warn} |"
        )
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--out", type=Path, default=None, help="keep the runs' outputs here")
    ap.add_argument("--logs", nargs="*", help="only logs whose file name contains one of these")
    ap.add_argument("--backends", nargs="*", default=["isam2", "ekf"])
    ap.add_argument("--timeout", type=float, default=3600.0, help="s per command")
    ap.add_argument(
        "--workers", type=int, default=1, help="Dask workers (1: the wall times undisturbed)"
    )
    args = ap.parse_args()
    work = args.out or Path(tempfile.mkdtemp(prefix="fgslam-corpus-"))
    work.mkdir(parents=True, exist_ok=True)
    found = logs(args.data, args.logs)

    def progress(p: dict) -> None:
        if "dashboard" not in p:
            print(f"{p['done']} of {p['total']} runs done", file=sys.stderr, flush=True)

    opts = {"timeout": args.timeout, "work": str(work)}
    rows = sweep_function(
        partial(_cell_row, opts),
        {"log": [str(p) for p in found], "backend": list(args.backends)},
        work / "sweep",
        workers=args.workers,
        name="real corpus",
        progress=progress,
    )
    print(table(rows))
    print(f"\n(outputs in {work})")


if __name__ == "__main__":
    main()
