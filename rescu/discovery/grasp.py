"""GRASP baseline (Liu & Liu, CVPR 2013): greedy randomized adaptive search for RP
matrices, with fixed parameters.

The same RP-matrix objective U(Omega) = 1/(M N) sum u is optimised, but as GRASP does
it, without RESCU-I's precomputed URP table, candidate voting or batch moves:

* each iteration starts from a randomly selected pair of visual words: a random
  candidate correspondence ``(a, b)`` (rng) and a random spatial neighbour ``c`` of ``a``
  with its copy ``d`` near ``b``;
* randomized greedy construction: every step generates the add-column moves (a copy of
  the first instance through each correspondence of one of its features, the other
  words placed at the translated positions) and add-row moves (an unused feature near
  the first instance copied by translation into every instance), up to
  ``max_candidates`` of them (sampled), scores each by recomputing U of the enlarged
  matrix from scratch, and picks one at random from the restricted candidate list
  (the ``rcl_size`` best improving moves);
* local search: drop any row or column whose removal raises U;
* the best matrix over ``iterations`` iterations is one RP; its features are removed and
  the procedure repeats for up to ``max_patterns`` RPs.

Parameters P_d, P_s, P_theta are fixed (0.2 of the diagonal, 0.5, 30 degrees).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..params import config_section, params_from_dict
from .stage1 import Stage1Output
from ..types import Features, RPMatrix
from .urp import AffinityMatchGroups, Gates, match_candidates, objective, root_sift


@dataclass(frozen=True)
@config_section("grasp")
class GraspParams(AffinityMatchGroups):
    """Parameters of the GRASP baseline.

    Attributes
    ----------
    iterations : int
        GRASP iterations (random starts) per RP.
    rcl_size : int
        Restricted candidate list size.
    max_candidates : int
        Moves evaluated per construction step (sampled).
    max_steps : int
        Construction steps per iteration.
    P_d, P_s, P_theta : fixed gates (fraction of diagonal, size difference, degrees).
    sigma_s, sigma_theta, orientation_mode : affinity (see rescu.discovery.urp).
    match_k, match_max_dist, match_min_sep : candidate correspondences.
    pos_tol : float
        Position tolerance of a translated copy, fraction of the instance size (min 3 px).
    max_patterns, min_instances, min_words : output limits.
    box_grow : float
        Instance box growth (keypoint radii), as in stage I.
    max_keypoints : int
        GRASP works on at most this many keypoints (the strongest: features are sorted
        by decreasing response, so RP feature indices stay valid for the full set).
        Caps its run time (its cost grows quickly with the keypoint count); 0 = all.
    seed : int
        Random seed.
    """

    iterations: int
    rcl_size: int
    max_candidates: int
    max_steps: int
    P_d: float
    P_s: float
    P_theta: float
    sigma_s: float
    sigma_theta: float
    orientation_mode: str
    match_k: int
    match_max_dist: float
    match_min_sep: float
    pos_tol: float
    max_patterns: int
    min_instances: int
    min_words: int
    box_grow: float
    max_keypoints: int
    seed: int

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "GraspParams":
        """Build from a mapping; raises ValueError naming any unknown key."""
        return params_from_dict(cls, d)


class _Grasp:
    def __init__(self, features: Features, p: GraspParams) -> None:
        self.p = p
        self.xy = features.xy.astype(np.float64)
        self.s = features.scale.astype(np.float64)
        self.a = features.angle.astype(np.float64)
        self.rs = root_sift(features.descriptors)
        self.affinity = p.affinity
        self.nbr, _ = match_candidates(features.descriptors, features.xy, features.scale,
                                       p.match)
        self.tree = cKDTree(self.xy)
        w, h = features.image_size
        self.gates = Gates(p.P_d * float(np.hypot(w, h)), p.P_s, p.P_theta)
        # desc_close's answers: the search asks about the same pairs of features again
        # and again (an order of magnitude more calls than pairs)
        self._close: dict[tuple[int, int], bool] = {}

    def U(self, om: np.ndarray) -> float:
        return objective(self.xy, self.s, self.a, om, self.affinity, self.gates)

    def desc_close(self, i: int, j: int) -> bool:
        """Whether features ``i`` and ``j`` have RootSIFT descriptors within
        ``match_max_dist`` (each pair computed once)."""
        key = (i, j)
        close = self._close.get(key)
        if close is None:
            d2 = 2.0 - 2.0 * float(self.rs[i] @ self.rs[j])
            close = self._close[key] = d2 <= self.p.match_max_dist ** 2
        return close

    def copy_at(self, ref: int, pos: np.ndarray, tol: float, taken: set[int],
                avail: np.ndarray) -> int:
        dd, qq = self.tree.query(pos, k=4, distance_upper_bound=tol)
        return self.pick(ref, dd.tolist(), qq.tolist(), taken, avail)

    def pick(self, ref: int, dd: list[float], qq: list[int], taken: set[int],
             avail: np.ndarray) -> int:
        """The first of a position's nearest features (``dd``, ``qq``: one row of a k-d
        tree query) that is free and matches ``ref``'s descriptor; -1 when none."""
        # plain Python scalars: this runs ~10^5 times per image (numpy scalar checks cost
        # more than the test); a missing neighbour has d = inf and q = n
        for d, q in zip(dd, qq):
            if d != math.inf and q not in taken and avail[q] and self.desc_close(ref, q):
                return q
        return -1

    def tol(self, om: np.ndarray) -> float:
        p = self.xy[om[:, 0][om[:, 0] >= 0]]
        size = float(np.max(p.max(0) - p.min(0))) if len(p) > 1 else 10.0
        return max(3.0, self.p.pos_tol * size)

    def start(self, rng: np.random.Generator, avail: np.ndarray) -> np.ndarray | None:
        has = np.nonzero(avail & (self.nbr >= 0).any(1))[0]
        for _ in range(20):
            if len(has) == 0:
                return None
            a = int(rng.choice(has))
            bs = [int(b) for b in self.nbr[a] if b >= 0 and avail[b]]
            if not bs:
                continue
            b = bs[int(rng.integers(len(bs)))]
            dd, cc = self.tree.query(self.xy[a], k=9, distance_upper_bound=self.gates.max_dist)
            cs = [int(c) for d, c in zip(dd[1:], cc[1:]) if np.isfinite(d) and c != b and avail[c]]
            if not cs:
                continue
            c = cs[int(rng.integers(len(cs)))]
            pos = self.xy[b] + self.xy[c] - self.xy[a]
            d = self.copy_at(c, pos, max(3.0, self.p.pos_tol * float(np.hypot(*(self.xy[c] - self.xy[a])))),
                             {a, b, c}, avail)
            if d >= 0:
                return np.array([[a, b], [c, d]], np.int64)
        return None

    def moves(self, om: np.ndarray, rng: np.random.Generator, avail: np.ndarray) -> list[np.ndarray]:
        m, n = om.shape
        taken = set(int(v) for v in om.ravel() if v >= 0)
        tol = self.tol(om)
        out: list[np.ndarray] = []
        # add column: translate instance 0 through a correspondence of one of its features
        # (each candidate column's positions looked up in one k-d tree query, then taken
        # one instance after the other, as one query per position would)
        rows = [k for k in range(m) if om[k, 0] >= 0]
        refs = [int(om[k, 0]) for k in rows]
        base = self.xy[refs]                # their features' positions, (len(rows), 2)
        for i in range(m):
            f = om[i, 0]
            if f < 0:
                continue
            for h in self.nbr[f]:
                if h < 0 or h in taken or not avail[h]:
                    continue
                t = self.xy[h] - self.xy[f]
                dd, qq = self.tree.query(base + t, k=4, distance_upper_bound=tol)
                dd, qq = dd.tolist(), qq.tolist()
                col = np.full(m, -1, np.int64)
                loc = set(taken)
                for r, k in enumerate(rows):
                    q = int(h) if k == i else self.pick(refs[r], dd[r], qq[r], loc, avail)
                    if q >= 0:
                        col[k] = q
                        loc.add(q)
                if (col >= 0).sum() >= 2:
                    out.append(np.hstack([om, col[:, None]]))
        # add row: a feature near instance 0 copied by translation into every instance
        c0 = self.xy[om[:, 0][om[:, 0] >= 0]].mean(0)
        near = self.tree.query_ball_point(c0, self.gates.max_dist / 2.0)
        ref0 = om[:, 0] >= 0
        cols, shifts = [], []               # each instance's mean translation from instance 0
        for j in range(1, n):
            both = ref0 & (om[:, j] >= 0)
            if both.any():
                cols.append(j)
                shifts.append((self.xy[om[both, j]] - self.xy[om[both, 0]]).mean(0))
        shift = np.array(shifts).reshape(-1, 2)
        for e in sorted(near):
            if e in taken or not avail[e]:
                continue
            row = np.full(n, -1, np.int64)
            row[0] = e
            loc = set(taken) | {e}
            if cols:
                dd, qq = self.tree.query(self.xy[e] + shift, k=4,
                                         distance_upper_bound=tol)
                dd, qq = dd.tolist(), qq.tolist()
                for r, j in enumerate(cols):
                    q = self.pick(int(e), dd[r], qq[r], loc, avail)
                    if q >= 0:
                        row[j] = q
                        loc.add(q)
            if (row >= 0).sum() >= 2:
                out.append(np.vstack([om, row[None]]))
        if len(out) > self.p.max_candidates:
            idx = rng.choice(len(out), self.p.max_candidates, replace=False)
            out = [out[i] for i in sorted(idx)]
        return out

    def local_search(self, om: np.ndarray) -> np.ndarray:
        best = self.U(om)
        improved = True
        while improved:
            improved = False
            m, n = om.shape
            for axis, size in ((0, m), (1, n)):
                if size <= 2:
                    continue
                for i in range(size):
                    cand = np.delete(om, i, axis=axis)
                    u = self.U(cand)
                    if u > best + 1e-12:
                        om, best, improved = cand, u, True
                        break
                if improved:
                    break
        return om

    def run_iteration(self, rng: np.random.Generator, avail: np.ndarray) -> np.ndarray | None:
        om = self.start(rng, avail)
        if om is None:
            return None
        cur = self.U(om)
        for _ in range(self.p.max_steps):
            cands = self.moves(om, rng, avail)
            scored = [(self.U(c), i) for i, c in enumerate(cands)]
            scored = [s for s in scored if s[0] > cur + 1e-12]
            if not scored:
                break
            scored.sort(key=lambda t: (-t[0], t[1]))
            rcl = scored[: self.p.rcl_size]
            u, i = rcl[int(rng.integers(len(rcl)))]
            om, cur = cands[i], u
        return self.local_search(om)


def discover_grasp(features: Features, params: GraspParams | None = None) -> Stage1Output:
    """GRASP baseline on one image's features.

    Returns
    -------
    Stage1Output
        ``rps`` best first, ``chosen`` = the fixed P_d, P_s, P_theta. Fewer than 4
        features (or no recurrence) gives no RP.
    """
    p = params or GraspParams()
    if not isinstance(features, Features):
        raise TypeError(f"discover_grasp: features must be a Features, got {type(features).__name__}")
    chosen = {"P_d": float(p.P_d), "P_s": float(p.P_s), "P_theta": float(p.P_theta)}
    if len(features) < 4:
        return Stage1Output([], chosen, 0.0, {"match": 0.0, "search": 0.0})
    t0 = time.perf_counter()
    if p.max_keypoints > 0 and len(features) > p.max_keypoints:
        k = int(p.max_keypoints)
        features = Features(features.xy[:k], features.scale[:k], features.angle[:k],
                            features.response[:k], features.descriptors[:k],
                            features.image_size, features.scale_factor)
    g = _Grasp(features, p)
    t1 = time.perf_counter()
    rng = np.random.default_rng(p.seed)
    avail = np.ones(len(features), bool)
    rps: list[RPMatrix] = []
    from .instances import instance_boxes
    for _ in range(p.max_patterns):
        best: tuple[float, np.ndarray] | None = None
        for _ in range(p.iterations):
            om = g.run_iteration(rng, avail)
            if om is None:
                continue
            u = g.U(om)
            if om.shape[0] >= p.min_words and om.shape[1] >= p.min_instances and u > 0 and \
                    (best is None or u > best[0]):
                best = (u, om)
        if best is None:
            break
        u, om = best
        rps.append(RPMatrix(om, float(u), dict(chosen, box_grow=p.box_grow)))
        avail[om[om >= 0]] = False
        for bx in instance_boxes(features, om, p.box_grow):
            x, y = g.xy[:, 0], g.xy[:, 1]
            avail &= ~((x >= bx[0]) & (x <= bx[0] + bx[2]) & (y >= bx[1]) & (y <= bx[1] + bx[3]))
    t2 = time.perf_counter()
    rps.sort(key=lambda r: -r.objective)
    return Stage1Output(rps, chosen, rps[0].objective if rps else 0.0,
                        {"match": t1 - t0, "search": t2 - t1})
