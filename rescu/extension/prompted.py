"""Every instance of what an example box shows: template correlation on the backbone's map.

"Count these": one to a few example boxes of the same kind of object (a red cell, a
fish, a car seen from above) and the photo; :func:`find_like` returns a box on every
instance. The method, one implementation for prompts (:func:`rescu.api.discover`'s
``examples``) and for the completion of a group found without any prompt:

1. **Scale.** The photo is resized so that the examples' mean side is
   ``target_side`` pixels (the backbone's receptive fields then see each object at the
   size ImageNet objects have in its crops), its longer side at most ``max_side``.
2. **Map.** The backbone's stride-8 + stride-16 hypercolumn
   (:func:`rescu.extension.turned.hypercolumn`, unit norm per cell) of the resized photo,
   with ``turn`` the same of the photo turned by 90 degrees (objects lying the other
   way: cars parked across a row, fish swimming up), and with ``half_turn`` of the photo
   turned by 180 degrees (objects facing the other way: the cars of the opposite row of
   a car park seen from above).
3. **Template.** The example's window of ``kh x kw`` cells, kept as a window (its layout
   matters: a car's front is not its side), the mean over the examples.
4. **Correlation.** At every cell the normalised inner product of the stacked window
   around it with the template (a cosine in ``C x kh x kw`` dimensions; at the border
   over the cells inside the map). Local maxima within half a window are candidates, a
   box of the examples' size on each (turned back: width and height swapped for the
   quarter-turned map); non-maximum suppression (IoU) and a coverage rule (a box mostly covered by
   more likely ones is the gap between two objects, not a third one).
5. **Second round.** The template becomes the mean window of the confident finds
   (score at least ``round_fraction`` of the way from the photo's median score to the
   best find's), each from the map it was found on, averaged with the examples' (half
   each), so the instances' own variety tempers the one example's particulars; step 4
   again.
6. **Photo model** (``photo_model``, optional). A logistic regression of the positive windows
   (the examples' and the first round's confident finds') against windows on a grid
   over the rest of the photo (:func:`fit_photo_model`); a find's score becomes the
   geometric mean of its correlation and the model's probability at its window
   (:func:`linear_map`). The correlation ranks the finds of one photo; the probability
   says where "like the examples" ends in this photo, so that one threshold carries
   over from photo to photo.
7. **Threshold.** A find is kept when its score is at least ``min_score`` and at least
   ``b + relative_score x (r - b)``, ``r`` the examples' own score against the final
   template (what an instance scores, measured where we know there is one), ``b`` the
   median score over the whole photo (what a typical patch of it scores): the score
   measured on the photo's own scale from "like any patch" (0) to "like the example" (1).

The examples themselves are always instances (score 1). Coordinates in and out are pixels
of the image given (``rgb``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from ..params import config_section, params_from_dict

__all__ = ["PromptParams", "Finds", "check_examples", "find_like", "fit_photo_model",
           "linear_map"]


@dataclass(frozen=True)
@config_section("prompt")
class PromptParams:
    """Parameters of :func:`find_like` (config section ``prompt``).

    Attributes
    ----------
    target_side : float
        The examples' mean side after resizing the photo, pixels.
    max_side : int
        Longer side of the resized photo at most, pixels (small objects in a large photo
        are then seen smaller than ``target_side``).
    turn : bool
        Also look for the objects turned by 90 degrees (one more backbone pass).
    half_turn : bool
        Also look for the objects turned by 180 degrees, facing the other way (one more
        backbone pass).
    half_turn_margin : float
        A find on the map of the photo turned by 180 degrees is kept only where it scores
        at least this much more than the unturned template does at its centre: an object
        that looks the same both ways (a cell, a window) is left to the unturned map, so
        the turned one adds the objects that truly face the other way and not a second
        chance for every patch to pass the threshold.
    photo_model : bool
        Score each find also by a per-photo model: a logistic regression of the windows
        of the examples (and of the first round's confident finds) against windows from
        the rest of the photo (:func:`fit_photo_model`); a find's score is then the
        geometric mean of its correlation and the model's probability. The correlation
        ranks the instances of one photo; the probability says where, in this photo,
        "like the examples" ends, so one threshold carries over from photo to photo.
    negatives : int
        The photo model's negative windows: about this many, on a regular grid of the
        unturned map, none within half a window of a positive one.
    model_c : float
        The photo model's inverse L2 regularisation (scikit-learn's ``C``).
    rounds : int
        1: the examples' template only; 2: a second round from the confident finds.
    round_fraction : float
        Finds scoring at least ``b + round_fraction x (best - b)`` (``b`` the photo's
        median score) make the second round's template.
    nms_iou : float
        Of two finds overlapping by more than this IoU, the lower scoring is dropped.
    max_covered : float
        A find whose box is covered by more than this share by the boxes of better finds
        is dropped (1 = off).
    min_inside : float
        A box cut by the photo's border keeps at least this share of its area inside, or
        it is dropped.
    min_score : float
        Least score of a reported find: its correlation (cosine, in [-1, 1]), or with
        ``photo_model`` the geometric mean of its correlation (0 where negative) and the
        model's probability (in [0, 1]).
    relative_score : float
        ... and at least ``b + relative_score x (r - b)``: ``r`` the examples' mean score
        against the final template, ``b`` the photo's median score.
    min_box_px : float
        An example box must be at least this many pixels wide and high (original pixels).
    unprompted : bool
        With examples, the RPs found without them are still reported after the prompted
        one; false: the prompted RP alone.
    sizes : tuple of float
        Object sides looked for, as ratios to the examples' mean side, each in
        [0.25, 4]: a ratio ``r`` other than 1 adds the map of the resized photo resized
        again by ``1 / r`` (capped by ``max_side``; turned too with ``turn`` and
        ``half_turn``), where
        objects ``r`` x the examples' side look like them; their boxes are ``r`` x the
        examples' size.
    """

    target_side: float
    max_side: int
    turn: bool
    half_turn: bool
    half_turn_margin: float
    rounds: int
    round_fraction: float
    nms_iou: float
    max_covered: float
    min_inside: float
    min_score: float
    relative_score: float
    min_box_px: float
    unprompted: bool
    sizes: tuple[float, ...] = (1.0,)
    photo_model: bool = False
    negatives: int = 3000
    model_c: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "sizes", tuple(float(r) for r in self.sizes))

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "PromptParams":
        """Build from a mapping; unknown keys raise ValueError naming them."""
        return params_from_dict(cls, d)


@dataclass
class Finds:
    """What :func:`find_like` found.

    Attributes
    ----------
    boxes : (N, 4) float
        ``x, y, w, h`` in pixels of the image given, the examples first.
    scores : (N,) float
        Scores (1 for the examples), in the order of ``boxes``: the correlation, or
        with ``photo_model`` its geometric mean with the photo model's probability.
    is_example : (N,) bool
        Which boxes are the examples.
    turned : (N,) bool
        Found on a map of the photo turned by 90 degrees (width and height are the
        examples' swapped).
    candidates : (M, 4) float, candidate_scores : (M,) float
        Every candidate above the peak floor before the threshold, examples excluded
        (for studies of the threshold).
    reference : float
        The examples' mean score against the final template (and photo model).
    background : float
        The median score over the whole photo (every cell, the mean over the views):
        what a typical patch of the photo scores.
    scale : float
        Resized photo px per given px.
    threshold : float
        The least score of a reported find.
    """

    boxes: np.ndarray
    scores: np.ndarray
    is_example: np.ndarray
    turned: np.ndarray
    candidates: np.ndarray
    candidate_scores: np.ndarray
    reference: float
    background: float
    scale: float
    threshold: float

    @property
    def count(self) -> int:
        return int(len(self.boxes))


def check_examples(examples: Sequence[Sequence[float]], width: int, height: int,
                   min_px: float = 4.0, where: str = "example") -> np.ndarray:
    """The example boxes as an ``(K, 4)`` float array, each checked against the photo.

    Parameters
    ----------
    examples : sequence of (x, y, w, h)
        Boxes in pixels of the photo (top-left corner, width, height).
    width, height : int
        The photo's size, pixels.
    min_px : float
        Least width and height of a box, pixels.
    where : str
        How the error messages name the boxes (e.g. ``"--example"``).

    Returns
    -------
    (K, 4) float64, K >= 1.

    Raises
    ------
    ValueError
        No box; a box that is not four finite numbers, has a side under ``min_px``, or
        does not lie inside the photo (more than a pixel out on any side).

    >>> check_examples([(10, 10, 20, 30)], 100, 100)
    array([[10., 10., 20., 30.]])
    >>> check_examples([(90, 10, 20, 30)], 100, 100)
    Traceback (most recent call last):
    ...
    ValueError: example 1 (90, 10, 20, 30): leaves the 100 x 100 photo (x + w = 110 > 100)
    """
    if len(examples) == 0:
        raise ValueError(f"{where}: no box given")
    out = []
    for i, b in enumerate(examples, 1):
        label = f"{where} {i} ({', '.join(_num(v) for v in b)})" if _is_seq(b) else \
            f"{where} {i} ({b!r})"
        try:
            vals = [float(v) for v in b]
        except (TypeError, ValueError):
            raise ValueError(f"{label}: a box is four numbers x, y, w, h") from None
        if len(vals) != 4:
            raise ValueError(f"{label}: a box is four numbers x, y, w, h, got {len(vals)}")
        x, y, w, h = vals
        if not all(np.isfinite(vals)):
            raise ValueError(f"{label}: not finite")
        if w < min_px or h < min_px:
            raise ValueError(f"{label}: width and height must be at least {_num(min_px)} "
                             f"pixels")
        tol = 1.0
        for bad, text in ((x < -tol, f"x = {_num(x)} < 0"), (y < -tol, f"y = {_num(y)} < 0"),
                          (x + w > width + tol, f"x + w = {_num(x + w)} > {width}"),
                          (y + h > height + tol, f"y + h = {_num(y + h)} > {height}")):
            if bad:
                raise ValueError(f"{label}: leaves the {width} x {height} photo ({text})")
        x0, y0 = max(x, 0.0), max(y, 0.0)
        out.append([x0, y0, min(x + w, width) - x0, min(y + h, height) - y0])
    return np.asarray(out, np.float64)


def _is_seq(b: Any) -> bool:
    return isinstance(b, (list, tuple, np.ndarray))


def _num(v: Any) -> str:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return repr(v)
    return str(int(f)) if f.is_integer() else f"{f:g}"


# ---------------------------------------------------------------------------- maps
CELL = 8  # pixels of the resized photo per cell of the hypercolumn


def _windows(f: np.ndarray, centres: np.ndarray, kh: int, kw: int) -> np.ndarray:
    """The ``(C, kh, kw)`` windows of ``f`` (C, h, w) whose top-left cells are
    ``centres`` (n, 2) rows, cols (cells outside the map are zero): (n, C, kh, kw)."""
    c, h, w = f.shape
    pad = np.zeros((c, h + 2 * kh, w + 2 * kw), np.float32)
    pad[:, kh:kh + h, kw:kw + w] = f
    out = np.empty((len(centres), c, kh, kw), np.float32)
    for i, (r, q) in enumerate(np.asarray(centres, int)):
        r = int(np.clip(r, -kh, h)) + kh
        q = int(np.clip(q, -kw, w)) + kw
        out[i] = pad[:, r:r + kh, q:q + kw]
    return out


def correlation(f: np.ndarray, template: np.ndarray) -> np.ndarray:
    """Normalised correlation of the template with every window of the map.

    Parameters
    ----------
    f : (C, h, w) float32
        Feature map (unit norm per cell).
    template : (C, kh, kw) float
        The window to look for.

    Returns
    -------
    (h, w) float32 in [-1, 1]: at cell ``(i, j)`` the cosine between ``template`` and the
    window whose top-left cell is ``(i - kh // 2, j - kw // 2)`` (cells outside the map
    count as zeros; the norm is that of the cells inside).

    >>> f = np.zeros((1, 6, 6), np.float32); f[0] = 1.0
    >>> round(float(correlation(f, np.ones((1, 3, 3)))[3, 3]), 5)
    1.0
    """
    import torch

    t = torch.from_numpy(np.ascontiguousarray(template, np.float32))[None]
    with torch.no_grad():
        out = _window_products(f, t / (t.norm() + 1e-9))
    return out.numpy().astype(np.float32)


def _window_products(f: np.ndarray, t: Any) -> Any:
    """The inner product of the weights ``t`` (torch, (1, C, kh, kw) float32) with every
    ``kh x kw`` window of ``f`` (C, h, w) scaled to unit norm (cells outside the map are
    zeros; the norm is that of the cells inside), laid out as :func:`correlation`'s:
    torch (h, w). Call under ``torch.no_grad()``."""
    import torch
    import torch.nn.functional as F

    kh, kw = int(t.shape[2]), int(t.shape[3])
    x = torch.from_numpy(np.ascontiguousarray(f, np.float32))[None]
    pad = (kw // 2, kw - 1 - kw // 2, kh // 2, kh - 1 - kh // 2)
    num = F.conv2d(F.pad(x, pad), t)[0, 0]
    energy = F.conv2d(F.pad((x * x).sum(1, keepdim=True), pad),
                      torch.ones(1, 1, kh, kw))[0, 0]
    return num / energy.clamp_min(1e-9).sqrt()


def fit_photo_model(pos: np.ndarray, neg: np.ndarray, c: float = 1.0
                    ) -> tuple[np.ndarray, float]:
    """A linear model of the positive windows against the negative ones, of one photo.

    A logistic regression (L2, inverse strength ``c``, the classes weighed equally) on
    the windows scaled to unit norm, as :func:`correlation` compares them.

    Parameters
    ----------
    pos, neg : (n, C, kh, kw) float
        Windows of the instances and of the rest of the photo (at least one each).
    c : float
        scikit-learn's ``C``.

    Returns
    -------
    weights : (C, kh, kw) float32, bias : float
        For :func:`linear_map`.

    >>> rng = np.random.default_rng(0)
    >>> neg = rng.normal(size=(50, 2, 1, 1)); pos = neg[:5] + np.array([3.0, 0])[:, None, None]
    >>> w, b = fit_photo_model(pos, neg)
    >>> bool(w[0, 0, 0] > abs(w[1, 0, 0]))
    True
    """
    from sklearn.linear_model import LogisticRegression

    pos, neg = np.asarray(pos, np.float64), np.asarray(neg, np.float64)
    if not len(pos) or not len(neg):
        raise ValueError(f"need positive and negative windows, got {len(pos)} and {len(neg)}")
    x = np.concatenate([pos, neg]).reshape(len(pos) + len(neg), -1)
    x = x / (np.linalg.norm(x, axis=1, keepdims=True) + 1e-9)
    y = np.r_[np.ones(len(pos)), np.zeros(len(neg))]
    clf = LogisticRegression(C=float(c), class_weight="balanced", max_iter=500)
    clf.fit(x, y)
    return clf.coef_[0].reshape(pos.shape[1:]).astype(np.float32), float(clf.intercept_[0])


def linear_map(f: np.ndarray, weights: np.ndarray, bias: float) -> np.ndarray:
    """The probability of :func:`fit_photo_model`'s model at every window of a map,
    laid out as :func:`correlation`'s (window of top-left cell ``(i - kh // 2, j - kw //
    2)`` at ``(i, j)``, each window scaled to unit norm): (h, w) float32 in [0, 1].

    >>> f = np.ones((1, 4, 4), np.float32)
    >>> round(float(linear_map(f, np.ones((1, 1, 1), np.float32), 0.0)[2, 2]), 3)
    0.731
    """
    import torch

    t = torch.from_numpy(np.ascontiguousarray(weights, np.float32))[None]
    with torch.no_grad():
        out = torch.sigmoid(_window_products(f, t) + bias)
    return out.numpy().astype(np.float32)


def _negative_cells(shape: tuple[int, int], kh: int, kw: int, positives: np.ndarray,
                    n: int) -> np.ndarray:
    """Top-left cells (m, 2) of about ``n`` windows on a regular grid over a map of
    ``shape`` (h, w), none within half a window of a ``positives`` (k, 2) top-left cell."""
    h, w = shape
    ys = np.arange(-(kh // 2), h - kh // 2)
    xs = np.arange(-(kw // 2), w - kw // 2)
    step = max(1, int(np.ceil(np.sqrt(len(ys) * len(xs) / max(n, 1)))))
    g = np.stack(np.meshgrid(ys[::step], xs[::step], indexing="ij"), -1).reshape(-1, 2)
    far = np.ones(len(g), bool)
    for q in np.asarray(positives, int).reshape(-1, 2):
        far &= (np.abs(g[:, 0] - q[0]) > kh / 2) | (np.abs(g[:, 1] - q[1]) > kw / 2)
    return g[far]


def _peaks(sim: np.ndarray, kh: int, kw: int, floor: float) -> tuple[np.ndarray, np.ndarray]:
    """Local maxima of ``sim`` within half a ``kh x kw`` window (at least 3 cells),
    at least ``floor``: (n, 2) rows, cols and their values."""
    from scipy.ndimage import maximum_filter

    size = (max(3, int(round(0.5 * kh)) | 1), max(3, int(round(0.5 * kw)) | 1))
    ys, xs = np.nonzero((sim == maximum_filter(sim, size, mode="constant", cval=-2.0))
                        & (sim >= floor))
    return np.c_[ys, xs], sim[ys, xs].astype(np.float64)


def _score_at(sim: np.ndarray, centres: np.ndarray, kh: int, kw: int) -> np.ndarray:
    """The values of :func:`correlation`'s map ``sim`` (of the unturned, unzoomed resized
    photo, a ``kh x kw`` template) for the windows centred nearest ``centres`` (n, 2)
    ``x, y`` in its pixels: (n,) float.

    >>> sim = np.arange(20.0).reshape(4, 5)
    >>> _score_at(sim, np.array([[20.0, 12.0], [0.0, 0.0]]), 2, 2).tolist()
    [8.0, 0.0]
    """
    r = np.round(centres[:, 1] / CELL - kh / 2.0).astype(int) + kh // 2
    c = np.round(centres[:, 0] / CELL - kw / 2.0).astype(int) + kw // 2
    return sim[np.clip(r, 0, sim.shape[0] - 1), np.clip(c, 0, sim.shape[1] - 1)].astype(float)


def _scaled(rgb: np.ndarray, s: float) -> np.ndarray:
    import cv2

    h, w = rgb.shape[:2]
    size = (max(CELL * 2, int(round(w * s))), max(CELL * 2, int(round(h * s))))
    interp = cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR
    return cv2.resize(rgb, size, interpolation=interp)


@dataclass
class _View:
    """One map the objects are looked for on: of the photo turned counterclockwise by
    ``quarters`` x 90 degrees (0, 1 or 2: ``np.rot90``); ``wh`` the resized photo's (width,
    height) before turning."""

    f: np.ndarray
    quarters: int
    wh: tuple[int, int]
    zoom: float = 1.0

    def boxes(self, cells: np.ndarray, kh: int, kw: int, bw: float, bh: float) -> np.ndarray:
        """Boxes (n, 4) in resized-photo pixels, centred on the windows whose top-left
        cells are ``cells`` (rows, cols; a (kh, kw) window), of the examples' size
        ``bw x bh`` in this view (as seen in its own orientation before turning back):
        ``bw / zoom x bh / zoom`` in the resized photo, whose pixels this view's
        ``zoom`` x enlarges (``wh``: the view's (width, height) before turning)."""
        cy = (cells[:, 0] + kh / 2.0) * CELL
        cx = (cells[:, 1] + kw / 2.0) * CELL
        W, H = self.wh
        n = np.full(len(cx), 1.0)
        if self.quarters == 0:
            b = np.c_[cx - bw / 2, cy - bh / 2, n * bw, n * bh]
        elif self.quarters == 1:
            ox, oy = W - cy, cx  # turned point (x', y') <- photo point (W - y', x')
            b = np.c_[ox - bh / 2, oy - bw / 2, n * bh, n * bw]
        elif self.quarters == 2:
            ox, oy = W - cx, H - cy  # turned point (x', y') <- photo point (W - x', H - y')
            b = np.c_[ox - bw / 2, oy - bh / 2, n * bw, n * bh]
        else:
            raise ValueError(f"quarters must be 0, 1 or 2, got {self.quarters}")
        return b / self.zoom


def _cover_filter(boxes: np.ndarray, order: np.ndarray, max_covered: float,
                  shape: tuple[int, int]) -> np.ndarray:
    """Indices of ``order`` (best first) kept when a box covered by more than
    ``max_covered`` of its area by the boxes kept before it is dropped; coverage is
    measured on a mask of the photo (``shape`` = height, width) at about 16 cells per box
    side."""
    if max_covered >= 1.0 or len(order) == 0:
        return order
    side = float(np.median(np.minimum(boxes[order, 2], boxes[order, 3])))
    q = max(side / 16.0, 1.0)
    hh, ww = int(np.ceil(shape[0] / q)) + 1, int(np.ceil(shape[1] / q)) + 1
    mask = np.zeros((hh, ww), bool)
    keep = []
    for i in order:
        x, y, w, h = boxes[i]
        x0, y0 = int(max(0, np.floor(x / q))), int(max(0, np.floor(y / q)))
        x1, y1 = int(min(ww, np.ceil((x + w) / q))), int(min(hh, np.ceil((y + h) / q)))
        if x1 <= x0 or y1 <= y0:
            continue
        if mask[y0:y1, x0:x1].mean() > max_covered:
            continue
        keep.append(i)
        mask[y0:y1, x0:x1] = True
    return np.asarray(keep, int)


def find_like(rgb: np.ndarray, examples: np.ndarray, backbone: Any,
              params: PromptParams | None = None) -> Finds:
    """Every instance of what the example boxes show (see the module docstring).

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        The photo.
    examples : (K, 4) float
        Example boxes ``x, y, w, h`` in pixels of ``rgb``, checked
        (:func:`check_examples`).
    backbone : rescu.extension.backbone.FrozenBackbone
        The frozen backbone (EfficientNet-Lite0; its stride-8 and -16 maps).
    params : PromptParams, optional
        Default: the configuration's ``prompt`` section.

    Returns
    -------
    Finds
        The examples first (score 1), then the finds, best first, in pixels of ``rgb``.
    """
    from ..boxes import iou_matrix, nms
    from .turned import hypercolumn

    p = params or PromptParams()
    ex = np.asarray(examples, np.float64).reshape(-1, 4)
    H, W = rgb.shape[:2]
    mean_side = float(np.mean(np.sqrt(ex[:, 2] * ex[:, 3])))
    s = min(p.target_side / mean_side, p.max_side / max(H, W))
    img = _scaled(rgb, s)
    sh, sw = img.shape[:2]
    sx, sy = sw / W, sh / H
    exs = ex * [sx, sy, sx, sy]
    bw, bh = float(exs[:, 2].mean()), float(exs[:, 3].mean())
    kw = max(1, int(round(bw / CELL)))
    kh = max(1, int(round(bh / CELL)))
    turns = [0] + [1] * p.turn + [2] * p.half_turn     # quarter turns looked at

    def turned(im: np.ndarray, q: int) -> np.ndarray:
        return im if q == 0 else np.ascontiguousarray(np.rot90(im, q))

    views = [_View(hypercolumn(backbone, turned(img, q)), q, (sw, sh)) for q in turns]
    for r in p.sizes:
        # objects r x the examples' side look like the examples in the photo resized by
        # 1 / r more (capped by max_side)
        z = min(1.0 / r, p.max_side / max(sw, sh))
        if r == 1.0 or abs(z - 1.0) < 0.05:
            continue
        zi = _scaled(img, z)
        zwh = (zi.shape[1], zi.shape[0])
        zx = zwh[0] / sw
        views += [_View(hypercolumn(backbone, turned(zi, q)), q, zwh, zx) for q in turns]
    plain = views[0].f
    # the examples' windows: kh x kw cells centred on each example's centre
    ecells = np.c_[np.round((exs[:, 1] + exs[:, 3] / 2) / CELL - kh / 2.0),
                   np.round((exs[:, 0] + exs[:, 2] / 2) / CELL - kw / 2.0)].astype(int)
    template = _windows(plain, ecells, kh, kw).mean(0)

    level: list[float] = []
    sims: list[np.ndarray] = []  # the last search's correlation map of each view

    def search(template: np.ndarray, floor: float):
        boxes, scores, where, cells = [], [], [], []
        level.clear()
        sims.clear()
        unturned = None
        for vi, v in enumerate(views):
            sim = correlation(v.f, template)
            unturned = sim if vi == 0 else unturned
            level.append(float(np.median(sim)))
            sims.append(sim)
            pk, val = _peaks(sim, kh, kw, floor)
            tl = pk - [kh // 2, kw // 2]  # top-left cells of the windows
            bx = v.boxes(tl, kh, kw, bw, bh)
            if v.quarters == 2 and len(bx):
                # facing the other way: more like the template turned than unturned
                ahead = _score_at(unturned, bx[:, :2] + bx[:, 2:] / 2, kh, kw)
                keep = val >= ahead + p.half_turn_margin
                val, tl, bx = val[keep], tl[keep], bx[keep]
            boxes.append(bx)
            scores.append(val)
            where.append(np.full(len(val), vi))
            cells.append(tl)
        b, sc = np.concatenate(boxes), np.concatenate(scores)
        vi, tl = np.concatenate(where), np.concatenate(cells)
        # clip to the photo; drop boxes mostly outside it
        x0, y0 = np.clip(b[:, 0], 0, sw), np.clip(b[:, 1], 0, sh)
        x1, y1 = np.clip(b[:, 0] + b[:, 2], 0, sw), np.clip(b[:, 1] + b[:, 3], 0, sh)
        inside = (x1 - x0) * (y1 - y0) / np.maximum(b[:, 2] * b[:, 3], 1e-9)
        ok = inside >= p.min_inside
        b = np.c_[x0, y0, x1 - x0, y1 - y0][ok]
        sc, vi, tl = sc[ok], vi[ok], tl[ok]
        keep = nms(b, sc, p.nms_iou) if len(b) else np.zeros(0, int)
        keep = _cover_filter(b, np.asarray(keep, int), p.max_covered, (sh, sw))
        return b[keep], sc[keep], vi[keep], tl[keep]

    floor = min(p.min_score, 0.2)

    def not_examples(b, sc, vi, tl):
        # the examples are instances already: finds on them are dropped
        if not len(b):
            return b, sc, vi, tl
        other = iou_matrix(b, exs).max(1) <= p.nms_iou
        return b[other], sc[other], vi[other], tl[other]

    b, sc, vi, tl = not_examples(*search(template, floor))
    if p.rounds == 2 and len(sc):
        # confident: at least round_fraction of the way from the photo's median score
        # to the best find's (a share of the best alone lets a photo whose patches all
        # score 0.3 to 0.5 against the example fill the template with background)
        bg1 = float(np.mean(level))
        conf = sc >= bg1 + p.round_fraction * (sc.max() - bg1)
        wins = np.stack([_windows(views[v].f, tl[i:i + 1], kh, kw)[0]
                         for i, v in zip(np.flatnonzero(conf), vi[conf])])
        # the examples weigh as much as all the finds together
        template = 0.5 * (wins.mean(0) + _windows(plain, ecells, kh, kw).mean(0))
        pos_cells = np.r_[ecells, tl[conf & (vi == 0)]]
        positives = np.concatenate([_windows(plain, ecells, kh, kw), wins])
        b, sc, vi, tl = not_examples(*search(template, floor))
    else:
        pos_cells, positives = ecells, _windows(plain, ecells, kh, kw)
    # the examples' own score against the final template
    ewin = _windows(plain, ecells, kh, kw)
    t = template.ravel() / (np.linalg.norm(template) + 1e-9)
    ecos = np.array([w.ravel() @ t / (np.linalg.norm(w) + 1e-9) for w in ewin])
    ref = float(np.mean(ecos))
    background = float(np.mean(level))
    negcells = (_negative_cells(plain.shape[1:], kh, kw, pos_cells, p.negatives)
                if p.photo_model else np.zeros((0, 2), int))
    if len(negcells):  # (a photo no larger than the examples has no negatives)
        # the instances against the rest of this photo: the probability, read at each
        # find's window on its own view, tempers the correlation (geometric mean)
        neg = _windows(plain, negcells, kh, kw)
        weights, bias = fit_photo_model(positives, neg, p.model_c)
        maps = [linear_map(v.f, weights, bias) for v in views]
        centre = tl + [kh // 2, kw // 2]
        prob = np.array([maps[v][min(max(r, 0), maps[v].shape[0] - 1),
                                 min(max(q, 0), maps[v].shape[1] - 1)]
                         for v, (r, q) in zip(vi, centre)], np.float64)
        sc = np.sqrt(np.clip(sc, 0.0, None) * prob)
        eprob = maps[0][
            np.clip(ecells[:, 0] + kh // 2, 0, plain.shape[1] - 1),
            np.clip(ecells[:, 1] + kw // 2, 0, plain.shape[2] - 1)]
        ref = float(np.mean(np.sqrt(np.clip(ecos, 0.0, None) * eprob)))
        background = float(np.mean([np.median(np.sqrt(np.clip(c, 0.0, None) * m))
                                    for c, m in zip(sims, maps)]))
    thr = max(p.min_score, background + p.relative_score * (ref - background))
    good = sc >= thr
    back = np.array([1 / sx, 1 / sy, 1 / sx, 1 / sy])
    return Finds(boxes=np.r_[ex, b[good] * back].reshape(-1, 4),
                 scores=np.r_[np.ones(len(ex)), sc[good]],
                 is_example=np.r_[np.ones(len(ex), bool), np.zeros(int(good.sum()), bool)],
                 turned=np.r_[np.zeros(len(ex), bool),
                              np.array([views[v].quarters == 1 for v in vi[good]], bool)],
                 candidates=(b * back).reshape(-1, 4), candidate_scores=sc,
                 reference=ref, background=background, scale=float(s),
                 threshold=float(thr))


def otsu_split(scores: np.ndarray, bins: int = 64) -> float:
    """Otsu's threshold of a 1-D sample: the value that best splits it into a low and
    a high class (most between-class variance); ``-inf`` for fewer than two values.

    >>> round(otsu_split(np.array([0.1, 0.12, 0.15, 0.7, 0.72, 0.8])), 2)
    0.15
    """
    s = np.asarray(scores, np.float64).ravel()
    if len(s) < 2 or s.max() <= s.min():
        return float("-inf")
    edges = np.linspace(s.min(), s.max(), bins + 1)
    hist, _ = np.histogram(s, edges)
    mid = (edges[:-1] + edges[1:]) / 2
    w0 = np.cumsum(hist)[:-1]
    w1 = len(s) - w0
    m0 = np.cumsum(hist * mid)[:-1] / np.maximum(w0, 1)
    m1 = (np.sum(hist * mid) - np.cumsum(hist * mid)[:-1]) / np.maximum(w1, 1)
    between = w0 * w1 * (m0 - m1) ** 2
    return float(edges[1:][int(np.argmax(between))])
