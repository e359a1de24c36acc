"""RESCU in memory: each stage a function from records to records, and :func:`run`.

The data flow of one photo, with no file in between::

    prepare_array / prepare_file      -> Prepared      (processed RGB + meta)
    extract_features                  -> Features      (SIFT, stage I's input)
    find_dense                        -> ImageResult   (the dense source, optional)
    discover_patterns                 -> ImageResult   (RESCU-I or GRASP) + RP matrices
    stage2_features / stage2_train /
    stage2_predict  (or extend)       -> ImageResult   (RESCU-II)
    analyse_scene                     -> ImageResult   (+ rectified views)
    image_vanishing_points            -> ImageResult   (the joint image VPs)
    describe                          -> ImageResult   (supported claims + caption)

:func:`run` chains them for one RGB array (or photo file) and returns the final
:class:`~rescu.types.ImageResult`, exactly what the pipeline's per-image JSON holds for
the same image and configuration. The file steps of :mod:`rescu.pipeline` (one per
Snakemake rule) read their inputs, call the function of their stage here and write the
outputs; :func:`rescu.api.discover` calls :func:`run_image` and writes the results.

Failures (documented empty results, see :mod:`rescu.pipeline`): a step that fails on the
image gives a result with ``extra["failure"]`` = ``{"stage", "type", "message"}``; a
step that refines a good result keeps that result, ``"degraded_to"`` naming its method
(:func:`degraded_result`). Errors in the configuration raise.

>>> import numpy as np, rescu
>>> r = rescu.run(np.zeros((64, 64, 3), np.uint8), method="rescu-i")
>>> r.patterns, r.caption["base"]
([], 'No recurring pattern found.')
>>> rescu.run(np.zeros((8, 64, 3), np.uint8)).extra["failure"]["message"]
'image: image too small (64x8 pixels; at least 16 pixels per side are needed)'
>>> from rescu.data.example import example_image
>>> img, truth = example_image()
>>> r = rescu.run(img, method="rescu-i")
>>> r.patterns[0].count, r.caption["base"] is not None
(5, True)
"""

from __future__ import annotations

import copy
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Union

import numpy as np

from . import io
from .sections import section_params
from .names import METHODS
# the failure rule lives in rescu.failures; its names stay importable from here
from .failures import attempt, empty_result, failed_output
from .failures import blocking, degraded_result, is_degraded  # noqa: F401
from .types import Failure, Features, ImageResult, Pattern, RPMatrix

if TYPE_CHECKING:  # annotations only: each step imports its modules when it runs
    from .captions.caption import CaptionParams
    from .config import Sections
    from .discovery.features import FeatureParams
    from .discovery.grasp import GraspParams
    from .discovery.sources import DenseParams
    from .discovery.stage1 import Stage1Params
    from .extension.params import Stage2Params
    from .scene.claims import ClaimParams

#: Section ``stage2``: the mapping, or parameters already built (an ablation variant's)
Stage2Section = Union[Mapping[str, Any], "Stage2Params"]

log = logging.getLogger("rescu")


# --------------------------------------------------------------------------- records
@dataclass
class Prepared:
    """A photo ready for processing.

    Attributes
    ----------
    rgb : (H, W, 3) uint8
        The processed image: displayed orientation, longer side at most
        ``image.max_side``; a 1 x 1 placeholder when ``meta`` has a failure.
    meta : dict
        What the pipeline's ``meta.json`` holds: ``image`` (the name), ``source``,
        ``original_size`` and ``processed_size`` ([w, h] pixels), ``scale_factor``
        (processed = original x scale_factor), ``notes``, and ``failure`` when the photo
        could not be prepared.
    """

    rgb: np.ndarray
    meta: dict[str, Any]

    @property
    def scale_factor(self) -> float:
        """processed = original x ``scale_factor``."""
        return float(self.meta.get("scale_factor", 1.0))

    @property
    def failure(self) -> Failure | None:
        """The failure record of a photo that could not be prepared, else None."""
        return self.meta.get("failure")

    def gray(self) -> np.ndarray:
        """The processed image in grey, (H, W) uint8."""
        import cv2

        return cv2.cvtColor(self.rgb, cv2.COLOR_RGB2GRAY)


@dataclass
class RunOutput:
    """Everything :func:`run_image` made for one photo.

    Attributes
    ----------
    result : ImageResult
        The final result (the pipeline's ``final/<image>.json``).
    prepared : Prepared
        The processed image the result was computed on (for pictures).
    rectified : dict[int, (h, w, 3) uint8]
        A rectified view per pattern id that has a vanishing point.
    intermediate : dict[str, Any]
        The records of the steps by name (``features``, ``dense``, ``stage1``,
        ``rp_matrices``, ``stage2_features``, ``head``, ``rescu-ii``, ``scene``,
        ``joint``), for inspection; only the steps that ran.
    """

    result: ImageResult
    prepared: Prepared
    rectified: dict[int, np.ndarray] = field(default_factory=dict)
    intermediate: dict[str, Any] = field(default_factory=dict)


def as_written(res: ImageResult) -> ImageResult:
    """``res`` as a later step reads it back from its JSON file (plain floats, lists):
    what makes an in-memory run and the file pipeline compute the same numbers."""
    return ImageResult.from_json(json.loads(io.json_text(res)))


# --------------------------------------------------------------------------- prepare
def prepare_file(path: str | Path, image_name: str | None = None, *, max_side: int,
                 min_side: int, max_pixels: int | None = None) -> Prepared:
    """The photo at ``path`` ready for processing (:func:`rescu.io.load_image`).

    A bad photo (unreadable, too small, above ``max_pixels``) does not raise: its
    :class:`Prepared` has a 1 x 1 placeholder image and ``meta["failure"]``. Names that
    are not UTF-8 get U+FFFD for their undecodable bytes (:func:`rescu.io.display_name`).
    """
    meta: dict[str, Any] = {"image": io.display_name(image_name or Path(path).name),
                            "source": io.display_name(str(path))}
    im, failure = attempt("prepare", lambda: io.load_image(
        path, max_side=max_side, min_side=min_side, max_pixels=max_pixels))
    return _prepared(meta, im, failure)


def prepare_array(rgb: np.ndarray, image_name: str = "image", *, max_side: int,
                  min_side: int) -> Prepared:
    """An in-memory image ready for processing.

    Parameters
    ----------
    rgb : (H, W, 3) or (H, W) uint8
        The photo in displayed orientation (RGB channel order; grey is repeated).
    image_name : str
        The name the result carries (``ImageResult.image``).
    max_side, min_side : int
        The configuration's ``image`` section (pixels).

    Raises
    ------
    rescu.io.InputError
        ``rgb`` is not an (H, W, 3) or (H, W) uint8 array. An image that is too small
        does not raise: its :class:`Prepared` has ``meta["failure"]``, as for a file.
    """
    a = np.asarray(rgb)
    if a.dtype != np.uint8 or not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
        raise io.InputError(f"{image_name}: expected an (H, W, 3) or (H, W) uint8 RGB "
                            f"array, got {a.dtype} {a.shape}")
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    meta: dict[str, Any] = {"image": image_name, "source": "<array>"}
    im, failure = attempt("prepare", lambda: io.fit_image(np.ascontiguousarray(a), max_side,
                                                          min_side, image_name))
    return _prepared(meta, im, failure)


def _prepared(meta: dict[str, Any], im: io.LoadedImage | None,
              failure: Failure | None) -> Prepared:
    if im is None:
        meta.update(original_size=[0, 0], processed_size=[1, 1], scale_factor=1.0,
                    notes=[], failure=failure)
        return Prepared(np.zeros((1, 1, 3), np.uint8), meta)
    meta.update(original_size=list(im.original_size),
                processed_size=[int(im.rgb.shape[1]), int(im.rgb.shape[0])],
                scale_factor=float(im.scale_factor), notes=im.notes)
    return Prepared(im.rgb, meta)


# --------------------------------------------------------------------------- stage I
def extract_features(prep: Prepared, params: Mapping[str, Any] | FeatureParams) -> Features:
    """SIFT features of the processed image (config section ``features``: its mapping or
    its parameters, :func:`rescu.config.section_params`), as stored
    (float32 arrays, :func:`rescu.discovery.features.save_features`)."""
    from .discovery import features as F

    f = F.extract_features(prep.rgb, section_params("features", params),
                           scale_factor=prep.scale_factor)
    return Features(xy=f.xy.astype(np.float32).reshape(-1, 2),
                    scale=f.scale.astype(np.float32), angle=f.angle.astype(np.float32),
                    response=f.response.astype(np.float32),
                    descriptors=f.descriptors.astype(np.float32),
                    image_size=(int(f.image_size[0]), int(f.image_size[1])),
                    scale_factor=float(f.scale_factor))


def find_dense(prep: Prepared, params: Mapping[str, Any] | DenseParams) -> ImageResult:
    """The dense source's RPs (:func:`rescu.extension.dense.find_dense`, config section
    ``dense``), instances in original pixels, ``method="dense"``."""
    from .extension import dense as D

    res = empty_result(prep.meta, "dense", None)
    res.patterns = D.find_dense(prep.rgb, section_params("dense", params),
                                scale_factor=prep.scale_factor)
    return res


def discover_patterns(feats: Features,
                      params: Mapping[str, Any] | Stage1Params | GraspParams,
                      meta: dict[str, Any], method: str = "rescu-i",
                      rgb: np.ndarray | None = None, dense: ImageResult | None = None,
                      dense_params: Mapping[str, Any] | DenseParams | None = None,
                      dense_map: tuple[np.ndarray, float] | None = None
                      ) -> tuple[ImageResult, Any]:
    """RESCU-I (``method="rescu-i"``, section ``stage1``) or GRASP (``"grasp"``, section
    ``grasp``) on one image's features.

    With ``rgb`` (the processed image, (H, W, 3) uint8) and ``stage1.refine_boxes``,
    RESCU-I's boxes are moved onto the edges each RP's instances share
    (:mod:`rescu.discovery.edge_extent`); GRASP's never are. With ``dense`` (the dense
    source's result, possibly failed) RESCU-I's RPs are combined with it
    (:func:`rescu.discovery.sources.add_dense`, section ``dense``) and, with ``rgb``,
    scored (:func:`rescu.extension.dense.score_and_split`). With ``dense.mode: dense`` and
    a dense result that did not fail, the stage-I search is skipped
    (``extra["chosen_by"] == "skipped"``). ``dense_map``: the dense step's coarse map of
    ``rgb`` (:func:`rescu.extension.dense.dense_map`) when it was kept; without it the
    scoring makes its own (one backbone pass).

    Returns the result (``method`` set, instances in original pixels) and the search's
    :class:`rescu.discovery.stage1.Stage1Output` (its RP matrices).
    """
    from .discovery import stage1 as S1
    from .discovery.sources import add_dense, skips_stage1

    found = None if method == "grasp" else dense
    dp = None if dense_params is None else section_params("dense", dense_params)
    if method == "grasp":
        from .discovery import grasp as G

        out = G.discover_grasp(feats, section_params("grasp", params))
    else:
        p = section_params("stage1", params)
        if skips_stage1(found, dp):
            out = S1.Stage1Output(rps=[], chosen={}, objective=0.0, chosen_by="skipped")
        else:
            out = S1.discover(feats, p)
    res = empty_result(meta, method, None)
    if method == "grasp":
        res.patterns = S1.rps_to_patterns(feats, out.rps)
    else:
        gray = _gray(rgb) if rgb is not None and p.refine_boxes and out.rps else None
        res.patterns = rescu_i_patterns(feats, out.rps, p, gray, float(meta["scale_factor"]))
        if found is not None:
            add_dense(res, found, dp)
            if rgb is not None:
                from .extension.dense import score_and_split

                score_and_split(res, found, dp, rgb, meta, fmap=dense_map)
    res.extra.update(chosen_params=out.chosen, chosen_by=out.chosen_by,
                     objective=out.objective, n_features=len(feats))
    return res, out


def rescu_i_patterns(feats: Features, rps: list[RPMatrix], p: Stage1Params,
                     gray: np.ndarray | None, scale_factor: float) -> list[Pattern]:
    """RESCU-I's RP matrices as patterns (original pixels); with ``gray`` (the processed
    image, (H, W) uint8; processed = original x ``scale_factor``) and ``p.refine_boxes``,
    their boxes moved onto the edges each RP's instances share
    (:func:`rescu.discovery.edge_extent.refine_pattern_boxes`)."""
    from .discovery import stage1 as S1

    pats = S1.rps_to_patterns(feats, rps)
    if gray is not None and p.refine_boxes and pats:
        from .discovery.edge_extent import refine_pattern_boxes

        refine_pattern_boxes(gray, scale_factor, pats, p.refine_shifts, p.refine_scales)
    return pats


def _gray(rgb: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


# --------------------------------------------------------------------------- stage II
def stage2_features(prep: Prepared, s1: ImageResult, params: Stage2Section
                    ) -> dict[str, Any]:
    """Proposals and pooled backbone features of one image (section ``stage2``, a mapping
    or :class:`~rescu.extension.params.Stage2Params`), as
    stored: ``{name: array | {name: array}}`` (:func:`as_stored`)."""
    from .extension.proposal_features import compute_stage2_features

    return as_stored(compute_stage2_features(prep.rgb, prep.scale_factor, s1,
                                             _stage2(params)))


def _stage2(params: Stage2Section) -> Stage2Params:
    """Section ``stage2`` as :class:`rescu.extension.params.Stage2Params` (a mapping is
    checked and converted; parameters already built, e.g. an ablation variant's, are
    used as they are)."""
    return section_params("stage2", params)


def as_stored(arrays: dict[str, Any]) -> dict[str, Any]:
    """A nested mapping of arrays as :func:`rescu.io.read_h5` gives it back after
    :func:`rescu.io.write_h5` (numpy arrays; 0-d ones as numpy scalars)."""
    out: dict[str, Any] = {}
    for k, v in arrays.items():
        if isinstance(v, dict):
            out[k] = as_stored(v)
        else:
            a = np.asarray(v)
            out[k] = a[()] if a.ndim == 0 else a
    return out


def stage2_train(feats2: dict[str, Any], s1: ImageResult, params: Stage2Section
                 ) -> dict[str, Any]:
    """The per-image head trained on cached features: the checkpoint
    ``{"head": state, "info": training record}``."""
    from .extension.train import train_heads

    head, info = train_heads(feats2, s1, _stage2(params))
    return {"head": head, "info": info}


def stage2_predict(feats2: dict[str, Any], ckpt: dict[str, Any], s1: ImageResult,
                   params: Stage2Section, method: str = "rescu-ii") -> ImageResult:
    """RESCU-II instances: stage-I instances plus the head's positive proposals; the
    head's training record and prediction's own in ``extra["stage2"]``."""
    from .extension.predict import predict_stage2

    res = predict_stage2(feats2, ckpt["head"], s1, _stage2(params))
    res.method = method
    res.extra["stage2"] = {**ckpt.get("info", {}), "prediction": res.extra.get("stage2", {})}
    return res


# --------------------------------------------------------------------------- scene
def analyse_scene(prep: Prepared, src: ImageResult,
                  params: dict[str, Any]) -> tuple[ImageResult, dict[int, np.ndarray]]:
    """Row completion, vanishing points, translation symmetry and counts (section
    ``scene``; its ``completion`` entry fills the missing instances of equally spaced
    rows first), and a rectified view ((h, w, 3) uint8) per pattern id with a VP."""
    from .scene import analyse as SC
    from .scene import completion as CO

    p = section_params("scene", params)
    cp = section_params("scene.completion", params.get("completion"))
    completed = CO.complete_rows(src, prep.gray(), cp, scale_factor=prep.scale_factor,
                                 vp_params=p.vp)
    res = SC.analyse_scene(completed, p)
    views = {}
    for pat in res.patterns:
        if pat.vanishing_point is None:
            continue
        view = SC.rectify_pattern(prep.rgb, prep.scale_factor, pat, p)
        if view is not None:
            views[pat.id] = view
    return res, views


def image_vanishing_points(prep: Prepared, src: ImageResult, params: dict[str, Any],
                           focal_px: float | None = None) -> ImageResult:
    """The image's VPs from RP rows and LSD lines together (section ``scene``, its
    ``image_vp`` entry); ``focal_px`` the true focal length (original pixels) when
    known (:mod:`rescu.scene.image_vp`)."""
    from .scene.image_vp import image_vanishing_points as joint

    return joint(prep.rgb, prep.scale_factor, src, section_params("scene", params),
                 section_params("scene.image_vp", params.get("image_vp")), focal_px)


def describe(prep: Prepared, src: ImageResult, params: Mapping[str, Any] | CaptionParams,
             claims: Mapping[str, Any] | ClaimParams | None = None) -> ImageResult:
    """Only the supported claims (:func:`rescu.scene.claims.supported_claims`, ``claims``
    the config's ``scene.claims``), then the base and enhanced caption of them (section
    ``caption``)."""
    from .captions import caption as CAP
    from .scene.claims import supported_claims

    p = section_params("caption", params)
    captioner = CAP.make_captioner(p, log=log.warning)
    res = supported_claims(src, section_params("scene.claims", claims))
    res.caption = CAP.caption_result(prep.rgb, res, Path(prep.meta["image"]).name,
                                     captioner, p)
    return res


# --------------------------------------------------------------------------- prompt
def find_prompted(prep: Prepared, src: ImageResult, examples: np.ndarray,
                  cfg: dict[str, Any]) -> ImageResult:
    """``src`` with the pattern of every instance of what ``examples`` show first.

    ``examples`` (K, 4) are ``x, y, w, h`` in original pixels, checked
    (:func:`rescu.extension.prompted.check_examples`). The new pattern (id one above
    ``src``'s, 0 when it has none) holds the examples (``source`` ``"example"``, score
    1) and the finds of :func:`rescu.extension.prompted.find_like` (``"prompt"``, score
    the correlation) on the processed image with the stage-II backbone (config sections
    ``prompt``, ``stage2.backbone``); its ``extra``: ``source`` ``"prompt"``,
    ``examples`` (K), ``reference`` and ``threshold`` (scores). It is the dominant
    pattern (:func:`rescu.scene.counting.dominant_pattern`).
    """
    from .extension.prompted import find_like
    from .extension.proposal_features import get_backbone
    from .types import Instance

    p = section_params("prompt", cfg["prompt"])
    backbone = get_backbone(section_params("stage2", cfg["stage2"]))
    s = float(prep.scale_factor)
    with _threads(cfg, "in_process"):
        found = find_like(prep.rgb, np.asarray(examples, np.float64) * s, backbone, p)
    boxes = found.boxes / s
    boxes[:found.is_example.sum()] = examples  # the user's boxes, as given
    inst = [Instance(bbox=tuple(float(v) for v in b), score=float(min(1.0, sc)),
                     source="example" if e else "prompt")
            for b, sc, e in zip(boxes, found.scores, found.is_example)]
    finds = found.scores[~found.is_example]
    pid = 1 + max((q.id for q in src.patterns), default=-1)
    pat = Pattern(id=pid, score=float(finds.mean()) if len(finds) else 1.0, instances=inst,
                  extra={"source": "prompt", "examples": int(found.is_example.sum()),
                         "reference": round(found.reference, 6),
                         "threshold": round(found.threshold, 6)})
    res = copy.copy(src)
    res.patterns = [pat] + list(src.patterns)
    res.extra = dict(src.extra, prompted={"examples": int(found.is_example.sum()),
                                          "pattern": pid, "unprompted": p.unprompted})
    return res


# --------------------------------------------------------------------------- run
def run(image: np.ndarray | str | Path, config: dict[str, Any] | None = None,
        method: str = "rescu-ii", name: str | None = None,
        examples: Any = None) -> ImageResult:
    """Discover the recurring patterns of one image and describe the scene, in memory.

    Parameters
    ----------
    image : (H, W, 3) or (H, W) uint8 array, or path
        An RGB array in displayed orientation, or a photo file (any format Pillow
        reads).
    config : dict, optional
        A full configuration, checked (:func:`rescu.config.validate_config`); the default
        configuration when omitted.
    method : {"rescu-ii", "rescu-i", "grasp"}
        Which instances the scene analysis and caption use.
    name : str, optional
        The result's ``image`` name (default: the file's name, or ``"image"``).
    examples : sequence of (x, y, w, h), optional
        "Count these": boxes of one kind of object, pixels of the original photo. The
        result's first pattern is then every instance of it (:func:`find_prompted`),
        dominant, its instances' ``source`` ``"example"`` or ``"prompt"``.

    Returns
    -------
    ImageResult
        The same as the pipeline's per-image JSON for this image and configuration;
        with ``extra["failure"]`` (and no pattern) when the image could not be processed
        (too small, unreadable file). Nothing is written.

    Raises
    ------
    rescu.io.InputError
        ``image`` is not a uint8 RGB or grey array nor a path; ``method`` or ``config``
        is invalid; an example box is malformed or leaves the photo
        (:class:`ExampleError`).

    Examples
    --------
    >>> import numpy as np, rescu
    >>> r = rescu.run(np.zeros((64, 64, 3), np.uint8), method="rescu-i")
    >>> r.width, r.height, r.patterns
    (64, 64, [])
    """
    return run_image(image, config, method, name, examples=examples).result


def run_image(image: np.ndarray | str | Path, config: dict[str, Any] | None = None,
              method: str = "rescu-ii", name: str | None = None, keep: bool = False,
              examples: Any = None) -> RunOutput:
    """:func:`run` with everything it made: the prepared image, the rectified views and,
    with ``keep``, the intermediate records (:class:`RunOutput`). ``config`` is checked
    (:func:`rescu.config.validate_config`: once per content in a process). ``examples``:
    as :func:`run`'s, checked against the photo's size once it is read
    (:class:`ExampleError`)."""
    from .config import load_config, validate_config

    if method not in METHODS:
        raise io.InputError(f"method must be one of {METHODS}, got {method!r}")
    if config is None:
        cfg = load_config(stage2=method == "rescu-ii")
    else:
        cfg = validate_config(config, "config", stage2=method == "rescu-ii")
    im = cfg["image"]
    if isinstance(image, (str, Path)):
        prep = prepare_file(image, name, max_side=im["max_side"], min_side=im["min_side"],
                            max_pixels=im["max_pixels"])
    elif isinstance(image, np.ndarray):
        prep = prepare_array(image, name or "image", max_side=im["max_side"],
                             min_side=im["min_side"])
    else:
        raise io.InputError(f"image must be an RGB array or a path, got "
                            f"{type(image).__name__}")
    if prep.failure:  # nothing to process
        return RunOutput(empty_result(prep.meta, method, prep.failure), prep)
    ex = None
    if examples is not None:
        from .extension.prompted import check_examples

        w, h = prep.meta["original_size"]
        try:
            ex = check_examples(examples, int(w), int(h), cfg["prompt"]["min_box_px"])
        except ValueError as e:
            raise ExampleError(f"{prep.meta['image']}: {e}") from None
    return _chain(prep, cfg, method, keep, ex)


class ExampleError(io.InputError):
    """An example box of "count these" that cannot be used on its photo (malformed,
    too small, outside the photo); the message names the photo and the box."""


def _chain(prep: Prepared, cfg: dict[str, Any], method: str, keep: bool,
           examples: np.ndarray | None = None) -> RunOutput:
    """The steps after preparing, with the pipeline's failure semantics; with
    ``examples`` ((K, 4) original pixels, checked) the prompted pattern is added before
    the scene step, and with ``prompt.unprompted`` false nothing is discovered without
    them."""
    meta = prep.meta
    kept: dict[str, Any] = {}
    out = RunOutput(empty_result(meta, method, None), prep, {}, kept)
    from .config import typed_config

    typed = typed_config(cfg)  # every section's parameters, built once
    if examples is not None and not typed.prompt.unprompted:
        src = empty_result(meta, method, None)
    else:
        src = _discover(prep, cfg, typed, method, kept, out)
        if src is None:
            return out
    return _describe(prep, cfg, typed, src, kept, out, keep, examples)


def _discover(prep: Prepared, cfg: dict[str, Any], typed: Sections, method: str,
              kept: dict[str, Any], out: RunOutput) -> ImageResult | None:
    """Discovery without examples (features, dense source, stage I, stage II); None, with
    ``out.result`` the failure, when a step the rest needs failed."""
    meta = prep.meta
    s1_method = "grasp" if method == "grasp" else "rescu-i"

    feats, f = attempt("features", lambda: extract_features(prep, typed.features))
    if f is not None:
        out.result = empty_result(meta, method, f)
        return None
    kept["features"] = feats
    found = None
    if s1_method == "rescu-i" and typed.dense.enabled:
        with _threads(cfg, "in_process"):
            found, f = attempt("dense", lambda: find_dense(prep, typed.dense))
        found = as_written(found) if f is None else empty_result(meta, "dense", f)
        kept["dense"] = found
    got, f = attempt(s1_method, lambda: discover_patterns(
        feats, typed.grasp if s1_method == "grasp" else typed.stage1, meta, s1_method,
        prep.rgb, found, typed.dense))
    if f is not None:
        out.result = empty_result(meta, method, f)
        return None
    src = as_written(got[0])
    kept["stage1"], kept["rp_matrices"] = src, got[1]
    if method == "rescu-ii":
        src = _extend(prep, src, cfg, typed, kept)
    return src


def _describe(prep: Prepared, cfg: dict[str, Any], typed: Sections, src: ImageResult,
              kept: dict[str, Any], out: RunOutput, keep: bool,
              examples: np.ndarray | None) -> RunOutput:
    """The prompted pattern (with ``examples``), the scene, the image VPs and the
    caption, each step's failure keeping the previous result."""
    def step(stage: str, fn: Callable[[ImageResult], ImageResult]) -> None:
        nonlocal src
        res, f = attempt(stage, lambda: fn(src))
        src = as_written(res) if f is None else failed_output(prep.meta, src, src.method, f)

    if examples is not None:
        step("prompt", lambda s: find_prompted(prep, s, examples, cfg))
        kept["prompt"] = src
    views: dict[int, np.ndarray] = {}

    def scene(s: ImageResult) -> ImageResult:
        res, v = analyse_scene(prep, s, cfg["scene"])
        views.update(v)
        return res

    step("scene", scene)
    out.rectified = views
    kept["scene"] = src
    step("image-vp", lambda s: image_vanishing_points(prep, s, cfg["scene"]))
    kept["joint"] = src
    step("caption", lambda s: describe(prep, s, typed.caption, typed.claims))
    out.result = src
    if not keep:
        out.intermediate = {}
    return out


def _extend(prep: Prepared, s1: ImageResult, cfg: dict[str, Any], typed: Sections,
            kept: dict[str, Any]) -> ImageResult:
    """Stage II's three steps on a good stage-I result; a failure keeps ``s1``."""
    p = typed.stage2
    with _threads(cfg, "in_process"):
        feats2, f = attempt("stage2-features", lambda: stage2_features(prep, s1, p))
    if f is None:
        kept["stage2_features"] = feats2
        with _threads(cfg, "stage2_head"):
            ckpt, f = attempt("stage2-train", lambda: stage2_train(feats2, s1, p))
            if f is None:
                kept["head"] = ckpt
                res, f = attempt("stage2-predict", lambda: _one_box(
                    prep, s1, stage2_predict(feats2, ckpt, s1, p), cfg, typed.dense))
    if f is not None:
        return failed_output(prep.meta, s1, "rescu-ii", f)
    kept["rescu-ii"] = res = as_written(res)
    return res


def _one_box(prep: Prepared, s1: ImageResult, res: ImageResult,
             cfg: dict[str, Any], d: DenseParams) -> ImageResult:
    """RESCU-II's ``res`` with one box per object (as the pipeline's prediction step:
    :func:`rescu.extension.objects.one_box_after_stage2`) on this process's dense map."""
    from .extension.dense import dense_map
    from .extension.objects import one_box_after_stage2

    def get_map(dp: DenseParams) -> tuple[np.ndarray, float]:
        with _threads(cfg, "in_process"):
            return dense_map(prep.rgb, dp)

    return one_box_after_stage2(res, s1, d if d.enabled else None, prep.scale_factor,
                                get_map)


class _threads:
    """The thread count of a torch step run in this process (config ``threads``:
    ``in_process`` for the backbone steps, ``stage2_head`` for the head; a fixed count
    gives fixed floats, and no threads spin against each other), the caller's torch and
    OpenCV settings restored afterwards. With ``threads.in_process`` equal to
    ``threads.stage2_features`` the results are the pipeline's."""

    def __init__(self, cfg: dict[str, Any], key: str) -> None:
        self.n = (cfg.get("threads") or {}).get(key, 1 if key == "stage2_head" else 2)

    def __enter__(self) -> None:
        import cv2
        import torch

        self.restore = (torch.get_num_threads(), cv2.getNumThreads())
        limit_threads(self.n, torch=True)

    def __exit__(self, *exc: object) -> None:
        import cv2
        import torch

        torch.set_num_threads(self.restore[0])
        cv2.setNumThreads(self.restore[1])


# --------------------------------------------------------------------------- threads
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
