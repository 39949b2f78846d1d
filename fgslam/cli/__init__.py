"""The ``fgslam`` command line. Each subcommand has its own ``--help``.

Bad input is reported as one line on stderr with exit status 2; no traceback reaches the user
for a problem with their files or options.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import warnings
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path

from fgslam import __version__
from fgslam.choices import (
    CALIBRATION_CHOICES,
    LASER_CALIBRATION_CHOICES,
    SCANMATCH_CHOICES,
    SONAR_CALIBRATION_CHOICES,
    SONAR_TIMING_CHOICES,
)
from fgslam.errors import OutputWarning, RunWarning, UserError

EPILOG = """\
Typical use:
  fgslam config                         show the default robot configuration (TOML)
  fgslam config --config my_robot.toml  validate your robot file and show the merged result
  fgslam simulate --seed 1 --out run.log.gz     the paper's lab-and-corridor run, simulated
  fgslam plot-log run.log.gz --out run.png      look at it
  fgslam run run.log.gz --backend isam2 --out out/   SLAM on a log (native, CARMEN, ROS bag)
  fgslam compare run.log.gz --out cmp/          EKF, iSAM2, batch x fused, laser, sonar
  fgslam demo                                   simulate the built-in run and compare
  fgslam evaluate out/trajectory.tum --reference ref.tum   ATE, RPE, NEES
  fgslam export-reference run.log.gz --out ref.tum   truth/reference poses as TUM (for evo)
  fgslam emulate --speed 4 --link-dir /tmp/robot   emulated devices on pseudo-terminals
  fgslam online --laser PORT --sonar PORT --sonar PORT --odom PORT --out DIR   live SLAM

Frames follow REP-103 (x forward, y left, yaw counter-clockwise); units are SI.
"""

WORLD_HELP = "built-in world (corridor, corridor-oneway) or a world JSON file (default corridor)"
CONFIG_OVER_LOG_HELP = (
    "TOML file whose keys override the log's robot configuration (or the built-in one for "
    "logs that carry none), key by key; it must not contradict the log (beam count, sonar "
    "arrays)"
)

# What each command writes with --out (a file or a folder), checked before any work starts,
# and the options naming its inputs (an input is never an output).
OUTPUT_KINDS = {
    "run": "dir",
    "compare": "dir",
    "demo": "dir",
    "online": "dir",
    "simulate": "file",
    "convert": "file",
    "replay": "file",
    "plot-log": "file",
    "evaluate": "file",
    "export-reference": "file",
    "calibrate": "file",
}
INPUT_OPTIONS = (
    "log",
    "config",
    "world",
    "trajectory",
    "reference",
    "covariances",
    "map",
    "relations",
    "odometry_log",
)


def _cmd_config(args: argparse.Namespace) -> int:
    import tomli_w

    from fgslam.config import load_config

    cfg = load_config(args.config)
    data = cfg.to_dict()
    if args.json:
        print(json.dumps(data, indent=2))
    else:
        print(f"# robot configuration from {cfg.source}")
        print(tomli_w.dumps(data), end="")
    return 0


def _progress_bar(desc: str, unit: str = "s"):
    """A tqdm bar driven by (value, total) calls; silent when stderr is not a terminal."""
    from tqdm import tqdm

    state: dict = {}

    def update(value: float, total: float) -> None:
        bar = state.get("bar")
        if bar is None:
            bar = state["bar"] = tqdm(
                total=round(total, 1), desc=desc, unit=unit, disable=None, leave=False
            )
        step = round(value, 1) - bar.n
        if step >= 1.0 or value >= total:
            bar.update(step)

    def close() -> None:
        if "bar" in state:
            state["bar"].close()

    update.close = close  # type: ignore[attr-defined]
    return update


def _cmd_simulate(args: argparse.Namespace) -> int:
    import time

    from fgslam.config import load_config
    from fgslam.sim import simulate_to_log
    from fgslam.sim.world import load_world

    cfg = load_config(args.config)
    world = load_world(args.world)
    if args.duration is not None and args.duration <= 0:
        raise UserError(f"--duration must be positive, got {args.duration}")
    t0 = time.perf_counter()
    bar = _progress_bar("simulating")
    try:
        run = simulate_to_log(world, cfg, args.out, args.seed, args.duration, progress=bar)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    print(
        f"wrote {args.out}: world '{world.name}', seed {args.seed}, {run.duration:.1f} s "
        f"simulated, {run.distance:.1f} m travelled, in {wall:.1f} s "
        f"({run.duration / wall:.0f}x real time)"
    )
    return 0


def _cmd_plot_log(args: argparse.Namespace) -> int:
    from fgslam.plotting import plot_log
    from fgslam.sim.world import load_world

    world = load_world(args.world) if args.world else None
    info = plot_log(args.log, args.out, world, args.scan_time, _reader_options(args))
    extra = ""
    if "odometry_final_error_m" in info:
        extra = f"; odometry-only final position error {info['odometry_final_error_m']:.2f} m"
    print(
        f"wrote {args.out}: {info['scans']} laser scans, {info['sonar_readings']} sonar cycles"
        f"{extra}"
    )
    return 0


def _image_path(out: str, log: str) -> str:
    """The file ``plot-log --out`` writes: OUT/<log name>.png for a folder, OUT.png without a
    known image suffix; an unknown image format is refused."""
    from matplotlib.backend_bases import FigureCanvasBase

    from fgslam.safeio import is_special

    p = Path(out)
    if is_special(p):
        return out  # /dev/null: written as PNG in place
    if p.is_dir() or out.endswith(("/", os.sep)):
        name = Path(log).name.split(".")[0] or "log"
        return str(p / f"{name}.png")
    suffix = p.suffix.lower().lstrip(".")
    if not suffix:
        return f"{out}.png"
    if suffix not in FigureCanvasBase.get_supported_filetypes():
        known = ", ".join(sorted(FigureCanvasBase.get_supported_filetypes()))
        raise UserError(f"--out {out}: unknown image format '.{suffix}' (known: {known})")
    return out


def _log_duration(path: str) -> float | None:
    from fgslam.logfile import LogReader

    with LogReader(path) as r:
        d = r.meta.get("duration")
    return float(d) if isinstance(d, int | float) else None


def _cmd_run(args: argparse.Namespace) -> int:
    from fgslam.config import with_options
    from fgslam.readers import open_log
    from fgslam.slam.outputs import write_outputs
    from fgslam.slam.runner import run_slam

    reader = open_log(args.log, **_reader_options(args))
    cfg = with_options(_run_config(reader, args.config, args.log), _config_options(args))
    d = reader.meta.get("duration")
    total = float(d) if isinstance(d, int | float) else None
    bar = _progress_bar(f"{args.backend}/{args.sensors}")
    t_first: list[float] = []

    def progress(t: float) -> None:
        if not t_first:
            t_first.append(t)
        if total:
            bar(min(t - t_first[0], total), total)

    tap = _Tap(reader)
    try:
        res = run_slam(tap, cfg, args.backend, args.sensors, progress, association=args.association)
    finally:
        bar.close()
    extra, notes = _input_notes(reader, tap, [res])
    extra["config_source"] = cfg.source
    from fgslam.dense import write_dense_trajectory

    def dense(path: Path) -> int:
        return write_dense_trajectory(
            path, *res.every_scan, res.odometry_samples, cfg.odometry.wheelbase
        )

    rep = write_outputs(
        res,
        args.out,
        reader.meta.get("true_map"),
        extra=extra,
        world=_log_world(reader),
        scans=tap.sample.scans,
        cfg=cfg,
        more={"trajectory_dense.tum": dense},
    )
    for line in notes:
        print(line)
    _print_summary(rep, args.out)
    return _report_partial(rep, args.out)


class _Tap:
    """Passes a reader's events on, counting them and keeping a thinned sample of the laser
    scans for map.png."""

    def __init__(self, reader) -> None:
        from fgslam.slam.outputs import ScanSample

        self.reader = reader
        self.events = 0
        self.by_type: Counter = Counter()
        self.sample = ScanSample()

    def __iter__(self):
        add = self.sample.add
        count = self.by_type
        for ev in self.reader:
            self.events += 1
            count[type(ev).__name__] += 1
            add(ev)
            yield ev


def _run_config(reader, config: str | None, log: str):
    """The log's configuration (or the built-in one for logs without) with the keys of
    ``--config`` overriding it; refused where it contradicts the log."""
    from fgslam.config import check_against_log, override_config

    cfg = override_config(reader.config, config)
    check_against_log(cfg, reader.config, str(log))
    return cfg


def _log_world(reader):
    """The simulator's world of a native log whose world is built in, else None."""
    from fgslam.sim.world import BUILTIN_WORLDS, load_world

    name = getattr(reader, "world", None)
    return load_world(name) if name in BUILTIN_WORLDS else None


WARN_FRACTION = 0.01  # records not used (skipped, dropped) beyond this fraction: a warning
_STREAM_TYPES = {
    "odometry": "OdometryEvent",
    "laser": "LaserScan",
    "sonar": "SonarReading",
    "truth": "TruthPose",
}


def _input_notes(reader, tap: _Tap, results: list) -> tuple[dict, list[str]]:
    """What happened to the input's records (report.json keys, console lines): read, skipped
    as bad, stamped earlier than the record before them, put back in order or dropped as too
    late by the pipeline; a warning when more than WARN_FRACTION of them were not used. Where
    the comparison trajectory is a reference rather than ground truth, that too."""
    problems = getattr(reader, "problems", None)
    if problems is not None and not isinstance(problems, list):
        summary = problems.summary()
    elif hasattr(reader, "summary"):
        summary = reader.summary()
    else:
        summary = {}
    stats = results[0].stats if results else {}
    dropped = int(stats.get("events_out_of_order", 0))
    reordered = int(stats.get("events_reordered", 0))
    by_reason = dict(summary.get("skipped_by_reason", {}))
    # records of types a foreign reader does not use (CARMEN NEFF, ...) are not data lost
    foreign = problems is not None and not isinstance(problems, list)
    ignored = {k: n for k, n in by_reason.items() if foreign and k.startswith("unknown record")}
    skipped = int(summary.get("skipped", 0)) - sum(ignored.values())
    back = summary.get("timestamps_backwards", {})
    total = tap.events + skipped
    info = {
        "records": total,
        "events_read": tap.events,
        "skipped": skipped,
        "skipped_by_reason": {k: n for k, n in by_reason.items() if k not in ignored},
        "ignored_record_types": ignored,
        "timestamps_backwards": back,
        "events_put_back_in_order": reordered,
        "events_dropped_out_of_order": dropped,
    }
    if summary.get("problems"):
        info["problems"] = summary["problems"]
    notes = []
    if skipped:
        notes.append(f"skipped {skipped} bad records: {info['skipped_by_reason']}")
    if ignored:
        notes.append(f"ignored records of types not used: {ignored}")
    if back or dropped or reordered:
        by = ", ".join(f"{n} {k}" for k, n in sorted(back.items())) or "none"
        notes.append(
            f"timestamps going backwards: {by}; the pipeline put {reordered} events back in "
            f"order and dropped {dropped} (more than its reorder window late)"
        )
    lost = skipped + dropped
    if total and lost > WARN_FRACTION * total:
        msg = (
            f"{lost} of {total} records ({100 * lost / total:.1f} %) were not used "
            f"({skipped} bad, {dropped} out of time order): the results cover only part "
            "of the log"
        )
        info["warning"] = msg
        notes.append(f"WARNING: {msg}")
    elif not foreign:  # a few lost records of one kind (odometry) can matter more than
        # their number says; foreign readers carry or drop such records themselves and say so
        for stream, n in sorted(back.items()):
            of = tap.by_type.get(_STREAM_TYPES.get(stream, ""), 0)
            if of and n > WARN_FRACTION * of:
                msg = (
                    f"{n} of {of} {stream} records ({100 * n / of:.1f} %) are stamped earlier "
                    "than the one before them: the results may be wrong"
                )
                info["warning"] = msg
                notes.append(f"WARNING: {msg}")
                break
    extra: dict = {"input": info}
    kind = getattr(reader, "reference_kind", None)
    if kind:
        extra["truth_source"] = kind
        if kind == "reference":
            notes.append("note: ATE is against the log's reference trajectory, not ground truth")
    if problems is not None and not isinstance(problems, list):
        extra["reader"] = summary  # a foreign reader's own account
        notes += [f"warning: {w}" for w in summary.get("warnings", [])]
    elif "timestamps" in summary or "plausibility" in summary:  # a native log's checks
        keys = ("timestamps", "plausibility", "warnings")  # (docs/readers.md)
        extra["reader"] = {k: summary[k] for k in keys if k in summary}
        notes += [f"warning: {w}" for w in _reader_warnings(summary)]
    return extra, notes


def _reader_warnings(summary: dict) -> list[str]:
    """A reader's one-line warnings (``summary["warnings"]`` of the foreign readers; for a
    native log read in record order for want of a usable clock, that)."""
    if "warnings" in summary:
        return list(summary["warnings"])
    from fgslam.readers.common import clock_warnings

    return clock_warnings(summary.get("timestamps"))


def _report_partial(rep: dict, out: str) -> int:
    """Exit status of a run: 1 when its backend failed mid-run (outputs written up to the
    last good keyframe) or an output could not be written (``output_errors``; each was
    warned about), with a message saying so; 0 otherwise."""
    failed = [e["output"] for e in rep.get("output_errors", [])]
    if failed:
        print(
            f"fgslam: error: not written: {', '.join(failed)} (the other outputs in {out} are)",
            file=sys.stderr,
        )
    part = rep.get("partial")
    if not part:
        return 1 if failed else 0
    t = part.get("t")
    when = f" (t = {t:.2f} s)" if isinstance(t, int | float) else ""
    print(
        f"fgslam: error: {rep['backend']} failed at keyframe {part.get('keyframe')}{when}: "
        f"{part.get('error')}; the outputs in {out} hold the run up to the last good "
        "keyframe (report.json: partial)",
        file=sys.stderr,
    )
    return 1


def _reader_options(args: argparse.Namespace) -> dict:
    """Options of the foreign-log readers (fgslam.readers.open_log) from the command line."""
    opts: dict = {
        "tolerant": getattr(args, "tolerant", False),
        "strict": getattr(args, "strict", False),
        "format": args.format,
    }
    for key in ("scan_topic", "odom_topic", "range_topics", "carmen_mode", "timestamps"):
        value = getattr(args, key, None)
        if value:
            opts["mode" if key == "carmen_mode" else key] = value
    return opts


def _print_summary(rep: dict, out: str) -> None:
    """The run in a few lines: poses, landmarks, time, ATE (or why there is none)."""
    lm = rep.get("landmarks", {})
    msg = f"{rep['backend']}/{rep['sensors']}: {rep['poses']} poses"
    if "landmarks_total" in rep:
        msg += (
            f", {rep['landmarks_total']} landmarks "
            f"({', '.join(f'{v} {k}s' for k, v in lm.items())}), "
            f"{rep['wall_time_s']:.1f} s for {rep['log_duration_s']:.1f} s of log"
        )
    if "ate" in rep:
        odo = rep.get("ate_odometry")
        alone = f", odometry alone {odo['rmse']:.3f} m" if odo else ""
        msg += f"; ATE RMSE {rep['ate']['rmse']:.3f} m (max {rep['ate']['max']:.3f} m{alone})"
    print(msg)
    for name, why in rep.get("not_evaluated", {}).items():
        print(f"note: {name} not evaluated: {why}")
    cal = rep.get("calibration")
    if cal:  # relative errors in 1e-3, the laser offset in mm
        sig = cal.get("sigma") or [None] * len(cal["parameters"])
        cells = [
            f"{n} {1e3 * v:+.2f}" + ("" if s is None else f" +- {1e3 * s:.2f}")
            for n, v, s in zip(cal["parameters"], cal["estimate"], sig, strict=True)
        ]
        print(f"calibration (1e-3; laser_offset in mm): {', '.join(cells)}")
    failed = {e["output"] for e in rep.get("output_errors", [])}
    names = ["trajectory.tum", "map.json", "report.json", "map.png"]
    print(f"wrote {out}/{', '.join(n for n in names if n not in failed)}")


def _cmd_compare(args: argparse.Namespace) -> int:
    rows = _compare(
        args.log,
        args.out,
        args.config,
        _reader_options(args),
        args.association,
        _config_options(args),
    )
    names = ("comparison.json", "comparison.md", "comparison.png")
    written = [n for n in names if (Path(args.out) / n).exists()]  # a failed one is removed
    if "comparison.md" in written:
        print((Path(args.out) / "comparison.md").read_text(), end="")
    print(f"wrote {args.out}/{', '.join(written)} and one folder per run")
    failed = [n for n in names if n not in written] + [
        f"{r['backend']}-{r['sensors']}/{e['output']}"
        for r in rows
        for e in r.get("output_errors", [])
    ]
    if failed:
        print(f"fgslam compare: error: not written: {', '.join(failed)}", file=sys.stderr)
    partial = [f"{r['backend']}/{r['sensors']}" for r in rows if r.get("partial")]
    if partial:
        print(
            f"fgslam compare: error: {', '.join(partial)} failed mid-run: their outputs hold "
            "the run up to the last good keyframe (report.json: partial)",
            file=sys.stderr,
        )
    return 0 if rows and not failed and not partial else 1


def _compare(
    log: str,
    out: str,
    config: str | None,
    options: dict | None = None,
    association: str = "jcbb",
    sections: dict | None = None,
) -> list:
    from tqdm import tqdm

    from fgslam.slam.compare import compare
    from fgslam.slam.runner import BACKENDS, SENSORS

    with tqdm(
        total=len(BACKENDS) * len(SENSORS),
        desc="backends x sensors",
        unit="run",
        disable=None,
        leave=False,
    ) as bar:
        return compare(
            log,
            out,
            config,
            on_done=lambda _res: bar.update(1),
            options=options,
            association=association,
            sections=sections,
        )


def _cmd_demo(args: argparse.Namespace) -> int:
    import time

    from fgslam.config import load_config
    from fgslam.sim import simulate_to_log
    from fgslam.sim.world import load_world

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "corridor.log.gz"
    t0 = time.perf_counter()
    bar = _progress_bar("simulating")
    try:
        run = simulate_to_log(load_world("corridor"), load_config(), log, args.seed, progress=bar)
    finally:
        bar.close()
    print(f"simulated the corridor run: {run.duration:.0f} s, {run.distance:.0f} m -> {log}")
    # the paper's experiment in the paper's scheme (wheel odometry, every scan a keyframe);
    # `fgslam compare` on the log runs the scan-matching defaults
    paper = {"odometry": "wheels", "keyframes": "every-scan", "loop_closures": "off"}
    _compare(str(log), str(out), None, sections={"scanmatch": paper})
    print((out / "comparison.md").read_text(), end="")
    print(
        f"demo done in {time.perf_counter() - t0:.0f} s: see {out}/comparison.png and "
        f"{out}/<backend>-<sensors>/map.png"
    )
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from fgslam.config import load_config, override_config
    from fgslam.ports import replay_to_log, session_config

    cfg = None
    if args.config:  # key by key over the recorded configuration (or the built-in one)
        cfg = override_config(session_config(args.raw_dir) or load_config(), args.config)
    with tqdm(desc="replaying", unit=" events", disable=None, leave=False) as bar:
        try:
            res = replay_to_log(args.raw_dir, args.out, cfg, progress=lambda _t: bar.update())
        except OSError as exc:
            raise UserError(f"cannot write {args.out}: {exc.strerror or exc}") from None
    kinds = ", ".join(f"{n} {k}" for k, n in sorted(res.by_kind.items())) or "no events"
    print(f"wrote {args.out}: {res.events} events ({kinds}) from {args.raw_dir}")
    for name, c in res.files.items():
        counts = ("crc_errors", "dropped_frames")
        notes = [f"{c[k]} {k.replace('_', ' ')}" for k in counts if c.get(k)]
        if c["truncated"]:
            notes.append("last record truncated")
        if c["skipped_bytes"]:
            notes.append(f"{c['skipped_bytes']} damaged bytes skipped")
        if notes:
            print(f"  {name}: {', '.join(notes)}")
    if res.rejected:
        print(f"  {res.rejected} measurements not usable (bad status, wrong beam count, faults)")
    return 0


def _cmd_emulate(args: argparse.Namespace) -> int:
    from fgslam.config import load_config
    from fgslam.online import StopSignal, emulate_main, emulation_faults

    cfg = load_config(args.config)
    faults = emulation_faults(
        cfg,
        noise=args.noise,
        drop=args.drop,
        flip=args.flip,
        disconnects=args.disconnect or [],
        seed=args.seed,
    )
    with StopSignal() as sig:
        return emulate_main(
            cfg,
            args.world,
            seed=args.seed,
            speed=args.speed,
            duration=args.duration,
            link_dir=args.link_dir,
            faults=faults,
            stop=sig.event,
        )


def _cmd_online(args: argparse.Namespace) -> int:
    from fgslam.config import load_config, with_options
    from fgslam.online import StopSignal, device_summary, online_main

    cfg = with_options(load_config(args.config), _config_options(args))
    with StopSignal("stopping: processing what has arrived, writing outputs") as sig:
        run, rep = online_main(
            cfg,
            laser=args.laser,
            sonar=args.sonar or [],
            odometry=args.odom,
            out=args.out,
            record=args.record,
            backend=args.backend,
            sensors=args.sensors,
            speed=args.speed,
            idle_timeout=args.idle_timeout,
            connect_timeout=args.connect_timeout,
            stop=sig.event,
            meta={"command": " ".join(sys.argv)},
        )
    print(f"stopped ({run.reason}); events: {dict(sorted(run.events.items()))}")
    print("devices: " + " | ".join(device_summary(n, s) for n, s in run.status.items()))
    if args.record:
        print(f"recorded every byte received into {args.record} (fgslam replay to decode)")
    _print_summary(rep, args.out)
    return 0


def _add_association_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--association",
        choices=["jcbb", "nn"],
        default="jcbb",
        help="data association: joint compatibility (JCBB) or nearest neighbour (default jcbb)",
    )
    _add_scanmatch_arguments(p)


def _add_scanmatch_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "scan matching (beyond the paper; the defaults come from the configuration's "
        "[scanmatch] section: both, motion, on)"
    )
    g.add_argument(
        "--odometry",
        choices=SCANMATCH_CHOICES["odometry"],
        help="what links consecutive keyframes: wheel odometry (the paper), laser scan "
        "matching, or both as two robust constraints",
    )
    g.add_argument(
        "--keyframes",
        choices=SCANMATCH_CHOICES["keyframes"],
        help="a keyframe after a set travel or turn (the scans between are carried by scan "
        "matching), or every scan (the paper)",
    )
    g.add_argument(
        "--loops",
        choices=SCANMATCH_CHOICES["loop_closures"],
        help="verified loop closures by scan matching (iSAM2 and batch; the EKF keeps no "
        "past poses to close a loop on)",
    )
    g.add_argument(
        "--calibration",
        choices=CALIBRATION_CHOICES,
        help="estimate the wheel calibration (relative errors of the wheel radii and the "
        "wheelbase; report.json: calibration) or take the configuration's as exact "
        "(default: the configuration's [odometry] calibration)",
    )
    g.add_argument(
        "--laser-calibration",
        choices=LASER_CALIBRATION_CHOICES,
        help="estimate the laser's range offset, or its offset and scale, with the map "
        "(report.json: calibration; the scale is seen only against the wheels', so 'range' "
        "needs wheels whose scale is known), instead of the paper's worst-case term in each "
        "line and corner covariance (default: the configuration's [laser] calibration)",
    )
    g.add_argument(
        "--sonar-calibration",
        choices=SONAR_CALIBRATION_CHOICES,
        help="estimate the relative error of the speed of sound the sonar assumes (air "
        "temperature; report.json: calibration) with the map, or take the nominal one "
        "(default: the configuration's [sonar] calibration)",
    )
    g.add_argument(
        "--sonar-timing",
        choices=SONAR_TIMING_CHOICES,
        help="iSAM2 and batch: attach each sonar point or plane measurement to the pose at "
        "its reading's own time (interpolated between keyframes) or move it by odometry "
        "into the laser scan's frame as the paper does (the EKF always does the latter; "
        "default: the configuration's [sonar] timing)",
    )


def _config_options(args: argparse.Namespace) -> dict[str, dict]:
    """The command line's overrides of the configuration, by section."""
    return {
        "scanmatch": {
            "odometry": getattr(args, "odometry", None),
            "keyframes": getattr(args, "keyframes", None),
            "loop_closures": getattr(args, "loops", None),
        },
        "odometry": {"calibration": getattr(args, "calibration", None)},
        "laser": {"calibration": getattr(args, "laser_calibration", None)},
        "sonar": {
            "timing": getattr(args, "sonar_timing", None),
            "calibration": getattr(args, "sonar_calibration", None),
        },
    }


def _add_reader_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("foreign logs (docs/readers.md)")
    g.add_argument(
        "--format",
        choices=["fgslam", "carmen", "ros"],
        help="input format (default: detected from the file)",
    )
    g.add_argument(
        "--carmen-mode",
        choices=["auto", "corrected", "raw"],
        help="CARMEN: corrected log (reference poses, odometry rebuilt) or raw (default auto)",
    )
    g.add_argument(
        "--timestamps",
        choices=["auto", "ipc", "logger", "index", "header", "bag", "log"],
        help="the clock to use (docs/readers.md); default auto: the sound one, else (CARMEN "
        "and fgslam logs) index with a warning, or an error naming the defect (bags, "
        "--strict). CARMEN: the stamp field ipc or logger; ROS: header stamps or bag (record "
        "times); fgslam logs: log (its stamps as they are); CARMEN and fgslam logs: index "
        "(record order, scans 0.2 s apart; odometry speeds not checked)",
    )
    g.add_argument(
        "--strict",
        action="store_true",
        help="refuse a log with implausible records (laser ranges out of range, scans with "
        "no valid beam, odometry faster than 3 m/s or 6 rad/s, absurd truth, stamps out of "
        "order: docs/readers.md, Plausibility) or without a usable clock; by default such "
        "records are counted and warned about (out-of-range beams read as no return, "
        "implausible odometry and truth skipped) and such a log is read in record order",
    )
    g.add_argument("--scan-topic", help="ROS: sensor_msgs/LaserScan topic (default: the only)")
    g.add_argument("--odom-topic", help="ROS: nav_msgs/Odometry topic (default: the only)")
    g.add_argument(
        "--range-topic",
        dest="range_topics",
        action="append",
        metavar="TOPIC",
        help="ROS: sensor_msgs/Range topic read as a sonar array (repeatable)",
    )


def _cmd_convert(args: argparse.Namespace) -> int:

    from fgslam.logfile import LogWriter
    from fgslam.readers import open_log

    reader = open_log(args.log, **_reader_options(args))
    counts: Counter = Counter()
    try:  # the log appears at --out only when complete (LogWriter writes a temporary file)
        with reader, LogWriter(args.out, reader.config, reader.world, meta=reader.meta) as w:
            for ev in reader:
                w.write(ev)
                counts[type(ev).__name__] += 1
    except OSError as exc:
        raise UserError(f"cannot write {args.out}: {exc.strerror or exc}") from None
    kinds = ", ".join(f"{n} {k}" for k, n in sorted(counts.items())) or "no events"
    print(f"wrote {args.out}: {kinds}")
    problems = getattr(reader, "problems", None)
    summary = reader.summary() if isinstance(problems, list) else problems.summary()
    if summary["skipped"]:
        print(f"skipped {summary['skipped']} bad records: {summary['skipped_by_reason']}")
    if summary["timestamps_backwards"]:
        print(f"timestamps going backwards (kept as they are): {summary['timestamps_backwards']}")
    for w in _reader_warnings(summary):
        print(f"warning: {w}")
    kind = getattr(reader, "reference_kind", None)
    if kind == "reference":
        print("truth records hold the log's reference poses (not ground truth)")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from fgslam.cli.evaluate import evaluate_command

    rep = evaluate_command(args)
    print(rep.pop("_text"))
    if args.out:
        from fgslam.safeio import write_json

        write_json(args.out, rep)
        print(f"wrote {args.out}")
    return 0


def _cmd_export_reference(args: argparse.Namespace) -> int:
    from fgslam.evaluation import write_tum
    from fgslam.events import TruthPose
    from fgslam.readers import open_log
    from fgslam.safeio import atomic_path

    reader = open_log(args.log, **_reader_options(args))
    t: list[float] = []
    poses: list[tuple[float, float, float]] = []
    backwards = 0
    for ev in reader:
        if isinstance(ev, TruthPose):
            if t and ev.t < t[-1]:
                backwards += 1
                continue
            t.append(ev.t)
            poses.append((ev.x, ev.y, ev.theta))
    if not t:
        raise UserError(f"{args.log}: the log has no truth or reference poses")
    kind = getattr(reader, "reference_kind", None) or "ground truth"
    with atomic_path(args.out) as tmp:
        write_tum(tmp, t, poses)
    print(f"wrote {args.out}: {len(t)} poses ({kind}) over {t[-1] - t[0]:.1f} s")
    if backwards:
        print(f"left out {backwards} poses stamped earlier than the one before them")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fgslam",
        description=(
            "Laser + advanced sonar SLAM (lines, right-angle corners, points) as a GTSAM "
            "factor graph (iSAM2 or batch), with the paper's EKF kept for comparison."
        ),
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"fgslam {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser(
        "config",
        help="show or validate a robot configuration",
        description=(
            "Print the effective robot configuration: the shipped default (the paper's "
            "SLAMbot) overridden by --config FILE. Any subset of keys may be overridden; an "
            "unknown key, a missing value or a wrong type is reported with file and key. "
            "Redirect the output to a file to start your own robot configuration."
        ),
    )
    p.add_argument("--config", metavar="ROBOT.toml", help="TOML file overriding the default")
    p.add_argument("--json", action="store_true", help="print JSON instead of TOML")
    p.set_defaults(func=_cmd_config)

    p = sub.add_parser(
        "simulate",
        help="simulate a run of the robot in a world and write a log",
        description=(
            "Simulate SLAMbot driving a world's route (the built-in 'corridor' is the paper's "
            "experiment: loops in a lab, out along a 60 m corridor to both ends and back) with "
            "odometry, the SICK PLS and two panning advanced sonar arrays, and write the native "
            "log (docs/log-format.md; '.gz' to compress) with ground truth. Deterministic for a "
            "given seed."
        ),
    )
    p.add_argument("--world", default="corridor", help=WORLD_HELP)
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--duration", type=float, help="stop after this many seconds (default: whole route)"
    )
    p.add_argument(
        "--config", metavar="ROBOT.toml", help="robot configuration overriding the default"
    )
    p.add_argument("--out", required=True, metavar="FILE.log", help="log file to write")
    p.set_defaults(func=_cmd_simulate)

    p = sub.add_parser(
        "plot-log",
        help="draw a log: world, true and odometry paths, a scan with sonar",
        description=(
            "Draw a log as a PNG: the world (when the log's world is built in, or --world), the "
            "true (or reference) path, the odometry-only path, and one laser scan with the "
            "sonar readings of the 6 s around it, placed with the true poses. Any log `run` "
            "reads."
        ),
    )
    p.add_argument("log", help="log: fgslam, CARMEN (.gz or not) or a ROS 1/2 bag")
    _add_reader_arguments(p)
    p.add_argument(
        "--out",
        required=True,
        metavar="FILE.png",
        help="image to write ('.png' added without a suffix; a folder: FOLDER/<log>.png)",
    )
    p.add_argument("--world", help="world JSON file, when the log's world is not built in")
    p.add_argument("--scan-time", type=float, help="time (s) of the scan to draw (default: middle)")
    p.set_defaults(func=_cmd_plot_log)

    p = sub.add_parser(
        "run",
        help="run SLAM on a log (EKF, iSAM2 or batch; fused, laser or sonar)",
        description=(
            "Run the front end (line, corner and point features, sonar-aided segmentation and "
            "fusion) and one SLAM backend over a log, and write trajectory.tum (TUM format), "
            "map.json, report.json (accuracy against the truth when the log has it, timing) "
            "and map.png into --out."
        ),
    )
    p.add_argument("log", help="log: fgslam, CARMEN (.gz or not) or a ROS 1/2 bag")
    _add_reader_arguments(p)
    p.add_argument(
        "--backend",
        choices=["ekf", "isam2", "batch"],
        default="isam2",
        help="the paper's EKF, incremental smoothing, or batch LM smoothing (default isam2)",
    )
    p.add_argument(
        "--sensors",
        choices=["fused", "laser", "sonar"],
        default="fused",
        help="laser and sonar fused (the paper), laser only, or sonar only (default fused)",
    )
    _add_association_argument(p)
    p.add_argument("--config", metavar="ROBOT.toml", help=CONFIG_OVER_LOG_HELP)
    p.add_argument(
        "--tolerant", action="store_true", help="skip malformed records instead of stopping"
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser(
        "convert",
        help="convert a CARMEN log or a ROS bag into the native log",
        description=(
            "Read a CARMEN log (FLASER/ROBOTLASER1/ODOM, gzipped or not) or a ROS 1/2 bag "
            "(LaserScan, Odometry, Range topics) and write the native log (docs/log-format.md; "
            "'.gz' to compress) with the robot configuration derived from the data: the "
            "laser's beams and field of view, odometry as ticks of a virtual differential "
            "drive (0.1 mm per tick), reference poses as truth records. See docs/readers.md."
        ),
    )
    p.add_argument("log", help="CARMEN log or ROS bag (or a native log, copied)")
    _add_reader_arguments(p)
    p.add_argument(
        "--tolerant", action="store_true", help="skip malformed records instead of stopping"
    )
    p.add_argument("--out", required=True, metavar="FILE.log", help="log file to write")
    p.set_defaults(func=_cmd_convert)

    p = sub.add_parser(
        "evaluate",
        help="trajectory (and map) error against a reference: ATE, RPE, NEES, map error",
        description=(
            "Compare a TUM trajectory (e.g. a run's trajectory.tum) with a reference: a TUM "
            "file, or a log with truth or reference poses (fgslam, CARMEN corrected). Poses "
            "are matched by time (the reference interpolated). Prints and writes ATE after "
            "SE(2) alignment (RMSE, mean, max), RPE over --rpe-delta metres of travel, NEES "
            "with --covariances, map error with --map against a simulator log's true map."
        ),
    )
    p.add_argument("trajectory", metavar="TRAJ", help="estimated trajectory (TUM) or run dir")
    p.add_argument("--reference", metavar="REF", help="TUM file or log")
    p.add_argument(
        "--relations",
        metavar="FILE",
        help="relations benchmark file (t1 t2 x y z roll pitch yaw per line): errors of the "
        "estimate's relative poses; a run dir's trajectory_dense.tum is used when present",
    )
    p.add_argument(
        "--odometry-log",
        metavar="LOG",
        help="with --relations: the CARMEN log the run read; relation ends are filled from "
        "the keyframes and the log's odometry records (the benchmark's method)",
    )
    p.add_argument("--rpe-delta", type=float, default=1.0, metavar="METRES", help="default 1")
    p.add_argument("--covariances", metavar="FILE", help="pose covariances (for the NEES)")
    p.add_argument("--map", metavar="MAP.json", help="estimated map (for the map error)")
    p.add_argument("--max-gap", type=float, metavar="S", help="ignore poses this far from REF")
    p.add_argument("--out", metavar="report.json", help="write the report as JSON")
    p.set_defaults(func=_cmd_evaluate)

    from fgslam.calibrate import add_parser as add_calibrate_parser

    add_calibrate_parser(sub)

    p = sub.add_parser(
        "compare",
        help="every backend and sensor mode on one log, compared",
        description=(
            "Run EKF, iSAM2 and batch smoothing in fused, laser-only and sonar-only modes on the "
            "same log (the front end runs once per mode), write each run's outputs into "
            "DIR/<backend>-<sensors>/, and comparison.json, comparison.md and comparison.png "
            "(trajectories and errors over time) into DIR. Any log `run` reads."
        ),
    )
    p.add_argument("log", help="log: fgslam, CARMEN (.gz or not) or a ROS 1/2 bag")
    _add_reader_arguments(p)
    p.add_argument("--config", metavar="ROBOT.toml", help=CONFIG_OVER_LOG_HELP)
    _add_association_argument(p)
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.set_defaults(func=_cmd_compare)

    p = sub.add_parser(
        "export-reference",
        help="write a log's truth or reference poses as a TUM trajectory (for evo)",
        description=(
            "Write the ground truth of a simulated log, or the reference poses of a corrected "
            "CARMEN log, as a TUM trajectory (timestamp x y z qx qy qz qw), e.g. for evo: "
            "`evo_ape tum ref.tum out/trajectory.tum`."
        ),
    )
    p.add_argument("log", help="log: fgslam, CARMEN (.gz or not) or a ROS 1/2 bag")
    _add_reader_arguments(p)
    p.add_argument(
        "--tolerant", action="store_true", help="skip malformed records instead of stopping"
    )
    p.add_argument("--out", required=True, metavar="FILE.tum", help="TUM file to write")
    p.set_defaults(func=_cmd_export_reference)

    p = sub.add_parser(
        "demo",
        help="simulate the paper's corridor run and compare all backends (a few minutes)",
        description=(
            "Simulate the built-in corridor run (the paper's experiment) and run `fgslam "
            "compare` on it in the paper's scheme (wheel odometry, every scan a keyframe: "
            "`--odometry wheels --keyframes every-scan --loops off`): EKF vs iSAM2 vs batch, "
            "fused vs laser-only vs sonar-only."
        ),
    )
    p.add_argument(
        "--out",
        default="fgslam-demo",
        metavar="DIR",
        help="output directory (default ./fgslam-demo)",
    )
    p.add_argument("--seed", type=int, default=0, help="simulation seed (default 0)")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser(
        "replay",
        help="decode a raw device recording into a log",
        description=(
            "Decode a raw recording (every byte the laser, sonar and odometry drivers received, "
            "timestamped: RAW_DIR/*.raw, as written by an online run with --record) through the "
            "drivers' own decoders into the native log (docs/log-format.md; '.gz' to "
            "compress). The same recording always gives the same log. Formats: "
            "docs/devices.md."
        ),
    )
    p.add_argument("raw_dir", metavar="RAW_DIR", help="directory of a raw recording")
    p.add_argument("--out", required=True, metavar="FILE.log", help="log file to write")
    p.add_argument(
        "--config", metavar="ROBOT.toml", help="robot configuration (default: the recorded one)"
    )
    p.set_defaults(func=_cmd_replay)

    speed_help = (
        "log time runs K times faster than wall time (default 1). It must be the same for "
        "`fgslam emulate` and `fgslam online`: the host stamps every frame with its own "
        "clock scaled by K, so with another K the odometry, sonar and laser times would not "
        "match the emulated run (wrong speeds, sonar windows and device-clock mapping)"
    )
    p = sub.add_parser(
        "emulate",
        help="emulate the robot's devices on pseudo-terminals, fed by a simulated run",
        description=(
            "Start emulators of the SICK PLS, the two advanced sonar arrays and the odometry "
            "board on pseudo-terminals, byte for byte in their protocols (docs/devices.md), "
            "print their ports and the `fgslam online` command to use, and play a simulated "
            "run of the world into them once a host streams from every port. Stops at the "
            "end of the run or on Ctrl-C. Faults (noise, dropped bytes, bit flips, cable "
            "pulls) can be injected."
        ),
    )
    p.add_argument("--world", default="corridor", help=WORLD_HELP)
    p.add_argument("--seed", type=int, default=0, help="random seed of the run (default 0)")
    p.add_argument("--speed", type=float, default=1.0, metavar="K", help=speed_help)
    p.add_argument(
        "--duration", type=float, metavar="S", help="stop after S s of the run (default: all)"
    )
    p.add_argument(
        "--link-dir",
        metavar="DIR",
        help="put the port links (laser, sonar0, sonar1, odometry) here (default: a temp dir)",
    )
    p.add_argument(
        "--config", metavar="ROBOT.toml", help="robot configuration overriding the default"
    )
    p.add_argument(
        "--noise",
        type=float,
        default=0.0,
        metavar="P",
        help="fault: probability of random bytes before a frame",
    )
    p.add_argument(
        "--drop",
        type=float,
        default=0.0,
        metavar="P",
        help="fault: probability of losing bytes of a frame",
    )
    p.add_argument(
        "--flip",
        type=float,
        default=0.0,
        metavar="P",
        help="fault: probability of a flipped bit in a frame",
    )
    p.add_argument(
        "--disconnect",
        action="append",
        metavar="DEVICE:AT:DOWN",
        help="fault: pull DEVICE's cable (laser, sonar0, sonar1, odometry) at AT s of the run "
        "for DOWN s; repeatable",
    )
    p.set_defaults(func=_cmd_emulate)

    p = sub.add_parser(
        "online",
        help="run SLAM online on the robot's devices (or emulators) over serial ports",
        description=(
            "Open the SICK PLS, the sonar arrays and the odometry board on their serial "
            "ports, run the front end and iSAM2 (or the EKF) incrementally as data arrives, "
            "with a live status line on stderr (pose, landmarks, keyframe latency, per-device "
            "disconnects, CRC errors, dropped frames). A device that disconnects is reopened "
            "while the others go on. On Ctrl-C, or when no data came for --idle-timeout s, "
            "write the outputs of `fgslam run` into --out. With --record every byte received "
            "is also recorded (`fgslam replay` decodes it into a log)."
        ),
        epilog=(
            "With emulated devices: run `fgslam emulate --speed 4` in one terminal and the "
            "command it prints in another."
        ),
    )
    p.add_argument("--laser", metavar="PORT", help="SICK PLS serial port")
    p.add_argument(
        "--sonar",
        action="append",
        metavar="PORT",
        help="sonar array port, once per array in the configuration's order",
    )
    p.add_argument("--odom", metavar="PORT", help="odometry board serial port")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--record", metavar="RAW_DIR", help="record every byte received here")
    p.add_argument(
        "--backend",
        choices=["isam2", "ekf"],
        default="isam2",
        help="incremental smoothing or the paper's EKF (default isam2)",
    )
    p.add_argument(
        "--sensors",
        choices=["fused", "laser", "sonar"],
        default="fused",
        help="laser and sonar fused, laser only, or sonar only (default fused)",
    )
    p.add_argument(
        "--config", metavar="ROBOT.toml", help="robot configuration overriding the default"
    )
    p.add_argument("--speed", type=float, default=1.0, metavar="K", help=speed_help)
    p.add_argument(
        "--idle-timeout",
        type=float,
        default=5.0,
        metavar="S",
        help="end of data: stop after S wall s without any data, once data flowed (default 5)",
    )
    p.add_argument(
        "--connect-timeout",
        type=float,
        default=30.0,
        metavar="S",
        help="give up if a device has not answered after S s (default 30)",
    )
    _add_scanmatch_arguments(p)
    p.set_defaults(func=_cmd_online)
    return parser


def _check_outputs(args: argparse.Namespace) -> None:
    """Refuse an --out that cannot be written or that is one of the inputs, before any work."""
    from fgslam.safeio import check_output_dir, check_output_file

    kind = OUTPUT_KINDS.get(args.command)
    out = getattr(args, "out", None)
    if kind is None or out is None:
        return
    log = getattr(args, "log", None)
    if log is not None and not Path(log).exists():
        return  # the command says so; no output folder is created for nothing
    inputs = [getattr(args, k, None) for k in INPUT_OPTIONS]
    inputs.append(getattr(args, "raw_dir", None))
    if args.command == "plot-log":
        args.out = out = _image_path(out, args.log)
    if kind == "dir":
        check_output_dir(out, inputs)
    else:
        check_output_file(out, inputs)


def main(argv: Sequence[str] | None = None) -> int:
    try:
        return _main(argv)
    except BrokenPipeError:
        # the reader of our output went away (`fgslam ... | head`): no traceback, and none
        # at exit either when Python flushes stdout
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141


def _one_line_warning(command: str, show: Callable) -> Callable:
    """``warnings.showwarning`` that prints an OutputWarning (an output not written) or a
    RunWarning (something odd the run survived) as one line, ``fgslam COMMAND: warning:
    ...``, and leaves other warnings to ``show``."""

    def showwarning(message, category, filename, lineno, file=None, line=None) -> None:
        if issubclass(category, (OutputWarning, RunWarning)):
            print(f"fgslam {command}: warning: {message}", file=sys.stderr)
        else:
            show(message, category, filename, lineno, file, line)

    return showwarning


def _one_line(text: str) -> str:
    """An error message as one line: characters that are not printable (line breaks and
    other separators a file's bytes can put into a key or a name) escaped."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] | None = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        sys.stdout.flush()
        return 0
    try:
        _check_outputs(args)
        with warnings.catch_warnings():
            warnings.simplefilter("always", OutputWarning)
            warnings.simplefilter("always", RunWarning)
            warnings.showwarning = _one_line_warning(args.command, warnings.showwarning)
            status = func(args)
        sys.stdout.flush()  # a closed pipe shows here, not at exit
        return status
    except UserError as exc:
        print(f"fgslam {args.command}: error: {_one_line(str(exc))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"fgslam {args.command}: interrupted", file=sys.stderr)
        return 130
