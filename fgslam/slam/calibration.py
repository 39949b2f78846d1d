"""The calibration errors estimated with the map (DESIGN 6): one vector c, the graph's variable
``C`` and the EKF's states 3:3+dim, holding the wheels' relative errors (e_r, e_l, e_b) and/or
the laser's range errors (offset in m, scale in m per m: a range reads r (1 + scale) +
offset). Odometry moves with the wheel part through the preintegration's Jacobian; a line or
corner measurement reads z = h(pose, landmark) + Jc c_laser + noise (:attr:`Feature.Jc`), its
covariance then holding the random errors only. The layout is the one rule both backends
follow for where each part sits in c."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import block_diag

WHEEL_NAMES = ("e_r", "e_l", "e_b")
LASER_NAMES = ("laser_offset", "laser_scale")  # the first one or both


@dataclass(frozen=True)
class Calibration:
    """Which calibration errors c holds (``wheels``, ``laser``: their slices of c, None when
    not estimated), their names and their prior covariance (zero mean)."""

    prior: NDArray[np.float64]
    names: tuple[str, ...]
    wheels: slice | None
    laser: slice | None

    @staticmethod
    def of(wheels: ArrayLike | None = None, laser: ArrayLike | None = None) -> Calibration | None:
        """c of the parts whose prior covariance is given (wheels 3x3, then the laser's 1x1
        offset or 2x2 offset and scale); None when neither is."""
        blocks, names = [], ()
        sl: dict[str, slice | None] = {"wheels": None, "laser": None}
        for part, cov, n in (("wheels", wheels, WHEEL_NAMES), ("laser", laser, LASER_NAMES)):
            if cov is None:
                continue
            cov = np.atleast_2d(np.asarray(cov, dtype=float))
            if part == "laser":
                n = n[: len(cov)]
            if cov.shape != (len(n), len(n)):
                raise ValueError(f"{part} calibration prior: expected {len(n)}x{len(n)}")
            sl[part] = slice(len(names), len(names) + len(n))
            blocks.append(cov)
            names = names + n
        if not blocks:
            return None
        return Calibration(block_diag(*blocks), names, sl["wheels"], sl["laser"])

    @staticmethod
    def from_config(cfg) -> Calibration | None:
        """The calibration a :class:`fgslam.config.RobotConfig` asks to estimate."""
        return Calibration.of(cfg.odometry.calibration_prior(), cfg.laser.calibration_prior())

    @property
    def dim(self) -> int:
        return len(self.names)

    def wheel_jacobian(self, J: NDArray[np.float64]) -> NDArray[np.float64]:
        """A Jacobian w.r.t. (e_r, e_l, e_b) (rows x 3) as one w.r.t. c (zero elsewhere)."""
        return self._embed(J, self.wheels)

    def laser_jacobian(self, J: NDArray[np.float64]) -> NDArray[np.float64]:
        """A Jacobian w.r.t. the laser's (offset, scale) (rows x 2) as one w.r.t. c (the
        columns of the parts estimated)."""
        if self.laser is None:
            raise ValueError("the laser's range errors are not estimated")
        return self._embed(J[:, : self.laser.stop - self.laser.start], self.laser)

    def _embed(self, J: NDArray[np.float64], sl: slice | None) -> NDArray[np.float64]:
        if sl is None:
            raise ValueError("this part of the calibration is not estimated")
        out = np.zeros((J.shape[0], self.dim))
        out[:, sl] = J
        return out

    def measurement_jacobian(self, Jc: NDArray[np.float64] | None) -> NDArray[np.float64] | None:
        """A feature's dz/dc (None: its measurement does not involve c)."""
        if self.laser is None or Jc is None:
            return None
        return self.laser_jacobian(np.asarray(Jc, dtype=float))


def as_calibration(value: Calibration | ArrayLike | None) -> Calibration | None:
    """A backend's ``calibration`` argument: a :class:`Calibration`, or (as before the laser
    part existed) the 3x3 prior covariance of the wheel errors alone, or None."""
    if value is None or isinstance(value, Calibration):
        return value
    return Calibration.of(wheels=value)
