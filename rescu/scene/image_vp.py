"""The image's vanishing points from every cue: RP rows and explicit lines together.

:func:`image_vanishing_points` is the joint step after the scene step: the implicit lines
of every RP row (:func:`rescu.scene.analyse.pattern_implicit_lines`, feature tracks along
a row) and the LSD segments of the image (:func:`rescu.scene.vp.lsd.lsd_segments`) vote
in one estimator (:func:`rescu.scene.vp.manhattan.manhattan_vps`) for up to three
mutually orthogonal VPs and the focal length; the RP-based VPs of the scene step (the
image's from the reported RPs and each pattern's) enter as point hypotheses. The
result's image-level ``vanishing_point`` becomes that estimator's dominant VP; the
RP-only VP of the scene step is kept as ``rp_vanishing_point``, and the new fields are

* ``vanishing_points``: a list (dominant first) of ``{"homogeneous", "inside_image",
  "support", "direction" (unit 3D, camera frame: x right, y down, z forward),
  "weight", "cues": {"lines": n, "rp_rows": n}}``;
* ``focal_px``: the focal length (original pixels) the directions are in, and
  ``focal_estimated``: whether it was estimated (principal point at the image centre);
* ``vp_lines``: ``{"lines": n, "rp_rows": n, "weight": w, "inlier_angle_deg": a}``, the
  lines every VP was drawn from, their total weight (on the scale of each VP's
  ``weight``) and the angle within which a line supports a VP (``refine_angle_deg``),
  which the claim tests weigh a VP's support against (:mod:`rescu.scene.claims`).

Documented empty result: with fewer than three lines in all (a blank image, no pattern),
``vanishing_points`` is ``[]``, ``focal_px`` is null and ``vanishing_point`` stays the
RP-only one (which may be null).
"""

from __future__ import annotations

import copy

import numpy as np

from ..types import ImageResult, VanishingPoint
from .analyse import SceneParams, pattern_implicit_lines, processed_image
from .vp.geometry import _canonical, inside_image
from .vp.lines import Lines
from .vp.lsd import lsd_segments
from .vp.manhattan import ImageVPParams, ManhattanResult, manhattan_vps


def rp_row_lines(result: ImageResult, params: SceneParams = SceneParams()) -> Lines:
    """The implicit lines of all patterns' rows, original pixels, weighted by their span.

    Each line's weight is the extent (pixels) of its points along it: an implicit line
    through features 300 pixels apart weighs as much as a 300-pixel segment.
    """
    parts = []
    for p in result.patterns:
        if not p.extra.get("rows"):
            continue
        lines = pattern_implicit_lines(p, params, spacing=False)
        if not len(lines):
            continue
        if lines.points is not None:
            span = np.array([float(np.ptp(q @ d)) if len(q) >= 2 else 0.0
                             for q, d in zip(lines.points, lines.directions)])
        else:
            span = np.asarray(lines.weights, float)
        parts.append(Lines(lines.midpoints, lines.directions, span, points=lines.points))
    return Lines.concat(parts) if parts else Lines.empty()


def _reported_rp_vp(result: ImageResult) -> VanishingPoint | None:
    """The scene step's RP-based image VP of the reported RPs: its
    ``extra["reported_rp_vanishing_point"]`` where it also read the rows of hidden
    stage-I RPs (``scene.vp.hidden_rows``), else its ``vanishing_point``. The rows of RPs
    too small or thin for the map are less precise than the lines; they do not propose
    VPs to the joint estimator."""
    if "reported_rp_vanishing_point" not in result.extra:
        return result.vanishing_point
    v = result.extra["reported_rp_vanishing_point"]
    return None if v is None else VanishingPoint.from_json(v)


def _to_original(v: np.ndarray, scale_factor: float) -> np.ndarray:
    return _canonical(np.diag([1.0, 1.0, scale_factor]) @ np.asarray(v, float))


def image_vanishing_points(rgb: np.ndarray, scale_factor: float, result: ImageResult,
                           scene_params: SceneParams = SceneParams(),
                           params: ImageVPParams = ImageVPParams(),
                           focal_px: float | None = None) -> ImageResult:
    """A copy of the scene result with the image's VPs from RP rows and LSD lines.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        The processed image (original * ``scale_factor``).
    scale_factor : float
        processed = original * scale_factor.
    result : ImageResult
        The scene step's result (patterns with ``rows``), original pixels.
    scene_params : SceneParams
        Row lines (``vp.max_line_residual`` ...) and the LSD settings (``vp.lsd_*``).
    params : ImageVPParams
    focal_px : float or None
        The true focal length in original pixels; None: ``params.focal_px``, and when
        that is null too, estimated.

    Returns
    -------
    ImageResult
        See the module docstring; ``result`` is not modified.
    """
    img = processed_image(rgb, scale_factor)
    h, w = img.shape[:2]
    vpp = scene_params.vp
    segs = lsd_segments(img, vpp.lsd_min_length * float(np.hypot(w, h)), vpp.lsd_max_segments)
    rp = rp_row_lines(result, scene_params)
    rp_proc = Lines(rp.midpoints * scale_factor, rp.directions, rp.weights * scale_factor,
                    points=None if rp.points is None else [q * scale_factor for q in rp.points])
    cues = [("lines", Lines.from_segments(segs), params.line_weight),
            ("rp_rows", rp_proc, params.rp_weight)]
    focal = focal_px if focal_px is not None else params.focal_px
    to_proc = np.diag([scale_factor, scale_factor, 1.0])
    points = [to_proc @ np.asarray(v.homogeneous, float)
              for v in [_reported_rp_vp(result)] + [p.vanishing_point for p in result.patterns]
              if v is not None]
    mh = manhattan_vps(cues, (w, h), params,
                       focal_px=None if focal is None else float(focal) * scale_factor,
                       point_hypotheses=points)
    out = _with_vps(result, mh, scale_factor)
    # what the VPs were drawn from, for the claim tests (rescu.scene.claims): the lines
    # of each cue and their total weight, on the scale of each VP's ``weight``
    total = sum(float(np.sum(ln.weights)) * cw for _, ln, cw in cues if cw > 0)
    out.extra["vp_lines"] = {"lines": int(len(cues[0][1])), "rp_rows": int(len(rp_proc)),
                             "weight": round(total / scale_factor, 3),
                             "inlier_angle_deg": float(params.refine_angle_deg)}
    return out


def _with_vps(result: ImageResult, mh: ManhattanResult | None,
              scale_factor: float) -> ImageResult:
    res = copy.copy(result)
    res.extra = copy.deepcopy(result.extra)
    res.vanishing_point = copy.deepcopy(result.vanishing_point)
    res.extra["rp_vanishing_point"] = (result.vanishing_point.to_json()
                                       if result.vanishing_point is not None else None)
    size = (int(result.width), int(result.height))
    listed = []
    for m in (mh.vps if mh is not None else []):
        v = _to_original(m.vanishing_point.homogeneous, scale_factor)
        m = copy.copy(m)
        m.vanishing_point = VanishingPoint(v, inside_image(v, size), m.vanishing_point.support)
        m.weight = m.weight / scale_factor
        listed.append(m)
    res.extra["vanishing_points"] = [m.to_json() for m in listed]
    res.extra["focal_px"] = (round(mh.focal_px / scale_factor, 6)
                             if mh is not None and listed else None)
    res.extra["focal_estimated"] = bool(mh.focal_estimated) if mh is not None else None
    if listed:
        res.vanishing_point = copy.deepcopy(listed[0].vanishing_point)
    return res
