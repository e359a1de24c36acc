"""A second source of RPs: recurring blobs in a frozen CNN's dense feature map.

Stage I finds recurrence among SIFT keypoints; small or smooth objects (cars seen from
above, chess pieces) carry too few keypoints for it. This source works on the frozen
ImageNet backbone of stage II instead, once per image:

1. **Feature map** (:func:`hypercolumn`), on the prepared image scaled to a longer side
   within [``min_side``, ``max_side``]: the backbone's stride-8 and stride-16 maps,
   each L2-normalised per location, the coarse one upsampled, concatenated: one
   ``(C, h, w)`` map, a cell = 8 pixels of the backbone input.
2. **Blobs** (:func:`feature_blobs`): centre-surround contrast in feature space at
   several square sizes (the feature-space analogue of a difference-of-Gaussians blob
   detector): the mean feature of an ``a x a`` window against the mean of the ring
   around it (``surround * a`` wide); local maxima over position and size, strongest
   first. An object differs from its surroundings; plain background does not.
3. **RPs** (:func:`dense_patterns`): the blobs' mean features, grouped by
   average-linkage clustering on cosine similarity; a group of ``min_instances`` or more
   non-overlapping blobs is one RP, its instances the blobs' square boxes. RPs are
   ranked by the mean centre-surround contrast of their boxes
   (:func:`rescu.extension.boxmaps.box_contrast`)
   times their rarity (1 - cosine of their mean feature with the image's mean feature:
   background is what the image mostly is) times their objectness (the backbone's
   ImageNet classifier's mean top-class probability on crops of their instances,
   :func:`objectness`: objects are what its classes name, stuff is not). A group
   whose boxes abut one another on more than ``max_touching`` sides on average
   (:func:`touching_sides`) tiles the plane (board squares, floor tiles) and is
   dropped; the first ``max_patterns`` of the rest are kept.
4. **With stage I** (:func:`rescu.discovery.sources.combine_sources`): ``mode="both"``
   keeps stage I's RPs and adds the dense RPs' instances that do not overlap them;
   ``"dense"`` keeps the dense RPs only.

Dense RPs have no feature correspondences (``feature_points`` is None): stage II,
counting and captions use them as they are; the vanishing point and translation
symmetry steps use their instance centres where they need points. Instances carry
``source="stage1"`` (found before stage II) and the pattern ``extra["source"] =
"dense"``.

Measured on every image of ``../shared/data`` in ``docs/results.md`` (section "Whole
objects"); on by default (config ``dense.enabled``), in mode ``objects`` with the whole
objects of :mod:`rescu.extension.objects`.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, replace
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from ..discovery.sources import DenseParams, is_whole_object
from ..boxes import cover_matrix, touching_sides
from ..types import ImageResult, Instance, Pattern
from .boxmaps import integral_map, map_score, maximum_filter, read_only, unit_mean
from .linkage import average_linkage_labels
from .contrast_extent import colour_integrals, rect_sums
from .turned import complete_turned, hypercolumn, level_image, turned_map

__all__ = ["DenseParams", "DenseCandidate", "hypercolumn", "box_means", "feature_blobs",
           "blob_boxes", "distinct_blobs", "integral_map", "touching_sides",
           "central_colours", "split_by_colour", "colour_for",
           "dense_candidates", "objectness", "rank_candidates", "dense_patterns",
           "objectness_for", "dense_map", "save_map", "load_map", "dense_levels",
           "level_sizes", "level_candidates", "iter_level_candidates", "find_dense",
           "score_and_split"]


# --------------------------------------------------------------------- feature map
def box_means(f: np.ndarray, side: int) -> np.ndarray:
    """Mean of ``f`` (C, h, w) over the ``side x side`` window centred at each cell
    (reflected at the border) -> (C, h, w) float32."""
    import cv2

    out = np.empty_like(f)
    for c in range(f.shape[0]):
        out[c] = cv2.boxFilter(f[c], -1, (side, side), normalize=True,
                               borderType=cv2.BORDER_REFLECT)
    return out


def feature_blobs(f: np.ndarray, sizes: Sequence[int], surround: int, max_blobs: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre-surround blobs of a feature map, strongest first.

    The response at a cell and size ``a`` is ``(1 - cos(m_c, m_r)) * |m_c|`` with ``m_c``
    the mean feature of the ``a x a`` window and ``m_r`` that of the ring out to
    ``surround * a``; ``|m_c|`` (<= 1) rewards windows whose features agree. Blobs are
    the maxima of their 3 x 3 x 3 neighbourhood over (size, y, x) whose window lies
    inside the map (a window cut by the border is compared with reflected features).

    Parameters
    ----------
    f : (C, h, w) float32, unit-norm per cell (:func:`hypercolumn`)
    sizes : blob sides, cells
    surround : ring side / blob side
    max_blobs : how many to return at most

    Returns
    -------
    cells : (n, 3) int, ``[size index, y, x]`` of each blob
    response : (n,) float, descending
    emb : (n, C) float32, the unit mean feature of each blob's window
    """
    resp, means, where = [], [], []
    for a in sizes:
        mc = box_means(f, int(a))
        ms = box_means(f, int(a) * surround)
        inner, outer = float(a * a), float((a * surround) ** 2)
        mr = (ms * outer - mc * inner) / (outer - inner)
        del ms
        nc = np.linalg.norm(mc, axis=0) + 1e-9
        nr = np.linalg.norm(mr, axis=0) + 1e-9
        rs = (1.0 - (mc * mr).sum(0) / (nc * nr)) * nc
        del mr
        resp.append(rs)
        # the unit means are kept only where this size's response peaks in its own plane
        # (every peak over (size, y, x) is one), not as C x h x w floats per size (about
        # 0.1 GB of the dense step's peak on a fine map)
        y, x = np.nonzero((rs == maximum_filter(rs, 3)) & (rs > 0))
        at = np.full(rs.shape, -1, np.int64)
        at[y, x] = np.arange(len(y))
        means.append(mc[:, y, x] / nc[y, x])
        where.append(at)
        del mc
    r = np.stack(resp)
    peaks = np.argwhere((r == maximum_filter(r, 3)) & (r > 0))
    # a window that leaves the map is measured against reflected features: its contrast
    # is an artefact of the border, not an object (such blobs recur along every edge)
    a = np.asarray(sizes, float)[peaks[:, 0]] / 2.0
    inside = ((peaks[:, 1] + 0.5 - a >= 0) & (peaks[:, 1] + 0.5 + a <= f.shape[1])
              & (peaks[:, 2] + 0.5 - a >= 0) & (peaks[:, 2] + 0.5 + a <= f.shape[2]))
    peaks = peaks[inside]
    val = r[tuple(peaks.T)]
    order = np.lexsort((peaks[:, 2], peaks[:, 1], peaks[:, 0], -val))[:max_blobs]
    peaks, val = peaks[order], val[order]
    emb = np.array([means[s][:, where[s][y, x]] for s, y, x in peaks], np.float32).reshape(
        len(peaks), f.shape[0])
    return peaks.astype(int), val.astype(float), emb


def blob_boxes(cells: np.ndarray, sizes: Sequence[int], cell_px: float) -> np.ndarray:
    """Square boxes ``[x, y, w, h]`` (pixels of the backbone input) of blobs
    ``[size index, y, x]`` (:func:`feature_blobs`) -> (n, 4) float."""
    a = np.array([sizes[s] for s in cells[:, 0]], float) if len(cells) else np.zeros(0)
    return np.c_[(cells[:, 2] - a / 2 + 0.5) * cell_px, (cells[:, 1] - a / 2 + 0.5) * cell_px,
                 a * cell_px, a * cell_px] if len(cells) else np.zeros((0, 4))


# ------------------------------------------------------------------------------ RPs
@dataclass
class DenseCandidate:
    """One group of recurring blobs, before the selection of :func:`dense_patterns`.

    Attributes
    ----------
    boxes : (n, 4) float, ``[x, y, w, h]`` in backbone-input pixels, strongest blob first
    score : float, mean box contrast x rarity (1 - cosine of the group's mean feature
        with the image's mean feature; :func:`rescu.extension.boxmaps.map_score`)
    touching : float, mean :func:`touching_sides` of the boxes (0..4)
    emb : (n, C) float32 or None, the blobs' unit mean features (row i of box i)
    level : int, the map it was found on (index in :func:`dense_levels`; 0 the coarse
        one), whose pixels ``boxes`` are in
    """

    boxes: np.ndarray
    score: float
    touching: float
    emb: np.ndarray | None = None
    level: int = 0


def distinct_blobs(f: np.ndarray, cell_px: float, params: DenseParams,
                   sizes: Sequence[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The blobs the dense RPs are grouped from: :func:`feature_blobs`, strongest first,
    less each blob that overlaps a stronger one (cover > 0.5, any size: the same thing).

    Parameters
    ----------
    f : (C, h, w) float32 (:func:`hypercolumn`)
    cell_px : backbone-input pixels per cell (8)
    params : DenseParams (``sizes``, ``surround``, ``max_blobs``)
    sizes : blob sides, cells (None: ``params.sizes``)

    Returns
    -------
    boxes : (n, 4) float, ``[x, y, w, h]`` in backbone-input pixels
    emb : (n, C) float32, each blob's unit mean feature
    """
    sizes = params.sizes if sizes is None else tuple(sizes)
    cells, _, emb = feature_blobs(f, sizes, params.surround, params.max_blobs)
    boxes = blob_boxes(cells, sizes, cell_px)
    keep = np.ones(len(boxes), bool)
    ov = cover_matrix(boxes, boxes) if len(boxes) else np.zeros((0, 0))
    for i in range(len(boxes)):
        if keep[i]:
            keep[i + 1:] &= ov[i, i + 1:] <= 0.5
    return boxes[keep], emb[keep]


def central_colours(integrals: tuple[np.ndarray, np.ndarray], boxes: np.ndarray
                    ) -> np.ndarray:
    """Mean CIELAB colour of the central half of each box (half its width and height,
    same centre): the colour of the object rather than of what its box's corners hold.

    Parameters
    ----------
    integrals : :func:`rescu.extension.objects.colour_integrals` of the image (OpenCV's
        8-bit L, a, b)
    boxes : (n, 4) ``[x, y, w, h]``, pixels of that image

    Returns
    -------
    (n, 3) float64, L, a, b in [0, 255]

    >>> import numpy as np
    >>> from rescu.extension.contrast_extent import colour_integrals
    >>> rgb = np.zeros((20, 40, 3), np.uint8); rgb[:, 20:] = 255
    >>> central_colours(colour_integrals(rgb), np.array([[0, 0, 20, 20], [20, 0, 20, 20]]))[:, 0]
    array([  0., 255.])
    """
    ii = integrals[0]
    H, W = ii.shape[0] - 1, ii.shape[1] - 1
    b = np.asarray(boxes, float).reshape(-1, 4)
    cx, cy = b[:, 0] + b[:, 2] / 2, b[:, 1] + b[:, 3] / 2
    x0 = np.clip(np.round(cx - b[:, 2] / 4), 0, W - 1).astype(int)
    y0 = np.clip(np.round(cy - b[:, 3] / 4), 0, H - 1).astype(int)
    x1 = np.clip(np.round(cx + b[:, 2] / 4), x0 + 1, W).astype(int)
    y1 = np.clip(np.round(cy + b[:, 3] / 4), y0 + 1, H).astype(int)
    return rect_sums(ii, x0, y0, x1, y1) / ((x1 - x0) * (y1 - y0)).astype(float)[:, None]


def split_by_colour(labels: np.ndarray, colours: np.ndarray, max_distance: float,
                    min_instances: int) -> np.ndarray:
    """Groups of alike features split where their colours differ.

    Each group of ``labels`` with at least ``min_instances`` members is clustered again
    by average linkage on the Euclidean distance of its members' ``colours``, cut at
    ``max_distance``: black and white squares of a board, dark and light cars, which an
    ImageNet backbone's features see alike, become groups of their own. Smaller groups
    are left as they are (they are not RPs either way).

    Parameters
    ----------
    labels : (n,) int, group of each blob
    colours : (n, 3) float, each blob's colour (:func:`central_colours`)
    max_distance : float > 0, in the colours' units
    min_instances : int

    Returns
    -------
    (n,) int, new labels (the same partition when no group is split)

    >>> import numpy as np
    >>> split_by_colour(np.array([1, 1, 1, 1, 2]), np.array([[0, 0, 0], [5, 0, 0],
    ...     [250, 0, 0], [245, 0, 0], [0, 0, 0]], float), 60.0, 2).tolist()
    [1, 1, 3, 3, 2]
    """
    labels = np.asarray(labels).copy()
    colours = np.asarray(colours, np.float64).reshape(len(labels), -1)
    nxt = int(labels.max()) + 1 if len(labels) else 0
    for lab in np.unique(labels):
        m = np.flatnonzero(labels == lab)
        if len(m) < max(min_instances, 2):
            continue
        sub = average_linkage_labels(colours[m], max_distance, "euclidean")
        for k in np.unique(sub)[1:]:            # the first sub-group keeps the label
            labels[m[sub == k]] = nxt
            nxt += 1
    return labels


def dense_candidates(f: np.ndarray, cell_px: float, params: DenseParams,
                     sizes: Sequence[int] | None = None, level: int = 0,
                     colour_of: Callable[[np.ndarray], np.ndarray] | None = None
                     ) -> list[DenseCandidate]:
    """Every group of ``params.min_instances`` or more recurring blobs of one feature map
    (step 3 of the module docstring before the selection), best score first.

    Parameters
    ----------
    f : (C, h, w) float32 (:func:`hypercolumn`)
    cell_px : backbone-input pixels per cell (8)
    params : DenseParams (``sizes``, ``surround``, ``max_blobs``, ``min_similarity``,
        ``max_colour_distance``, ``min_instances``, ``touch_tolerance``)
    sizes : blob sides, cells (None: ``params.sizes``)
    level : the map's index in :func:`dense_levels`, given to each candidate
    colour_of : callable or None
        Boxes (n, 4) in backbone-input pixels -> (n, 3) colours (:func:`central_colours`);
        with ``params.max_colour_distance > 0`` each group of alike features is split by
        colour (:func:`split_by_colour`). None: not split.

    Returns
    -------
    list of :class:`DenseCandidate`, by descending score (ties: top-left first)
    """
    boxes, emb = distinct_blobs(f, cell_px, params, sizes)
    if len(boxes) < params.min_instances:
        return []
    # average-linkage clustering on cosine distance, cut at 1 - min_similarity (the
    # partition of scipy's linkage and fcluster, or scikit-learn's AgglomerativeClustering,
    # without their imports: rescu.extension.linkage)
    labels = average_linkage_labels(emb, 1.0 - params.min_similarity, "cosine")
    if colour_of is not None and params.max_colour_distance > 0:
        labels = split_by_colour(labels, colour_of(boxes), params.max_colour_distance,
                                 params.min_instances)
    ii = integral_map(f)
    g = unit_mean(f)
    out = []
    for lab in np.unique(labels):
        m = np.flatnonzero(labels == lab)
        if len(m) < params.min_instances:
            continue
        out.append(DenseCandidate(
            boxes=boxes[m], score=map_score(f, cell_px, boxes[m], emb[m], ii, g),
            touching=float(touching_sides(boxes[m], params.touch_tolerance).mean()),
            emb=emb[m], level=level))
    out.sort(key=lambda c: (-c.score, c.boxes[0, 1], c.boxes[0, 0]))
    return out


def objectness(backbone: Any, rgb: np.ndarray, boxes: np.ndarray, params: DenseParams
               ) -> float:
    """How much the instances of one RP look like objects to the backbone's ImageNet
    classifier: its mean top-class probability on square crops around the first
    ``params.objectness_crops`` boxes (side ``params.objectness_context`` x the box's
    longer side, cut at the image border, resized to ``params.objectness_px``).

    Objects that recur (cars, windows, chess pieces) are what ImageNet's classes name;
    stuff (wall, asphalt, grass, board squares) spreads the probability over many
    classes. No training: the classifier is the frozen backbone's own.

    Parameters
    ----------
    backbone : rescu.extension.backbone.FrozenBackbone
    rgb : (H, W, 3) uint8
    boxes : (n, 4) float, ``[x, y, w, h]`` in pixels of ``rgb``, strongest first
    params : DenseParams (``objectness_crops``, ``objectness_px``, ``objectness_context``)

    Returns
    -------
    float in (0, 1]; 1.0 when ``params.objectness_crops`` is 0 or there is no box
    """
    import cv2

    b = np.asarray(boxes, float).reshape(-1, 4)[:params.objectness_crops]
    if not len(b):
        return 1.0
    h, w = rgb.shape[:2]
    side = params.objectness_px
    crops = []
    for x, y, bw, bh in b:
        cx, cy, r = x + bw / 2, y + bh / 2, max(bw, bh) * params.objectness_context / 2
        x0, y0 = int(np.clip(cx - r, 0, w - 1)), int(np.clip(cy - r, 0, h - 1))
        x1 = int(np.clip(np.ceil(cx + r), x0 + 1, w))
        y1 = int(np.clip(np.ceil(cy + r), y0 + 1, h))
        crops.append(cv2.resize(rgb[y0:y1, x0:x1], (side, side),
                                interpolation=cv2.INTER_AREA if y1 - y0 > side
                                else cv2.INTER_LINEAR))
    return float(backbone.class_probabilities(np.stack(crops)).max(1).mean())


def rank_candidates(cands: Sequence[DenseCandidate],
                    objectness_of: Callable[[np.ndarray], float] | None,
                    top: int | None = None) -> list[DenseCandidate]:
    """``cands`` with each score multiplied by ``objectness_of(boxes)`` (None: as they
    are), best score first (ties: top-left first); with ``top``, only the first ``top``.

    Objectness is at most 1, so with ``top`` a candidate whose score is already below the
    ``top``-th rescored one cannot enter: the others are not classified (the result is the
    same as ranking all and cutting)."""
    key = (lambda c: (-c.score, c.boxes[0, 1], c.boxes[0, 0]))
    out: list[DenseCandidate] = []
    for c in sorted(cands, key=key):
        if top is not None and len(out) >= top and \
                c.score < sorted(x.score for x in out)[-top]:
            break
        out.append(c if objectness_of is None else
                   replace(c, score=c.score * objectness_of(c.boxes)))
    out.sort(key=key)
    return out if top is None else out[:top]


def dense_patterns(f: np.ndarray, cell_px: float, params: DenseParams,
                   objectness_of: Callable[[np.ndarray], float] | None = None
                   ) -> list[tuple[float, np.ndarray]]:
    """RPs of recurring blobs in one feature map (steps 2-3 of the module docstring).

    Parameters
    ----------
    f : (C, h, w) float32 (:func:`hypercolumn`)
    cell_px : backbone-input pixels per cell (8)
    params : DenseParams
    objectness_of : callable or None
        Boxes (n, 4) in backbone-input pixels -> the RP's objectness (:func:`objectness`),
        a factor of its score; None: contrast x rarity alone.

    Returns
    -------
    list of ``(score, boxes)``, best first (score = mean box contrast x rarity [x
    objectness]), at most ``params.max_patterns``, none that tiles the plane (mean
    :func:`touching_sides` above ``params.max_touching``): boxes (n, 4) ``[x, y, w, h]``
    in backbone-input pixels, n >= ``params.min_instances``.
    """
    kept = rank_candidates([c for c in dense_candidates(f, cell_px, params)
                            if c.touching <= params.max_touching], objectness_of,
                           params.max_patterns)
    return [(c.score, c.boxes) for c in kept]


def objectness_for(rgb: np.ndarray, s: float, params: DenseParams, backbone: Any
                   ) -> Callable[[np.ndarray], float] | None:
    """The ``objectness_of`` of :func:`dense_patterns` for the map :func:`dense_map` made
    of ``rgb`` at scale ``s`` (None when ``params.objectness_crops`` is 0)."""
    if not params.objectness_crops:
        return None
    return lambda boxes: objectness(backbone, rgb, np.asarray(boxes, float) / s, params)


#: A wide map (``dense.wide_scales``) whose input's shorter side would be under this many
#: pixels (16 cells) is left out: its blobs' surrounds would be the whole map.
WIDE_MIN_PX = 128

_LAST_MAP: dict[tuple[Any, ...], tuple[np.ndarray, float]] = {}


def dense_map(rgb: np.ndarray, params: DenseParams, backbone: Any = None
              ) -> tuple[np.ndarray, float]:
    """The feature map the dense source works on, and the scale it was taken at.

    The last map made on CPU is kept (one entry, keyed by the image's bytes, the backbone
    and the sizes), so that the dense step and the scoring of stage I's RPs that follows
    it in the same process (:func:`rescu.core.run`) pass the backbone over the image
    once; the returned map is read-only.

    Parameters
    ----------
    rgb : (H, W, 3) uint8, the prepared image
    params : DenseParams (``backbone``, ``max_side``, ``min_side``, ``rotations``)
    backbone : FrozenBackbone or None (None: ``params.backbone`` at stride 16, CPU)

    Returns
    -------
    f : (C, h, w) float32 (:func:`hypercolumn`) of ``rgb`` resized by ``s``
    s : float, backbone-input pixels per prepared-image pixel (longer side brought into
        [``min_side``, ``max_side``])
    """
    from .backbone import shared_backbone

    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be an (H, W, 3) uint8 image, got shape {rgb.shape} "
                         f"dtype {rgb.dtype}")
    name = params.backbone if backbone is None else getattr(backbone, "name", None)
    cpu = backbone is None or str(getattr(backbone, "device", "")) == "cpu"
    key = (hashlib.sha1(np.ascontiguousarray(rgb).data).hexdigest(), rgb.shape, name,
           params.max_side, params.min_side, params.rotations)
    if cpu and key in _LAST_MAP:
        return _LAST_MAP[key]
    if backbone is None:
        backbone = shared_backbone(params.backbone, feature_stride=16)
    longer = max(rgb.shape[:2])
    s = min(1.0, params.max_side / longer) if longer >= params.min_side \
        else params.min_side / longer
    im = level_image(rgb, s)
    # half precision, as the dense step stores it for the scoring of stage I's RPs
    # (:func:`save_map`): the map in memory and the one read back are the same
    out = (hypercolumn(backbone, im, params.rotations).astype(np.float16).astype(np.float32),
           float(s))
    out[0].setflags(write=False)
    if cpu:
        _LAST_MAP.clear()
        _LAST_MAP[key] = out
    return out


def _map_key(params: DenseParams) -> dict[str, Any]:
    """What a stored map depends on besides the image (:func:`save_map`)."""
    return {"backbone": str(params.backbone), "max_side": int(params.max_side),
            "min_side": int(params.min_side), "rotations": int(params.rotations)}


def save_map(path: str | os.PathLike[str], fmap: tuple[np.ndarray, float] | None,
             params: DenseParams, failure: str | None = None) -> None:
    """Store :func:`dense_map`'s result so that a later step (the scoring of stage I's RPs,
    :func:`score_and_split`) needs no backbone pass of its own.

    HDF5 (:func:`rescu.io.write_h5`, atomic): dataset ``map`` (C, h, w) float16,
    attributes ``scale`` (backbone input px per prepared-image px) and what the map
    depends on (``backbone``, ``max_side``, ``min_side``, ``rotations``). ``fmap`` None (a
    failed dense step): no dataset, the attribute ``failure`` says why.
    """
    from ..io import write_h5

    if fmap is None:
        write_h5(path, {}, attrs={**_map_key(params), "failure": failure or "no map"})
    else:
        write_h5(path, {"map": np.asarray(fmap[0], np.float16)},
                 attrs={**_map_key(params), "scale": float(fmap[1])})


def load_map(path: str | os.PathLike[str], params: DenseParams
             ) -> tuple[np.ndarray, float] | None:
    """A map stored by :func:`save_map`: ``(f (C, h, w) float32 read-only, s)``, or None
    when it holds none (failed dense step) or was made with other ``backbone``,
    ``max_side``, ``min_side`` or ``rotations`` than ``params`` say. A file that cannot be
    read raises :class:`rescu.io.InputError` naming it (:func:`rescu.io.read_h5`)."""
    from ..io import read_h5

    arrays, attrs = read_h5(path)
    attrs = {"rotations": 1, **attrs}     # maps stored before ``rotations`` are plain ones
    if "map" not in arrays or any(attrs.get(k) != v for k, v in _map_key(params).items()):
        return None
    f = np.asarray(arrays["map"], np.float32)
    f.setflags(write=False)
    return f, float(attrs["scale"])


def dense_levels(rgb: np.ndarray, params: DenseParams, backbone: Any = None
                 ) -> list[tuple[np.ndarray, float]]:
    """The maps the dense source looks for objects on: the coarse one (:func:`dense_map`);
    with ``params.fine_scale > 1``, a fine one of the image enlarged ``fine_scale`` times
    more (its longer side at most ``params.fine_max_side``), for objects too small to
    span two cells of the coarse map's stride-16 half; for each of
    ``params.wide_scales``, a wide one of the image reduced to that fraction of the
    coarse map's scale, for objects too large for the coarse map's largest blob (coins or
    cookies filling a tray: a tenth of the photo's side and more), left out when its
    input's shorter side would be under :data:`WIDE_MIN_PX`.

    Parameters
    ----------
    rgb : (H, W, 3) uint8, the prepared image
    params : DenseParams (``backbone``, ``max_side``, ``min_side``, ``fine_scale``,
        ``fine_max_side``, ``wide_scales``, ``rotations``)
    backbone : FrozenBackbone or None (None: ``params.backbone`` at stride 16, CPU)

    Returns
    -------
    list of ``(f, s)``: the coarse level first, then the fine one, then the wide ones;
    ``f`` (C, h, w) float32, read-only (:func:`hypercolumn`) of ``rgb`` resized by ``s``
    (backbone-input pixels per prepared-image pixel). The fine level is left out when it
    would enlarge the coarse one by less than 5 %. :func:`level_sizes` gives each
    level's blob sides.
    """
    from .backbone import shared_backbone

    if backbone is None:
        backbone = shared_backbone(params.backbone, feature_stride=16)
    f, s = dense_map(rgb, params, backbone)
    out = [(f, s)]
    longer = max(rgb.shape[:2])
    s_fine = min(s * params.fine_scale, params.fine_max_side / longer)
    if s_fine > 1.05 * s:
        out.append((read_only(hypercolumn(backbone, level_image(rgb, s_fine),
                                           params.rotations)), float(s_fine)))
    for w in params.wide_scales:
        if min(rgb.shape[:2]) * s * w >= WIDE_MIN_PX:
            out.append((read_only(hypercolumn(backbone, level_image(rgb, s * w),
                                               params.rotations)), float(s * w)))
    return out


def level_sizes(levels: Sequence[tuple[np.ndarray, float]], params: DenseParams
                ) -> list[tuple[int, ...]]:
    """The blob sides (cells) of each map of :func:`dense_levels`: ``params.sizes`` on the
    coarse one (the first), ``params.fine_sizes`` on a map of a larger scale,
    ``params.wide_sizes`` on one of a smaller scale."""
    s0 = levels[0][1] if levels else 1.0
    return [params.sizes if k == 0 else params.fine_sizes if s > s0 else params.wide_sizes
            for k, (_, s) in enumerate(levels)]


def _flat_candidates(f: np.ndarray, params: DenseParams,
                     sizes: Sequence[int] | None = None, level: int = 0,
                     colour_of: Callable[[np.ndarray], np.ndarray] | None = None
                     ) -> list[DenseCandidate]:
    """:func:`dense_candidates` of one map less the groups that tile the plane."""
    return [c for c in dense_candidates(f, 8.0, params, sizes, level, colour_of)
            if c.touching <= params.max_touching]


def colour_for(rgb: np.ndarray, s: float, params: DenseParams,
               integrals: tuple[np.ndarray, np.ndarray] | None = None
               ) -> Callable[[np.ndarray], np.ndarray] | None:
    """The ``colour_of`` of :func:`dense_candidates` for a map of ``rgb`` resized by ``s``:
    boxes in that map's input pixels -> :func:`central_colours` on ``rgb``; None when
    ``params.max_colour_distance`` is 0 (groups not split by colour)."""
    if params.max_colour_distance <= 0:
        return None
    ii = colour_integrals(rgb) if integrals is None else integrals
    return lambda boxes: central_colours(ii, np.asarray(boxes, float) / s)


def level_candidates(levels: Sequence[tuple[np.ndarray, float]], rgb: np.ndarray,
                     params: DenseParams, backbone: Any = None) -> list[DenseCandidate]:
    """The groups of recurring blobs of every level (:func:`dense_candidates`, each map
    with its blob sides, :func:`level_sizes`) that do not tile
    the plane, ranked together by contrast x rarity [x objectness], best first, at most
    ``params.max_candidates``: the whole of :func:`iter_level_candidates`.

    Parameters
    ----------
    levels : :func:`dense_levels`
    rgb : (H, W, 3) uint8, the prepared image (objectness crops)
    params : DenseParams (``objectness_crops`` 0: no objectness)
    backbone : FrozenBackbone, for the objectness (needed when ``objectness_crops`` > 0)

    Returns
    -------
    list of :class:`DenseCandidate` (``level`` set; boxes in its level's pixels)
    """
    return list(iter_level_candidates(levels, rgb, params, backbone))


def iter_level_candidates(levels: Sequence[tuple[np.ndarray, float]], rgb: np.ndarray,
                          params: DenseParams, backbone: Any = None
                          ) -> Iterator[DenseCandidate]:
    """:func:`level_candidates` one at a time, each group classified (:func:`objectness`,
    a backbone pass on its crops) only when the ranking needs it.

    Objectness is at most 1, so a group's contrast x rarity bounds its final score: the
    best group not yet yielded is the first in the order (final score, level, top, left)
    whose bound is its final score, the unclassified ones ranked by their bound. The
    order is the same as classifying every group and sorting (:func:`level_candidates`);
    a caller that stops early (:func:`rescu.extension.objects.whole_objects`, once it
    holds ``max_patterns`` RPs) skips the classifier on the groups it never reaches.

    Yields
    ------
    :class:`DenseCandidate`, best first, at most ``params.max_candidates`` (``score``
    multiplied by the objectness)
    """
    import heapq

    of = [objectness_for(rgb, s, params, backbone) for _, s in levels]
    # one set of colour tables for both maps (only when groups are split by colour)
    integrals = colour_integrals(rgb) if params.max_colour_distance > 0 else None
    heap: list[tuple[float, int, float, float, int, bool]] = []
    cands: list[DenseCandidate] = []
    for k, ((f, s), sizes) in enumerate(zip(levels, level_sizes(levels, params))):
        for c in _flat_candidates(f, params, sizes, k, colour_for(rgb, s, params, integrals)):
            heap.append((-c.score, k, float(c.boxes[0, 1]), float(c.boxes[0, 0]),
                         len(cands), of[k] is None))
            cands.append(c)
    heapq.heapify(heap)
    n = 0
    while heap and n < params.max_candidates:
        _, k, y, x, i, scored = heapq.heappop(heap)
        c = cands[i]
        if scored:
            n += 1
            yield c
        else:
            objectness_of = of[k]
            assert objectness_of is not None
            cands[i] = c = replace(c, score=c.score * objectness_of(c.boxes))
            heapq.heappush(heap, (-c.score, k, y, x, i, True))


def find_dense(rgb: np.ndarray, params: DenseParams, backbone: Any = None,
               scale_factor: float = 1.0,
               levels: Sequence[tuple[np.ndarray, float]] | None = None) -> list[Pattern]:
    """The dense source on one prepared image.

    Groups of recurring blobs on each map of :func:`dense_levels` that do not tile the
    plane, ranked together by contrast x rarity [x objectness]
    (:func:`level_candidates`); with ``params.whole_objects`` each is turned into an RP
    of whole objects on its own map (:func:`rescu.extension.objects.whole_objects`:
    completion by exemplar correlation, extent, size checks, one RP per object,
    confidence), else the first ``params.max_patterns`` of the coarse map's groups are
    kept as they are (the blobs' squares).

    Parameters
    ----------
    rgb : (H, W, 3) uint8, the prepared image (processed pixels)
    params : DenseParams
    backbone : FrozenBackbone or None (None: ``params.backbone`` at stride 16, CPU)
    scale_factor : processed = original x scale_factor (the prepared image's meta)
    levels : :func:`dense_levels` of ``rgb`` when already computed

    Returns
    -------
    list of Pattern (ids 0..; instances in **original** pixels, ``source="stage1"``;
    ``score`` = contrast x rarity x objectness; ``extra={"source": "dense"}``, with
    ``whole_objects`` also ``"confidence"`` (:func:`rescu.extension.objects.pattern_confidence`),
    ``"seeds"`` (blobs of the group), ``"gap"``, ``"separation"`` (when defined),
    ``"extent"`` (the box transform) and ``"level"`` (the map's index in
    :func:`dense_levels`: 0 the coarse one))

    >>> import numpy as np
    >>> find_dense(np.zeros((64, 64, 3), np.uint8), DenseParams())
    []
    """
    from .backbone import shared_backbone
    from .objects import whole_objects

    if backbone is None:
        backbone = shared_backbone(params.backbone, feature_stride=16)
    rgb = np.asarray(rgb)
    if levels is None:
        levels = dense_levels(rgb, params, backbone) if params.whole_objects \
            else [dense_map(rgb, params, backbone)]
    to_orig = 1.0 / float(scale_factor)
    pats = []
    if params.whole_objects:
        ranked = iter_level_candidates(levels, rgb, params, backbone)
        found = whole_objects(levels, 8.0, rgb, ranked, params,
                              _turned_completion(rgb, levels, params, backbone))
    else:
        f, s = levels[0]
        found = [(c.score, c.boxes / s, {}) for c in
                 rank_candidates(_flat_candidates(f, params, None, 0,
                                                  colour_for(rgb, s, params)),
                                 objectness_for(rgb, s, params, backbone),
                                 params.max_patterns)]
    for k, (score, boxes, info) in enumerate(found):
        b = np.asarray(boxes, float) * to_orig
        pats.append(Pattern(id=k, score=float(score), instances=[
            Instance(bbox=tuple(float(v) for v in row), score=1.0, source="stage1")
            for row in b], extra={"source": "dense", **info}))
    return pats


def _turned_completion(rgb: np.ndarray, levels: Sequence[tuple[np.ndarray, float]],
                       params: DenseParams, backbone: Any
                       ) -> Callable[..., tuple[np.ndarray, np.ndarray]] | None:
    """The ``turned`` of :func:`rescu.extension.objects.whole_objects`: ``(level, boxes,
    integral) -> (boxes, is_turned)``, :func:`complete_turned` on that level's map and
    its :func:`turned_map` (made on first use: one backbone pass per level with a group to
    complete); None without ``params.completion_turn`` (or without completion)."""
    if not (params.completion_turn and params.complete):
        return None
    made: dict[int, np.ndarray] = {}

    def turned(level: int, boxes: np.ndarray, integral: np.ndarray | None
               ) -> tuple[np.ndarray, np.ndarray]:
        f, s = levels[level]
        if level not in made:
            made[level] = read_only(turned_map(backbone, level_image(rgb, s),
                                                params.rotations, (f.shape[1], f.shape[2])))
        b, _, is_turned = complete_turned(f, made[level], 8.0, boxes,
                                          params.completion_margin,
                                          params.completion_floor, integral=integral)
        return b, is_turned

    return turned


def score_and_split(res: ImageResult, found: ImageResult, dense_params: DenseParams,
                    rgb: np.ndarray,
                    meta: dict[str, Any], backbone: Any = None,
                    fmap: tuple[np.ndarray, float] | None = None) -> None:
    """RESCU-I with ``dense.mode: objects``: every RP of ``res`` gets a confidence
    (:func:`rescu.extension.objects.score_patterns` on the map of :func:`dense_map`, one
    backbone pass, only when a pattern needs it); those below ``dense.min_confidence``,
    sitting on a more confident RP's objects, or left with too few instances by one move
    to ``candidate_patterns``, the others are reported most confident first
    (:func:`rescu.discovery.sources.split_by_confidence`), in place; stage-I RPs on a
    checkerboard (:func:`rescu.discovery.tiling.board_outline`, its outline recorded in
    ``res.extra["checkerboard"]``) are not reported either. Then one box per object: a
    reported instance whose nearest earlier one (of a more confident RP, or earlier in
    its own) is a box on the same object, with no gap between the two on the
    map, is dropped (``dense.min_object_separation`` null: off;
    :func:`rescu.extension.objects.one_box_per_object`). Nothing in the other modes or
    after a failed dense step (``found``'s failure).

    Parameters
    ----------
    res : :class:`rescu.types.ImageResult`, RESCU-I's result (instances in original pixels)
    found : :class:`rescu.types.ImageResult`, the dense step's result
    dense_params : the ``dense`` parameters
    rgb : (H, W, 3) uint8, the prepared image
    meta : its meta (``scale_factor``: processed = original x scale_factor)
    backbone : FrozenBackbone or None (None: ``dense.backbone``)
    fmap : :func:`dense_map` of ``rgb`` when already made (e.g. stored by the dense step,
        :func:`load_map`); None: made here when needed
    """
    from ..discovery.sources import split_by_confidence
    from ..discovery.tiling import board_outline
    from .objects import one_box_applies, one_box_per_object, score_patterns

    dp = dense_params
    if dp.mode != "objects" or found.extra.get("failure"):
        return
    unscored = any("confidence" not in p.extra for p in res.patterns)
    boxes = bool(res.patterns) and one_box_applies(dp)
    if unscored or boxes:
        fmap = dense_map(rgb, dp, backbone) if fmap is None else fmap
    if unscored:
        score_patterns(rgb, res.patterns, float(meta["scale_factor"]), dp, *fmap)
    board = (None if all(map(is_whole_object, res.patterns))
             else board_outline(rgb, float(meta["scale_factor"]), dp))
    if board is not None:                       # the board's outline, for experts
        res.extra["checkerboard"] = [[round(float(x), 2), round(float(y), 2)] for x, y in board]
    split_by_confidence(res, dp.min_confidence, dp, board)
    if boxes:
        one_box_per_object(res, fmap, float(meta["scale_factor"]), dp)
    res.extra["n_dense_patterns"] = sum(map(is_whole_object, res.patterns))
