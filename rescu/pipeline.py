"""Per-image steps of the RESCU pipeline, file to file.

Each function here is one step of the data flow (one Snakemake rule, or one call of the
``rescu discover`` command): it reads the files the previous step wrote, calls the
algorithms of the other ``rescu`` modules, and writes its outputs atomically.

Failure isolation (documented empty results): when a step fails on an image (bad file,
no features, an exception inside an algorithm), it still writes all its outputs, empty,
with a ``failure`` record ``{"stage", "message", "type"}`` (a JSON field, or an HDF5 root
attribute). Every later step sees the failure in its input and passes it on, so the
final per-image JSON says where and why the image failed, the failures table collects
it, and the other images are unaffected. Errors in the pipeline's own configuration
are not caught: they stop the run with a message.

Degradation (a failed step keeps the previous step's result): when a step that refines
a result fails on an image whose input result is good, its output is that input result
instead of an empty one, with the failure record extended by ``"degraded_to"``, the
method whose patterns were kept (:func:`degraded_result`):

* stage II (``stage2-features``, ``stage2-train``, ``stage2-predict`` and the
  ``stage2-predict-variants`` / ``stage2-ablation`` variants): the RESCU-II JSON is the
  stage-I JSON (patterns, scene-free) with ``method`` ``"rescu-ii"`` (or
  ``"rescu-ii[<variant>]"``) and ``failure = {"stage": "stage2-...", "type", "message",
  "degraded_to": "rescu-i"}``; a failure in stage2-features or stage2-train reaches
  stage2-predict through the HDF5 / checkpoint record as before;
* ``scene``: the input result (no VP, symmetry or completion) with
  ``"degraded_to": <its method>``;
* ``caption``: the scene result without caption (as before), marked the same way.

A degraded record does not make later steps skip: scene and caption run on the kept
patterns and pass the record on, so the final JSON has patterns, scene fields and a
caption, and its ``failure`` (still counted by the failures table) says which step
failed and which result was kept. When a degraded result fails again later, the new
record keeps the first ``degraded_to`` and the earlier record under ``"upstream"``.
A genuine upstream failure (bad image, no features, a stage-I exception: stage I has
no result to keep) still gives empty outputs everywhere. Test for a degraded record
with :func:`is_degraded`; a record without ``degraded_to`` means the image has no
result.
"""

from __future__ import annotations

import json
import logging
import os
import traceback
from pathlib import Path
from typing import Any, Callable

import numpy as np

from . import io
from .types import Failure, Features, ImageResult, Pattern, RPMatrix, failure_record

log = logging.getLogger("rescu")


# --------------------------------------------------------------------------- failures
def _json_failure(path: str | os.PathLike[str]) -> Failure | None:
    d = io.read_json(path)
    return d.get("failure") if isinstance(d, dict) else None


def _h5_failure(path: str | os.PathLike[str]) -> Failure | None:
    _, attrs = io.read_h5(path)
    f = attrs.get("failure")
    return json.loads(f) if f else None


def is_degraded(failure: Failure | None) -> bool:
    """True when ``failure`` is the record of a degraded result (a failed step whose
    output is the previous step's result, see the module docstring): the image keeps
    patterns, and later steps run on it."""
    return bool(failure) and bool(failure.get("degraded_to"))


def _blocking(failure: Failure | None) -> Failure | None:
    """The upstream failure that makes a step skip: ``failure`` unless it is degraded."""
    return None if not failure or is_degraded(failure) else failure


def degraded_result(kept: ImageResult, method: str, failure: Failure) -> ImageResult:
    """``kept`` (the previous step's result) as the output of a step that failed.

    A copy of ``kept`` with ``method`` set and ``extra["failure"]`` = ``failure`` plus
    ``"degraded_to"``: the method whose patterns were kept (``kept.method``, or the
    ``degraded_to`` of ``kept``'s own degraded record, which is then also kept under
    ``"upstream"``).
    """
    res = ImageResult.from_json(kept.to_json())
    prev = kept.extra.get("failure")
    rec: Failure = {**failure, "degraded_to": (prev or {}).get("degraded_to") or kept.method}
    if prev:
        rec["upstream"] = prev
    res.method = method
    res.extra["failure"] = rec
    return res


def _kept_stage1(stage1_json: str) -> ImageResult | None:
    """The stage-I result a failed stage-II step keeps, or None when stage I itself
    failed (or its JSON cannot be read): then the outputs are empty."""
    try:
        s1 = io.read_result(stage1_json)
    except Exception:  # noqa: BLE001 - degradation must not raise in the failure path
        log.error("cannot read %s to keep stage I's patterns:\n%s", stage1_json,
                  traceback.format_exc())
        return None
    return None if s1.extra.get("failure") else s1


def _guard(stage: str, upstream: Failure | None, run: Callable[[], None],
           write_empty: Callable[[Failure], None]) -> Failure | None:
    """Run a step; on an upstream failure or an exception write empty outputs instead.

    ``write_empty`` gets the failure record; a step that degrades writes the previous
    result there (:func:`degraded_result`) when the record is its own failure.
    """
    if upstream is not None:
        log.warning("skipping %s: upstream failure in %s: %s", stage, upstream.get("stage"),
                    upstream.get("message"))
        write_empty(upstream)
        return upstream
    try:
        run()
        return None
    except (MemoryError, KeyboardInterrupt, io.DiskFullError):  # not the image's fault
        raise
    except Exception as e:  # noqa: BLE001 - isolation is the point
        log.error("%s failed: %s\n%s", stage, e, traceback.format_exc())
        rec = failure_record(stage, e)
        write_empty(rec)
        return rec


def _keep_input(meta: dict[str, Any], src: ImageResult,
                out_json: str) -> Callable[[Failure], None]:
    """The ``write_empty`` of a step that refines ``src``: on an upstream failure (nothing
    to keep) an empty result, on the step's own failure its input, degraded."""
    upstream = _blocking(src.extra.get("failure"))

    def empty(f: Failure) -> None:
        io.write_json(out_json, empty_result(meta, src.method, f) if upstream is not None
                      else degraded_result(src, src.method, f))

    return empty


def empty_result(meta: dict[str, Any], method: str, failure: Failure | None) -> ImageResult:
    """A result with no pattern for the image described by ``meta``."""
    w, h = meta.get("original_size", [0, 0])
    extra = {"failure": failure} if failure else {}
    return ImageResult(image=meta.get("image", ""), width=int(w), height=int(h),
                       method=method, extra=extra)


# --------------------------------------------------------------------------- prepare
def prepare(image_path: str, out_png: str, out_meta: str, *, image_name: str,
            max_side: int, min_side: int, max_pixels: int | None = None) -> Failure | None:
    """Load a photo (orientation, mode, downscale) and write the processed PNG + meta.

    ``out_meta`` JSON: ``{"image": image_name, "source": image_path, "original_size":
    [w, h], "processed_size": [w, h], "scale_factor": s, "notes": [...], "failure"?}``.
    A bad image (or one above ``max_pixels``, None: the configuration's) gets a 1x1
    placeholder PNG and a meta with ``failure`` set. Names that are not UTF-8 are written
    with U+FFFD in place of their undecodable bytes (:func:`rescu.io.display_name`).
    """
    meta: dict[str, Any] = {"image": io.display_name(image_name),
                            "source": io.display_name(str(image_path))}

    def run() -> None:
        im = io.load_image(image_path, max_side=max_side, min_side=min_side,
                           max_pixels=max_pixels)
        meta.update(original_size=list(im.original_size),
                    processed_size=[int(im.rgb.shape[1]), int(im.rgb.shape[0])],
                    scale_factor=float(im.scale_factor), notes=im.notes)
        io.write_image(out_png, im.rgb)
        io.write_json(out_meta, meta)

    def empty(f: Failure) -> None:
        meta.update(original_size=[0, 0], processed_size=[1, 1], scale_factor=1.0, notes=[],
                    failure=f)
        io.write_image(out_png, np.zeros((1, 1, 3), np.uint8))
        io.write_json(out_meta, meta)

    return _guard("prepare", None, run, empty)


def read_prepared(png: str, meta_path: str) -> tuple[np.ndarray, dict[str, Any]]:
    """The processed RGB image (H, W, 3) uint8 and its meta dict."""
    import cv2

    meta = io.read_json(meta_path)
    bgr = cv2.imread(str(png), cv2.IMREAD_COLOR)
    if bgr is None:
        raise io.InputError(f"{png}: unreadable processed image")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), meta


# --------------------------------------------------------------------------- features
def features(png: str, meta_path: str, out_h5: str, params: dict[str, Any]) -> Failure | None:
    """SIFT features of the processed image to HDF5
    (:func:`rescu.discovery.features.save_features`)."""
    from .discovery import features as F
    from .types import Features

    meta = io.read_json(meta_path)

    def run() -> None:
        rgb, _ = read_prepared(png, meta_path)
        feats = F.extract_features(rgb, F.FeatureParams.from_dict(params),
                                   scale_factor=float(meta["scale_factor"]))
        F.save_features(out_h5, feats)

    def empty(f: Failure) -> None:
        size = tuple(meta.get("processed_size", [1, 1]))
        F.save_features(out_h5, Features.empty(size, float(meta.get("scale_factor", 1.0))),
                        attrs={"failure": json.dumps(f)})

    return _guard("features", meta.get("failure"), run, empty)


# --------------------------------------------------------------------------- stage I
def stage1(features_h5: str, meta_path: str, out_json: str, out_h5: str,
           params: dict[str, Any], method: str = "rescu-i",
           png: str | None = None, dense_json: str | None = None,
           dense_params: dict[str, Any] | None = None) -> Failure | None:
    """RESCU-I (``method="rescu-i"``) or GRASP (``"grasp"``) on one image's features.

    Writes the per-image JSON (``method`` set, instances in original pixels) and the RP
    matrices (feature indices) to HDF5. With ``png`` (the prepared image) and
    ``stage1.refine_boxes``, RESCU-I's boxes are moved onto the edges each RP's instances
    share (:mod:`rescu.discovery.extent`); GRASP's never are. With ``dense_json`` (the
    :func:`dense` step's result) RESCU-I's RPs are combined with the dense ones
    (:func:`rescu.discovery.sources.combine_sources`, section ``dense``); a failed dense
    step, or a dense result that cannot be read, leaves stage I's RPs alone and is
    recorded as ``extra["dense_failure"]``. With
    ``dense.mode: dense`` and a dense result that did not fail, the stage-I search is
    not run at all (its RPs would be dropped): the RP matrices file holds no RP, and
    ``extra["chosen_by"]`` is ``"skipped"``.
    """
    from .discovery import features as F
    from .discovery import stage1 as S1
    from .discovery.sources import add_dense, read_dense, skips_stage1

    meta = io.read_json(meta_path)

    def run() -> None:
        feats = F.load_features(features_h5)
        found = None if dense_json is None or method == "grasp" else read_dense(dense_json)
        if method == "grasp":
            from .discovery import grasp as G

            out = G.discover_grasp(feats, G.GraspParams.from_dict(params))
        else:
            p = S1.Stage1Params.from_dict(params)
            if skips_stage1(found, dense_params):
                out = S1.Stage1Output(rps=[], chosen={}, objective=0.0, chosen_by="skipped")
            else:
                out = S1.discover(feats, p)
        S1.save_rps(out_h5, out)
        res = empty_result(meta, method, None)
        if method == "grasp":
            res.patterns = S1.rps_to_patterns(feats, out.rps)
        else:
            gray = _prepared_gray(png if p.refine_boxes and out.rps else None, meta_path)
            res.patterns = _rescu_i_patterns(feats, out.rps, p, gray, float(meta["scale_factor"]))
            if found is not None:
                add_dense(res, found, dense_params)
                if png is not None:
                    from .extension.dense import score_and_split

                    score_and_split(res, found, dense_params, *read_prepared(png, meta_path))
        res.extra.update(chosen_params=out.chosen, chosen_by=out.chosen_by,
                         objective=out.objective, n_features=len(feats))
        io.write_json(out_json, res)

    def empty(f: Failure) -> None:
        io.write_h5(out_h5, {}, attrs={"failure": json.dumps(f)})
        io.write_json(out_json, empty_result(meta, method, f))

    return _guard(method, _h5_failure(features_h5), run, empty)


def _rescu_i_patterns(feats: Features, rps: list[RPMatrix], p: Any,
                      gray: np.ndarray | None, scale_factor: float) -> list[Pattern]:
    """RESCU-I's RP matrices as patterns (original pixels); with ``gray`` (the prepared
    image, :func:`_prepared_gray`; processed = original x ``scale_factor``, the meta's
    value) and ``p.refine_boxes``, their boxes moved onto the
    edges each RP's instances share (:func:`rescu.discovery.extent.refine_pattern_boxes`)."""
    from .discovery import stage1 as S1

    pats = S1.rps_to_patterns(feats, rps)
    if gray is not None and p.refine_boxes and pats:
        from .discovery.extent import refine_pattern_boxes

        refine_pattern_boxes(gray, scale_factor, pats, p.refine_shifts,
                             p.refine_scales)
    return pats


def dense(png: str, meta_path: str, out_json: str, params: dict[str, Any]) -> Failure | None:
    """The dense source (:func:`rescu.extension.dense.find_dense`) on one prepared image:
    its RPs (instances in original pixels, ``method="dense"``) -> ``out_json``. A failed
    upstream step or an error writes an empty result with the failure recorded."""
    from .extension import dense as D

    meta = io.read_json(meta_path)

    def run() -> None:
        rgb, _ = read_prepared(png, meta_path)
        res = empty_result(meta, "dense", None)
        res.patterns = D.find_dense(rgb, D.DenseParams.from_dict(params),
                                    scale_factor=float(meta["scale_factor"]))
        io.write_json(out_json, res)

    return _guard("dense", _blocking(meta.get("failure")), run,
                  lambda f: io.write_json(out_json, empty_result(meta, "dense", f)))


def _prepared_gray(png: str | None, meta_path: str) -> np.ndarray | None:
    """The prepared image in grey (H, W) uint8, read once per step; None without ``png``."""
    if png is None:
        return None
    import cv2

    rgb, _ = read_prepared(png, meta_path)
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def ablation(features_h5: str, meta_path: str, out_jsons: dict[str, str],
             params: dict[str, Any], variants: dict[str, Any],
             png: str | None = None, dense_json: str | None = None,
             dense_params: dict[str, Any] | None = None) -> Failure | None:
    """Stage I once per ablation variant (which of P_d, P_s, P_theta are adaptive, and
    optionally another ``orientation_mode``; see
    :func:`rescu.discovery.ablation.ablation_overrides`).

    ``out_jsons`` maps each variant name to its per-image result JSON (method
    ``rescu-i[<variant>]``). Features are loaded once. ``png``: as :func:`stage1`.

    With ``dense_json`` (:func:`dense`'s result) and ``dense_params``, also the source rows,
    named in ``out_jsons`` too (:func:`rescu.discovery.ablation.source_rows`).
    """
    from .discovery import ablation as A
    from .discovery import features as F
    from .discovery import stage1 as S1

    meta = io.read_json(meta_path)
    overrides = {name: A.ablation_overrides(v) for name, v in variants.items()}

    def run() -> None:
        feats = F.load_features(features_h5)
        gray = _prepared_gray(png if params.get("refine_boxes") else None, meta_path)
        done: list[tuple[Any, list[Pattern]]] = []
        for name, over in overrides.items():
            p = S1.Stage1Params.from_dict({**params, **over})
            o = S1.discover(feats, p)
            res = empty_result(meta, f"rescu-i[{name}]", None)
            res.patterns = _rescu_i_patterns(feats, o.rps, p, gray, float(meta["scale_factor"]))
            res.extra.update(chosen_params=o.chosen, chosen_by=o.chosen_by,
                             objective=o.objective, ablation=over)
            io.write_json(out_jsons[name], res)
            done.append((p, res.patterns))
        if dense_json is not None:
            _source_rows(feats, meta, gray, params, done, dense_json, dense_params, out_jsons)

    def empty(f: Failure) -> None:
        for name in out_jsons:
            io.write_json(out_jsons[name], empty_result(meta, f"rescu-i[{name}]", f))

    return _guard("ablation", _h5_failure(features_h5), run, empty)


def _source_rows(feats: Features, meta: dict[str, Any], gray: np.ndarray | None,
                 params: dict[str, Any], done: list[tuple[Any, list[Pattern]]],
                 dense_json: str, dense_params: dict[str, Any] | None,
                 out_jsons: dict[str, str]) -> None:
    """The source rows of :func:`ablation` (``done``: the variants' parameters and RPs)."""
    from .discovery import ablation as A
    from .discovery import sources as D
    from .discovery import stage1 as S1

    p = S1.Stage1Params.from_dict(params)
    sparse = next((pats for q, pats in done if q == p), None)
    if sparse is None:
        sparse = _rescu_i_patterns(feats, S1.discover(feats, p).rps, p, gray,
                                   float(meta["scale_factor"]))
    found = D.read_dense(dense_json)  # unreadable: costs the dense rows, not the variants
    dense, failure = found.patterns, found.extra.get("failure")
    rows = A.source_rows(sparse, dense, D.DenseParams.from_dict(dense_params), failure)
    for name, (pats, extra) in rows.items():
        res = empty_result(meta, f"rescu-i[{name}]", None)
        res.patterns, res.extra = pats, {**res.extra, **extra}
        io.write_json(out_jsons[name], res)


# --------------------------------------------------------------------------- stage II
def stage2_features(png: str, meta_path: str, stage1_json: str, out_h5: str,
                    params: dict[str, Any]) -> Failure | None:
    """Proposals and pooled backbone features of one image to HDF5."""
    from .extension.proposal_features import compute_stage2_features
    from .extension.params import Stage2Params

    meta = io.read_json(meta_path)

    def run() -> None:
        rgb, _ = read_prepared(png, meta_path)
        s1 = io.read_result(stage1_json)
        feats = compute_stage2_features(rgb, float(meta["scale_factor"]), s1,
                                        Stage2Params.from_dict(params))
        backbone = (params.get("backbone") or {}).get("name", "")
        io.write_h5(out_h5, feats, attrs={"backbone": str(backbone)})

    def empty(f: Failure) -> None:
        io.write_h5(out_h5, {}, attrs={"failure": json.dumps(f)})

    return _guard("stage2-features", _json_failure(stage1_json), run, empty)


def stage2_train(feats_h5: str, stage1_json: str, out_ckpt: str,
                 params: dict[str, Any]) -> Failure | None:
    """Train the per-image head on cached features; save the checkpoint."""
    from .extension.params import Stage2Params
    from .extension.train import save_checkpoint, train_heads

    def run() -> None:
        feats, _ = io.read_h5(feats_h5)
        ckpt, info = train_heads(feats, io.read_result(stage1_json),
                                 Stage2Params.from_dict(params))
        save_checkpoint(out_ckpt, {"head": ckpt, "info": info})

    def empty(f: Failure) -> None:
        save_checkpoint(out_ckpt, {"failure": f})

    return _guard("stage2-train", _h5_failure(feats_h5), run, empty)


def stage2_predict(feats_h5: str, ckpt_path: str, stage1_json: str, out_json: str,
                   meta_path: str, params: dict[str, Any]) -> Failure | None:
    """RESCU-II instances: stage-I instances plus the head's positive proposals."""
    from .extension.params import Stage2Params
    from .extension.predict import predict_stage2
    from .extension.train import load_checkpoint

    meta = io.read_json(meta_path)
    ckpt = load_checkpoint(ckpt_path)

    def run() -> None:
        feats, _ = io.read_h5(feats_h5)
        res = predict_stage2(feats, ckpt["head"], io.read_result(stage1_json),
                             Stage2Params.from_dict(params))
        res.method = "rescu-ii"
        # the head's training record, and prediction's own (instances added, RPs merged)
        res.extra["stage2"] = {**ckpt.get("info", {}),
                               "prediction": res.extra.get("stage2", {})}
        io.write_json(out_json, res)

    def empty(f: Failure) -> None:
        # a failure in stage II (features, train or here): keep stage I's patterns
        s1 = _kept_stage1(stage1_json)
        io.write_json(out_json, empty_result(meta, "rescu-ii", f) if s1 is None
                      else degraded_result(s1, "rescu-ii", f))

    return _guard("stage2-predict", ckpt.get("failure"), run, empty)


def stage2_predict_variants(feats_h5: str, ckpt_path: str, stage1_json: str,
                            meta_path: str, out_jsons: dict[str, str], params: dict[str, Any],
                            variants: dict[str, dict[str, Any]]) -> Failure | None:
    """RESCU-II once per prediction-only variant, from the run's own features and head.

    Each variant is a nested mapping of ``stage2`` keys in the ``predict`` section only
    (the keys that act only in prediction; a ValueError names any other) overriding
    ``params``; ``out_jsons`` maps each variant to its per-image JSON (method
    ``rescu-ii[<variant>]``). Costs one prediction per variant, no backbone pass.
    """
    from .extension.params import Stage2Params, predict_only_error
    from .extension.predict import predict_stage2
    from .extension.train import load_checkpoint

    meta = io.read_json(meta_path)
    plist = {}
    for name, over in variants.items():
        why = predict_only_error(over)
        if why:
            raise ValueError(f"prediction-only stage-II variant {name!r}: {why}")
        plist[name] = Stage2Params.variant(params, over)
    ckpt = load_checkpoint(ckpt_path)

    def run() -> None:
        feats, _ = io.read_h5(feats_h5)
        s1 = io.read_result(stage1_json)
        for name, p in plist.items():
            res = predict_stage2(feats, ckpt["head"], s1, p)
            res.method = f"rescu-ii[{name}]"
            res.extra["stage2"] = {**ckpt.get("info", {}),
                                   "prediction": res.extra.get("stage2", {})}
            res.extra["ablation"] = dict(variants[name])
            io.write_json(out_jsons[name], res)

    def empty(f: Failure) -> None:
        s1 = _kept_stage1(stage1_json)
        for name in variants:
            m = f"rescu-ii[{name}]"
            io.write_json(out_jsons[name], empty_result(meta, m, f) if s1 is None
                          else degraded_result(s1, m, f))

    return _guard("stage2-predict-variants", ckpt.get("failure"), run, empty)


def stage2_ablation(png: str, meta_path: str, stage1_json: str, out_jsons: dict[str, str],
                    params: dict[str, Any], variants: dict[str, dict[str, Any]]) -> Failure | None:
    """RESCU-II once per stage-II ablation variant (e.g. another ``proposal_method``).

    Each variant is a mapping of ``stage2`` keys overriding ``params``. Features, head
    and prediction are computed in memory (nothing but the JSONs is written);
    ``out_jsons`` maps each variant to its per-image result JSON (method
    ``rescu-ii[<variant>]``).
    """
    from .extension.proposal_features import compute_stage2_features
    from .extension.params import Stage2Params
    from .extension.predict import predict_stage2
    from .extension.train import train_heads

    meta = io.read_json(meta_path)
    s1 = io.read_result(stage1_json)
    for name, over in variants.items():
        if not isinstance(over, dict):
            raise ValueError(f"stage-II ablation variant {name!r} must be a mapping of "
                             f"stage2 keys, got {over!r}")
    plist = {name: Stage2Params.variant(params, over) for name, over in variants.items()}

    def run() -> None:
        rgb, _ = read_prepared(png, meta_path)
        for name, p in plist.items():
            feats = compute_stage2_features(rgb, float(meta["scale_factor"]), s1, p)
            ckpt, info = train_heads(feats, s1, p)
            res = predict_stage2(feats, ckpt, s1, p)
            res.method = f"rescu-ii[{name}]"
            res.extra["stage2"] = info
            res.extra["ablation"] = dict(variants[name])
            io.write_json(out_jsons[name], res)

    def empty(f: Failure) -> None:
        for name in variants:
            m = f"rescu-ii[{name}]"
            io.write_json(out_jsons[name], empty_result(meta, m, f) if s1.extra.get("failure")
                          else degraded_result(s1, m, f))

    return _guard("stage2-ablation", s1.extra.get("failure"), run, empty)


# --------------------------------------------------------------------------- scene
def scene(png: str, meta_path: str, in_json: str, out_json: str, out_rectified_dir: str,
          params: dict[str, Any]) -> Failure | None:
    """Row completion, vanishing points, translation symmetry, counts; rectified views.

    ``params`` is the config's ``scene`` section; its ``completion`` entry
    (:class:`rescu.scene.completion.CompletionParams`, absent = defaults) fills the missing
    instances of equally spaced rows first (:func:`rescu.scene.completion.complete_rows`).
    ``out_rectified_dir`` receives ``rp<id>.png`` for every pattern that has a VP (the
    folder may be empty).
    """
    import cv2

    from .scene import completion as CO
    from .scene import analyse as SC

    meta = io.read_json(meta_path)
    Path(out_rectified_dir).mkdir(parents=True, exist_ok=True)
    src = io.read_result(in_json)

    def run() -> None:
        p = SC.SceneParams.from_config(params)
        cp = CO.CompletionParams.from_dict(params.get("completion") or {})
        rgb, _ = read_prepared(png, meta_path)
        completed = CO.complete_rows(src, cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), cp,
                                     scale_factor=float(meta["scale_factor"]), vp_params=p.vp)
        res = SC.analyse_scene(completed, p)
        for pat in res.patterns:
            if pat.vanishing_point is None:
                continue
            view = SC.rectify_pattern(rgb, float(meta["scale_factor"]), pat, p)
            if view is not None:
                io.write_image(Path(out_rectified_dir) / f"rp{pat.id}.png", view)
        io.write_json(out_json, res)

    return _guard("scene", _blocking(src.extra.get("failure")), run,
                  _keep_input(meta, src, out_json))


def line_vp(png: str, meta_path: str, out_json: str, params: dict[str, Any]) -> Failure | None:
    """The explicit-line baseline (LSD + RANSAC) VP as a per-image JSON (method "lsd")."""
    from .scene import analyse as SC
    from .scene.vp.lsd import line_vanishing_point

    meta = io.read_json(meta_path)

    def run() -> None:
        rgb, _ = read_prepared(png, meta_path)
        p = SC.SceneParams.from_config(params)
        vp = line_vanishing_point(rgb, p.vp, scale_factor=float(meta["scale_factor"]))
        res = empty_result(meta, "lsd", None)
        res.vanishing_point = vp
        io.write_json(out_json, res)

    def empty(f: Failure) -> None:
        io.write_json(out_json, empty_result(meta, "lsd", f))

    return _guard("lsd-vp", meta.get("failure"), run, empty)


def vp_truth(annotations_json: str, out_json: str) -> None:
    """The derived VP ground truth of a dataset of rectified photos
    (:func:`rescu.data.datasets.rectified_vp_truth`) from its ``annotations.json``."""
    from .data.datasets import rectified_vp_truth

    try:
        truth = rectified_vp_truth(io.read_json(annotations_json))
    except io.InputError as e:
        raise io.InputError(f"{annotations_json}: {e}") from None
    io.write_json(out_json, truth)


def dataset_focal(gt_json: str | None, meta_path: str) -> float | None:
    """The true focal length (original pixels) of the image of ``meta_path`` in a dataset's
    ``vanishing_points.json`` (its calibration); None when not given there."""
    if not gt_json:
        return None
    from .io import load_vanishing_points

    g = load_vanishing_points(gt_json).get(io.read_json(meta_path).get("image", ""))
    f = None if g is None else g.get("focal_px")
    return None if f is None else float(f)


def image_vp(png: str, meta_path: str, in_json: str, out_json: str,
             params: dict[str, Any], focal_px: float | None = None) -> Failure | None:
    """The image's VPs from RP rows and LSD lines together (the joint estimator).

    ``params`` is the config's ``scene`` section (its ``image_vp`` entry:
    :class:`rescu.scene.vp.manhattan.ImageVPParams`); ``focal_px`` the true focal length
    (original pixels) when known. See :mod:`rescu.scene.image_vp`; a failure of this
    step keeps the scene result (degraded).
    """
    from .scene import analyse as SC
    from .scene.image_vp import image_vanishing_points
    from .scene.vp.manhattan import ImageVPParams

    meta = io.read_json(meta_path)
    src = io.read_result(in_json)

    def run() -> None:
        p = SC.SceneParams.from_config(params)
        ip = ImageVPParams.from_dict(params.get("image_vp"))
        rgb, _ = read_prepared(png, meta_path)
        res = image_vanishing_points(rgb, float(meta["scale_factor"]), src, p, ip, focal_px)
        io.write_json(out_json, res)

    return _guard("image-vp", _blocking(src.extra.get("failure")), run,
                  _keep_input(meta, src, out_json))


def peer_vp(png: str, meta_path: str, out_json: str, params: dict[str, Any],
            focal_px: float | None = None) -> Failure | None:
    """A peer's VPs (``lu-vp-detect``, Lu et al. 2017) as a per-image JSON (method
    "lu-vp-detect"); ``focal_px`` (original pixels) defaults to the larger image side.
    See :func:`rescu.scene.vp.peers.lu_vanishing_points`."""
    from .scene.vp.peers import lu_vanishing_points

    meta = io.read_json(meta_path)

    def run() -> None:
        rgb, _ = read_prepared(png, meta_path)
        sf = float(meta["scale_factor"])
        w, h = meta["original_size"]
        f = float(focal_px) if focal_px is not None else float(max(w, h))
        res = empty_result(meta, "lu-vp-detect", None)
        vps = lu_vanishing_points(rgb, f * sf, seed=int(params["seed"]),
                                  length_px=float(params["length_px"]) * sf,
                                  scale_factor=sf)
        res.vanishing_point = vps[0].vanishing_point if vps else None
        res.extra["vanishing_points"] = [m.to_json() for m in vps]
        res.extra["focal_px"] = f
        io.write_json(out_json, res)

    def empty(f: Failure) -> None:
        io.write_json(out_json, empty_result(meta, "lu-vp-detect", f))

    return _guard("peer-vp", meta.get("failure"), run, empty)


# --------------------------------------------------------------------------- captions
def caption(png: str, meta_path: str, in_json: str, out_json: str,
            params: dict[str, Any], claims: dict[str, Any] | None = None) -> Failure | None:
    """The final per-image JSON: only the supported claims
    (:func:`rescu.scene.claims.supported_claims`, ``claims`` the config's
    ``scene.claims``, None = defaults), then base and enhanced caption of them."""
    from .captions import caption as CAP
    from .scene.claims import ClaimParams, supported_claims

    meta = io.read_json(meta_path)
    src = io.read_result(in_json)

    def run() -> None:
        p = CAP.CaptionParams.from_dict(params)
        captioner = CAP.make_captioner(p, log=log.warning)
        rgb, _ = read_prepared(png, meta_path)
        res = supported_claims(src, ClaimParams.from_dict(claims))
        res.caption = CAP.caption_result(rgb, res, Path(meta["image"]).name, captioner, p)
        io.write_json(out_json, res)

    upstream = _blocking(src.extra.get("failure"))

    def empty(f: Failure) -> None:
        if upstream is not None:
            res = ImageResult.from_json(src.to_json())
            res.extra["failure"] = f
        else:       # the caption step's own failure: the scene result, without caption
            res = degraded_result(src, src.method, f)
        io.write_json(out_json, res)

    return _guard("caption", upstream, run, empty)


def overlay(png: str, meta_path: str, result_json: str, out_png: str,
            rectified_dir: str | None = None, mode: str = "full") -> None:
    """Picture of what was found (:func:`rescu.visualize.overlay`; ``mode`` ``full`` or
    ``boxes``: the config's ``report.overlay``)."""
    from . import visualize

    rgb, meta = read_prepared(png, meta_path)
    res = io.read_result(result_json)
    img = visualize.overlay(rgb, float(meta.get("scale_factor", 1.0)), res, mode=mode)
    io.write_image(out_png, img)


# --------------------------------------------------------------------------- logging
def setup_logging(log_path: str | None = None, level: int = logging.INFO) -> None:
    """Send the ``rescu`` logger (and warnings) to ``log_path`` or stderr."""
    handler: logging.Handler
    if log_path:
        Path(log_path).parent.mkdir(parents=True, exist_ok=True)
        handler = logging.FileHandler(log_path, mode="w")
    else:
        handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger("rescu")
    root.handlers[:] = [handler]
    root.setLevel(level)
    logging.captureWarnings(True)


def limit_threads(n: int, torch: bool = False) -> None:
    """Use at most ``n`` CPU threads in OpenCV, and in torch when ``torch`` is true or
    torch is already imported.

    Importing torch costs about 2 s, so steps that do not use it (everything but
    stage II) leave it alone instead of importing it to set its thread count.
    """
    import sys

    import cv2

    cv2.setNumThreads(max(1, int(n)))
    if torch or "torch" in sys.modules:
        import torch as _torch

        _torch.set_num_threads(max(1, int(n)))
        retain_freed_memory()


#: freed blocks up to this size stay in the process for reuse (see retain_freed_memory)
RETAIN_BYTES = 1 << 30


def retain_freed_memory(limit: int = RETAIN_BYTES) -> bool:
    """Let glibc keep freed memory (blocks up to ``limit`` bytes) for reuse.

    By default glibc serves blocks over 128 KiB-32 MiB with ``mmap`` and returns them to
    the kernel on ``free``; torch's CPU convolutions allocate and free such buffers on
    every layer, so each backbone pass faults the same pages in again (about 2 million
    page faults and 4 s of system time per stage-II image on a 2-core machine). This sets
    glibc's ``M_MMAP_THRESHOLD`` and ``M_TRIM_THRESHOLD`` to ``limit``: the process's
    peak resident memory grows by about 0.4 GB and stage II runs about 1.5x faster
    (``benchmarks/speed/stage2_cost.py``). Outputs do not change. A no-op returning False
    where the C library has no ``mallopt`` (macOS, Windows); True once set.
    """
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt  # the process's C library
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's malloc.h
    limit = int(limit)
    return bool(mallopt(m_mmap_threshold, limit)) and bool(mallopt(m_trim_threshold, limit))
