"""Polar line and right-angle corner fits to laser ranges, with covariances
(docs/design.md, 3.2-3.3).

Both minimise the sum of squared *range* residuals over the beams (bearings phi_i, rad, in the
laser frame; ranges r_i, m) by Gauss-Newton, and give the covariance sigma_r^2 (H^T H)^-1
plus the paper's worst-case systematic term: each systematic range-error source is propagated
through the same regression, the absolute contributions are summed, squared and added to the
diagonal. Where the fit's own residual exceeds sigma_r beyond chance (a chi-square test at
:data:`RESIDUAL_TEST`), sigma_r^2 is replaced by the residual variance with the
degrees-of-freedom correction (:func:`residual_scale`): a wall that is not planar is not a
confident line.

A fit that cannot be trusted raises :class:`FitRejected` with a short reason code, which the
front end counts in its per-scan statistics; nothing else escapes.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.geometry import wrap_angle
from factors.line import normalize_line
from fgslam.frontend import kernels


class FitRejected(Exception):
    """A fit was rejected; ``reason`` is a short code for statistics."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


@dataclass
class Fit:
    """Fitted parameters, their covariance (random only and with systematic errors added),
    the iterations used, the rms range residual (m), the beams kept, and (on request) the
    parameter history of every iteration."""

    params: NDArray[np.float64]
    cov: NDArray[np.float64]
    cov_random: NDArray[np.float64]
    iterations: int
    rms: float
    used: NDArray[np.bool_]
    history: list[NDArray[np.float64]] = field(default_factory=list)
    scale: float = 1.0  # variance factor from the fit's own residual (residual_scale)
    # d params / d s for each unit range-error source s of ``sources`` (one column each)
    source_jacobian: NDArray[np.float64] | None = None


def with_common_error(fit: Fit, sigma: float) -> Fit:
    """``fit`` with a range error of RMS ``sigma`` (m) shared by all its beams (the range
    quantum's, :func:`factors.sensor_models.quantum_common_sigma`) added to both its
    covariances: sigma^2 j j^T, j its parameters' response to 1 m on every range (the first
    column of :attr:`Fit.source_jacobian`: the fit's ``sources`` must start with the unit
    offset). Unchanged without sources or for sigma 0."""
    J = fit.source_jacobian
    if not sigma or J is None:
        return fit
    j = J[:, 0]
    add = sigma * sigma * np.outer(j, j)
    return dataclasses.replace(fit, cov=fit.cov + add, cov_random=fit.cov_random + add)


def _prepare(phi: ArrayLike, r: ArrayLike, min_points: int):
    phi = np.asarray(phi, dtype=float)
    r = np.asarray(r, dtype=float)
    if phi.shape != r.shape or phi.ndim != 1:
        raise FitRejected("bad_input", "bearings and ranges must be 1-D and of equal length")
    ok = np.isfinite(phi) & np.isfinite(r) & (r > 0)
    if ok.sum() < min_points:
        raise FitRejected("too_few_points", f"{int(ok.sum())} valid points")
    return phi, r, ok


RESIDUAL_TEST = 0.99  # a chi-square level for residual_test (the readers' configurations)


def residual_scale(res: ArrayLike, n_params: int, sigma_r: float, level: float | None) -> float:
    """Variance factor of a fit's random covariance from its own residuals ``res`` (m):
    ``s^2 / sigma_r^2`` with ``s^2 = sum(res^2) / (n - n_params)`` (the degrees-of-freedom
    correction) when the residual exceeds the configured sigma beyond chance, i.e. when
    ``sum(res^2) / sigma_r^2`` exceeds the ``level`` quantile of chi-square with n - n_params
    degrees of freedom; else 1 (a fit consistent with the range model keeps its covariance).
    ``level`` None: always 1."""
    res = np.asarray(res, dtype=float)
    return _residual_scale(float(np.sum(res * res)), res.size, n_params, sigma_r, level)


def _residual_scale(ssq: float, n: int, n_params: int, sigma_r: float, level: float | None):
    """:func:`residual_scale` from the sum ``ssq`` of the ``n`` squared residuals."""
    dof = n - n_params
    if level is None or dof <= 0:
        return 1.0
    q = ssq / sigma_r**2
    if q <= _chi2_quantile(level, dof):
        return 1.0
    return q / dof


@functools.cache
def _chi2_quantile(level: float, dof: int) -> float:
    """scipy's chi-square quantile, remembered (0.3 ms a call, several calls per scan)."""
    from scipy.stats import chi2

    return float(chi2.ppf(level, dof))


def _covariances(H, sigma_r, systematic, used, scale=1.0, sources=()):
    """scale sigma_r^2 (H^T H)^-1, that plus the systematic worst case on the diagonal, and
    the parameters' Jacobian (H^T H)^-1 H^T e w.r.t. each unit source e of ``sources``
    (None without sources)."""
    HtH = H.T @ H
    cond = np.linalg.cond(HtH)
    if not np.isfinite(cond) or cond > 1e12:
        raise FitRejected("ill_conditioned", f"condition number {cond:.3g}")
    inv = np.linalg.inv(HtH)
    cov_random = scale * sigma_r**2 * inv
    sys_sum = np.zeros(H.shape[1])
    for e in systematic:
        e = np.broadcast_to(np.asarray(e, dtype=float), used.shape)[used]
        sys_sum += np.abs(inv @ (H.T @ e))
    J = None
    if len(sources):
        E = np.column_stack(
            [np.broadcast_to(np.asarray(e, dtype=float), used.shape)[used] for e in sources]
        )
        J = inv @ (H.T @ E)
    return cov_random + np.diag(sys_sum**2), cov_random, J


# ------------------------------------------------------------------ lines


def line_ranges(alpha: float, d: float, phi: NDArray[np.float64]) -> NDArray[np.float64]:
    """Ranges (m) at bearings phi of the line (alpha, d): r = d / cos(alpha - phi)."""
    return d / np.cos(alpha - phi)


def tls_line(x: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[float, float]:
    """Total-least-squares (alpha, d >= 0) of Cartesian points."""
    mx, my = x.mean(), y.mean()
    sxx, syy, sxy = ((x - mx) ** 2).sum(), ((y - my) ** 2).sum(), ((x - mx) * (y - my)).sum()
    return _tls_of_moments(mx, my, sxx, syy, sxy)


def _tls_of_moments(mx: float, my: float, sxx: float, syy: float, sxy: float):
    """:func:`tls_line` from the points' means and centred second moments (sums)."""
    alpha = 0.5 * math.atan2(-2 * sxy, syy - sxx)
    d = mx * math.cos(alpha) + my * math.sin(alpha)
    return normalize_line(alpha, d)


# the most beams line-end trimming leaves out at either end: the segmentation gives the beams
# next to a vertex to the segment scanned first, one or two of them
TRIM_MAX_BEAMS = 2


def fit_line(
    phi: ArrayLike,
    r: ArrayLike,
    sigma_r: float,
    systematic: Sequence[ArrayLike] = (),
    max_iter: int = 10,
    residual_test: float | None = None,
    sources: Sequence[ArrayLike] = (),
    trim_ends: float | None = None,
) -> Fit:
    """Fit (alpha, d) to laser points by minimising squared range residuals.

    ``systematic``: per-source systematic range errors (m), each a scalar or one per beam.
    ``sources``: unit range-error sources (m per unit, e.g. 1 for an offset and r for a
    scale), each a scalar or one per beam, whose Jacobians the fit returns
    (:attr:`Fit.source_jacobian`). ``trim_ends``: beams at either end of the segment whose
    range residual to the fitted line exceeds this many times the residuals' robust spread
    (1.4826 MAD, at least 1 mm) are left out and the line refitted, then judged once more
    against the refitted line (the segmentation bounds the perpendicular distance, so a line
    may end with a grazing beam of the next wall, its range tens of cm off, which a range fit
    weighs by its range: ``Fit.used`` marks the beams kept).
    ``residual_test``: a chi-square level (e.g. :data:`RESIDUAL_TEST`), see
    :func:`residual_scale` (a wall that is not planar, or noisier than ``sigma_r``, gets the
    covariance of its own residual); None (default): the range model alone.
    Raises :class:`FitRejected` (too few points, a line through the sensor, no convergence).
    """
    phi, r, ok = _prepare(phi, r, 3)
    fit = _fit_line_once(phi, r, ok, sigma_r, systematic, max_iter, residual_test, sources)
    if trim_ends is None:
        return fit
    # the first and last beam (among ok) whose range residual is within the bound (the
    # numpy reference: _trim_bounds_numpy), judged again against the refitted line, which
    # the end beams no longer pull (grazing beams of the wall itself come back)
    idx = np.flatnonzero(ok)
    kept = (0, idx.size - 1)
    for _ in range(2):
        a, d = fit.params
        lo, hi, inside, n = kernels.trim_bounds(phi, r, ok, float(a), float(d), float(trim_ends))
        lo, hi = min(lo, TRIM_MAX_BEAMS), max(hi, n - 1 - TRIM_MAX_BEAMS)
        if inside < 3 or (lo, hi) == kept:
            break
        kept = (lo, hi)
        use = np.zeros_like(ok)
        use[idx[lo : hi + 1]] = True
        fit = _fit_line_once(phi, r, use, sigma_r, systematic, max_iter, residual_test, sources)
    return fit


def _trim_bounds_numpy(phi, r, ok, a, d, trim_ends) -> tuple[int, int, int, int]:
    """The reference of :func:`fgslam.frontend.kernels.trim_bounds`."""
    idx = np.flatnonzero(ok)
    c = np.cos(a - phi[idx])
    with np.errstate(divide="ignore"):
        e = np.where(c > 0.0, r[idx] - d / np.where(c > 0.0, c, 1.0), np.inf)  # range residuals, m
    spread = 1.4826 * float(np.median(np.abs(e - np.median(e))))
    spread = spread if math.isfinite(spread) else 0.0
    inside = np.flatnonzero(np.abs(e) <= trim_ends * max(spread, 1e-3))
    if inside.size == 0:
        return -1, -1, 0, idx.size
    return int(inside[0]), int(inside[-1]), int(inside.size), idx.size


def _rows(cols: Sequence[ArrayLike], n: int) -> NDArray[np.float64]:
    """Each of ``cols`` (a scalar or one per beam) on the ``n`` beams: a (len(cols), n)
    array."""
    out = np.empty((len(cols), n))
    for k, e in enumerate(cols):
        out[k] = e
    return out


def _fit_line_once(phi, r, ok, sigma_r, systematic, max_iter, residual_test, sources) -> Fit:
    """:func:`fit_line` on the beams ``ok``, compiled (:func:`fgslam.frontend.kernels.line_fit`;
    the reference: :func:`_fit_line_once_numpy`, which also takes the steps the kernel hands
    back)."""
    alpha, d = _tls_of_moments(*kernels.ok_sums(phi, r, ok))
    if d < 1e-3:
        raise FitRejected("through_sensor", "the line passes through the sensor")
    S, E = _rows(systematic, ok.size), _rows(sources, ok.size)
    try:
        out = kernels.line_fit(phi, r, ok, alpha, d, max_iter, S, E)
    except np.linalg.LinAlgError:  # LAPACK failed: the reference says how
        out = (kernels.FIT_FALLBACK,)
    if out[0] == kernels.FIT_FALLBACK:
        return _fit_line_once_numpy(
            phi, r, ok, sigma_r, systematic, max_iter, residual_test, sources
        )
    outcome, alpha, d, it, n, ssq, HtH, inv, sys_sum, J = out
    if outcome == kernels.FIT_GRAZING:
        raise FitRejected("grazing", "a beam runs (almost) parallel to the line")
    if outcome == kernels.FIT_NO_CONVERGENCE:
        raise FitRejected("no_convergence", f"{max_iter} iterations")
    if d <= 0:
        raise FitRejected("through_sensor", "the fitted line passes behind the sensor")
    scale = _residual_scale(ssq, n, 2, sigma_r, residual_test)
    # the 2x2 condition number from the eigenvalues; numpy's (an SVD) where it may matter
    (a00, a01), (_, a11) = HtH.tolist()
    lmax = 0.5 * (a00 + a11) + math.hypot(0.5 * (a00 - a11), a01)
    det = a00 * a11 - a01 * a01
    if not (lmax > 0 and det > 0 and lmax * lmax < 1e11 * det):
        cond = np.linalg.cond(HtH)
        if not np.isfinite(cond) or cond > 1e12:
            raise FitRejected("ill_conditioned", f"condition number {cond:.3g}")
    cov_random = scale * sigma_r**2 * inv
    cov = cov_random + np.diag(sys_sum**2)
    rms = float(np.sqrt(ssq / n))
    params = np.array([wrap_angle(alpha), d])
    J = J if len(sources) else None
    return Fit(params, cov, cov_random, it, rms, ok, scale=scale, source_jacobian=J)


def _fit_line_once_numpy(phi, r, ok, sigma_r, systematic, max_iter, residual_test, sources) -> Fit:
    """:func:`fit_line` on the beams ``ok``: the numpy reference of :func:`_fit_line_once`."""
    p, rr = phi[ok], r[ok]
    alpha, d = tls_line(rr * np.cos(p), rr * np.sin(p))
    if d < 1e-3:
        raise FitRejected("through_sensor", "the line passes through the sensor")
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - 'it' is reported in the result
        c = np.cos(alpha - p)
        if np.any(c <= 0.02):
            raise FitRejected("grazing", "a beam runs (almost) parallel to the line")
        pred = d / c
        H = np.column_stack([d * np.sin(alpha - p) / c**2, 1.0 / c])
        step, *_ = np.linalg.lstsq(H, rr - pred, rcond=None)
        alpha, d = alpha + step[0], d + step[1]
        if abs(step[0]) < 1e-8 and abs(step[1]) < 1e-7:  # far below any line's uncertainty
            break
    else:
        raise FitRejected("no_convergence", f"{max_iter} iterations")
    if d <= 0:
        raise FitRejected("through_sensor", "the fitted line passes behind the sensor")
    c = np.cos(alpha - p)
    H = np.column_stack([d * np.sin(alpha - p) / c**2, 1.0 / c])
    res = rr - d / c
    scale = residual_scale(res, 2, sigma_r, residual_test)
    cov, cov_random, J = _covariances(H, sigma_r, systematic, ok, scale, sources)
    rms = float(np.sqrt(np.mean(res**2)))
    params = np.array([wrap_angle(alpha), d])
    return Fit(params, cov, cov_random, it, rms, ok, scale=scale, source_jacobian=J)


# ------------------------------------------------------------------ corners


def corner_ranges(
    b: ArrayLike, phi: NDArray[np.float64], convex: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Paper eq 8: ranges at bearings phi of the corner b = (phi_c, r_c, gamma_p), and the
    Jacobian H (eqs 10-12, with the pi/4 of the erratum and the exact d r_i / d r_c).

    ``gamma_p`` is the paper's bisector angle: the walls' normals are gamma_p +- pi/4 (it
    points away from the sensor); a convex corner swaps which wall lies on which side.
    """
    phi_c, r_c, g = b
    s = np.sign(phi - phi_c)
    s[s == 0] = 1.0
    if convex:
        s = -s
    A = g + s * (math.pi / 4)
    cc, ci = np.cos(A - phi_c), np.cos(A - phi)
    pred = r_c * cc / ci
    H = np.column_stack([r_c * np.sin(A - phi_c) / ci, cc / ci, r_c * np.sin(phi_c - phi) / ci**2])
    return pred, H


def fit_corner(
    phi: ArrayLike,
    r: ArrayLike,
    init: ArrayLike,
    sigma_r: float,
    systematic: Sequence[ArrayLike] = (),
    convex: bool = False,
    max_iter: int = 20,
    keep_history: bool = False,
    residual_test: float | None = None,
    sources: Sequence[ArrayLike] = (),
) -> Fit:
    """Fit a right-angle corner by iterated linear regression (paper eqs 13-19).

    ``init`` = (phi_c, r_c, gamma_p) is the starting guess in the paper's convention. At each
    iteration beams whose predicted range is negative or more than twice the measured range
    are dropped. The result's ``params`` are (phi_c, r_c, gamma) in the project's convention:
    gamma = gamma_p + pi, the bisector pointing from the vertex into free space.
    ``systematic``, ``sources``: as :func:`fit_line`.
    Raises :class:`FitRejected` (too few points on a side, divergence, ill-conditioning).
    """
    phi, r, ok = _prepare(phi, r, 5)
    b = np.array(init, dtype=float)
    history = [b.copy()] if keep_history else []

    def cost(bb: NDArray[np.float64]) -> float:
        # pruned beams count as a residual of their own range: a capped, continuous cost
        pr = corner_ranges(bb, phi, convex)[0][ok]
        res = np.where((pr > 0) & (pr <= 2 * r[ok]), r[ok] - pr, r[ok])
        return float(np.sum(np.minimum(res * res, r[ok] ** 2)))

    c0 = cost(b)
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - 'it' is reported in the result
        pred, H = corner_ranges(b, phi, convex)
        used = ok & (pred > 0) & (pred <= 2 * r) & np.isfinite(pred)
        left, right = used & (phi > b[0]), used & (phi < b[0])
        if left.sum() < 2 or right.sum() < 2:
            raise FitRejected("one_sided", "fewer than 2 beams on a side of the vertex")
        Hu = H[used]
        step, *_ = np.linalg.lstsq(Hu, (r - pred)[used], rcond=None)
        # the model is only piecewise smooth (a beam changes wall when the vertex passes it):
        # halve steps that do not lower the cost, and stop at a kink
        for _ in range(12):
            c1 = cost(b + step)
            if c1 <= c0 or not np.isfinite(c1):
                break
            step = step / 2
        b = b + step
        if keep_history:
            history.append(b.copy())
        if not (np.all(np.isfinite(b)) and b[1] > 0):
            raise FitRejected("diverged", "corner range went non-positive")
        try:
            sd = sigma_r * np.sqrt(np.diag(np.linalg.inv(Hu.T @ Hu)))
        except np.linalg.LinAlgError:
            raise FitRejected("ill_conditioned", "singular normal equations") from None
        if float(np.max(np.abs(step) / np.maximum(sd, 1e-12))) < 1e-3:
            break
        c0 = min(c0, c1)
    else:
        raise FitRejected("no_convergence", f"{max_iter} iterations")
    pred, H = corner_ranges(b, phi, convex)
    used = ok & (pred > 0) & (pred <= 2 * r)
    if abs(wrap_angle(b[2] - b[0])) > math.pi / 4:
        raise FitRejected("not_facing", "a wall of the corner faces away from the sensor")
    res = (r - pred)[used]
    scale = residual_scale(res, 3, sigma_r, residual_test)
    cov, cov_random, J = _covariances(H[used], sigma_r, systematic, used, scale, sources)
    rms = float(np.sqrt(np.mean(res**2)))
    params = np.array([wrap_angle(b[0]), b[1], wrap_angle(b[2] + math.pi)])
    return Fit(params, cov, cov_random, it, rms, used, history, scale, J)
