"""Factor-graph backends: :class:`GraphBackend`, iSAM2 with one incremental update per
keyframe (it builds the graph and makes the association decisions), and
:class:`BatchSmoother`, Levenberg-Marquardt over the whole graph it built (offline
smoothing); :class:`GraphSolution` reads either final estimate (trajectory, covariances).

Variables: robot poses X(k) (``Pose2``), landmarks L(id): lines ``Vector2`` (alpha, d),
corners ``Pose2``, points ``Point2``. Factors: a prior on the first pose, preintegrated
odometry and the scan match between keyframes (``BetweenFactorPose2``; robust when both are
there), verified loop closures (robust ``BetweenFactorPose2``), the landmark factors of
``factors`` and the merge ties, both with the robust noise model of the backend (one policy
for iSAM2 and batch, :func:`factors.noise.noise_model`).

Association uses the current estimate and the *exact* joint marginal covariance of the last
pose and the candidate landmarks (``ISAM2.jointMarginalCovariance``), propagated through the
odometry of the new keyframe exactly as the EKF predicts; GTSAM's tangent-space covariances
are rotated into world coordinates first.

The graph never ends a run (docs/robustness.md): :mod:`fgslam.slam.graph_guard` (weak
priors, repairs, covariance fallbacks). The modules by responsibility: this one the iSAM2
backend; :mod:`~fgslam.slam.graph_keys` the variables; :mod:`~fgslam.slam.graph_solve` the
linear solve, Levenberg-Marquardt, the batch smoother and the whole-graph solution, whose
names this module re-exports; every noise model is :func:`factors.noise.noise_model`'s.
"""

from __future__ import annotations

import math
from collections import Counter

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.odometry import (
    COVARIANCE_FLOOR,
    Preintegrated,
    calibrated_odometry_factor,
    fuse_motions,
    with_calibration,
    with_time_registration,
)
from fgslam.choices import SONAR_TIMING_CHOICES
from fgslam.frontend.features import Feature
from fgslam.slam import models
from fgslam.slam.backend import Backend, Estimate
from fgslam.slam.calibration import Calibration, as_calibration
from fgslam.slam.graph_guard import GraphGuard, prior_factor, weak_noise
from fgslam.slam.graph_keys import C, L, S, X, blockdiag
from fgslam.slam.graph_solve import (
    GraphSolution,
    chi2_per_dof,
    isam2_params,
    solve_linear,
)

# the graph's names as callers import them (fgslam.slam.graph is the backends' one door)


class GraphBackend(GraphGuard, Backend):
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
        time_sigma: float = 0.0,
    ) -> None:
        super().__init__()
        self.time_sigma = time_sigma
        self._twists: dict[int, tuple[float, float]] = {}  # keyframe k's (m/s, rad/s)
        self._stamped: set[int] = set()  # the keyframes with a pose at the stamp, S(k)
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
        self._relinearize_threshold = relinearize_threshold
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
        self._origin = 0  # the keyframe the current one is linked to (predict)
        # iSAM2's pose estimates read since its last update, by (key, update count): the
        # same numbers as asking iSAM2 again (it changes only when updated, in commit)
        self._solves = 0
        self._poses: dict[tuple[int, int], gtsam.Pose2] = {}

    # ------------------------------------------------------------------ keyframes

    def start(
        self,
        t: float,
        pose: NDArray[np.float64],
        cov: NDArray[np.float64],
        *,
        twist: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        self.k = 0
        self.times.append(t)
        self._start_cov = np.array(cov, dtype=float)
        p = gtsam.Pose2(*pose)
        # the prior is on the body tangent: rotate the world covariance
        R = models.rot_block(pose[2])
        self.new_graph.add(gtsam.PriorFactorPose2(X(0), p, models.noise_model(R.T @ cov @ R)))
        self.new_values.insert(X(0), p)
        self._stamp_pose(0, p, twist)
        if self.cal is not None:
            self.new_values.insert(C, np.zeros(self.cal.dim))
            prior = models.noise_model(self.cal.prior)
            self.new_graph.add(gtsam.PriorFactorVector(C, np.zeros(self.cal.dim), prior))
            self._c_cov = self.cal.prior.copy()
        self._pose_pred = np.array(pose, dtype=float)
        self._pending_t = t

    def predict(
        self,
        t: float,
        pre: Preintegrated | None,
        scan: Preintegrated | None = None,
        origin: int | None = None,
        *,
        twist: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        """A new pose linked to keyframe ``origin`` (default: the last) by the wheel odometry
        ``pre`` and/or the scan match ``scan``: one between factor each; with both, each
        carries the robust kernel (they check each other, the landmarks arbitrate); one
        alone is Gaussian. (An earlier ``origin``: a continued session's first keyframe,
        placed on a restored one.) With :attr:`time_sigma`, the wheels link the poses at the
        stamps (:meth:`_stamp_pose`)."""
        o = self._origin = self.k if origin is None else int(origin)
        prev = self._prev = self._pose_estimate(X(o))
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
                gtsam.BetweenFactorPose2(X(o), X(self.k), first.delta, weak_noise(3))
            )
        # the wheels measure the motion between the stamps (S: with a time error modelled)
        wheel_keys = (
            S(o) if o in self._stamped else X(o),
            S(self.k) if self.time_sigma > 0 else X(self.k),
        )
        for m in motions:
            a, b = wheel_keys if m is pre else (X(o), X(self.k))
            if m is pre and self._calibrated:
                noise = models.noise_model(m.covariance_start, kernel)
                f = calibrated_odometry_factor(a, b, C, m, noise, cal.wheels, cal.dim)
                self.new_graph.add(f)
                continue
            noise = models.noise_model(m.covariance, kernel)
            self.new_graph.add(gtsam.BetweenFactorPose2(a, b, m.delta, noise))
        if self._calibrated:
            pre = with_calibration(pre, self._c[cal.wheels])
        if pre is not None and self.time_sigma > 0:  # the motion between the true times
            pre = with_time_registration(
                pre, self._twists.get(o, (0.0, 0.0)), twist, self.time_sigma
            )
        if pre is None or scan is None:
            self._pre = pre or scan
        else:
            self._pre = fuse_motions(pre, scan)
        pred = prev.compose(self._pre.delta)
        self.new_values.insert(X(self.k), pred)
        self._stamp_pose(self.k, pred, twist)
        self._pose_pred = np.array([pred.x(), pred.y(), pred.theta()])
        self._pending_t = t

    def time_registered(self, features: list[Feature], twist: tuple[float, float]) -> list[Feature]:
        """The features as measured: they see X(k), the pose at the scan's true time; the
        time error is on its tie to S(k) (:meth:`_stamp_pose`)."""
        return features

    def _stamp_pose(self, k: int, pose: gtsam.Pose2, twist: tuple[float, float]) -> None:
        """Keyframe ``k``'s pose at its scan's stamp, S(k), tied to X(k), the robot's at the
        scan's true time: the scan's time error d (sigma :attr:`time_sigma`) moves it by
        (v d, 0, omega d) in X(k)'s frame, a rank-one covariance (plus the odometry's
        numerical floor) (docs/design.md, 3.4). Off (no S) without a time error."""
        self._twists[k] = twist
        if self.time_sigma <= 0:
            return
        self._stamped.add(k)
        u = np.array([twist[0], 0.0, twist[1]])
        cov = self.time_sigma**2 * np.outer(u, u) + COVARIANCE_FLOOR * np.eye(3)
        self.new_graph.add(
            gtsam.BetweenFactorPose2(X(k), S(k), gtsam.Pose2(), models.noise_model(cov))
        )
        self.new_values.insert(S(k), pose)

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
        kp = self._origin
        A = self._pose_estimate(X(j))
        B = self._pose_estimate(X(kp))
        r = A.between(B)
        d = self._pre.delta
        if j == kp:
            return d, self._pre.covariance.copy()
        J = self.joint_covariance([X(j), X(kp)])
        Ad_d = d.inverse().AdjointMap()
        M = np.hstack([-Ad_d @ r.inverse().AdjointMap(), Ad_d])
        C = M @ J @ M.T + self._pre.covariance
        return r.compose(d), 0.5 * (C + C.T)

    def restore(
        self,
        times: NDArray[np.float64],
        poses: NDArray[np.float64],
        links: list[Preintegrated],
        loops: list[tuple[int, int, Preintegrated]],
        cov: NDArray[np.float64],
    ) -> None:
        """Saved keyframes as the graph's first part (:meth:`Backend.restore`), the saved
        poses as their initial estimate; one update. Links are Gaussian, loops robust, as
        when they were first added."""
        n = len(times)
        if len(links) != n - 1:
            raise ValueError(f"{len(links)} links for {n} keyframes")
        self.start(float(times[0]), np.asarray(poses[0], dtype=float), cov)
        for i in range(1, n):
            m = links[i - 1]
            noise = models.noise_model(m.covariance)
            self.new_graph.add(gtsam.BetweenFactorPose2(X(i - 1), X(i), m.delta, noise))
            self.new_values.insert(X(i), gtsam.Pose2(*poses[i]))
            self.times.append(float(times[i]))
            self.trajectory.append((float(times[i - 1]), np.array(poses[i - 1], float), None))
        self.k = n - 1
        for j, k, m in loops:
            self.add_loop(j, k, m)
        self._loop_added = True  # the whole estimate read after the update
        self._pre = links[-1] if links else None
        self._origin = max(n - 2, 0)
        self._pending_t = float(times[-1])
        self.commit()

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
        keys = [X(self._origin)] + ([C] if cal else []) + [L(lid) for lid in lids]
        J = self.joint_covariance(keys)
        # tangent (body) -> world for Pose2 blocks
        prev = self._prev
        blocks = [models.rot_block(prev.theta())] + ([np.eye(self.cal.dim)] if cal else [])
        for lid in lids:
            blocks.append(models.KINDS[self.kinds[lid]].tangent_to_world(means[lid]))
        T = blockdiag(blocks)
        P = T @ J @ T.T
        # propagate the pose through the new keyframe's odometry (as the EKF predicts)
        pre = self._pre
        th = prev.theta()
        c, s = math.cos(th), math.sin(th)
        dx, dy = pre.delta.x(), pre.delta.y()
        F = np.array([[1.0, 0.0, -s * dx - c * dy], [0.0, 1.0, c * dx - s * dy], [0.0, 0.0, 1.0]])
        G = models.rot_block(th)
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
        self.new_graph.add(prior_factor(L(lid), value, weak_noise(models.DIM[f.kind])))

    # a reading this far outside the last two keyframes' interval stays in the scan frame
    OWN_TIME_REACH = (-1.0, 2.0)

    def _factor(self, lid: int, f: Feature) -> gtsam.NonlinearFactor:
        """The measurement's factor: at the keyframe (the scan frame), or, with own time on
        and a sonar feature, from the pose at its reading's time between the last two
        keyframes (constant twist; a reading after the keyframe extrapolates it)."""
        kind = self.kinds[lid]
        own = f.own
        last_two = self.k > 0 and self._origin == self.k - 1
        if self.own_time and own is not None and last_two and kind in models.OWN_TIME_KINDS:
            ta, tb = self.times[self.k - 1], self.times[self.k]
            if tb > ta:
                s = (own.t - ta) / (tb - ta)
                if self.OWN_TIME_REACH[0] <= s <= self.OWN_TIME_REACH[1]:
                    self.stats["sonar_own_time"] += 1
                    J = None if self.cal is None else self.cal.measurement_jacobian(own.Jc)
                    return models.own_time_factor(
                        kind, X(self.k - 1), X(self.k), L(lid), s, own, self.robust, C, J,
                        self._cal_gain(J, own.z),
                    )  # fmt: skip
        J = self._cal_jacobian(f)
        return models.factor(kind, X(self.k), L(lid), f, self.robust, C, J, self._cal_gain(J, f.z))

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

    def _pose_estimate(self, key: int) -> gtsam.Pose2:
        """iSAM2's current estimate of pose ``key``, read once per update."""
        p = self._poses.get((key, self._solves))
        if p is None:
            if len(self._poses) > 64:
                self._poses.clear()
            p = self._poses[(key, self._solves)] = self.isam.calculateEstimatePose2(key)
        return p

    def commit(self) -> None:
        self._solves += 1
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
        p = self._pose_estimate(X(self.k))
        self._pose_pred = np.array([p.x(), p.y(), p.theta()])
        if self.cal is not None:
            self._c = np.asarray(self.isam.calculateEstimateVector(C), dtype=float)
            if self.cal.measured:  # for association (for_association)
                self._c_cov = self.joint_covariance([C])
        self.trajectory.append((self._pending_t, self._pose_pred.copy(), None))

    # ------------------------------------------------------------------ results

    def finish(self) -> list[tuple[float, NDArray[np.float64], NDArray[np.float64] | None]]:
        """Converge (:meth:`_converge`) and return the trajectory ``(t, pose, cov)`` of the
        final estimate (:attr:`solution`)."""
        if self.k < 0:
            return []
        self._converge()
        self._refresh_means()
        self.solution = GraphSolution(
            self.graph, self._est, self.times, self.kinds, self.covariances, self.time_spread()
        )
        return self.solution.trajectory()

    def time_spread(self) -> dict[int, NDArray[np.float64]]:
        """Per keyframe with a pose at its stamp: its time error's sigma times the robot's body
        twist (v, 0, omega) then (for :class:`GraphSolution`)."""
        sig = self.time_sigma
        return {
            k: sig * np.array([self._twists[k][0], 0.0, self._twists[k][1]]) for k in self._stamped
        }

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
