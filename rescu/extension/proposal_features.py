"""Step 1 of RESCU-II: :func:`compute_stage2_features` — region proposals and
frozen-backbone features of the proposals, the stage-I instances, their jittered copies and
hard negatives, in the image and its augmented copies (optionally after end-to-end
fine-tuning); plus the small helpers of the feature file (string fields, the fine-tuning
record, the RPs stage II extends, the cached backbone, the device check)."""

from __future__ import annotations

import copy
import json
from typing import Any

import numpy as np

from ..types import ImageResult
from .augment import augment_image, hard_negatives, jitter_boxes, occlude_instances, transform_boxes
from .examples import select_examples
from .params import Stage2Params
from .proposals import propose


def to_bytes(s: str) -> np.ndarray:
    return np.asarray(s.encode("utf-8"), dtype=np.bytes_)


def to_str(v: Any) -> str:
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
    return json.loads(to_str(feats["finetune_info"]))


def rp_list(stage1: ImageResult, min_instances: int = 2) -> list[tuple[int, np.ndarray]]:
    """(pattern index, (N, 4) original-pixel boxes) of every RP extended by stage II."""
    out = []
    for i, p in enumerate(stage1.patterns):
        if len(p.instances) >= max(2, int(min_instances)):
            out.append((i, np.array([ins.bbox for ins in p.instances], np.float64)))
    return out


def _empty_features(stage1: ImageResult, scale_factor: float, backbone: str,
                    size: tuple[int, int], dim: int = 0) -> dict[str, np.ndarray]:
    z4 = np.zeros((0, 4), np.float32)
    zf = np.zeros((0, dim), np.float32)
    return {
        "backbone": to_bytes(backbone), "image_size": np.array(size, np.int64),
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


def get_backbone(params: Stage2Params):
    """The frozen backbone of ``params``, the process's one of those settings
    (:func:`rescu.extension.backbone.shared_backbone`: the dense step uses the same)."""
    from .backbone import shared_backbone

    p = params.backbone
    return shared_backbone(p.name, p.weights_path, p.feature_stride, p.device)


def check_device(params: Stage2Params) -> None:
    """A CUDA device must be available when configured (clear error otherwise)."""
    import torch

    if str(params.backbone.device).startswith("cuda") and not torch.cuda.is_available():
        raise RuntimeError(f"stage2.backbone.device is {params.backbone.device!r} but "
                           "torch.cuda.is_available() is False (CPU-only torch or no GPU); set "
                           "stage2.backbone.device: cpu")


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
        ``merge_instance_features`` (N, D) — only when RESCU-I refined boxes: the
        instances' features on their boxes before the refinement, at the backbone scale
        those boxes give (:func:`backbone_scale`), which the split-RP merge compares
        (:func:`_unrefined_boxes`),
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
    check_device(params)
    h, w = rgb.shape[:2]
    size = (w, h)
    rps = rp_list(stage1, params.min_instances)
    if not rps:
        return _empty_features(stage1, scale_factor, params.backbone.name, size)
    rng = np.random.default_rng(params.seed)
    sf = float(scale_factor)
    inst = np.concatenate([b for _, b in rps]).astype(np.float32) * sf      # processed px
    inst_rp = np.concatenate([np.full(len(b), k) for k, (_, b) in enumerate(rps)]).astype(
        np.int64)
    from .proposals import clip_boxes

    inst = clip_boxes(inst, size)
    unrefined = _unrefined_boxes(stage1, rps, sf, size)
    pp = params.proposals.proposal_params()
    boxes, scores = propose(rgb, [inst[inst_rp == k] for k in range(len(rps))], pp)
    is_lat = np.zeros(len(boxes), np.int8)
    if params.proposals.lattice_windows:
        from .proposals import lattice_proposals

        lat = [lattice_proposals(inst[inst_rp == k], size, pp) for k in range(len(rps))]
        lat_b = np.concatenate(lat) if lat else np.zeros((0, 4), np.float32)
        boxes = np.concatenate([boxes, lat_b]).astype(np.float32)
        scores = np.concatenate([scores, np.zeros(len(lat_b), np.float32)])
        is_lat = np.concatenate([is_lat, np.ones(len(lat_b), np.int8)])
    jit, parent = jitter_boxes(inst, inst_rp, params.examples.n_jitter, params, rng, size)
    hneg = hard_negatives(inst, size)
    m = min(len(boxes), params.examples.n_aug_proposals)
    aug_idx = np.sort(rng.choice(len(boxes), size=m, replace=False)).astype(np.int64) \
        if m else np.zeros((0,), np.int64)

    bb = get_backbone(params)
    base = backbone_scale(inst, size, params)
    scales = [base * s for s in params.backbone.input_scales]
    # the merge's boxes at the scale they would have had without the refinement
    scales_u = None if unrefined is None else [
        backbone_scale(unrefined, size, params) * s for s in params.backbone.input_scales]
    aug_rng = copy.deepcopy(rng)  # the same augmented copies for a fine-tuned backbone

    def pooled(net) -> dict[str, np.ndarray]:
        r = copy.deepcopy(aug_rng)
        same = scales_u == scales
        sets = [boxes, inst, jit, hneg] + ([unrefined] if same else [])
        pf, inf_, jf, hf, *mf = image_features(net, rgb, sets, scales,
                                               params.backbone.pool_size)
        if unrefined is not None and not same:
            mf = image_features(net, rgb, [unrefined], scales_u, params.backbone.pool_size)
        aug: dict[str, list[np.ndarray]] = {"inst": [], "jit": [], "hneg": [], "prop": []}
        for k in range(params.examples.n_augment):
            img, sc, flip = augment_image(rgb, k, r)
            sets = [transform_boxes(x, sc, flip, w) for x in (inst, jit, hneg, boxes[aug_idx])]
            if params.examples.occlude_prob > 0:
                # own stream: the other augmentations stay as they are without occluders
                img = occlude_instances(img, sets[0], params.examples.occlude_prob,
                                        tuple(params.examples.occlude_fraction),
                                        np.random.default_rng([params.seed, 7919, k]))
            f = image_features(net, img, sets, scales, params.backbone.pool_size)
            for key, v in zip(("inst", "jit", "hneg", "prop"), f):
                aug[key].append(v)
        d = pf.shape[1]

        def stack(lst: list[np.ndarray], n: int) -> np.ndarray:
            return np.stack(lst).astype(np.float32) if lst else np.zeros((0, n, d), np.float32)

        merge = {"merge_instance_features": mf[0]} if mf else {}
        return {"proposal_features": pf, "instance_features": inf_, "jitter_features": jf,
                "hard_negative_features": hf, **merge,
                "aug_instance_features": stack(aug["inst"], len(inst)),
                "aug_jitter_features": stack(aug["jit"], len(jit)),
                "aug_hard_negative_features": stack(aug["hneg"], len(hneg)),
                "aug_proposal_features": stack(aug["prop"], m)}

    out = {
        "backbone": to_bytes(params.backbone.name), "image_size": np.array(size, np.int64),
        "scale_factor": np.float64(sf), "backbone_scale": np.float64(base),
        "rp_index": np.array([i for i, _ in rps], np.int64),
        "proposals": (boxes / sf).astype(np.float32), "proposal_scores": scores,
        "proposal_lattice": is_lat, "instance_boxes": (inst / sf).astype(np.float32),
        "instance_rp": inst_rp, "jitter_boxes": (jit / sf).astype(np.float32),
        "jitter_parent": parent, "hard_negative_boxes": (hneg / sf).astype(np.float32),
        "aug_proposal_index": aug_idx, **pooled(bb),
    }
    if params.backbone.finetune:
        from .finetune import finetune_backbone

        fb, fl = _finetune_examples(out, params, {"proposals": boxes, "instances": inst,
                                                  "jitter": jit, "hard": hneg})
        tuned, info = finetune_backbone(
            bb, rgb, fb, fl, len(rps) + 1, scale=scales[0], pool_size=params.backbone.pool_size,
            hidden_sizes=tuple(params.head.hidden_sizes), lr=params.head.lr,
            beta1=params.head.beta1, batch_size=params.head.batch_size,
            max_epochs=params.head.max_epochs, val_split=params.head.val_split,
            patience=params.head.patience, min_delta=params.head.min_delta,
            seed=params.seed)
        if tuned is not bb:
            out.update(pooled(tuned))
        out["finetune_info"] = to_bytes(json.dumps(info))
    return out


def backbone_scale(inst: np.ndarray, size: tuple[int, int], params: Stage2Params) -> float:
    """The backbone's base input scale for an image of ``size`` (W, H) pixels whose
    instances are ``inst`` (N, 4) in those pixels: ``input_side`` over the longer side,
    or with ``instance_target_px`` the median instance shorter side brought to it;
    capped so that no input side exceeds ``max_backbone_side``."""
    w, h = size
    base = min(1.0, params.backbone.input_side / float(max(w, h)))
    if params.backbone.instance_target_px > 0:
        # instance-adaptive scale: median instance shorter side -> instance_target_px
        short = float(np.median(np.minimum(inst[:, 2], inst[:, 3])))
        base = params.backbone.instance_target_px / max(short, 1.0)
    return min(base, params.backbone.max_backbone_side
               / (float(max(w, h)) * max(params.backbone.input_scales)))


def _unrefined_boxes(stage1: ImageResult, rps: list[tuple[int, np.ndarray]], sf: float,
                     size: tuple[int, int]) -> np.ndarray | None:
    """The stage-I instance boxes (rows as ``instance_boxes``, processed pixels, clipped)
    before RESCU-I's box refinement (:func:`rescu.discovery.edge_extent.unrefined_boxes`);
    None when no RP was refined."""
    from ..discovery.edge_extent import unrefined_boxes
    from .proposals import clip_boxes

    pats = [stage1.patterns[i] for i, _ in rps]
    if all(p.extra.get("box_transform") is None for p in pats):
        return None
    b = np.concatenate([unrefined_boxes(p) for p in pats])
    return clip_boxes((b * sf).astype(np.float32), size)


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
    n_want = int(np.ceil(params.examples.negatives_per_positive * max(len(pl), 1)))
    if len(nb) > n_want:
        nb = nb[np.sort(rng.choice(len(nb), n_want, replace=False))]
    boxes = np.concatenate([pb, nb]).astype(np.float32).reshape(-1, 4)
    labels = np.concatenate([pl, np.zeros(len(nb), np.int64)]).astype(np.int64)
    return boxes, labels
