"""The paper's filter: EKF SLAM with the robot pose and line (alpha, d), corner (x, y, theta)
and point (x, y) landmarks in one state vector (world frame, m, rad).

Prediction composes the preintegrated odometry of eq 4 (its covariance in the previous
keyframe's axes); updates use the shared measurement models of ``factors``; new landmarks are
appended with their cross-covariances; merged landmarks (any kind) are tied by a perfect
pseudo-measurement (:func:`fgslam.slam.models.difference`: the one line-flip rule) and the dropped
one is marginalised out of the state.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from factors.geometry import wrap_angle, wrap_angles
from factors.odometry import Preintegrated, fuse_motions, link_motions, with_calibration
from fgslam.config import KeyframeParams
from fgslam.frontend.features import Feature
from fgslam.slam import models
from fgslam.slam.backend import Backend, Estimate
from fgslam.slam.calibration import Calibration, as_calibration


class EkfBackend(Backend):
    """The paper's EKF. Protection matching the graph's robust factors: an innovation outside
    the chi-square gate ``gate_p`` (after the scan's earlier updates) is never applied
    (counted as ``ekf_rejected``); where R is tiny (the merge pseudo-measurement) the update
    is in Joseph form, which keeps P positive semi-definite for any gain.

    ``calibration``: the calibration errors c to estimate (:class:`Calibration`, or the 3x3
    prior covariance of the wheel errors (e_r, e_l, e_b) alone), then states 3:3+dim after
    the pose: the wheel part predicted through the wheel odometry's Jacobian w.r.t. it (a
    link fused with a scan match through the fusion's Jacobian,
    :func:`factors.odometry.fuse_motions`; a scan match alone does not involve it), the
    laser and sound parts in every update of a feature that involves them (:attr:`Feature.Jc`);
    None: off."""

    name = "ekf"
    supports_loops = False  # a filter keeps no past pose to close a loop on

    def __init__(
        self,
        gate_p: float | None = 0.9999,
        motion_gate_p: float = KeyframeParams.motion_gate_p,  # the configuration's default
        calibration: Calibration | NDArray[np.float64] | None = None,
        time_sigma: float = 0.0,
    ) -> None:
        super().__init__()
        self.time_sigma = time_sigma  # per scan: this filter inflates the features itself
        self.cal = as_calibration(calibration)
        self.nc = 0 if self.cal is None else self.cal.dim  # states 3:3+nc
        # None: no gate (the association is given and trusted, e.g. Victoria Park's file)
        self.gate = {n: float(chi2.ppf(gate_p, n)) if gate_p else math.inf for n in (1, 2, 3)}
        self.motion_gate = float(chi2.ppf(motion_gate_p, 3))
        self.stats: Counter = Counter()
        self.x = np.zeros(3)
        self.P = np.zeros((3, 3))
        self.index: dict[int, tuple[int, str]] = {}  # landmark id -> (offset, kind)
        self._angles = np.array([2])  # the state's angles (wrapped after each update)

    def start(
        self,
        t: float,
        pose: NDArray[np.float64],
        cov: NDArray[np.float64],
        *,
        twist: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        self.x = np.array(pose, dtype=float)
        self.P = np.array(cov, dtype=float)
        if self.cal is not None:  # states 3:3+nc, before any landmark
            self.x = np.concatenate([self.x, np.zeros(self.nc)])
            P = np.zeros((3 + self.nc, 3 + self.nc))
            P[:3, :3], P[3:, 3:] = self.P, self.cal.prior
            self.P = P
        self._pending_t = t

    def predict(
        self,
        t: float,
        pre: Preintegrated | None,
        scan: Preintegrated | None = None,
        *,
        twist: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        """Predict with the wheel odometry ``pre`` and/or the scan match ``scan``; with both,
        their fusion, or the scan match alone where the two disagree beyond
        ``motion_gate_p`` (:func:`factors.odometry.link_motions`, counted as
        ``motion_disagreements``): a filter must commit to one motion where the graph keeps
        both as robust factors and lets the landmarks and loops decide."""
        wcal = None if self.cal is None else self.cal.wheels  # the wheel part of c
        if wcal is not None and pre is not None:
            if pre.calibration_jacobian is not None:
                pre = with_calibration(pre, self.x[3:][wcal])
        if pre is None or scan is None:
            pre = pre or scan
            if pre is None:
                raise ValueError("predict needs the wheel odometry, a scan match or both")
        else:
            wheels, scan = link_motions(pre, scan, self.motion_gate)
            if wheels is None:
                self.stats["motion_disagreements"] += 1
                pre = scan
            else:
                pre = fuse_motions(wheels, scan)
        x, y, th = self.x[:3]
        dx, dy, dth = pre.delta.x(), pre.delta.y(), pre.delta.theta()
        c, s = math.cos(th), math.sin(th)
        self.x[:3] = (x + c * dx - s * dy, y + s * dx + c * dy, wrap_angle(th + dth))
        F = np.array([[1.0, 0.0, -s * dx - c * dy], [0.0, 1.0, c * dx - s * dy], [0.0, 0.0, 1.0]])
        G = np.eye(3)
        G[:2, :2] = [[c, -s], [s, c]]
        P = self.P
        if wcal is not None and pre.calibration_jacobian is not None:
            # the pose moves with the calibration errors
            Gc = G @ self.cal.wheel_jacobian(pre.calibration_jacobian)
            c = slice(3, 3 + self.nc)
            P[:3, :] = F @ P[:3, :] + Gc @ P[c, :]
            P[:, :3] = P[:, :3] @ F.T + P[:, c] @ Gc.T
        else:
            P[:3, :] = F @ P[:3, :]
            P[:, :3] = P[:, :3] @ F.T
        P[:3, :3] += G @ pre.covariance_start @ G.T
        self._pending_t = t

    def pose(self) -> NDArray[np.float64]:
        return self.x[:3].copy()

    def estimate(self, lids: list[int]) -> Estimate:
        idx = list(range(3))
        means = {}
        for lid in lids:
            o, kind = self.index[lid]
            n = models.DIM[kind]
            idx.extend(range(o, o + n))
            means[lid] = self.x[o : o + n].copy()
        return means, self.P[np.ix_(idx, idx)].copy()

    def means(self) -> dict[int, NDArray[np.float64]]:
        return {
            lid: self.x[o : o + models.DIM[kind]].copy() for lid, (o, kind) in self.index.items()
        }

    def _update(
        self,
        e: NDArray[np.float64],
        H: NDArray[np.float64],
        R: NDArray[np.float64],
        cols: NDArray[np.intp],
        gate: bool = False,
        joseph: bool = False,
    ) -> bool:
        """EKF update for residual e = prediction - measurement with Jacobian H, given by its
        nonzero columns: ``H`` (m x len(cols)) holds the columns ``cols`` of the state (a
        feature touches the pose and one landmark), so P H^T costs O(n m k), not O(n^2 m);
        the covariance update itself is O(n^2 m). With ``joseph`` (where R is tiny: the merge
        pseudo-measurement) in Joseph form P' = (I - KH) P (I - KH)^T + K R K^T, expanded:
        P - K (PH^T)^T - PH^T K^T + K S K^T; else P - K S K^T (half the cost). With
        ``gate``, an innovation outside the chi-square gate is not applied (returns False)."""
        P = self.P
        PHt = P[:, cols] @ H.T
        S = H @ PHt[cols] + R
        if gate:
            try:
                d2 = float(e @ np.linalg.solve(S, e))
            except np.linalg.LinAlgError:
                d2 = math.inf
            if not d2 <= self.gate[len(e)]:
                self.stats["ekf_rejected"] += 1
                return False
        K = np.linalg.solve(S, PHt.T).T
        self.x -= K @ e
        if joseph:
            KPHt = K @ PHt.T
            self.P = P - KPHt - KPHt.T + K @ S @ K.T
        else:
            self.P = P - K @ (S @ K.T)
        self.P = 0.5 * (self.P + self.P.T)
        self.x[self._angles] = wrap_angles(self.x[self._angles])
        return True

    def _index_angles(self) -> None:
        ang = [2]
        for o, kind in self.index.values():
            ang.extend(o + i for i, a in enumerate(models.ANGULAR[kind]) if a)
        self._angles = np.array(sorted(ang), dtype=np.intp)

    def measured_calibration_cov(self) -> NDArray[np.float64] | None:
        if self.cal is None or not self.cal.measured:
            return None
        idx = 3 + self.cal.measured_index
        return self.P[np.ix_(idx, idx)]

    def observe(self, lid: int, f: Feature) -> None:
        o, kind = self.index[lid]
        n = models.DIM[kind]
        e, Hx, Hl = models.residual(kind, self.x[:3], self.x[o : o + n], f.z)
        J = self._cal_jacobian(f)
        if J is None:
            cols = np.r_[0:3, o : o + n]
            self._update(e, np.hstack([Hx, Hl]), f.cov, cols, gate=True)
            return
        # z = h + J c: the residual and its Jacobian gain the calibration's columns (the
        # scales' taken at the prediction: factors.calibrated.calibrated)
        c = self.x[3 : 3 + self.nc]
        G = self._cal_gain(J, f.z)
        if G is not None:
            k = 1.0 + G @ c
            J = J + e[:, None] * G
            e, Hx, Hl = k * e, k[:, None] * Hx, k[:, None] * Hl
        e = e + J @ c
        cols = np.r_[0 : 3 + self.nc, o : o + n]
        self._update(e, np.hstack([Hx, J, Hl]), f.cov, cols, gate=True)

    def add_landmark(self, lid: int, f: Feature) -> None:
        kind = f.kind
        J = self._cal_jacobian(f)
        z = f.z if J is None else f.z - J @ self.x[3 : 3 + self.nc]
        lm, Hx, Hz = models.to_world(kind, self.x[:3], z)
        n0 = self.x.size
        n = lm.size
        P = self.P
        if J is not None:  # the landmark also moves with the calibration: -Hz J
            Hx = np.hstack([Hx, -Hz @ J])
        m = Hx.shape[1]
        Pxl = Hx @ P[:m, :]  # cross-covariance of the new landmark with the whole state
        Pll = Hx @ P[:m, :m] @ Hx.T + Hz @ f.cov @ Hz.T
        newP = np.zeros((n0 + n, n0 + n))
        newP[:n0, :n0] = P
        newP[n0:, :n0] = Pxl
        newP[:n0, n0:] = Pxl.T
        newP[n0:, n0:] = Pll
        self.P = newP
        self.x = np.concatenate([self.x, lm])
        self.index[lid] = (n0, kind)
        self._index_angles()

    def merge(self, keep: int, drop: int) -> None:
        ok, kind = self.index[keep]
        od, _ = self.index[drop]
        n = models.DIM[kind]
        a, b = self.x[ok : ok + n], self.x[od : od + n]
        e, Hb = models.difference(kind, a, b)
        cols = np.r_[ok : ok + n, od : od + n]
        self._update(e, np.hstack([np.eye(n), Hb]), np.eye(n) * 1e-10, cols, joseph=True)
        keepmask = np.ones(self.x.size, dtype=bool)
        keepmask[od : od + n] = False
        self.x = self.x[keepmask]
        self.P = self.P[np.ix_(keepmask, keepmask)]
        del self.index[drop]
        self.index = {lid: (o - n if o > od else o, k) for lid, (o, k) in self.index.items()}
        self._index_angles()

    def commit(self) -> None:
        self._record(self._pending_t)

    def _record(self, t: float) -> None:
        self.trajectory.append((t, self.x[:3].copy(), self.P[:3, :3].copy()))

    def calibration_estimate(
        self,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None] | None:
        """The calibration errors c (:class:`Calibration`) and their covariance, or None."""
        if self.cal is None:
            return None
        c = slice(3, 3 + self.nc)
        return self.x[c].copy(), self.P[c, c].copy()

    def landmark_covariances(self) -> dict[int, NDArray[np.float64]]:
        return {
            lid: self.P[o : o + models.DIM[k], o : o + models.DIM[k]].copy()
            for lid, (o, k) in self.index.items()
        }
