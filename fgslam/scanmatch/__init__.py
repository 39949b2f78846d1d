"""2-D laser scan matching: correlative search (branch and bound over max-pooled likelihood
grids) followed by point-to-line ICP, with an honest covariance and a rejection rule.

Frames and units: the reference points are in the *reference* frame, the query points in the
*query* frame (both m, usually a robot frame: see :func:`scan_points`). A pose (x, y, theta)
is T_ref_query: the query frame's origin and heading in the reference frame (m, rad).

Pipeline of :func:`match` (docs/design.md, 5b):

1. **Correlative search** (Olson 2009, Hess et al. 2016 "Cartographer"): the reference is
   rasterised (points joined to their nearest neighbours within ``link_distance``) into a
   likelihood grid g = exp(-d^2 / 2 s^2), cut at 3 s (d: distance to the reference, s:
   ``blur``); the score of a pose is the mean of g over the voxel-filtered query points, in
   [0, 1]. Every rotation of the window is tried (step: a cell at the far range); for each,
   translations are searched by branch and bound over grids max-pooled over 2^l x 2^l cells
   (a bound on every translation of a block), evaluated level by level for all surviving
   blocks at once. Every pose within ``mode_nats`` / N of the best score survives: the
   response surface. With the reference's sensor origins (:meth:`Reference.build`), only
   the query points that fall where the reference's beams looked are scored, which removes
   the bias towards more overlap (along a corridor).
2. **Point-to-line ICP** from the best pose: nearest reference point (cKDTree) within
   ``corr_distance``, the residual along its local line (PCA of its neighbours within
   ``normal_radius``: normal and centroid), Cauchy weights on a MAD scale, Gauss-Newton in
   the query's body tangent (GTSAM's Pose2 retract). ICP also starts from up to
   ``max_basins`` - 1 other basins of the response (poses within ``basin_nats`` / N of the
   best score, more than 3 cells or 3 rotation steps apart, ending inside the window):
   the correlative score on its grid is only a proxy, and a periodic scene (doors along a
   corridor) has several basins of similar score. The results are compared by their cost
   sum min(r^2 / s2, ``inlier_sigmas``^2) over the query points both match (a point matched
   at one pose only, far on a grazing wall, says as much about the sampling as about the
   pose). The estimate stays the best correlative basin's: the others only widen its
   covariance (3.). Taking the lowest cost instead broke the MIT map (relations 0.037 ->
   0.043 m, max 0.35 -> 2.6 m).
3. **Covariance**, body tangent at the estimate (GTSAM's BetweenFactorPose2 convention;
   ``cov_ref`` in the reference's axes):

   - H = sum J J^T over the inliers, minus what the noise of the reference normals adds to
     it (sum var(alpha) Jt Jt^T, Jt: the Jacobian along the line): along a featureless wall
     noisy normals otherwise fake information. var(alpha) is the PCA line's: scatter across
     the line over the spread along it, the scatter never below ``sigma_range``^2 (the
     PLS's 5 cm quantum makes a straight wall a staircase whose local fits look straighter,
     and tilted, than they are: in the simulated corridor those tilts of 3-6 deg were the
     only information along it, and matches slid by 0.3 m a scan).
   - s2 = residual variance (sum r^2 / (m - 3)), never below ``sigma_range``^2.
   - kappa, per axis = ``cov_inflation`` * max(1, S_ii / (s2 H_ii)), S the Newey-West (HAC,
     ``hac_lags`` beams, Bartlett) covariance of the gradient sum J r in beam order:
     correlated errors of neighbouring beams, measured on each match. ``cov_inflation`` =
     1.3 is the rest, measured: Monte Carlo over simulated PLS scans gives mean NEES 3.9
     (lab) and 4.7 (corridor) with 1.0 (experiments/scanmatch_consistency.py); the reference
     scan's own noise, shared by neighbouring query points, is what the residuals miss.
   - cov_icp = (K^-1/2 H K^-1/2 / s2 + P)^-1, P = 3 / w^2 the information of a uniform prior
     over the window (so that a direction the scan does not constrain gets the window's
     variance, not infinity).
   - plus the second moment about the estimate of the response's poses outside the best
     basin (Mahalanobis^2 > ``basin_chi2`` under cov_icp plus a grid cell), weighted by
     exp(-``response_gain`` N (score_best - score) / kappa) (Olson 2009's covariance from
     the response surface, as a Gaussian-mixture moment). A featureless corridor has a
     ridge of equal scores along it: the covariance is large along it and small across.
     ``response_gain`` = 3 nats per point per unit score was chosen on the simulated scenes
     (1 is conservative in corridors; the sensor's own 1/s2 scale, about 10, overconfident
     where 5 cm quantisation fakes the 4 cm door recesses).
   - plus, likewise, the other basins' ICP results, weighted by exp(-t^2 / 2), t the cost
     difference to the estimate's over its own noise (a paired test: sqrt(n kappa) times the
     spread of the per-point differences): a basin as good as the estimate within the
     residuals' noise is a tie, weighs as much and widens the covariance over both (then
     usually rejected as ambiguous), instead of a confident answer one door period off.
     These basins' response poses no longer count on their own.
4. **Rejection** (``ok`` False, ``reason``): too few points (query, reference, inliers);
   diverged (non-finite, or ICP moved beyond the window from the search's pose); score below
   ``min_score`` (0.5) or inlier fraction below ``min_overlap`` (0.25): on the Intel and
   Freiburg logs right consecutive pairs score ~0.8, pairs of places 4 m apart median 0.14,
   at most 0.61 (experiment); ambiguous: the covariance's 1-sigma extent exceeds
   ``max_ambiguity`` (0.5) of the window's half-width in xy or theta, i.e. the scan hardly
   narrows the window down in some direction. ``pose`` and ``cov`` are returned even
   then: an odometry-like caller may use a corridor match with its honest covariance by
   raising ``max_ambiguity``.

Modules (:class:`MatchParams` is the configuration's ``[matcher]`` section, in
:mod:`fgslam.config`): :mod:`~fgslam.scanmatch.points` (:func:`scan_points`, point filters),
:mod:`~fgslam.scanmatch.reference` (:class:`Reference`: grid, lines, fans),
:mod:`~fgslam.scanmatch.search` (1.),
:mod:`~fgslam.scanmatch.icp` (2.), :mod:`~fgslam.scanmatch.basins` (2., the other basins),
:mod:`~fgslam.scanmatch.covariance` (3.), :mod:`~fgslam.scanmatch.matcher` (:func:`match`,
:class:`Match`, 4.).

numpy/scipy only, no I/O.
"""

from fgslam.config.robot import MatchParams
from fgslam.scanmatch.matcher import Match, match
from fgslam.scanmatch.points import scan_points
from fgslam.scanmatch.reference import Reference

__all__ = ["Match", "MatchParams", "Reference", "match", "scan_points"]
