"""Local SIFT features: the entries of the RP matrix Omega (stage I of RESCU).

Each feature is a SIFT keypoint (position, scale ``s``, orientation ``theta``) with its
128-D descriptor. Extraction is deterministic: OpenCV's SIFT is run single-threaded
and the keypoints are put in a canonical order (decreasing response, then position).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..io import read_h5, write_h5
from ..types import Features
from ..params import config_section, params_from_dict


@dataclass(frozen=True)
@config_section("features")
class FeatureParams:
    """Parameters of SIFT extraction (OpenCV ``SIFT_create``).

    Attributes
    ----------
    n_features : int
        Keep at most this many keypoints (the strongest by response).
    contrast_threshold : float
        SIFT contrast threshold (lower: more keypoints on low-contrast texture).
    edge_threshold : float
        SIFT edge threshold.
    sigma : float
        Gaussian sigma of the first octave, pixels.
    n_octave_layers : int
        Scale levels per octave.
    min_size : float
        Drop keypoints with ``size`` below this (processed pixels); tiny keypoints are
        mostly noise and JPEG artefacts.
    upsample_below : int
        Images whose longer side is below this (pixels) are upsampled before SIFT so
        that small objects (e.g. 40 x 70 px chess pieces) get enough keypoints; 0 never.
    upsample_factor : float
        Factor of that upsampling (bicubic). The returned features are in the upsampled
        pixels and ``scale_factor`` is multiplied by it (processed = original *
        scale_factor still holds), so :func:`rescu.discovery.stage1.rps_to_patterns` gives
        original pixels unchanged.
    """

    n_features: int
    contrast_threshold: float
    edge_threshold: float
    sigma: float
    n_octave_layers: int
    min_size: float
    upsample_below: int
    upsample_factor: float

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "FeatureParams":
        """Build from a mapping; raises ValueError naming any unknown key."""
        return params_from_dict(cls, d)


def extract_features(rgb: np.ndarray, params: FeatureParams | None = None,
                     scale_factor: float = 1.0) -> Features:
    """SIFT features of one processed image.

    Parameters
    ----------
    rgb : (H, W, 3) uint8 or (H, W) uint8
        The processed image (RGB, as returned by :func:`rescu.io.load_image`).
    params : FeatureParams
    scale_factor : float
        processed = original * scale_factor of ``rgb``; the result stores it times the
        internal upsampling factor (``params.upsample_below``), if any.

    Returns
    -------
    Features
        ``xy`` (K, 2) processed pixels (of the upsampled image when upsampled),
        ``scale`` (K,) pixels (keypoint diameter),
        ``angle`` (K,) degrees, ``response`` (K,), ``descriptors`` (K, 128) float32,
        sorted by decreasing response. A uniform image gives ``Features.empty``.

    >>> from rescu.data.example import example_image
    >>> img, _ = example_image()                  # 432 x 144 px: below upsample_below
    >>> f = extract_features(img)
    >>> f.image_size, f.scale_factor, len(f) > 100
    ((864, 288), 2.0, True)
    """
    import cv2

    params = params or FeatureParams()
    img = np.asarray(rgb)
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3)):
        raise ValueError(f"extract_features: rgb must have shape (H, W, 3) or (H, W), "
                         f"got {img.shape}")
    if img.dtype != np.uint8:
        raise ValueError(f"extract_features: rgb must be uint8, got {img.dtype}")
    if not (scale_factor > 0):
        raise ValueError(f"extract_features: scale_factor must be > 0, got {scale_factor}")
    h, w = img.shape[:2]
    gray = img if img.ndim == 2 else (img[..., 0] if img.shape[2] == 1 else
                                      cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))
    gray = np.ascontiguousarray(gray)
    sf = float(scale_factor)
    if params.upsample_below > 0 and max(h, w) < params.upsample_below \
            and params.upsample_factor > 1.0:
        up = float(params.upsample_factor)
        w2, h2 = int(round(w * up)), int(round(h * up))
        gray = cv2.resize(gray, (w2, h2), interpolation=cv2.INTER_CUBIC)
        # exact ratio of the sizes, so original = processed / scale_factor stays exact
        sf = sf * w2 / w
        w, h = w2, h2
    prev = cv2.getNumThreads()
    cv2.setNumThreads(1)  # deterministic order of keypoints
    try:
        sift = cv2.SIFT_create(nfeatures=0, nOctaveLayers=int(params.n_octave_layers),
                               contrastThreshold=float(params.contrast_threshold),
                               edgeThreshold=float(params.edge_threshold),
                               sigma=float(params.sigma))
        kps, desc = sift.detectAndCompute(gray, None)
    finally:
        cv2.setNumThreads(prev)
    if not kps or desc is None:
        return Features.empty((w, h), sf)
    xy = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
    size = np.array([k.size for k in kps], np.float32)
    ang = np.array([k.angle for k in kps], np.float32) % np.float32(360.0)
    resp = np.array([k.response for k in kps], np.float32)
    desc = np.asarray(desc, np.float32)
    keep = size >= params.min_size
    xy, size, ang, resp, desc = xy[keep], size[keep], ang[keep], resp[keep], desc[keep]
    # canonical order: decreasing response, ties by y, x, size, angle
    order = np.lexsort((ang, size, xy[:, 0], xy[:, 1], -resp))
    order = order[: int(params.n_features)]
    return Features(xy=xy[order], scale=size[order], angle=ang[order],
                    response=resp[order], descriptors=desc[order],
                    image_size=(int(w), int(h)), scale_factor=sf)


def save_features(path: str | os.PathLike[str], feats: Features,
                  attrs: dict[str, object] | None = None) -> None:
    """Write features to HDF5 (atomic): datasets ``xy, scale, angle, response,
    descriptors``; attrs ``image_size`` (width, height), ``scale_factor`` and any extra
    ``attrs`` (e.g. the pipeline's ``failure`` record)."""
    write_h5(path, {"xy": feats.xy.astype(np.float32), "scale": feats.scale.astype(np.float32),
                    "angle": feats.angle.astype(np.float32),
                    "response": feats.response.astype(np.float32),
                    "descriptors": feats.descriptors.astype(np.float32)},
             attrs={"image_size": np.asarray(feats.image_size, np.int64),
                    "scale_factor": float(feats.scale_factor), "kind": "rescu-features",
                    **(attrs or {})})


def load_features(path: str | os.PathLike[str]) -> Features:
    """Read features written by :func:`save_features`."""
    arrays, attrs = read_h5(path)
    size = tuple(int(v) for v in np.asarray(attrs["image_size"]).ravel())
    xy = np.asarray(arrays["xy"], np.float32).reshape(-1, 2)
    desc = np.asarray(arrays["descriptors"], np.float32)
    if desc.ndim != 2:  # (K, D) as written; (0, D) for an image without features
        desc = desc.reshape(len(xy), -1)
    return Features(xy=xy,
                    scale=np.asarray(arrays["scale"], np.float32),
                    angle=np.asarray(arrays["angle"], np.float32),
                    response=np.asarray(arrays["response"], np.float32),
                    descriptors=desc,
                    image_size=(size[0], size[1]),
                    scale_factor=float(attrs["scale_factor"]))
