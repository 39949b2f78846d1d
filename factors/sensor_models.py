"""Measurement covariance models (docs/design.md, 3.2-3.5): sonar error model, laser range error
parameters and the laser's time-registration inflation. Units: m, rad, s."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

# Which components of each measurement vector are angles (True) or lengths (False).
LINE_ANGULAR = (True, False)  # (alpha, d)
CORNER_ANGULAR = (True, False, True)  # (phi_c, r_c, gamma)


@dataclass(frozen=True)
class SonarErrorModel:
    """Paper II-B: white noise on the bearing (sigma_bearing, rad) and on the speed of sound
    (relative sigma_sound_rel, so sigma_r = sigma_sound_rel * r)."""

    sigma_bearing: float = math.radians(2.0)
    sigma_sound_rel: float = 0.02

    def covariance(self, r: float) -> NDArray[np.float64]:
        """2x2 covariance of a sonar (bearing, range) at range r (m), and likewise of the
        (alpha, d) line measurement of a plane seen at its normal point."""
        if not math.isfinite(r) or r < 0:
            raise ValueError(f"sonar range must be finite and >= 0, got {r!r}")
        return np.diag([self.sigma_bearing**2, (self.sigma_sound_rel * r) ** 2])

    def plane_to_line(
        self, bearing: float, r: float
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """A sonar plane echo as a line measurement (alpha, d) = (bearing, r), its covariance."""
        return np.array([bearing, r]), self.covariance(r)

    def point(self, bearing: float, r: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """A sonar corner or edge echo as a point measurement (phi, r), its covariance."""
        return np.array([bearing, r]), self.covariance(r)


@dataclass(frozen=True)
class LaserRangeModel:
    """Laser range errors: random sigma (m) and the systematic estimate offset + per_metre*r,
    which the line and corner fits propagate (docs/design.md, 3.2)."""

    sigma_range: float  # the laser's ([laser] sigma_range of the configuration)
    systematic_offset: float = 0.01
    systematic_per_metre: float = 0.002

    def systematic(self, ranges: ArrayLike) -> NDArray[np.float64]:
        """Estimated systematic range error (m) at each range (m)."""
        return self.systematic_offset + self.systematic_per_metre * np.asarray(ranges, float)


def laser_feature_time_inflation(
    covariance: ArrayLike, kind: str, speed: float, turn_rate: float, sigma_t: float
) -> NDArray[np.float64]:
    """:func:`time_registration_inflation` of a laser ``kind`` ("line": (alpha, d), "corner":
    (phi_c, r_c, gamma)) measurement's covariance; speed m/s and turn rate rad/s of either
    sign."""
    angular = LINE_ANGULAR if kind == "line" else CORNER_ANGULAR
    return time_registration_inflation(covariance, angular, abs(speed), abs(turn_rate), sigma_t)


def quantum_common_sigma(resolution: float, sigma_range: float, harmonics: int = 64) -> float:
    """The part of a range quantum's error that beams at (nearly) one range share (m, RMS).

    A reading is the true range plus Gaussian noise, rounded to ``resolution`` q; its error
    has the mean b(x) = E[round(x + n) - x] over the noise, a function of where the true
    range x falls between quanta. With the noise's sigma s_n well above q/2 the noise dithers
    the rounding and b vanishes; below, every beam of a wall at one range shares b(x), which
    no number of beams averages out. By the sawtooth's Fourier series, each harmonic damped
    by the noise's characteristic function: b_rms^2 = sum_k (q / (pi k))^2
    exp(-4 pi^2 k^2 s_n^2 / q^2) / 2, with s_n^2 = ``sigma_range``^2 - q^2 / 12 (the
    configured sigma includes the quantum's own q^2/12). 2.5 mm for the PLS (q 5 cm, sigma
    2 cm); nothing for a SICK LMS (1 cm, 1 cm): below 1 um it is 0."""
    q = float(resolution)
    if not (math.isfinite(q) and math.isfinite(sigma_range)) or q <= 0:
        return 0.0
    sn2 = max(float(sigma_range) ** 2 - q * q / 12.0, 0.0)
    total = sum(
        (q / (math.pi * k)) ** 2 * math.exp(-4.0 * math.pi**2 * k * k * sn2 / (q * q)) / 2.0
        for k in range(1, harmonics + 1)
    )
    rms = math.sqrt(total)
    return rms if rms >= 1e-6 else 0.0


def time_registration_inflation(
    covariance: ArrayLike,
    angular: Sequence[bool],
    speed: float,
    turn_rate: float,
    sigma_t: float,
) -> NDArray[np.float64]:
    """docs/design.md, 3.4: add (v sigma_t)^2 to the positional and (omega sigma_t)^2 to the angular
    diagonal terms of a laser feature's covariance; v in m/s, omega in rad/s, sigma_t in s."""
    C = np.array(covariance, dtype=float)
    if C.shape != (len(angular), len(angular)):
        raise ValueError(f"covariance shape {C.shape} does not match {len(angular)} components")
    if not all(math.isfinite(v) for v in (speed, turn_rate, sigma_t)) or sigma_t < 0:
        raise ValueError("speed, turn rate and sigma_t must be finite, sigma_t >= 0")
    add = np.where(angular, (turn_rate * sigma_t) ** 2, (speed * sigma_t) ** 2)
    return C + np.diag(add)
