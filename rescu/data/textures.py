"""Instance textures and silhouettes of the synthetic benchmark.

Procedural textures (shapes, stripes, glyphs) and crops of the photos shipped in
scikit-image's package folder (:data:`PHOTO_TEXTURES`, read from disk, none fetched),
kept only when textured enough for SIFT; silhouettes cut instances out of them. Every
function draws from the generator it is given, so an image stays a function of its
seed.
"""

from __future__ import annotations

import os
from functools import lru_cache
from typing import Any

import numpy as np


#: Photos inside scikit-image's package folder used as instance textures (read
#: directly from disk; none is fetched).
PHOTO_TEXTURES: tuple[str, ...] = (
    "astronaut.png", "coffee.png", "chelsea.png", "rocket.jpg", "brick.png", "coins.png",
    "camera.png", "grass.png", "gravel.png", "motorcycle_left.png",
    "hubble_deep_field.jpg", "ihc.png", "page.png", "text.png", "logo.png",
)


@lru_cache(maxsize=None)
def _photo(name: str) -> np.ndarray:
    """An RGB uint8 photo from scikit-image's package folder (read-only, cached)."""
    import cv2
    import skimage.data

    path = os.path.join(os.path.dirname(skimage.data.__file__), name)
    im = cv2.imread(path, cv2.IMREAD_COLOR)
    if im is None:
        raise FileNotFoundError(f"{path}: photo missing from scikit-image's package folder")
    im = cv2.cvtColor(im, cv2.COLOR_BGR2RGB)
    im.setflags(write=False)
    return im


def available_photos() -> tuple[str, ...]:
    import skimage.data

    d = os.path.dirname(skimage.data.__file__)
    return tuple(n for n in PHOTO_TEXTURES if os.path.exists(os.path.join(d, n)))


def rand_colour(rng: np.random.Generator) -> tuple[int, int, int]:
    import cv2

    hsv = np.uint8([[[rng.integers(0, 180), rng.integers(90, 256), rng.integers(60, 256)]]])
    return tuple(int(c) for c in cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0])


def procedural_texture(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """A random textured patch (h, w, 3) uint8: gradient, shapes, stripes, glyphs."""
    import cv2

    c0, c1 = np.array(rand_colour(rng), float), np.array(rand_colour(rng), float)
    ramp = np.linspace(0, 1, h)[:, None, None] if rng.random() < 0.5 else \
        np.linspace(0, 1, w)[None, :, None]
    img = np.ascontiguousarray(np.broadcast_to(c0 * (1 - ramp) + c1 * ramp, (h, w, 3))
                               ).astype(np.uint8)
    s = min(w, h)
    if rng.random() < 0.6:  # stripes or checker in a sub-rectangle
        x0, y0 = rng.integers(0, w // 2), rng.integers(0, h // 2)
        x1, y1 = x0 + rng.integers(w // 4, w // 2 + 1), y0 + rng.integers(h // 4, h // 2 + 1)
        period = int(rng.integers(max(3, s // 24), max(4, s // 8)))
        yy, xx = np.mgrid[y0:min(y1, h), x0:min(x1, w)]
        if rng.random() < 0.5:
            on = ((xx + yy * rng.integers(0, 2)) // period) % 2 == 0
        else:
            on = ((xx // period) + (yy // period)) % 2 == 0
        patch = img[y0:min(y1, h), x0:min(x1, w)]
        patch[on] = rand_colour(rng)
    for n_shape in range(int(rng.integers(16, 29))):
        col = rand_colour(rng)
        kind = rng.integers(0, 5)
        cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
        big = n_shape < 6   # a few large shapes, then smaller detail
        r = int(rng.integers(max(3, s // (8 if big else 16)), max(4, s // (4 if big else 8))))
        if kind == 0:
            cv2.circle(img, (cx, cy), r, col, -1, cv2.LINE_AA)
        elif kind == 1:
            cv2.ellipse(img, (cx, cy), (r, max(2, r // 2)), float(rng.uniform(0, 180)), 0, 360,
                        col, -1, cv2.LINE_AA)
        elif kind == 2:
            pts = np.stack([cx + rng.integers(-r, r + 1, 5), cy + rng.integers(-r, r + 1, 5)],
                           1).astype(np.int32)
            cv2.fillPoly(img, [pts], col, cv2.LINE_AA)
        elif kind == 3:
            cv2.rectangle(img, (cx - r, cy - r // 2), (cx + r, cy + r // 2), col, -1)
        else:
            p2 = (int(rng.integers(0, w)), int(rng.integers(0, h)))
            cv2.line(img, (cx, cy), p2, col, int(rng.integers(2, max(3, s // 30))), cv2.LINE_AA)
    glyphs = "ABCDEFGHKMNPRSTWXYZ23456789#&@%"
    fonts = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
             cv2.FONT_HERSHEY_TRIPLEX)
    for _ in range(int(rng.integers(1, 3))):
        g = "".join(glyphs[int(i)] for i in rng.integers(0, len(glyphs), rng.integers(1, 3)))
        scale = s / 60.0 * rng.uniform(0.7, 1.2)
        font = fonts[int(rng.integers(0, len(fonts)))]
        th = max(2, int(s / 40))
        (tw, tth), _ = cv2.getTextSize(g, font, scale, th)
        org = (int(rng.integers(0, max(1, w - tw))), int(rng.integers(tth, max(tth + 1, h))))
        cv2.putText(img, g, org, font, scale, rand_colour(rng), th, cv2.LINE_AA)
    return img


def _texture_score(tex: np.ndarray) -> float:
    """Mean |Laplacian| (grey levels) of the texture seen at 48 x 48 px: a proxy for how
    many SIFT keypoints a small instance of it yields."""
    import cv2

    g = cv2.cvtColor(cv2.resize(tex, (48, 48), interpolation=cv2.INTER_AREA),
                     cv2.COLOR_RGB2GRAY).astype(np.float32)
    return float(np.abs(cv2.Laplacian(g, cv2.CV_32F)).mean())


def textured(make: Any, tries: int, min_score: float = 16.0) -> np.ndarray:
    """Call ``make()`` until the texture scores >= min_score (at most ``tries`` times);
    returns the best-scoring texture."""
    best, best_s = None, -1.0
    for _ in range(tries):
        tex = make()
        sc = _texture_score(tex)
        if sc > best_s:
            best, best_s = tex, sc
        if sc >= min_score:
            break
    return best  # type: ignore[return-value]


def photo_texture(rng: np.random.Generator, name: str, w: int, h: int) -> np.ndarray:
    """A crop (h, w, 3) uint8 of a package photo; grey photos are tinted."""
    import cv2

    ph = _photo(name)
    H, W = ph.shape[:2]
    ch = int(min(H, W) * rng.uniform(0.22, 0.45))
    cw = min(W, max(8, int(round(ch * w / h))))
    ch = min(H, ch)
    x0, y0 = int(rng.integers(0, W - cw + 1)), int(rng.integers(0, H - ch + 1))
    crop = cv2.resize(np.ascontiguousarray(ph[y0:y0 + ch, x0:x0 + cw]), (w, h),
                      interpolation=cv2.INTER_AREA).astype(np.float32)
    lo, hi = np.percentile(crop, (2, 98))
    crop = (crop - lo) * (215.0 / max(hi - lo, 1.0)) + 20.0   # contrast stretch
    if np.ptp(crop.reshape(-1, 3).mean(0)) < 3 and np.abs(crop[..., 0] - crop[..., 1]).max() < 3:
        tint = np.array(rand_colour(rng), np.float32) / 255.0
        crop = crop * (0.45 + 0.55 * tint)
    return np.clip(crop, 0, 255).astype(np.uint8)


def silhouette(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """Outline polygon (P, 2) in texture pixels (continuous coords): rect, ellipse or
    rounded rectangle."""
    kind = rng.random()
    if kind < 0.5:
        return np.array([[0, 0], [w, 0], [w, h], [0, h]], float)
    a = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    if kind < 0.75:
        return np.column_stack([w / 2 + w / 2 * np.cos(a), h / 2 + h / 2 * np.sin(a)])
    r = 0.22 * min(w, h)
    pts = []
    for (cx, cy), a0 in (((w - r, h - r), 0.0), ((r, h - r), 0.5 * np.pi),
                         ((r, r), np.pi), ((w - r, r), 1.5 * np.pi)):
        aa = a0 + np.linspace(0, 0.5 * np.pi, 7)
        pts.append(np.column_stack([cx + r * np.cos(aa), cy + r * np.sin(aa)]))
    return np.concatenate(pts)
