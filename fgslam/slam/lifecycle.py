"""Landmark lifecycle (docs/design.md, 5): ids, tentative -> confirmed, merges, unreliable marks.

- A feature that matches no landmark starts a *tentative* landmark, kept here (world mean and
  covariance, fused from its sightings; not in the estimator). Tentatives are association
  candidates too (an individual gate), so a second sighting is not a second tentative.
- A tentative is *confirmed* (enters the backend) after ``confirm_sightings`` consistent
  sightings over at least ``confirm_keyframes`` keyframes, and only when its sightings
  constrain it: every standard deviation of the estimate its sightings alone give (their
  information summed, relative to the robot, so that the robot's own drift does not count)
  below ``confirm_sigma_m`` (default: a quarter of ``max_range``; a landmark known worse
  than that is not localised) and ``confirm_sigma_rad`` for angles. A landmark seen from
  poses that do not constrain it (e.g. bearing-only-like sightings from one place) never
  reaches the estimator, where it would make the system indeterminate. A tentative not
  seen for ``tentative_keyframes`` keyframes is discarded (counted).
- Duplicates of every kind: two confirmed landmarks whose difference passes a chi-square
  test with their joint covariance (and, lines, whose segments overlap or nearly touch) are
  merged into the older one; the dropped id resolves to the kept one.
- A confirmed landmark predicted in the field of view ``unseen_limit`` times in a row
  without being seen is marked ``unreliable`` (reported in map.json; seen again, it is
  ``confirmed`` again).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from factors.geometry import wrap_angle
from fgslam.frontend.features import Feature
from fgslam.slam import geometry, models
from fgslam.slam.association import Candidate, chi2_gate

TENTATIVE, CONFIRMED, UNRELIABLE = "tentative", "confirmed", "unreliable"
REMOVED = "removed"  # taken out of the estimator (a repaired graph); its id is not reused


@dataclass
class Landmark:
    """A map landmark: kind, lifecycle status, segment ends (lines, world (2, 2)) or corner
    arms (world (2, 2)), and counts of its sightings by source and of supporting sonar
    readings."""

    id: int
    kind: str
    created: float
    ends: NDArray[np.float64] | None = None  # lines: world segment ends
    arms: NDArray[np.float64] | None = None  # corners: the arm ends, world
    observations: Counter = field(default_factory=Counter)  # laser / sonar / fused
    sonar_readings: int = 0
    convex: bool = False
    merged_into: int | None = None
    status: str = CONFIRMED
    sightings: int = 0
    keyframes: int = 0  # distinct keyframes with a sighting
    last_keyframe: int = -1
    misses: int = 0  # predicted in view and not seen, in a row
    mean: NDArray[np.float64] | None = None  # tentatives: fused world estimate
    cov: NDArray[np.float64] | None = None
    line: NDArray[np.float64] | None = None  # lines: the estimate the ends were last put on
    info: NDArray[np.float64] | None = None  # tentatives: information of the sightings alone

    @property
    def active(self) -> bool:
        """In the estimator's map (confirmed or unreliable), not merged away."""
        return self.merged_into is None and self.status in (CONFIRMED, UNRELIABLE)

    @property
    def extent(self) -> NDArray[np.float64] | None:
        """Lines: (s0, s1) along (-sin a, cos a) of the d >= 0 form of the last estimate."""
        if self.ends is None or self.line is None:
            return None
        return np.sort(geometry.along(models.normalize("line", self.line), self.ends))


class Lifecycle:
    """The landmarks of one map and the rules of their lives (see module doc)."""

    def __init__(self, params) -> None:
        self.p = params
        self.landmarks: dict[int, Landmark] = {}
        self._next = 0
        self.stats: Counter = Counter()
        self._tested: dict[tuple[int, int], int] = {}  # pair -> keyframe of a failed test
        self.k = 0  # the current keyframe (set by the caller)

    def resolve(self, lid: int) -> int:
        while self.landmarks[lid].merged_into is not None:
            lid = self.landmarks[lid].merged_into  # type: ignore[assignment]
        return lid

    def new_id(self, t: float, f: Feature, status: str) -> int:
        lid = self._next
        self._next += 1
        self.landmarks[lid] = Landmark(lid, f.kind, t, convex=f.convex, status=status)
        return lid

    # ------------------------------------------------------------------ candidates

    def candidates(
        self, pose: NDArray[np.float64], means: dict[int, NDArray[np.float64]]
    ) -> list[Candidate]:
        """Confirmed (and unreliable) landmarks within ``max_range`` of the robot (lines:
        of their segment), from the means given."""
        lms = [lm for lid, lm in self.landmarks.items() if lm.active and lid in means]
        return [Candidate(lm.id, lm.kind, lm.ends) for lm in self._near(pose, lms, means)]

    def _near(self, pose, lms: list[Landmark], means) -> list[Landmark]:
        if not lms:
            return []
        rows = []
        for lm in lms:
            m = means[lm.id]
            if lm.kind != "line":
                rows.append((m[0], m[1], m[0], m[1]))
            elif lm.ends is not None:
                rows.append((lm.ends[0, 0], lm.ends[0, 1], lm.ends[1, 0], lm.ends[1, 1]))
            else:
                foot = geometry.line_frame(m)[0]
                rows.append((foot[0], foot[1], foot[0], foot[1]))
        ends = np.array(rows, dtype=float)
        d = geometry.segment_distance(np.asarray(pose[:2], dtype=float), ends)
        return [lm for lm, di in zip(lms, d, strict=True) if di < self.p.max_range]

    # ------------------------------------------------------------------ tentatives

    def sight_tentative(
        self,
        t: float,
        k: int,
        f: Feature,
        pose: NDArray[np.float64],
        Pxx: NDArray[np.float64],
    ) -> tuple[int, bool]:
        """A feature no confirmed landmark took: fuse it into the compatible tentative (the
        nearest by Mahalanobis distance) or start one. Returns (id, confirmed now)."""
        lm_w, Hx, Hz = models.to_world(f.kind, pose, f.z)
        Cz = Hz @ f.cov @ Hz.T  # the sighting alone (relative to the robot)
        C = Hx @ Pxx @ Hx.T + Cz
        best, best_d2 = None, chi2_gate(len(lm_w), self.p.tentative_gate_p)
        for lid, lm in self.landmarks.items():
            if lm.status != TENTATIVE or lm.kind != f.kind or lm.last_keyframe == k:
                continue
            e, Hb = models.difference(f.kind, lm_w, lm.mean)
            S = Hb @ lm.cov @ Hb.T + C
            try:
                d2 = float(e @ np.linalg.solve(S, e))
            except np.linalg.LinAlgError:
                continue
            if d2 < best_d2:
                best, best_d2 = lid, d2
        if best is None:
            lid = self.new_id(t, f, TENTATIVE)
            lm = self.landmarks[lid]
            lm.mean, lm.cov = lm_w, C
            lm.info = np.zeros((len(lm_w), len(lm_w)))
            self.stats[f"{f.kind}s_tentative"] += 1
        else:
            lid, lm = best, self.landmarks[best]
            # fuse as a measurement of the tentative's parameters (Kalman, identity model)
            e, Hb = models.difference(f.kind, lm_w, lm.mean)
            Pb = Hb @ lm.cov @ Hb.T
            K = lm.cov @ (-Hb.T) @ np.linalg.inv(Pb + C)
            lm.mean = models.normalize(f.kind, lm.mean + K @ e)
            lm.cov = lm.cov - K @ (-Hb) @ lm.cov
            lm.cov = 0.5 * (lm.cov + lm.cov.T)
        try:
            lm.info = lm.info + np.linalg.inv(Cz)
        except np.linalg.LinAlgError:
            pass  # a degenerate sighting adds nothing
        lm.sightings += 1
        if lm.last_keyframe != k:
            lm.keyframes += 1
            lm.last_keyframe = k
        return lid, self._confirmable(lm)

    def _confirmable(self, lm: Landmark) -> bool:
        p = self.p
        if lm.sightings < p.confirm_sightings or lm.keyframes < p.confirm_keyframes:
            return False
        try:
            sig = np.sqrt(np.maximum(np.diag(np.linalg.inv(lm.info)), 0.0))
        except np.linalg.LinAlgError:
            sig = np.full(len(lm.info), np.inf)
        lim = np.where(
            models.ANGULAR[lm.kind], p.confirm_sigma_rad, p.confirm_sigma_m or p.max_range / 4
        )
        if not np.all(sig <= lim):
            self.stats[f"{lm.kind}s_unconstrained"] += 1
            return False
        return True

    def confirm(self, lid: int) -> None:
        lm = self.landmarks[lid]
        lm.status = CONFIRMED
        lm.misses = 0
        self.stats[f"{lm.kind}s_confirmed"] += 1

    def expire(self, k: int) -> None:
        """Discard (forget) the tentatives not seen for ``tentative_keyframes`` keyframes;
        their ids are not reused."""
        old = [
            lid
            for lid, lm in self.landmarks.items()
            if lm.status == TENTATIVE and k - lm.last_keyframe > self.p.tentative_keyframes
        ]
        for lid in old:
            self.stats[f"{self.landmarks.pop(lid).kind}s_never_confirmed"] += 1

    def remove(self, lid: int) -> None:
        """``lid`` left the estimator (the backend removed it): no longer active."""
        lm = self.landmarks.get(lid)
        if lm is None:  # never the map's (a variable the backend was given directly)
            return
        lm.status = REMOVED
        self.stats[f"{lm.kind}s_removed"] += 1

    # ------------------------------------------------------------------ merges, visibility

    def merge(self, keep: int, drop: int) -> None:
        """``drop`` is ``keep`` from now on: counts move over (geometry: the caller's)."""
        a, b = self.landmarks[keep], self.landmarks[drop]
        b.merged_into = keep
        a.observations.update(b.observations)
        a.sonar_readings += b.sonar_readings
        a.sightings += b.sightings

    def duplicates(self, lids: list[int], means, estimate) -> list[tuple[int, int]]:
        """Pairs (keep, drop): each landmark of ``lids`` against the active landmarks of its
        kind that pass a cheap pre-gate on the means (vectorised), then the chi-square test on
        their difference with the joint covariance (lines: and whose segments overlap or leave
        at most ``max_gap``). The older landmark is kept."""
        p = self.p
        by_kind: dict[str, tuple[list[int], NDArray[np.float64]]] = {}
        for lid, lm in self.landmarks.items():
            if lm.active and lid in means:
                by_kind.setdefault(lm.kind, ([], []))[0].append(lid)
        for kind, (ids, _) in list(by_kind.items()):
            by_kind[kind] = (ids, np.array([means[i] for i in ids], dtype=float))
        # the pre-gate of every queried landmark of a kind against all of its kind at once
        near: dict[int, NDArray[np.intp]] = {}
        queried = [a for a in lids if a in means and self.landmarks[a].active]
        for kind, (_, M) in by_kind.items():
            qs = [a for a in queried if self.landmarks[a].kind == kind]
            if not qs:
                continue
            E = models.differences(kind, np.array([means[a] for a in qs], dtype=float), M)
            lim = np.where(models.ANGULAR[kind], p.duplicate_pregate_rad, p.duplicate_pregate_m)
            for a, ok in zip(qs, np.all(np.abs(E) <= lim, axis=2), strict=True):
                near[a] = np.flatnonzero(ok)
        out: list[tuple[int, int]] = []
        done: set[int] = set()
        for a in lids:
            la = self.landmarks[a]
            if a not in means or a in done or not la.active:
                continue
            ids, _ = by_kind[la.kind]
            for j in near[a]:
                b = ids[j]
                lb = self.landmarks[b]
                if b == a or b in done:
                    continue
                pair = (min(a, b), max(a, b))
                if self.k - self._tested.get(pair, -(10**9)) < p.duplicate_retest:
                    continue  # failed recently: the joint covariance query is the costly part
                if la.kind == "line":
                    if la.ends is None or lb.ends is None:
                        continue
                    if geometry.overlap(means[a], la.ends, lb.ends) < -p.max_gap:
                        continue
                m, P = estimate([a, b])
                e, Hb = models.difference(la.kind, m[a], m[b])
                n = len(e)
                J = np.hstack([np.eye(n), Hb])
                S = J @ P[3:, 3:] @ J.T
                try:
                    d2 = float(e @ np.linalg.solve(S, e))
                except np.linalg.LinAlgError:
                    continue
                self._tested[pair] = self.k
                if d2 < chi2_gate(n, p.duplicate_p):
                    keep, drop = (a, b) if la.created <= lb.created else (b, a)
                    out.append((keep, drop))
                    done.update((a, b))
                    self.stats[f"{la.kind}_duplicates_merged"] += 1
                    break
        return out

    def visibility(self, pose, means, seen: set[int]) -> None:
        """Count, per active landmark in range and in the field of view, misses in a row;
        mark ``unreliable`` after ``unseen_limit`` of them."""
        p = self.p
        half = 0.5 * p.fov
        for lid, lm in self.landmarks.items():
            if not lm.active or lid not in means:
                continue
            if lid in seen:
                lm.misses = 0
                if lm.status == UNRELIABLE:
                    lm.status = CONFIRMED
                continue
            if lm.kind == "line":
                if lm.ends is None:
                    continue
                q = 0.5 * (lm.ends[0] + lm.ends[1])
            else:
                q = means[lid][:2]
            dx, dy = q[0] - pose[0], q[1] - pose[1]
            if math.hypot(dx, dy) > p.max_range:
                continue
            if abs(wrap_angle(math.atan2(dy, dx) - pose[2])) > half:
                continue
            lm.misses += 1
            if lm.misses >= p.unseen_limit and lm.status == CONFIRMED:
                lm.status = UNRELIABLE
                self.stats[f"{lm.kind}s_unreliable"] += 1
