"""What several commands share: help texts, the options of the foreign-log readers and of
scan matching, the progress bar and the summary of a run."""

from __future__ import annotations

import argparse
import math

from fgslam.choices import (
    CALIBRATION_CHOICES,
    LASER_CALIBRATION_CHOICES,
    SCANMATCH_CHOICES,
    SONAR_CALIBRATION_CHOICES,
    SONAR_TIMING_CHOICES,
)

WORLD_HELP = "built-in world (corridor, corridor-oneway) or a world JSON file (default corridor)"
CONFIG_OVER_LOG_HELP = (
    "TOML file whose keys override the log's robot configuration (or the built-in one for "
    "logs that carry none), key by key; it must not contradict the log (beam count, sonar "
    "arrays)"
)
SPEED_HELP = (
    "log time runs K times faster than wall time (default 1). It must be the same for "
    "`fgslam emulate` and `fgslam online`: the host stamps every frame with its own "
    "clock scaled by K, so with another K the odometry, sonar and laser times would not "
    "match the emulated run (wrong speeds, sonar windows and device-clock mapping)"
)


def progress_bar(desc: str, unit: str = "s"):
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


def log_progress(reader, desc: str):
    """A progress callback for a run over ``reader``'s log: called with each event's time, it
    moves a :func:`progress_bar` by the log time since the first event, out of the log's
    duration (no bar when the reader does not know it); ``.close()`` it at the end."""
    d = reader.meta.get("duration")
    total = float(d) if isinstance(d, int | float) else None
    bar = progress_bar(desc)
    first: list[float] = []

    def progress(t: float) -> None:
        if not first:
            first.append(t)
        if total:
            bar(min(t - first[0], total), total)

    progress.close = bar.close  # type: ignore[attr-defined]
    return progress


def add_reader_arguments(p: argparse.ArgumentParser) -> None:
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


LOG_HELP = "log: fgslam, CARMEN (.gz or not) or a ROS 1/2 bag"


def add_log_arguments(
    p: argparse.ArgumentParser,
    out_metavar: str,
    out_help: str,
    *,
    log_help: str = LOG_HELP,
    config: bool = False,
    tolerant: bool = False,
) -> None:
    """The arguments of every command that reads a log, declared once: the positional LOG,
    the options of the foreign-log readers (:func:`add_reader_arguments`), ``--config``
    overriding the log's robot configuration where the command runs SLAM on it (``config``),
    ``--tolerant`` where it skips malformed records (``tolerant``) and the required
    ``--out``."""
    p.add_argument("log", help=log_help)
    add_reader_arguments(p)
    if config:
        p.add_argument("--config", metavar="ROBOT.toml", help=CONFIG_OVER_LOG_HELP)
    if tolerant:
        p.add_argument(
            "--tolerant", action="store_true", help="skip malformed records instead of stopping"
        )
    p.add_argument("--out", required=True, metavar=out_metavar, help=out_help)


def add_robot_config_argument(p: argparse.ArgumentParser) -> None:
    """``--config``: the robot configuration, where no log brings one."""
    p.add_argument(
        "--config", metavar="ROBOT.toml", help="robot configuration overriding the default"
    )


def add_simulation_arguments(p: argparse.ArgumentParser) -> None:
    """What a simulated run is made of (``simulate``, ``emulate``): the world, the seed, how
    much of the route, the robot configuration."""
    p.add_argument("--world", default="corridor", help=WORLD_HELP)
    p.add_argument("--seed", type=int, default=0, help="random seed of the run (default 0)")
    p.add_argument(
        "--duration",
        type=float,
        metavar="S",
        help="stop after S s of the run (default: the whole route)",
    )
    add_robot_config_argument(p)


def add_speed_argument(p: argparse.ArgumentParser) -> None:
    """``--speed`` of the emulated devices and of the host reading them (:data:`SPEED_HELP`)."""
    p.add_argument("--speed", type=float, default=1.0, metavar="K", help=SPEED_HELP)


def add_backend_arguments(
    p: argparse.ArgumentParser, backends: list[str], backend_help: str
) -> None:
    """``--backend`` (one of ``backends``, default isam2) and ``--sensors`` of a SLAM run."""
    p.add_argument("--backend", choices=backends, default="isam2", help=backend_help)
    p.add_argument(
        "--sensors",
        choices=["fused", "laser", "sonar"],
        default="fused",
        help="laser and sonar fused (the paper), laser only, or sonar only (default fused)",
    )


def reader_options(args: argparse.Namespace) -> dict:
    """Options of the foreign-log readers (fgslam.io.formats.open_log) from the command line."""
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


def reader_warnings(reader) -> list[str]:
    """A reader's one-line warnings, the same for every format (its clock, its input, one per
    kind of implausible record: ``reader.problems.warnings()``), for every command that reads
    a log to print as ``warning: ...``."""
    return reader.problems.warnings()


def add_association_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--association",
        choices=["jcbb", "nn"],
        default="jcbb",
        help="data association: joint compatibility (JCBB) or nearest neighbour (default jcbb)",
    )
    add_scanmatch_arguments(p)


def add_scanmatch_arguments(p: argparse.ArgumentParser) -> None:
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


def config_options(args: argparse.Namespace) -> dict[str, dict]:
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


def print_summary(rep: dict, out: str) -> None:
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


def parse_pose(text: str) -> tuple[float, float, float]:
    """An argparse type: ``X,Y,THETA`` (m, m, rad), finite."""
    try:
        x, y, th = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,THETA (m, m, rad), got {text!r}") from None
    if not all(math.isfinite(v) for v in (x, y, th)):
        raise argparse.ArgumentTypeError(f"not finite: {text!r}")
    return x, y, th
