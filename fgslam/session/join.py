"""Continuing a saved session with a new log (``fgslam run LOG --continue DIR``;
docs/sessions.md).

The new log is first localized on the saved map (:class:`~fgslam.session.localize.Localizer`,
from ``--initial-pose`` or by the global search) as far as its first tracked match: the
*anchor*, the pose (map's world frame) of one of its scans. Mapping then starts at that scan:
the graph holds the saved keyframes first (their poses as the initial estimate, their scan
and odometry links and loop closures as between factors, :meth:`Continuation.replay`), and
the new log's first keyframe is tied to the saved keyframe nearest the anchor by the anchor's
match (a between factor with the match's covariance; the link from the last saved keyframe
is left out: the new log did not start there). Loop closures between the new keyframes and the
saved ones are then searched as in any run, which joins the two graphs. The saved keyframes'
times are shifted to end before the new log's first (``time_offset``, recorded in the
session's ``segments``).

What a continued run does not do: the log's stretch before the anchor is not mapped (the
robot's place on the map is not known there), and the saved landmarks are carried into the
joined session as they were, not associated with the new log's features (their saved
covariances would count the old measurements twice); the new run builds its own.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from factors.geometry import between_poses
from factors.odometry import Preintegrated, relative_pose
from fgslam.config import RobotConfig
from fgslam.errors import UserError
from fgslam.events import Event
from fgslam.session.localize import Localizer
from fgslam.session.store import Session

TIME_GAP = 1.0  # s between the last saved keyframe and the new log's first event, at least
# a link between two saved keyframes that the session does not hold (m, m, rad): the saved
# poses' difference, keeping the chain whole with next to no information
BRIDGE_SIGMA = (100.0, 100.0, 3.0)


@dataclass
class Anchor:
    """Where the new log was first placed on the map: its scan at ``t`` (s, the log's
    clock) at ``pose`` (world, m, rad) with covariance ``cov`` (body frame, GTSAM's between
    convention), matched against the map near saved keyframe ``keyframe``; ``how``: "global
    search" or "initial pose"; ``log_start``: the log's first event time (s)."""

    t: float
    pose: NDArray[np.float64]
    cov: NDArray[np.float64]
    keyframe: int
    how: str
    log_start: float

    def to_json(self) -> dict[str, Any]:
        return {
            "t": round(self.t, 6),
            "pose": [round(float(v), 6) for v in self.pose],
            "sigma": [round(float(v), 6) for v in np.sqrt(np.diag(self.cov))],
            "keyframe": self.keyframe,
            "how": self.how,
            "after_s": round(self.t - self.log_start, 3),
        }


def find_anchor(
    session: Session,
    events: Iterable[Event],
    cfg: RobotConfig,
    initial_pose: tuple[float, float, float] | None = None,
    progress: Callable[[float], None] | None = None,
) -> Anchor:
    """Localize ``events`` on ``session`` up to the first tracked match (reads no further);
    :class:`UserError` when the log ends first."""
    loc = Localizer(session, cfg, initial_pose, progress=progress)
    for ev in events:
        loc.add(ev)
        if loc.first_fix is not None:
            break
    else:
        loc.finish()
    if loc.first_fix is None:
        raise UserError(
            "the log was never localized on the saved map, so it cannot continue it "
            "(does it start where the map was made? try --initial-pose X,Y,THETA)"
        )
    t, pose, cov = loc.first_fix
    how = next(e["how"] for e in reversed(loc.events) if e["event"] == "localized")
    has = np.array([s is not None for s in session.scans])
    d = np.hypot(*(session.poses[:, :2] - pose[:2]).T)
    d[~has] = np.inf
    return Anchor(t, pose, cov, int(np.argmin(d)), how, float(loc.first_t))


@dataclass
class Continuation:
    """A saved session to continue and the new log's :class:`Anchor` on it; ``source``
    names the session (its folder)."""

    session: Session
    anchor: Anchor
    source: str = ""

    @property
    def keyframes(self) -> int:
        return self.session.keyframes

    @property
    def time_offset(self) -> float:
        """s added to the saved scans' times: 0 when they end before the new log starts,
        else what makes them end :data:`TIME_GAP` before it."""
        last = float(max(self.session.times[-1], self.session.between[:, 0].max(initial=-np.inf)))
        if last < self.anchor.log_start:
            return 0.0
        return self.anchor.log_start - TIME_GAP - last

    def to_json(self) -> dict[str, Any]:
        """report.json's ``continued``."""
        return {
            "session": self.source,
            "saved_keyframes": self.keyframes,
            "time_offset_s": self.time_offset,
            "anchor": self.anchor.to_json(),
        }

    def times(self) -> NDArray[np.float64]:
        return self.session.times + self.time_offset

    def links(self) -> list[tuple[NDArray[np.float64], NDArray[np.float64], str] | None]:
        """The saved link into each keyframe after the first ((x, y, theta) in the one
        before's frame, covariance, kind "scan" or "odometry"), None where none was saved."""
        out: list = [None] * max(self.keyframes - 1, 0)
        for c in self.session.constraints:
            i, j = c["from"], c["to"]
            if c["kind"] in ("scan", "odometry") and j == i + 1 and 0 <= i < len(out):
                out[i] = (np.asarray(c["pose"], float), np.asarray(c["cov"], float), c["kind"])
        return out

    def replay(
        self,
    ) -> tuple[list[Preintegrated], list[tuple[int, int, Preintegrated]], int]:
        """The graph's saved part: a link per keyframe after the first (a pair without a
        saved link: the saved poses' difference, weak) and the loop closures and earlier
        anchors as (j, k, measurement); and how many pairs had no link."""
        p = self.session.poses
        links, missing = [], 0
        for i, link in enumerate(self.links()):
            if link is None:
                missing += 1
                links.append(relative_pose(between_poses(p[i], p[i + 1]), bridge_cov()))
            else:
                links.append(relative_pose(link[0], link[1]))
        loops = [
            (int(c["from"]), int(c["to"]), relative_pose(c["pose"], c["cov"]))
            for c in self.session.constraints
            if c["kind"] in ("loop", "anchor")
        ]
        return links, loops, missing

    def first_link(
        self, pose: NDArray[np.float64], cov: NDArray[np.float64]
    ) -> tuple[int, Preintegrated]:
        """The new log's first keyframe at ``pose`` (world) with covariance ``cov`` (body
        frame) as seen from the saved keyframe nearest the anchor: (j, measurement)."""
        j = self.anchor.keyframe
        return j, relative_pose(between_poses(self.session.poses[j], pose), cov)

    def constraints(self, first_new: int) -> list[dict[str, Any]]:
        """The saved loop closures and anchors, and this run's anchor (into keyframe
        ``first_new``), as session constraints (:class:`~fgslam.session.store.Session`)."""
        out = [dict(c) for c in self.session.constraints if c["kind"] in ("loop", "anchor")]
        j = self.anchor.keyframe
        rel = between_poses(self.session.poses[j], self.anchor.pose)
        out.append(
            {
                "kind": "anchor",
                "from": j,
                "to": int(first_new),
                "pose": [float(v) for v in rel],
                "cov": np.asarray(self.anchor.cov, float).tolist(),
            }
        )
        return out

    def segments(self, log: str, new_keyframes: int) -> list[dict[str, Any]]:
        """The joined session's parts: each log's keyframes [first, end) and the seconds
        added to its times."""
        off = self.time_offset
        old = self.session.meta.get("segments") or [
            {
                "log": self.session.meta.get("log", ""),
                "keyframes": [0, self.keyframes],
                "time_offset": 0.0,
            }
        ]
        segs = [dict(s, time_offset=float(s.get("time_offset", 0.0)) + off) for s in old]
        n = self.keyframes
        segs.append(
            {
                "log": log,
                "keyframes": [n, n + int(new_keyframes)],
                "time_offset": 0.0,
                "anchor": self.anchor.to_json(),
            }
        )
        return segs


def bridge_cov() -> NDArray[np.float64]:
    return np.diag(np.square(BRIDGE_SIGMA))
