"""Step 3 of RESCU-II: :func:`predict_stage2` — the head's scores of the proposals (and,
optionally, of the visible halves of lattice windows), the prediction gates, suppression
against the stage-I instances and the merge of RPs of one pattern."""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from ..discovery.sources import is_whole_object
from ..types import ImageResult, Instance, Pattern
from ..boxes import size_gate, suppress
from .examples import select_examples
from .proposal_features import to_str
from .params import METHOD, Stage2Params


def score_features(x: np.ndarray, ckpt: dict[str, Any]) -> np.ndarray:
    """Class probabilities of box features ``x`` (N, D), (N, R + 1) float32 (column 0
    background; an untrained head gives background 1). No box (N = 0, e.g. an image
    whose proposal set is empty) gives a (0, R + 1) array.

    The head of :func:`rescu.extension.head.make_head` evaluated in NumPy (float32) from
    the checkpoint's weights: dense, ReLU, dense, ReLU, dense, softmax, on the features
    standardised with the training set's ``mean`` and ``std``. No torch import.
    """
    x = np.asarray(x, np.float32)
    n_cls = int(ckpt["n_classes"])
    sd = ckpt["state_dict"]
    if not sd or len(x) == 0:
        # checked before the reshape: (0, D) cannot be reshaped to (0, -1)
        out = np.zeros((len(x), n_cls), np.float32)
        out[:, 0] = 1.0
        return out
    h = (x.reshape(len(x), -1) - np.asarray(ckpt["mean"], np.float32)) \
        / np.asarray(ckpt["std"], np.float32)
    layers = sorted({int(k.split(".")[0]) for k in sd})
    for j, i in enumerate(layers):
        w = np.asarray(sd[f"{i}.weight"], np.float32)
        h = h @ w.T + np.asarray(sd[f"{i}.bias"], np.float32)
        if j < len(layers) - 1:
            h = np.maximum(h, 0.0)
    h = h - h.max(1, keepdims=True)
    e = np.exp(h)
    return (e / e.sum(1, keepdims=True)).astype(np.float32)


def score_proposals(feats: dict[str, np.ndarray], ckpt: dict[str, Any]) -> np.ndarray:
    """Class probabilities of every proposal, (P, R + 1) float32 (column 0 background)."""
    return score_features(np.asarray(feats["proposal_features"], np.float32), ckpt)


def impute_half(x: np.ndarray, fill: np.ndarray, side: int, pool_size: int) -> np.ndarray:
    """Box features with one half of the RoI grid kept and the other taken from ``fill``.

    Parameters
    ----------
    x : (N, C * pool_size**2) float
        Pooled box features (:func:`rescu.extension.backbone.pool_boxes`: a (C, rows, cols) grid,
        flattened).
    fill : (C * pool_size**2,) float
        The feature whose cells replace the hidden half (e.g. an RP's mean instance).
    side : int
        The half kept: 0 left, 1 right, 2 top, 3 bottom.
    pool_size : int
        Even grid size.

    Returns
    -------
    (N, C * pool_size**2) float32, each row L2-normalised as pooled features are.
    """
    if pool_size % 2 or side not in (0, 1, 2, 3):
        raise ValueError(f"need an even pool_size and side in 0..3, got {pool_size}, {side}")
    x = np.asarray(x, np.float32)
    n, d = x.shape
    c = d // (pool_size * pool_size)
    g = x.reshape(n, c, pool_size, pool_size).copy()
    f = np.asarray(fill, np.float32).reshape(c, pool_size, pool_size)
    h = pool_size // 2
    hidden = {0: (slice(None), slice(h, None)), 1: (slice(None), slice(0, h)),
              2: (slice(h, None), slice(None)), 3: (slice(0, h), slice(None))}[side]
    g[(slice(None), slice(None)) + hidden] = f[(slice(None),) + hidden]
    g = g.reshape(n, d)
    return g / (np.linalg.norm(g, axis=1, keepdims=True) + 1e-12)


def visible_half_features(feats: dict[str, np.ndarray], ckpt: dict[str, Any],
                          params: Stage2Params = Stage2Params()
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Proposal features with each lattice window's best half-imputed feature.

    An instance hidden in part (by another object, a shadow, the image border) still
    shows one half. For every lattice window (``feats["proposal_lattice"]``) whose own
    best RP probability is at least ``visible_half_min_score`` and under the lattice
    gate ``lattice_score_threshold`` (a window that passes keeps its own feature), and
    every RP k whose instance centres' bounding box, grown by ``visible_half_margin``
    times the median instance size, holds the window's centre, the window's left /
    right / top / bottom half is kept and the other half replaced by RP k's mean
    instance feature (:func:`impute_half`). The imputed feature with the highest probability of its RP
    replaces the window's own when that probability is at least
    ``visible_half_threshold`` and above the window's own best RP probability. The
    replaced rows then pass every gate of :func:`predict_stage2` (class, probability,
    feature distance) as any window does.

    Returns
    -------
    features : (P, D) float32
        ``feats["proposal_features"]`` with the replaced rows.
    replaced : (P,) bool
    """
    own_f = np.asarray(feats["proposal_features"], np.float32)
    pf = own_f.copy()
    replaced = np.zeros(len(pf), bool)
    lat = np.asarray(feats.get("proposal_lattice", np.zeros(len(pf), np.int8))).reshape(-1) > 0
    rp_index = np.asarray(feats["rp_index"]).reshape(-1)
    if len(lat) != len(pf) or not lat.any() or not ckpt["state_dict"] or not len(rp_index):
        return pf, replaced
    prob = score_features(own_f[lat], ckpt)
    idx = np.nonzero(lat)[0]
    top = prob[:, 1:].max(1)
    keep = ((top >= params.predict.visible_half_min_score)
            & (top < params.predict.lattice_score_threshold))
    idx, best = idx[keep], prob[keep, 1:].max(1)
    best = np.maximum(best, np.nextafter(np.float32(params.predict.visible_half_threshold), -1))
    if not len(idx):
        return pf, replaced
    inst = np.asarray(feats["instance_features"], np.float32)
    inst_rp = np.asarray(feats["instance_rp"], np.int64).reshape(-1)
    ib = np.asarray(feats["instance_boxes"], np.float64).reshape(-1, 4)
    pb = np.asarray(feats["proposals"], np.float64).reshape(-1, 4)[idx]
    pc = pb[:, :2] + pb[:, 2:] / 2
    for k in range(len(rp_index)):
        own = inst_rp == k
        if not own.any():
            continue
        ic = ib[own, :2] + ib[own, 2:] / 2
        grow = params.predict.visible_half_margin * np.median(ib[own, 2:], 0)
        inside = np.all((pc >= ic.min(0) - grow) & (pc <= ic.max(0) + grow), 1)
        if not inside.any():
            continue
        mean = inst[own].mean(0)
        for side in range(4):
            g = impute_half(own_f[idx[inside]], mean, side, params.backbone.pool_size)
            pk = score_features(g, ckpt)[:, k + 1]
            rows = np.nonzero(inside)[0]
            better = pk > best[rows]
            best[rows[better]] = pk[better]
            pf[idx[rows[better]]] = g[better]
            replaced[idx[rows[better]]] = True
    return pf, replaced


def proposal_gates(lattice: np.ndarray, params: Stage2Params = Stage2Params(),
                   whole_objects: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Each proposal's probability gate and feature-distance ratio: the lattice gates
    (``lattice_score_threshold``, ``lattice_distance_ratio``) for lattice windows
    (``lattice`` (P,) bool), ``score_threshold`` and ``max_distance_ratio`` for the
    others (those of ``predict.whole_objects`` when ``whole_objects``, the first value of
    :func:`rp_gates`); two (P,) float arrays."""
    pr = params.predict
    other = pr.whole_objects if whole_objects else pr
    return (np.where(lattice, pr.lattice_score_threshold, other.score_threshold),
            np.where(lattice, pr.lattice_distance_ratio, other.max_distance_ratio))


def rp_gates(pattern: Pattern, params: Stage2Params = Stage2Params()
             ) -> tuple[bool, float, bool]:
    """``(whole_objects, max_new_fraction, lattice_only)`` of one RP in prediction: an RP
    of whole objects (``pattern.extra["source"] == "dense"``, RESCU-I's RPs from the
    dense source) gets ``predict.whole_objects``' values when that section is enabled,
    every other RP the section's own."""
    pr = params.predict
    whole = is_whole_object(pattern) and pr.whole_objects.enabled
    g = pr.whole_objects if whole else pr
    return whole, float(g.max_new_fraction), bool(g.lattice_only)


def predict_stage2(feats: dict[str, np.ndarray], ckpt: dict[str, Any], stage1: ImageResult,
                   params: Stage2Params = Stage2Params()) -> ImageResult:
    """RESCU-II instances: stage-I instances + the classifier's new positive proposals.

    Parameters
    ----------
    feats : dict
        Output of :func:`rescu.extension.proposal_features.compute_stage2_features`.
    ckpt : dict
        Output of :func:`rescu.extension.train.train_heads` /
        :func:`rescu.extension.train.load_checkpoint`.
    stage1 : ImageResult
        Stage-I result; patterns with < 2 instances and images with no RP come back
        unchanged (method ``"rescu-ii"``, every instance source ``"stage1"``).
    params : Stage2Params

    Returns
    -------
    ImageResult
        ``method = "rescu-ii"``; each pattern keeps its stage-I instances (source
        "stage1"), feature points and scene results, and gets the new instances (source
        "stage2", score = class probability) appended, sorted by (y, x);
        ``extra["stage2"]`` records the backbone and counts, and each extended pattern's
        ``extra["stage2_added"]`` the number added.

    An image with RPs but no proposal at all (every RP's instances too small or too
    large for instance-scale and lattice windows: ``feats["proposals"]`` is (0, 4)) is
    a documented empty case, not an error: no RP gets a new instance (``stage2_added``
    0) and ``extra["stage2"]["status"]`` is ``"no_proposals"``.
    """
    out = copy.deepcopy(stage1)
    out.method = METHOD
    for p in out.patterns:
        for ins in p.instances:
            ins.source = "stage1"
    rp_index = [int(v) for v in np.asarray(feats["rp_index"]).reshape(-1)]
    backbone = to_str(feats["backbone"])
    if [int(v) for v in ckpt.get("rp_index", [])] != rp_index:
        raise ValueError(f"checkpoint rp_index {ckpt.get('rp_index')} does not match "
                         f"feats rp_index {rp_index}")
    summary: dict[str, Any] = {"backbone": backbone, "added": 0,
                               "status": "no_rp" if not rp_index else "ok"}
    if not rp_index or not ckpt["state_dict"]:
        if rp_index:
            summary["status"] = "untrained"
        out.extra["stage2"] = summary
        return _merge_split(out, feats, rp_index, params)
    replaced = np.zeros(len(np.asarray(feats["proposals"]).reshape(-1, 4)), bool)
    if params.predict.visible_half:
        pf, replaced = visible_half_features(feats, ckpt, params)
        feats = dict(feats, proposal_features=pf)
    prob = score_proposals(feats, ckpt)
    # distances to the DBSCAN centres, as the head's training selected them (again for a
    # checkpoint without its selection, or one of other proposals)
    sel = ckpt.get("selection")
    if sel is None or np.shape(sel["distance"]) != (len(prob), len(rp_index)):
        sel = select_examples(feats, params)
    boxes = np.asarray(feats["proposals"], np.float64).reshape(-1, 4)
    if not len(boxes):
        summary["status"] = "no_proposals"     # every RP below: no candidate, none added
    all_inst = np.array([i.bbox for p in stage1.patterns for i in p.instances],
                        np.float64).reshape(-1, 4)
    arg = prob.argmax(1)
    lat = np.asarray(feats.get("proposal_lattice", np.zeros(len(boxes), np.int8))).reshape(-1) > 0
    if len(lat) != len(boxes):
        lat = np.zeros(len(boxes), bool)
    total = by_half = 0
    for k, pi in enumerate(rp_index):
        pat = out.patterns[pi]
        whole, new_fraction, lattice_only = rp_gates(stage1.patterns[pi], params)
        thr, ratio = proposal_gates(lat, params, whole)
        own = np.array([i.bbox for i in stage1.patterns[pi].instances], np.float64)
        pk = prob[:, k + 1]
        near = sel["distance"][:, k] <= ratio * max(sel["radius"][k], 1e-6)
        allowed = lat if lattice_only else np.ones(len(boxes), bool)
        cand = np.nonzero((arg == k + 1) & (pk >= thr) & near & allowed
                          & size_gate(boxes, own, params.examples.size_tolerance))[0]
        cand = cand[np.argsort(-pk[cand], kind="stable")]
        # lattice spacing: median distance of an instance centre to its nearest other one
        co = own[:, :2] + own[:, 2:] / 2
        dd = np.linalg.norm(co[:, None] - co[None], axis=2)
        np.fill_diagonal(dd, np.inf)
        spacing = float(np.median(dd.min(1))) if len(own) > 1 else 0.0
        cand = suppress(boxes, cand, own, all_inst, params.predict.nms_iou,
                         params.predict.min_spacing_fraction * spacing)
        limit = int(np.floor(new_fraction * len(own)))
        cand = cand[np.argsort(-pk[cand], kind="stable")][:limit]
        new = [Instance(bbox=tuple(float(v) for v in boxes[c]), score=float(pk[c]),
                        source="stage2") for c in cand]
        new.sort(key=lambda ins: (ins.bbox[1], ins.bbox[0]))
        pat.instances = list(pat.instances) + new
        pat.extra = dict(pat.extra, stage2_added=len(new))
        total += len(new)
        by_half += int(replaced[cand].sum())
    summary["added"] = total
    if params.predict.visible_half:
        summary["added_by_visible_half"] = by_half
    out.extra["stage2"] = summary
    return _merge_split(out, feats, rp_index, params)


def _merge_split(out: ImageResult, feats: dict[str, np.ndarray], rp_index: list[int],
                 params: Stage2Params) -> ImageResult:
    """The last step of :func:`predict_stage2`: merge RPs that are parts of one pattern
    (:func:`rescu.extension.merge.merge_split_patterns` on the stage-I instance features,
    those of the boxes before RESCU-I's refinement where the features file has them);
    ``extra["stage2"]["merged"]`` lists the merged id pairs (ids before the merge)."""
    if not params.predict.merge.enabled or len(rp_index) < 2:
        return out
    from .merge import compared_features, merge_split_patterns

    inst_rp = np.asarray(feats["instance_rp"], np.int64).reshape(-1)
    pattern_of = np.asarray(rp_index, np.int64)[inst_rp]
    res, log = merge_split_patterns(out, np.asarray(feats["instance_boxes"], np.float64),
                                    compared_features(feats),
                                    pattern_of, params.predict.merge.merge_params())
    if log:
        res.extra["stage2"] = dict(res.extra.get("stage2", {}),
                                   merged=[[int(v) for v in r["ids"]] for r in log])
    return res
