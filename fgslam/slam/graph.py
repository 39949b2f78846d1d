"""Factor-graph backends: :class:`GraphBackend`, iSAM2 with one incremental update per
keyframe (it builds the graph and makes the association decisions), and
:class:`BatchSmoother`, Levenberg-Marquardt over the whole graph it built (offline
smoothing); :class:`GraphSolution` reads either final estimate (trajectory, covariances).

Variables: robot poses X(k) (``Pose2``), landmarks L(id): lines ``Vector2`` (alpha, d),
corners ``Pose2``, points ``Point2``. Factors: a prior on the first pose, preintegrated
odometry and the scan match between keyframes (``BetweenFactorPose2``; robust when both are
there), verified loop closures (robust ``BetweenFactorPose2``), the landmark factors of
``factors`` and the merge ties, both with the robust noise model of the backend (one policy
for iSAM2 and batch).

Association uses the current estimate and the *exact* joint marginal covariance of the last
pose and the candidate landmarks (``ISAM2.jointMarginalCovariance``), propagated through the
odometry of the new keyframe exactly as the EKF predicts; GTSAM's tangent-space covariances
are rotated into world coordinates first.

The graph never ends a run (docs/robustness.md): iSAM2 factorises by QR (GTSAM's Cholesky
declares a system indeterminate when two consecutive pivots differ by more than 2^12, which a
well-measured wall beside a poorly constrained direction along a corridor reaches on real
logs); every new landmark carries a weak prior and every keyframe whose links are all robust a
weak Gaussian link, so no variable is ever unconstrained; an update that still fails or gives
a non-finite estimate is repaired (:meth:`GraphBackend._repair`: the offending new landmark
removed, or a weak prior on the offending variable) with a warning naming it; a covariance
query that fails falls back to the separate marginals, then to a wide covariance, counted.
"""

from __future__ import annotations

import dataclasses
import math
import re
import time
import warnings
from collections import Counter

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.odometry import (
    Preintegrated,
    calibrated_odometry_factor,
    fuse_motions,
    with_calibration,
)
from fgslam.choices import SONAR_TIMING_CHOICES
from fgslam.errors import RunWarning, UserError
from fgslam.frontend.features import Feature
from fgslam.slam import models
from fgslam.slam.backend import Backend, Estimate
from fgslam.slam.calibration import Calibration, as_calibration


def X(k: int) -> int:
    return gtsam.symbol("x", k)


def L(i: int) -> int:
    return gtsam.symbol("l", i)


# the calibration errors (fgslam.slam.calibration.Calibration), one Vector for the whole run
C = gtsam.symbol("c", 0)


class BackendError(UserError):
    """The optimiser could not solve the problem (reported to the user, never a traceback)."""


# a weak prior's standard deviation (m and rad alike): information 1e-6, far below any
# measurement's, so it moves no estimate measurably but no variable is ever unconstrained
WEAK_SIGMA = 1e3
# the covariance assumed when a marginal cannot be computed at all: wide (1 m, 1 rad), so
# association gates stay open rather than closed; counted as covariance_fallbacks
FALLBACK_VARIANCE = 1.0
MAX_REPAIRS = 4  # attempts to repair one keyframe's update before giving up


def weak_noise(dim: int) -> gtsam.noiseModel.Base:
    """The noise of a weak prior or link of dimension ``dim`` (:data:`WEAK_SIGMA`)."""
    return gtsam.noiseModel.Isotropic.Sigma(dim, WEAK_SIGMA)


def _prior(key: int, value: object, noise: gtsam.noiseModel.Base) -> gtsam.NonlinearFactor:
    """A prior on ``key`` at ``value`` (a ``Pose2`` or a vector)."""
    if isinstance(value, gtsam.Pose2):
        return gtsam.PriorFactorPose2(key, value, noise)
    return gtsam.PriorFactorVector(key, np.asarray(value, dtype=float), noise)


def isam2_params(
    factorization: str, relinearize_threshold: float = 0.1, relinearize_skip: int = 10
) -> gtsam.ISAM2Params:
    """iSAM2's parameters: ``factorization`` "QR" or "CHOLESKY" (docs/robustness.md: QR
    where Cholesky's pivot heuristic declares a sound system indeterminate)."""
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(relinearize_threshold)
    params.relinearizeSkip = relinearize_skip
    params.setFactorization(factorization)
    return params


def _culprit(reason: str) -> int | None:
    """The key GTSAM named in an indeterminate-system message ("... (Symbol: l160)")."""
    m = re.search(r"Symbol: ([a-zA-Z])(\d+)", reason)
    return gtsam.symbol(m.group(1), int(m.group(2))) if m else None


# the robot's poses are Pose2 variables like a corner's; the calibration is a plain vector
POSE_VARIABLE = dataclasses.replace(models.KINDS["corner"], name="pose")


def _key_name(key: int) -> str:
    sym = gtsam.Symbol(key)
    return f"{chr(sym.chr())}{sym.index()}"


def _rot_block(th: float) -> NDArray[np.float64]:
    c, s = math.cos(th), math.sin(th)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class GraphBackend(Backend):
    """iSAM2 online, one update per keyframe; :class:`BatchSmoother` solves the graph it
    built by Levenberg-Marquardt (offline), from its final estimate.

    Noise policy (one for iSAM2 and batch, which share the graph): landmark factors and
    merge factors carry a robust noise model with kernel ``robust`` (models.m_estimator;
    "none": Gaussian); a merge is a robust tie of sigma ``merge_sigma`` (m, rad), never a
    hard equality. Relinearisation during the run: every ``relinearize_skip`` updates, of the
    variables whose step exceeds ``relinearize_threshold`` (GTSAM's 0.1: fast). That leaves
    variables with smaller steps at old linearisation points, and with robust kernels their
    weights too (on Victoria Park's first 300 steps: 12-18 cm from the batch optimum). So
    after the last keyframe :meth:`finish` relinearises the whole graph at the current
    estimate and takes Gauss-Newton steps (every factor linearised, one sparse solve) until
    no variable moves by ``converge_tol`` (or ``max_final_updates`` steps), so iSAM2's final
    estimate is at the optimum. (Until d4a6cdb: a new ISAM2 over the same factors, threshold
    0.01, updated until converged; its first update alone, a full elimination inside iSAM2,
    cost ~1 s of CPU on 200 s of the corridor against ~0.1 s per Gauss-Newton step, and it
    stopped further from the optimum: CHANGELOG.md, issue 12.)

    :meth:`means` is a cache: refreshed in full every ``refresh_every`` keyframes, and for the
    landmarks each keyframe touched; association uses it only to pick candidates (a loose
    pre-gate), the gate itself the fresh :meth:`estimate`.

    ``calibration``: the calibration errors to estimate (:class:`Calibration`, or the 3x3
    prior covariance of the wheel errors (e_r, e_l, e_b) alone), one variable ``C`` of the
    graph: its wheel part in every wheel odometry factor
    (:func:`factors.odometry.calibrated_odometry_factor`), its laser and sound parts in every
    factor of a feature that involves them (:attr:`Feature.Jc`); None: the nominal
    calibration is taken as exact.
    :meth:`calibration_estimate` reads it.
    """

    name = "isam2"

    def __init__(
        self,
        covariances: bool = True,
        robust: str = "cauchy",
        merge_sigma: float = 0.01,
        relinearize_threshold: float = 0.1,
        relinearize_skip: int = 10,
        refresh_every: int = 10,
        max_final_updates: int = 20,
        converge_tol: float = 0.01,
        loop_updates: int = 2,
        calibration: Calibration | NDArray[np.float64] | None = None,
        sonar_timing: str = "scan-frame",
        factorization: str = "QR",
    ) -> None:
        super().__init__()
        if sonar_timing not in SONAR_TIMING_CHOICES:
            raise ValueError(f"unknown sonar timing {sonar_timing!r}")
        self.own_time = sonar_timing == "own-time"
        self.stats: Counter = Counter()  # sonar_own_time: measurements at their own time
        self.cal = as_calibration(calibration)
        self._c = np.zeros(0 if self.cal is None else self.cal.dim)  # c's current estimate
        self._c_cov: NDArray[np.float64] | None = None  # c's marginal after the last commit
        self._calibrated = False  # the last link's wheels carry the calibration
        self.solution: GraphSolution | None = None  # after finish()
        self.covariances = covariances
        self.robust = robust
        self.merge_sigma = merge_sigma
        self.refresh_every = refresh_every
        self.max_final_updates = max_final_updates
        self.converge_tol = converge_tol
        self.loop_updates = loop_updates
        self.final_updates = 0
        self._final = False  # _est is the converged final estimate
        self.failed: str | None = None
        self._start_cov = np.eye(3)
        self._params = isam2_params(factorization, relinearize_threshold, relinearize_skip)
        self.isam = gtsam.ISAM2(self._params)
        # what the guard did (docs/robustness.md): one line per repair or fallback, and the
        # landmarks removed by a repair (the map manager takes them out: take_removed)
        self.repairs: list[str] = []
        self._removed: list[int] = []
        self.graph = gtsam.NonlinearFactorGraph()  # everything, for batch and for reports
        self.new_graph = gtsam.NonlinearFactorGraph()
        self.new_values = gtsam.Values()
        self.kinds: dict[int, str] = {}
        self.k = -1
        self.times: list[float] = []
        self._pose_pred = np.zeros(3)
        self._pre: Preintegrated | None = None
        self._est = gtsam.Values()
        self._est_poses: NDArray[np.float64] | None = np.zeros((0, 3))  # of _est (None: to do)
        self._means: dict[int, NDArray[np.float64]] = {}
        self._touched: set[int] = set()
        self._loop_added = False
        self._prev = gtsam.Pose2()

    # ------------------------------------------------------------------ keyframes

    def start(self, t: float, pose: NDArray[np.float64], cov: NDArray[np.float64]) -> None:
        self.k = 0
        self.times.append(t)
        self._start_cov = np.array(cov, dtype=float)
        p = gtsam.Pose2(*pose)
        # the prior is on the body tangent: rotate the world covariance
        R = _rot_block(pose[2])
        self.new_graph.add(gtsam.PriorFactorPose2(X(0), p, models.noise_model(R.T @ cov @ R)))
        self.new_values.insert(X(0), p)
        if self.cal is not None:
            self.new_values.insert(C, np.zeros(self.cal.dim))
            prior = models.noise_model(self.cal.prior)
            self.new_graph.add(gtsam.PriorFactorVector(C, np.zeros(self.cal.dim), prior))
            self._c_cov = self.cal.prior.copy()
        self._pose_pred = np.array(pose, dtype=float)
        self._pending_t = t

    def predict(
        self, t: float, pre: Preintegrated | None, scan: Preintegrated | None = None
    ) -> None:
        """A new pose linked to the last one by the wheel odometry ``pre`` and/or the scan
        match ``scan``: one between factor each; with both, each carries the robust kernel
        (they check each other, the landmarks arbitrate); one alone is Gaussian."""
        prev = self._prev = self.isam.calculateEstimatePose2(X(self.k))
        self.k += 1
        self.times.append(t)
        motions = [m for m in (pre, scan) if m is not None]
        if not motions:
            raise ValueError("predict needs the wheel odometry, a scan match or both")
        kernel = self.robust if len(motions) > 1 else "none"
        cal = self.cal
        self._calibrated = (
            cal is not None
            and cal.wheels is not None
            and (pre is not None and pre.calibration_jacobian is not None)
        )
        if kernel != "none":  # every link robust: a weak Gaussian one keeps the chain whole
            first = motions[0]
            self.new_graph.add(
                gtsam.BetweenFactorPose2(X(self.k - 1), X(self.k), first.delta, weak_noise(3))
            )
        for m in motions:
            if m is pre and self._calibrated:
                noise = models.noise_model(m.covariance_start, kernel)
                f = calibrated_odometry_factor(
                    X(self.k - 1), X(self.k), C, m, noise, cal.wheels, cal.dim
                )
                self.new_graph.add(f)
                continue
            noise = models.noise_model(m.covariance, kernel)
            self.new_graph.add(gtsam.BetweenFactorPose2(X(self.k - 1), X(self.k), m.delta, noise))
        if self._calibrated:
            pre = with_calibration(pre, self._c[cal.wheels])
        if pre is None or scan is None:
            self._pre = pre or scan
        else:
            self._pre = fuse_motions(pre, scan)
        pred = prev.compose(self._pre.delta)
        self.new_values.insert(X(self.k), pred)
        self._pose_pred = np.array([pred.x(), pred.y(), pred.theta()])
        self._pending_t = t

    # ------------------------------------------------------------------ loop closures

    supports_loops = True

    def keyframe_poses(self) -> NDArray[np.float64]:
        """(x, y, theta) of every keyframe before the current one, world: the cached estimate
        (refreshed every ``refresh_every`` keyframes), the filtered poses after it."""
        if self._est_poses is None:  # read from _est when first needed after a refresh
            poses = []
            for k in range(len(self.times)):
                if not self._est.exists(X(k)):
                    break
                p = self._est.atPose2(X(k))
                poses.append((p.x(), p.y(), p.theta()))
            self._est_poses = np.array(poses, dtype=float).reshape(-1, 3)
        cached = self._est_poses
        newer = [p for _, p, _ in self.trajectory[len(cached) :]]
        return np.vstack([cached, np.array(newer, dtype=float).reshape(-1, 3)])

    def relative(self, j: int) -> tuple[gtsam.Pose2, NDArray[np.float64]]:
        """The current (predicted) pose in the frame of keyframe ``j`` and its covariance in
        GTSAM's between convention (tangent at the relative pose): from the joint marginal of
        X(j) and the last committed pose, propagated through the new keyframe's motion."""
        kp = self.k - 1
        A = self.isam.calculateEstimatePose2(X(j))
        B = self.isam.calculateEstimatePose2(X(kp))
        r = A.between(B)
        d = self._pre.delta
        if j == kp:
            return d, self._pre.covariance.copy()
        J = self.joint_covariance([X(j), X(kp)])
        Ad_d = d.inverse().AdjointMap()
        M = np.hstack([-Ad_d @ r.inverse().AdjointMap(), Ad_d])
        C = M @ J @ M.T + self._pre.covariance
        return r.compose(d), 0.5 * (C + C.T)

    def add_loop(self, j: int, k: int, m: Preintegrated) -> None:
        """A verified loop closure: keyframe ``j`` to keyframe ``k`` (at most the current
        one), robust."""
        noise = models.noise_model(m.covariance, self.robust)
        self.new_graph.add(gtsam.BetweenFactorPose2(X(j), X(k), m.delta, noise))
        self._loop_added = True

    def pose(self) -> NDArray[np.float64]:
        return self._pose_pred.copy()

    def _mean(self, lid: int, fresh: bool = False) -> NDArray[np.float64]:
        """A landmark's mean: from the cached estimate, or (``fresh``) solved for now."""
        kind = models.KINDS[self.kinds[lid]]
        return kind.read_isam(self.isam, L(lid)) if fresh else kind.read(self._est, L(lid))

    def means(self) -> dict[int, NDArray[np.float64]]:
        return self._means

    def _refresh_means(self) -> None:
        self._means = {lid: self._mean(lid) for lid in self.kinds if self._est.exists(L(lid))}
        self._est_poses = None  # keyframe_poses reads them from _est when asked

    def estimate(self, lids: list[int]) -> Estimate:
        """Means and world-frame joint covariance of [predicted pose, landmarks] (fresh: solved
        for now). At the first keyframe (nothing committed yet): the start covariance."""
        if self.k == 0 and self._pre is None:
            if lids:
                raise ValueError("no landmark exists before the first keyframe is committed")
            return {}, self._start_cov.copy()
        means = {lid: self._mean(lid, fresh=True) for lid in lids}
        # with calibration on a wheels-only link, its uncertainty enters the prediction
        cal = self._calibrated and self._pre.calibration_jacobian is not None
        keys = [X(self.k - 1)] + ([C] if cal else []) + [L(lid) for lid in lids]
        J = self.joint_covariance(keys)
        # tangent (body) -> world for Pose2 blocks
        prev = self._prev
        blocks = [_rot_block(prev.theta())] + ([np.eye(self.cal.dim)] if cal else [])
        for lid in lids:
            blocks.append(models.KINDS[self.kinds[lid]].tangent_to_world(means[lid]))
        T = _blockdiag(blocks)
        P = T @ J @ T.T
        # propagate the pose through the new keyframe's odometry (as the EKF predicts)
        pre = self._pre
        th = prev.theta()
        c, s = math.cos(th), math.sin(th)
        dx, dy = pre.delta.x(), pre.delta.y()
        F = np.array([[1.0, 0.0, -s * dx - c * dy], [0.0, 1.0, c * dx - s * dy], [0.0, 0.0, 1.0]])
        G = _rot_block(th)
        if cal:  # the pose also moves with the calibration errors: rows [F, G J_c]
            Gc = G @ self.cal.wheel_jacobian(pre.calibration_jacobian)
            c = np.s_[3 : 3 + self.cal.dim]
            P[:3, :] = F @ P[:3, :] + Gc @ P[c, :]
            P[:, :3] = P[:, :3] @ F.T + P[:, c] @ Gc.T
            P = np.delete(np.delete(P, c, axis=0), c, axis=1)
        else:
            P[:3, :] = F @ P[:3, :]
            P[:, :3] = P[:, :3] @ F.T
        P[:3, :3] += G @ pre.covariance_start @ G.T
        return means, P

    # ------------------------------------------------------------------ measurements

    def observe(self, lid: int, f: Feature) -> None:
        self.new_graph.add(self._factor(lid, f))
        self._touched.add(lid)

    def add_landmark(self, lid: int, f: Feature) -> None:
        self.kinds[lid] = f.kind
        self._touched.add(lid)
        J = self._cal_jacobian(f)
        z = f.z if J is None else f.z - J @ self._c  # the measurement, calibrated
        lm, _, _ = models.to_world(f.kind, self._pose_pred, z)
        value = models.value(f.kind, lm)
        self.new_values.insert(L(lid), value)
        self.new_graph.add(self._factor(lid, f))
        # never unconstrained, whatever the robust kernel makes of its measurements
        self.new_graph.add(_prior(L(lid), value, weak_noise(models.DIM[f.kind])))

    # a reading this far outside the last two keyframes' interval stays in the scan frame
    OWN_TIME_REACH = (-1.0, 2.0)

    def _factor(self, lid: int, f: Feature) -> gtsam.NonlinearFactor:
        """The measurement's factor: at the keyframe (the scan frame), or, with own time on
        and a sonar feature, from the pose at its reading's time between the last two
        keyframes (constant twist; a reading after the keyframe extrapolates it)."""
        kind = self.kinds[lid]
        own = f.own
        if self.own_time and own is not None and self.k > 0 and kind in models.OWN_TIME_KINDS:
            ta, tb = self.times[self.k - 1], self.times[self.k]
            if tb > ta:
                s = (own.t - ta) / (tb - ta)
                if self.OWN_TIME_REACH[0] <= s <= self.OWN_TIME_REACH[1]:
                    self.stats["sonar_own_time"] += 1
                    J = None if self.cal is None else self.cal.measurement_jacobian(own.Jc)
                    return models.own_time_factor(
                        kind, X(self.k - 1), X(self.k), L(lid), s, own, self.robust, C, J
                    )
        return models.factor(kind, X(self.k), L(lid), f, self.robust, C, self._cal_jacobian(f))

    def measured_calibration_cov(self) -> NDArray[np.float64] | None:
        if self.cal is None or not self.cal.measured or self._c_cov is None:
            return None
        idx = self.cal.measured_index
        return self._c_cov[np.ix_(idx, idx)]

    def merge(self, keep: int, drop: int) -> None:
        """A robust tie (sigma ``merge_sigma``) between two variables of one landmark."""
        kind = models.KINDS[self.kinds[keep]]
        noise = models.noise_model(np.eye(kind.dim) * self.merge_sigma**2, self.robust)
        self.new_graph.add(kind.equality(L(keep), L(drop), noise))

    def commit(self) -> None:
        self._update_guarded()
        self.graph.push_back(self.new_graph)
        # start a new empty graph: re-adding factors would silently double information
        self.new_graph = gtsam.NonlinearFactorGraph()
        self.new_values = gtsam.Values()
        # the whole estimate (for the candidate search) every few keyframes; in between, the
        # landmarks this keyframe touched; association re-solves its candidates exactly
        if self._loop_added:  # a loop moves much of the graph: relinearise, refresh all
            for _ in range(self.loop_updates):
                self.isam.update()
        if self.k % self.refresh_every == 0 or self._loop_added:
            self._loop_added = False
            self._est = self.isam.calculateEstimate()
            self._refresh_means()
        else:
            for lid in self._touched:
                self._means[lid] = self._mean(lid, fresh=True)
        self._touched = set()
        p = self.isam.calculateEstimatePose2(X(self.k))
        self._pose_pred = np.array([p.x(), p.y(), p.theta()])
        if self.cal is not None:
            self._c = np.asarray(self.isam.calculateEstimateVector(C), dtype=float)
            if self.cal.measured:  # for association (for_association)
                self._c_cov = self.joint_covariance([C])
        self.trajectory.append((self._pending_t, self._pose_pred.copy(), None))

    # ------------------------------------------------------------------ the guard

    def take_removed(self) -> list[int]:
        """The landmarks a repair removed since the last call (the map manager drops them)."""
        out, self._removed = self._removed, []
        return out

    def _unsolved(self, isam: gtsam.ISAM2, keys) -> int | None:
        """The first of ``keys`` (poses, landmarks, the calibration) whose estimate by
        ``isam`` is not finite (a singular QR factorisation gives inf or NaN), or None."""
        for key in keys:
            if not isam.valueExists(key):
                continue
            if not np.all(np.isfinite(self._kind(key).read_isam(isam, key))):
                return key
        return None

    def _update_guarded(self) -> None:
        """iSAM2's update with this keyframe's factors and values; when GTSAM cannot solve
        them (an indeterminate system) or the estimate of the new variables is not finite,
        :meth:`_repair` the keyframe. Raises :class:`BackendError` only when every repair
        failed."""
        keys = sorted(set(self.new_values.keys()) | ({X(self.k)} if self.k >= 0 else set()))
        try:
            self.isam.update(self.new_graph, self.new_values)
            bad = self._unsolved(self.isam, keys)
            if bad is None:
                return
            reason = f"no finite estimate of {_key_name(bad)}"
        except RuntimeError as exc:  # IndeterminantLinearSystemException and kin
            bad, reason = None, _reason(exc)
        try:
            self._repair(reason, keys, bad)
        except BackendError:  # back to the last good keyframe: this one's variables dropped
            for key in self.new_values.keys():
                if gtsam.Symbol(key).chr() == ord("l"):
                    self.kinds.pop(gtsam.Symbol(key).index(), None)
            if self.k > 0:
                self.times.pop()
            self.k -= 1
            self.new_graph = gtsam.NonlinearFactorGraph()
            self.new_values = gtsam.Values()
            raise

    def _repair(self, reason: str, keys: list[int], bad: int | None = None) -> None:
        """Rebuild iSAM2 over the whole graph with this keyframe repaired: the variable GTSAM
        named gets a weak prior, or, a landmark new in this keyframe, is removed with its
        factors; failing that, all of this keyframe's new landmarks are removed and every
        variable it touches gets a weak prior. Each repair is one line in :attr:`repairs`."""
        try:  # the estimate so far (the failed update left iSAM2 unusable)
            base = gtsam.Values(self.isam.getLinearizationPoint())
        except RuntimeError:
            base = gtsam.Values(self._est)
        missing = {k for k in self.new_values.keys() if not base.exists(k)}
        base.insert(self._values_without(self.new_values, set(self.new_values.keys()) - missing))
        new_lms = {k for k in self.new_values.keys() if gtsam.Symbol(k).chr() == ord("l")}
        drop: set[int] = set()
        priors: set[int] = set()
        what = ""
        for attempt in range(MAX_REPAIRS + 1):
            key = _culprit(reason) if bad is None else bad
            if attempt == MAX_REPAIRS or key is None or key in drop or key in priors:
                drop |= new_lms  # the last resort: no new landmark, weak priors around
                priors |= {k for k in keys if k not in new_lms}
                names = ", ".join(_key_name(k) for k in sorted(new_lms)) or "none"
                what = f"new landmarks removed ({names}), weak priors on the keyframe's poses"
            elif key in new_lms:
                drop.add(key)
                what = f"new landmark {_key_name(key)} removed"
            else:
                priors.add(key)
                what = f"weak prior on {_key_name(key)}"
            graph = gtsam.NonlinearFactorGraph()
            graph.push_back(self.graph)
            for i in range(self.new_graph.size()):
                f = self.new_graph.at(i)
                if f is not None and not drop.intersection(f.keys()):
                    graph.add(f)
            values = self._values_without(base, drop)
            for key in priors:
                graph.add(self._weak_prior(key, values))
            isam = gtsam.ISAM2(self._params)
            try:
                isam.update(graph, values)
                bad = self._unsolved(isam, [k for k in keys if k not in drop])
                if bad is None:
                    break
                reason = f"no finite estimate of {_key_name(bad)}"
            except RuntimeError as exc:
                bad, reason = None, _reason(exc)
        else:
            self.failed = (
                f"iSAM2 could not solve keyframe {self.k} (t = {self._pending_t:.2f} s) even "
                f"after repairs: {reason}"
            )
            raise BackendError(self.failed)
        msg = f"keyframe {self.k} (t = {self._pending_t:.2f} s): {what} ({reason})"
        self.repairs.append(msg)
        warnings.warn(f"the graph was repaired at {msg}", RunWarning, stacklevel=2)
        self.stats["graph_repairs"] += 1
        for key in drop:
            lid = gtsam.Symbol(key).index()
            self.kinds.pop(lid, None)
            self._means.pop(lid, None)
            self._touched.discard(lid)
            self._removed.append(lid)
            self.stats["landmarks_removed_by_repair"] += 1
        self.isam = isam
        # the rebuilt graph replaces the committed one (commit pushes nothing more)
        self.graph = graph
        self.new_graph = gtsam.NonlinearFactorGraph()
        self._est = self.isam.calculateEstimate()
        self._est_poses = None

    def _values_without(self, base: gtsam.Values, drop: set[int]) -> gtsam.Values:
        """A copy of ``base`` without the keys ``drop``."""
        values = gtsam.Values()
        for key in base.keys():
            if key not in drop:
                kind = self._kind(key)
                values.insert(key, kind.value(kind.read(base, key)))
        return values

    def _weak_prior(self, key: int, values: gtsam.Values) -> gtsam.NonlinearFactor:
        kind = self._kind(key)
        return _prior(key, kind.value(kind.read(values, key)), weak_noise(kind.dim))

    def _kind(self, key: int) -> models.Kind:
        """How variable ``key`` is stored: a pose, the calibration vector or a landmark."""
        sym = gtsam.Symbol(key)
        if sym.chr() == ord("x"):
            return POSE_VARIABLE
        if key == C:
            n = self.cal.dim
            return dataclasses.replace(
                models.KINDS["point"], name="calibration", dim=n, angular=(False,) * n
            )
        return models.KINDS[self.kinds[sym.index()]]

    def joint_covariance(self, keys: list[int]) -> NDArray[np.float64]:
        """iSAM2's joint marginal covariance of ``keys`` (tangent spaces); when GTSAM cannot
        compute it, the block diagonal of the separate marginals, and failing those a wide
        covariance (:data:`FALLBACK_VARIANCE`), each counted (``covariance_fallbacks``)."""
        try:
            return self.isam.jointMarginalCovariance(keys).fullMatrix()
        except RuntimeError:
            self.stats["covariance_fallbacks"] += 1
        blocks = []
        for key in keys:
            try:
                blocks.append(np.asarray(self.isam.marginalCovariance(key)))
            except RuntimeError:
                blocks.append(np.eye(self._kind(key).dim) * FALLBACK_VARIANCE)
        return _blockdiag(blocks)

    # ------------------------------------------------------------------ results

    def finish(self) -> list[tuple[float, NDArray[np.float64], NDArray[np.float64] | None]]:
        """Converge (:meth:`_converge`) and return the trajectory ``(t, pose, cov)`` of the
        final estimate (:attr:`solution`)."""
        if self.k < 0:
            return []
        self._converge()
        self._refresh_means()
        self.solution = GraphSolution(
            self.graph, self._est, self.times, self.kinds, self.covariances
        )
        return self.solution.trajectory()

    def calibration_estimate(
        self,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None] | None:
        """The calibration errors c: the final estimate's with its marginal covariance after
        :meth:`finish`, before it iSAM2's current estimate alone."""
        if self.cal is None:
            return None
        if self.solution is not None:
            return self.solution.calibration()
        return self._c.copy(), None

    def final_estimate(self) -> gtsam.Values:
        """The converged estimate after :meth:`finish`, else iSAM2's current one."""
        return self._est if self._final else self.isam.calculateEstimate()

    def _converge(self) -> None:
        """Gauss-Newton on the whole graph from the current estimate: relinearise every
        factor, solve, step, until the largest step (tangent, per component) falls below
        ``converge_tol`` (or ``max_final_updates`` steps), as iSAM2's own updates step (no
        error evaluation: one costs half a step); a solve that fails or a step that is not
        finite ends it, the estimate before it kept. ``final_updates`` counts the steps."""
        est = self.isam.calculateEstimate()
        self.final_updates = 0
        for _ in range(self.max_final_updates):
            try:
                delta = solve_linear(self.graph.linearize(est))
            except RuntimeError:  # an ill-conditioned graph: keep the estimate so far
                break
            step = float(np.max(np.abs(delta.vector()), initial=0.0))
            if not math.isfinite(step):
                break
            est = est.retract(delta)
            self.final_updates += 1
            if step < self.converge_tol:
                break
        self._est = est
        self._final = True

    def chi2_per_dof(self, values: gtsam.Values | None = None) -> float:
        """:func:`chi2_per_dof` of ``values`` (default: the current final estimate)."""
        values = self._est if values is None else values
        return chi2_per_dof(self.graph, values, len(self.times), self.kinds)

    def landmark_covariances(self) -> dict[int, NDArray[np.float64]]:
        """World-frame marginal covariances of the landmarks at the final estimate (after
        :meth:`finish`; before it, none)."""
        return self.solution.landmark_covariances() if self.solution is not None else {}


class GraphSolution:
    """A whole-graph estimate and what is read from it (iSAM2's converged one or the batch
    solution): the trajectory with world-frame pose covariances and the landmarks'
    covariances, from one factorisation of the whole graph (far cheaper than asking iSAM2 for
    thousands of marginals one at a time); ``covariances`` False: none computed."""

    def __init__(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        times: list[float],
        kinds: dict[int, str],
        covariances: bool = True,
    ) -> None:
        self.graph, self.values, self.times, self.kinds = graph, values, list(times), kinds
        self.covariances = covariances
        self._marg: gtsam.Marginals | None = None

    def _marginals(self) -> gtsam.Marginals | gtsam.ISAM2:
        """GTSAM's marginals of the whole graph (one Cholesky factorisation); where Cholesky
        declares the system indeterminate (pivots more than 2^12 apart), one QR
        factorisation by an iSAM2 over the same graph at the same estimate. Either answers
        ``marginalCovariance(key)``; raises RuntimeError when neither can."""
        if self._marg is None:
            try:
                self._marg = gtsam.Marginals(self.graph, self.values)
            except RuntimeError:
                isam = gtsam.ISAM2(isam2_params("QR"))
                isam.update(self.graph, self.values)
                self._marg = isam
        return self._marg

    def trajectory(self) -> list[tuple[float, NDArray[np.float64], NDArray[np.float64] | None]]:
        covs = self._pose_covariances()
        out = []
        for k, t in enumerate(self.times):
            p = self.values.atPose2(X(k))
            out.append((t, np.array([p.x(), p.y(), p.theta()]), covs[k] if covs else None))
        return out

    def means(self) -> dict[int, NDArray[np.float64]]:
        return {
            lid: models.KINDS[kind].read(self.values, L(lid))
            for lid, kind in self.kinds.items()
            if self.values.exists(L(lid))
        }

    def _pose_covariances(self) -> list[NDArray[np.float64]] | None:
        if not self.covariances:
            return None
        try:
            m = self._marginals()
        except RuntimeError:  # an ill-conditioned final graph: report no covariances
            return None
        out = []
        try:  # a fallback factorisation may still refuse a query: report no covariances
            for k in range(len(self.times)):
                C = m.marginalCovariance(X(k))
                R = _rot_block(self.values.atPose2(X(k)).theta())
                out.append(R @ C @ R.T)
        except RuntimeError:
            return None
        return out

    def calibration(self) -> tuple[NDArray[np.float64], NDArray[np.float64] | None] | None:
        """The calibration errors c and their marginal covariance (None if it cannot be
        computed), or None when the graph has no calibration variable."""
        if not self.values.exists(C):
            return None
        mean = np.asarray(self.values.atVector(C), dtype=float)
        try:
            return mean, self._marginals().marginalCovariance(C)
        except RuntimeError:
            return mean, None

    def landmark_covariances(self) -> dict[int, NDArray[np.float64]]:
        try:
            m = self._marginals()
        except RuntimeError:
            return {}
        out = {}
        for lid, kind in self.kinds.items():
            if not self.values.exists(L(lid)):
                continue
            R = models.KINDS[kind].tangent_to_world(models.KINDS[kind].read(self.values, L(lid)))
            try:
                out[lid] = R @ m.marginalCovariance(L(lid)) @ R.T
            except RuntimeError:  # this landmark's marginal refused: left out
                continue
        return out


class BatchSmoother:
    """Offline smoothing: Levenberg-Marquardt over the whole graph that an iSAM2 run
    (:class:`GraphBackend`) built, from iSAM2's final estimate: the same factors, noise and
    robust policy, the association decisions iSAM2's estimate made. Results as a backend
    gives them (:meth:`finish`, :meth:`means`, :meth:`landmark_covariances`); raises
    :class:`BackendError` when the solve fails."""

    name = "batch"

    def __init__(self, source: GraphBackend) -> None:
        t0 = time.perf_counter()
        dims = {X(k): 3 for k in range(len(source.times))}
        dims.update({L(lid): models.DIM[kind] for lid, kind in source.kinds.items()})
        if source.cal is not None:
            dims[C] = source.cal.dim
        try:
            values, self.iterations = levenberg_marquardt(
                source.graph, source.final_estimate(), dims
            )
        except RuntimeError as exc:
            raise BackendError(f"batch optimisation failed: {_reason(exc)}") from None
        self.source = source
        self.stats = getattr(source, "stats", {})
        self.solution = GraphSolution(
            source.graph, values, source.times, source.kinds, source.covariances
        )
        self.seconds = time.perf_counter() - t0

    @property
    def values(self) -> gtsam.Values:
        return self.solution.values

    def finish(self) -> list[tuple[float, NDArray[np.float64], NDArray[np.float64] | None]]:
        return self.solution.trajectory()

    def means(self) -> dict[int, NDArray[np.float64]]:
        return self.solution.means()

    def landmark_covariances(self) -> dict[int, NDArray[np.float64]]:
        return self.solution.landmark_covariances()

    def calibration_estimate(
        self,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None] | None:
        return self.solution.calibration()

    def chi2_per_dof(self) -> float:
        sol = self.solution
        return chi2_per_dof(sol.graph, sol.values, len(sol.times), sol.kinds)


def chi2_per_dof(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, poses: int, kinds: dict[int, str]
) -> float:
    """2 x graph error / (measurement dof - variable dof) of ``values`` (``poses`` poses and
    the landmarks of ``kinds``); ~1 at the optimum of a consistent graph."""
    m = sum(graph.at(i).dim() for i in range(graph.size()))
    n = 3 * poses + sum(models.DIM[k] for k in kinds.values()) + 3 * values.exists(C)
    return 2.0 * graph.error(values) / max(m - n, 1)


def levenberg_marquardt(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    dims: dict[int, int],
    max_iterations: int = 30,
    rel_tol: float = 1e-6,
) -> tuple[gtsam.Values, int]:
    """Levenberg-Marquardt with identity damping (lambda I on every variable's tangent),
    solved by GTSAM's sparse elimination. (GTSAM's own optimizer classes spend far longer per
    iteration on graphs of Python ``CustomFactor``s than one linearisation and one solve do.)
    Returns the solution and the number of iterations."""
    lam = 1e-5
    err = graph.error(values)
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007 - returned
        lin = graph.linearize(values)
        improved = False
        while lam < 1e10:
            damped = gtsam.GaussianFactorGraph()
            damped.push_back(lin)
            s = math.sqrt(lam)
            for key, n in dims.items():
                damped.add(key, s * np.eye(n), np.zeros(n), gtsam.noiseModel.Unit.Create(n))
            new = values.retract(solve_linear(damped))
            new_err = graph.error(new)
            if new_err <= err:
                improved = True
                break
            lam *= 10.0
        if not improved:
            break
        rel = (err - new_err) / max(err, 1e-300)
        values, err = new, new_err
        lam = max(lam / 10.0, 1e-12)
        if rel < rel_tol:
            break
    return values, it


def solve_linear(lin: gtsam.GaussianFactorGraph) -> gtsam.VectorValues:
    """The least-squares solution of ``lin``: by Cholesky (fast), or by QR where Cholesky
    declares the system indeterminate (pivots more than 2^12 apart, which real graphs reach:
    module doc); raises RuntimeError only when QR fails too."""
    try:
        return lin.optimize()
    except RuntimeError:
        return lin.optimize(gtsam.EliminateQR)


def _reason(exc: BaseException) -> str:
    """The first paragraph of a GTSAM exception's message on one line (the
    indeterminate-system message starts with a blank line and names the variable on its
    second line)."""
    words = []
    for line in str(exc).splitlines():
        if line.strip():
            words.append(line.strip())
        elif words:
            break
    return " ".join(words) or f"{type(exc).__name__} (GTSAM gave no message)"


def _blockdiag(blocks: list[NDArray[np.float64]]) -> NDArray[np.float64]:
    n = sum(b.shape[0] for b in blocks)
    T = np.zeros((n, n))
    o = 0
    for b in blocks:
        k = b.shape[0]
        T[o : o + k, o : o + k] = b
        o += k
    return T
