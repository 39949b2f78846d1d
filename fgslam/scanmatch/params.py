"""Parameters of the scan matcher (:class:`MatchParams`; m, rad)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from fgslam.config import RobotConfig


@dataclass(frozen=True)
class MatchParams:
    """Parameters of :func:`fgslam.scanmatch.match` (m, rad). Zero for a derived parameter
    means "derive it" (see the field's comment); :meth:`for_laser` derives them from the
    sensor."""

    search_xy: float = 0.3  # half-width (m) of the correlative search window around the guess
    search_theta: float = 0.25  # half-width (rad)
    resolution: float = 0.03  # finest grid cell (m)
    sigma_range: float = 0.01  # laser range noise (m): from the sensor configuration
    max_range: float = 30.0  # beams beyond are ignored (m)
    # correlative search
    angular_step: float = 0.0  # rad between rotations; 0: resolution / far range (1-10 m)
    blur: float = 0.0  # likelihood grid's Gaussian s (m); 0: max(resolution, 2 sigma_range)
    levels: int = 0  # branch-and-bound pyramid depth; 0: coarsest block ~ window / 2
    voxel: float = 0.0  # query voxel filter for the search (m); 0: resolution
    link_distance: float = 0.3  # reference neighbours closer than this are joined (m)
    max_candidates: int = 3000  # most branch-and-bound nodes kept per level
    max_cells: int = 16_000_000  # largest likelihood grid; a wider reference gets coarser cells
    mode_nats: float = 7.0  # response poses within this log-likelihood of the best are kept
    min_coverage: float = 0.3  # fewer query points in the reference's view: search with all
    response_gain: float = 3.0  # nats per point per unit of score in the response weights
    basin_chi2: float = 11.34  # response poses within this Mahalanobis^2 are the best's basin
    # ICP
    icp_iterations: int = 15
    corr_distance: float = 0.3  # largest distance to a corresponding reference point (m)
    normal_radius: float = 0.25  # neighbourhood of a reference point for its normal (m)
    normal_k: int = 24  # at most this many neighbours (including the point)
    robust_scale: float = 3.0  # Cauchy scale in units of the residual sigma
    inlier_sigmas: float = 3.0  # inlier: |point-to-line residual| below this many sigmas
    # covariance
    hac_lags: int = 10  # beams over which residuals may be correlated (Newey-West)
    max_kappa: float = 25.0  # cap on the per-axis inflation from correlated residuals
    cov_inflation: float = 1.3  # constant factor on top of the measured per-axis inflation
    # model error the residuals cannot show (surfaces sampled at other places by the two
    # scans, clutter that is not a line): independent variance added to every match (m, rad)
    floor_xy: float = 0.0
    floor_theta: float = 0.0
    # rejection
    min_points: int = 20  # fewer query or reference points: rejected
    min_score: float = 0.5  # correlative score below: rejected
    min_overlap: float = 0.25  # inlier fraction below: rejected
    max_ambiguity: float = 0.5  # 1-sigma extent / window half-width above: rejected
    max_basins: int = 4  # ICP from this many distinct basins of the response; 1: the best only
    # response poses within this (score x points) below the best are basin starts: on the
    # 3-5 cm grid a basin one door period off scored 8 below the right one in a periodic
    # corridor (tests), so the starts reach further than the response's mode_nats
    basin_nats: float = 20.0

    @classmethod
    def for_laser(
        cls, sigma_range: float, angular_step: float, max_range: float, **kw: float
    ) -> MatchParams:
        """Defaults derived from the sensor: range noise ``sigma_range`` (m), beam spacing
        ``angular_step`` (rad), ``max_range`` (m). The grid cell is 2 sigma (3 cm to 5 cm);
        neighbouring beams at 10 m are joined and corresponded (at least 0.2 m)."""
        spacing = 10.0 * abs(angular_step)
        base = {
            "sigma_range": float(sigma_range),
            "max_range": float(max_range),
            "resolution": float(np.clip(2.0 * sigma_range, 0.03, 0.05)),
            "link_distance": max(0.2, 1.7 * spacing),
            "corr_distance": max(0.2, 1.7 * spacing),
            "normal_radius": max(0.25, 2.2 * spacing),
        }
        base.update(kw)
        # model error: half a grid cell and one beam (measured on real logs' relations)
        base.setdefault("floor_xy", 0.5 * float(base["resolution"]))
        base.setdefault("floor_theta", abs(float(angular_step)))
        return cls(**base)  # type: ignore[arg-type]

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> MatchParams:
        """The matcher for this robot's laser (:meth:`for_laser`), with the ``[scanmatch]``
        section's ``match_resolution`` and ``model_error_*`` where they are set."""
        las = cfg.laser
        step = math.radians(las.fov_deg) / max(las.n_beams - 1, 1)
        kw = {}
        if cfg.scanmatch.match_resolution:
            kw["resolution"] = cfg.scanmatch.match_resolution
        if cfg.scanmatch.model_error_xy >= 0:
            kw["floor_xy"] = cfg.scanmatch.model_error_xy
        if cfg.scanmatch.model_error_theta_deg >= 0:
            kw["floor_theta"] = math.radians(cfg.scanmatch.model_error_theta_deg)
        return cls.for_laser(las.sigma_range, step, las.max_range, **kw)
