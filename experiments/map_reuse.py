"""Map reuse (issue 35): localization on a saved session, measured.

Part ``corridor``: the simulated corridor world mapped once (seed 0, the whole route, laser
iSAM2, saved and read back as a session); then runs of seeds 1-10, each started at a random
time of its route with no initial pose (global localization), and each kidnapped once (the
log cut between two random times: the robot is carried away, its odometry saw nothing).
Success: localized, and every localized pose within 0.2 m and 3 deg of the truth (after the
relocalization, for the kidnapping).

Part ``freiburg``: Freiburg 079 (the corrected CARMEN log) cut in two halves at the median
scan time; the first half mapped (laser iSAM2, the scan-matching defaults) and saved; the
second localized on it without an initial pose (its relations error on the relations with
both ends in the second half, from the localized scans alone, the rest bridged by the log's
odometry as for every estimate, and from every scan with the gaps bridged by the localizer's
scan odometry), and the second continuing it (``--continue``: the joined
map's error on all relations); beside one run over the whole log scored on the same
relations; and the speeds (the continued run's real-time factor: the second half's
duration over the anchor search and the run).

    python experiments/map_reuse.py [--part corridor|freiburg|all] [--seeds 10] [--workers 1]

(the corridor's seeds run as a sweep on a local Dask cluster, fgslam.sweep)
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np

from factors.geometry import wrap_angles
from fgslam.config import load_config, with_options
from fgslam.evaluation import dense
from fgslam.evaluation.metrics import interpolate_poses
from fgslam.events import LaserScan, TruthPose
from fgslam.io.formats import open_log
from fgslam.io.readers.carmen import odometry_chain
from fgslam.session import Session, load_session, save_session
from fgslam.session.join import Continuation, find_anchor
from fgslam.session.localize import Localizer
from fgslam.sim import simulate_to_log
from fgslam.sim.world import load_world
from fgslam.slam.runner import run_backends
from fgslam.sweep import sweep_function

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
SCAN = {"odometry": "both", "keyframes": "motion", "loop_closures": "on"}
OK_XY, OK_DEG = 0.2, 3.0


def _errors(res, truth: np.ndarray, after: float = -math.inf) -> tuple[float, float]:
    """Largest position (m) and heading (deg) error of the localized scans after ``after``."""
    ok = np.isfinite(res.poses).all(axis=1) & (res.times > after)
    if not ok.any():
        return math.inf, math.inf
    t, p = res.times[ok], res.poses[ok]
    at = interpolate_poses(truth[:, 0], truth[:, 1:], t)
    dth = np.degrees(np.abs(wrap_angles(p[:, 2] - at[:, 2])))
    return float(np.hypot(p[:, 0] - at[:, 0], p[:, 1] - at[:, 1]).max()), float(dth.max())


def _localize(session, cfg, events, initial=None):
    loc = Localizer(session, cfg, initial)
    t0 = time.perf_counter()
    for e in events:
        loc.add(e)
    res = loc.finish()
    return res, time.perf_counter() - t0


def _corridor_seed(session_dir: str, settings: dict) -> dict:
    """One seed of the corridor part (a cell of its sweep): localized from a random start,
    and kidnapped once; the table's row and the two verdicts."""
    cfg = load_config(None)
    seed = settings["seed"]
    session = load_session(session_dir)
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "run.log.gz"
        simulate_to_log(load_world("corridor"), cfg, log, seed=seed)
        events = list(open_log(log))
    truth = np.array([(e.t, e.x, e.y, e.theta) for e in events if isinstance(e, TruthPose)])
    rng = np.random.default_rng(seed)
    end = float(truth[-1, 0])
    start = float(rng.uniform(0.0, end - 150.0))
    res, wall = _localize(session, cfg, [e for e in events if e.t >= start])
    rep = res.report()
    exy, eth = _errors(res, truth)
    win = rep["localized"] and exy <= OK_XY and eth <= OK_DEG
    after = f"{rep['localized_at'] - start:.1f}" if rep["localized"] else "never"
    # kidnapped: the log cut from a to b
    a = float(rng.uniform(30.0, end - 200.0))
    b = float(a + rng.uniform(30.0, 120.0))
    cut = [e for e in events if e.t < a] + [
        dataclasses.replace(e, t=e.t - (b - a)) for e in events if e.t >= b
    ]
    kt = np.array([(e.t, e.x, e.y, e.theta) for e in cut if isinstance(e, TruthPose)])
    kres, _ = _localize(session, cfg, cut)
    back = [e["t"] for e in kres.events if e["event"] == "localized" and e["t"] > a]
    kxy, kth = _errors(kres, kt, after=back[0] if back else math.inf)
    kwin = bool(back) and kxy <= OK_XY and kth <= OK_DEG
    found = f"{back[0] - a:.1f}" if back else "never"
    row = (
        f"| {seed} | {start:.0f} | {after} | {exy:.3f} / {eth:.2f} | {a:.0f} -> {b:.0f} "
        f"| {found} | {kxy:.3f} / {kth:.2f} | {res.log_duration / wall:.0f}x |"
    )
    return {"row": row, "win": bool(win), "kidnap_win": bool(kwin)}


def corridor(seeds: int, workers: int) -> None:
    cfg = load_config(None)
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        simulate_to_log(load_world("corridor"), cfg, d / "map.log.gz", seed=0)
        res = run_backends(open_log(d / "map.log.gz"), cfg, ["isam2"], "laser")[0]
        save_session(Session.from_result(res, cfg), d / "session")
        session = load_session(d / "session")
        print(f"map: seed 0, {session.keyframes} keyframes, {res.log_duration:.0f} s\n")
        rows = sweep_function(  # the seeds as a sweep (a fresh map each time: a new folder)
            partial(_corridor_seed, str(d / "session")),
            {"seed": list(range(1, seeds + 1))},
            d / "sweep",
            workers=workers,
            name="map reuse: corridor",
        )
    print(
        "| seed | start (s) | localized after (s) | max error m / deg | kidnapped "
        "a -> b (s) | found again after (s) | max error after m / deg | real time |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(r["row"])
    wins, kid_wins = sum(r["win"] for r in rows), sum(r["kidnap_win"] for r in rows)
    print(
        f"\nglobal localization right (within {OK_XY} m, {OK_DEG} deg): {wins} of {seeds}; "
        f"kidnapped robot found again and right: {kid_wins} of {seeds}"
    )


def freiburg() -> None:
    path = DATA / "freiburg-079-corrected.log.gz"
    rel = dense.read_relations(DATA / "freiburg-079-corrected.relations")
    chain = odometry_chain(path)
    reader = open_log(path)
    cfg = with_options(reader.config, {"scanmatch": SCAN})
    events = list(reader)
    scans = np.array([e.t for e in events if isinstance(e, LaserScan)])
    split = float(np.median(scans))
    half2 = rel[(rel[:, 0] >= split) & (rel[:, 1] >= split)]

    def score(t, poses, relations):
        est, has = dense.estimate_at_scans(chain, t, poses)
        m = dense.relations_error_chain(relations, chain, est, has)
        return f"{m['trans_mean']:.4f} / {m['rot_mean_deg']:.3f} ({m['relations_used']})"

    t0 = time.perf_counter()
    whole = run_backends(events, cfg, ["isam2"], "laser")[0]
    w_wall = time.perf_counter() - t0
    first = run_backends([e for e in events if e.t < split], cfg, ["isam2"], "laser")[0]
    second = [e for e in events if e.t >= split]
    with tempfile.TemporaryDirectory() as tmp:
        save_session(Session.from_result(first, cfg), Path(tmp) / "s")
        session = load_session(Path(tmp) / "s")
    runs = {}  # [localize] motion -> (result, wall)
    for motion in ("wheels", "fused", "scan"):
        c = with_options(cfg, {"localize": {"motion": motion}})
        runs[motion] = _localize(session, c, second)
    rep = runs["wheels"][0].report()
    t0 = time.perf_counter()
    anchor = find_anchor(session, second, cfg)
    cont = Continuation(session, anchor, "first half")
    joined = run_backends(second, cfg, ["isam2"], "laser", continuation=cont)[0]
    c_wall = time.perf_counter() - t0
    half_s = second[-1].t - second[0].t
    print(f"Freiburg 079 cut at t = {split:.1f} s ({len(scans)} scans; {len(rel)} relations,")
    print(f"{len(half2)} of them in the second half)\n")
    print(
        "| run | all relations m / deg (used) | second half's: localized scans | "
        "every scan, bridged | wall (s) | real time |"
    )
    print("|---|---|---|---|---|---|")
    print(
        f"| one run over the whole log (iSAM2) | {score(*whole.every_scan, rel)} | "
        f"{score(*whole.every_scan, half2)} | | {w_wall:.0f} | "
        f"{whole.log_duration / w_wall:.0f}x |"
    )
    for motion, (r, w) in runs.items():
        ok = np.isfinite(r.poses).all(axis=1)
        print(
            f"| first half mapped, second localized on it, motion {motion} | - | "
            f"{score(r.times[ok], r.poses[ok], half2)} | {score(r.times, r.bridged(), half2)} | "
            f"{w:.0f} | {r.log_duration / w:.0f}x |"
        )
    print(
        f"| first half mapped, second continues it (--continue) | "
        f"{score(*joined.every_scan, rel)} | {score(*joined.every_scan, half2)} | | "
        f"{c_wall:.0f} | {half_s / c_wall:.0f}x |"
    )
    loc = rep["first_localization"] or {}
    print(
        f"\nlocalization: localized at t = {rep['localized_at']} s ({loc.get('how')}, "
        f"{loc.get('answers_found')} answers); lost {len(rep['lost'])} times; "
        f"{rep['scans_localized']} of {rep['scans']} scans localized, "
        f"{rep['scans_matched']} matched"
    )
    n0 = cont.keyframes
    acc = [c for c in joined.loop_closures if c["accepted"]]
    print(
        f"continued: anchored {anchor.t - anchor.log_start:.1f} s into the second half "
        f"({anchor.how}); {n0} saved + {len(joined.times) - n0} new keyframes; "
        f"{sum(c['from'] < n0 for c in acc)} of its {len(acc)} loop closures to saved "
        "keyframes"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--part", choices=["corridor", "freiburg", "all"], default="all")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument(
        "--workers",
        type=int,
        default=1,
        help="Dask workers for the corridor's seeds (1: the real-time column undisturbed)",
    )
    args = ap.parse_args()
    if args.part in ("freiburg", "all"):
        freiburg()
        print()
    if args.part in ("corridor", "all"):
        corridor(args.seeds, args.workers)


if __name__ == "__main__":
    main()
