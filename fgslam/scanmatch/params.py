"""Parameters of the scan matcher (:class:`MatchParams`; m, rad): the ``[matcher]`` section
of the configuration, defined with every other parameter in :mod:`fgslam.config`
(docs/design.md, 2)."""

from __future__ import annotations

from fgslam.config import MatchParams

__all__ = ["MatchParams"]
