"""2-D laser scan matching: see :mod:`fgslam.scanmatch.matcher`."""

from fgslam.scanmatch.matcher import Match, MatchParams, Reference, match, scan_points

__all__ = ["Match", "MatchParams", "Reference", "match", "scan_points"]
