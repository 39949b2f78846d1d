"""Run every backend and sensor mode on one log and compare them: per-run outputs,
comparison.json, comparison.md and comparison.png (trajectories and errors over time)."""

from __future__ import annotations

import math
import os
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from fgslam.config import RobotConfig, check_against_log, override_config, with_options
from fgslam.evaluation import metrics as evaluation
from fgslam.io import safeio
from fgslam.io.formats import open_log
from fgslam.slam.outputs import OutputGuard, ScanSample, write_outputs
from fgslam.slam.runner import BACKENDS, SENSORS, SlamResult, run_backends

NEES_FLAG = 3.0  # a NEES mean beyond this factor of its dof (or below 1/factor) is flagged


def _open(
    log: str,
    config: str | None,
    options: dict[str, Any] | None,
    sections: dict[str, dict[str, Any]] | None = None,
):
    reader = open_log(log, **(options or {}))
    cfg = override_config(reader.config, config)
    check_against_log(cfg, reader.config, str(log))
    return reader, with_options(cfg, sections)


def _run_mode(
    log: str,
    config: str | None,
    sensors: str,
    backends: list[str],
    options: dict[str, Any] | None,
    keep_scans: bool,
    association: str = "jcbb",
    sections: dict[str, dict[str, Any]] | None = None,
) -> tuple[list[SlamResult], dict[str, Any]]:
    """The backends in one sensor mode; also what the log holds (event counts, a sample of
    its scans for the maps when ``keep_scans``)."""
    reader, cfg = _open(log, config, options, sections)
    counts: Counter = Counter()
    sample = ScanSample()

    def events():
        for ev in reader:
            counts[type(ev).__name__] += 1
            if keep_scans:
                sample.add(ev)
            yield ev

    results = run_backends(events(), cfg, backends, sensors, association=association)
    summary = reader.problems.summary()
    return results, {"events": dict(counts), "scans": sample.scans, "reader": summary}


def compare(
    log: str | Path,
    out: str | Path,
    config: str | None = None,
    backends: tuple[str, ...] = BACKENDS,
    sensors: tuple[str, ...] = SENSORS,
    workers: int | None = None,
    on_done: Callable[[SlamResult], None] | None = None,
    options: dict[str, Any] | None = None,
    association: str = "jcbb",
    sections: dict[str, dict[str, Any]] | None = None,
) -> list[dict[str, Any]]:
    """Every backend in every sensor mode on ``log`` (any format :func:`open_log` reads, with
    reader ``options``; ``config`` overrides the log's configuration key by key); one process
    per sensor mode (the front end runs once per mode and feeds all backends);
    ``association`` "jcbb" or "nn" for every run; ``sections`` overrides keys of the
    configuration's sections (``{"scanmatch": {...}, "odometry": {...}}``, the command
    line's options). Returns the rows of the comparison."""
    from fgslam.sim import true_calibration
    from fgslam.sim.world import BUILTIN_WORLDS, load_world

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    reader, cfg = _open(str(log), config, options, sections)
    true_map = reader.meta.get("true_map")
    world = load_world(reader.world) if reader.world in BUILTIN_WORLDS else None
    truth_kind = reader.reference_kind or "ground truth"
    workers = workers or min(len(sensors), os.cpu_count() or 1)
    results: list[SlamResult] = []
    info: dict[str, Any] = {}
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futs = [
            pool.submit(
                _run_mode,
                str(log),
                config,
                s,
                list(backends),
                options,
                i == 0,
                association,
                sections,
            )
            for i, s in enumerate(sensors)
        ]
        for fut in futs:
            res_list, mode_info = fut.result()
            info = info or mode_info
            for res in res_list:
                results.append(res)
                if on_done:
                    on_done(res)
    rows = []
    for res in results:
        rep = write_outputs(
            res,
            out / f"{res.backend}-{res.sensors}",
            true_map,
            true_calibration=true_calibration(reader.meta),
            extra={"truth_source": truth_kind} if res.has_truth else None,
            world=world,
            scans=info.get("scans"),
            cfg=cfg,
        )
        rows.append(rep)
    # each on its own, as a run's outputs: one that fails is warned about, the others written
    guard = OutputGuard(out)
    guard.write("comparison.json", lambda p: safeio.write_json(p, rows))
    guard.write("comparison.png", lambda p: plot_comparison(results, p, world=world))

    def table(path: Path) -> None:
        header = describe_run(
            str(log), results, cfg, info.get("events", {}), truth_kind, info.get("reader")
        )
        failed = "".join(f"\nNot written: {e['output']} ({e['error']}).\n" for e in guard.errors)
        safeio.write_text(path, header + markdown_table(rows) + failed)

    guard.write("comparison.md", table)
    return rows


def _path_length(xy: np.ndarray) -> float:
    return float(np.sum(np.hypot(*np.diff(xy[:, :2], axis=0).T))) if len(xy) > 1 else 0.0


def describe_run(
    log: str,
    results: list[SlamResult],
    cfg: RobotConfig,
    events: dict[str, int],
    truth_kind: str = "ground truth",
    reader: dict[str, Any] | None = None,
) -> str:
    """The head of comparison.md: what was run on what (log, duration, path length, sensors
    and how much of each the log holds, records the reader skipped or found out of order and
    the pipeline dropped) and the legend of the table's columns."""
    res = results[0] if results else None
    duration = res.log_duration if res else 0.0
    if res is not None and res.has_truth:
        length, how = _path_length(res.truth), f"along the {truth_kind}"
    elif res is not None:
        length, how = _path_length(res.poses), "along the first estimate"
    else:
        length, how = 0.0, ""
    las = cfg.laser
    arrays = ", ".join(a.name for a in cfg.sonar.arrays) or "none"
    n = {k: events.get(k, 0) for k in ("LaserScan", "SonarReading", "OdometryEvent", "TruthPose")}
    runs = ", ".join(sorted({r.backend for r in results}))
    modes = ", ".join(sorted({r.sensors for r in results}))
    return (
        f"# fgslam compare: {Path(log).name}\n\n"
        f"Backends {runs} in sensor modes {modes} on `{log}` (robot '{cfg.robot.name}').\n\n"
        f"- log: {duration:.1f} s, {length:.1f} m travelled ({how})\n"
        f"- laser: {n['LaserScan']} scans of {las.n_beams} beams over {las.fov_deg:g} deg, "
        f"max range {las.max_range:g} m\n"
        f"- sonar: {n['SonarReading']} readings from {len(cfg.sonar.arrays)} arrays ({arrays})\n"
        f"- odometry: {n['OdometryEvent']} samples; {n['TruthPose']} poses of {truth_kind}\n"
        f"{_input_line(reader or {}, res)}"
        f"{_scanmatch_line(cfg, results)}\n"
        "Columns: ATE RMSE / max: position error of the keyframe poses against the truth after "
        "an SE(2) alignment (m); final error: position error of the last pose, unaligned (m); "
        "NEES mean: mean normalised estimation error squared of the poses, expected near its "
        "3 degrees of freedom (much larger: the covariances are overconfident; much smaller: "
        "pessimistic); NEES scale-aligned: the same once the map's absolute scale, which "
        "odometry and laser cannot observe, is taken out (the estimate scaled about its first "
        "pose onto the truth); lines / corners / points: landmarks in the map; real-time "
        "factor: log time over wall time; latency p95: 95th percentile of the time a "
        "keyframe takes (ms). "
        "'-': not available (no truth, or no pose covariances).\n\n"
    )


def _scanmatch_line(cfg: RobotConfig, results: list[SlamResult]) -> str:
    """'- keyframes: ...': the scan-matching scheme, and that the EKF closes no loops."""
    sm = cfg.scanmatch
    line = (
        f"- keyframes (laser modes; sonar only: every step, wheel odometry): {sm.keyframes}, "
        f"linked by {sm.odometry} odometry; loop closures {sm.loop_closures}; wheel "
        f"calibration {cfg.odometry.calibration}"
    )
    loops = {
        r.backend: sum(c["accepted"] for c in r.loop_closures) for r in results if r.loop_closures
    }
    if sm.loop_closures == "on":
        line += (
            " (graph backends only: the EKF keeps no past poses to close a loop on, so it "
            "cannot use them"
        )
        line += f"; accepted: {loops})" if loops else ")"
    return line + "\n"


def _input_line(reader: dict[str, Any], res: SlamResult | None) -> str:
    """'- records: ...' when the reader skipped records or found stamps going backwards, or
    the pipeline dropped events as too late; empty otherwise."""
    dropped = int(res.stats.get("events_out_of_order", 0)) if res is not None else 0
    parts = []
    if reader.get("skipped"):
        parts.append(f"{reader['skipped']} skipped ({reader.get('skipped_by_reason', {})})")
    back = reader.get("timestamps_backwards") or {}
    if back:
        parts.append(f"stamps going backwards: {back}")
    if dropped:
        parts.append(f"{dropped} events dropped as too late to put back in order")
    return f"- records: {'; '.join(parts)}\n" if parts else ""


def markdown_table(rows: list[dict[str, Any]]) -> str:
    head = (
        "| backend | sensors | ATE RMSE (m) | ATE max (m) | final error (m) | NEES mean (3) | "
        "NEES scale-aligned | lines | corners | points | real-time factor | latency p95 (ms) |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    flags = []
    for r in rows:
        ate = r.get("ate", {})
        lm = r.get("landmarks", {})
        nees_d = r.get("nees", {})
        nees = nees_d.get("mean")
        dof = nees_d.get("dof", 3)
        fin = r.get("final_pose_error", {}).get("position_m")

        def f(v, p=3):
            return "-" if v is None or not math.isfinite(v) else f"{v:.{p}f}"

        nees_s = f(nees, 1)
        aligned = r.get("nees_scale_aligned", {}).get("mean")
        if nees is not None and math.isfinite(nees):
            if nees > NEES_FLAG * dof:
                nees_s += " (!)"
                scale = (
                    f"; with the map's absolute scale taken out (unobservable to odometry and "
                    f"laser) {aligned:.1f}"
                    if aligned is not None and math.isfinite(aligned)
                    else ""
                )
                flags.append(
                    f"- {r['backend']}/{r['sensors']}: NEES {nees:.1f} is {nees / dof:.0f}x its "
                    f"{dof} dof: the covariances are overconfident (errors larger than "
                    f"claimed){scale}"
                )
            elif nees < dof / NEES_FLAG:
                nees_s += " (!)"
                flags.append(
                    f"- {r['backend']}/{r['sensors']}: NEES {nees:.2f} is far below its {dof} "
                    "dof: the covariances are pessimistic"
                )
        name = r["backend"] + (" (PARTIAL)" if r.get("partial") else "")
        lines.append(
            f"| {name} | {r['sensors']} | {f(ate.get('rmse'))} | {f(ate.get('max'))} | "
            f"{f(fin)} | {nees_s} | {f(aligned, 1)} | {lm.get('line', 0)} | "
            f"{lm.get('corner', 0)} | "
            f"{lm.get('point', 0)} | {f(r.get('realtime_factor'), 1)} | "
            f"{f(r.get('keyframe_latency_ms', {}).get('p95'), 1)} |"
        )
    odo = next((r["ate_odometry"] for r in rows if "ate_odometry" in r), None)
    tail = (
        f"\nOdometry alone: ATE RMSE {odo['rmse']:.3f} m, max {odo['max']:.3f} m.\n" if odo else ""
    )
    if flags:
        tail += "\n(!) NEES far from its degrees of freedom:\n\n" + "\n".join(flags) + "\n"
    tail += calibration_table(rows)
    for r in rows:
        part = r.get("partial")
        if part:
            tail += (
                f"\n{r['backend']}/{r['sensors']} is PARTIAL: the backend failed at keyframe "
                f"{part.get('keyframe')} (t = {part.get('t')}): {part.get('error')}\n"
            )
        for e in r.get("output_errors", []):
            tail += f"\n{r['backend']}/{r['sensors']}: {e['output']} not written: {e['error']}\n"
    return head + "\n".join(lines) + "\n" + tail


def calibration_table(rows: list[dict[str, Any]]) -> str:
    """The runs' calibration estimates as a markdown table, in units of 1e-3 (relative errors;
    the laser's range offset in mm): estimate +- sigma and, where the truth is known (a
    simulated log), (estimate - truth) / sigma; a last row with the truth. Empty when no run
    estimated a calibration."""
    cal = [r for r in rows if r.get("calibration")]
    if not cal:
        return ""
    names: list[str] = []
    for r in cal:
        names += [n for n in r["calibration"]["parameters"] if n not in names]
    out = (
        "\nCalibration estimated (1e-3; laser offset in mm): estimate +- sigma "
        "(error / sigma against the truth)\n\n"
        f"| backend | sensors | {' | '.join(names)} |\n|---|---|{'---|' * len(names)}\n"
    )
    truth: dict[str, float] = {}
    for r in cal:
        c = r["calibration"]
        cells = dict.fromkeys(names, "-")
        sig = c.get("sigma") or [None] * len(c["parameters"])
        z = c.get("error_sigmas") or [None] * len(c["parameters"])
        for n, e, s_, z_, t in zip(
            c["parameters"], c["estimate"], sig, z, c.get("truth") or [None] * len(sig),
            strict=True,
        ):  # fmt: skip
            cell = f"{1e3 * e:.2f}" + (f" +- {1e3 * s_:.2f}" if s_ is not None else "")
            cells[n] = cell + (f" ({z_:+.1f})" if z_ is not None else "")
            if t is not None:
                truth[n] = t
        out += f"| {r['backend']} | {r['sensors']} | {' | '.join(cells.values())} |\n"
    if truth:
        row = " | ".join(f"{1e3 * truth[n]:.2f}" if n in truth else "-" for n in names)
        out += f"| truth | | {row} |\n"
    return out


def _errors_over_time(res: SlamResult, track: str) -> tuple[np.ndarray, np.ndarray]:
    """Times (s) and unaligned position errors (m; NaN where a pose is not finite) of one of
    the run's tracks (:meth:`SlamResult.tracks`) against its reference, over its poses within
    the reference's time span."""
    t, poses = res.tracks()[track]
    mask, ref = evaluation.match_times(t, res.truth_t, res.truth)
    p = np.asarray(poses, dtype=float)[mask]
    with np.errstate(over="ignore", invalid="ignore"):
        err = np.hypot(p[:, 0] - ref[:, 0], p[:, 1] - ref[:, 1])
    return np.asarray(t)[mask], np.where(np.isfinite(err), err, np.nan)


def plot_comparison(results: list[SlamResult], path: Path, world: Any = None) -> dict[str, Any]:
    """Trajectories on equal axes in a panel of the path's aspect ratio (with the world
    outline of a simulated log), and position errors against the truth over time on a linear
    axis clipped to the backends' errors (odometry alone may leave it: its error is in the
    table). Returns the axes' limits and scales."""
    xy = [r.poses[:, :2] for r in results if len(r.poses)]
    xy += [r.truth[:, :2] for r in results[:1] if r.has_truth]
    allxy = np.concatenate(xy) if xy else np.zeros((1, 2))
    allxy = allxy[np.isfinite(allxy).all(axis=1)]  # a diverged pose must not set the axes
    if not len(allxy):
        allxy = np.zeros((1, 2))
    lo, hi = allxy.min(axis=0), allxy.max(axis=0)
    pad = max(1.0, 0.06 * float(np.max(hi - lo)))
    lo, hi = lo - pad, hi + pad
    # no thinner than 1:4, so that a straight drive is not a hair-line strip
    short = int(np.argmin(hi - lo))
    grow = max(0.0, float(np.max(hi - lo)) / 4.0 - (hi[short] - lo[short]))
    lo[short] -= grow / 2
    hi[short] += grow / 2
    w, h = hi - lo
    top_h = float(np.clip(13.0 * h / w, 3.0, 12.0))
    fig, (ax1, ax2) = plt.subplots(
        2, 1, figsize=(14, top_h + 4.0), gridspec_kw={"height_ratios": [top_h, 3.5]}
    )
    if world is not None:
        from fgslam.evaluation.plotting import draw_world

        draw_world(ax1, world)
    truth_drawn = False
    worst = 0.0
    for res in results:
        if res.has_truth and not truth_drawn:
            ax1.plot(res.truth[:, 0], res.truth[:, 1], "-", color="0.5", lw=2, label="truth")
            t, err = _errors_over_time(res, "odometry")
            ax2.plot(t, err, ":", color="0.3", label="odometry only")
            truth_drawn = True
        label = f"{res.backend} / {res.sensors}"
        ax1.plot(res.poses[:, 0], res.poses[:, 1], "-", lw=0.9, label=label)
        if res.has_truth:
            t, err = _errors_over_time(res, "estimate")
            err_ok = err[np.isfinite(err)]
            worst = max(worst, float(err_ok.max()) if len(err_ok) else 0.0)
            ax2.plot(t, err, "-", lw=0.9, label=label)
    ax1.set_xlim(lo[0], hi[0])
    ax1.set_ylim(lo[1], hi[1])
    ax1.set_aspect("equal")
    ax1.set_xlabel("x (m)")
    ax1.set_ylabel("y (m)")
    handles, labels = ax1.get_legend_handles_labels()
    uniq = dict(zip(labels, handles, strict=True))
    ax1.legend(uniq.values(), uniq.keys(), fontsize=7, ncol=3)
    ax1.set_title("trajectories")
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("position error (m)")
    if worst > 0:
        ax2.set_ylim(0.0, 1.15 * worst)
    if ax2.get_legend_handles_labels()[0]:  # no reference: no error curves
        ax2.legend(fontsize=7, ncol=4)
    ax2.set_title(
        "position error against the truth (map anchored at the first true pose; axis clipped "
        "to the backends' largest error)"
    )
    fig.tight_layout()
    with safeio.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return {
        "xlim": ax1.get_xlim(),
        "ylim": ax1.get_ylim(),
        "aspect": ax1.get_aspect(),
        "error_yscale": ax2.get_yscale(),
        "error_ylim": ax2.get_ylim(),
    }
