"""Synthetic recurring-pattern benchmark with exact 3D ground truth.

Each image shows 1 to ``max_rps`` recurring patterns (RPs). An RP is a set of textured
instances (procedural shapes/stripes/glyphs or crops of photos shipped in scikit-image's
package folder; :mod:`rescu.data.textures`) laid out on a 3D plane as a *row* or a *grid*,
either equally spaced (3D translation symmetry; cross ratio of 4 consecutive instances =
4/3) or, as negatives, with clearly unequal spacing. The planes are rendered by a pinhole
camera: a *frontal* subset (plane parallel to the image: row vanishing points at infinity)
and a *projective* subset (plane tilted by 30-65 degrees: finite row VP, often outside the
image). Non-recurring clutter, lighting gradients, noise and, in the *hard* images, partial
occlusion and blur are added.

Geometry (:mod:`rescu.data.camera`; camera frame: x right, y down, z forward; pixels as
in :mod:`rescu.types`):

* plane points ``X = (u, v, 0)``; camera points ``X_c = R X + t``;
* ``K = [[f, 0, c_x], [0, f, c_y], [0, 0, 1]]``; image point ``x ~ K X_c``;
* plane -> image homography ``H = K [r_1 r_2 t]``;
* rows run along the plane axis ``d = (1, 0, 0)``; their vanishing point is
  ``v = K R d`` (homogeneous, unit norm, ``w = 0`` for frontal planes).

Outputs of :func:`generate_dataset` (``out_dir``)::

    images/synth_XXXX.png
    annotations.json      COCO; one category per RP per image ("synth_0003_rp1")
    vanishing_points.json shared format; one VP per row direction of projective RPs
    truth.json            per image: subset, hard, K, patterns (count, layout,
                          equal_spacing, translation_symmetry, rows, vanishing_point,
                          plane normal, R, t, per-instance centre/quad/visibility)

Every image ``i`` is drawn from its own generator ``np.random.default_rng([seed, i])``
so image ``i`` does not depend on ``n_images``; the frontal/projective and hard/easy
assignment uses low-discrepancy sequences of ``i`` so every few consecutive images
contain both kinds.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..params import config_section, params_from_dict
from ..scene.symmetry import CR_EQUAL_SPACING, row_cross_ratios
from .camera import (camera_matrix, plane_homography, project_points, rotation_matrix,
                     row_vanishing_point)
from .textures import (available_photos, photo_texture, procedural_texture, rand_colour,
                       silhouette, textured)

__all__ = [
    "SynthParams", "SynthImage", "synthetic_image_names", "generate_dataset",
    "render_synthetic_image",
]


_GOLDEN = 0.6180339887498949      # subset assignment sequence (frac(i * phi))
_SQRT3M1 = 0.7320508075688772     # hard assignment sequence (frac(i * (sqrt 3 - 1)))


# ============================================================================ params
#: An integer ``(min, max)`` range of :class:`SynthParams`, drawn from uniformly.
IntRange = tuple[int, int]
#: A real ``(min, max)`` range of :class:`SynthParams`, drawn from uniformly.
FloatRange = tuple[float, float]


def _range2(name: str, v: Any, integer: bool = False) -> tuple[Any, Any]:
    """The pair ``v`` as ``(min, max)`` of ints or floats; ValueError unless min <= max
    (the schema bounds each value)."""
    try:
        a, b = v
    except (TypeError, ValueError):
        raise ValueError(f"SynthParams.{name} must be a pair [min, max], got {v!r}") from None
    if integer:
        if int(a) != a or int(b) != b:
            raise ValueError(f"SynthParams.{name} must hold integers, got {v!r}")
        a, b = int(a), int(b)
    else:
        a, b = float(a), float(b)
    if a > b:
        raise ValueError(f"SynthParams.{name} must satisfy min <= max, got {v!r}")
    return a, b


@dataclass(frozen=True)
@config_section("synthetic")
class SynthParams:
    """Parameters of the synthetic benchmark (every tunable has a default).

    Ranges (:data:`IntRange`, :data:`FloatRange`) are ``(min, max)`` pairs, drawn
    uniformly per image / pattern / instance. The defaults, and what each field means,
    are the ``synthetic`` section of the shipped configuration (``rescu/defaults/config.yaml``).
    """

    n_images: int
    seed: int
    sizes: tuple[tuple[int, int], ...]
    projective_fraction: float
    min_rps: int
    max_rps: int
    grid_fraction: float
    unequal_fraction: float
    unequal_min_change: float
    hard_fraction: float
    photo_fraction: float
    row_length: IntRange
    grid_rows: IntRange
    grid_cols: IntRange
    instance_px: FloatRange
    aspect: FloatRange
    gap: FloatRange
    focal: FloatRange
    tilt_deg: FloatRange
    frontal_roll_deg: float
    shared_plane_prob: float
    texture_px: int
    colour_jitter: float
    light_jitter: float
    deform: float
    lighting_gradient: float
    noise_sigma: float
    blur_sigma: FloatRange
    occluded_instances: IntRange
    occlusion_fraction: FloatRange
    n_blobs: IntRange
    n_lines: IntRange
    n_distractors: IntRange

    def __post_init__(self) -> None:
        try:
            sizes = tuple((int(w), int(h)) for w, h in self.sizes)
        except (TypeError, ValueError):
            raise ValueError(f"SynthParams.sizes must be a list of [width, height], "
                             f"got {self.sizes!r}") from None
        object.__setattr__(self, "sizes", sizes)
        for name in ("projective_fraction", "grid_fraction", "unequal_fraction",
                     "hard_fraction", "photo_fraction", "shared_plane_prob"):
            object.__setattr__(self, name, float(getattr(self, name)))
        if self.min_rps > self.max_rps:
            raise ValueError(f"SynthParams needs min_rps <= max_rps, got "
                             f"min_rps={self.min_rps!r}, max_rps={self.max_rps!r}")
        for name in ("row_length", "grid_rows", "grid_cols", "occluded_instances", "n_blobs",
                     "n_lines", "n_distractors"):
            object.__setattr__(self, name, _range2(name, getattr(self, name), True))
        for name in ("instance_px", "aspect", "gap", "focal", "tilt_deg", "blur_sigma",
                     "occlusion_fraction"):
            object.__setattr__(self, name, _range2(name, getattr(self, name)))
        for name in ("unequal_min_change", "frontal_roll_deg", "colour_jitter",
                     "light_jitter", "deform", "lighting_gradient", "noise_sigma"):
            object.__setattr__(self, name, float(getattr(self, name)))

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "SynthParams":
        """Build from a mapping (e.g. a YAML section); raises ValueError naming any
        unknown key. Lists are accepted for the pair/list fields."""
        return params_from_dict(cls, d)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able mapping (pairs as lists)."""
        out = asdict(self)
        return {k: ([list(x) for x in v] if k == "sizes" else
                    list(v) if isinstance(v, tuple) else v) for k, v in out.items()}


def synthetic_image_names(n_images: int) -> list[str]:
    """File names of the images :func:`generate_dataset` writes: ``synth_0000.png`` ...

    Parameters
    ----------
    n_images : int
        Number of images, >= 0.
    """
    if int(n_images) != n_images or n_images < 0:
        raise ValueError(f"n_images must be a non-negative integer, got {n_images!r}")
    return [f"synth_{i:04d}.png" for i in range(int(n_images))]


# ============================================================================ geometry


# ============================================================================ textures


# ============================================================================ layouts
def _unequal_positions(rng: np.random.Generator, n: int, pitch0: float, change: float
                       ) -> np.ndarray:
    """n positions (plane units) whose consecutive spacings differ by >= ``change``
    (relative) and whose consecutive 4-tuples all have a cross ratio far from 4/3."""
    lo, hi = pitch0, pitch0 * 3.2
    for _ in range(200):
        p = [pitch0 * rng.uniform(1.0, 1.6)]
        for _k in range(n - 2):
            r = rng.uniform(1.0 + change, 1.0 + change + 0.6)
            up = rng.random() < 0.5
            cand = p[-1] * r if up else p[-1] / r
            if not lo <= cand <= hi:
                cand = p[-1] / r if up else p[-1] * r
            if not lo <= cand <= hi:
                break
            p.append(cand)
        if len(p) != n - 1:
            continue
        x = np.concatenate([[0.0], np.cumsum(p)])
        cr = row_cross_ratios(np.column_stack([x, np.zeros_like(x)]))
        ok = bool(np.all(np.abs(cr - CR_EQUAL_SPACING) > 0.08))
        if ok:
            return x
    raise RuntimeError("could not draw an unequally spaced row")  # pragma: no cover


@dataclass
class _Layout:
    kind: str                     # "row" | "grid"
    centres: np.ndarray           # (N, 2) plane units
    row_of: np.ndarray            # (N,) int
    col_of: np.ndarray            # (N,) int
    size: tuple[float, float]     # instance (width, height), plane units
    equal: bool
    pitches: list[float]          # spacings along the rows, plane units


def _draw_layout(rng: np.random.Generator, p: SynthParams, grid: bool, equal: bool,
                 n_cols: int, n_rows: int) -> _Layout:
    asp = rng.uniform(*p.aspect)
    size = (asp, 1.0)
    if equal:
        pitch = asp * (1.0 + rng.uniform(*p.gap))
        xs = np.arange(n_cols) * pitch
    else:
        xs = _unequal_positions(rng, n_cols, asp * (1.0 + p.gap[0]), p.unequal_min_change)
    ys = np.arange(n_rows) * (1.0 + rng.uniform(*p.gap)) if grid else np.zeros(1)
    xx, yy = np.meshgrid(xs, ys)
    rr, cc = np.meshgrid(np.arange(n_cols), np.arange(len(ys)))[::-1]
    cen = np.column_stack([xx.ravel(), yy.ravel()])
    cen -= (cen.min(0) + cen.max(0)) / 2
    return _Layout("grid" if grid else "row", cen, rr.ravel(), cc.ravel(), size, equal,
                   [float(v) for v in np.diff(xs)])


# ============================================================================ scene
@dataclass
class _Placed:
    layout: _Layout
    R: np.ndarray
    t: np.ndarray
    quads: np.ndarray             # (N, 4, 2) px, undeformed instance rectangles
    centres_px: np.ndarray        # (N, 2) px


def _regions(rng: np.random.Generator, n: int, w: int, h: int) -> list[tuple[float, ...]]:
    """Split the image into n disjoint rectangles (x0, y0, x1, y1), with margins."""
    m = 0.03 * min(w, h)
    X, Y = (m, w - m), (m, h - m)

    def split(a: tuple[float, float], k: int) -> list[tuple[float, float]]:
        e = np.linspace(a[0], a[1], k + 1)
        return [(e[i] + (m / 2 if i else 0), e[i + 1] - (m / 2 if i < k - 1 else 0))
                for i in range(k)]

    if n == 1:
        regs = [(X[0], Y[0], X[1], Y[1])]
    elif n == 2:
        if rng.random() < 0.6:
            regs = [(X[0], a, X[1], b) for a, b in split(Y, 2)]
        else:
            regs = [(a, Y[0], b, Y[1]) for a, b in split(X, 2)]
    elif n == 3:
        c = rng.random()
        if c < 0.4:
            regs = [(X[0], a, X[1], b) for a, b in split(Y, 3)]
        else:
            (ya, yb), (yc, yd) = split(Y, 2)
            (xa, xb), (xc, xd) = split(X, 2)
            regs = [(X[0], ya, X[1], yb), (xa, yc, xb, yd), (xc, yc, xd, yd)]
            if c > 0.7:
                regs = [(X[0], yc, X[1], yd), (xa, ya, xb, yb), (xc, ya, xd, yb)]
    else:
        cols = 2 if n <= 4 else 3
        rows = int(math.ceil(n / cols))
        regs = [(xa, ya, xb, yb) for ya, yb in split(Y, rows) for xa, xb in split(X, cols)]
        regs = regs[:n]
    order = rng.permutation(len(regs))
    return [tuple(float(v) for v in regs[i]) for i in order]


def _plane_rotation(rng: np.random.Generator, p: SynthParams, projective: bool
                    ) -> np.ndarray:
    """R (3, 3): frontal = small roll; projective = tilt 30-65 deg about an image axis
    (mostly vertical: facade-like; else horizontal: floor-like), rows receding."""
    if not projective:
        return rotation_matrix((0, 0, 1), math.radians(rng.uniform(-1, 1) * p.frontal_roll_deg))
    if rng.random() < 0.7:
        phi = math.radians(90.0 + rng.uniform(-15, 15))
    else:
        phi = math.radians(rng.uniform(-15, 15))
    axis = (math.cos(phi), math.sin(phi), 0.0)
    psi = phi - math.pi / 2 + math.radians(rng.uniform(-8, 8))
    theta = math.radians(rng.uniform(*p.tilt_deg)) * (1 if rng.random() < 0.5 else -1)
    return rotation_matrix(axis, theta) @ rotation_matrix((0, 0, 1), psi)


def _quads(lay: _Layout) -> np.ndarray:
    """(N, 4, 2) plane corners TL, TR, BR, BL of every instance."""
    hw, hh = lay.size[0] / 2, lay.size[1] / 2
    off = np.array([[-hw, -hh], [hw, -hh], [hw, hh], [-hw, hh]])
    return lay.centres[:, None, :] + off[None]


def _place(rng: np.random.Generator, p: SynthParams, K: np.ndarray, region: tuple[float, ...],
           R: np.ndarray, lay: _Layout) -> _Placed | None:
    """Choose t so the layout's projection fits the region with instance sizes in range;
    None if impossible."""
    x0, y0, x1, y1 = region
    rw, rh = x1 - x0, y1 - y0
    f = K[0, 0]
    lo_px, hi_px = p.instance_px
    s_px = rng.uniform(lo_px * 1.35, max(lo_px * 1.35, min(hi_px * 0.8, 0.6 * min(rw, rh))))
    Z = f / s_px
    ray = np.linalg.solve(K, [(x0 + x1) / 2, (y0 + y1) / 2, 1.0])
    t = ray * Z
    q3 = np.concatenate([_quads(lay).reshape(-1, 2), np.zeros((len(lay.centres) * 4, 1))], 1)
    ok = False
    for _ in range(16):
        xc = q3 @ R.T + t
        if xc[:, 2].min() < 0.25 * t[2]:
            t = t * 1.5
            continue
        pts = project_points(K, R, t, q3)
        bx0, by0 = pts.min(0)
        bx1, by1 = pts.max(0)
        k = max((bx1 - bx0) / rw, (by1 - by0) / rh)         # > 1: layout too big
        ext = pts.reshape(-1, 4, 2).max(1) - pts.reshape(-1, 4, 2).min(1)
        zoom = s_px / float(np.median(np.sqrt(ext.prod(1))))  # > 1: instances too small
        zoom = min(zoom, 0.97 / k)
        inside = bx0 >= x0 and by0 >= y0 and bx1 <= x1 and by1 <= y1
        if inside and k <= 1.0 and abs(zoom - 1.0) < 0.05:
            ok = True
            break
        t = t / zoom
        dx, dy = (x0 + x1) / 2 - (bx0 + bx1) / 2, (y0 + y1) / 2 - (by0 + by1) / 2
        t = t + np.array([dx * t[2] / f, dy * t[2] / f, 0.0]) * (1.0 / zoom if zoom < 1 else 1)
    if not ok:
        return None
    quads = project_points(K, R, t, q3).reshape(-1, 4, 2)
    ext = quads.max(1) - quads.min(1)
    if (ext.max(1).min() < lo_px * (1 + 2 * p.deform) or ext.max() > hi_px * (1 - 2 * p.deform)
            or np.sqrt(ext.prod(1)).min() < 0.8 * lo_px):
        return None
    cen = project_points(K, R, t, lay.centres)
    return _Placed(lay, R, t, quads, cen)


def _design_rp(rng: np.random.Generator, p: SynthParams, K: np.ndarray,
               region: tuple[float, ...], R: np.ndarray, projective: bool
               ) -> _Placed | None:
    """Draw a layout and place it in ``region``; after 12 failed attempts with the given
    plane rotation R, a new rotation is drawn every 6 attempts (e.g. a floor-like plane
    whose rows run vertically does not fit a wide, low region)."""
    grid = rng.random() < p.grid_fraction
    equal = rng.random() >= p.unequal_fraction
    for attempt in range(36):
        if attempt >= 12 and attempt % 6 == 0:
            R = _plane_rotation(rng, p, projective)
        g = grid and attempt % 12 < 6
        if g:
            n_rows = int(rng.integers(p.grid_rows[0], p.grid_rows[1] + 1))
            n_cols = int(rng.integers(p.grid_cols[0], p.grid_cols[1] + 1))
        else:
            n_rows = 1
            hi = p.row_length[1] - (attempt % 12) // 3
            n_cols = int(rng.integers(p.row_length[0], max(p.row_length[0], hi) + 1))
        if not equal:
            n_cols = max(n_cols, 4)   # the cross-ratio negative needs 4 instances
        lay = _draw_layout(rng, p, g, equal, n_cols, n_rows)
        placed = _place(rng, p, K, region, R, lay)
        if placed is not None:
            return placed
    return None


# ============================================================================ rendering
def _background(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """Smooth noise texture (h, w, 3) float32 between two random colours."""
    import cv2

    c0 = np.array(rand_colour(rng), np.float32) * rng.uniform(0.4, 0.9)
    c1 = np.array(rand_colour(rng), np.float32) * rng.uniform(0.4, 0.9)
    low = rng.random((max(2, h // 64), max(2, w // 64))).astype(np.float32)
    mid = rng.random((max(2, h // 12), max(2, w // 12))).astype(np.float32)
    a = cv2.resize(low, (w, h), interpolation=cv2.INTER_CUBIC)
    b = cv2.resize(mid, (w, h), interpolation=cv2.INTER_CUBIC)
    mix = np.clip(0.75 * a + 0.25 * b, 0, 1)[..., None]
    return c0 * (1 - mix) + c1 * mix


def _add_clutter(rng: np.random.Generator, p: SynthParams, img: np.ndarray) -> None:
    """Unique blobs and line segments (non-recurring clutter), in place on float32 img."""
    import cv2

    h, w = img.shape[:2]
    s = min(w, h)
    for _ in range(int(rng.integers(p.n_blobs[0], p.n_blobs[1] + 1))):
        col = tuple(float(c) for c in rand_colour(rng))
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        if rng.random() < 0.5:
            ax = (int(rng.integers(s // 40, s // 8)), int(rng.integers(s // 40, s // 8)))
            cv2.ellipse(img, c, ax, float(rng.uniform(0, 180)), 0, 360, col, -1, cv2.LINE_AA)
        else:
            r = int(rng.integers(s // 30, s // 8))
            k = int(rng.integers(3, 8))
            ang = np.sort(rng.uniform(0, 2 * np.pi, k))
            rad = r * rng.uniform(0.4, 1.0, k)
            pts = np.stack([c[0] + rad * np.cos(ang), c[1] + rad * np.sin(ang)], 1)
            cv2.fillPoly(img, [pts.astype(np.int32)], col, cv2.LINE_AA)
    for _ in range(int(rng.integers(p.n_lines[0], p.n_lines[1] + 1))):
        col = tuple(float(c) for c in rand_colour(rng))
        a = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        b = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        cv2.line(img, a, b, col, int(rng.integers(1, 5)), cv2.LINE_AA)


def _composite(img: np.ndarray, owner: np.ndarray, label: int, tex: np.ndarray,
               mask: np.ndarray, M: np.ndarray, box: tuple[int, int, int, int]) -> int:
    """Warp texture (and its alpha mask) with M (texture index -> image index coords)
    into the ROI ``box = (x0, y0, x1, y1)`` of img; returns covered pixel count."""
    import cv2

    x0, y0, x1, y1 = box
    if x1 <= x0 or y1 <= y0:
        return 0
    T = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1]], float)
    Mr = T @ M
    size = (x1 - x0, y1 - y0)
    wt = cv2.warpPerspective(tex, Mr, size, flags=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REPLICATE).astype(np.float32)
    wa = cv2.warpPerspective(mask, Mr, size, flags=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=0)[..., None]
    roi = img[y0:y1, x0:x1]
    roi *= 1.0 - wa
    roi += wt * wa
    cov = wa[..., 0] > 0.5
    owner[y0:y1, x0:x1][cov] = label
    return int(cov.sum())


_HALF = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]], float)      # index -> continuous
_UNHALF = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1]], float)   # continuous -> index


def _roi(pts: np.ndarray, w: int, h: int, pad: int = 2) -> tuple[int, int, int, int]:
    x0, y0 = np.floor(pts.min(0)).astype(int) - pad
    x1, y1 = np.ceil(pts.max(0)).astype(int) + pad
    return max(0, x0), max(0, y0), min(w, x1), min(h, y1)


@dataclass
class SynthImage:
    """One rendered synthetic image and its ground truth.

    Attributes
    ----------
    rgb : (H, W, 3) uint8
        The image.
    truth : dict
        The truth.json record of the image (see module docstring).
    annotations : list of dict
        COCO annotations (bbox ``[x, y, w, h]`` px, category_id, image_id, id ...).
    categories : list of dict
        COCO categories, one per RP.
    vanishing_points : dict
        The vanishing_points.json record of the image.
    """

    rgb: np.ndarray
    truth: dict[str, Any]
    annotations: list[dict[str, Any]] = field(default_factory=list)
    categories: list[dict[str, Any]] = field(default_factory=list)
    vanishing_points: dict[str, Any] = field(default_factory=dict)


def _r(x: Any, nd: int = 6) -> Any:
    """Round floats (recursively) for stable, compact JSON."""
    if isinstance(x, np.ndarray):
        x = x.tolist()
    if isinstance(x, (list, tuple)):
        return [_r(v, nd) for v in x]
    if isinstance(x, (float, np.floating)):
        v = round(float(x), nd)
        return 0.0 if v == 0 else v
    if isinstance(x, np.integer):
        return int(x)
    return x


def render_synthetic_image(params: SynthParams, index: int) -> SynthImage:
    """Render image ``index`` of the benchmark (independent of ``params.n_images``).

    Parameters
    ----------
    params : SynthParams
    index : int
        Image index >= 0; the image is drawn from ``default_rng([params.seed, index])``.

    Returns
    -------
    SynthImage
    """
    import cv2

    if not isinstance(params, SynthParams):
        raise ValueError(f"params must be a SynthParams, got {type(params).__name__}")
    if int(index) != index or index < 0:
        raise ValueError(f"index must be a non-negative integer, got {index!r}")
    p, i = params, int(index)
    rng = np.random.default_rng([int(p.seed), i])
    projective = ((i * _GOLDEN + 0.5) % 1.0) < p.projective_fraction
    hard = ((i * _SQRT3M1 + 0.5) % 1.0) < p.hard_fraction
    w, h = p.sizes[int(rng.integers(0, len(p.sizes)))]
    f = float(rng.uniform(*p.focal) * w)
    K = camera_matrix(f, w / 2.0, h / 2.0)
    name = synthetic_image_names(i + 1)[i]
    file_name = f"images/{name}"

    # ---- geometry of the recurring patterns
    n_rp = int(rng.integers(p.min_rps, p.max_rps + 1))
    regions = _regions(rng, n_rp, w, h)
    R_shared = _plane_rotation(rng, p, projective)
    shared = projective and rng.random() < p.shared_plane_prob
    placed: list[_Placed] = []
    for k_reg, reg in enumerate(regions):
        if projective and (shared or k_reg == 0):
            R = R_shared
        else:  # frontal planes each get their own small roll
            R = _plane_rotation(rng, p, projective)
        pl = _design_rp(rng, p, K, reg, R, projective)
        if pl is not None:
            placed.append(pl)
    if not placed:  # pragma: no cover - the full image always fits a small row
        raise RuntimeError(f"image {i}: no recurring pattern could be placed")

    # ---- textures, one per RP, distinct sources
    photos = list(available_photos())
    rng.shuffle(photos)
    tex_list = []
    for _k, pl in enumerate(placed):
        th = p.texture_px
        tw = max(8, int(round(th * pl.layout.size[0] / pl.layout.size[1])))
        if photos and rng.random() < p.photo_fraction:
            src = photos.pop()
            tex = textured(lambda: photo_texture(rng, src, tw, th), 8)
            if rng.random() < 0.5:
                cv2.rectangle(tex, (0, 0), (tw - 1, th - 1), rand_colour(rng),
                              max(2, th // 30))
        else:
            src = "procedural"
            tex = textured(lambda: procedural_texture(rng, tw, th), 4)
        outline = silhouette(rng, tw, th)
        tex_list.append((src, tex, outline))

    # ---- background and clutter
    img = _background(rng, w, h)
    _add_clutter(rng, p, img)
    owner = np.full((h, w), -1, np.int32)
    rp_boxes = [np.concatenate([pl.quads.reshape(-1, 2).min(0), pl.quads.reshape(-1, 2).max(0)])
                for pl in placed]
    s = min(w, h)
    for _ in range(int(rng.integers(p.n_distractors[0], p.n_distractors[1] + 1))):
        for _try in range(15):
            dw = int(rng.uniform(p.instance_px[0], min(p.instance_px[1], s * 0.3)))
            dh = int(dw * rng.uniform(0.7, 1.4))
            dx, dy = int(rng.integers(0, max(1, w - dw))), int(rng.integers(0, max(1, h - dh)))
            if all(dx + dw < b[0] - 4 or dx > b[2] + 4 or dy + dh < b[1] - 4 or dy > b[3] + 4
                   for b in rp_boxes):
                dtex = procedural_texture(rng, dw, dh).astype(np.float32)
                img[dy:dy + dh, dx:dx + dw] = dtex[:min(dh, h - dy), :min(dw, w - dx)]
                rp_boxes.append(np.array([dx, dy, dx + dw, dy + dh], float))
                break

    # ---- instances
    anns: list[dict[str, Any]] = []
    cats: list[dict[str, Any]] = []
    pat_truth: list[dict[str, Any]] = []
    vps: list[dict[str, Any]] = []
    inst_records: list[tuple[int, int, dict[str, Any], dict[str, Any]]] = []
    label = 0
    for k, (pl, (src, tex, outline)) in enumerate(zip(placed, tex_list)):
        lay = pl.layout
        th, tw = tex.shape[:2]
        cid = i * 16 + k + 1
        cname = f"{name[:-4]}_rp{k + 1}"
        cats.append({"id": cid, "name": cname, "supercategory": "recurring_pattern"})
        mask_full = np.zeros((th, tw), np.uint8)
        cv2.fillPoly(mask_full, [np.round((outline - 0.5) * 16).astype(np.int32)], 255,
                     cv2.LINE_AA, shift=4)
        H = plane_homography(K, pl.R, pl.t)
        ids = []
        for n in range(len(lay.centres)):
            uc, vc = lay.centres[n]
            sw, sh = lay.size
            # texture continuous px -> plane units (S), per-instance deformation A
            S = np.array([[sw / tw, 0, uc - sw / 2], [0, sh / th, vc - sh / 2], [0, 0, 1]])
            d = p.deform
            a = math.radians(rng.uniform(-2, 2))
            L = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]) @ \
                np.array([[1 + rng.uniform(-d, d), rng.uniform(-d, d)],
                          [rng.uniform(-d, d), 1 + rng.uniform(-d, d)]])
            c = np.array([tw / 2, th / 2])
            A = np.eye(3)
            A[:2, :2] = L
            A[:2, 2] = c - L @ c
            Mc = H @ S @ A                      # texture continuous -> image continuous
            ol = np.column_stack([outline, np.ones(len(outline))]) @ Mc.T
            ol = ol[:, :2] / ol[:, 2:3]
            # appearance jitter: colour gain, brightness, lighting ramp
            gain = (1 + rng.uniform(-p.colour_jitter, p.colour_jitter, 3)) * \
                (1 + rng.uniform(-p.light_jitter, p.light_jitter))
            ang = rng.uniform(0, 2 * np.pi)
            g = rng.uniform(0, p.light_jitter)
            yy, xx = np.mgrid[0:th, 0:tw].astype(np.float32)
            ramp = 1 + g * (((xx - tw / 2) * math.cos(ang) + (yy - th / 2) * math.sin(ang))
                            / max(tw, th))
            itex = tex.astype(np.float32) * (ramp[..., None] * gain[None, None, :]
                                             ).astype(np.float32)
            imask = mask_full.astype(np.float32) / 255.0
            # pre-shrink the texture so warping does not alias
            side = float((ol.max(0) - ol.min(0)).max())
            shrink = min(1.0, 1.25 * side / max(th, tw))
            Mcv = _UNHALF @ Mc @ _HALF
            if shrink < 0.8:
                nw, nh = max(4, int(round(tw * shrink))), max(4, int(round(th * shrink)))
                itex = cv2.resize(itex, (nw, nh), interpolation=cv2.INTER_AREA)
                imask = cv2.resize(imask, (nw, nh), interpolation=cv2.INTER_AREA)
                D = np.diag([tw / nw, th / nh, 1.0])
                Mcv = _UNHALF @ Mc @ D @ _HALF
            itex = np.clip(itex, 0, 255)
            box = _roi(ol, w, h)
            area = _composite(img, owner, label, itex, imask, Mcv, box)
            bx0, by0 = np.clip(ol.min(0), 0, [w, h])
            bx1, by1 = np.clip(ol.max(0), 0, [w, h])
            aid = i * 1000 + len(anns) + 1
            ann = {"id": aid, "image_id": i, "category_id": cid,
                   "bbox": _r([bx0, by0, bx1 - bx0, by1 - by0], 3),
                   "area": _r((bx1 - bx0) * (by1 - by0), 3), "iscrowd": 0,
                   "segmentation": [_r(ol.reshape(-1), 2)]}
            anns.append(ann)
            ids.append(aid)
            irec = {"id": aid, "row": int(lay.row_of[n]), "col": int(lay.col_of[n]),
                    "center": _r(pl.centres_px[n]), "quad": _r(pl.quads[n]),
                    "plane_center": _r(lay.centres[n]), "occluded_fraction": 0.0}
            inst_records.append((label, area, irec, ann))
            label += 1
        rows = [[ids[n] for n in np.flatnonzero(lay.row_of == r)[np.argsort(
            lay.col_of[lay.row_of == r])]] for r in range(int(lay.row_of.max()) + 1)]
        vp, direc = row_vanishing_point(K, pl.R)
        normal = pl.R[:, 2]  # plane normal, camera frame
        pat_truth.append({
            "category_id": cid, "category": cname, "count": len(ids), "layout": lay.kind,
            "equal_spacing": bool(lay.equal), "translation_symmetry": bool(lay.equal),
            "rows": rows, "vanishing_point": _r(vp, 9), "row_direction": _r(direc, 9),
            "plane_normal": _r(normal, 9), "R": _r(pl.R, 9), "t": _r(pl.t, 9),
            "instance_size": _r(lay.size), "pitches": _r(lay.pitches), "texture": src,
            "instances": [r[2] for r in inst_records[-len(ids):]],
        })
        if projective and not any(abs(float(np.dot(direc, np.asarray(v["direction"])))) >
                                  math.cos(math.radians(0.1)) for v in vps):
            vps.append({"direction": _r(direc, 9), "homogeneous": _r(vp, 9)})

    # ---- occluders (hard images)
    if hard and inst_records:
        n_occ = min(len(inst_records),
                    int(rng.integers(p.occluded_instances[0], p.occluded_instances[1] + 1)))
        for j in rng.choice(len(inst_records), n_occ, replace=False):
            bx, by, bw, bh = inst_records[int(j)][3]["bbox"]
            frac = rng.uniform(*p.occlusion_fraction)
            side = int(rng.integers(0, 4))
            if side == 0:
                r0 = (bx, by, bx + bw * frac, by + bh)
            elif side == 1:
                r0 = (bx + bw * (1 - frac), by, bx + bw, by + bh)
            elif side == 2:
                r0 = (bx, by, bx + bw, by + bh * frac)
            else:
                r0 = (bx, by + bh * (1 - frac), bx + bw, by + bh)
            x0o, y0o = int(round(r0[0])), int(round(r0[1]))
            x1o, y1o = int(round(r0[2])), int(round(r0[3]))
            if x1o - x0o < 2 or y1o - y0o < 2:
                continue
            occ = procedural_texture(rng, x1o - x0o, y1o - y0o).astype(np.float32)
            occ = 0.35 * occ + 0.65 * np.array(rand_colour(rng), np.float32)
            img[y0o:y1o, x0o:x1o] = occ
            owner[y0o:y1o, x0o:x1o] = -2
    counts = np.bincount(owner[owner >= 0].ravel(), minlength=max(1, label))
    for lab, area, irec, _ann in inst_records:
        vis = float(counts[lab]) / area if area else 0.0
        irec["occluded_fraction"] = _r(max(0.0, 1.0 - vis), 4)

    # ---- photometric: lighting gradient, blur (hard), noise
    ang = rng.uniform(0, 2 * np.pi)
    gmag = rng.uniform(0, p.lighting_gradient)
    xs = (np.arange(w, dtype=np.float32) - w / 2) * math.cos(ang)
    ys = (np.arange(h, dtype=np.float32) - h / 2) * math.sin(ang)
    light = 1.0 + gmag * (ys[:, None] + xs[None, :]) / math.hypot(w, h)
    img *= light[..., None]
    blur = 0.0
    if hard:
        blur = float(rng.uniform(*p.blur_sigma))
        if blur > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur)
    if p.noise_sigma > 0:
        img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(p.noise_sigma)
    rgb = np.clip(img + 0.5, 0, 255).astype(np.uint8)

    truth = {"file_name": file_name, "width": w, "height": h,
             "subset": "projective" if projective else "frontal", "hard": bool(hard),
             "K": _r(K, 6), "focal_px": _r(f, 6), "principal_point": [w / 2.0, h / 2.0],
             "blur_sigma": _r(blur, 4), "noise_sigma": p.noise_sigma, "patterns": pat_truth}
    vrec = {"file_name": file_name, "width": w, "height": h, "focal_px": _r(f, 6),
            "principal_point": [w / 2.0, h / 2.0], "vanishing_points": vps}
    return SynthImage(rgb, truth, anns, cats, vrec)


# ============================================================================ dataset
def generate_dataset(out_dir: str | os.PathLike[str], params: SynthParams | None = None
                     ) -> None:
    """Write the synthetic benchmark to ``out_dir`` (see module docstring for layout).

    Writes ``images/synth_XXXX.png`` (one per index ``0 .. n_images-1``),
    ``annotations.json`` (COCO), ``vanishing_points.json`` and ``truth.json``, all
    atomically (:mod:`rescu.io`). Deterministic: same params => identical bytes.

    Parameters
    ----------
    out_dir : path
        Destination folder (created if missing).
    params : SynthParams, optional
        Defaults to ``SynthParams()``.
    """
    from ..io import write_image, write_json

    p = params if params is not None else SynthParams()
    if not isinstance(p, SynthParams):
        raise ValueError(f"params must be a SynthParams, got {type(p).__name__}")
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    coco: dict[str, Any] = {"info": {"description": "RESCU synthetic recurring-pattern "
                                     "benchmark", "params": p.to_dict()},
                            "images": [], "annotations": [], "categories": []}
    truth: dict[str, Any] = {"params": p.to_dict(), "images": []}
    vpj: dict[str, Any] = {"images": []}
    for i in range(p.n_images):
        s = render_synthetic_image(p, i)
        write_image(out / s.truth["file_name"], s.rgb)
        coco["images"].append({"id": i, "file_name": s.truth["file_name"],
                               "width": s.truth["width"], "height": s.truth["height"]})
        coco["annotations"].extend(s.annotations)
        coco["categories"].extend(s.categories)
        truth["images"].append(s.truth)
        vpj["images"].append(s.vanishing_points)
    write_json(out / "annotations.json", coco)
    write_json(out / "vanishing_points.json", vpj)
    write_json(out / "truth.json", truth)
