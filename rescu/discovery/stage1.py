"""RESCU-I: recurring-pattern discovery from SIFT features with a URP-based search and
adaptive parameters.

Pipeline of :func:`discover`:

1. candidate correspondences (:func:`rescu.discovery.urp.match_candidates`, once);
2. URP precomputation (:func:`precompute_urps`, once): for every correspondence
   ``(a, b)`` and every spatial neighbour ``c`` of ``a`` the copy ``d`` of ``c`` near
   ``b`` is looked up among ``c``'s correspondences, and the URP ``(a, b, c, d)`` with its
   affinity u and its gate quantities (within-instance distances, size difference,
   orientation difference) is stored. The support of a correspondence (sum of u of its
   URPs) ranks the initial URPs;
3. adaptive parameters (:func:`choose_parameters`): for every parameter set of the
   adaptive grid (the product of the grids of the names in ``adaptive``, the others
   fixed) the table is only *filtered* by the gates (P_d, P_s, P_theta) to rank its
   initial URPs; the set with the largest U(Omega*) is chosen (the paper's rule).
   When no grid point's probe gives a valid RP at all (U(Omega*) = 0 everywhere: the
   best-supported initial URPs are pieces of edges or too small), the grid is probed
   again with ``grid_retry_initials`` initial URPs per grid point (``chosen_by``
   "grid-retry"); when that finds none either, the grid carries no information and the
   fixed ``P_d``, ``P_s``, ``P_theta`` are used (``chosen_by`` "fixed"), not the first
   (tightest) grid point, which finds the fewest RPs;
   Reuse work across the grid: each distinct initial URP is searched once with the
   loosest gates, and Omega* of a grid point is that matrix pruned under the grid
   point's gates (so the 45 grid points cost a few searches, not 45). The grid points
   also share the ungated affinities of the first prune pass of each loose matrix and
   of every distinct pruned matrix (:class:`rescu.discovery.urp.AffinityParts`): a grid point
   only applies its own gates to them;
4. with the chosen set, RPs are found one after the other: ``initials_per_pattern``
   searches from the best available initial URPs, the matrix with the largest U is
   accepted, its features and every feature inside its instances' extents
   (:func:`rescu.discovery.instances.instance_extents`) are removed, and the search repeats (at most
   ``max_patterns``). Matrices with fewer than ``min_instances`` columns, ``min_words``
   rows, U below ``min_objective`` or a one-dimensional word layout (``min_spread``,
   pieces of a straight edge) are no RP; their features are retired and the search
   goes on with the next initials (within ``n_initials`` searches).

P_d is a fraction of the image *diagonal* (processed pixels).

An instance box is the bounding box of the positions of its column's features, grown
on every side by ``box_grow`` times the median keypoint radius of the column. An
accepted RP loses instances that duplicate another of its instances (two parts of one
object; :func:`rescu.discovery.instances.drop_duplicate_instances`).

Known property (as in the paper): U = sum / (M N) grows with the matrix, so looser
gates never lower U(Omega*); the grid then tends to pick loose values unless the
non-overlap of instances stops larger matrices.
"""

from __future__ import annotations

import itertools
import os
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..params import config_section, params_from_dict, schema_enum
from ..io import read_h5, write_h5
from .instances import (drop_duplicate_instances, feature_points,  # noqa: F401
                        instance_boxes, instance_extents, layout_spread)
from .search import (SearchContext, SearchParams, matrix_objective, objective_parts, prune,
                     search)
from ..types import Features, Instance, Pattern, RPMatrix
from .urp import (AffinityMatchGroups, Gates, match_candidates, root_sift,
                  urp_affinity, urp_terms)

ADAPTIVE_NAMES: tuple[str, ...] = schema_enum("stage1", "adaptive")


@dataclass(frozen=True)
@config_section("stage1")
class Stage1Params(AffinityMatchGroups, SearchParams):
    """Parameters of RESCU-I (see module docstring).

    Attributes
    ----------
    sigma_s, sigma_theta : float
        Affinity bandwidths of the paper (0.2).
    orientation_mode : str
        "wrapped" (default), "relative" or "paper" (see :mod:`rescu.discovery.urp`).
    P_d : float
        Max distance between features of one instance, fraction of the image diagonal.
    P_s : float
        Max size difference among instances, ``1 - min(r, 1/r)``.
    P_theta : float
        Max orientation difference among instances, degrees.
    grid_P_d, grid_P_s, grid_P_theta : list of float
        Adaptive grids.
    adaptive : list of str
        Which of P_d / P_s / P_theta are chosen per image from their grid.
    max_patterns : int
        Most RPs per image.
    min_instances, min_words : int
        Smallest RP matrix accepted (columns, rows).
    min_objective : float
        Smallest U(Omega) accepted.
    min_spread : float
        Smallest :func:`layout_spread` (minor / major axis of the word layout of an
        instance) accepted; rejects "instances" that are pieces of one straight edge.
    n_initials : int
        Most searches in the final discovery.
    initials_per_pattern : int
        Searches (from distinct initial URPs) per accepted RP; the best is kept.
    grid_initials : int
        Searches per parameter set when choosing the adaptive parameters.
    grid_retry_initials : int
        When those searches give no valid RP at any grid point, the grid is probed
        again with this many searches per parameter set (0, or not more than
        ``grid_initials``: no retry; the fixed parameters are used).
    match_k, match_max_dist, match_min_sep : candidate correspondences (RootSIFT kNN).
    spatial_k : int
        Spatial neighbours per feature when forming initial URPs.
    pos_tol, u_min, min_fill, max_overlap, row_expand, max_rows, max_cols, max_iters
        The search's tunables (:class:`rescu.discovery.search.SearchParams`).
    box_grow : float
        Instance box = feature hull grown by box_grow * median keypoint radius.
    extent_grow : float
        After an RP is accepted, features within its instances' extents (the box grown
        up to half the instance spacing, by at most ``extent_grow`` times its larger
        side; :func:`instance_extents`) are removed.
    max_nested_cover, min_centre_distance : float
        After an RP is accepted, an instance that duplicates another of its instances
        (two parts of one object found as two instances) is dropped, keeping the one with
        more words (:func:`drop_duplicate_instances`): boxes overlapping by more than
        ``max_nested_cover`` of the smaller box (1.0: off), or registered centres closer
        than ``min_centre_distance`` x the median larger box side (0: off).
    refine_boxes : bool
        Move each RP's instance boxes onto the edges its instances share (one shift and
        scale per RP; :mod:`rescu.discovery.edge_extent`). Needs the image; done by
        :func:`rescu.pipeline.stage1` for RESCU-I.
    refine_shifts, refine_scales : list of float
        The candidate centre shifts (fractions of the box side) and side scales.
    seed : int
        Tie-break of the initial URPs: correspondences with equal support are ranked by
        their feature indices ``(a, b)`` when 0 (default), by a permutation drawn from
        ``numpy.random.default_rng(seed)`` otherwise (exact ties occur: among the 50
        best-supported correspondences of an image typically 0-6 tie). Nothing else is
        random; the same seed gives the same output.
    """

    sigma_s: float
    sigma_theta: float
    orientation_mode: str
    P_d: float
    P_s: float
    P_theta: float
    grid_P_d: tuple[float, ...]
    grid_P_s: tuple[float, ...]
    grid_P_theta: tuple[float, ...]
    adaptive: tuple[str, ...]
    max_patterns: int
    min_instances: int
    min_words: int
    min_objective: float
    min_spread: float
    n_initials: int
    initials_per_pattern: int
    grid_initials: int
    grid_retry_initials: int
    match_k: int
    match_max_dist: float
    match_min_sep: float
    spatial_k: int
    box_grow: float
    extent_grow: float
    max_nested_cover: float
    min_centre_distance: float
    refine_boxes: bool
    refine_shifts: tuple[float, ...]
    refine_scales: tuple[float, ...]
    seed: int

    def __post_init__(self) -> None:
        for name in ("grid_P_d", "grid_P_s", "grid_P_theta", "adaptive", "refine_shifts",
                     "refine_scales"):
            object.__setattr__(self, name, tuple(getattr(self, name)))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Stage1Params":
        """Build from a mapping; raises ValueError naming any unknown key."""
        return params_from_dict(cls, d)

    def grid(self) -> list[dict[str, float]]:
        """The parameter sets of the adaptive grid (one set when ``adaptive`` is empty)."""
        axes = []
        for name in ADAPTIVE_NAMES:
            if name in self.adaptive:
                axes.append([(name, float(v)) for v in getattr(self, "grid_" + name)])
            else:
                axes.append([(name, float(getattr(self, name)))])
        return [dict(c) for c in itertools.product(*axes)]


@dataclass
class Stage1Output:
    """Result of stage I on one image.

    Attributes
    ----------
    rps : list of RPMatrix
        Sorted by objective, best first.
    chosen : dict
        The parameter set chosen (``P_d``, ``P_s``, ``P_theta``).
    objective : float
        U(Omega*) of the best RP (0 when there is none).
    timings : dict
        Seconds per step.
    chosen_by : str
        "grid" when the adaptive grid chose ``chosen``; "grid-retry" when it did so only
        in the retry probe (``grid_retry_initials``); "fixed" when the fixed parameters
        were used (no adaptive names, no valid RP at any grid point, or fewer than 4
        features); "skipped" when the search did not run
        (:func:`rescu.pipeline.stage1` with ``dense.mode: dense``).
    """

    rps: list[RPMatrix]
    chosen: dict[str, float]
    objective: float
    timings: dict[str, float] = field(default_factory=dict)
    chosen_by: str = "fixed"


@dataclass
class URPTable:
    """Precomputed initial URPs ``(a, b, c, d)`` with affinity and gate quantities.

    All arrays have length T. ``u`` is the ungated affinity; ``dist`` the larger
    within-instance distance (pixels), ``size_diff`` and ``rot`` (degrees) as in
    :func:`rescu.discovery.urp.urp_terms`. ``seed`` breaks ties among correspondences of equal
    support (see :class:`Stage1Params`).
    """

    abcd: np.ndarray
    u: np.ndarray
    dist: np.ndarray
    size_diff: np.ndarray
    rot: np.ndarray
    seed: int = 0

    def __post_init__(self) -> None:
        # Gate-independent part of the ranking, done once for all grid points: the
        # correspondence (a, b) of every URP (``inv``: its index in the sorted unique
        # keys) and the URPs ordered by correspondence, best u first (``order``,
        # stable, so equal u keep table order).
        key = self.abcd[:, 0] * (int(self.abcd[:, 1].max(initial=0)) + 1) + self.abcd[:, 1]
        uk, self._inv = np.unique(key, return_inverse=True)
        self._order = np.lexsort((-self.u, self._inv))
        self._start = np.searchsorted(self._inv[self._order], np.arange(len(uk) + 1))
        # tie-break rank of every correspondence: key order, or a seeded permutation
        self._tie = np.arange(len(uk)) if self.seed == 0 else \
            np.random.default_rng(self.seed).permutation(len(uk))

    def seeds(self, gates: Gates, limit: int | None = None) -> np.ndarray:
        """Initial URPs ranked by the support of their correspondence ``(a, b)`` under
        ``gates``: (S, 4) int, best first, one per correspondence (ties: see
        ``seed``). ``limit=1`` returns only the best, without ranking the rest."""
        ok = (self.dist <= gates.max_dist) & (self.size_diff <= gates.max_size_diff) & \
            (self.rot <= gates.max_rot) & (self.u > 0)
        if not ok.any():
            return np.zeros((0, 4), np.int64)
        inv = self._inv
        # support: sum of u over the correspondence's URPs that pass the gates
        support = np.bincount(inv[ok], weights=self.u[ok])
        if limit == 1:
            top = np.flatnonzero(support == support.max())
            g = int(top[np.argmin(self._tie[top])])
            blk = self._order[self._start[g]:self._start[g + 1]]
            return self.abcd[blk[ok[blk]][:1]]
        # best partner per correspondence: first passing URP in the (inv, -u) order
        o = self._order[ok[self._order]]
        first = np.r_[True, inv[o][1:] != inv[o][:-1]]
        best = o[first]                       # one URP per present correspondence, by key
        grp = inv[best]
        order = np.lexsort((self._tie[grp], -support[grp]))
        return self.abcd[best[order]]


def search_context(features: Features, params: Stage1Params,
                   shared: dict[Any, Any] | None = None) -> tuple[SearchContext, float]:
    """The per-image :class:`SearchContext` of stage I and the image diagonal (pixels).

    Matches the candidate correspondences (``params.match``) and carries the search
    parameters of ``params``. Used by :func:`discover`; public for benchmarks and tests
    that time or probe one step. ``shared``: as in :func:`discover` (the matches, the
    RootSIFT descriptors and the k-d tree, which depend on the features and
    ``params.match`` alone).
    """
    key = ("match", params.match)
    if shared is not None and key in shared:
        xy, rs, nbr, tree = shared[key]
    else:
        xy = features.xy.astype(np.float64)
        nbr, _ = match_candidates(features.descriptors, features.xy, features.scale,
                                  params.match)
        rs, tree = root_sift(features.descriptors), cKDTree(xy)
        if shared is not None:
            shared[key] = (xy, rs, nbr, tree)
    ctx = SearchContext(
        xy=xy, scale=features.scale.astype(np.float64), angle=features.angle.astype(np.float64),
        rs=rs, nbr=nbr, tree=tree,
        affinity=params.affinity, desc_max_dist=params.match_max_dist, search=params)
    w, h = features.image_size
    return ctx, float(np.hypot(w, h))


def precompute_urps(ctx: SearchContext, max_dist: float, spatial_k: int,
                    pos_tol: float, seed: int = 0) -> URPTable:
    """All initial URPs of the image (vectorised).

    Parameters
    ----------
    ctx : SearchContext
    max_dist : float
        Loosest P_d of the grid times the diagonal, pixels.
    spatial_k : int
        Spatial neighbours ``c`` of each ``a``.
    pos_tol : float
        ``d`` must lie within ``pos_tol * d(a, c) + 2`` pixels of the predicted copy
        ``b + (c - a) * s_b / s_a``.
    seed : int
        Tie-break of the initial-URP ranking (:class:`URPTable`).
    """
    k = len(ctx.xy)
    empty = URPTable(np.zeros((0, 4), np.int64), *(np.zeros(0) for _ in range(4)), seed=seed)
    if k < 4:
        return empty
    a, j = np.nonzero(ctx.nbr >= 0)
    b = ctx.nbr[a, j]
    keep = a < b
    a, b = a[keep], b[keep]
    if len(a) == 0:
        return empty
    kq = min(spatial_k + 1, k)
    dd, cc = ctx.tree.query(ctx.xy, k=kq, distance_upper_bound=max_dist)
    cc = cc[:, 1:]
    dd = dd[:, 1:]
    A = np.repeat(a, kq - 1)
    B = np.repeat(b, kq - 1)
    C = cc[a].ravel()
    ok = np.isfinite(dd[a].ravel())
    A, B, C = A[ok], B[ok], C[ok]
    ok = (C != B)
    A, B, C = A[ok], B[ok], C[ok]
    ratio = ctx.scale[B] / ctx.scale[A]
    pred = ctx.xy[B] + (ctx.xy[C] - ctx.xy[A]) * ratio[:, None]
    dn = ctx.nbr[C]                                    # (T, k) candidate copies of c
    dv = dn >= 0
    dpos = ctx.xy[np.where(dv, dn, 0)]
    err = np.where(dv, np.hypot(dpos[..., 0] - pred[:, None, 0], dpos[..., 1] - pred[:, None, 1]),
                   np.inf)
    err = np.where((dn == A[:, None]) | (dn == B[:, None]), np.inf, err)
    jb = np.argmin(err, axis=1)
    e = err[np.arange(len(jb)), jb]
    tol = pos_tol * np.hypot(*(ctx.xy[C] - ctx.xy[A]).T) * ratio + 2.0
    ok = e <= tol
    A, B, C, D = A[ok], B[ok], C[ok], dn[np.arange(len(jb)), jb][ok]
    if len(A) == 0:
        return empty
    t = urp_terms(ctx.xy, ctx.scale, ctx.angle, A, B, C, D, ctx.affinity.orientation_mode)
    u = urp_affinity(ctx.xy, ctx.scale, ctx.angle, A, B, C, D, ctx.affinity)
    return URPTable(np.stack([A, B, C, D], 1).astype(np.int64), u,
                    np.maximum(t["d1"], t["d2"]), t["size_diff"], t["rot"], seed=seed)


def _valid(omega: np.ndarray, U: float, params: Stage1Params,
           xy: np.ndarray | None = None) -> bool:
    ok = (omega.ndim == 2 and omega.shape[0] >= params.min_words
          and omega.shape[1] >= params.min_instances and U >= params.min_objective
          and U > 0)
    if ok and xy is not None and params.min_spread > 0:
        ok = layout_spread(xy, omega) >= params.min_spread
    return ok


def run_discovery(ctx: SearchContext, table: URPTable, features: Features,
                  params: Stage1Params, pset: dict[str, float], diag: float
                  ) -> list[RPMatrix]:
    """Find RPs one after the other with one parameter set (module docstring, step 4)."""
    gates = Gates(pset["P_d"] * diag, pset["P_s"], pset["P_theta"])
    seeds = table.seeds(gates)
    k = len(ctx.xy)
    available = np.ones(k, bool)
    rps: list[RPMatrix] = []
    tried = 0
    budget = params.n_initials
    per = params.initials_per_pattern
    consumed = np.zeros(len(seeds), bool)
    n_rounds = params.max_patterns + params.n_initials
    for _ in range(n_rounds):
        if len(rps) >= params.max_patterns:
            break
        best: tuple[float, np.ndarray] | None = None
        blocked = ~available.copy()
        rejected: list[np.ndarray] = []
        n_this = 0
        while n_this < per and tried < budget:
            # next initial URP in rank order that is unused and touches no blocked
            # feature (blocked and consumed only grow, so skipped ones stay skipped)
            free = np.flatnonzero(~consumed & ~blocked[seeds].any(axis=1))
            if len(free) == 0:
                break
            s_ptr = int(free[0])
            sd = seeds[s_ptr]
            consumed[s_ptr] = True
            om = search(ctx, sd, available, gates)
            tried += 1
            n_this += 1
            if om.ndim == 2 and om.shape[0] >= 2 and om.shape[1] >= 2:
                blocked[om[om >= 0]] = True
                U = matrix_objective(ctx, om, gates)
                if _valid(om, U, params, ctx.xy):
                    if best is None or U > best[0]:
                        best = (U, om)
                else:
                    rejected.append(om[om >= 0])
            blocked[sd] = True
        if best is None:
            # no RP from these initials: their features form no valid RP (e.g. a
            # straight edge); retire them and go on with the next initials
            if n_this == 0 or tried >= budget:
                break
            for r in rejected:
                available[r] = False
            continue
        U, om = best
        available[om[om >= 0]] = False
        boxes = instance_extents(features, om, params.box_grow, params.extent_grow)
        x, y = ctx.xy[:, 0], ctx.xy[:, 1]
        for bx in boxes:
            available &= ~((x >= bx[0]) & (x <= bx[0] + bx[2]) & (y >= bx[1]) & (y <= bx[1] + bx[3]))
        kept = drop_duplicate_instances(features, om, params.box_grow,
                                        params.max_nested_cover, params.min_centre_distance)
        if kept.shape[1] != om.shape[1]:
            om = kept[np.any(kept >= 0, axis=1)]       # words left without any feature go
            if om.shape[1] < params.min_instances or om.shape[0] < params.min_words:
                continue                               # what is left is no RP
            U = matrix_objective(ctx, om, gates)
        rps.append(RPMatrix(om.astype(np.int64), float(U),
                            dict(pset, box_grow=params.box_grow)))
        if tried >= budget:
            break
    rps.sort(key=lambda r: -r.objective)
    return rps


def choose_parameters(ctx: SearchContext, table: URPTable, features: Features,
                      params: Stage1Params, grid: list[dict[str, float]],
                      diag: float,
                      searches: dict[tuple[int, ...], tuple[np.ndarray, dict]] | None = None
                      ) -> dict[str, float] | None:
    """The adaptive parameter set: the grid point with the largest U(Omega*).

    Returns the chosen grid point, or None when no grid point gives a valid RP
    (U(Omega*) = 0 at every one); :func:`discover` then uses the fixed parameters.
    ``searches`` (initial URP -> its loose search and first-prune parts) is filled and
    reused when given: a second call on the same grid (the retry with more initials)
    does not repeat the searches of the first.

    Reuse work across the grid: a grid point only changes the gates (P_d, P_s,
    P_theta). For every grid point its best ``grid_initials`` initial URPs are ranked
    on the precomputed table (cheap); each distinct initial URP is searched *once*,
    with the loosest gates of the grid. Omega* of a grid point is that loose matrix
    pruned under the grid point's own gates (entries, rows and columns whose mean
    affinity drops below the limits are removed, exactly as in the search's remove
    step), and U(Omega*) is evaluated under those gates. So the cost is a handful of
    searches plus one prune per grid point, instead of one search per grid point.
    Ties go to the earlier grid point.
    """
    loose = {n: max(p[n] for p in grid) for n in ADAPTIVE_NAMES}
    g_loose = Gates(loose["P_d"] * diag, loose["P_s"], loose["P_theta"])
    avail = np.ones(len(ctx.xy), bool)
    cache = {} if searches is None else searches
    # ungated affinities of each distinct pruned matrix: grid points whose gates prune
    # a loose matrix to the same Omega* share them and only apply their own gates
    obj_parts: dict[tuple, Any] = {}
    spread: dict[tuple, float] = {}
    best_u, chosen = -1.0, grid[0]
    for pset in grid:
        gates = Gates(pset["P_d"] * diag, pset["P_s"], pset["P_theta"])
        u_best = 0.0
        n_init = max(1, params.grid_initials)
        for sd in table.seeds(gates, 1 if n_init == 1 else None)[:n_init]:
            key = tuple(int(v) for v in sd)
            if key not in cache:
                cache[key] = (search(ctx, sd, avail, g_loose), {})
            om, first = cache[key]
            if om.ndim != 2 or om.shape[0] < 2 or om.shape[1] < 2:
                continue
            om = prune(ctx, om, gates, first)   # first pass shared by the grid points
            if om.shape[0] < 2 or om.shape[1] < 2:
                continue
            okey = (om.shape, om.tobytes())
            if okey not in obj_parts:
                obj_parts[okey] = objective_parts(ctx, om)
                spread[okey] = layout_spread(ctx.xy, om)
            U = matrix_objective(ctx, om, gates, obj_parts[okey])
            if _valid(om, U, params) and (params.min_spread <= 0
                                          or spread[okey] >= params.min_spread):
                u_best = max(u_best, U)
        if u_best > best_u + 1e-12:
            best_u, chosen = u_best, pset
    return chosen if best_u > 0 else None


def discover(features: Features, params: Stage1Params | None = None,
             shared: dict[Any, Any] | None = None) -> Stage1Output:
    """RESCU-I on one image's features.

    Parameters
    ----------
    features : Features
        SIFT features of the processed image.
    params : Stage1Params
    shared : dict or None
        For several calls on the same ``features`` with different parameters (the
        ablation's variants): a dict the caller keeps between the calls, empty at the
        first. The candidate correspondences and the tables of initial URPs go in it,
        keyed by the parameters they depend on, and later calls whose parameters give the
        same ones reuse them; the results are those of calls without it. Calls on other
        features need another dict.

    Returns
    -------
    Stage1Output
        ``rps`` best first. An image with fewer than 4 features or without recurrence
        gives ``rps == []``, ``objective == 0`` and the fixed parameters as ``chosen``.

    >>> from rescu.data.example import example_image
    >>> from rescu.discovery.features import extract_features
    >>> img, truth = example_image()              # one row of 5 copies
    >>> f = extract_features(img)
    >>> out = discover(f, Stage1Params(adaptive=()))   # fixed P_d, P_s, P_theta: fast
    >>> [p.count for p in rps_to_patterns(f, out.rps)][:1]
    [5]
    """
    params = params or Stage1Params()
    if not isinstance(features, Features):
        raise TypeError(f"discover: features must be a Features, got {type(features).__name__}")
    timings: dict[str, float] = {}
    fixed = {"P_d": float(params.P_d), "P_s": float(params.P_s), "P_theta": float(params.P_theta)}
    if len(features) < 4:
        return Stage1Output([], fixed, 0.0, {"match": 0.0, "precompute": 0.0, "grid": 0.0,
                                             "search": 0.0})
    t0 = time.perf_counter()
    if shared is not None and shared.setdefault("features", features) is not features:
        raise ValueError("discover: a shared dict serves the features it was first used with")
    ctx, diag = search_context(features, params, shared)
    t1 = time.perf_counter()
    grid = params.grid()
    pd_max = max(p["P_d"] for p in grid)
    # the table depends on the matches, the affinity (orientation mode, bandwidths) and these
    key = ("urps", params.match, params.affinity, pd_max * diag, params.spatial_k,
           params.pos_tol, params.seed)
    table = shared.get(key) if shared is not None else None
    if table is None:
        table = precompute_urps(ctx, pd_max * diag, params.spatial_k, params.pos_tol,
                                params.seed)
        if shared is not None:
            shared[key] = table
    t2 = time.perf_counter()
    chosen, chosen_by = fixed, "fixed"
    if len(grid) > 1:
        searches: dict[tuple[int, ...], tuple[np.ndarray, dict]] = {}
        pick = choose_parameters(ctx, table, features, params, grid, diag, searches)
        if pick is not None:
            chosen, chosen_by = pick, "grid"
        elif params.grid_retry_initials > max(1, params.grid_initials):
            retry = replace(params, grid_initials=params.grid_retry_initials)
            pick = choose_parameters(ctx, table, features, retry, grid, diag, searches)
            if pick is not None:
                chosen, chosen_by = pick, "grid-retry"
    t3 = time.perf_counter()
    rps = run_discovery(ctx, table, features, params, chosen, diag)
    t4 = time.perf_counter()
    timings = {"match": t1 - t0, "precompute": t2 - t1, "grid": t3 - t2, "search": t4 - t3}
    return Stage1Output(rps, dict(chosen), rps[0].objective if rps else 0.0, timings,
                        chosen_by)


def rps_to_patterns(features: Features, rps: list[RPMatrix]) -> list[Pattern]:
    """RP matrices as :class:`Pattern` records in ORIGINAL pixels.

    Instance score = fraction of the RP's words present in that instance. Boxes (``box_grow`` from ``rp.params``, default 0.5) and ``feature_points``
    (M, N, 2; NaN where missing) are divided by ``features.scale_factor``; the score is
    the objective U; instances have source "stage1"; sorted by score (desc), ids 0...
    """
    sf = float(features.scale_factor)
    out = []
    for rp in sorted(rps, key=lambda r: -r.objective):
        om = np.asarray(rp.feature_index, np.int64)
        if om.ndim != 2 or om.shape[1] == 0:
            continue
        boxes = instance_boxes(features, om, float(rp.params.get("box_grow", 0.5))) / sf
        fp = feature_points(features, om) / sf
        fill = (om >= 0).mean(axis=0)  # instance score: fraction of the words present
        insts = [Instance(bbox=(float(b[0]), float(b[1]), float(b[2]), float(b[3])),
                          score=float(fl), source="stage1") for b, fl in zip(boxes, fill)]
        out.append(Pattern(id=len(out), score=float(rp.objective), instances=insts,
                           feature_points=fp))
    return out


def save_rps(path: str | os.PathLike[str], out: Stage1Output) -> None:
    """Write stage-I output to HDF5 (atomic): group ``rp_<i>`` per RP with
    ``feature_index`` (M, N) int64 and ``objective``; attrs ``chosen`` / ``params``
    (JSON), ``objective``, ``timings`` (JSON), ``n_rps``."""
    import json

    arrays: dict[str, Any] = {}
    for i, rp in enumerate(out.rps):
        arrays[f"rp_{i:03d}"] = {"feature_index": np.asarray(rp.feature_index, np.int64),
                                 "objective": np.float64(rp.objective)}
    write_h5(path, arrays, attrs={
        "n_rps": len(out.rps), "objective": float(out.objective),
        "chosen": json.dumps(out.chosen, sort_keys=True),
        "params": json.dumps([rp.params for rp in out.rps], sort_keys=True),
        "timings": json.dumps(out.timings, sort_keys=True)})


def load_rps(path: str | os.PathLike[str]) -> Stage1Output:
    """Read a file written by :func:`save_rps`."""
    import json

    arrays, attrs = read_h5(path)
    n = int(attrs["n_rps"])
    plist = json.loads(attrs["params"])
    rps = [RPMatrix(np.asarray(arrays[f"rp_{i:03d}"]["feature_index"], np.int64),
                    float(arrays[f"rp_{i:03d}"]["objective"]), dict(plist[i]))
           for i in range(n)]
    return Stage1Output(rps, json.loads(attrs["chosen"]), float(attrs["objective"]),
                        json.loads(attrs["timings"]))


def params_dict(params: Stage1Params) -> dict[str, Any]:
    """The parameters as a plain dict (lists for the grids)."""
    d = asdict(params)
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}
