"""The response's other basins: ICP from each (a periodic scene has several of similar
score), one run per basin, compared with the best's by their point-to-line costs over the
points both match."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from factors.geometry import rot, wrap_angle, wrap_angles
from fgslam.config.robot import MatchParams
from fgslam.scanmatch.icp import _correspond, _Icp, _icp
from fgslam.scanmatch.reference import Reference
from fgslam.scanmatch.search import _Response


def _other_basins(
    ref: Reference,
    q: NDArray,
    g: NDArray,
    icp: _Icp,
    resp: _Response,
    seed_poses: NDArray,
    params: MatchParams,
) -> tuple[list[tuple[_Icp, float, float]], NDArray[np.bool_]]:
    """ICP from the response's other basins: ``seed_poses`` (:func:`_seeds`; the first is
    the best's, whose run is ``icp``), ``g`` the guess, ``resp`` the response's poses within
    ``mode_nats``. Returns, for each other basin whose run ends inside the window at a pose of
    its own with enough points in common: the run, its cost minus the best's and that
    difference's standard deviation (:func:`_dcost`); and which of ``resp``'s poses lie in
    those basins (within 3 cells and 3 rotation steps of the start): they no longer count on
    their own."""
    res = params.resolution
    alts: list[tuple[_Icp, float, float]] = []
    owned = np.zeros(len(resp.poses), dtype=bool)
    if len(seed_poses) > 1 and len(icp.r) >= 6:
        qr = q @ rot(float(g[2])).T + g[:2]
        use = ref.covered(qr, params.search_theta, params.search_xy)
        qc = q[use] if use.sum() >= max(params.min_coverage * len(q), 3) else q
        s2_0 = max(params.sigma_range**2, float(icp.r @ icp.r) / max(len(icp.r) - 3, 1))
        runs = [(icp, _costs(ref, qc, icp.pose, s2_0, params), 0)]
        for k in range(1, len(seed_poses)):
            # a run that settles next to a basin already found is that basin: stopped there
            # (_same would drop it at the end)
            done = np.array([a.pose for a, _, _ in runs])
            alt = _icp(ref, q, seed_poses[k], params, (done, 0.5 * res, 0.5 * resp.step))
            # one run per basin (the first, by score), and only inside the window
            if (
                alt is not None
                and len(alt.r) >= 6
                and _inside(alt.pose, g, params, res, resp.step)
                and not any(_same(alt.pose, a.pose, res, resp.step) for a, _, _ in runs)
            ):
                runs.append((alt, _costs(ref, qc, alt.pose, s2_0, params), k))
        c0 = runs[0][1]
        for a, c, k in runs[1:]:
            dc, sd = _dcost(c, c0)
            if not math.isfinite(sd):
                continue  # too few common points: the response speaks for it
            alts.append((a, dc, sd))
            # the response's poses in this basin stand for it no more
            dd = resp.poses - seed_poses[k]
            dd[:, 2] = wrap_angles(dd[:, 2])
            owned |= (np.hypot(dd[:, 0], dd[:, 1]) <= 3 * res) & (np.abs(dd[:, 2]) <= 3 * resp.step)
    return alts, owned


def _seeds(resp: _Response, res: float, most: int) -> list[int]:
    """Indices of up to ``most`` response poses, best first, each more than 3 cells or 3
    rotation steps from every one before it: one start per basin."""
    out: list[int] = []
    if most <= 0 or len(resp.scores) == 0:
        return out
    for k in np.argsort(-resp.scores, kind="stable"):
        p = resp.poses[k]
        far = True
        for j in out:
            d = p - resp.poses[j]
            if np.hypot(d[0], d[1]) <= 3 * res and abs(wrap_angle(float(d[2]))) <= 3 * resp.step:
                far = False
                break
        if far:
            out.append(int(k))
            if len(out) >= most:
                break
    return out


def _same(a: NDArray, b: NDArray, res: float, step: float) -> bool:
    """Whether two ICP results are one basin: within 2 cells and 2 rotation steps."""
    d = a - b
    return bool(np.hypot(d[0], d[1]) <= 2 * res and abs(wrap_angle(float(d[2]))) <= 2 * step)


def _inside(pose: NDArray, guess: NDArray, params: MatchParams, res: float, step: float) -> bool:
    """Whether ``pose`` lies in the search window around ``guess`` (a cell, a step of margin)."""
    d = pose - guess
    return bool(
        max(abs(d[0]), abs(d[1])) <= params.search_xy + res
        and abs(wrap_angle(float(d[2]))) <= params.search_theta + step
    )


def _costs(ref: Reference, q: NDArray, pose: NDArray, s2: float, params: MatchParams) -> NDArray:
    """Per query point at ``pose``: its point-to-line r^2 / s2, capped at
    ``inlier_sigmas``^2; NaN where it has no correspondence."""
    _, idx, _, _, r = _correspond(ref, q, pose, params)
    out = np.full(len(q), np.nan)
    out[idx] = np.minimum(r**2 / s2, params.inlier_sigmas**2)
    return out


def _dcost(a: NDArray, b: NDArray) -> tuple[float, float]:
    """Cost of ``a`` minus that of ``b`` over the points both matched (a point matched at
    one pose only says as much about the sampling of far, grazing surfaces as about the
    pose), and the standard deviation of that sum from the spread of the per-point
    differences (paired: how much of it the residuals' own noise explains; NaN below 6
    common points)."""
    both = np.isfinite(a) & np.isfinite(b)
    d = a[both] - b[both]
    if len(d) < 6:
        return 0.0, math.nan
    return float(d.sum()), math.sqrt(len(d) * float(np.var(d, ddof=1)))
