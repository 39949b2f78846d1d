"""``fgslam evaluate``: a trajectory (TUM) against a reference (TUM, or a log with truth or
reference poses), with the metrics of :mod:`fgslam.evaluation.metrics`."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from fgslam.errors import UserError
from fgslam.evaluation import metrics as evaluation
from fgslam.evaluation.reference import load_reference, read_tum_file


def _finite_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _map_error(map_path: Path, true_map: Any, reference: str | Path) -> dict[str, Any]:
    """:func:`evaluation.map_error` of a map.json's landmarks against a log's true map;
    UserError naming the file and the landmark (or feature) for one it cannot compare (not
    an object, a field missing or not a finite number)."""
    try:
        landmarks = json.loads(map_path.read_text(encoding="utf-8"))["landmarks"]
    except (OSError, ValueError, KeyError, TypeError, RecursionError) as exc:
        raise UserError(f"{map_path}: not a map.json ({exc!r})") from None
    fields = {"line": ("alpha", "d"), "corner": ("x", "y"), "point": ("x", "y")}

    def check(items: Any, where: str, kind: str | None = None) -> None:
        if not isinstance(items, list):
            raise UserError(f"{where}: expected a list")
        for k, lm in enumerate(items):
            what = kind or (lm.get("kind") if isinstance(lm, dict) else None)
            need = fields.get(what, ()) if isinstance(what, str) else ()
            if not isinstance(lm, dict) or not all(_finite_number(lm.get(f)) for f in need):
                raise UserError(
                    f"{where} {k}: {str(lm)[:80]} is not a landmark "
                    f"({', '.join(need) or 'fields'}: finite numbers)"
                )

    check(landmarks, f"{map_path}: landmark")
    if not isinstance(true_map, dict):
        raise UserError(f"{reference}: the true map is not an object")
    for key, kind in (("lines", "line"), ("corners", "corner"), ("points", "point")):
        check(true_map.get(key, []), f"{reference}: true map {key[:-1]}", kind)
    with np.errstate(over="ignore", invalid="ignore"):
        out = evaluation.map_error(landmarks, true_map)
    for k, v in out.items():
        if not all(math.isfinite(x) for x in v.values()):
            raise UserError(f"{map_path}: the map error ({k}) overflows")
    return out


def relations_report(
    traj: Path, relations: str | Path, log: str | Path | None = None
) -> dict[str, Any]:
    """The relations metric of a TUM trajectory: with ``log`` (the CARMEN log the run read),
    the trajectory's poses at the log's scans and the log's odometry records
    (:func:`fgslam.evaluation.dense.relations_error_chain`, the benchmark's method); without,
    the trajectory interpolated (:func:`fgslam.evaluation.dense.relations_error`; right for a
    dense one)."""
    from fgslam.evaluation import dense

    t_est, est = read_tum_file(traj)
    if not len(t_est):
        raise UserError(f"{traj}: no poses: no relation can be evaluated")
    try:
        rel = dense.read_relations(relations)
    except (ValueError, OSError) as exc:
        raise UserError(f"{relations}: not a relations file ({exc})") from None
    if log is not None:
        from fgslam.io.formats import sniff_format

        if sniff_format(log) != "carmen":
            raise UserError(f"{log}: --odometry-log takes a CARMEN log")
    try:
        if log is not None:
            from fgslam.io.readers.carmen import odometry_chain

            chain = odometry_chain(log)
            e, has = dense.estimate_at_scans(chain, t_est, est)
            out = dense.relations_error_chain(rel, chain, e, has)
            out["scans_with_estimate"] = int(has.sum())
        else:
            out = dense.relations_error(rel, t_est, est)
    except ValueError as exc:
        raise UserError(f"{relations}: {exc}") from None
    src = {"odometry": str(log)} if log is not None else {}
    return {"trajectory": str(traj), "file": str(relations), **src, **out}


def _relations_text(r: dict[str, Any]) -> str:
    return (
        f"relations ({r['relations_used']} of {r['relations']}, {r['trajectory']}): "
        f"translation {r['trans_mean']:.3f} +- {r['trans_std']:.3f} m (max "
        f"{r['trans_max']:.3f}), rotation {r['rot_mean_deg']:.2f} +- {r['rot_std_deg']:.2f} "
        f"deg (max {r['rot_max_deg']:.2f})"
    )


def evaluate_command(args: argparse.Namespace) -> dict[str, Any]:
    traj = Path(args.trajectory)
    map_path = Path(args.map) if args.map else None
    relations = getattr(args, "relations", None)
    dense_traj = traj
    if traj.is_dir():
        if map_path is None and (traj / "map.json").exists():
            map_path = traj / "map.json"
        dense_traj = traj / "trajectory_dense.tum"
        if not dense_traj.exists():
            dense_traj = traj / "trajectory.tum"
        traj = traj / "trajectory.tum"
    if not args.reference and not relations:
        raise UserError("nothing to compare with: give --reference, --relations or both")
    odo_log = getattr(args, "odometry_log", None)
    if odo_log:  # the keyframes and the log's own odometry records
        dense_traj = traj
    rel_rep = relations_report(dense_traj, relations, odo_log) if relations else None
    if not args.reference:
        assert rel_rep is not None
        return {"relations": rel_rep, "_text": _relations_text(rel_rep)}
    t_est, est = read_tum_file(traj)
    t_ref, ref, true_map, kind = load_reference(args.reference)
    covs = None
    if args.covariances:
        try:
            t_c, covs = evaluation.read_covariances(args.covariances)
        except (ValueError, OSError) as exc:
            raise UserError(f"{args.covariances}: {exc}") from None
        if len(t_c) != len(t_est) or not np.allclose(t_c, t_est, atol=1e-6):
            raise UserError(f"{args.covariances}: times differ from the trajectory's")
    if not 0 < args.rpe_delta < math.inf:
        raise UserError(f"--rpe-delta must be a positive number of metres, got {args.rpe_delta}")
    if args.max_gap is not None and not args.max_gap >= 0:
        raise UserError(f"--max-gap must be a number of seconds >= 0, got {args.max_gap}")
    try:
        rep = evaluation.evaluate_trajectory(
            t_est, est, t_ref, ref, args.rpe_delta, covs, args.max_gap
        )
    except ValueError as exc:
        raise UserError(f"{traj} against {args.reference}: {exc}") from None
    rep = {"trajectory": str(traj), "reference": str(args.reference), "reference_kind": kind, **rep}
    if map_path is not None and true_map:
        rep["map_error"] = _map_error(map_path, true_map, args.reference)
    lines = [
        f"{rep['poses_compared']} poses against the {kind} "
        f"({rep['poses_outside_reference']} outside its time span)"
    ]
    if "ate" in rep:
        a = rep["ate"]
        lines.append(
            f"ATE (SE(2)-aligned): RMSE {a['rmse']:.3f} m, mean {a['mean']:.3f} m, "
            f"max {a['max']:.3f} m, heading RMSE {a['heading_rmse_deg']:.2f} deg"
        )
    elif "ate_unaligned" in rep:  # too few poses to align
        a = rep["ate_unaligned"]
        lines.append(
            f"ATE (not aligned): RMSE {a['rmse']:.3f} m, max {a['max']:.3f} m, "
            f"heading RMSE {a['heading_rmse_deg']:.2f} deg"
        )
    if "rpe" in rep:
        r = rep["rpe"]
        lines.append(
            f"RPE over {r['delta_m']:g} m ({r['pairs']} pairs): translation RMSE "
            f"{r['trans_rmse']:.3f} m (max {r['trans_max']:.3f}), rotation RMSE "
            f"{r['rot_rmse_deg']:.2f} deg (max {r['rot_max_deg']:.2f})"
        )
    for name, why in rep.get("not_evaluated", {}).items():
        hint = " (give a smaller --rpe-delta)" if name == "rpe" and "travels" in why else ""
        lines.append(f"warning: {name} not evaluated: {why}{hint}")
    if "nees" in rep:
        lines.append(
            f"NEES: mean {rep['nees']['mean']:.2f} (3 dof), "
            f"{100 * rep['nees']['within_95']:.0f} % within the 95 % interval"
        )
    for k, v in rep.get("map_error", {}).items():
        lines.append(f"map error {k}: median {v['median']:.3f}, mean {v['mean']:.3f} (n={v['n']})")
    if rel_rep is not None:
        rep["relations"] = rel_rep
        lines.append(_relations_text(rel_rep))
    rep["_text"] = "\n".join(lines)
    return rep


def register(sub: argparse._SubParsersAction) -> None:
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
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    rep = evaluate_command(args)
    print(rep.pop("_text"))
    if args.out:
        from fgslam.io.safeio import write_json

        write_json(args.out, rep)
        print(f"wrote {args.out}")
    return 0
