"""A frozen copy of fgslam.slam.association as of commit d4a6cdb (per-pair covariances,
JCBB on per-pair blocks): the reference that the vectorised module is tested against
(test_association_equivalence.py). Not used by the package."""

from __future__ import annotations

import functools
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from fgslam.frontend.features import Feature
from fgslam.slam import geometry, models

METHODS = ("jcbb", "nn")

EstimateFn = Callable[[list[int]], tuple[dict[int, NDArray[np.float64]], NDArray[np.float64]]]


@functools.cache
def chi2_gate(dof: int, p: float = 0.99) -> float:
    """Chi-square quantile ``p`` for ``dof`` degrees of freedom."""
    return float(chi2.ppf(p, dof))


@dataclass(frozen=True)
class AssociationParams:
    """Association thresholds; gates are probabilities, lengths m, angles rad."""

    method: str = "jcbb"
    gate_p: float = 0.99  # individual and joint chi-square gate
    ambiguous_p: float = 0.9999  # a miss inside this gate is a near miss (ambiguous)
    ambiguity_margin: float = 1.0  # chi-square units: two hypotheses "equally good"
    merge_overlap: float = 0.4  # a measurement covering this much of two lines merges them
    max_gap: float = 0.5  # a line measurement may extend a map line by leaving this gap
    sonar_line_gap: float = 1.0  # a sonar plane's foot point within this of a map line
    # residuals beyond these (rad or m, per component) cannot pass any sensible gate
    pregate: tuple[float, float, float] = (0.35, 1.0, 0.6)
    max_nodes: int = 1000  # branch-and-bound budget per scan (then: the best so far)


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
    A: NDArray[np.float64]  # Jacobian w.r.t. the joint state [pose, candidates]


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
    pre: list[list[int]] = []
    needed: set[int] = set()
    by_kind: dict[str, tuple[list[int], NDArray[np.float64]]] = {}
    for kind in {f.kind for f in features}:
        lids = [lid for lid, c in cand.items() if c.kind == kind]
        by_kind[kind] = (lids, np.array([means_hint[lid] for lid in lids]))
    for f in features:
        lids, M = by_kind[f.kind]
        rows: list[int] = []
        if lids:
            E = models.residuals(f.kind, pose, M, f.z)
            ok = np.all(np.abs(E) < p.pregate[: len(f.z)], axis=1)
            rows = [lids[i] for i in np.flatnonzero(ok)]
            needed.update(rows)
        pre.append(rows)
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
    # 3. individual compatibility with the fresh means
    compat: list[list[_Pair]] = []
    near = [False] * n
    for i, (f, rows) in enumerate(zip(features, pre, strict=True)):
        dim = len(f.z)
        gate, amb = chi2_gate(dim, p.gate_p), chi2_gate(dim, p.ambiguous_p)
        hits: list[_Pair] = []
        meas = geometry.measured_ends(f, pose) if f.kind == "line" else None
        for lid in rows:
            m = means[lid]
            e, Hx, Hl = models.residual(f.kind, pose, m, f.z)
            k, nl = offs[lid], models.DIM[cand[lid].kind]
            A = np.zeros((dim, dimx))
            A[:, :3] = Hx
            A[:, k : k + nl] = Hl
            idx = [0, 1, 2, *range(k, k + nl)]
            Ai = A[:, idx]
            S = Ai @ P[np.ix_(idx, idx)] @ Ai.T + f.cov
            try:
                d2 = float(e @ np.linalg.solve(S, e))
            except np.linalg.LinAlgError:
                continue
            if d2 > gate:
                near[i] |= d2 < amb
                continue
            ov = np.inf
            if f.kind == "line":
                ov = _line_overlap(f, m, cand[lid].ends, meas, p)
                if ov is None:
                    continue
            hits.append(_Pair(lid, d2, ov, e, A))
        hits.sort(key=lambda h: h.d2)
        compat.append(hits)
        out.compatible.update(h.lid for h in hits)
    # 4. the strategy
    if p.method == "nn":
        for i, hits in enumerate(compat):
            if hits:
                out.pairs[i], out.d2[i] = hits[0].lid, hits[0].d2
    else:
        _jcbb(out, features, compat, P, pose, p)
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
    P: NDArray[np.float64],
    pose: NDArray[np.float64],
    p: AssociationParams,
) -> None:
    """Joint compatibility branch and bound over the features with candidates."""
    order = [i for i, h in enumerate(compat) if h]
    if not order:
        return
    # measured world segments of line features (for the two-segments-of-one-wall exception)
    segs = {
        i: geometry.measured_ends(features[i], pose) for i in order if features[i].kind == "line"
    }
    # per pair: A P (rows of the cross covariances), computed once
    AP = {(i, h.lid): h.A @ P for i in order for h in compat[i]}
    best: dict = {"n": 0, "d2": np.inf, "pairs": {}}
    nodes = [0]
    # the common case first: the nearest-neighbour pairing, if mutually exclusive and jointly
    # compatible, pairs every feature that has a candidate: no hypothesis pairs more
    nn = {i: compat[i][0] for i in order}
    lids = [h.lid for h in nn.values()]
    if len(set(lids)) == len(lids):
        state = (0.0, None, None, 0, [])
        for i, h in nn.items():
            state = _extend(state, {}, i, h, AP, features[i].cov, features)
            if state is None or state[0] > chi2_gate(state[3], p.gate_p):
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
        line = _line_of(features[i], pose)
        for j in others:
            if features[j].endpoints is None or geometry.overlap(line, segs[j], segs[i]) >= 0.0:
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
            new = _extend(state, pairs, i, h, AP, f.cov, features)
            if new is None:
                continue
            dof = new[3]
            if new[0] > chi2_gate(dof, p.gate_p):
                continue
            pairs[i] = h
            used.setdefault(h.lid, []).append(i)
            rec(level + 1, pairs, used, new)
            used[h.lid].pop()
            del pairs[i]
        # the star branch: feature i unpaired, if it can still beat the best
        if npairs + len(order) - level - 1 >= max(best["n"], 1) or best["n"] == 0:
            rec(level + 1, pairs, used, state)

    rec(0, {}, {}, (0.0, None, None, 0, []))  # (d2, e, Sinv, dof, pairs in order)
    for i, h in best["pairs"].items():
        out.pairs[i], out.d2[i] = h.lid, h.d2
    out.joint_d2 = float(best["d2"]) if best["n"] else 0.0
    out.stats["jcbb_nodes"] += nodes[0]
    if nodes[0] > p.max_nodes:
        out.stats["jcbb_budget_exhausted"] += 1


def _line_of(f: Feature, pose: NDArray[np.float64]) -> NDArray[np.float64]:
    """World (alpha, d) of a line feature seen from ``pose``."""
    return models.to_world("line", pose, f.z)[0]


def _extend(state, pairs: dict[int, _Pair], i: int, h: _Pair, AP, R, features):
    """Add pairing (i, h) to a hypothesis: incremental inverse of the joint innovation
    covariance (block inversion). ``state`` = (d2, e, Sinv, dof, keys)."""
    d2, e, Sinv, dof, keys = state
    s = AP[(i, h.lid)] @ h.A.T + R
    if e is None:
        try:
            Qinv = np.linalg.inv(s)
        except np.linalg.LinAlgError:
            return None
        return (float(h.e @ Qinv @ h.e), h.e, Qinv, len(h.e), [(i, h)])
    c = np.vstack([AP[(j, g.lid)] @ h.A.T for j, g in keys])  # cross blocks (m_old, m_new)
    k = Sinv @ c
    Q = s - c.T @ k
    try:
        Qinv = np.linalg.inv(Q)
    except np.linalg.LinAlgError:
        return None
    v = h.e - k.T @ e
    d2n = d2 + float(v @ Qinv @ v)
    kQ = k @ Qinv
    top = np.hstack([Sinv + kQ @ k.T, -kQ])
    bot = np.hstack([-kQ.T, Qinv])
    return (d2n, np.concatenate([e, h.e]), np.vstack([top, bot]), dof + len(h.e), [*keys, (i, h)])
