"""Solving a whole factor graph (docs/design.md, 6; docs/robustness.md): the linear solve
(Cholesky, QR where Cholesky declares a sound system indeterminate), iSAM2's parameters,
Levenberg-Marquardt over a built graph (:class:`BatchSmoother`, offline smoothing) and what
is read from a whole-graph estimate (:class:`GraphSolution`: trajectory, covariances)."""

from __future__ import annotations

import math
import time

import gtsam
import numpy as np
from numpy.typing import NDArray

from fgslam.errors import UserError
from fgslam.slam import models
from fgslam.slam.backend import Backend
from fgslam.slam.graph_keys import C, L, X


class BackendError(UserError):
    """The optimiser could not solve the problem (reported to the user, never a traceback)."""


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
        time_spread: dict[int, NDArray[np.float64]] | None = None,
    ) -> None:
        self.graph, self.values, self.times, self.kinds = graph, values, list(times), kinds
        self.covariances = covariances
        # keyframe k's time error times the robot's body twist (v, 0, omega), s x (m/s, rad/s)
        self.time_spread = time_spread or {}
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
        """(t, pose, world covariance) per keyframe: X(k), the robot at its scan's true time,
        as the pose at the keyframe's time t: where the scan's time error is modelled per scan
        (:attr:`time_spread`), its covariance gains the motion over that error (world frame;
        docs/design.md, 3.4)."""
        covs = self._pose_covariances()
        out = []
        for k, t in enumerate(self.times):
            p = self.values.atPose2(X(k))
            cov = covs[k] if covs else None
            u = self.time_spread.get(k)
            if cov is not None and u is not None:
                c, s = math.cos(p.theta()), math.sin(p.theta())
                w = np.array([c * u[0] - s * u[1], s * u[0] + c * u[1], u[2]])
                cov = cov + np.outer(w, w)
            out.append((t, np.array([p.x(), p.y(), p.theta()]), cov))
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
                R = models.rot_block(self.values.atPose2(X(k)).theta())
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
    (``source``, a :class:`fgslam.slam.graph.GraphBackend`) built, from iSAM2's final
    estimate: the same factors, noise and robust policy, the association decisions iSAM2's
    estimate made. Results as a backend
    gives them (:meth:`finish`, :meth:`means`, :meth:`landmark_covariances`); raises
    :class:`BackendError` when the solve fails."""

    name = "batch"

    def __init__(self, source: Backend) -> None:
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
            raise BackendError(f"batch optimisation failed: {gtsam_reason(exc)}") from None
        self.source = source
        self.stats = getattr(source, "stats", {})
        self.solution = GraphSolution(
            source.graph,
            values,
            source.times,
            source.kinds,
            source.covariances,
            source.time_spread(),
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


def gtsam_reason(exc: BaseException) -> str:
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
