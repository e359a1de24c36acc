"""Self-supervised examples of RESCU-II: DBSCAN on the features of each RP's instances
gives cluster centres (:func:`cluster_centres`); the proposals nearest to them are
positives, those far from all are negatives (:func:`select_examples`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..boxes import iou_matrix, size_gate
from .params import Stage2Params


def dbscan_labels(x: np.ndarray, eps: float, min_samples: int) -> np.ndarray:
    """DBSCAN labels of the rows of ``x``, as ``sklearn.cluster.DBSCAN(eps, min_samples)``.

    The same algorithm as scikit-learn's (Euclidean neighbourhoods with distance <= eps,
    each point counted in its own; core points have at least ``min_samples``; clusters
    numbered in the order of their first core point, a border point joining the first
    cluster that reaches it; -1 = noise), written in NumPy for the few dozen instances
    of one RP: importing ``sklearn.cluster`` alone costs about 0.9 s per process.
    Squared distances are computed as scikit-learn's brute-force search computes them
    (float64, ``|a|^2 - 2 a.b + |b|^2``). ``tests/test_stage2.py`` checks the labels
    against scikit-learn.

    Parameters
    ----------
    x : (N, D) float
        Points.
    eps : float
        Neighbourhood radius (same units as ``x``).
    min_samples : int
        Neighbourhood size (the point included) that makes a core point.

    Returns
    -------
    (N,) int64 labels: 0, 1, ... per cluster, -1 for noise.
    """
    x64 = np.asarray(x, np.float64)
    n = len(x64)
    labels = np.full(n, -1, np.int64)
    if n == 0:
        return labels
    sq = np.einsum("ij,ij->i", x64, x64)
    d2 = np.maximum(sq[:, None] - 2.0 * (x64 @ x64.T) + sq[None, :], 0.0)
    np.fill_diagonal(d2, 0.0)
    near = d2 <= float(eps) ** 2
    core = near.sum(1) >= int(min_samples)
    label = 0
    for i in range(n):
        if labels[i] != -1 or not core[i]:
            continue
        stack = [i]
        while stack:
            j = stack.pop()
            if labels[j] != -1:
                continue
            labels[j] = label
            if core[j]:
                stack.extend(int(k) for k in np.nonzero(near[j] & (labels == -1))[0])
        label += 1
    return labels


def cluster_centres(x: np.ndarray, eps: float | None = None, min_samples: int = 2
                    ) -> tuple[np.ndarray, np.ndarray]:
    """DBSCAN cluster centres of one RP's instance features.

    Parameters
    ----------
    x : (N, D) float
        Instance features (L2-normalised).
    eps : float or None
        DBSCAN radius; ``None`` = median nearest-other-instance distance.
    min_samples : int

    Returns
    -------
    centres : (N_c, D) float32
        Mean feature of each cluster; noise points (label -1) each form their own
        centre, so every instance is represented.
    labels : (N,) int
        Cluster of every instance (noise points relabelled to their own centre).
    """
    x = np.asarray(x, np.float32)
    if x.ndim != 2 or len(x) == 0:
        raise ValueError(f"x must be an (N, D) array with N >= 1, got {x.shape}")
    if eps is None:
        if len(x) < 2:
            eps = 1.0
        else:
            dd = np.linalg.norm(x[:, None] - x[None], axis=2)
            np.fill_diagonal(dd, np.inf)
            eps = float(np.median(dd.min(1))) * 1.5
    eps = max(float(eps), 1e-6)
    lab = dbscan_labels(x, eps, int(min_samples))
    nxt = lab.max() + 1 if len(lab) else 0
    lab = lab.copy()
    for i in np.nonzero(lab < 0)[0]:
        lab[i] = nxt
        nxt += 1
    centres = np.stack([x[lab == c].mean(0) for c in range(nxt)]).astype(np.float32)
    return centres, lab


def select_examples(feats: dict[str, np.ndarray], params: Stage2Params = Stage2Params()
                    ) -> dict[str, Any]:
    """Self-supervised positive/negative proposals of every RP (DBSCAN centres).

    Parameters
    ----------
    feats : dict
        Output of :func:`rescu.extension.proposal_features.compute_stage2_features`.
    params : Stage2Params

    Returns
    -------
    dict with ``proposal_label`` (P,) int (-1 unused, 0 background, k + 1 RP k),
    ``n_centres`` (R,) int, ``n_positive`` (R,) int, ``n_negative`` int and
    ``distance`` (P, R) float (distance of every proposal to each RP's nearest centre),
    ``radius`` (R,) float (largest distance of an RP instance to its own centre, at least
    the median distance of the augmented copies of the RP's instances to the nearest
    centre).
    """
    pf = np.asarray(feats["proposal_features"], np.float32)
    boxes = np.asarray(feats["proposals"], np.float64).reshape(-1, 4)
    inst = np.asarray(feats["instance_boxes"], np.float64).reshape(-1, 4)
    inst_rp = np.asarray(feats["instance_rp"], np.int64)
    inf_ = np.asarray(feats["instance_features"], np.float32)
    R = len(np.asarray(feats["rp_index"]))
    P = len(boxes)
    label = np.full(P, -1, np.int64)
    dist = np.full((P, R), np.inf)
    n_cent = np.zeros(R, np.int64)
    n_pos = np.zeros(R, np.int64)
    radii = np.zeros(R)
    if P == 0 or R == 0:
        return {"proposal_label": label, "n_centres": n_cent, "n_positive": n_pos,
                "n_negative": 0, "distance": dist, "radius": radii}
    iou = iou_matrix(boxes, inst) if len(inst) else np.zeros((P, 0))
    cap = max(1, int(np.floor(params.examples.max_positive_fraction * P - 1e-9)))
    total_pos = 0
    for k in range(R):
        xk = inf_[inst_rp == k]
        centres, lab = cluster_centres(xk, params.examples.dbscan_eps,
                                       params.examples.dbscan_min_samples)
        n_cent[k] = len(centres)
        dk = np.linalg.norm(pf[:, None, :] - centres[None], axis=2).min(1)   # (P,)
        dist[:, k] = dk
        radius = float(np.max(np.linalg.norm(xk - centres[lab], axis=1)))
        aug = np.asarray(feats.get("aug_instance_features", np.zeros((0, 0, 0))), np.float32)
        if aug.ndim == 3 and aug.shape[0] and aug.shape[1] == len(inst_rp):
            # the augmented copies (blur, light, flip, rescale) of the instances show how
            # far an instance's feature moves under nuisance changes: a floor for the radius
            ak = aug[:, inst_rp == k].reshape(-1, aug.shape[2])
            da = np.linalg.norm(ak[:, None, :] - centres[None], axis=2).min(1)
            radius = max(radius, float(np.median(da)))
        radii[k] = radius
        size_ok = size_gate(boxes, inst[inst_rp == k], params.examples.size_tolerance)
        mx = iou.max(1) if iou.shape[1] else np.zeros(P)
        unambiguous = (mx < 0.3) | (mx >= 0.7)
        cand = np.nonzero(size_ok & unambiguous & (label < 0)
                          & (dk <= params.examples.positive_radius * max(radius, 1e-6)))[0]
        top_k = int(n_cent[k] * params.examples.top_p)          # top k = N x P in the paper
        room = max(0, cap - total_pos)
        take = cand[np.argsort(dk[cand], kind="stable")][:min(top_k, room)]
        label[take] = k + 1
        n_pos[k] = len(take)
        total_pos += len(take)
    dmin = dist.min(1)
    thr = np.quantile(dmin, params.examples.negative_quantile)
    mx = iou.max(1) if iou.shape[1] else np.zeros(P)
    neg = (label < 0) & (dmin >= thr) & (mx < 0.3)
    label[neg] = 0
    return {"proposal_label": label, "n_centres": n_cent, "n_positive": n_pos,
            "n_negative": int(neg.sum()), "distance": dist, "radius": radii}
