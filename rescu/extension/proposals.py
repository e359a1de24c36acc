"""Region proposals for RESCU-II: EdgeBoxes and instance-scale sliding windows.

The paper takes region proposals from EdgeBoxes (Zitnick & Dollar, ECCV 2014). EdgeBoxes
scores a box by the number of edge contours wholly inside it; it needs an edge map and
an edge-orientation map. Its learned structured-edge model is not available here, so
unless ``edge_model_path`` names a structured-edge model file (used through
``cv2.ximgproc.createStructuredEdgeDetection``) the edge map is computed from smoothed
Scharr gradients of the Lab image (thinned by non-maximum suppression along the gradient,
normalised to [0, 1]) and the orientation from the smoothed gradients, mod pi.

In addition, :func:`instance_scale_proposals` offers boxes at the scale of the stage-I
instances of each RP (the RP's median instance width/height at a few scales, slid with
a stride of a quarter of the box size): the ablation compares ``"edgeboxes"``,
``"instance_scale"`` and ``"both"``.

All boxes here are ``[x, y, w, h]`` in *processed* pixels (float32).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from ..params import check_schema_fields, checked_mapping, config_defaults, schema_enum

PROPOSAL_METHODS: tuple[str, ...] = schema_enum("stage2", "proposals", "method")

#: The :class:`ProposalParams` field of each ``stage2.proposals`` key named otherwise.
FIELD_OF_KEY = {"max_proposals": "max_boxes", "window_scales": "scales",
                "window_stride": "stride_fraction"}
#: ``stage2.proposals`` keys that are not proposal parameters (the caller reads them).
SECTION_ONLY_KEYS = ("lattice_windows",)


@dataclass(frozen=True)
class ProposalParams:
    """Tunables of the region proposals; made by :func:`proposal_params`, which takes
    the fields the ``stage2.proposals`` configuration section sets from there (they have
    no defaults here). The EdgeBoxes internals after them are not configured.

    Attributes
    ----------
    method : str
        ``"edgeboxes"``, ``"instance_scale"`` or ``"both"``.
    edge_model_path : str or None
        Structured-edge model (``model.yml.gz``); ``None`` = computed gradient edges.
    max_boxes : int
        Most EdgeBoxes proposals (``max_proposals`` in the configuration).
    scales : tuple of float
        Instance-scale windows: multiples of the RP's median instance size
        (``window_scales``).
    stride_fraction : float
        Instance-scale windows: stride as a fraction of the window size
        (``window_stride``).
    max_windows : int
        Most instance-scale windows per RP (the stride grows to stay under it).
    lattice_neighbours : int
        Lattice windows: each instance's k nearest instances give its lattice steps.
    lattice_steps : int
        Lattice windows: extrapolate up to this many steps past an instance (m below).
    lattice_scales : tuple of float
        Lattice windows: multiples of the source instance's width and height.
    edgeboxes_alpha, edgeboxes_beta : float
        EdgeBoxes sliding-window step and NMS threshold (alpha, beta in the paper).
    edgeboxes_min_score : float
        Smallest EdgeBoxes score kept.
    min_box_side : float
        Smallest proposal side, processed pixels.
    edge_sigma : float
        Gaussian smoothing before the gradients, pixels.
    """

    method: str
    edge_model_path: str | None
    max_boxes: int
    scales: tuple[float, ...]
    stride_fraction: float
    max_windows: int
    lattice_neighbours: int
    lattice_steps: int
    lattice_scales: tuple[float, ...]
    edgeboxes_alpha: float = 0.65
    edgeboxes_beta: float = 0.75
    edgeboxes_min_score: float = 0.01
    min_box_side: float = 8.0
    edge_sigma: float = 1.0

    def __post_init__(self) -> None:
        # the fields the section sets, against its schema (keys renamed: FIELD_OF_KEY)
        check_schema_fields(self, ("stage2", "proposals"),
                            {f: k for k, f in FIELD_OF_KEY.items()})

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "ProposalParams":
        """Build from a mapping of fields (the others from the configuration, as
        :func:`proposal_params`); raises ValueError naming any unknown key."""
        d = checked_mapping(cls, d, "proposal parameter")
        for k in ("scales", "lattice_scales"):
            if k in d:
                d[k] = tuple(float(s) for s in d[k])
        return proposal_params(**d)


def proposal_params(section: Mapping[str, Any] | None = None, **fields: Any
                    ) -> ProposalParams:
    """The region-proposal parameters of a ``stage2.proposals`` configuration section:
    the one way their defaults are made.

    Parameters
    ----------
    section : mapping, optional
        ``stage2.proposals`` keys, as the configuration names them (``max_proposals``,
        ``window_scales``, ...; see :data:`FIELD_OF_KEY`); the keys it leaves out take
        the shipped configuration's values. :data:`SECTION_ONLY_KEYS` are ignored.
    **fields
        :class:`ProposalParams` fields set directly (``method="edgeboxes"``), over the
        section.

    Returns
    -------
    ProposalParams
        Raises ValueError naming an unknown key.
    """
    sec = config_defaults("stage2", "proposals")
    sec.update(section or {})
    d = {FIELD_OF_KEY.get(k, k): tuple(v) if isinstance(v, list) else v
         for k, v in sec.items() if k not in SECTION_ONLY_KEYS}
    d.update(fields)
    return ProposalParams(**checked_mapping(ProposalParams, d, "proposal parameter"))


def _check_rgb(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be an (H, W, 3) uint8 image, got shape {rgb.shape} "
                         f"dtype {rgb.dtype}")
    return rgb


def edge_and_orientation(rgb: np.ndarray, sigma: float = 1.0,
                         edge_model_path: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Edge magnitude and orientation maps for EdgeBoxes.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        Image.
    sigma : float
        Gaussian smoothing, pixels (computed edges only).
    edge_model_path : str or None
        Structured-edge model file; when given, ``detectEdges`` of that model is used.

    Returns
    -------
    edges : (H, W) float32 in [0, 1]
        Thin edge magnitude.
    orientation : (H, W) float32 in [0, pi)
        Edge orientation, radians (the gradient direction mod pi, as
        ``StructuredEdgeDetection.computeOrientation`` reports it).
    """
    import cv2

    rgb = _check_rgb(rgb)
    if edge_model_path:
        sed = cv2.ximgproc.createStructuredEdgeDetection(str(edge_model_path))
        e = sed.detectEdges(rgb.astype(np.float32) / 255.0)
        o = sed.computeOrientation(e)
        return sed.edgesNms(e, o).astype(np.float32), o.astype(np.float32)
    lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2Lab).astype(np.float32)
    if sigma > 0:
        lab = cv2.GaussianBlur(lab, (0, 0), sigma)
    gx = cv2.Scharr(lab, cv2.CV_32F, 1, 0)
    gy = cv2.Scharr(lab, cv2.CV_32F, 0, 1)
    mag2 = gx * gx + gy * gy                              # (H, W, 3)
    best = np.argmax(mag2, axis=2)[..., None]             # strongest Lab channel per pixel
    gx = np.take_along_axis(gx, best, 2)[..., 0]
    gy = np.take_along_axis(gy, best, 2)[..., 0]
    mag = np.sqrt(np.take_along_axis(mag2, best, 2)[..., 0])
    # orientation from smoothed gradients, mod pi
    sgx = cv2.GaussianBlur(gx, (0, 0), 2.0)
    sgy = cv2.GaussianBlur(gy, (0, 0), 2.0)
    theta = np.mod(np.arctan2(sgy, sgx), np.pi).astype(np.float32)
    # non-maximum suppression along the gradient (4 directions), thin edges
    q = (np.round(theta / (np.pi / 4)).astype(int)) % 4
    pad = np.pad(mag, 1, mode="edge")
    h, w = mag.shape
    keep = np.zeros_like(mag, bool)
    offs = {0: (0, 1), 1: (1, 1), 2: (1, 0), 3: (1, -1)}  # (dy, dx) along gradient
    for k, (dy, dx) in offs.items():
        a = pad[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
        b = pad[1 - dy:1 - dy + h, 1 - dx:1 - dx + w]
        keep |= (q == k) & (mag >= a) & (mag >= b)
    mag = np.where(keep, mag, 0.0)
    hi = float(np.percentile(mag[mag > 0], 99)) if np.any(mag > 0) else 0.0
    edges = np.clip(mag / hi, 0.0, 1.0).astype(np.float32) if hi > 0 else \
        np.zeros_like(mag, np.float32)
    return edges, theta


def edgeboxes_proposals(rgb: np.ndarray, params: ProposalParams | None = None
                        ) -> tuple[np.ndarray, np.ndarray]:
    """EdgeBoxes proposals.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        Processed image.
    params : ProposalParams, optional
        Default: :func:`proposal_params` (the configuration's).

    Returns
    -------
    boxes : (P, 4) float32
        ``[x, y, w, h]``, processed pixels, inside the image.
    scores : (P,) float32
        EdgeBoxes objectness scores (higher = better).
    """
    params = proposal_params() if params is None else params
    import cv2

    rgb = _check_rgb(rgb)
    h, w = rgb.shape[:2]
    key = (hashlib.sha1(np.ascontiguousarray(rgb).tobytes()).hexdigest(), rgb.shape,
           params.edge_sigma, params.edge_model_path, params.edgeboxes_alpha,
           params.edgeboxes_beta, params.edgeboxes_min_score, int(params.max_boxes),
           float(params.min_box_side))
    if key in _LAST_EDGEBOXES:  # the stage-II ablation's variants ask again for the same image
        b, s = _LAST_EDGEBOXES[key]
        return b.copy(), s.copy()
    edges, orient = edge_and_orientation(rgb, params.edge_sigma, params.edge_model_path)
    eb = cv2.ximgproc.createEdgeBoxes(alpha=params.edgeboxes_alpha, beta=params.edgeboxes_beta,
                                      minScore=params.edgeboxes_min_score,
                                      maxBoxes=int(params.max_boxes),
                                      minBoxArea=float(params.min_box_side ** 2))
    out = eb.getBoundingBoxes(edges, orient)
    boxes, scores = (out if isinstance(out, tuple) else (out, None))
    boxes = np.asarray(boxes, np.float32).reshape(-1, 4)
    scores = (np.asarray(scores, np.float32).reshape(-1) if scores is not None and len(boxes)
              else np.ones(len(boxes), np.float32))
    boxes = clip_boxes(boxes, (w, h))
    ok = (boxes[:, 2] >= params.min_box_side) & (boxes[:, 3] >= params.min_box_side)
    _LAST_EDGEBOXES.clear()
    _LAST_EDGEBOXES[key] = (boxes[ok], scores[ok])
    return boxes[ok].copy(), scores[ok].copy()


_LAST_EDGEBOXES: dict[tuple[Any, ...], tuple[np.ndarray, np.ndarray]] = {}
"""The last image's EdgeBoxes (keyed on its pixels and the parameters that act): a
process that proposes on one image several times (the stage-II ablation, one variant
after another) runs the detector once (about 3 s per 1-MP image)."""


def instance_scale_proposals(instance_boxes: np.ndarray, image_size: tuple[int, int],
                             params: ProposalParams | None = None) -> np.ndarray:
    """Sliding windows at the scale of one RP's instances.

    Parameters
    ----------
    instance_boxes : (N, 4) float
        The RP's stage-I instance boxes ``[x, y, w, h]``, processed pixels (N >= 1).
    image_size : (int, int)
        ``(width, height)`` of the processed image.
    params : ProposalParams, optional
        ``scales`` (multiples of the median instance width and height), ``stride_fraction``
        and ``max_windows``; default :func:`proposal_params`.

    Returns
    -------
    (Q, 4) float32
        Windows ``[x, y, w, h]`` wholly inside the image, processed pixels. The grid of
        each scale is anchored on the first instance so that windows aligned with the
        instance lattice are generated.
    """
    params = proposal_params() if params is None else params
    b = np.asarray(instance_boxes, np.float64).reshape(-1, 4)
    if len(b) == 0:
        return np.zeros((0, 4), np.float32)
    W, H = int(image_size[0]), int(image_size[1])
    mw, mh = float(np.median(b[:, 2])), float(np.median(b[:, 3]))
    ax, ay = float(b[0, 0]), float(b[0, 1])
    out = []
    per_scale = max(1, int(params.max_windows) // max(1, len(params.scales)))
    for s in params.scales:
        bw, bh = mw * s, mh * s
        if bw < params.min_box_side or bh < params.min_box_side or bw > W or bh > H:
            continue
        sx, sy = max(1.0, bw * params.stride_fraction), max(1.0, bh * params.stride_fraction)
        nx, ny = (W - bw) / sx + 1, (H - bh) / sy + 1
        if nx * ny > per_scale:                         # grow the stride to stay under the cap
            g = np.sqrt(nx * ny / per_scale)
            sx, sy = sx * g, sy * g
        # anchor on the (scaled) first instance centre
        cx0, cy0 = ax + b[0, 2] / 2 - bw / 2, ay + b[0, 3] / 2 - bh / 2
        xs = cx0 + sx * np.arange(np.ceil(-cx0 / sx), np.floor((W - bw - cx0) / sx) + 1)
        ys = cy0 + sy * np.arange(np.ceil(-cy0 / sy), np.floor((H - bh - cy0) / sy) + 1)
        if len(xs) == 0 or len(ys) == 0:
            continue
        gx, gy = np.meshgrid(xs, ys)
        n = gx.size
        out.append(np.stack([gx.ravel(), gy.ravel(), np.full(n, bw), np.full(n, bh)], 1))
    if not out:
        return np.zeros((0, 4), np.float32)
    return clip_boxes(np.concatenate(out).astype(np.float32), (W, H))


def lattice_proposals(instance_boxes: np.ndarray, image_size: tuple[int, int],
                      params: ProposalParams | None = None) -> np.ndarray:
    """Windows at the positions the RP's instance lattice predicts for missing instances.

    Instances of an RP lie on rows / grids (in perspective, approximately), so a missing
    instance sits one lattice step t_ij = c_i - c_j past an instance i, away from a
    neighbour j (c = box centre): c_i + m t_ij for m = 1..``lattice_steps``, or halfway
    between two neighbours (a gap of one in a row). Each window has the source
    instance's size times ``lattice_scales`` (halfway windows only for pairs 1.6 to 2.4
    lattice spacings apart, the spacing being the median nearest-instance distance); windows whose centre falls in an existing
    instance or outside the image are dropped.

    Parameters
    ----------
    instance_boxes : (N, 4) float
        The RP's stage-I instance boxes ``[x, y, w, h]``, processed pixels.
    image_size : (int, int)
        ``(width, height)`` of the processed image.
    params : ProposalParams, optional
        ``lattice_neighbours`` (k), ``lattice_steps`` (m), ``lattice_scales``; default
        :func:`proposal_params`.

    Returns
    -------
    (Q, 4) float32
        Windows ``[x, y, w, h]`` clipped to the image, processed pixels (Q = 0 when
        N < 2).
    """
    params = proposal_params() if params is None else params
    b = np.asarray(instance_boxes, np.float64).reshape(-1, 4)
    W, H = float(image_size[0]), float(image_size[1])
    if len(b) < 2:
        return np.zeros((0, 4), np.float32)
    c = b[:, :2] + b[:, 2:] / 2                                  # (N, 2) centres
    d = np.linalg.norm(c[:, None] - c[None], axis=2)
    np.fill_diagonal(d, np.inf)
    k = min(max(1, int(params.lattice_neighbours)), len(b) - 1)
    nn = np.argsort(d, axis=1, kind="stable")[:, :k]              # (N, k)
    s = float(np.median(d.min(1)))                                # lattice spacing
    cen, wh = [], []
    for i in range(len(b)):
        for j in nn[i]:
            t = c[i] - c[j]                                       # t_ij: one lattice step
            for m in range(1, int(params.lattice_steps) + 1):
                cen.append(c[i] + m * t)
                wh.append(b[i, 2:])
            if (i < j or i not in nn[j]) and 1.6 * s <= d[i, j] <= 2.4 * s:
                cen.append((c[i] + c[j]) / 2)                     # gap of one between i, j
                wh.append((b[i, 2:] + b[j, 2:]) / 2)
    cen_a, wh_a = np.array(cen), np.array(wh)
    inside = (cen_a[:, 0] >= 0) & (cen_a[:, 0] < W) & (cen_a[:, 1] >= 0) & (cen_a[:, 1] < H)
    # centre inside an existing instance: that instance is already found
    occ = ((np.abs(cen_a[:, None, 0] - c[None, :, 0]) < b[None, :, 2] / 2)
           & (np.abs(cen_a[:, None, 1] - c[None, :, 1]) < b[None, :, 3] / 2)).any(1)
    keep = inside & ~occ
    cen_a, wh_a = cen_a[keep], wh_a[keep]
    out = [np.concatenate([cen_a - wh_a * s / 2, wh_a * s], 1) for s in params.lattice_scales]
    if not out or not len(cen_a):
        return np.zeros((0, 4), np.float32)
    q = clip_boxes(np.concatenate(out).astype(np.float32), (int(W), int(H)))
    q = q[(q[:, 2] >= params.min_box_side) & (q[:, 3] >= params.min_box_side)]
    _, idx = np.unique(np.round(q * 2).astype(np.int64), axis=0, return_index=True)
    return q[np.sort(idx)]


def clip_boxes(boxes: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """Clip ``[x, y, w, h]`` boxes (N, 4) to the image ``(width, height)``."""
    b = np.asarray(boxes, np.float32).reshape(-1, 4).copy()
    W, H = float(image_size[0]), float(image_size[1])
    x0 = np.clip(b[:, 0], 0, W)
    y0 = np.clip(b[:, 1], 0, H)
    x1 = np.clip(b[:, 0] + b[:, 2], 0, W)
    y1 = np.clip(b[:, 1] + b[:, 3], 0, H)
    return np.stack([x0, y0, x1 - x0, y1 - y0], 1).astype(np.float32)


def propose(rgb: np.ndarray, rp_instance_boxes: Sequence[np.ndarray],
            params: ProposalParams | None = None) -> tuple[np.ndarray, np.ndarray]:
    """All proposals of an image for the configured ``method``.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        Processed image.
    rp_instance_boxes : list of (N_k, 4) float
        Stage-I instance boxes of each RP, processed pixels (used by instance-scale
        windows).
    params : ProposalParams, optional
        Default: :func:`proposal_params` (the configuration's).

    Returns
    -------
    boxes : (P, 4) float32
        Unique proposals ``[x, y, w, h]``, processed pixels.
    scores : (P,) float32
        EdgeBoxes score, or 0 for instance-scale windows.
    """
    params = proposal_params() if params is None else params
    rgb = _check_rgb(rgb)
    h, w = rgb.shape[:2]
    boxes, scores = [np.zeros((0, 4), np.float32)], [np.zeros((0,), np.float32)]
    if params.method in ("edgeboxes", "both"):
        b, s = edgeboxes_proposals(rgb, params)
        boxes.append(b)
        scores.append(s)
    if params.method in ("instance_scale", "both"):
        for ib in rp_instance_boxes:
            q = instance_scale_proposals(ib, (w, h), params)
            boxes.append(q)
            scores.append(np.zeros(len(q), np.float32))
    B = np.concatenate(boxes)
    S = np.concatenate(scores)
    if len(B) == 0:
        return B, S
    # exact duplicates (rounded to 0.5 px) removed, first kept
    key = np.round(B * 2).astype(np.int64)
    _, idx = np.unique(key, axis=0, return_index=True)
    idx = np.sort(idx)
    B, S = B[idx], S[idx]
    ok = (B[:, 2] >= 1) & (B[:, 3] >= 1)
    return B[ok], S[ok]
