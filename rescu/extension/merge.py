"""Merging split recurring patterns (the last step of RESCU-II).

Stage I can return one recurring pattern (RP) as two or three RPs: under strong
foreshortening the SIFT descriptors change along a row, so the unit-recurring-pattern
search builds one URP per part of the row. Stage II already has what is needed to see
that the parts are one pattern: the frozen ImageNet features of every stage-I instance
(``instance_features`` / ``instance_rp`` / ``instance_boxes`` of
:func:`rescu.extension.proposal_features.compute_stage2_features`). Two RPs A and B are *one* pattern when

* appearance: B continues A. Along a foreshortened row the appearance drifts, so the
  far ends of the two parts differ while the instances where they meet look alike, as
  neighbours within a part do. With s(i, j) the cosine similarity of the L2-normalised
  backbone features, ``S_AA`` (``S_BB``) the median over the instances of A (B) of the
  similarity to the most similar other instance of A (B), and ``S_AB`` the largest
  similarity of an instance of A to one of B, the test is
  ``S_AB >= rho * min(S_AA, S_BB)`` (rho = ``similarity_ratio``) and
  ``S_AB >= min_similarity``. Nearest-neighbour statistics keep an RP of 2 instances
  usable (its one pair) and, measured on the synthetic benchmark, separate split parts
  from different RPs of similar objects better than the means over all pairs (which
  the drift along the row pulls down);
* size: the median instance width and height of A and B are within a factor
  ``size_tolerance`` (foreshortening changes the size along a row, so the factor is
  looser than stage II's size gate);
* no overlap conflict: no instance of A partly overlaps or nests in an instance of B
  (intersection over the smaller box > ``conflict_cover`` while IoU < ``duplicate_iou``)
  — nested boxes are a part and its whole (a window and its pane), not one pattern;
* geometry (``max_line_residual`` > 0): B continues A's row: every instance centre
  of A and B lies within ``max_line_residual`` instance sizes (median shorter box
  side) of the total-least-squares line through all of them (a row stays a line under
  perspective). Appearance alone merged a row with a row of similar objects elsewhere
  in the image (synthetic benchmark); the price is that the parts of a split *grid*
  are not merged. Two RPs of *whole objects* (both ``source: dense``) have their own
  limit, ``max_object_line_residual`` (0: no line test): cars or coins stand where they
  like rather than in rows, and the dense source's grouping splits one kind of object
  into groups by colour and orientation. By default it is the rows' limit: without the
  line test the appearance test joins split groups of cars, but also groups of board
  edges on chess (``docs/studies/whole-objects.md``, "The dominant RP").

Merging is agglomerative: the most similar admissible pair (largest
``S_AB / min(S_AA, S_BB)``) is merged first and the evidence recomputed for the merged
RP, until no admissible pair is left. The merged RP has the lower id's position, the
higher score, the union of the instances (each keeps its box; of two duplicates, IoU >
``duplicate_iou``, the stage-I / higher-score instance stays), stage-I instances first
(A's then B's) and stage-II instances after, feature points stacked block-diagonally
(A's visual words are missing, NaN, in B's instances and vice versa, so column n still
belongs to ``instances[n]``), A's scene results (A = the higher score), ``stage2_added``
summed and ``merged_from`` (the original ids); ``box_transform`` only when both parts
had the same. Patterns are renumbered 0..K-1 in order.

The tests and the search for duplicates compare the instances on their boxes *before*
RESCU-I's box refinement. The refinement moves each RP's boxes by one transform of its
own (``extra["box_transform"]``), so two parts of one row get different boxes, sizes
and rows, and their features differ more than the parts do (``docs/studies/merge.md``).
The appearance test takes the features of those boxes when the features step made them
(``merge_instance_features``); the geometry tests and the duplicates undo each RP's
transform.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..discovery.edge_extent import unrefined_boxes
from ..discovery.sources import is_whole_object
from ..boxes import cover_matrix, iou_matrix
from ..params import checked_mapping, config_section
from ..types import ImageResult, Instance, Pattern


@dataclass(frozen=True)
@config_section("stage2", "predict", "merge")
class MergeParams:
    """Tunables of the split-RP merge (config section ``stage2.predict.merge``, less ``enabled``).

    Attributes
    ----------
    similarity_ratio : float
        rho: merge when ``S_AB >= rho * min(S_AA, S_BB)`` (nearest-neighbour cosine
        similarities, see the module docstring).
    min_similarity : float
        Smallest cross similarity ``S_AB`` of a merge, unitless.
    size_tolerance : float
        Median instance width and height of A and B within this factor (>= 1).
    duplicate_iou : float
        Instances of A and B with IoU above this are one instance (kept once).
    conflict_cover : float
        An A/B box pair whose intersection covers more than this fraction of the smaller
        box without being a duplicate is a conflict; any conflict blocks the merge.
    max_line_residual : float
        Geometry test: every instance centre of A and B within this many instance sizes
        (median shorter box side) of their common total-least-squares line; 0 disables.
    max_object_line_residual : float
        The same limit when both RPs are whole objects
        (:func:`rescu.discovery.sources.is_whole_object`); 0 disables
        the line test for them.
    """

    similarity_ratio: float
    min_similarity: float
    size_tolerance: float
    duplicate_iou: float
    conflict_cover: float
    max_line_residual: float
    max_object_line_residual: float

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "MergeParams":
        """Build from a mapping; raises ValueError naming any unknown key."""
        return cls(**checked_mapping(cls, d, "merge parameter"))


# ----------------------------------------------------------------------------- evidence
def _boxes(p: Pattern) -> np.ndarray:
    return np.array([i.bbox for i in p.instances], np.float64).reshape(-1, 4)


def compared_features(feats: dict[str, np.ndarray]) -> np.ndarray:
    """The stage-I instance features (N, D) the merge compares, from a stage-II features
    dict: ``merge_instance_features`` (those of the boxes before RESCU-I's refinement)
    where the features step made them, else ``instance_features``."""
    return np.asarray(feats.get("merge_instance_features", feats["instance_features"]),
                      np.float64)


def _iou_cover(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) IoU and intersection / smaller area of two box sets (x, y, w, h)."""
    return iou_matrix(a, b), cover_matrix(a, b)


def _nn_similarity(s: np.ndarray) -> float:
    """Median over instances of the similarity to the most similar other instance of
    the same RP (the neighbour-to-neighbour similarity S_AA); (n, n) -> float."""
    n = len(s)
    if n < 2:
        return float("nan")
    s = s.copy()
    np.fill_diagonal(s, -np.inf)
    return float(np.median(s.max(1)))


def line_residual(centres: np.ndarray) -> float:
    """Largest distance of a centre to the total-least-squares line of all centres.

    Parameters
    ----------
    centres : (N, 2) float, pixels

    Returns
    -------
    float, pixels
        0 for N < 3 (two points always lie on a line).
    """
    c = np.asarray(centres, float).reshape(-1, 2)
    if len(c) < 3:
        return 0.0
    c = c - c.mean(0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    return float(np.abs(c @ vt[-1]).max())       # distance along the line's normal


def pair_evidence(feats_a: np.ndarray, feats_b: np.ndarray, boxes_a: np.ndarray,
                  boxes_b: np.ndarray, params: MergeParams = MergeParams(),
                  objects: bool = False) -> dict[str, Any]:
    """Evidence that RPs A and B are one pattern, and the merge decision.

    Parameters
    ----------
    feats_a, feats_b : (Na, D), (Nb, D) float
        Backbone features of the stage-I instances of A and B (any scale; normalised here).
    boxes_a, boxes_b : (Ka, 4), (Kb, 4) float
        All instance boxes of A and B, ``[x, y, w, h]`` pixels.
    params : MergeParams
    objects : bool
        Both RPs are whole objects: the line test uses ``params.max_object_line_residual``
        instead of ``params.max_line_residual``.

    Returns
    -------
    dict
        ``s_aa, s_ab, s_bb`` (nearest-neighbour cosine similarities), ``ratio`` = s_ab / min(s_aa,
        s_bb), ``size_ratio`` (largest of the width / height median ratios, >= 1),
        ``conflicts`` (number of conflicting box pairs), ``line_residual`` (in instance
        sizes; 0 when the test is off) and ``merge`` (bool).
    """
    fa = np.asarray(feats_a, np.float64)
    fb = np.asarray(feats_b, np.float64)
    if fa.ndim != 2 or fb.ndim != 2 or fa.shape[1] != fb.shape[1]:
        raise ValueError(f"feats_a and feats_b must be (Na, D) and (Nb, D) arrays, got "
                         f"{fa.shape} and {fb.shape}")
    ba = np.asarray(boxes_a, np.float64).reshape(-1, 4)
    bb = np.asarray(boxes_b, np.float64).reshape(-1, 4)
    out: dict[str, Any] = {"s_aa": float("nan"), "s_ab": float("nan"), "s_bb": float("nan"),
                           "ratio": float("nan"), "size_ratio": float("nan"), "conflicts": 0,
                           "line_residual": 0.0, "merge": False}
    if len(fa) < 2 or len(fb) < 2 or len(ba) == 0 or len(bb) == 0:
        return out
    fa = fa / np.maximum(np.linalg.norm(fa, axis=1, keepdims=True), 1e-12)
    fb = fb / np.maximum(np.linalg.norm(fb, axis=1, keepdims=True), 1e-12)
    s_aa, s_bb = _nn_similarity(fa @ fa.T), _nn_similarity(fb @ fb.T)    # S_AA, S_BB
    s_ab = float((fa @ fb.T).max())                                      # S_AB
    within = min(s_aa, s_bb)
    ratio = s_ab / within if within > 1e-12 else float("inf")
    wa, ha = np.median(ba[:, 2]), np.median(ba[:, 3])
    wb, hb = np.median(bb[:, 2]), np.median(bb[:, 3])
    size_ratio = float(max(max(wa, wb) / max(min(wa, wb), 1e-9),
                           max(ha, hb) / max(min(ha, hb), 1e-9)))
    iou, cover = _iou_cover(ba, bb)
    conflicts = int(((cover > params.conflict_cover) & (iou <= params.duplicate_iou)).sum())
    ok = (s_ab >= params.similarity_ratio * within and s_ab >= params.min_similarity
          and size_ratio <= params.size_tolerance and conflicts == 0)
    res = 0.0
    limit = params.max_object_line_residual if objects else params.max_line_residual
    if limit > 0:
        allb = np.concatenate([ba, bb])
        size = float(np.median(np.minimum(allb[:, 2], allb[:, 3])))
        res = line_residual(allb[:, :2] + allb[:, 2:] / 2) / max(size, 1e-9)
        ok = ok and res <= limit
    out.update(s_aa=s_aa, s_ab=s_ab, s_bb=s_bb, ratio=float(ratio), size_ratio=size_ratio,
               conflicts=conflicts, line_residual=float(res), merge=bool(ok))
    return out


# ----------------------------------------------------------------------------- merging
def _merge_two(a: Pattern, b: Pattern, duplicate_iou: float, geom_a: np.ndarray,
               geom_b: np.ndarray) -> tuple[Pattern, np.ndarray]:
    """One pattern from A (the higher score) and B (see the module docstring), and the
    boxes of its instances the tests compare (``geom_a`` / ``geom_b``: A's and B's, in
    the order of their instances; duplicates are found on them)."""
    ia = [(ins, 0, n) for n, ins in enumerate(a.instances)]
    ib = [(ins, 1, n) for n, ins in enumerate(b.instances)]
    geom = {0: np.asarray(geom_a, float).reshape(-1, 4),
            1: np.asarray(geom_b, float).reshape(-1, 4)}

    def rank(t: tuple[Instance, int, int]) -> tuple[int, float, int, int]:
        return (0 if t[0].source == "stage1" else 1, -float(t[0].score), t[1], t[2])

    kept: list[tuple[Instance, int, int]] = []
    for t in sorted(ia + ib, key=rank):           # stage-I and higher score win duplicates
        bx = geom[t[1]][t[2]][None]
        if kept:
            iou, _ = _iou_cover(bx, np.array([geom[k[1]][k[2]] for k in kept], float))
            if (iou > duplicate_iou).any():
                continue
        kept.append(t)
    alive = {(src, n) for _, src, n in kept}
    order = ([t for t in ia if (0, t[2]) in alive and t[0].source == "stage1"]
             + [t for t in ib if (1, t[2]) in alive and t[0].source == "stage1"]
             + [t for t in ia if (0, t[2]) in alive and t[0].source != "stage1"]
             + [t for t in ib if (1, t[2]) in alive and t[0].source != "stage1"])
    fp = None
    if a.feature_points is not None or b.feature_points is not None:
        blocks = []
        cols = [(src, n) for _, src, n in order]
        for src, p in ((0, a), (1, b)):
            f = (np.asarray(p.feature_points, float) if p.feature_points is not None
                 else np.zeros((0, 0, 2)))
            blk = np.full((f.shape[0], len(cols), 2), np.nan)
            for c, (s, n) in enumerate(cols):
                if s == src and n < f.shape[1]:
                    blk[:, c] = f[:, n]
            blocks.append(blk)
        fp = np.concatenate(blocks, axis=0)
        # columns: the leading stage-I instances that have a feature-point column
        n_cols = 0
        for s, n in cols:
            p = a if s == 0 else b
            width = 0 if p.feature_points is None else np.asarray(p.feature_points).shape[1]
            if n >= width:
                break
            n_cols += 1
        fp = fp[:, :n_cols]
    out = copy.deepcopy(a)
    out.instances = [copy.deepcopy(t[0]) for t in order]
    out.feature_points = fp
    extra = dict(a.extra)
    if "stage2_added" in a.extra or "stage2_added" in b.extra:
        extra["stage2_added"] = sum(1 for i in out.instances if i.source == "stage2")
    extra["merged_from"] = sorted(set(a.extra.get("merged_from", [a.id]))
                                  | set(b.extra.get("merged_from", [b.id])))
    if a.extra.get("box_transform") != b.extra.get("box_transform"):
        extra.pop("box_transform", None)        # RESCU-I's box refinement: one per part
    out.extra = extra
    return out, np.array([geom[src][n] for _, src, n in order], float).reshape(-1, 4)


def merge_split_patterns(result: ImageResult, inst_boxes: np.ndarray, inst_feats: np.ndarray,
                         inst_pattern: np.ndarray, params: MergeParams = MergeParams()
                         ) -> tuple[ImageResult, list[dict[str, Any]]]:
    """Merge the RPs of ``result`` that are parts of one pattern.

    Parameters
    ----------
    result : ImageResult
        RESCU-II result (original pixels); not modified. A pattern's
        ``extra["box_transform"]`` (RESCU-I's box refinement) is undone for the size,
        conflict and line tests.
    inst_boxes : (N, 4) float
        Stage-I instance boxes with features, ``[x, y, w, h]`` original pixels (only
        checked for shape; the features identify the instances).
    inst_feats : (N, D) float
        Frozen backbone feature of each of those instances (the features step's
        ``merge_instance_features`` where RESCU-I refined the boxes).
    inst_pattern : (N,) int
        Position in ``result.patterns`` of the RP each instance belongs to.
    params : MergeParams

    Returns
    -------
    (ImageResult, list of dict)
        A copy with the merged patterns (ids renumbered 0..K-1, ``dominant_pattern`` the
        id of :func:`rescu.scene.counting.dominant_pattern`'s choice when anything
        merged), and one record
        per merge: ``{"ids": [id_a, id_b], **pair_evidence}`` (ids as on input).
    """
    ib = np.asarray(inst_boxes, np.float64)
    f = np.asarray(inst_feats, np.float64)
    ip = np.asarray(inst_pattern).reshape(-1)
    n = len(ip)
    if ib.shape != (n, 4):
        raise ValueError(f"inst_boxes must have shape ({n}, 4), got {ib.shape}")
    if f.ndim != 2 or len(f) != n:
        raise ValueError(f"inst_feats must have shape ({n}, D), got {f.shape}")
    if n and (ip.min() < 0 or ip.max() >= len(result.patterns)):
        raise ValueError(f"inst_pattern must index result.patterns (0..{len(result.patterns) - 1}),"
                         f" got values in [{ip.min()}, {ip.max()}]")
    out = copy.deepcopy(result)
    # groups: position -> (pattern, feature rows, boxes of the geometry tests)
    groups: dict[int, tuple[Pattern, np.ndarray, np.ndarray]] = {
        k: (p, f[ip == k], unrefined_boxes(p)) for k, p in enumerate(out.patterns)}
    log: list[dict[str, Any]] = []
    while True:
        best: tuple[float, int, int, dict[str, Any]] | None = None
        keys = sorted(groups)
        for x, ka in enumerate(keys):
            for kb in keys[x + 1:]:
                pa, fa, ba = groups[ka]
                pb, fb, bb = groups[kb]
                ev = pair_evidence(fa, fb, ba, bb, params,
                                   objects=is_whole_object(pa) and is_whole_object(pb))
                if ev["merge"] and (best is None or ev["ratio"] > best[0]):
                    best = (ev["ratio"], ka, kb, ev)
        if best is None:
            break
        _, ka, kb, ev = best
        pa, fa, ba = groups[ka]
        pb, fb, bb = groups[kb]
        log.append({"ids": [int(pa.id), int(pb.id)], **ev})
        first, second = (pa, pb) if float(pa.score) >= float(pb.score) else (pb, pa)
        ga, gb = (ba, bb) if first is pa else (bb, ba)
        merged, geom = _merge_two(first, second, params.duplicate_iou, ga, gb)
        groups[ka] = (merged, np.concatenate([fa, fb]), geom)
        del groups[kb]
    if not log:
        return out, log
    out.patterns = []
    for new_id, k in enumerate(sorted(groups)):
        p = groups[k][0]
        p.id = new_id
        out.patterns.append(p)
    from ..scene.counting import dominant_pattern

    dom = dominant_pattern(out.patterns)
    out.dominant_pattern = None if dom is None else int(out.patterns[dom].id)
    return out, log
