"""The guard of the iSAM2 backend (docs/robustness.md): the graph never ends a run.

iSAM2 factorises by QR (GTSAM's Cholesky declares a system indeterminate when two consecutive
pivots differ by more than 2^12, which a well-measured wall beside a poorly constrained
direction along a corridor reaches on real logs); every new landmark carries a weak prior
and every keyframe whose links are all robust a weak Gaussian link (:func:`weak_noise`), so
no variable is ever unconstrained; an update that still fails or gives a non-finite estimate
is repaired (:meth:`GraphGuard._repair`: the offending new landmark removed, or a weak prior
on the offending variable) with a warning naming it; a covariance query that fails falls back
to the separate marginals, then to a wide covariance, counted.
"""

from __future__ import annotations

import dataclasses
import re
import warnings

import gtsam
import numpy as np
from numpy.typing import NDArray

from fgslam.errors import RunWarning
from fgslam.slam import models
from fgslam.slam.graph_keys import POSE_VARIABLE, C, X, blockdiag, key_name
from fgslam.slam.graph_solve import BackendError, gtsam_reason

# measurement's, so it moves no estimate measurably but no variable is ever unconstrained
WEAK_SIGMA = 1e3
# the covariance assumed when a marginal cannot be computed at all: wide (1 m, 1 rad), so
# association gates stay open rather than closed; counted as covariance_fallbacks
FALLBACK_VARIANCE = 1.0
MAX_REPAIRS = 4  # attempts to repair one keyframe's update before giving up


def weak_noise(dim: int) -> gtsam.noiseModel.Base:
    """The noise of a weak prior or link of dimension ``dim`` (:data:`WEAK_SIGMA`)."""
    return gtsam.noiseModel.Isotropic.Sigma(dim, WEAK_SIGMA)


def prior_factor(key: int, value: object, noise: gtsam.noiseModel.Base) -> gtsam.NonlinearFactor:
    """A prior on ``key`` at ``value`` (a ``Pose2`` or a vector)."""
    if isinstance(value, gtsam.Pose2):
        return gtsam.PriorFactorPose2(key, value, noise)
    return gtsam.PriorFactorVector(key, np.asarray(value, dtype=float), noise)


def _culprit(reason: str) -> int | None:
    """The key GTSAM named in an indeterminate-system message ("... (Symbol: l160)")."""
    m = re.search(r"Symbol: ([a-zA-Z])(\d+)", reason)
    return gtsam.symbol(m.group(1), int(m.group(2))) if m else None


class GraphGuard:
    """The guard's part of :class:`fgslam.slam.graph.GraphBackend` (a mixin over its state:
    ``isam``, ``graph``, ``new_graph``, ``new_values``, ``kinds``, ``cal``, ``stats``): the
    guarded update, its repairs, the weak priors and the covariance query with fallbacks."""

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
            reason = f"no finite estimate of {key_name(bad)}"
        except RuntimeError as exc:  # IndeterminantLinearSystemException and kin
            bad, reason = None, gtsam_reason(exc)
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
                names = ", ".join(key_name(k) for k in sorted(new_lms)) or "none"
                what = f"new landmarks removed ({names}), weak priors on the keyframe's poses"
            elif key in new_lms:
                drop.add(key)
                what = f"new landmark {key_name(key)} removed"
            else:
                priors.add(key)
                what = f"weak prior on {key_name(key)}"
            graph = gtsam.NonlinearFactorGraph()
            graph.push_back(self.graph)
            for i in range(self.new_graph.size()):
                f = self.new_graph.at(i)
                if f is not None and not drop.intersection(f.keys()):
                    graph.add(f)
            values = self._values_without(base, drop)
            for key in priors:
                graph.add(self._weakprior_factor(key, values))
            isam = gtsam.ISAM2(self._params)
            try:
                isam.update(graph, values)
                bad = self._unsolved(isam, [k for k in keys if k not in drop])
                if bad is None:
                    break
                reason = f"no finite estimate of {key_name(bad)}"
            except RuntimeError as exc:
                bad, reason = None, gtsam_reason(exc)
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

    def _weakprior_factor(self, key: int, values: gtsam.Values) -> gtsam.NonlinearFactor:
        kind = self._kind(key)
        return prior_factor(key, kind.value(kind.read(values, key)), weak_noise(kind.dim))

    def _kind(self, key: int) -> models.Kind:
        """How variable ``key`` is stored: a pose, the calibration vector or a landmark."""
        sym = gtsam.Symbol(key)
        if sym.chr() in (ord("x"), ord("s")):
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
        return blockdiag(blocks)
