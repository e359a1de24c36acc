"""Per-image steps of the RESCU pipeline, file to file.

Each function here is one step of the data flow (one Snakemake rule): it reads the files
the previous step wrote, calls its stage's in-memory function (:mod:`rescu.core`), and
writes its outputs atomically.

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
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

if TYPE_CHECKING:  # annotations only
    from .discovery.sources import DenseParams

from . import core, io
from .sections import section_params, stage2_variant
from .core import RETAIN_BYTES, limit_threads, retain_freed_memory  # noqa: F401
from .failures import blocking as _blocking
from .failures import degraded_result, empty_result, is_degraded  # noqa: F401
from .types import Failure, Features, ImageResult, Pattern

__all__ = ["RETAIN_BYTES", "degraded_result", "empty_result", "is_degraded", "limit_threads",
           "retain_freed_memory"]

log = logging.getLogger("rescu")


# --------------------------------------------------------------------------- failures
def _json_failure(path: str | os.PathLike[str]) -> Failure | None:
    d = io.read_json(path)
    return d.get("failure") if isinstance(d, dict) else None


def _h5_failure(path: str | os.PathLike[str]) -> Failure | None:
    _, attrs = io.read_h5(path)
    f = attrs.get("failure")
    return json.loads(f) if f else None








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
    _, rec = core.attempt(stage, run)
    if rec is not None:
        write_empty(rec)
    return rec


def _keep_input(meta: dict[str, Any], src: ImageResult,
                out_json: str) -> Callable[[Failure], None]:
    """The ``write_empty`` of a step that refines ``src``: on an upstream failure (nothing
    to keep) an empty result, on the step's own failure its input, degraded
    (:func:`rescu.core.failed_output`)."""
    def empty(f: Failure) -> None:
        io.write_json(out_json, core.failed_output(meta, src, src.method, f))

    return empty




# --------------------------------------------------------------------------- prepare
def prepare(image_path: str, out_png: str, out_meta: str, *, image_name: str,
            max_side: int, min_side: int, max_pixels: int | None = None) -> Failure | None:
    """Load a photo (orientation, mode, downscale) and write the processed PNG + meta.

    ``out_meta`` JSON: ``{"image": image_name, "source": image_path, "original_size":
    [w, h], "processed_size": [w, h], "scale_factor": s, "notes": [...], "failure"?}``.
    A bad image (or one above ``max_pixels``, None: the configuration's) gets a 1x1
    placeholder PNG and a meta with ``failure`` set (:func:`rescu.core.prepare_file`).
    """
    prep = core.prepare_file(image_path, image_name, max_side=max_side, min_side=min_side,
                             max_pixels=max_pixels)
    io.write_image(out_png, prep.rgb)
    io.write_json(out_meta, prep.meta)
    return prep.failure


def read_prepared(png: str, meta_path: str) -> tuple[np.ndarray, dict[str, Any]]:
    """The processed RGB image (H, W, 3) uint8 and its meta dict."""
    import cv2

    meta = io.read_json(meta_path)
    bgr = cv2.imread(str(png), cv2.IMREAD_COLOR)
    if bgr is None:
        raise io.InputError(f"{png}: unreadable processed image")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), meta


def read_prepared_image(png: str, meta_path: str) -> core.Prepared:
    """The :func:`prepare` step's outputs as the in-memory record."""
    return core.Prepared(*read_prepared(png, meta_path))


# --------------------------------------------------------------------------- features
def features(png: str, meta_path: str, out_h5: str, params: dict[str, Any]) -> Failure | None:
    """SIFT features of the processed image to HDF5 (:func:`rescu.core.extract_features`,
    :func:`rescu.discovery.features.save_features`)."""
    from .discovery import features as F

    meta = io.read_json(meta_path)

    def run() -> None:
        F.save_features(out_h5, core.extract_features(read_prepared_image(png, meta_path),
                                                      params))

    def empty(f: Failure) -> None:
        size = tuple(meta.get("processed_size", [1, 1]))
        F.save_features(out_h5, Features.empty(size, float(meta.get("scale_factor", 1.0))),
                        attrs={"failure": json.dumps(f)})

    return _guard("features", meta.get("failure"), run, empty)


# --------------------------------------------------------------------------- stage I
def stage1(features_h5: str, meta_path: str, out_json: str, out_h5: str,
           params: dict[str, Any], method: str = "rescu-i",
           png: str | None = None, dense_json: str | None = None,
           dense_params: dict[str, Any] | None = None,
           dense_map_h5: str | None = None) -> Failure | None:
    """RESCU-I (``method="rescu-i"``) or GRASP (``"grasp"``) on one image's features
    (:func:`rescu.core.discover_patterns`).

    Writes the per-image JSON (``method`` set, instances in original pixels) and the RP
    matrices (feature indices) to HDF5. ``png`` (the prepared image) is what box
    refinement and the dense source's scoring look at; ``dense_json`` the :func:`dense`
    step's result, ``dense_map_h5`` the coarse feature map it kept (scoring then needs no
    backbone pass; a map made with other settings is made again). A failed dense step,
    or a dense result that cannot be read, leaves
    stage I's RPs alone and is recorded as ``extra["dense_failure"]``. With
    ``dense.mode: dense`` and a dense result that did not fail, the stage-I search is
    not run at all: the RP matrices file holds no RP, and ``extra["chosen_by"]`` is
    ``"skipped"``.
    """
    from .discovery import features as F
    from .discovery import stage1 as S1
    from .discovery.sources import read_dense

    meta = io.read_json(meta_path)

    def run() -> None:
        feats = F.load_features(features_h5)
        found = None if dense_json is None or method == "grasp" else read_dense(dense_json)
        rgb = None if png is None else read_prepared(png, meta_path)[0]
        fmap = None
        if dense_map_h5 is not None and found is not None and dense_params is not None:
            from .extension.dense import load_map

            try:
                fmap = load_map(dense_map_h5, section_params("dense", dense_params))
            except io.InputError as e:  # a cache: made again below when needed
                log.warning("%s; the scoring makes the map again", e)
        res, out = core.discover_patterns(feats, params, meta, method, rgb, found,
                                          dense_params, fmap)
        S1.save_rps(out_h5, out)
        io.write_json(out_json, res)

    def empty(f: Failure) -> None:
        io.write_h5(out_h5, {}, attrs={"failure": json.dumps(f)})
        io.write_json(out_json, empty_result(meta, method, f))

    return _guard(method, _h5_failure(features_h5), run, empty)





def dense(png: str, meta_path: str, out_json: str, params: dict[str, Any],
          out_map: str | None = None) -> Failure | None:
    """The dense source (:func:`rescu.core.find_dense`) on one prepared image: its RPs
    (instances in original pixels, ``method="dense"``) -> ``out_json``; with ``out_map``
    its coarse feature map too (:func:`rescu.extension.dense.save_map`), which RESCU-I's
    scoring reads instead of passing the backbone over the image again. A failed
    upstream step or an error writes an empty result (and a map file without a map)
    with the failure recorded."""
    from .extension import dense as D

    meta = io.read_json(meta_path)

    def run() -> None:
        prep = read_prepared_image(png, meta_path)
        res = core.find_dense(prep, params)
        if out_map is not None:
            dp = section_params("dense", params)
            D.save_map(out_map, D.dense_map(prep.rgb, dp), dp)  # made above: no new pass
        io.write_json(out_json, res)

    def empty(f: Failure) -> None:
        if out_map is not None:
            D.save_map(out_map, None, section_params("dense", params), json.dumps(f))
        io.write_json(out_json, empty_result(meta, "dense", f))

    return _guard("dense", _blocking(meta.get("failure")), run, empty)


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
        shared: dict[Any, Any] = {}      # matches and URP tables the variants have in common
        for name, over in overrides.items():
            p = section_params("stage1", {**params, **over})
            o = S1.discover(feats, p, shared)
            res = empty_result(meta, f"rescu-i[{name}]", None)
            res.patterns = core.rescu_i_patterns(feats, o.rps, p, gray, float(meta["scale_factor"]))
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

    p = section_params("stage1", params)
    sparse = next((pats for q, pats in done if q == p), None)
    if sparse is None:
        sparse = core.rescu_i_patterns(feats, S1.discover(feats, p).rps, p, gray,
                                   float(meta["scale_factor"]))
    found = D.read_dense(dense_json)  # unreadable: costs the dense rows, not the variants
    dense, failure = found.patterns, found.extra.get("failure")
    rows = A.source_rows(sparse, dense, section_params("dense", dense_params), failure)
    for name, (pats, extra) in rows.items():
        res = empty_result(meta, f"rescu-i[{name}]", None)
        res.patterns, res.extra = pats, {**res.extra, **extra}
        io.write_json(out_jsons[name], res)


# --------------------------------------------------------------------------- stage II
def stage2_features(png: str, meta_path: str, stage1_json: str, out_h5: str,
                    params: dict[str, Any]) -> Failure | None:
    """Proposals and pooled backbone features of one image to HDF5
    (:func:`rescu.core.stage2_features`)."""

    def run() -> None:
        feats = core.stage2_features(read_prepared_image(png, meta_path),
                                     io.read_result(stage1_json), params)
        backbone = (params.get("backbone") or {}).get("name", "")
        io.write_h5(out_h5, feats, attrs={"backbone": str(backbone)})

    def empty(f: Failure) -> None:
        io.write_h5(out_h5, {}, attrs={"failure": json.dumps(f)})

    return _guard("stage2-features", _json_failure(stage1_json), run, empty)


def stage2_train(feats_h5: str, stage1_json: str, out_ckpt: str,
                 params: dict[str, Any]) -> Failure | None:
    """Train the per-image head on cached features (:func:`rescu.core.stage2_train`);
    save the checkpoint."""
    from .extension.train import save_checkpoint

    def run() -> None:
        feats, _ = io.read_h5(feats_h5)
        save_checkpoint(out_ckpt, core.stage2_train(feats, io.read_result(stage1_json),
                                                    params))

    def empty(f: Failure) -> None:
        save_checkpoint(out_ckpt, {"failure": f})

    return _guard("stage2-train", _h5_failure(feats_h5), run, empty)


def _one_box(res: Any, s1: Any, meta: dict[str, Any], dense_map_h5: str | None,
             dense_params: dict[str, Any] | None) -> None:
    """RESCU-II's result ``res`` with one box per object on the map the dense step kept
    (:func:`rescu.extension.objects.one_box_after_stage2`), in place; nothing without
    the dense source (no map or no ``dense`` section); an unreadable map file is logged
    and stage II's instances are then all kept."""
    from .extension.dense import load_map
    from .extension.objects import one_box_after_stage2

    def get_map(dp: DenseParams) -> tuple[Any, float] | None:
        try:
            return load_map(dense_map_h5, dp)
        except io.InputError as e:
            log.warning("%s; RESCU-II keeps every box stage II found", e)
            return None

    one_box_after_stage2(res, s1, section_params("dense", dense_params)
                         if dense_map_h5 is not None and dense_params is not None else None,
                         float(meta["scale_factor"]), get_map)


def stage2_predict(feats_h5: str, ckpt_path: str, stage1_json: str, out_json: str,
                   meta_path: str, params: dict[str, Any], dense_map_h5: str | None = None,
                   dense_params: dict[str, Any] | None = None) -> Failure | None:
    """RESCU-II instances: stage-I instances plus the head's positive proposals
    (:func:`rescu.core.stage2_predict`), one box per object on the dense step's map
    (:func:`_one_box`)."""
    from .extension.train import load_checkpoint

    meta = io.read_json(meta_path)
    ckpt = load_checkpoint(ckpt_path)

    def run() -> None:
        feats, _ = io.read_h5(feats_h5)
        s1 = io.read_result(stage1_json)
        res = core.stage2_predict(feats, ckpt, s1, params)
        _one_box(res, s1, meta, dense_map_h5, dense_params)
        io.write_json(out_json, res)

    def empty(f: Failure) -> None:
        # a failure in stage II (features, train or here): keep stage I's patterns
        io.write_json(out_json, core.failed_output(meta, _kept_stage1(stage1_json),
                                                   "rescu-ii", f))

    return _guard("stage2-predict", ckpt.get("failure"), run, empty)


def stage2_predict_variants(feats_h5: str, ckpt_path: str, stage1_json: str,
                            meta_path: str, out_jsons: dict[str, str], params: dict[str, Any],
                            variants: dict[str, dict[str, Any]],
                            dense_map_h5: str | None = None,
                            dense_params: dict[str, Any] | None = None) -> Failure | None:
    """RESCU-II once per prediction-only variant, from the run's own features and head.

    Each variant is a nested mapping of ``stage2`` keys in the ``predict`` section only
    (the keys that act only in prediction; a ValueError names any other) overriding
    ``params``; ``out_jsons`` maps each variant to its per-image JSON (method
    ``rescu-ii[<variant>]``). Costs one prediction per variant, no backbone pass.
    """
    from .extension.params import predict_only_error
    from .extension.train import load_checkpoint

    meta = io.read_json(meta_path)
    plist = {}
    for name, over in variants.items():
        why = predict_only_error(over)
        if why:
            raise ValueError(f"prediction-only stage-II variant {name!r}: {why}")
        plist[name] = stage2_variant(params, over)
    ckpt = load_checkpoint(ckpt_path)

    def run() -> None:
        feats, _ = io.read_h5(feats_h5)
        s1 = io.read_result(stage1_json)
        for name, p in plist.items():
            res = core.stage2_predict(feats, ckpt, s1, p, method=f"rescu-ii[{name}]")
            _one_box(res, s1, meta, dense_map_h5, dense_params)
            res.extra["ablation"] = dict(variants[name])
            io.write_json(out_jsons[name], res)

    def empty(f: Failure) -> None:
        s1 = _kept_stage1(stage1_json)
        for name in variants:
            io.write_json(out_jsons[name],
                          core.failed_output(meta, s1, f"rescu-ii[{name}]", f))

    return _guard("stage2-predict-variants", ckpt.get("failure"), run, empty)


def stage2_ablation(png: str, meta_path: str, stage1_json: str, out_jsons: dict[str, str],
                    params: dict[str, Any], variants: dict[str, dict[str, Any]],
                    dense_map_h5: str | None = None,
                    dense_params: dict[str, Any] | None = None) -> Failure | None:
    """RESCU-II once per stage-II ablation variant (e.g. another ``proposal_method``).

    Each variant is a mapping of ``stage2`` keys overriding ``params``. Features, head
    and prediction are computed in memory (nothing but the JSONs is written), a backbone
    pass over pixels that several variants pass over once
    (:func:`rescu.extension.backbone.remembered_maps`);
    ``out_jsons`` maps each variant to its per-image result JSON (method
    ``rescu-ii[<variant>]``).
    """
    from .extension.proposal_features import compute_stage2_features
    from .extension.predict import predict_stage2
    from .extension.train import train_heads

    meta = io.read_json(meta_path)
    s1 = io.read_result(stage1_json)
    for name, over in variants.items():
        if not isinstance(over, dict):
            raise ValueError(f"stage-II ablation variant {name!r} must be a mapping of "
                             f"stage2 keys, got {over!r}")
    plist = {name: stage2_variant(params, over) for name, over in variants.items()}

    def run() -> None:
        from .extension.backbone import remembered_maps

        rgb, _ = read_prepared(png, meta_path)
        with remembered_maps():  # a pass over pixels that two variants share: made once
            for name, p in plist.items():
                feats = compute_stage2_features(rgb, float(meta["scale_factor"]), s1, p)
                ckpt, info = train_heads(feats, s1, p)
                res = predict_stage2(feats, ckpt, s1, p)
                _one_box(res, s1, meta, dense_map_h5, dense_params)
                res.method = f"rescu-ii[{name}]"
                res.extra["stage2"] = info
                res.extra["ablation"] = dict(variants[name])
                io.write_json(out_jsons[name], res)

    def empty(f: Failure) -> None:
        for name in variants:
            io.write_json(out_jsons[name],
                          core.failed_output(meta, s1, f"rescu-ii[{name}]", f))

    return _guard("stage2-ablation", s1.extra.get("failure"), run, empty)


# --------------------------------------------------------------------------- scene
def scene(png: str, meta_path: str, in_json: str, out_json: str, out_rectified_dir: str,
          params: dict[str, Any]) -> Failure | None:
    """Row completion, vanishing points, translation symmetry, counts; rectified views
    (:func:`rescu.core.analyse_scene`).

    ``params`` is the config's ``scene`` section. ``out_rectified_dir`` receives
    ``rp<id>.png`` for every pattern that has a VP (the folder may be empty).
    """
    meta = io.read_json(meta_path)
    Path(out_rectified_dir).mkdir(parents=True, exist_ok=True)
    src = io.read_result(in_json)

    def run() -> None:
        res, views = core.analyse_scene(read_prepared_image(png, meta_path), src, params)
        for pid, view in views.items():
            io.write_image(Path(out_rectified_dir) / f"rp{pid}.png", view)
        io.write_json(out_json, res)

    return _guard("scene", _blocking(src.extra.get("failure")), run,
                  _keep_input(meta, src, out_json))


def line_vp(png: str, meta_path: str, out_json: str, params: dict[str, Any]) -> Failure | None:
    """The explicit-line baseline (LSD + RANSAC) VP as a per-image JSON (method "lsd")."""
    from .scene.analyse import SceneParams  # the section's module: part of this step
    from .scene.vp.lsd import line_vanishing_point

    meta = io.read_json(meta_path)

    def run() -> None:
        rgb, _ = read_prepared(png, meta_path)
        p: SceneParams = section_params("scene", params)
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
    """The image's VPs from RP rows and LSD lines together (the joint estimator,
    :func:`rescu.core.image_vanishing_points`).

    ``params`` is the config's ``scene`` section; ``focal_px`` the true focal length
    (original pixels) when known. A failure of this step keeps the scene result
    (degraded).
    """
    meta = io.read_json(meta_path)
    src = io.read_result(in_json)

    def run() -> None:
        io.write_json(out_json, core.image_vanishing_points(
            read_prepared_image(png, meta_path), src, params, focal_px))

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
    ``scene.claims``, None = defaults), then base and enhanced caption of them
    (:func:`rescu.core.describe`)."""
    meta = io.read_json(meta_path)
    src = io.read_result(in_json)

    def run() -> None:
        io.write_json(out_json, core.describe(read_prepared_image(png, meta_path), src,
                                              params, claims))

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
def setup_logging(log_path: str | None = None, level: int = logging.INFO,
                  stream: Any = None) -> None:
    """Send the ``rescu`` logger (and warnings) to ``log_path``, ``stream`` (an open text
    stream, e.g. :func:`rescu.outputs.open_log`'s) or stderr."""
    handler: logging.Handler
    if stream is not None:
        handler = logging.StreamHandler(stream)
    elif log_path:
        Path(log_path).parent.mkdir(parents=True, exist_ok=True)
        handler = logging.FileHandler(log_path, mode="w")
    else:
        handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger("rescu")
    root.handlers[:] = [handler]
    root.setLevel(level)
    logging.captureWarnings(True)
