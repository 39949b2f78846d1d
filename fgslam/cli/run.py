"""``fgslam run``: SLAM on a log (EKF, iSAM2 or batch; fused, laser or sonar), and the account
of what happened to the log's records."""

from __future__ import annotations

import argparse
import math
import sys
from collections import Counter
from pathlib import Path

from fgslam.cli.common import (
    add_association_argument,
    add_backend_arguments,
    add_log_arguments,
    config_options,
    log_progress,
    parse_pose,
    print_summary,
    reader_options,
    reader_warnings,
)
from fgslam.errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
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
    add_log_arguments(p, "DIR", "output directory", config=True, tolerant=True)
    add_backend_arguments(
        p,
        ["ekf", "isam2", "batch"],
        "the paper's EKF, incremental smoothing, or batch LM smoothing (default isam2)",
    )
    add_association_argument(p)
    p.add_argument(
        "--save",
        metavar="SESSION",
        help="also save the run as a session folder (docs/sessions.md: the optimised graph, "
        "the keyframes' scans, the configuration, map.pgm + map.yaml) for `fgslam localize "
        "--map`; an existing session there is replaced, any other folder content refused",
    )
    p.add_argument(
        "--continue",
        dest="continue_from",
        metavar="SESSION",
        help="continue a saved session: localize the log on it (from --initial-pose, else by "
        "a search over the whole map), then map on from there, the saved keyframes and the "
        "new ones in one graph (loop closures between them join the two); saved as one "
        "session into --save, by default back into SESSION (replaced only once the run is "
        "done). isam2 or batch only. The log before the robot is placed on the map is not "
        "mapped (docs/sessions.md)",
    )
    p.add_argument(
        "--initial-pose",
        metavar="X,Y,THETA",
        type=parse_pose,
        help="with --continue: the log's start pose in the session's frame (m, m, rad)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fgslam.config import with_options
    from fgslam.io.formats import open_log
    from fgslam.sim import true_calibration
    from fgslam.slam.outputs import write_outputs
    from fgslam.slam.runner import run_slam

    if args.initial_pose is not None and not args.continue_from:
        raise UserError("--initial-pose places the log on a saved session: give --continue")
    if args.continue_from:
        if args.backend == "ekf":
            raise UserError("--continue needs isam2 or batch: the EKF keeps no past keyframes")
        args.save = args.save or args.continue_from
    if args.save:  # refused before the work, not after
        from fgslam.session.store import SessionError, check_replaceable

        if Path(args.save).resolve() == Path(args.out).resolve():
            raise SessionError(f"--save {args.save}: give the session its own folder, not --out")
        check_replaceable(args.save)
    reader = open_log(args.log, **reader_options(args))
    cfg = with_options(_run_config(reader, args.config, args.log), config_options(args))
    continuation = _continuation(args, cfg) if args.continue_from else None
    progress = log_progress(reader, f"{args.backend}/{args.sensors}")
    tap = _Tap(reader)
    try:
        res = run_slam(
            tap,
            cfg,
            args.backend,
            args.sensors,
            progress,
            association=args.association,
            continuation=continuation,
        )
    finally:
        progress.close()
    extra, notes = _input_notes(reader, tap, [res])
    extra["config_source"] = cfg.source
    from fgslam.evaluation.dense import write_dense_trajectory

    def dense(path: Path) -> int:
        return write_dense_trajectory(
            path, *res.every_scan, res.odometry_samples, cfg.odometry.wheelbase
        )

    rep = write_outputs(
        res,
        args.out,
        reader.meta.get("true_map"),
        true_calibration=true_calibration(reader.meta),
        extra=extra,
        world=_log_world(reader),
        scans=tap.sample.scans,
        cfg=cfg,
        more={"trajectory_dense.tum": dense},
    )
    for line in notes:
        print(line)
    print_summary(rep, args.out)
    if args.save:
        from fgslam.session import Session, save_session

        meta = {"log": Path(args.log).name, "log_duration_s": res.log_duration}
        save_session(Session.from_result(res, cfg, meta, continuation), args.save)
        print(f"saved the session in {args.save} (session.json, scans.npz, map.pgm, map.yaml)")
    return _report_partial(rep, args.out)


def _continuation(args: argparse.Namespace, cfg):
    """The saved session to continue and where the log starts on it (a first pass over the
    log, as far as its first match on the map)."""
    from fgslam.config import check_against_log
    from fgslam.io.formats import open_log
    from fgslam.session import load_session
    from fgslam.session.join import Continuation, find_anchor

    session = load_session(args.continue_from)
    try:
        check_against_log(session.robot_config(), cfg, str(args.log))
    except UserError as e:
        msg = f"the session {args.continue_from} was made by another robot: {e}"
        raise UserError(msg) from None
    reader = open_log(args.log, **reader_options(args))
    progress = log_progress(reader, "localize on the session")
    try:
        anchor = find_anchor(session, reader, cfg, args.initial_pose, progress)
    finally:
        progress.close()
    x, y, th = anchor.pose
    print(
        f"placed on {args.continue_from} at t = {anchor.t:.2f} s ({anchor.how}; "
        f"{anchor.t - anchor.log_start:.1f} s into the log): x {x:.2f} y {y:.2f} "
        f"th {math.degrees(th):.1f} deg; mapping from there"
    )
    return Continuation(session, anchor, str(args.continue_from))


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

    return load_world(reader.world) if reader.world in BUILTIN_WORLDS else None


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
    problems = reader.problems  # every reader's (fgslam.io.readers.source.Problems)
    summary = problems.summary()
    stats = results[0].stats if results else {}
    dropped = int(stats.get("events_out_of_order", 0))
    reordered = int(stats.get("events_reordered", 0))
    by_reason = dict(summary.get("skipped_by_reason", {}))
    # records of types the reader does not use (CARMEN NEFF, ...) are not data lost
    ignored = dict(problems.ignored)
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
    elif problems.passes_out_of_order:  # a few lost records of one kind (odometry) can
        # matter more than their number says; readers that carry or drop such records
        # themselves say so
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
    kind = reader.reference_kind
    if kind:
        extra["truth_source"] = kind
        if kind == "reference":
            notes.append("note: ATE is against the log's reference trajectory, not ground truth")
    section = problems.report()  # the reader's own account (docs/readers.md)
    if section is not None:
        extra["reader"] = section
    notes += [f"warning: {w}" for w in reader_warnings(reader)]
    return extra, notes


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
