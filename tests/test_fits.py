"""Polar line and corner fits against known geometry, Monte Carlo covariances, rejections."""

from __future__ import annotations

import math

import numpy as np
import pytest

from factors.geometry import wrap_angle
from factors.sensor_models import quantum_common_sigma
from fgslam.frontend.fits import (
    RESIDUAL_TEST,
    TRIM_MAX_BEAMS,
    FitRejected,
    corner_ranges,
    fit_corner,
    fit_line,
    line_ranges,
    with_common_error,
)

PHI = np.radians(np.arange(-90, 90.01, 0.5))


SPAN = math.radians(25)


def check_monte_carlo(trials, rtol, nees_range):
    """``trials``: (error, the fit's stated covariance) per Monte Carlo trial. The errors'
    sample sigmas match the stated ones (the last fit's) within ``rtol``, and the mean
    normalised squared error lies strictly inside ``nees_range``."""
    S = np.cov(np.array([e for e, _ in trials]).T)
    cov = trials[-1][1]
    np.testing.assert_allclose(np.sqrt(np.diag(S)), np.sqrt(np.diag(cov)), rtol=rtol)
    nees = [e @ np.linalg.solve(c, e) for e, c in trials]
    assert nees_range[0] < np.mean(nees) < nees_range[1]


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
    trials = []
    for _ in range(600):
        fit = fit_line(p, r0 + rng.normal(0, 0.02, p.size), 0.02, residual_test=None)
        trials.append((fit.params - [-0.5, 2.5], fit.cov_random))
    check_monte_carlo(trials, 0.1, (1.7, 2.3))


def test_quantum_common_sigma_by_monte_carlo():
    """The mean rounding error over the noise, b(x), as a function of where the true range
    falls between quanta: its RMS over x against the formula (noise well below, near and
    above half a quantum)."""
    rng = np.random.default_rng(5)
    q = 0.05
    x = rng.uniform(0, q, 400)
    for sigma_n in (0.005, 0.0138, 0.03):
        n = rng.normal(0, sigma_n, (4000, 1))
        b = (np.round((x + n) / q) * q - x).mean(axis=0)
        se = 0.5 * sigma_n / math.sqrt(4000)  # sampling noise of each b(x), roughly
        want = quantum_common_sigma(q, math.sqrt(sigma_n**2 + q * q / 12))
        got = math.sqrt(max(np.mean(b**2) - se**2, 0.0))
        assert got == pytest.approx(want, rel=0.05, abs=3e-4), (sigma_n, got, want)
    assert quantum_common_sigma(0.01, 0.01) == 0.0  # a SICK LMS: the noise dithers it away


def test_quantised_wall_head_on_covariance_by_monte_carlo():
    """A wall faced head-on (its ranges within one quantum across the fit), ranges with noise
    rounded to 5 cm (the PLS): the line's d carries the rounding every beam shares. With the
    common term its covariance holds the errors; without, it is overconfident."""
    rng = np.random.default_rng(2)
    q, sigma = 0.05, 0.02  # sigma: the PLS's total random error, quantum included
    sigma_n = math.sqrt(sigma**2 - q * q / 12)
    p = PHI[np.abs(PHI) < math.radians(6)]
    common = quantum_common_sigma(q, sigma)
    with_term, without = [], []
    for _ in range(600):
        d = rng.uniform(2.0, 3.0)
        r = np.round((line_ranges(0.0, d, p) + rng.normal(0, sigma_n, p.size)) / q) * q
        fit = fit_line(p, r, sigma, sources=[np.ones(p.size), r])
        e = fit.params - [0.0, d]
        e[0] = wrap_angle(e[0])
        with_term.append((e, with_common_error(fit, common).cov_random))
        without.append((e, fit.cov_random))
    nees = [np.mean([e @ np.linalg.solve(c, e) for e, c in t]) for t in (with_term, without)]
    z2_d = [np.mean([e[1] ** 2 / c[1, 1] for e, c in t]) for t in (with_term, without)]
    assert 1.7 < nees[0] < 2.3 and 0.85 < z2_d[0] < 1.15, (nees, z2_d)
    assert z2_d[1] > 1.15, z2_d  # without: d overconfident (1.24)


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
    trials = []
    for _ in range(500):
        fit = fit_corner(
            p, r0 + rng.normal(0, 0.02, p.size), truth + np.array([0.05, 0.1, -0.1]), 0.02
        )
        e = fit.params - [truth[0], truth[1], truth[2] + math.pi]
        e[2] = wrap_angle(e[2])
        trials.append((e, fit.cov_random))
    check_monte_carlo(trials, 0.12, (2.6, 3.4))


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


# ------------------------------------------------------------------ the fit's own residual


def test_residual_scale_rule():
    """Consistent residuals keep the covariance; residuals 3 sigma wide scale it by their
    dof-corrected variance (sum r^2 / (n - p)) / sigma^2."""
    from fgslam.frontend.fits import residual_scale

    rng = np.random.default_rng(3)
    ok = rng.normal(0, 0.02, 60)
    assert residual_scale(ok, 2, 0.02, 0.99) == 1.0
    wide = rng.normal(0, 0.06, 60)
    assert residual_scale(wide, 2, 0.02, 0.99) == pytest.approx(np.sum(wide**2) / 58 / 0.02**2)
    assert residual_scale(wide, 2, 0.02, None) == 1.0
    assert residual_scale(wide[:2], 2, 0.02, 0.99) == 1.0  # no degrees of freedom


def test_planar_wall_covariance_unchanged_non_planar_wall_covered():
    """Monte Carlo over 400 scans of a wall at (alpha, d) = (-0.5, 2.5), range noise sigma
    = 2 cm (the configured value): the covariance is the unscaled one in >= 97 % of the fits
    and the NEES is 2. The same wall with a 4 cm rough surface (non-planar: every point off
    the plane by its own N(0, 4 cm)) under the same configured sigma: without the scaling
    the NEES of the line against the mean plane is about 5 (overconfident); with it, about
    2 (its error covered), and every fit is scaled."""
    rng = np.random.default_rng(11)
    p = PHI[np.abs(PHI + 0.2) < 0.4]
    truth = np.array([-0.5, 2.5])
    r0 = line_ranges(*truth, p)
    c = np.cos(truth[0] - p)

    def run(rough):
        nees, nees_raw, scaled = [], [], 0
        for _ in range(400):
            off = rng.normal(0, rough, p.size) if rough else 0.0
            r = r0 + off / c + rng.normal(0, 0.02, p.size)
            fit = fit_line(p, r, 0.02, residual_test=RESIDUAL_TEST)
            raw = fit_line(p, r, 0.02, residual_test=None)
            e = fit.params - truth
            nees.append(e @ np.linalg.solve(fit.cov_random, e))
            nees_raw.append(e @ np.linalg.solve(raw.cov_random, e))
            scaled += fit.scale > 1
        return np.mean(nees), np.mean(nees_raw), scaled

    n, n_raw, scaled = run(0.0)
    assert scaled <= 12 and 1.7 < n < 2.3 and n == pytest.approx(n_raw, rel=0.02)
    n, n_raw, scaled = run(0.04)
    assert scaled == 400 and n_raw > 4.0 and 1.7 < n < 2.4


def test_corner_covariance_scaled_by_its_residual():
    """A corner on rough walls (3 cm) under sigma 1 cm: the scaled corner covariance covers
    its error (NEES about 3), the unscaled one does not."""
    rng = np.random.default_rng(5)
    b = (0.2, 3.0, 0.15)
    p, r0 = corner_scan(*b)
    nees, nees_raw = [], []
    truth = np.array([0.2, 3.0, wrap_angle(b[2] + math.pi)])
    for _ in range(200):
        r = r0 + rng.normal(0, 0.03, p.size)
        init = np.array(b) + np.array([0.03, 0.05, -0.05])
        fit = fit_corner(p, r, init, 0.01, residual_test=RESIDUAL_TEST)
        raw = fit_corner(p, r, init, 0.01, residual_test=None)
        e = fit.params - truth
        e[0], e[2] = wrap_angle(e[0]), wrap_angle(e[2])
        nees.append(e @ np.linalg.solve(fit.cov_random, e))
        nees_raw.append(e @ np.linalg.solve(raw.cov_random, e))
    assert np.mean(nees_raw) > 6 and 2.4 < np.mean(nees) < 3.8


# ------------------------------------------------------------------ range calibration


def _refit(kind, p, r, init=None):
    if kind == "line":
        return fit_line(p, r, 0.02).params
    return fit_corner(p, r, init, 0.02).params


@pytest.mark.parametrize("kind", ["line", "corner"])
def test_source_jacobian_matches_finite_differences(kind):
    """d params / d (range offset, range scale): refitting the ranges r (1 + s) + o moves
    the parameters by the returned Jacobian times (o, s)."""
    if kind == "line":
        p = PHI[np.abs(PHI - 0.2) < 0.5]
        r, init = line_ranges(0.1, 3.0, p), None
    else:
        truth = np.array([-0.3, 2.5, -0.25])
        p, r = corner_scan(*truth)
        init = truth
    fit = (
        fit_line(p, r, 0.02, sources=[1.0, r])
        if kind == "line"
        else fit_corner(p, r, init, 0.02, sources=[1.0, r])
    )
    J = fit.source_jacobian
    assert J.shape == (len(fit.params), 2)
    for k, (o, s) in enumerate([(1e-4, 0.0), (0.0, 1e-5)]):
        moved = _refit(kind, p, r * (1 + s) + o, init)
        num = (moved - fit.params) / (o + s)
        num[0] = wrap_angle(moved[0] - fit.params[0]) / (o + s)
        np.testing.assert_allclose(num, J[:, k], rtol=1e-3, atol=1e-6)


def test_worst_case_term_is_the_source_jacobians_weighed_by_the_bounds():
    """The paper's worst-case term (added to the diagonal) is (|J_o| o + |J_s| s)^2 with J
    the source Jacobians and (o, s) the configured systematic bounds: one regression."""
    p = PHI[np.abs(PHI + 0.1) < 0.6]
    r = line_ranges(-0.2, 4.0, p)
    fit = fit_line(p, r, 0.02, systematic=[0.01, 0.002 * r], sources=[1.0, r])
    expected = (np.abs(fit.source_jacobian) @ [0.01, 0.002]) ** 2
    np.testing.assert_allclose(np.diag(fit.cov - fit.cov_random), expected, rtol=1e-9)


def test_random_covariance_plus_calibration_covers_a_random_range_bias_monte_carlo():
    """Monte Carlo: a range offset and scale drawn per scan from N(0, diag(1 cm, 0.2 %)^2)
    on top of the random error; the parameters scatter as cov_random + J Sigma J^T."""
    rng = np.random.default_rng(5)
    truth = np.array([0.35, 2.8, 0.3])
    p, r0 = corner_scan(*truth)
    Sc = np.diag([0.01**2, 0.002**2])
    trials = []
    for _ in range(400):
        o, s = rng.multivariate_normal(np.zeros(2), Sc)
        r = r0 * (1 + s) + o + rng.normal(0, 0.02, p.size)
        fit = fit_corner(p, r, truth, 0.02, sources=[1.0, r])
        e = fit.params - [truth[0], truth[1], truth[2] + math.pi]
        e[0], e[2] = wrap_angle(e[0]), wrap_angle(e[2])
        trials.append((e, fit.cov_random + fit.source_jacobian @ Sc @ fit.source_jacobian.T))
    check_monte_carlo(trials, 0.12, (2.6, 3.4))


def test_line_end_trimming_drops_the_next_walls_grazing_beam():
    """A wall seen at grazing angles up to a concave corner, and one beam of the next wall
    6.9 cm off the line (inside the segmentation's perpendicular bound, its range 44 cm
    short): with ``trim_ends`` that end beam is left out and the line is unbiased; without,
    the range fit is pulled by it. Noise-only ends are kept."""
    rng = np.random.default_rng(4)
    p = np.radians(np.arange(-80.0, -9.4, 0.5))  # the wall y = -1.2 ahead of the sensor
    r = line_ranges(-math.pi / 2, 1.2, p) + rng.normal(0, 0.005, p.size)
    x_corner = 1.2 / math.tan(math.radians(9.5))
    phi_b = math.radians(-9.0)  # the next beam hits the wall x = x_corner, 6.9 cm up
    r_b = x_corner / math.cos(phi_b)
    pb, rb = np.append(p, phi_b), np.append(r, r_b)
    plain = fit_line(pb, rb, 0.02)
    trimmed = fit_line(pb, rb, 0.02, trim_ends=4.0)
    assert abs(plain.params[1] - 1.2) > 0.005  # pulled 7 mm by the one grazing beam
    assert abs(trimmed.params[1] - 1.2) < 0.002
    assert not trimmed.used[-1] and trimmed.used[:-1].all()
    clean = fit_line(p, r, 0.02, trim_ends=4.0)
    assert clean.used.all()
    np.testing.assert_allclose(clean.params, fit_line(p, r, 0.02).params)


def test_line_end_trimming_judges_range_residuals():
    """The PLS's noise (1.4 cm) and a vertex beam 2 cm in front of the wall at 15 deg of
    grazing: inside three perpendicular spreads (1.1 cm: a grazing beam's range error is
    mostly along the wall), but its range is 7.8 cm short, 5.5 range sigmas. The fit
    minimises range residuals, so the trimming judges those: the beam is left out in nearly
    every draw and the line's d is unbiased over 300 draws (the beam pulls it 1.3 mm)."""
    rng = np.random.default_rng(8)
    p = np.radians(np.arange(-90.0, -15.2, 0.5))  # the wall y = -1.5, up to the corner
    x_corner = 1.48 / math.tan(math.radians(15.0))  # the next wall: beam -15 deg, 2 cm up
    pb = np.append(p, math.radians(-15.0))
    r0 = np.append(line_ranges(-math.pi / 2, 1.5, p), x_corner / math.cos(math.radians(15.0)))
    dropped, d_trim, d_plain = 0, [], []
    for _ in range(300):
        r = r0 + rng.normal(0, 0.014, r0.size)
        fit = fit_line(pb, r, 0.02, trim_ends=3.0)
        dropped += not fit.used[-1]
        d_trim.append(fit.params[1])
        d_plain.append(fit_line(pb, r, 0.02).params[1])
    assert dropped >= 285, dropped
    assert abs(np.mean(d_trim) - 1.5) < 0.0004, np.mean(d_trim)
    assert abs(np.mean(d_plain) - 1.5) > 0.001, np.mean(d_plain)


def test_line_end_trimming_leaves_out_at_most_two_beams_per_end():
    """The trimming is for the vertex's beam or two that the segmentation hands a line: five
    wild beams at an end lose only the outer two (a segment that bad is the segmentation's
    business), and the beams inside are all kept."""
    rng = np.random.default_rng(2)
    p = np.radians(np.arange(-60.0, 60.0, 0.5))
    r = line_ranges(0.1, 2.0, p) + rng.normal(0, 0.005, p.size)
    r[-5:] -= 0.3
    fit = fit_line(p, r, 0.02, trim_ends=3.0)
    assert TRIM_MAX_BEAMS == 2
    assert not fit.used[-2:].any() and fit.used[:-2].all()
