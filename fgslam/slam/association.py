"""Data association (docs/design.md, 5): pure functions, the backend's estimate in, decisions out.

Two strategies over the features of one scan, seen from the predicted pose (world x, y, theta):

- ``nn``: the old greedy rule: each feature takes its nearest individually compatible
  landmark (chi-square gate on the innovation with the joint covariance of pose and
  landmark), features independently (two may take the same landmark).
- ``jcbb``: joint compatibility branch and bound (Neira & Tardos 2001): the largest set of
  pairings that is jointly compatible, i.e. whose stacked innovation passes the chi-square
  gate of its total dimension with the joint covariance of the pose and all paired
  landmarks (all predictions of a scan share the pose error); ties go to the smaller joint
  Mahalanobis distance. Mutual exclusion: a landmark takes at most one feature per scan,
  except one wall seen as two segments (two line features whose world segments are
  disjoint may share a line landmark).

Both strategies then reject a point or corner feature that two landmarks explain about equally
well (their distances within ``ambiguity_margin``), and report, for lines, the landmarks that
the measurement covers by at least ``merge_overlap`` (merge candidates, paper IV). A feature
with no compatible landmark but one just outside the gate (chi-square 99.99 %) is ambiguous
too: neither associated nor new.

Means and covariances for the gate come from ``estimate(ids)`` (fresh, the single source);
``means_hint`` (possibly stale by a few keyframes, e.g. GraphBackend's cache) only chooses the
candidates by a loose residual pre-gate, sized so that staleness cannot hide a match that the
fresh gate would accept.
"""

from __future__ import annotations

import functools
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from fgslam.config import ASSOCIATION_METHODS, AssociationParams
from fgslam.frontend.features import Feature
from fgslam.slam import geometry, models

METHODS = ASSOCIATION_METHODS

EstimateFn = Callable[[list[int]], tuple[dict[int, NDArray[np.float64]], NDArray[np.float64]]]


@functools.cache
def chi2_gate(dof: int, p: float = 0.99) -> float:
    """Chi-square quantile ``p`` for ``dof`` degrees of freedom."""
    return float(chi2.ppf(p, dof))


@dataclass(frozen=True)
class Candidate:
    """A landmark that may be seen: id, kind and (lines) its world segment ends."""

    lid: int
    kind: str
    ends: NDArray[np.float64] | None = None


@dataclass
class Association:
    """Decisions for one scan, one entry per feature: ``pairs[i]`` the landmark id or None;
    ``ambiguous[i]`` neither associated nor new; ``merges[i]`` line landmarks the
    measurement covers by ``merge_overlap`` (two or more: they are one wall);
    ``d2[i]`` the individual Mahalanobis distance of the pairing."""

    pairs: list[int | None]
    ambiguous: list[bool]
    merges: list[list[int]]
    d2: list[float]
    joint_d2: float = 0.0
    stats: Counter = field(default_factory=Counter)
    compatible: set[int] = field(default_factory=set)  # individually compatible with any
    pose_cov: NDArray[np.float64] | None = None  # the estimate's pose covariance, if asked


@dataclass
class _Pair:
    lid: int
    d2: float
    overlap: float
    e: NDArray[np.float64]
    row: int  # first row of the pair in the joint covariance C = A P A^T of all pairs


def associate(
    features: list[Feature],
    pose: NDArray[np.float64],
    candidates: list[Candidate],
    means_hint: dict[int, NDArray[np.float64]],
    estimate: EstimateFn,
    params: AssociationParams | None = None,
) -> Association:
    """Associate the features of one scan with the candidate landmarks (see module doc)."""
    p = params or AssociationParams()
    if p.method not in METHODS:
        raise ValueError(f"unknown association {p.method!r}; expected one of {METHODS}")
    n = len(features)
    out = Association([None] * n, [False] * n, [[] for _ in range(n)], [0.0] * n)
    cand = {c.lid: c for c in candidates if c.lid in means_hint}
    # 1. a loose pre-gate on the (possibly stale) hint: which landmarks to ask the estimate for
    pre: list[list[int]]
    needed: set[int] = set()
    by_kind: dict[str, tuple[list[int], NDArray[np.float64]]] = {}
    for kind in {f.kind for f in features}:
        lids = [lid for lid, c in cand.items() if c.kind == kind]
        by_kind[kind] = (lids, np.array([means_hint[lid] for lid in lids]))
    pre = [[] for _ in features]
    groups: dict[tuple[str, int], list[int]] = {}  # features by kind and measurement size
    for i, f in enumerate(features):
        groups.setdefault((f.kind, len(f.z)), []).append(i)
    for (kind, dim), idx in groups.items():
        lids, M = by_kind[kind]
        if not lids:
            continue
        E = models.residuals_grid(kind, pose, M, np.array([features[i].z for i in idx]))
        ok = np.all(np.abs(E) < p.pregate[:dim], axis=2)
        for i, row in zip(idx, ok, strict=True):
            pre[i] = [lids[j] for j in np.flatnonzero(row)]
            needed.update(pre[i])
    ids = sorted(needed)
    if not ids:
        _near_misses(out, features, [[] for _ in features], [False] * n)
        return out
    # 2. the fresh estimate: means and the joint covariance of [pose, ids]
    means, P = estimate(ids)
    out.pose_cov = P[:3, :3].copy()
    offs, o = {}, 3
    for lid in ids:
        offs[lid] = o
        o += models.DIM[cand[lid].kind]
    dimx = o
    # 3. individual compatibility with the fresh means. Every (feature, candidate) pair's
    # Jacobian is a block of rows of one matrix A over the joint state [pose, ids]: one
    # product C = A P A^T holds every pair's innovation covariance (less R) and every cross
    # covariance between pairs (JCBB's), instead of one small product per pair.
    raw: list[tuple[int, int, NDArray[np.float64], int]] = []  # (feature, lid, e, row of C)
    jac: list[tuple[NDArray[np.float64], NDArray[np.float64], int]] = []
    r = 0
    for i, (f, rows) in enumerate(zip(features, pre, strict=True)):
        for lid in rows:
            e, Hx, Hl = models.residual(f.kind, pose, means[lid], f.z)
            raw.append((i, lid, e, r))
            jac.append((Hx, Hl, offs[lid]))
            r += len(e)
    A = np.zeros((r, dimx))
    for (_, _, e, r0), (Hx, Hl, k) in zip(raw, jac, strict=True):
        A[r0 : r0 + len(e), :3] = Hx
        A[r0 : r0 + len(e), k : k + Hl.shape[1]] = Hl
    C = A @ P @ A.T
    d2s = _individual_d2(raw, C, features)
    compat: list[list[_Pair]] = [[] for _ in features]
    near = [False] * n
    meas: dict[int, NDArray[np.float64]] = {}
    for (i, lid, e, r0), d2 in zip(raw, d2s, strict=True):
        if d2 is None:
            continue
        f = features[i]
        if d2 > chi2_gate(len(f.z), p.gate_p):
            near[i] |= d2 < chi2_gate(len(f.z), p.ambiguous_p)
            continue
        ov = np.inf
        if f.kind == "line":
            if i not in meas:
                meas[i] = geometry.measured_ends(f, pose)
            ov = _line_overlap(f, means[lid], cand[lid].ends, meas[i], p)
            if ov is None:
                continue
        compat[i].append(_Pair(lid, d2, ov, e, r0))
    for hits in compat:
        hits.sort(key=lambda h: h.d2)
        out.compatible.update(h.lid for h in hits)
    # 4. the strategy
    if p.method == "nn":
        for i, hits in enumerate(compat):
            if hits:
                out.pairs[i], out.d2[i] = hits[0].lid, hits[0].d2
    else:
        _jcbb(out, features, compat, C, pose, p, meas)
    # 5. line merges, ambiguities, near misses
    for i, (f, hits) in enumerate(zip(features, compat, strict=True)):
        if f.kind == "line":
            big = [h.lid for h in hits if h.overlap >= p.merge_overlap]
            if len(big) >= 2 and out.pairs[i] in big:
                out.merges[i] = big
        elif out.pairs[i] is not None:
            d_best = out.d2[i]
            rivals = [
                h for h in hits if h.lid != out.pairs[i] and h.d2 < d_best + p.ambiguity_margin
            ]
            if rivals:
                out.pairs[i] = None
                out.ambiguous[i] = True
                out.stats[f"{f.kind}s_ambiguous"] += 1
    _near_misses(out, features, compat, near)
    return out


def _near_misses(out: Association, features, compat, near) -> None:
    for i, f in enumerate(features):
        if out.pairs[i] is None and not out.ambiguous[i] and not compat[i] and near[i]:
            out.ambiguous[i] = True
            out.stats[f"{f.kind}s_ambiguous"] += 1


def _individual_d2(
    raw: list[tuple[int, int, NDArray[np.float64], int]],
    C: NDArray[np.float64],
    features: list[Feature],
) -> list[float | None]:
    """Each pair's Mahalanobis distance e S^-1 e, S = its diagonal block of ``C`` plus the
    feature's covariance; solved in one batch per dimension (None: S singular)."""
    out: list[float | None] = [None] * len(raw)
    for dim in {len(e) for _, _, e, _ in raw}:
        idx = [j for j, (_, _, e, _) in enumerate(raw) if len(e) == dim]
        E = np.array([raw[j][2] for j in idx])
        S = np.array(
            [C[raw[j][3] : raw[j][3] + dim, raw[j][3] : raw[j][3] + dim] for j in idx]
        ) + np.array([features[raw[j][0]].cov for j in idx])
        try:
            X = np.linalg.solve(S, E[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:  # one singular block: solve them one by one
            for j, e, Sj in zip(idx, E, S, strict=True):
                try:
                    out[j] = float(e @ np.linalg.solve(Sj, e))
                except np.linalg.LinAlgError:
                    pass
            continue
        for j, d2 in zip(idx, np.einsum("ij,ij->i", E, X), strict=True):
            out[j] = float(d2)
    return out


def _line_overlap(f: Feature, m, ends, meas, p: AssociationParams) -> float | None:
    """Overlap (m) of a measured line with the map segment; None when too far apart. A sonar
    plane has no extent: its foot point must lie within ``sonar_line_gap`` of the segment."""
    if ends is None:
        return 0.0
    if f.endpoints is None:
        s = geometry.along(m, meas[:1])[0]
        e = np.sort(geometry.along(m, ends))
        gap = max(e[0] - s, s - e[1], 0.0)
        return None if gap > p.sonar_line_gap else 0.0
    ov = geometry.overlap(m, ends, meas)
    return None if ov < -p.max_gap else ov


def _jcbb(
    out: Association,
    features: list[Feature],
    compat: list[list[_Pair]],
    C: NDArray[np.float64],
    pose: NDArray[np.float64],
    p: AssociationParams,
    meas: dict[int, NDArray[np.float64]],
) -> None:
    """Joint compatibility branch and bound over the features with candidates; ``C``: the
    joint covariance A P A^T of all pairs (rows ``_Pair.row``); ``meas``: measured world
    ends of line features, where known."""
    order = [i for i, h in enumerate(compat) if h]
    if not order:
        return
    # measured world segments of line features (for the two-segments-of-one-wall exception)
    segs = {i: meas.get(i) for i in order if features[i].kind == "line"}
    for i in segs:
        if segs[i] is None:
            segs[i] = geometry.measured_ends(features[i], pose)
    apart: dict[tuple[int, int], bool] = {}  # (i, j): segments of i and j apart along i's line
    best: dict = {"n": 0, "d2": np.inf, "pairs": {}}
    nodes = [0]
    empty = (0.0, None, None, 0, [])  # (d2, e, Sinv, dof, rows of C in order)
    # the common case first: the nearest-neighbour pairing, if mutually exclusive and jointly
    # compatible, pairs every feature that has a candidate: no hypothesis pairs more
    nn = {i: compat[i][0] for i in order}
    lids = [h.lid for h in nn.values()]
    if len(set(lids)) == len(lids):
        state = empty
        for i, h in nn.items():
            state = _extend(state, h, C, features[i].cov, p.gate_p)
            if state is None:
                break
        else:
            for i, h in nn.items():
                out.pairs[i], out.d2[i] = h.lid, h.d2
            out.joint_d2 = float(state[0])
            out.stats["jcbb_nearest_compatible"] += 1
            return

    def shareable(i: int, lid: int, used: dict[int, list[int]]) -> bool:
        others = used.get(lid)
        if not others:
            return True
        if features[i].kind != "line":
            return False
        if features[i].endpoints is None:
            return False
        for j in others:
            if features[j].endpoints is None:
                return False
            if (i, j) not in apart:
                line = _line_of(features[i], pose)
                apart[i, j] = geometry.overlap(line, segs[j], segs[i]) < 0.0
            if not apart[i, j]:
                return False
        return True

    def rec(level: int, pairs: dict[int, _Pair], used: dict[int, list[int]], state) -> None:
        nodes[0] += 1
        npairs = len(pairs)
        if level == len(order):
            d2 = state[0]
            if npairs > best["n"] or (npairs == best["n"] and d2 < best["d2"]):
                best.update(n=npairs, d2=d2, pairs=dict(pairs))
            return
        if npairs + len(order) - level < best["n"] or nodes[0] > p.max_nodes:
            return
        i = order[level]
        f = features[i]
        for h in compat[i]:
            if not shareable(i, h.lid, used):
                continue
            new = _extend(state, h, C, f.cov, p.gate_p)
            if new is None:
                continue
            pairs[i] = h
            used.setdefault(h.lid, []).append(i)
            rec(level + 1, pairs, used, new)
            used[h.lid].pop()
            del pairs[i]
        # the star branch: feature i unpaired, if it can still beat the best
        if npairs + len(order) - level - 1 >= max(best["n"], 1) or best["n"] == 0:
            rec(level + 1, pairs, used, state)

    rec(0, {}, {}, empty)
    for i, h in best["pairs"].items():
        out.pairs[i], out.d2[i] = h.lid, h.d2
    out.joint_d2 = float(best["d2"]) if best["n"] else 0.0
    out.stats["jcbb_nodes"] += nodes[0]
    if nodes[0] > p.max_nodes:
        out.stats["jcbb_budget_exhausted"] += 1


def _line_of(f: Feature, pose: NDArray[np.float64]) -> NDArray[np.float64]:
    """World (alpha, d) of a line feature seen from ``pose``."""
    return models.to_world("line", pose, f.z)[0]


def _extend(state, h: _Pair, C: NDArray[np.float64], R: NDArray[np.float64], gate_p: float):
    """Add pairing ``h`` (its feature's covariance ``R``) to a hypothesis: incremental inverse
    of the joint innovation covariance (block inversion), its blocks taken from ``C``.
    ``state`` = (d2, e, Sinv, dof, rows of C); None when the joint innovation covariance is
    singular or the extended hypothesis fails the joint gate (chi-square ``gate_p``)."""
    d2, e, Sinv, dof, rows = state
    m = len(h.e)
    new = list(range(h.row, h.row + m))
    s = C[h.row : h.row + m, h.row : h.row + m] + R
    if e is None:
        try:
            Qinv = np.linalg.inv(s)
        except np.linalg.LinAlgError:
            return None
        d2n = float(h.e @ Qinv @ h.e)
        return None if d2n > chi2_gate(m, gate_p) else (d2n, h.e, Qinv, m, new)
    c = C[rows, h.row : h.row + m]  # cross blocks (m_old, m_new)
    k = Sinv @ c
    Q = s - c.T @ k
    try:
        Qinv = np.linalg.inv(Q)
    except np.linalg.LinAlgError:
        return None
    v = h.e - k.T @ e
    d2n = d2 + float(v @ Qinv @ v)
    if d2n > chi2_gate(dof + m, gate_p):
        return None  # the inverse of a hypothesis that goes no further is not needed
    kQ = k @ Qinv
    n0 = len(rows)
    S = np.empty((n0 + m, n0 + m))
    S[:n0, :n0] = Sinv + kQ @ k.T
    S[:n0, n0:] = -kQ
    S[n0:, :n0] = -kQ.T
    S[n0:, n0:] = Qinv
    return (d2n, np.concatenate([e, h.e]), S, dof + m, rows + new)
