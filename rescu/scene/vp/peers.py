"""A peer's vanishing points for the VPD table: ``lu-vp-detect`` (Lu et al., WACV 2017).

``lu-vp-detect`` (PyPI, MIT licence, https://github.com/rayryeng/XiaohuLuVPDetection) is an
optional extra, imported lazily. Its wheel requires ``opencv-contrib-python``, which would
replace this project's OpenCV (``opencv-contrib-python-headless``, same ``cv2`` module,
OpenCV 4); install it with ``pip install --no-deps lu-vp-detect==1.0.4`` (``make setup``
does). It needs the focal length and returns three orthogonal VPs; their support (for the
dominant one) is counted here the way the package clusters lines for its own debug image:
each LSD segment of at least ``length_px`` pixels goes to the VP it points to best, within
6 degrees.
"""

from __future__ import annotations

import numpy as np

from ...types import VanishingPoint
from .geometry import _canonical, inside_image
from .lsd import lsd_segments
from .manhattan import ManhattanVP, _sines

LU_INSTALL = ("lu-vp-detect is not installed: pip install --no-deps lu-vp-detect==1.0.4 "
              "(--no-deps: its wheel asks for opencv-contrib-python, which would replace "
              "this project's OpenCV)")


def lu_available() -> bool:
    """Whether ``lu_vp_detect`` can be imported (without importing it)."""
    import importlib.util

    return importlib.util.find_spec("lu_vp_detect") is not None


def lu_vanishing_points(rgb: np.ndarray, focal_px: float, seed: int = 0,
                        length_px: float = 30.0,
                        scale_factor: float = 1.0) -> list[ManhattanVP]:
    """The three VPs of ``lu-vp-detect``, ordered by support (dominant first).

    Parameters
    ----------
    rgb : (H, W, 3) uint8
        The processed image (original * ``scale_factor``).
    focal_px : float
        Focal length in processed pixels (principal point at the image centre).
    seed : int
        The package's RANSAC seed.
    length_px : float
        Shortest LSD segment used, processed pixels (the package's ``length_thresh``).
    scale_factor : float
        processed = original * scale_factor; VPs are returned in original pixels.

    Raises
    ------
    ImportError
        With the install command, when the package is absent.
    """
    try:
        from lu_vp_detect import VPDetection
    except ImportError as e:
        raise ImportError(LU_INSTALL) from e
    img = np.asarray(rgb)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"rgb must have shape (H, W, 3), got {img.shape}")
    h, w = img.shape[:2]
    det = VPDetection(length_thresh=length_px, principal_point=None,
                      focal_length=float(focal_px), seed=int(seed))
    dirs = np.asarray(det.find_vps(np.ascontiguousarray(img[:, :, ::-1])), float)
    segs = lsd_segments(img, length_px)
    mids = (segs[:, :2] + segs[:, 2:]) / 2
    d = segs[:, 2:] - segs[:, :2]
    length = np.linalg.norm(d, axis=1)
    d = d / np.maximum(length, 1e-12)[:, None]
    pp = np.array([w / 2.0, h / 2.0])
    k_img = np.array([[focal_px, 0, pp[0]], [0, focal_px, pp[1]], [0, 0, 1.0]])
    vps = (k_img @ dirs.T).T                                              # (3, 3) processed px
    e = _sines(vps, mids, d) if len(segs) else np.ones((3, 0))
    k = e.argmin(axis=0) if len(segs) else np.zeros(0, int)
    ok = e[k, np.arange(len(k))] <= np.sin(np.pi / 30) if len(segs) else np.zeros(0, bool)
    size = (round(w / scale_factor), round(h / scale_factor))
    out = []
    for j in range(3):
        sel = ok & (k == j)
        v = _canonical(np.diag([1.0, 1.0, scale_factor]) @ vps[j])
        dj = dirs[j] / np.linalg.norm(dirs[j])
        if dj[2] < 0 or (dj[2] == 0 and float(dj[:2] @ v[:2]) < 0):
            dj = -dj
        out.append(ManhattanVP(VanishingPoint(v, inside_image(v, size), int(sel.sum())),
                               dj + 0.0, float(length[sel].sum() / scale_factor),
                               {"lines": int(sel.sum())}))
    out.sort(key=lambda m: -m.weight)
    return out
