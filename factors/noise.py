"""The one noise scheme of the graph (docs/design.md, 3.7, 6): every measurement's GTSAM noise
model is built here from its covariance and a robust kernel's name, by :func:`noise_model`.

A covariance goes in floored (:func:`floored`: symmetric, every eigenvalue at least
:data:`VARIANCE_FLOOR`); a kernel other than "none" wraps the Gaussian in GTSAM's
``noiseModel.Robust`` with the M-estimator of :func:`m_estimator`, whose threshold is the 95 %
quantile of the whitened residual's norm for a correct measurement.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

ROBUST_KERNELS = ("none", "huber", "cauchy", "dcs")
CHI2_95 = {1: 3.841, 2: 5.991, 3: 7.815}

# the smallest variance a noise model takes (sigma 1 um, 1 urad): below every real sensor, so
# that a model parameter that comes out as zero (a standing robot's odometry) gives a factor
# of finite information instead of a singular system; the sensors' own floors are larger
VARIANCE_FLOOR = 1e-12


def m_estimator(kernel: str, dim: int) -> gtsam.noiseModel.mEstimator.Base | None:
    """The M-estimator of a robust noise model for ``dim``-dimensional residuals (None for
    "none"). GTSAM weighs by the norm of the whitened residual, which is chi-distributed
    with ``dim`` dof for a correct association: the threshold k is its 95 % quantile,
    sqrt(chi2_95(dim)), so correct sightings keep (nearly) full weight."""
    if kernel == "none":
        return None
    k = math.sqrt(CHI2_95[dim])
    if kernel == "huber":
        return gtsam.noiseModel.mEstimator.Huber.Create(k)
    if kernel == "cauchy":
        return gtsam.noiseModel.mEstimator.Cauchy.Create(k)
    if kernel == "dcs":
        return gtsam.noiseModel.mEstimator.DCS.Create(k * k)
    raise ValueError(f"unknown robust kernel {kernel!r}; expected one of {ROBUST_KERNELS}")


def floored(cov: ArrayLike) -> NDArray[np.float64]:
    """``cov`` made symmetric with every eigenvalue at least :data:`VARIANCE_FLOOR`; raises
    ValueError when it is not finite."""
    cov = np.asarray(cov, dtype=float)
    if not np.all(np.isfinite(cov)):
        raise ValueError(f"a covariance that is not finite: {cov.tolist()}")
    cov = 0.5 * (cov + cov.T)
    w, V = np.linalg.eigh(cov)
    if w.min() >= VARIANCE_FLOOR:
        return cov
    return (V * np.maximum(w, VARIANCE_FLOOR)) @ V.T


def noise_model(cov: ArrayLike, kernel: str = "none") -> gtsam.noiseModel.Base:
    """THE noise model of a measurement: Gaussian of covariance ``cov`` (:func:`floored`),
    robust with ``kernel`` (one of :data:`ROBUST_KERNELS`, see :func:`m_estimator`)."""
    noise = gtsam.noiseModel.Gaussian.Covariance(floored(cov))
    est = m_estimator(kernel, len(cov))
    return noise if est is None else gtsam.noiseModel.Robust.Create(est, noise)
