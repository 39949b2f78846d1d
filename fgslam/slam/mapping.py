"""Map management parameters (paper IV, docs/design.md, 5), shared by every backend.

The work is split by responsibility: :mod:`fgslam.slam.association` (pure: estimate in,
decisions out), :mod:`fgslam.slam.lifecycle` (ids, tentative/confirmed, merges, unreliable
marks), :mod:`fgslam.slam.geometry` (segment ends and corner arms in world coordinates), and
:mod:`fgslam.slam.step` (the per-keyframe protocol that uses them). World frame, m, rad.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from fgslam.config import RobotConfig, frontend_thresholds
from fgslam.slam.association import AssociationParams
from fgslam.slam.lifecycle import Landmark

__all__ = ["Landmark", "MapParams"]


@dataclass(frozen=True)
class MapParams:
    """Map management thresholds (m, rad; gates as probabilities)."""

    # association (see fgslam.slam.association)
    association: str = "jcbb"  # "jcbb" or "nn" (the old greedy nearest neighbour)
    gate_p: float = 0.99
    ambiguous_p: float = 0.9999
    ambiguity_margin: float = 1.0
    merge_overlap: float = 0.4  # a measurement covering this much of two lines merges them
    max_gap: float = 0.5  # a line measurement may extend a map line by leaving this gap
    sonar_line_gap: float = 1.0  # a sonar plane's foot point within this of a map line
    pregate: tuple[float, float, float] = (0.35, 1.0, 0.6)
    # geometry
    min_line_length: float = 0.7  # only longer lines enter the map
    big_step: float = 0.5  # endpoint moved this fraction toward a reliable measured end
    small_step: float = 0.1  # ... toward an unreliable one
    max_range: float = 10.0  # landmarks farther than this are not association candidates
    fov: float = 3.141592653589793  # field of view for "predicted in view" (rad)
    # lifecycle (see fgslam.slam.lifecycle; N and the window: CHANGELOG.md, issue 12)
    confirm_sightings: int = 2
    confirm_keyframes: int = 2
    confirm_sigma_m: float | None = None  # sightings constrain a landmark this well (None:
    confirm_sigma_rad: float = 0.5  # max_range / 4); angles: rad
    tentative_keyframes: int = 10  # a tentative unseen this long is discarded
    tentative_gate_p: float = 0.99
    duplicate_p: float = 0.99
    duplicate_pregate_m: float = 0.5
    duplicate_pregate_rad: float = 0.2
    duplicate_retest: int = 10  # a pair that failed the test is tested again after this
    unseen_limit: int = 30  # predicted in view this often in a row, unseen: unreliable

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> MapParams:
        """The defaults with the sensor-dependent thresholds of ``cfg``
        (:func:`fgslam.config.frontend_thresholds`)."""
        return cls(max_range=frontend_thresholds(cfg)["map_max_range"])

    def association_params(self) -> AssociationParams:
        names = {f.name for f in fields(AssociationParams)}
        kw = {k: getattr(self, k) for k in names if hasattr(self, k)}
        return AssociationParams(method=self.association, **kw)
