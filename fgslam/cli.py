"""The ``fgslam`` command line. Each subcommand has its own ``--help``.

Bad input is reported as one line on stderr with exit status 2; no traceback reaches the user
for a problem with their files or options.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from fgslam import __version__
from fgslam.errors import UserError

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
  fgslam emulate --speed 4 --link-dir /tmp/robot   emulated devices on pseudo-terminals
  fgslam online --laser PORT --sonar PORT --sonar PORT --odom PORT --out DIR   live SLAM

Frames follow REP-103 (x forward, y left, yaw counter-clockwise); units are SI.
"""


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
    from fgslam.logfile import LogReader
    from fgslam.plotting import plot_log
    from fgslam.sim.world import BUILTIN_WORLDS, load_world

    world = None
    if args.world:
        world = load_world(args.world)
    else:
        with LogReader(args.log) as reader:
            name = reader.world
        if name in BUILTIN_WORLDS:
            world = load_world(name)
    info = plot_log(args.log, args.out, world, args.scan_time)
    extra = ""
    if "odometry_final_error_m" in info:
        extra = f"; odometry-only final position error {info['odometry_final_error_m']:.2f} m"
    print(
        f"wrote {args.out}: {info['scans']} laser scans, {info['sonar_readings']} sonar cycles"
        f"{extra}"
    )
    return 0


def _log_duration(path: str) -> float | None:
    from fgslam.logfile import LogReader

    with LogReader(path) as r:
        d = r.meta.get("duration")
    return float(d) if isinstance(d, int | float) else None


def _cmd_run(args: argparse.Namespace) -> int:
    from fgslam.config import load_config
    from fgslam.readers import open_log
    from fgslam.slam.outputs import write_outputs
    from fgslam.slam.runner import run_slam

    reader = open_log(args.log, **_reader_options(args))
    cfg = load_config(args.config) if args.config else reader.config
    d = reader.meta.get("duration")
    total = float(d) if isinstance(d, int | float) else None
    bar = _progress_bar(f"{args.backend}/{args.sensors}")
    t_first: list[float] = []

    def progress(t: float) -> None:
        if not t_first:
            t_first.append(t)
        if total:
            bar(min(t - t_first[0], total), total)

    try:
        res = run_slam(
            reader, cfg, args.backend, args.sensors, progress, association=args.association
        )
    finally:
        bar.close()
    rep = write_outputs(res, args.out, reader.meta.get("true_map"))
    if reader.skipped:
        print(f"skipped {reader.skipped} bad records: {dict(reader.skipped_by_reason)}")
    _reader_notes(reader, rep, args.out)
    _print_summary(rep, args.out)
    return 0


def _reader_options(args: argparse.Namespace) -> dict:
    """Options of the foreign-log readers (fgslam.readers.open_log) from the command line."""
    opts: dict = {"tolerant": args.tolerant, "format": args.format}
    for key in ("scan_topic", "odom_topic", "range_topics", "carmen_mode"):
        value = getattr(args, key, None)
        if value:
            opts["mode" if key == "carmen_mode" else key] = value
    return opts


def _reader_notes(reader, rep: dict, out: str) -> None:
    """What a foreign-log reader found (records skipped, stamps going backwards), and where
    the comparison trajectory is a reference rather than ground truth, say so in the report."""
    problems = getattr(reader, "problems", None)
    if problems is not None and not isinstance(problems, list):
        back = dict(problems.backwards)
        if back:
            print(f"timestamps going backwards (kept in order, dropped or carried): {back}")
        rep["reader"] = problems.summary()
    kind = getattr(reader, "reference_kind", None)
    if kind:
        rep["truth_source"] = kind
        if kind == "reference":
            print("note: ATE is against the log's reference trajectory, not ground truth")
    if problems is not None or kind:
        (Path(out) / "report.json").write_text(json.dumps(rep, indent=2))


def _print_summary(rep: dict, out: str) -> None:
    lm = rep["landmarks"]
    msg = (
        f"{rep['backend']}/{rep['sensors']}: {rep['poses']} poses, "
        f"{rep['landmarks_total']} landmarks ({', '.join(f'{v} {k}s' for k, v in lm.items())}), "
        f"{rep['wall_time_s']:.1f} s for {rep['log_duration_s']:.1f} s of log"
    )
    if "ate" in rep:
        msg += (
            f"; ATE RMSE {rep['ate']['rmse']:.3f} m (max {rep['ate']['max']:.3f} m, "
            f"odometry alone {rep['ate_odometry']['rmse']:.3f} m)"
        )
    print(msg)
    print(f"wrote {out}/trajectory.tum, map.json, report.json, map.png")


def _cmd_compare(args: argparse.Namespace) -> int:
    from fgslam.slam.compare import compare

    rows = _compare(args.log, args.out, args.config, args.association)
    print((Path(args.out) / "comparison.md").read_text(), end="")
    print(f"wrote {args.out}/comparison.json, comparison.md, comparison.png and one folder per run")
    return 0 if rows and compare else 1


def _compare(log: str, out: str, config: str | None, association: str = "jcbb") -> list:
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
            log, out, config, on_done=lambda _res: bar.update(1), association=association
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
    _compare(str(log), str(out), None)
    print((out / "comparison.md").read_text(), end="")
    print(
        f"demo done in {time.perf_counter() - t0:.0f} s: see {out}/comparison.png and "
        f"{out}/<backend>-<sensors>/map.png"
    )
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from fgslam.config import load_config
    from fgslam.ports import replay_to_log

    cfg = load_config(args.config) if args.config else None
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
    from fgslam.config import load_config
    from fgslam.online import StopSignal, device_summary, online_main

    cfg = load_config(args.config)
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
    from collections import Counter

    from fgslam.logfile import LogWriter
    from fgslam.readers import open_log

    reader = open_log(args.log, **_reader_options(args))
    counts: Counter = Counter()
    try:
        with LogWriter(args.out, reader.config, reader.world, meta=reader.meta) as w:
            for ev in reader:
                w.write(ev)
                counts[type(ev).__name__] += 1
    except OSError as exc:
        raise UserError(f"cannot write {args.out}: {exc.strerror or exc}") from None
    kinds = ", ".join(f"{n} {k}" for k, n in sorted(counts.items())) or "no events"
    print(f"wrote {args.out}: {kinds}")
    problems = getattr(reader, "problems", None)
    if problems is not None and not isinstance(problems, list):
        if problems.skipped:
            print(f"skipped: {dict(problems.skipped_by_reason)}")
        if problems.backwards:
            print(f"timestamps going backwards: {dict(problems.backwards)}")
    elif reader.skipped:
        print(f"skipped {reader.skipped} bad records: {dict(reader.skipped_by_reason)}")
    kind = getattr(reader, "reference_kind", None)
    if kind == "reference":
        print("truth records hold the log's reference poses (not ground truth)")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from fgslam.evaluate_cli import evaluate_command

    rep = evaluate_command(args)
    print(rep.pop("_text"))
    if args.out:
        Path(args.out).write_text(json.dumps(rep, indent=2))
        print(f"wrote {args.out}")
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
    p.add_argument("--world", default="corridor", help="built-in world name or world JSON file")
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
            "true path, the odometry-only path, and one laser scan with the sonar readings of "
            "the 6 s around it, placed with the true poses."
        ),
    )
    p.add_argument("log", help="native log file (.log or .log.gz)")
    p.add_argument("--out", required=True, metavar="FILE.png", help="image to write")
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
    p.add_argument(
        "--association",
        choices=["jcbb", "nn"],
        default="jcbb",
        help="data association: joint compatibility (JCBB) or nearest neighbour (default jcbb)",
    )
    p.add_argument(
        "--config", metavar="ROBOT.toml", help="robot configuration (default: the log's)"
    )
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
    p.add_argument("--reference", required=True, metavar="REF", help="TUM file or log")
    p.add_argument("--rpe-delta", type=float, default=1.0, metavar="METRES", help="default 1")
    p.add_argument("--covariances", metavar="FILE", help="pose covariances (for the NEES)")
    p.add_argument("--map", metavar="MAP.json", help="estimated map (for the map error)")
    p.add_argument("--max-gap", type=float, metavar="S", help="ignore poses this far from REF")
    p.add_argument("--out", metavar="report.json", help="write the report as JSON")
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser(
        "compare",
        help="every backend and sensor mode on one log, compared",
        description=(
            "Run EKF, iSAM2 and batch smoothing in fused, laser-only and sonar-only modes on the "
            "same log (the front end runs once per mode), write each run's outputs into "
            "DIR/<backend>-<sensors>/, and comparison.json, comparison.md and comparison.png "
            "(trajectories and errors over time) into DIR."
        ),
    )
    p.add_argument("log", help="native log file (.log or .log.gz)")
    p.add_argument(
        "--config", metavar="ROBOT.toml", help="robot configuration (default: the log's)"
    )
    p.add_argument(
        "--association",
        choices=["jcbb", "nn"],
        default="jcbb",
        help="data association: joint compatibility (JCBB) or nearest neighbour (default jcbb)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.set_defaults(func=_cmd_compare)

    p = sub.add_parser(
        "demo",
        help="simulate the paper's corridor run and compare all backends (a few minutes)",
        description=(
            "Simulate the built-in corridor run (the paper's experiment) and run `fgslam "
            "compare` on it: EKF vs iSAM2 vs batch, fused vs laser-only vs sonar-only."
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
    p.add_argument("--world", default="corridor", help="built-in world name or world JSON file")
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
    p.set_defaults(func=_cmd_online)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] | None = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 0
    try:
        return func(args)
    except UserError as exc:
        print(f"fgslam {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"fgslam {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
