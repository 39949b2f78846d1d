"""Polar line and corner fits against known geometry, Monte Carlo covariances, rejections."""

from __future__ import annotations

import math

import numpy as np
import pytest

from factors.geometry import wrap_angle
from fgslam.frontend.fits import FitRejected, corner_ranges, fit_corner, fit_line, line_ranges

PHI = np.radians(np.arange(-90, 90.01, 0.5))


SPAN = math.radians(25)


def corner_scan(phi_c, r_c, gamma_p, convex=False, span=SPAN):
    sel = np.abs(PHI - phi_c) < span
    p = PHI[sel]
    return p, corner_ranges((phi_c, r_c, gamma_p), p, convex)[0]


def test_line_fit_exact_and_jacobian():
    sel = np.abs(PHI - 0.3) < 0.5
    p = PHI[sel]
    r = line_ranges(0.4, 3.0, p)
    fit = fit_line(p, r, 0.02)
    np.testing.assert_allclose(fit.params, [0.4, 3.0], atol=1e-9)
    assert fit.rms < 1e-9 and np.all(np.linalg.eigvalsh(fit.cov) > 0)
    # alpha near +-pi: a wall behind-left of a scanner that sees over 360 deg
    p2 = np.linspace(2.9, 3.4, 60)
    fit2 = fit_line(p2, line_ranges(math.pi - 0.01, 2.0, p2), 0.02)
    assert abs(wrap_angle(fit2.params[0] - (math.pi - 0.01))) < 1e-9


def test_line_fit_monte_carlo_covariance():
    rng = np.random.default_rng(1)
    sel = np.abs(PHI + 0.2) < 0.4
    p = PHI[sel]
    r0 = line_ranges(-0.5, 2.5, p)
    errs, nees = [], []
    for _ in range(600):
        fit = fit_line(p, r0 + rng.normal(0, 0.02, p.size), 0.02)
        e = fit.params - [-0.5, 2.5]
        errs.append(e)
        nees.append(e @ np.linalg.solve(fit.cov_random, e))
    S = np.cov(np.array(errs).T)
    np.testing.assert_allclose(np.sqrt(np.diag(S)), np.sqrt(np.diag(fit.cov_random)), rtol=0.1)
    assert 1.7 < np.mean(nees) < 2.3


def test_line_systematic_term_bounds_a_constant_offset():
    p = PHI[np.abs(PHI - 0.2) < 0.4]
    r0 = line_ranges(0.1, 3.0, p)
    fit = fit_line(p, r0, 0.02, systematic=[0.01])
    shifted = fit_line(p, r0 + 0.01, 0.02)
    actual = np.abs(shifted.params - fit.params)
    added = np.sqrt(np.diag(fit.cov - fit.cov_random))
    np.testing.assert_allclose(added, actual, rtol=0.02, atol=1e-7)


@pytest.mark.parametrize("convex", [False, True])
def test_corner_fit_converges_from_poor_guess(convex):
    truth = (0.2, 3.0, 0.2 + 0.1)
    p, r = corner_scan(*truth, convex=convex)
    fit = fit_corner(p, r, init=(0.35, 2.6, 0.0), sigma_r=0.02, convex=convex, keep_history=True)
    np.testing.assert_allclose(fit.params[:2], truth[:2], atol=1e-7)
    assert abs(wrap_angle(fit.params[2] - (truth[2] + math.pi))) < 1e-7  # into free space
    assert fit.iterations <= 10 and len(fit.history) == fit.iterations + 1


def test_corner_fit_monte_carlo_covariance():
    rng = np.random.default_rng(2)
    truth = np.array([-0.3, 2.5, -0.25])
    p, r0 = corner_scan(*truth)
    errs, nees = [], []
    for _ in range(500):
        fit = fit_corner(
            p, r0 + rng.normal(0, 0.02, p.size), truth + np.array([0.05, 0.1, -0.1]), 0.02
        )
        e = fit.params - [truth[0], truth[1], truth[2] + math.pi]
        e[2] = wrap_angle(e[2])
        errs.append(e)
        nees.append(e @ np.linalg.solve(fit.cov_random, e))
    S = np.cov(np.array(errs).T)
    np.testing.assert_allclose(np.sqrt(np.diag(S)), np.sqrt(np.diag(fit.cov_random)), rtol=0.12)
    assert 2.6 < np.mean(nees) < 3.4


def test_corner_fit_prunes_outlying_beams():
    truth = (0.0, 3.0, 0.0)
    p, r = corner_scan(*truth)
    r = r.copy()
    r[3] = 0.4  # a leg in front: predicted range is > 2x the measured one
    fit = fit_corner(p, r, init=(0.05, 2.9, 0.05), sigma_r=0.02)
    assert not fit.used[3]
    np.testing.assert_allclose(fit.params[:2], truth[:2], atol=1e-6)


def test_corner_fit_rejections():
    p = PHI[np.abs(PHI) < 0.4]
    with pytest.raises(FitRejected) as exc:  # collinear points: a straight wall
        fit_corner(p, line_ranges(0.0, 3.0, p), init=(0.0, 3.0, 0.0), sigma_r=0.02)
    assert exc.value.reason in {
        "ill_conditioned",
        "diverged",
        "no_convergence",
        "not_facing",
        "one_sided",
    }
    with pytest.raises(FitRejected, match="too_few_points"):
        fit_corner(p[:4], np.full(4, 3.0), init=(0.0, 3.0, 0.0), sigma_r=0.02)
    pc, rc = corner_scan(0.0, 3.0, 0.0)
    with pytest.raises(FitRejected, match="one_sided"):
        fit_corner(pc, rc, init=(0.6, 3.0, 0.6), sigma_r=0.02)
    rc = rc.copy()
    rc[::2] = np.nan  # NaN readings are ignored, not propagated
    assert np.all(np.isfinite(fit_corner(pc, rc, (0.0, 3.0, 0.0), 0.02).params))


def test_line_fit_rejections():
    with pytest.raises(FitRejected, match="too_few_points"):
        fit_line([0.1, 0.2], [1.0, 1.0], 0.02)
    with pytest.raises(FitRejected, match="too_few_points"):
        fit_line([0.1, 0.2, 0.3], [1.0, np.nan, 0.0], 0.02)
    with pytest.raises(FitRejected, match="bad_input"):
        fit_line([0.1, 0.2, 0.3], [1.0, 2.0], 0.02)
