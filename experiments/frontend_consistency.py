"""Covariance consistency of the laser line and corner fits: mean NEES over noisy simulated scans.

Run: python experiments/frontend_consistency.py [--n 500] [--seed 0] [--laser-sigma S]
Each trial draws one scan of a known wall (line) or a known concave right-angle corner with
the simulator's laser model (``fgslam.sim.sensors.laser_scan``: Gaussian noise, 5 cm range
quantisation, optionally the simulator's systematic errors and mixed pixels), from a laser
pose jittered by +-5 cm and +-2 deg so that every trial sees the quantisation at a different
phase. The beams on the object are fitted with ``fit_line`` / ``fit_corner`` with the robot
configuration's ``laser.sigma_range`` and the systematic sources of ``FrontEnd._systematic``,
and the NEES e^T C^-1 e of the fitted parameters (alpha, d) or (phi_c, r_c, gamma) is computed
with C = ``fit.cov_random`` (no systematic inflation) and C = ``fit.cov`` (with it).

Prints: (1) the mean NEES in the four cases of issue 4 (random errors only / with the
simulator's systematic errors, each without / with the inflation); (2) the random-only mean
NEES at several ranges and incidence angles; (3) the simulated range error itself (sd, and the
correlation of neighbouring beams that quantisation could cause) and the mean NEES for several
values of the simulator's random sigma (0.5, 1 and 2 cm besides the default). Draws
frontend_consistency.png next to this file.
The target (issue 4): random-only mean NEES in [0.8, 1.25] x dimension without inflation.
The simulator's default ``SimParams.laser_sigma`` (1.38 cm) is the calibrated value: with the
5 cm quantisation (sd 1.44 cm) it makes the simulated random range error the configured
``sigma_range`` (2 cm). With ``--laser-sigma`` set to another value, the tables and the figure
show the calibrated value next to it.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from scipy import stats

from factors.geometry import wrap_angle
from fgslam.config import load_config
from fgslam.frontend.fits import FitRejected, fit_corner, fit_line
from fgslam.frontend.pipeline import FrontEnd
from fgslam.sim.sensors import SimParams, laser_scan
from fgslam.sim.world import parse_world

CFG = load_config()
LASER = CFG.laser
PHI = LASER.bearings
SYSTEMATIC = FrontEnd(CFG, "laser")._systematic  # the front end's systematic error sources
# a wall x = 0 (free space at x < 0) and a concave corner at the origin (free space x, y < 0)
WALL = parse_world(
    {"name": "wall", "walls": [{"id": "w", "points": [[0, -40], [0, 40]]}]}, "<wall>"
)
CORNER = parse_world(
    {"name": "corner", "walls": [{"id": "c", "points": [[0, -40], [0, 0], [-40, 0]]}]}, "<corner>"
)
BISECTOR = -3 * math.pi / 4  # the corner's bisector into free space (world)


@dataclasses.dataclass
class Result:
    nees_random: np.ndarray  # NEES with cov_random, per trial
    nees_full: np.ndarray  # NEES with cov (systematic inflation)
    rejected: int


def line_trials(d, incidence_deg, params, n, rng, half_deg=15.0) -> Result:
    """Wall at distance d (m), beams within half_deg of the direction incidence_deg off the
    wall's normal."""
    out, rejected = [], 0
    for _ in range(n):
        x0 = -d + rng.uniform(-0.05, 0.05)
        th = math.radians(rng.uniform(-2, 2))
        truth = np.array([wrap_angle(-th), -x0])  # (alpha, d) in the laser frame
        r = laser_scan(WALL, LASER, params, (x0, rng.uniform(-0.05, 0.05), th), 0.0, rng)
        centre = math.radians(incidence_deg) - th
        sel = (np.abs(PHI - centre) <= math.radians(half_deg)) & np.isfinite(r)
        try:
            fit = fit_line(PHI[sel], r[sel], LASER.sigma_range, SYSTEMATIC(r[sel]))
        except FitRejected:
            rejected += 1
            continue
        e = fit.params - truth
        e[0] = wrap_angle(e[0])
        out.append((e @ np.linalg.solve(fit.cov_random, e), e @ np.linalg.solve(fit.cov, e)))
    a = np.array(out).reshape(-1, 2)
    return Result(a[:, 0], a[:, 1], rejected)


def corner_trials(r_c, bearing_deg, params, n, rng, half_deg=25.0) -> Result:
    """Concave corner seen along its bisector from r_c (m), at bearing bearing_deg in the scan;
    beams within half_deg of the vertex."""
    out, rejected = [], 0
    for _ in range(n):
        ang = BISECTOR + math.radians(rng.uniform(-2, 2))
        rr = r_c + rng.uniform(-0.05, 0.05)
        px, py = rr * math.cos(ang), rr * math.sin(ang)
        th = math.atan2(-py, -px) - math.radians(bearing_deg) + math.radians(rng.uniform(-2, 2))
        phi_c = wrap_angle(math.atan2(-py, -px) - th)
        truth = np.array([phi_c, rr, wrap_angle(BISECTOR - th)])
        r = laser_scan(CORNER, LASER, params, (px, py, th), 0.0, rng)
        sel = (np.abs(PHI - phi_c) <= math.radians(half_deg)) & np.isfinite(r)
        init = (phi_c + 0.03, rr + 0.05, truth[2] - math.pi + 0.05)  # paper's gamma convention
        try:
            fit = fit_corner(PHI[sel], r[sel], init, LASER.sigma_range, SYSTEMATIC(r[sel]))
        except FitRejected:
            rejected += 1
            continue
        e = fit.params - truth
        e[0], e[2] = wrap_angle(e[0]), wrap_angle(e[2])
        out.append((e @ np.linalg.solve(fit.cov_random, e), e @ np.linalg.solve(fit.cov, e)))
    a = np.array(out).reshape(-1, 2)
    return Result(a[:, 0], a[:, 1], rejected)


def range_errors(params, rng, n=400, d=3.0):
    """Random range errors of the simulated laser on a wall at normal incidence (beams within
    +-15 deg), the wall's distance jittered by +-5 cm per scan as in the NEES trials: the sd
    over all beams and scans, and the correlation of the errors of neighbouring beams in a
    scan (the quantisation error of two beams with nearly the same true range is correlated
    when the Gaussian noise is small against the 5 cm quantum)."""
    sel = np.abs(PHI) <= math.radians(15)
    errs = []
    for _ in range(n):
        x0 = -d + rng.uniform(-0.05, 0.05)
        r = laser_scan(WALL, LASER, params, (x0, 0.0, 0.0), 0.0, rng)[sel]
        errs.append(r - (-x0) / np.cos(PHI[sel]))
    err = np.array(errs)
    sd = float(np.sqrt(np.mean(err**2)))
    rho = float(np.mean(err[:, 1:] * err[:, :-1]) / np.mean(err**2))
    return sd, rho


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=500, help="scans per case")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--laser-sigma",
        type=float,
        help=f"override SimParams.laser_sigma (m; default {SimParams().laser_sigma}, calibrated)",
    )
    args = ap.parse_args()
    default = SimParams()
    if args.laser_sigma is not None:
        default = dataclasses.replace(default, laser_sigma=args.laser_sigma)
    q = LASER.range_resolution
    # the Gaussian sigma that makes Gaussian + quantisation the configured random error
    calibrated = math.sqrt(LASER.sigma_range**2 - q**2 / 12)
    sims = {"default": default}  # the calibrated sigma too, unless it is the default
    if round(calibrated, 4) != round(default.laser_sigma, 4):
        sims["calibrated"] = dataclasses.replace(default, laser_sigma=round(calibrated, 4))
    seeds = np.random.SeedSequence(args.seed).spawn(64)
    rngs = iter(np.random.default_rng(s) for s in seeds)
    n = args.n
    print(
        f"configured: sigma_range {100 * LASER.sigma_range:.1f} cm, systematic "
        f"{100 * LASER.systematic_offset:.1f} cm + {1000 * LASER.systematic_per_metre:.1f} mm/m."
        f" simulator: systematic {100 * default.laser_sys_offset:.1f} cm + "
        f"{1000 * default.laser_sys_per_metre:.1f} mm/m, {100 * q:.0f} cm quantisation "
        f"(sd {100 * q / math.sqrt(12):.2f} cm) + Gaussian laser_sigma:"
    )
    for name, sp in sims.items():
        eff = math.hypot(sp.laser_sigma, q / math.sqrt(12))
        same = " (= calibrated)" if len(sims) == 1 else ""
        print(
            f"  {name:10s} laser_sigma {100 * sp.laser_sigma:.2f} cm{same} -> random range error "
            f"{100 * eff:.2f} cm"
        )

    # (1) the four cases, for the simulator's default sigma (and the calibrated one if not)
    res = {}
    for name, sp in sims.items():
        random_only = dataclasses.replace(sp, laser_sys_offset=0.0, laser_sys_per_metre=0.0)
        for errors, p in (("random", random_only), ("systematic", sp)):
            res[(name, errors, "line")] = line_trials(3.0, 0.0, p, n, next(rngs))
            res[(name, errors, "corner")] = corner_trials(3.0, 0.0, p, n, next(rngs))
    print(
        f"\n(1) mean NEES over {n} scans each: wall at 3 m, normal incidence, beams within "
        "+-15 deg; corner at 3 m seen along its bisector, beams within +-25 deg"
    )
    print(
        "| laser_sigma    | simulated errors    | covariance                | line (dim 2) "
        "| /2    | corner (dim 3) | /3    |"
    )
    print(
        "|----------------|---------------------|---------------------------|--------------"
        "|-------|----------------|-------|"
    )
    for name, sp in sims.items():
        for errors, err_name in (("random", "random only"), ("systematic", "random + systematic")):
            for attr, cov_name in (
                ("nees_random", "cov_random (no inflation)"),
                ("nees_full", "cov (+ systematic)"),
            ):
                ln = getattr(res[(name, errors, "line")], attr).mean()
                cn = getattr(res[(name, errors, "corner")], attr).mean()
                sig = f"{100 * sp.laser_sigma:.2f} cm ({name[:3]})"
                print(
                    f"| {sig:14s} | {err_name:19s} | {cov_name:25s} | {ln:12.2f} | {ln / 2:5.2f} "
                    f"| {cn:14.2f} | {cn / 3:5.2f} |"
                )
    print(f"fits rejected: {sum(r.rejected for r in res.values())}")

    # (2) geometry sweep, random errors only, no inflation
    print("\n(2) random errors only, mean NEES / dimension with cov_random, by geometry")
    print(
        "| feature | geometry                          |"
        + "".join(f" {name} sigma {100 * sp.laser_sigma:.2f} cm |" for name, sp in sims.items())
    )
    print(
        "|---------|-----------------------------------|"
        + "".join("-" * (len(name) + 16) + "|" for name in sims)
    )
    cases = [
        ("line", "d 1.5 m, normal incidence", line_trials, (1.5, 0), {}),
        ("line", "d 6 m, normal incidence", line_trials, (6.0, 0), {}),
        ("line", "d 3 m, beams 30 deg off normal", line_trials, (3.0, 30), {}),
        ("line", "d 3 m, beams 45 deg off normal", line_trials, (3.0, 45), {}),
        ("line", "d 3 m, beams 60 deg off normal", line_trials, (3.0, 60), {}),
        ("line", "  same, mixed pixels off", line_trials, (3.0, 60), {"mixed_pixel_prob": 0.0}),
        ("corner", "r_c 1.5 m, on the bisector", corner_trials, (1.5, 0), {}),
        ("corner", "r_c 5 m, on the bisector", corner_trials, (5.0, 0), {}),
        ("corner", "r_c 3 m, at bearing 50 deg", corner_trials, (3.0, 50), {}),
    ]
    for kind, geom, trials, where, extra in cases:
        dim = 2 if kind == "line" else 3
        cells = []
        for sp in sims.values():
            p = dataclasses.replace(sp, laser_sys_offset=0.0, laser_sys_per_metre=0.0, **extra)
            r = trials(*where, p, n, next(rngs))
            rej = f" ({r.rejected} rejected)" if r.rejected else ""
            cells.append(f"{r.nees_random.mean() / dim:.2f}{rej}")
        print(
            f"| {kind:7s} | {geom:33s} |"
            + "".join(f" {c:>{len(name) + 14}s} |" for c, name in zip(cells, sims, strict=True))
        )

    # (3) the simulated range error and the simulator's sigma
    print(
        "\n(3) simulated random range error (wall at 3 +- 0.05 m, normal incidence, beams "
        "within +-15 deg) and random-only mean NEES / dimension, by SimParams.laser_sigma"
    )
    print(
        "| laser_sigma (cm)    | expected sd (cm) | range error sd (cm) | neighbour corr. "
        "| line NEES/2 | corner NEES/3 |"
    )
    print(
        "|---------------------|------------------|---------------------|-----------------"
        "|-------------|---------------|"
    )
    sweep = {}  # laser_sigma -> (line, corner) random-only NEES per scan (cov_random)
    for s in sorted({0.005, 0.01, 0.02, *(sp.laser_sigma for sp in sims.values())}):
        p = dataclasses.replace(default, laser_sigma=s, laser_sys_offset=0, laser_sys_per_metre=0)
        sd, rho = range_errors(p, next(rngs))
        name = next((k for k, sp in sims.items() if sp.laser_sigma == s), None)
        if name is not None:  # measured in (1) already
            sweep[s] = (
                res[(name, "random", "line")].nees_random,
                res[(name, "random", "corner")].nees_random,
            )
        else:
            sweep[s] = (
                line_trials(3.0, 0.0, p, n, next(rngs)).nees_random,
                corner_trials(3.0, 0.0, p, n, next(rngs)).nees_random,
            )
        ln, cn = sweep[s][0].mean() / 2, sweep[s][1].mean() / 3
        expected = 100 * math.hypot(s, q / math.sqrt(12))
        label = f"{100 * s:.2f}" + (f" ({name})" if name else "")
        print(
            f"| {label:>19s} | {expected:16.2f} | {100 * sd:19.2f} | {rho:15.3f} "
            f"| {ln:11.2f} | {cn:13.2f} |"
        )

    draw(res, sims, sweep, Path(__file__).with_suffix(".png"))


def draw(res, sims, sweep, path: Path) -> None:
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4))
    bins = np.linspace(0, 16, 41)
    x = np.linspace(0.01, 16, 400)
    default = sims["default"].laser_sigma
    others = [s for s in sorted(sweep) if s != default and s >= 0.01]  # 1 cm, 2 cm, (cal.)
    for ax, kind, dim, k in ((axes[0], "line", 2, 0), (axes[1], "corner", 3, 1)):
        dft, sysd = res[("default", "random", kind)], res[("default", "systematic", kind)]
        ax.hist(
            np.clip(dft.nees_random, 0, 16),
            bins,
            density=True,
            alpha=0.45,
            label=f"random, default sigma {100 * default:.2f} cm: "
            f"mean {dft.nees_random.mean():.2f}",
        )
        for s in others:
            ax.hist(
                np.clip(sweep[s][k], 0, 16),
                bins,
                density=True,
                histtype="step",
                lw=1.5,
                label=f"random, sigma {100 * s:.2f} cm: mean {sweep[s][k].mean():.2f}",
            )
        ax.hist(
            np.clip(sysd.nees_full, 0, 16),
            bins,
            density=True,
            histtype="step",
            lw=1.2,
            ls="--",
            color="k",
            label=f"+ sim. systematic, cov with inflation: mean {sysd.nees_full.mean():.2f}",
        )
        ax.plot(x, stats.chi2.pdf(x, dim), "k", lw=2, label=rf"$\chi^2_{dim}$ density")
        ax.set(
            title=f"{kind} fit: NEES of {len(dft.nees_random)} scans each (clipped at 16)",
            xlabel="NEES",
            ylabel="density",
            xlim=(0, 16),
        )
        ax.legend(fontsize=7)
    ax = axes[2]
    s = np.array(sorted(sweep))
    ax.axhspan(0.8, 1.25, color="g", alpha=0.15, label="target band [0.8, 1.25]")
    ax.plot(100 * s, [sweep[v][0].mean() / 2 for v in s], "o-", label="line NEES / 2")
    ax.plot(100 * s, [sweep[v][1].mean() / 3 for v in s], "s-", label="corner NEES / 3")
    for k, sp in sims.items():
        ax.axvline(100 * sp.laser_sigma, color="gray", ls="--" if k == "default" else ":")
        ax.text(100 * sp.laser_sigma, 1.3, f" {k}", fontsize=8, color="gray", rotation=90)
    ax.set(
        title="random errors only: mean NEES / dim (cov_random)",
        xlabel="simulator laser_sigma (cm), plus 5 cm quantisation",
        ylabel="mean NEES / dimension",
    )
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=80)


if __name__ == "__main__":
    main()
