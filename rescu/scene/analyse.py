"""Scene understanding from recurring patterns: VPs, 3D translation symmetry, counts.

:func:`analyse_scene` takes an :class:`~rescu.types.ImageResult` from stage I or II and
returns a copy in which

* every pattern has ``vanishing_point`` (RP-based VPD, :mod:`rescu.scene.vp`) and
  ``translation_symmetry`` (cross-ratio test, :mod:`rescu.scene.symmetry`) set, None where not
  determinable (fewer than two instances or no row; no row of ``min_instances``), and
  ``extra["rows"]``: the instance indices of each row used, ordered along the row
  towards the VP (for a VP at infinity: along its direction);
* ``dominant_pattern`` is the ``id`` of the pattern with most instances (ties: higher
  score, then earlier pattern; :func:`rescu.scene.counting.dominant_pattern`), None without
  patterns;
* the image-level ``vanishing_point`` is the *dominant VP*: the VP shared by the most
  RP instances, read with ``vp.hidden_rows`` from the reported RPs and the stage-I RPs
  the confidence hid (:func:`hidden_patterns`: the paper's stage III reads every RP
  stage I found; they are never reported, and give the image VP even when no RP is
  reported; the VP of the reported RPs alone is then kept as
  ``extra["reported_rp_vanishing_point"]``, the joint image VP's point hypothesis,
  :mod:`rescu.scene.image_vp`); when those give none, the RPs set aside as one structure
  (:func:`structure_patterns`) are read too (not with ``vp.joint_alpha = 0``). With
  ``vp.union_rows`` it is first sought among the rows of all patterns together
  (:func:`rescu.scene.vp.estimator.union_vanishing_point`: lines weighted by their
  track length, so rows of several patterns that each have too few
  lines for a VP of their own still find theirs), kept when every pattern with a VP of
  its own accepts it (likelihood-ratio test of level ``vp.joint_alpha``). Otherwise
  each pattern's VP is re-estimated jointly with the patterns that share it
  (:func:`rescu.scene.vp.estimator.joint_vanishing_point`) and the group with the most
  instances wins (ties: the group of the more dominant pattern), so without sharing it
  is the dominant pattern's VP, and when that has none the VP of the largest other
  pattern. With ``vp.joint_alpha = 0``: the dominant pattern's own VP, else the VP with
  the largest support among the others. None when no pattern has a VP (nor the union
  of their rows) — in particular an ImageResult with no patterns (and no hidden stage-I
  RP) comes back with no VP, no dominant pattern and nothing else changed (the
  documented empty result).

``method``, instances, scores and captions are unchanged. All coordinates are original
pixels. :func:`rectify_pattern` warps the region of one pattern so that its VP goes to
infinity (see :func:`rescu.scene.symmetry.vp_rectifying_homography`).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Callable, Sequence

import numpy as np

from .. import layout as L
from . import counting as CNT
from . import symmetry as S
from .vp.estimator import joint_vanishing_point, rp_vanishing_point, union_vanishing_point
from .vp.geometry import INFINITY_EPS
from .vp.lines import Lines, pattern_lines
from .vp.params import VPParams
from ..types import ImageResult, Pattern, VanishingPoint
from ..params import checked_mapping, config_section


@dataclass(frozen=True)
@config_section("scene")
class SceneParams:
    """Parameters of the scene step (config section ``scene``).

    Attributes
    ----------
    vp : VPParams
        Vanishing-point detection (RP-based and the LSD baseline).
    symmetry : SymmetryParams
        Translation-symmetry test.
    rectify_max_side : int
        Largest side of a rectified view, pixels.
    rectify_padding : float
        The RP region (union of the instance boxes) is padded by this fraction of its
        larger side before rectification.
    rectify_min_w : float
        A region part whose homogeneous scale after rectification would fall below
        this (i.e. magnified more than 1 / rectify_min_w times relative to the centre)
        makes the rectification ill-posed: no view is returned.
    """

    vp: VPParams = field(default_factory=VPParams)
    symmetry: S.SymmetryParams = field(default_factory=S.SymmetryParams)
    rectify_max_side: int
    rectify_padding: float
    rectify_min_w: float

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "SceneParams":
        """Build from the nested mapping ``{"vp": {...}, "symmetry": {...}, ...}``.

        Unknown keys (at any level) raise ValueError naming them.
        """
        d = checked_mapping(cls, d)
        for key in ("vp", "symmetry"):
            if key in d and not isinstance(d[key], (dict, type(None))):
                raise ValueError(f"SceneParams.{key} must be a mapping, got "
                                 f"{type(d[key]).__name__}")
        d["vp"] = VPParams.from_dict(d.get("vp"))
        d["symmetry"] = S.SymmetryParams.from_dict(d.get("symmetry"))
        return cls(**d)

    @classmethod
    def from_config(cls, section: dict[str, Any] | None) -> "SceneParams":
        """Build from the configuration's whole ``scene`` section: its ``source`` (which
        instances the scene step reads), ``completion``
        (:class:`rescu.scene.completion.CompletionParams`), ``image_vp``
        (:class:`rescu.scene.vp.manhattan.ImageVPParams`), ``claims``
        (:class:`rescu.scene.claims.ClaimParams`) and ``peer_vp`` belong to other steps and
        are left out; every other key goes to :meth:`from_dict`.

        >>> from rescu.params import config_defaults
        >>> p = SceneParams.from_config(config_defaults("scene"))
        >>> p.vp.ransac_iterations, p.symmetry.threshold
        (1000, 0.06)
        """
        return cls.from_dict({k: v for k, v in (section or {}).items()
                              if k not in ("source", "completion", "image_vp", "peer_vp",
                                           "claims")})


def _boxes(p: Pattern) -> np.ndarray:
    return np.array([i.bbox for i in p.instances], float).reshape(-1, 4)


def _orient_rows(rows: list[np.ndarray], centres: np.ndarray,
                 vp: VanishingPoint | None) -> list[np.ndarray]:
    """Order each row towards the VP (first instance farthest from it)."""
    if vp is None:
        return rows
    v = np.asarray(vp.homogeneous, float)
    out = []
    for r in rows:
        a, b = centres[r[0]], centres[r[-1]]
        if abs(v[2]) <= INFINITY_EPS:
            towards = float((b - a) @ v[:2]) >= 0
        else:
            p = v[:2] / v[2]
            towards = np.linalg.norm(b - p) <= np.linalg.norm(a - p)
        out.append(r if towards else r[::-1])
    return out


def equal_rows(feature_points: np.ndarray | None, centres: np.ndarray,
               rows: Sequence[np.ndarray], symmetry_params: S.SymmetryParams | None,
               params: VPParams = VPParams()) -> list[bool] | None:
    """Per row, whether it passes the translation-symmetry test on its own.

    The row test of the VP estimator (:data:`rescu.scene.vp.estimator.RowTest`): equally
    spaced rows also constrain the VP by their spacing.

    Parameters
    ----------
    feature_points : (M, N', 2) float or None
        Corresponding features, pixels, NaN where missing.
    centres : (N, 2) float
        Instance centres, pixels.
    rows : list of int arrays
        Instance indices of each row, in order along it.
    symmetry_params : SymmetryParams or None
    params : VPParams

    Returns
    -------
    list of bool or None
        None when ``symmetry_params`` is None or ``params.spacing_alpha`` is 0 (spacing
        model off); rows shorter than ``symmetry_params.min_instances`` are False.
    """
    if symmetry_params is None or params.spacing_alpha <= 0 or not rows:
        return None
    out = []
    for r in rows:
        r = np.asarray(r, int)
        ts = (S.translation_symmetry(feature_points, centres, [r], symmetry_params)
              if len(r) >= symmetry_params.min_instances else None)
        out.append(bool(ts is not None and ts.detected))
    return out


def analyse_pattern(pattern: Pattern, image_size: tuple[int, int],
                    params: SceneParams = SceneParams()) -> Pattern:
    """A copy of ``pattern`` with its VP, translation symmetry and rows set.

    Parameters
    ----------
    pattern : Pattern
        Instances (original pixels) and optional ``feature_points`` (M, N', 2).
    image_size : (int, int)
        ``(width, height)``, original pixels.
    params : SceneParams
    """
    p = copy.deepcopy(pattern)
    b = _boxes(p)
    fp = p.feature_points
    if fp is not None:
        fp = np.asarray(fp, float)
        if fp.ndim != 3 or fp.shape[2] != 2 or fp.shape[1] > len(b):
            raise ValueError(f"pattern {p.id}: feature_points must have shape (M, N, 2) "
                             f"with N <= {len(b)} instances, got {fp.shape}")
    vp, rows = rp_vanishing_point(b, fp, image_size, params.vp,
                                    partial(equal_rows, symmetry_params=params.symmetry,
                                            params=params.vp))
    centres, _, _ = L.pattern_rows(b, fp, params.vp) if len(b) else (np.zeros((0, 2)),
                                                                      None, None)
    rows = _orient_rows(rows, centres, vp)
    p.vanishing_point = vp
    p.translation_symmetry = (S.translation_symmetry(fp, centres, rows, params.symmetry)
                              if rows else None)
    p.extra["rows"] = [[int(i) for i in r] for r in rows]
    return p


def analyse_scene(result: ImageResult, params: SceneParams = SceneParams()) -> ImageResult:
    """VPs, translation symmetry, dominant pattern and image VP of one image.

    Parameters
    ----------
    result : ImageResult
        Output of stage I or II (original pixels).
    params : SceneParams

    Returns
    -------
    ImageResult
        A copy with the scene fields set (see the module docstring); ``result`` is not
        modified.
    """
    if not isinstance(result, ImageResult):
        raise TypeError(f"result must be an ImageResult, got {type(result).__name__}")
    if result.width <= 0 or result.height <= 0:
        raise ValueError(f"result.width and result.height must be > 0, got "
                         f"{result.width} x {result.height}")
    res = copy.copy(result)
    size = (int(result.width), int(result.height))
    res.patterns = [analyse_pattern(p, size, params) for p in result.patterns]
    res.extra = copy.deepcopy(result.extra)
    dom = CNT.dominant_pattern(res.patterns)
    res.dominant_pattern = None if dom is None else int(res.patterns[dom].id)
    res.vanishing_point = _image_rp_vp(result, res.patterns, [], dom, size, params)
    res.extra.pop("reported_rp_vanishing_point", None)
    hidden = _analysed_hidden(result, size, params)
    if hidden:
        vp = res.vanishing_point
        res.extra["reported_rp_vanishing_point"] = None if vp is None else vp.to_json()
        res.vanishing_point = _image_rp_vp(result, res.patterns, hidden, dom, size, params)
    return res


def image_rp_vp(result: ImageResult, params: SceneParams = SceneParams(),
                votes: Callable[[Pattern, Lines], np.ndarray] | None = None,
                ) -> VanishingPoint | None:
    """The RP-based image VP of a result whose patterns are already analysed (a scene
    step's result; :func:`analyse_pattern`), as :func:`analyse_scene` finds it: from its
    patterns and, with ``params.vp.hidden_rows``, the stage-I RPs the confidence hid
    (:func:`hidden_patterns`), else the RPs set aside as one structure. ``votes``: as in
    :func:`rp_image_vp` (a study of the weighting). None where they give no VP."""
    size = (int(result.width), int(result.height))
    return _image_rp_vp(result, list(result.patterns), _analysed_hidden(result, size, params),
                        CNT.dominant_pattern(result.patterns), size, params, votes)


def _analysed_hidden(result: ImageResult, size: tuple[int, int],
                     params: SceneParams) -> list[Pattern]:
    """The stage-I RPs the confidence hid (:func:`hidden_patterns`), analysed, where the
    image VP reads them (``vp.hidden_rows`` with ``vp.joint_alpha`` > 0); else none. Their
    rows point to VPs too; they are never reported."""
    if not (params.vp.hidden_rows and params.vp.joint_alpha > 0):
        return []
    return [analyse_pattern(p, size, params) for p in hidden_patterns(result)]


def _image_rp_vp(result: ImageResult, patterns: list[Pattern], hidden: list[Pattern],
                 dom: int | None, size: tuple[int, int], params: SceneParams,
                 votes: Callable[[Pattern, Lines], np.ndarray] | None = None,
                 ) -> VanishingPoint | None:
    """The RP-based image VP (see the module docstring) of the analysed reported
    ``patterns`` (``dom`` the dominant one's index, None without any) and the analysed
    ``hidden`` stage-I RPs; ``result`` gives the RPs set aside as one structure."""
    if params.vp.joint_alpha > 0:
        if dom is None and not hidden:
            return None
        # the dominant pattern, or without a reported one the hidden one with most instances
        first = dom if dom is not None else len(patterns) + CNT.dominant_pattern(hidden)
        vp = rp_image_vp(patterns + hidden, first, size, params, votes)
        aside = structure_patterns(result) if vp is None else []
        if aside:
            # the rows of RPs set aside as one structure (a ledge, a kerb sampled
            # along its length) point to a VP too: read when the others' do not
            lined = patterns + hidden + [analyse_pattern(p, size, params) for p in aside]
            vp = rp_image_vp(lined, first, size, params, votes)
        return vp
    if dom is None:
        return None
    if patterns[dom].vanishing_point is not None:
        return copy.deepcopy(patterns[dom].vanishing_point)
    cands = [(p.vanishing_point.support, p.count, float(p.score), -i)
             for i, p in enumerate(patterns) if p.vanishing_point is not None]
    if cands:
        return copy.deepcopy(patterns[-max(cands)[3]].vanishing_point)
    return None


def pattern_implicit_lines(p: Pattern, params: SceneParams, spacing: bool = True) -> Lines:
    """Implicit lines (with their points, original pixels) of an analysed pattern: one per
    visual word and row of ``p.extra["rows"]`` (:func:`rescu.scene.vp.lines.pattern_lines`).

    With ``spacing`` the rows that pass the translation-symmetry test give their lines the
    instance ordinals (``Lines.positions``, for the spacing model); False skips those
    tests (``positions`` None) for a caller that uses directions and points only."""
    b = _boxes(p)
    c, sz = L.instance_centres_sizes(b)
    if params.vp.register_centres and len(c) >= 2:
        c = L.registered_centres(c, None if p.feature_points is None
                                 else np.asarray(p.feature_points, float))
    rows = [np.asarray(r, int) for r in p.extra.get("rows", [])]
    fp = None if p.feature_points is None else np.asarray(p.feature_points, float)
    equal = equal_rows(fp, c, rows, params.symmetry, params.vp) if spacing else None
    return pattern_lines(fp, c, rows, sz, params.vp.max_line_residual,
                           params.vp.precision_floor_px, equal)


def _candidates(result: ImageResult, dropped: str, stage_one: bool) -> list[Pattern]:
    """The RPs of ``extra["candidate_patterns"]`` dropped for ``dropped`` (with
    ``stage_one``: not the dense source's), as patterns; unreadable entries skipped."""
    out = []
    for d in result.extra.get("candidate_patterns") or []:
        if not isinstance(d, dict) or d.get("dropped") != dropped:
            continue
        if stage_one and d.get("source") == "dense":
            continue
        try:
            out.append(Pattern.from_json(d))
        except (KeyError, TypeError, ValueError):
            continue
    return out


def hidden_patterns(result: ImageResult) -> list[Pattern]:
    """The stage-I RPs that the confidence hid (``extra["candidate_patterns"]`` with
    ``dropped`` ``"low confidence"`` and a ``source`` other than ``"dense"``), as patterns
    in original pixels; entries that cannot be read are skipped. Keypoint patterns the
    URP search verified but too small or thin for the feature map to vouch for them as
    objects (:func:`rescu.extension.objects.rp_confidence`): not reported, but their rows
    still lie along lines toward a VP (``scene.vp.hidden_rows``).

    >>> r = ImageResult(image="x", width=10, height=10, method="rescu-ii", extra={
    ...     "candidate_patterns": [
    ...         {"id": 0, "score": 1.0, "dropped": "low confidence",
    ...          "instances": [{"bbox": [0, 0, 2, 2]}]},
    ...         {"id": 1, "score": 1.0, "dropped": "low confidence", "source": "dense",
    ...          "instances": [{"bbox": [0, 0, 2, 2]}, {"bbox": [4, 0, 2, 2]}]},
    ...         {"id": 2, "score": 1.0, "dropped": "same objects",
    ...          "instances": [{"bbox": [0, 0, 2, 2]}] * 3}]})
    >>> [p.count for p in hidden_patterns(r)]
    [1]
    """
    return _candidates(result, "low confidence", stage_one=True)


def structure_patterns(result: ImageResult) -> list[Pattern]:
    """The RPs that RESCU-I set aside as samples of one structure
    (``extra["candidate_patterns"]`` with ``dropped`` ``"one structure"``,
    :func:`rescu.discovery.sources.split_by_confidence`), as patterns in original pixels;
    entries that cannot be read are skipped. Not reported as RPs, their rows still lie
    along lines toward a VP.

    >>> r = ImageResult(image="x", width=10, height=10, method="rescu-i", extra={
    ...     "candidate_patterns": [{"id": 0, "score": 1.0, "dropped": "one structure",
    ...                             "instances": [{"bbox": [0, 0, 2, 2]}]},
    ...                            {"id": 1, "score": 1.0, "dropped": "low confidence",
    ...                             "instances": [{"bbox": [0, 0, 2, 2]}]}]})
    >>> [p.count for p in structure_patterns(r)]
    [1]
    """
    return _candidates(result, "one structure", stage_one=False)


def rp_image_vp(patterns: list[Pattern], dom: int, size: tuple[int, int],
                params: SceneParams,
                votes: Callable[[Pattern, Lines], np.ndarray] | None = None,
                ) -> VanishingPoint | None:
    """The dominant VP: the VP shared by the most RP instances.

    With ``params.vp.union_rows``, the VP of all patterns' rows together when every
    pattern with a VP accepts it (:func:`union_vanishing_point`). Otherwise every
    pattern with a VP seeds a group: its VP re-estimated with the other patterns that
    share it (:func:`rescu.scene.vp.estimator.joint_vanishing_point`, the others tried in
    order of decreasing VP support, i.e. number of inlier implicit lines, then count). The
    group with the most instances in total gives the image VP; ties go to the group seeded
    by the more dominant pattern (the dominant pattern first, then by count, score, order).
    Without any sharing this is the dominant pattern's own VP whenever it has one; a large
    spurious RP no longer outvotes several smaller RPs along one 3D direction.

    Parameters
    ----------
    patterns : list of Pattern
        Analysed patterns (:func:`analyse_pattern`: ``vanishing_point`` and
        ``extra["rows"]`` set), original pixels.
    dom : int
        Index of the dominant pattern in ``patterns``.
    size : (int, int)
        ``(width, height)`` of the image, original pixels.
    params : SceneParams
    votes : callable or None
        ``votes(pattern, its implicit lines)`` -> (L,) vote of each line in the union
        (a study of the weighting); None: each line's track length.

    Returns
    -------
    VanishingPoint or None
        Unit-norm homogeneous VP in original pixels; None when neither the union of the
        rows nor any pattern gives one.
    """
    have = [i for i in range(len(patterns)) if patterns[i].vanishing_point is not None]
    rowed = [i for i in range(len(patterns)) if patterns[i].extra.get("rows")]
    # each pattern's implicit lines once, for the union and the groups alike
    lines = {i: pattern_implicit_lines(patterns[i], params)
             for i in (rowed if params.vp.union_rows else []) + have}
    if params.vp.union_rows and rowed:
        vp, _ = union_vanishing_point(
            [lines[i] for i in rowed], [patterns[i].vanishing_point for i in rowed], size,
            params.vp, None if votes is None else [votes(patterns[i], lines[i]) for i in rowed])
        if vp is not None:
            return vp
    if not have:
        return None
    seeds = sorted(have, key=lambda i: (i != dom, -patterns[i].count,
                                        -float(patterns[i].score), i))
    best: tuple[int, VanishingPoint | None] | None = None
    for s in seeds:
        order = [s] + sorted((i for i in have if i != s),
                             key=lambda i: (-patterns[i].vanishing_point.support,
                                            -patterns[i].count, i))
        vp, used = joint_vanishing_point([lines[i] for i in order],
                                           [patterns[i].vanishing_point for i in order],
                                           size, params.vp)
        total = sum(patterns[order[u]].count for u in used)
        if best is None or total > best[0]:
            best = (total, vp)
    assert best is not None
    return copy.deepcopy(best[1])


def processed_image(rgb: np.ndarray, scale_factor: float) -> np.ndarray:
    """``rgb`` as an array after checking it is a processed (H, W, 3) image with a
    positive ``scale_factor`` (processed = original * scale_factor); ValueError if not."""
    img = np.asarray(rgb)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"rgb must have shape (H, W, 3), got {img.shape}")
    if scale_factor <= 0:
        raise ValueError(f"scale_factor must be > 0, got {scale_factor}")
    return img


def rectify_pattern(rgb: np.ndarray, scale_factor: float, pattern: Pattern,
                    params: SceneParams = SceneParams()) -> np.ndarray | None:
    """Rectified view of a pattern's region: its VP sent to infinity.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        The processed image (original * ``scale_factor``).
    scale_factor : float
        processed = original * scale_factor (the pattern is in original pixels).
    pattern : Pattern
        With instances and (optionally) ``vanishing_point``.
    params : SceneParams

    Returns
    -------
    (h, w, 3) uint8 or None
        The warped region (bounding box of the union of the instance boxes, padded by
        ``rectify_padding``, clipped to the image), scaled so that its larger side is at
        most ``rectify_max_side``. Without a VP or with a VP at infinity this is the plain
        crop. None when the pattern has no instance or the rectification is ill-posed
        (the VP inside or too close to the region).
    """
    import cv2

    img = processed_image(rgb, scale_factor)
    hh, ww = img.shape[:2]
    b = _boxes(pattern) * scale_factor
    if len(b) == 0:
        return None
    x0, y0 = b[:, 0].min(), b[:, 1].min()
    x1, y1 = (b[:, 0] + b[:, 2]).max(), (b[:, 1] + b[:, 3]).max()
    pad = params.rectify_padding * max(x1 - x0, y1 - y0)
    x0, y0 = max(0.0, x0 - pad), max(0.0, y0 - pad)
    x1, y1 = min(float(ww), x1 + pad), min(float(hh), y1 + pad)
    if x1 - x0 < 1 or y1 - y0 < 1:
        return None
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    h = np.eye(3)
    vp = pattern.vanishing_point
    if vp is not None:
        v = np.diag([scale_factor, scale_factor, 1.0]) @ np.asarray(vp.homogeneous, float)
        v = v / np.linalg.norm(v)
        if abs(v[2]) > INFINITY_EPS:
            try:
                h = S.vp_rectifying_homography(v, corners.mean(axis=0))
            except ValueError:
                return None
    wc = np.c_[corners, np.ones(4)] @ h.T
    if np.any(wc[:, 2] < params.rectify_min_w):
        return None
    wc = wc[:, :2] / wc[:, 2:]
    lo, hi = wc.min(axis=0), wc.max(axis=0)
    ext = np.maximum(hi - lo, 1e-9)
    s = min(1.0, params.rectify_max_side / float(ext.max()))
    out_w = max(1, min(params.rectify_max_side, int(np.ceil(ext[0] * s))))
    out_h = max(1, min(params.rectify_max_side, int(np.ceil(ext[1] * s))))
    a = np.array([[s, 0, -s * lo[0]], [0, s, -s * lo[1]], [0, 0, 1.0]])
    m = a @ h
    return cv2.warpPerspective(np.ascontiguousarray(img, dtype=np.uint8), m, (out_w, out_h),
                               flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                               borderValue=(0, 0, 0))
