"""``fgslam calibrate LOG --reference REF``: fit the odometry's motion error model by maximum
likelihood over relative motions, and write it as a TOML snippet for ``fgslam run --config``.

Relative motions: the pairs ``(t1, t2)`` of a relations file (``t1 t2 x y z roll pitch yaw``,
the true pose at t2 in the frame of the pose at t1), or consecutive poses of a reference (a
TUM file, or a log with truth or reference poses); pairs longer than ``max_span`` s are left
out (the linearised covariance does not hold over long drifts). For each pair the odometry's
own relative motion comes from the log's odometry samples (the cumulative odometry path
interpolated at t1 and t2, :mod:`fgslam.evaluation.dense`), its error ``e = d_true - d_odo`` (x,
y in
the frame of the pose at t1, heading wrapped), and its covariance ``P(alpha)`` from the
samples in (t1, t2] through :func:`factors.odometry.step_noise`. ``P`` is linear in the
model's parameters: ``P = floor + sum_i alpha_i C_i`` with ``C_i`` the covariance of unit
``alpha_i`` alone, so the negative log-likelihood ``sum_k log det P_k + e_k^T P_k^-1 e_k``
is minimised over ``log alpha`` (scipy) with the eq 5 wheel terms set to 0: the fitted model
replaces them. The odometry NEES (``e^T P^-1 e``, 3 dof: 3 on average if consistent) is
reported before (the log's configuration) and after.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize

from factors.geometry import wrap_angles
from factors.odometry import COVARIANCE_FLOOR, OdometryParams, step_noise
from fgslam.errors import UserError

N_ALPHA = 5
MAX_SPAN = 10.0  # s: longest relative motion used


def _samples_and_reference(log: str, reference: str, options: dict[str, Any]):
    from fgslam.events import OdometryEvent
    from fgslam.io.formats import open_log

    reader = open_log(log, **options)
    o = reader.config.odometry
    samples = []
    for ev in reader:
        if isinstance(ev, OdometryEvent):
            samples.append((ev.t, *o.wheel_travel(ev.ticks_right, ev.ticks_left)))
    return reader.config, np.array(samples, dtype=float).reshape(-1, 3)


def relative_motions(reference: str | Path, **reader_options: Any) -> NDArray[np.float64]:
    """Rows ``(t1, t2, x, y, yaw)`` from a relations file, or from consecutive poses of a TUM
    file or a log with truth/reference poses."""
    from factors.geometry import between_poses
    from fgslam.evaluation.dense import read_relations
    from fgslam.evaluation.reference import load_reference

    p = Path(reference)
    if p.suffix == ".relations":
        try:
            return read_relations(p)
        except (OSError, ValueError) as exc:
            raise UserError(f"{reference}: not a relations file ({exc})") from None
    t, poses, _, _ = load_reference(p, **reader_options)
    d = between_poses(poses[:-1], poses[1:])
    return np.column_stack([t[:-1], t[1:], d])


def motion_covariances(
    samples: NDArray[np.float64], pairs: NDArray[np.float64], params: OdometryParams
) -> tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]]:
    """For each pair (t1, t2): whether it has odometry samples, the covariance of the
    odometry motion under ``params`` (K, 3, 3) and the unit-alpha covariances (K, 5, 3, 3),
    in the frame of the pose at t1."""
    t = samples[:, 0]
    units = [
        dataclasses.replace(
            params, k_r=0.0, k_l=0.0, k_d=0.0, **{f"alpha{j + 1}": float(i == j) for j in range(5)}
        )
        for i in range(N_ALPHA)
    ]
    models = [params, *units]
    K = len(pairs)
    ok = np.zeros(K, dtype=bool)
    out = np.zeros((K, len(models), 3, 3))
    for k, (t1, t2) in enumerate(pairs[:, :2]):
        i0, i1 = np.searchsorted(t, t1, "right"), np.searchsorted(t, t2, "right")
        if i1 <= i0:
            continue
        ok[k] = True
        P = np.zeros((len(models), 3, 3))
        th = 0.0
        D = params.wheelbase
        for lr, ll in samples[i0:i1, 1:].tolist():
            for m, mp in enumerate(models):
                F, Q = step_noise(th, lr, ll, mp)
                P[m] = F @ P[m] @ F.T + Q
            th += (lr - ll) / D
        out[k] = P
    return ok, out[:, 0], out[:, 1:]


def _nees(e: NDArray, P: NDArray) -> NDArray:
    return np.einsum("ki,ki->k", e, np.linalg.solve(P, e[..., None])[..., 0])


def fit_alphas(e: ArrayLike, C: ArrayLike, floor: float = COVARIANCE_FLOOR) -> NDArray:
    """Maximum-likelihood alpha1..5 for errors ``e`` (K, 3) with covariances
    ``floor I + sum_i alpha_i C[:, i]``."""
    e = np.asarray(e, dtype=float)
    C = np.asarray(C, dtype=float)
    eye = np.eye(3) * floor

    def nll(theta: NDArray) -> float:
        a = np.exp(theta)
        P = eye + np.einsum("i,kirc->krc", a, C)
        sign, logdet = np.linalg.slogdet(P)
        if np.any(sign <= 0):
            return 1e300
        return float(np.sum(logdet + _nees(e, P)))

    # start: each alpha alone explaining the mean squared error of its component
    best = None
    for start in (-4.0, -7.0, -10.0):
        res = minimize(nll, np.full(N_ALPHA, start), method="L-BFGS-B", bounds=[(-30, 5)] * 5)
        if best is None or res.fun < best.fun:
            best = res
    return np.exp(best.x)


def calibrate(
    log: str | Path,
    reference: str | Path,
    max_span: float = MAX_SPAN,
    reader_options: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Fit the motion error model of ``log``'s odometry against ``reference``; returns the
    fitted parameters, the NEES before and after and the counts."""
    opts = reader_options or {}
    cfg, samples = _samples_and_reference(str(log), str(reference), opts)
    if len(samples) < 2:
        raise UserError(f"{log}: no odometry to calibrate")
    pairs = relative_motions(reference, **opts)
    span = pairs[:, 1] - pairs[:, 0]
    inside = (pairs[:, 0] >= samples[0, 0]) & (pairs[:, 1] <= samples[-1, 0])
    pairs = pairs[inside & (span > 0) & (span <= max_span)]
    if not len(pairs):
        raise UserError(
            f"{reference}: no relative motion of at most {max_span:g} s within the log's "
            "odometry: nothing to calibrate against"
        )
    from factors.geometry import between_poses
    from fgslam.evaluation.dense import _at, odometry_path

    before = cfg.odometry.params()
    ok, P0, C = motion_covariances(samples, pairs, before)
    pairs, P0, C = pairs[ok], P0[ok], C[ok]
    ot, op = odometry_path(samples, cfg.odometry.wheelbase)
    d_odo = between_poses(_at(ot, op, pairs[:, 0]), _at(ot, op, pairs[:, 1]))
    e = pairs[:, 2:5] - d_odo
    e[:, 2] = wrap_angles(e[:, 2])
    alphas = fit_alphas(e, C)
    eye = np.eye(3) * COVARIANCE_FLOOR
    n_before = _nees(e, P0 + eye)
    n_after = _nees(e, eye + np.einsum("i,kirc->krc", alphas, C))
    return {
        "log": str(log),
        "reference": str(reference),
        "motions": len(pairs),
        "max_span_s": max_span,
        "alphas": [float(a) for a in alphas],
        "nees_before": {"mean": float(n_before.mean()), "median": float(np.median(n_before))},
        "nees_after": {"mean": float(n_after.mean()), "median": float(np.median(n_after))},
        "rms_error": [float(v) for v in np.sqrt(np.mean(e**2, axis=0))],
    }


def toml_snippet(rep: dict[str, Any], command: str) -> str:
    """The fitted model as an ``[odometry]`` TOML section (eq 5's wheel terms off)."""
    a = rep["alphas"]
    nb, na = rep["nees_before"], rep["nees_after"]
    units = ("rad^2/rad", "rad^2/m", "m^2/m", "m^2/rad", "m^2/m lateral")
    lines = [
        f"# {command}",
        f"# {rep['motions']} relative motions of at most {rep['max_span_s']:g} s; odometry NEES "
        f"(3 dof) mean {nb['mean']:.3g} / median {nb['median']:.3g} before, "
        f"{na['mean']:.3g} / {na['median']:.3g} after",
        "[odometry]",
        "k_r = 0.0",
        "k_l = 0.0",
        "k_d = 0.0",
    ]
    lines += [
        f"alpha{i + 1} = {v:.6g}  # {u}" for i, (v, u) in enumerate(zip(a, units, strict=True))
    ]
    return "\n".join(lines) + "\n"


def add_parser(sub: Any) -> None:
    """Register ``fgslam calibrate`` on the CLI's subparsers."""
    p = sub.add_parser(
        "calibrate",
        help="fit the odometry error model to a reference (writes a TOML snippet)",
        description=(
            "Fit the odometry's motion error model (alpha1..5, see the default configuration) "
            "by maximum likelihood over the relative motions of a reference: a relations "
            "file, a TUM file or a log with reference poses; print the odometry NEES before "
            "and after and write the [odometry] TOML section (for fgslam run --config)."
        ),
    )
    p.add_argument("log", help="log with odometry (fgslam, CARMEN, ROS bag)")
    p.add_argument("--reference", required=True, metavar="REF", help=".relations, TUM or log")
    p.add_argument(
        "--max-span", type=float, default=MAX_SPAN, metavar="S", help="longest motion (10 s)"
    )
    p.add_argument("--out", metavar="FILE.toml", help="write the snippet here (default: stdout)")
    p.set_defaults(func=calibrate_command)


def calibrate_command(args: argparse.Namespace) -> int:
    import sys

    if not (args.max_span > 0 and math.isfinite(args.max_span)):
        raise UserError(f"--max-span must be positive, got {args.max_span}")
    rep = calibrate(args.log, args.reference, args.max_span)
    cmd = "fgslam " + " ".join(sys.argv[1:]) if sys.argv[1:] else "fgslam calibrate"
    text = toml_snippet(rep, cmd)
    nb, na = rep["nees_before"], rep["nees_after"]
    print(
        f"{rep['motions']} relative motions: odometry NEES mean {nb['mean']:.3g} (median "
        f"{nb['median']:.3g}) before, {na['mean']:.3g} ({na['median']:.3g}) after; rms error "
        f"x {rep['rms_error'][0]:.3f} m, y {rep['rms_error'][1]:.3f} m, "
        f"theta {rep['rms_error'][2]:.4f} rad"
    )
    if args.out:
        Path(args.out).write_text(text, encoding="utf-8")
        print(f"wrote {args.out}")
    else:
        print(text, end="")
    return 0
