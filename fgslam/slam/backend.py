"""The interface every SLAM backend offers the map manager and the runner (world frame)."""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod

import numpy as np
from numpy.typing import NDArray

from factors.odometry import Preintegrated
from factors.sensor_models import laser_feature_time_inflation
from fgslam.frontend.features import Feature
from fgslam.slam.calibration import Calibration

# landmark means by id, and the joint covariance of [pose, those landmarks] in world
# coordinates (pose x, y, theta first; then each landmark's parameters in the order given)
Estimate = tuple[dict[int, NDArray[np.float64]], NDArray[np.float64]]


class Backend(ABC):
    """One keyframe at a time: :meth:`predict` with the odometry since the last keyframe, then
    :meth:`observe` / :meth:`add_landmark` / :meth:`merge` as the map manager decides, then
    :meth:`commit`. ``trajectory`` collects (t, pose, 3x3 covariance) per keyframe as the
    backend estimated it at that time (filtered for the EKF); :meth:`finish` returns the final
    (smoothed, for graphs) trajectory."""

    name = "backend"
    cal: Calibration | None = None  # the calibration errors estimated (None: none)
    # s: a scan's time error where it is modelled once per scan (``[laser] time_registration
    # = "per-scan"``; 0: the front end inflated the features already, or no time error)
    time_sigma: float = 0.0

    def __init__(self) -> None:
        self.trajectory: list[tuple[float, NDArray[np.float64], NDArray[np.float64]]] = []
        self._pending_t = 0.0

    @abstractmethod
    def start(
        self,
        t: float,
        pose: NDArray[np.float64],
        cov: NDArray[np.float64],
        *,
        twist: tuple[float, float] = (0.0, 0.0),
    ) -> None: ...

    # whether :meth:`keyframe_poses`, :meth:`relative` and :meth:`add_loop` work (a filter
    # keeps no past poses to close a loop on)
    supports_loops = False

    @abstractmethod
    def predict(
        self,
        t: float,
        pre: Preintegrated | None,
        scan: Preintegrated | None = None,
        *,
        twist: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        """A new keyframe at ``t``, reached by the wheel odometry ``pre`` and/or the scan
        match ``scan`` (relative poses from the last keyframe; at least one given); ``twist``
        the robot's (speed m/s, turn rate rad/s) at its scan."""

    def time_registered(self, features: list[Feature], twist: tuple[float, float]) -> list[Feature]:
        """The keyframe's features as this backend weighs the scan's time error modelled per
        scan (:attr:`time_sigma`, ``twist`` the robot's (m/s, rad/s) at the scan): a backend
        with no pose at the scan's true time (a filter) inflates each laser line and corner by
        the motion, as the front end does per feature (docs/design.md, 3.4)."""
        if not self.time_sigma:
            return features
        out = []
        for f in features:
            if f.source in ("laser", "fused") and f.kind in ("line", "corner"):
                cov = laser_feature_time_inflation(
                    f.cov, f.kind, twist[0], twist[1], self.time_sigma
                )
                f = dataclasses.replace(f, cov=cov)
            out.append(f)
        return out

    @abstractmethod
    def pose(self) -> NDArray[np.float64]:
        """Current (predicted or updated) pose estimate (x, y, theta)."""

    @abstractmethod
    def estimate(self, lids: list[int]) -> Estimate: ...

    @abstractmethod
    def means(self) -> dict[int, NDArray[np.float64]]:
        """All landmark means (world parameters) by id."""

    @abstractmethod
    def observe(self, lid: int, f: Feature) -> None: ...

    @abstractmethod
    def add_landmark(self, lid: int, f: Feature) -> None: ...

    @abstractmethod
    def merge(self, keep: int, drop: int) -> None: ...

    @abstractmethod
    def commit(self) -> None: ...

    @abstractmethod
    def landmark_covariances(self) -> dict[int, NDArray[np.float64]]: ...

    def take_removed(self) -> list[int]:
        """The landmarks the backend had to remove since the last call (a repaired graph:
        :meth:`fgslam.slam.graph.GraphBackend._repair`); the map manager drops them."""
        return []

    def calibration_estimate(
        self,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None] | None:
        """The calibration errors c (:class:`fgslam.slam.calibration.Calibration`) and their
        covariance (None: not known), or None when the backend does not estimate them."""
        return None

    def measured_calibration_cov(self) -> NDArray[np.float64] | None:
        """The current marginal covariance of the calibration errors that features'
        measurements involve (c at :attr:`Calibration.measured_index`: the laser's range
        errors, the speed of sound), or None when none is estimated."""
        return None

    def _cal_jacobian(self, f: Feature) -> NDArray[np.float64] | None:
        """``f``'s dz/dc (None: it involves no estimated calibration error)."""
        return None if self.cal is None else self.cal.measurement_jacobian(f.Jc)

    def _cal_gain(
        self, J: NDArray[np.float64] | None, z: NDArray[np.float64]
    ) -> NDArray[np.float64] | None:
        """The gain that takes ``J``'s scale columns at the prediction (None: no scale)."""
        return None if self.cal is None else self.cal.measurement_gain(J, z)

    def for_association(self, f: Feature) -> Feature:
        """``f`` as association and the tentative map should weigh it: where the range errors
        it involves are estimated (its ``cov`` then random only), with their uncertainty
        added, J S J^T (S their current marginal; conservative: the landmarks' correlation
        with them, which would cancel part of it, is left out)."""
        J = self._cal_jacobian(f)
        S = None if J is None else self.measured_calibration_cov()
        if S is None:
            return f
        J = J[:, self.cal.measured_index]
        return dataclasses.replace(f, cov=f.cov + J @ S @ J.T)

    def keyframe_poses(self) -> NDArray[np.float64]:
        """Current estimates (x, y, theta) of the keyframes before the current one."""
        raise NotImplementedError(f"{self.name} does not close loops")

    def relative(self, j: int) -> tuple:
        """The current pose in keyframe ``j``'s frame (``gtsam.Pose2``) and its covariance
        (GTSAM's between convention)."""
        raise NotImplementedError(f"{self.name} does not close loops")

    def add_loop(self, j: int, k: int, m: Preintegrated) -> None:
        """A verified relative pose from keyframe ``j`` to keyframe ``k`` (the current one or
        an earlier one)."""
        raise NotImplementedError(f"{self.name} does not close loops")

    def restore(
        self,
        times: NDArray[np.float64],
        poses: NDArray[np.float64],
        links: list[Preintegrated],
        loops: list[tuple[int, int, Preintegrated]],
        cov: NDArray[np.float64],
    ) -> None:
        """Start from saved keyframes (a continued session): keyframe i at ``times[i]`` (s)
        and ``poses[i]`` (world), ``links[i]`` from keyframe i to i + 1, ``loops`` (j, k,
        measurement) between any two, a prior of covariance ``cov`` on the first."""
        raise NotImplementedError(f"{self.name} keeps no past keyframes to continue from")

    def finish(self) -> list[tuple[float, NDArray[np.float64], NDArray[np.float64]]]:
        """The final trajectory estimate: (t, pose, covariance) per keyframe."""
        return self.trajectory
