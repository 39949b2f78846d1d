"""The paper's Fig. 3: a right-angle corner fit converging from a deliberately poor initial guess.

Run: python experiments/frontend_corner_convergence.py [--seed 3]
One simulated PLS scan (``fgslam.sim.sensors.laser_scan`` with the simulator's default errors:
Gaussian noise, 5 cm range quantisation, systematic range error) of a concave right-angle
corner 3 m from the laser, whose bisector is turned 20 deg away from the line of sight. The
beams within +-30 deg of the vertex are fitted with ``fit_corner(..., keep_history=True)``
from an initial guess 10 deg, 0.6 m and 30 deg off. Prints the iterations (vertex bearing
phi_c, range r_c, bisector gamma into free space, rms range residual over the beams kept) and
draws the scan points and the corner (two arms) at every iteration in Cartesian coordinates
(laser frame) to frontend_corner_convergence.png next to this file.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from factors.geometry import wrap_angle
from fgslam.config import load_config
from fgslam.frontend.fits import corner_ranges, fit_corner
from fgslam.frontend.pipeline import FrontEnd
from fgslam.sim.sensors import SimParams, laser_scan
from fgslam.sim.world import parse_world

# a concave corner at the origin, free space at x < 0, y < 0; its bisector points to -135 deg
WORLD = {"name": "corner", "walls": [{"id": "c", "points": [[0.0, -6.0], [0.0, 0.0], [-6.0, 0.0]]}]}
BISECTOR = -3 * math.pi / 4
RANGE, OFF_AXIS, BEARING = 3.0, math.radians(20), math.radians(10)  # laser placement
ERROR = (math.radians(10), -0.6, math.radians(30))  # initial guess minus truth
ARM = 1.6  # m of each arm drawn


def arms(phi_c: float, r_c: float, gamma: float) -> np.ndarray:
    """The corner's two arms from the vertex (gamma: bisector into free space): 3 x 2 points."""
    v = np.array([r_c * math.cos(phi_c), r_c * math.sin(phi_c)])
    a = v + ARM * np.array([math.cos(gamma + math.pi / 4), math.sin(gamma + math.pi / 4)])
    b = v + ARM * np.array([math.cos(gamma - math.pi / 4), math.sin(gamma - math.pi / 4)])
    return np.array([a, v, b])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args()
    cfg = load_config()
    world = parse_world(WORLD, "<corner>")
    # the laser RANGE m from the vertex along the bisector turned by OFF_AXIS, looking so that
    # the vertex is at bearing BEARING in the scan
    ang = BISECTOR + OFF_AXIS
    px, py = RANGE * math.cos(ang), RANGE * math.sin(ang)
    th = math.atan2(-py, -px) - BEARING
    truth = np.array([BEARING, RANGE, wrap_angle(BISECTOR - th)])  # laser frame
    rng = np.random.default_rng(args.seed)
    r = laser_scan(world, cfg.laser, SimParams(), (px, py, th), 0.0, rng)
    phi = cfg.laser.bearings
    sel = (np.abs(phi - truth[0]) <= math.radians(30)) & np.isfinite(r)
    p, rr = phi[sel], r[sel]
    init = truth + np.array(ERROR)
    init_paper = (init[0], init[1], init[2] - math.pi)  # fit_corner's guess: paper's gamma
    fit = fit_corner(
        p,
        rr,
        init_paper,
        cfg.laser.sigma_range,
        FrontEnd(cfg, "laser")._systematic(rr),
        keep_history=True,
    )

    print(
        f"corner: truth phi_c {math.degrees(truth[0]):.2f} deg, r_c {truth[1]:.3f} m, "
        f"gamma {math.degrees(truth[2]):.2f} deg; {p.size} beams (+-30 deg), seed {args.seed}"
    )
    print("| iteration | phi_c (deg) | r_c (m) | gamma (deg) | rms (m) | beams kept |")
    print("|-----------|-------------|---------|-------------|---------|------------|")
    params = []
    for k, b in enumerate(fit.history):
        pred = corner_ranges(b, p)[0]
        kept = (pred > 0) & (pred <= 2 * rr)
        rms = float(np.sqrt(np.mean((rr - pred)[kept] ** 2))) if kept.any() else math.nan
        g = wrap_angle(b[2] + math.pi)  # the project's gamma: bisector into free space
        params.append((b[0], b[1], g))
        print(
            f"| {k:9d} | {math.degrees(b[0]):11.2f} | {b[1]:7.3f} | {math.degrees(g):11.2f} "
            f"| {rms:7.4f} | {int(kept.sum()):10d} |"
        )
    sd = np.sqrt(np.diag(fit.cov))
    err = fit.params - truth
    err[0], err[2] = wrap_angle(err[0]), wrap_angle(err[2])
    print(
        f"final: {fit.iterations} iterations, error phi_c {math.degrees(err[0]):+.2f} deg, "
        f"r_c {100 * err[1]:+.1f} cm, gamma {math.degrees(err[2]):+.2f} deg; sd (cov incl. "
        f"systematic) {math.degrees(sd[0]):.2f} deg, {100 * sd[1]:.1f} cm, "
        f"{math.degrees(sd[2]):.2f} deg"
    )

    fig, ax = plt.subplots(figsize=(6.5, 6.8))
    x, y = r * np.cos(phi), r * np.sin(phi)
    ax.plot(x, y, ".", color="0.75", ms=3, label="scan points")
    ax.plot(x[sel], y[sel], ".", color="k", ms=4, label="beams fitted")
    cmap = plt.get_cmap("viridis")
    n = len(params)
    for k, b in enumerate(params):
        a = arms(*b)
        if k == 0:
            ax.plot(a[:, 0], a[:, 1], "--", color="tab:orange", lw=2, label="initial guess")
        elif k == n - 1:
            ax.plot(a[:, 0], a[:, 1], "-", color="tab:red", lw=2.5, label=f"iteration {k} (final)")
        else:
            ax.plot(a[:, 0], a[:, 1], "-", color=cmap(k / n), lw=1.2, label=f"iteration {k}")
        colour = "tab:orange" if k == 0 else ("tab:red" if k == n - 1 else cmap(k / n))
        ax.plot(a[1, 0], a[1, 1], "o", color=colour, ms=4)
    ax.plot(0, 0, "k^", ms=9, label="laser")
    ax.set(
        aspect="equal",
        xlabel="x (m, laser frame)",
        ylabel="y (m)",
        title="Right-angle corner fit from a poor initial guess (paper Fig. 3)",
    )
    ax.set(xlim=(-0.3, 3.7), ylim=(-1.3, 2.7))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(Path(__file__).with_suffix(".png"), dpi=90)


if __name__ == "__main__":
    main()
