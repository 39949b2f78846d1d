"""The calibration errors estimated with the map (docs/design.md, 6): one vector c, the graph's
variable ``C`` and the EKF's states 3:3+dim, holding the wheels' relative errors (e_r, e_l, e_b),
the laser's range errors (offset in m, scale in m per m: a range reads r (1 + scale) +
offset) and the sonar's relative speed-of-sound error (``sound``: an echo's range reads
r (1 + sound)), each part when estimated. Odometry moves with the wheel part through the
preintegration's Jacobian; a feature's measurement reads z = h(pose, landmark) + J c + noise,
J its Jacobian w.r.t. the range error sources (:attr:`Feature.Jc`, columns
:data:`SOURCES`) placed in c's columns, its covariance then holding the random errors only.
The layout is the one rule both backends follow for where each part sits in c."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import block_diag

from factors.calibrated import scale_gain
from fgslam.frontend.features import SOURCES

WHEEL_NAMES = ("e_r", "e_l", "e_b")
LASER_NAMES = SOURCES[:2]  # the first one or both
SOUND_NAMES = SOURCES[2:]


@dataclass(frozen=True)
class Calibration:
    """Which calibration errors c holds (``wheels``, ``laser``, ``sound``: their slices of c,
    None when not estimated), their names and their prior covariance (zero mean)."""

    prior: NDArray[np.float64]
    names: tuple[str, ...]
    wheels: slice | None
    laser: slice | None
    sound: slice | None = None

    @staticmethod
    def of(
        wheels: ArrayLike | None = None,
        laser: ArrayLike | None = None,
        sound: ArrayLike | None = None,
    ) -> Calibration | None:
        """c of the parts whose prior covariance is given (wheels 3x3, then the laser's 1x1
        offset or 2x2 offset and scale, then the sound's 1x1); None when none is."""
        blocks, names = [], ()
        sl: dict[str, slice | None] = {"wheels": None, "laser": None, "sound": None}
        parts = (("wheels", wheels, WHEEL_NAMES), ("laser", laser, LASER_NAMES))
        for part, cov, n in (*parts, ("sound", sound, SOUND_NAMES)):
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
        return Calibration(block_diag(*blocks), names, sl["wheels"], sl["laser"], sl["sound"])

    @staticmethod
    def from_config(cfg) -> Calibration | None:
        """The calibration a :class:`fgslam.config.RobotConfig` asks to estimate."""
        return Calibration.of(
            cfg.odometry.calibration_prior(),
            cfg.laser.calibration_prior(),
            cfg.sonar.calibration_prior(),
        )

    @property
    def dim(self) -> int:
        return len(self.names)

    @property
    def measured(self) -> bool:
        """Whether c holds a part that features' measurements involve (laser or sound)."""
        return self.laser is not None or self.sound is not None

    @property
    def measured_index(self) -> NDArray[np.intp]:
        """The indices in c of the parts that features' measurements involve."""
        parts = [sl for sl in (self.laser, self.sound) if sl is not None]
        return np.concatenate([np.arange(sl.start, sl.stop) for sl in parts]).astype(np.intp)

    @property
    def scale_columns(self) -> NDArray[np.intp]:
        """The indices in c of the relative scale errors of measured lengths: the laser's range
        scale (when estimated) and the speed of sound's error."""
        cols = []
        if self.laser is not None and self.laser.stop - self.laser.start == 2:
            cols.append(self.laser.start + 1)
        if self.sound is not None:
            cols.append(self.sound.start)
        return np.array(cols, dtype=np.intp)

    def measurement_gain(
        self, J: NDArray[np.float64] | None, z: NDArray[np.float64]
    ) -> NDArray[np.float64] | None:
        """For a feature's dz/dc ``J`` (:meth:`measurement_jacobian`) and its measurement ``z``:
        the gain that takes the scale columns at the prediction
        (:func:`factors.calibrated.scale_gain`), or None."""
        return None if J is None else scale_gain(J, z, self.scale_columns)

    def wheel_jacobian(self, J: NDArray[np.float64]) -> NDArray[np.float64]:
        """A Jacobian w.r.t. (e_r, e_l, e_b) (rows x 3) as one w.r.t. c (zero elsewhere)."""
        return self._embed(J, self.wheels)

    def _embed(self, J: NDArray[np.float64], sl: slice | None) -> NDArray[np.float64]:
        if sl is None:
            raise ValueError("this part of the calibration is not estimated")
        out = np.zeros((J.shape[0], self.dim))
        out[:, sl] = J
        return out

    def measurement_jacobian(self, Jc: NDArray[np.float64] | None) -> NDArray[np.float64] | None:
        """A feature's dz/dc from its Jacobian w.r.t. the sources (``Jc``: len(z) x
        len(:data:`SOURCES`)), or None where its measurement involves no estimated part
        (then its factor and update stay those without calibration)."""
        if Jc is None or not self.measured:
            return None
        Jc = np.asarray(Jc, dtype=float)
        out = np.zeros((Jc.shape[0], self.dim))
        if self.laser is not None:
            out[:, self.laser] = Jc[:, : self.laser.stop - self.laser.start]
        if self.sound is not None:
            out[:, self.sound] = Jc[:, len(LASER_NAMES) :]
        return out if out.any() else None


def as_calibration(value: Calibration | ArrayLike | None) -> Calibration | None:
    """A backend's ``calibration`` argument: a :class:`Calibration`, or (as before the laser
    part existed) the 3x3 prior covariance of the wheel errors alone, or None."""
    if value is None or isinstance(value, Calibration):
        return value
    return Calibration.of(wheels=value)
