"""Map management parameters (paper IV, docs/design.md, 5), shared by every backend.

The work is split by responsibility: :mod:`fgslam.slam.association` (pure: estimate in,
decisions out), :mod:`fgslam.slam.lifecycle` (ids, tentative/confirmed, merges, unreliable
marks), :mod:`fgslam.slam.geometry` (segment ends and corner arms in world coordinates), and
:mod:`fgslam.slam.step` (the per-keyframe protocol that uses them). World frame, m, rad.
"""

from __future__ import annotations
