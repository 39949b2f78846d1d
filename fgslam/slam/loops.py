"""Loop closures by scan matching (docs/design.md, 5b; beyond the paper).

At a keyframe, old keyframes whose estimated position lies within ``radius`` of the current
one and that are at least ``min_travel`` of path behind are candidates (nearest first, at
most ``max_candidates``). The current scan is matched against a local map of the candidate's
scan and its ``neighbours`` keyframes either side (placed in the candidate's frame with their
current estimates), searched around the backend's relative pose within a window sized by
that pose's uncertainty (3 sigma, clamped). A closure is accepted only when it is verified:
the match passes its own checks and the current scan does not see through the old place's
surfaces (negative information: at most ``grey_see_through`` of the local map's points that
lie in the scan's view are behind its returns by more than ``see_through_margin``; a
similar-looking room with one thing moved fails here). It enters at once only when nothing
casts doubt on it: its score and overlap reach the stricter loop thresholds, it sees through
at most ``max_see_through``, it agrees with the backend's relative pose and covariance
(chi-square gate ``gate_p`` on the difference), and the estimate is sure of the relative
pose (3 sigma within ``confident_xy`` and ``confident_theta``). A closure in doubt (the first
closure of a long loop, where a similar-looking corridor elsewhere would pass; one that an
overconfident estimate calls inconsistent: on the real logs every such rejection was right,
CHANGELOG.md, issue 14) waits for a second one, from a keyframe at most ``confirm_window``
later, that agrees with it through the estimate's local geometry (both old keyframes in the
old map, both new ones along the new chain: within ``pair_xy`` and ``pair_theta``); then both
enter. A false match rarely repeats consistently. Accepted closures enter the graph as
robust between factors. Every attempt is kept in :attr:`LoopCloser.closures`
(report.json, map.png).

What a search costs (a match over the window is most of it; CHANGELOG.md, issue
14): a candidate's local map is built once and kept (the last ``cache_size`` candidates)
while its keyframes keep their poses relative to it (within ``cache_xy``, ``cache_theta``). A
candidate is not matched when the local map's beams cover less than ``min_view`` of the
current scan placed at the predicted pose (the old scans looked elsewhere: the robot passes
facing the other way; of such matches none passed on MIT CSAIL, Intel and Freiburg 079: 115,
24 and 169), nor when its place (it or a keyframe within 2 ``neighbours`` of it) had a match
rejected at most ``retry_after`` keyframes ago because nothing there fitted the scan (low
score or overlap, too few correspondences, diverged): such a failure mostly repeats at the
next keyframe (there, 52 of 594, 153 of 714 and 100 of 1577 such matches passed), while a
place that fitted but was ambiguous or seen through often passes soon after (27 of 69, 99 of
167, 2 of 5): it is tried again at once (backing off after every rejection, Intel kept 545
of its 707 closures and scored 0.049 instead of 0.048 m).

Frames: scan points in the robot frame (m); poses (x, y, theta) in the world (m, rad).
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter, OrderedDict
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from factors.geometry import (
    between_poses,
    compose_poses,
    invert_pose,
    transform_points,
    wrap_angle,
    wrap_angles,
)
from factors.odometry import relative_pose
from fgslam.config import LoopParams
from fgslam.scanmatch import MatchParams, Reference, match
from fgslam.slam.keyframes import _key, timing_inflation


@dataclass
class Closure:
    """One loop-closure attempt between keyframes ``j`` (old) and ``k`` (current): the
    matched relative pose (x, y, theta of k in j's frame), its covariance (between
    convention), and whether it was accepted (``reason``: why not)."""

    j: int
    k: int
    pose: NDArray[np.float64] | None
    cov: NDArray[np.float64] | None
    accepted: bool
    reason: str
    score: float = 0.0
    overlap: float = 0.0
    mahalanobis2: float = math.nan
    see_through: float = math.nan

    def to_json(self) -> dict:
        return {
            "from": self.j,
            "to": self.k,
            "accepted": self.accepted,
            "reason": self.reason,
            "pose": None if self.pose is None else [round(float(v), 5) for v in self.pose],
            "cov": None if self.cov is None else [float(f"{v:.6g}") for v in np.ravel(self.cov)],
            "score": round(self.score, 4),
            "overlap": round(self.overlap, 4),
            "see_through": None
            if not math.isfinite(self.see_through)
            else round(self.see_through, 4),
            "mahalanobis2": None
            if not math.isfinite(self.mahalanobis2)
            else round(self.mahalanobis2, 3),
        }


AWAITING = "awaiting confirmation"
# rejections of a match that found the old place but doubted it: tried again at once
FITTED = ("ambiguous", "sees through the old place")


@dataclass
class _LocalMap:
    """A candidate's local map as built: its keyframes, their poses in the candidate's frame
    (when they move, it is rebuilt), the points (candidate's frame) and the matcher's
    :class:`fgslam.scanmatch.Reference` of them."""

    keys: tuple[int, ...]
    rel: NDArray[np.float64]
    points: NDArray[np.float64]
    ref: Reference


def see_through(query: NDArray[np.float64], ref: NDArray[np.float64], pose, margin: float) -> float:
    """The fraction of the reference points (their frame) that lie within the query scan's
    view (query robot frame at ``pose`` in the reference frame) but in front of its return
    at that bearing by more than ``margin`` m: surfaces the query sees through. Bearings and
    ranges from the robot origin; points with no return near their bearing are not counted."""
    q = np.asarray(query, dtype=float)
    if len(q) < 2 or not len(ref):
        return 0.0
    x, y, th = (float(v) for v in pose)
    c, s = math.cos(th), math.sin(th)
    d = np.asarray(ref, dtype=float) - (x, y)
    rx, ry = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    rb, rr = np.arctan2(ry, rx), np.hypot(rx, ry)
    qb, qr = np.arctan2(q[:, 1], q[:, 0]), np.hypot(q[:, 0], q[:, 1])
    order = np.argsort(qb)
    qb, qr = qb[order], qr[order]
    step = float(np.median(np.diff(qb))) if len(qb) > 2 else math.radians(1.0)
    i = np.clip(np.searchsorted(qb, rb), 1, len(qb) - 1)
    j = np.where(np.abs(rb - qb[i - 1]) <= np.abs(qb[i] - rb), i - 1, i)
    seen = (np.abs(qb[j] - rb) <= 1.5 * step) & (rr > 0.2)
    if not seen.any():
        return 0.0
    return float(np.mean(qr[j][seen] > rr[seen] + margin))


class LoopCloser:
    """Keeps every keyframe's scan and proposes verified closures (module doc)."""

    def __init__(
        self,
        params: LoopParams,
        match_params: MatchParams,
        origin: tuple[float, float] = (0.0, 0.0),
        sigma_time: float = 0.0,
    ) -> None:
        """``origin``: the laser's position on the robot (m, robot frame); ``sigma_time``
        (s): a scan's time uncertainty, which inflates a closure by the motion at both
        keyframes (:func:`fgslam.slam.keyframes.timing_inflation`)."""
        self.sigma_time = sigma_time
        self.speeds: dict[int, tuple[float, float]] = {}
        self.p = params
        self.mp = match_params
        self.origin = np.asarray(origin, dtype=float).reshape(1, 2)
        self.scans: dict[int, NDArray[np.float64]] = {}
        self.path: list[float] = []  # path length (m) at each keyframe, from its estimate
        self._last_pos: NDArray[np.float64] | None = None
        self.closures: list[Closure] = []
        self.stats: Counter = Counter()
        self._gate = float(chi2.ppf(params.gate_p, 3))
        self.pending: list[Closure] = []  # verified, waiting for a second that agrees
        self._maps: OrderedDict[int, _LocalMap] = OrderedDict()  # least recently used first
        self._rejected: list[tuple[int, int]] = []  # (j, k) of the recent rejected matches

    def add_keyframe(
        self,
        k: int,
        points: NDArray[np.float64] | None,
        pose,
        speed: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        """Keyframe ``k``'s scan (robot frame; None: no laser), its predicted pose and the
        robot's (speed m/s, turn rate rad/s) at it."""
        self.speeds[k] = speed
        pos = np.asarray(pose[:2], dtype=float)
        step = 0.0 if self._last_pos is None else float(np.hypot(*(pos - self._last_pos)))
        self._last_pos = pos
        self.path.append((self.path[-1] if self.path else 0.0) + step)
        if points is not None and len(points):
            self.scans[k] = np.asarray(points, dtype=float)

    def candidates(self, k: int, poses: NDArray[np.float64], pose) -> list[int]:
        """Old keyframes near ``pose`` (world) with enough path in between, nearest first."""
        p = self.p
        n = min(len(poses), k)
        if n == 0:
            return []
        far = np.nonzero(self.path[k] - np.asarray(self.path[:n]) >= p.min_travel)[0]
        if far.size == 0:
            return []
        d = np.hypot(*(poses[far, :2] - np.asarray(pose[:2])).T)
        near = far[d <= p.radius]
        near = near[np.argsort(d[d <= p.radius])]
        out: list[int] = []
        for j in near.tolist():  # one candidate per place: skip neighbours of a chosen one
            if j in self.scans and all(abs(j - o) > 2 * p.neighbours for o in out):
                out.append(j)
            if len(out) >= p.max_candidates:
                break
        return out

    def local_map(
        self, j: int, poses: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Keyframe ``j``'s scan and its neighbours', in ``j``'s frame, and for each point the
        position of the laser that saw it."""
        parts, origins = [], []
        for i in range(j - self.p.neighbours, j + self.p.neighbours + 1):
            if i in self.scans and i < len(poses):
                rel = between_poses(poses[j], poses[i])
                parts.append(transform_points(rel, self.scans[i]))
                origins.append(
                    np.repeat(transform_points(rel, self.origin), len(self.scans[i]), axis=0)
                )
        return np.vstack(parts), np.vstack(origins)

    def reference(self, j: int, poses: NDArray[np.float64]) -> tuple[Reference, NDArray]:
        """Keyframe ``j``'s local map (:meth:`local_map`) prepared for matching, and its
        points: the one built before while none of its keyframes moved more than
        ``cache_xy`` / ``cache_theta`` relative to ``j`` since (module doc)."""
        p = self.p
        keys = tuple(i for i in range(j - p.neighbours, j + p.neighbours + 1) if i in self.scans)
        keys = tuple(i for i in keys if i < len(poses))
        rel = np.array([between_poses(poses[j], poses[i]) for i in keys]).reshape(-1, 3)
        m = self._maps.get(j)
        if m is not None and m.keys == keys:
            d = rel - m.rel
            dth = np.abs(wrap_angles(d[:, 2]))
            if np.hypot(d[:, 0], d[:, 1]).max() <= p.cache_xy and dth.max() <= p.cache_theta:
                self._maps.move_to_end(j)
                self.stats["loop_maps_reused"] += 1
                return m.ref, m.points
        points, origins = self.local_map(j, poses)
        ref = Reference.build(points, self.mp, origins)
        self.stats["loop_maps_built"] += 1
        if p.cache_size > 0:
            self._maps[j] = _LocalMap(keys, rel, points, ref)
            self._maps.move_to_end(j)
            while len(self._maps) > p.cache_size:
                self._maps.popitem(last=False)
        return ref, points

    def view(self, k: int, ref: Reference, guess) -> float:
        """The fraction of keyframe ``k``'s scan that, placed at ``guess`` (x, y, theta in the
        local map's frame), lies in directions the local map's beams covered."""
        q = transform_points(np.asarray(guess, dtype=float), self.scans[k])
        return float(np.mean(ref.covered(q))) if len(q) else 0.0

    def try_close(self, k: int, backend, pose) -> list[Closure]:
        """The closures of keyframe ``k`` (already added with :meth:`add_keyframe`) with the
        backend's estimate; returns the accepted ones (all attempts go to ``closures``)."""
        p = self.p
        if not p.enabled or k not in self.scans or k % p.every:
            return []
        poses = backend.keyframe_poses()
        out: list[Closure] = []
        self._expire(k)
        self._rejected = [(j, kr) for j, kr in self._rejected if k - kr <= p.retry_after]
        for j in self.candidates(k, poses, pose):
            if any(abs(j - jr) <= 2 * p.neighbours for jr, _ in self._rejected):
                self.stats["loop_skipped_place_just_rejected"] += 1
                continue
            rel, rel_cov = backend.relative(j)
            if p.min_view > 0:
                ref, _ = self.reference(j, poses)
                if self.view(k, ref, (rel.x(), rel.y(), rel.theta())) < p.min_view:
                    self.stats["loop_skipped_little_view"] += 1
                    continue
            c = self.verify(j, k, poses, rel, rel_cov)
            self.closures.append(c)
            self.stats["loop_closures_tried"] += 1
            if c.reason == AWAITING:
                out.extend(self._confirm(c, poses, pose))
            elif c.accepted:
                self.stats["loop_closures_accepted"] += 1
                out.append(c)
            else:
                self.stats[f"loop_rejected_{_key(c.reason)}"] += 1
                if not c.reason.startswith(FITTED):
                    self._rejected.append((j, k))
        return out

    def _expire(self, k: int) -> None:
        keep = []
        for c in self.pending:
            if k - c.k > self.p.confirm_window:
                c.reason = "unconfirmed"
                self.stats["loop_rejected_unconfirmed"] += 1
            else:
                keep.append(c)
        self.pending = keep

    def _confirm(self, c2: Closure, poses, pose) -> list[Closure]:
        """Accept ``c2`` and an earlier pending closure that agrees with it, if any; else
        keep ``c2`` pending."""
        p = self.p
        for c1 in self.pending:
            if c1.k == c2.k:
                continue
            old = between_poses(poses[c1.j], poses[c2.j])
            new = between_poses(poses[c1.k], pose) if c1.k < len(poses) else None
            if new is None:
                continue
            pred = compose_poses(compose_poses(invert_pose(old), c1.pose), new)
            d = c2.pose - pred
            dth = wrap_angle(float(d[2]))
            if math.hypot(d[0], d[1]) <= p.pair_xy and abs(dth) <= p.pair_theta:
                self.pending.remove(c1)
                for c in (c1, c2):
                    c.accepted, c.reason = True, ""
                    self.stats["loop_closures_accepted"] += 1
                    self.stats["loop_closures_confirmed_by_a_second"] += 1
                return [c1, c2]
        self.pending.append(c2)
        return []

    def verify(self, j: int, k: int, poses, rel, rel_cov) -> Closure:
        """Match keyframe ``k``'s scan against ``j``'s local map around the predicted relative
        pose ``rel`` (``gtsam.Pose2``; covariance ``rel_cov``, between convention) and check
        the result (module doc)."""
        p = self.p
        guess = np.array([rel.x(), rel.y(), rel.theta()])
        sd = np.sqrt(np.clip(np.diag(rel_cov), 0.0, None))
        mp = dataclasses.replace(
            self.mp,
            search_xy=float(np.clip(3.0 * max(sd[0], sd[1]), p.min_search_xy, p.max_search_xy)),
            search_theta=float(np.clip(3.0 * sd[2], p.min_search_theta, p.max_search_theta)),
        )
        ref, ref_points = self.reference(j, poses)
        m = match(ref, self.scans[k], guess, mp)
        cov = timing_inflation(
            np.asarray(m.cov),
            self.speeds.get(j, (0.0, 0.0)),
            self.speeds.get(k, (0.0, 0.0)),
            self.sigma_time,
        )
        c = Closure(j, k, np.asarray(m.pose, dtype=float), cov, False, "")
        c.score, c.overlap = float(m.score), float(m.overlap)
        if not m.ok:
            c.reason = m.reason or "match rejected"
            return c
        doubt = []  # passed, but only a second closure that agrees may confirm it
        if m.score < p.min_score or m.overlap < p.min_overlap:
            doubt.append("weak match")
        c.see_through = see_through(self.scans[k], ref_points, m.pose, p.see_through_margin)
        if c.see_through > p.grey_see_through:
            c.reason = "sees through the old place"
            return c
        if c.see_through > p.max_see_through:
            doubt.append("sees through a little")
        meas = relative_pose(m.pose, cov)
        xi = rel.localCoordinates(meas.delta)
        S = np.asarray(rel_cov) + meas.covariance
        try:
            c.mahalanobis2 = float(xi @ np.linalg.solve(S, xi))
        except np.linalg.LinAlgError:
            c.mahalanobis2 = math.inf
        if not c.mahalanobis2 <= self._gate:
            doubt.append("inconsistent with the estimate")
        if 3.0 * max(sd[0], sd[1]) > p.confident_xy or 3.0 * sd[2] > p.confident_theta:
            doubt.append("uncertain estimate")
        if doubt and not p.doubt and doubt != ["uncertain estimate"]:
            c.reason = next(d for d in doubt if d != "uncertain estimate")
            return c
        if doubt:
            for d in doubt:
                self.stats[f"loop_doubt_{_key(d)}"] += 1
            c.reason = AWAITING
            return c
        c.accepted = True
        return c
