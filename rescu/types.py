"""Typed records that flow between the stages of RESCU.

Coordinate conventions (used everywhere in the package):

* Pixel coordinates are ``(x, y)`` with ``x`` to the right and ``y`` down, origin at
  the top-left corner of the top-left pixel, in the *displayed* orientation of the photo
  (EXIF rotation applied).
* "Original pixels" are pixels of the full-resolution photo. Processing may downscale an
  image by ``scale_factor`` (processed = original * scale_factor); features are stored in
  processed pixels, everything written to the per-image JSON is in original pixels.
* Boxes are ``[x, y, width, height]`` (COCO), in pixels.
* Angles of SIFT keypoints are in degrees in ``[0, 360)`` as OpenCV reports them.
* A vanishing point is a homogeneous pixel point ``(x, y, w)`` normalised to unit norm, so
  a point far outside the image or at infinity (``w = 0``) is representable.

The per-image JSON written by every method follows ``../shared/README.md``:
see :class:`ImageResult`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

BBox = tuple[float, float, float, float]
"""``(x, y, width, height)`` in pixels."""

Failure = dict[str, Any]
"""The record of a step that failed on one image: ``stage``, ``type`` (the exception's
class name), ``message``, and for a degraded result ``degraded_to`` (see
:mod:`rescu.pipeline`)."""


def failure_record(stage: str, exc: BaseException) -> Failure:
    """A failure record for ``exc`` raised in ``stage``.

    >>> failure_record("dense", ValueError("bad file"))
    {'stage': 'dense', 'type': 'ValueError', 'message': 'bad file'}
    """
    return {"stage": stage, "type": type(exc).__name__, "message": str(exc)}


@dataclass
class Features:
    """SIFT features of one (processed) image.

    Attributes
    ----------
    xy : (K, 2) float32
        Keypoint positions, processed pixels.
    scale : (K,) float32
        Keypoint size (OpenCV ``KeyPoint.size``, the diameter of the meaningful
        neighbourhood), processed pixels.
    angle : (K,) float32
        Keypoint orientation, degrees in ``[0, 360)``.
    response : (K,) float32
        Detector response (contrast), unitless.
    descriptors : (K, 128) float32
        SIFT descriptors (RootSIFT is *not* applied here).
    image_size : (int, int)
        ``(width, height)`` of the processed image, pixels.
    scale_factor : float
        processed = original * scale_factor (1.0 when not downscaled).
    """

    xy: np.ndarray
    scale: np.ndarray
    angle: np.ndarray
    response: np.ndarray
    descriptors: np.ndarray
    image_size: tuple[int, int]
    scale_factor: float = 1.0

    def __post_init__(self) -> None:
        k = len(self.xy)
        if self.xy.shape != (k, 2):
            raise ValueError(f"Features.xy must have shape (K, 2), got {self.xy.shape}")
        for name in ("scale", "angle", "response"):
            arr = getattr(self, name)
            if arr.shape != (k,):
                raise ValueError(f"Features.{name} must have shape ({k},), got {arr.shape}")
        if self.descriptors.ndim != 2 or self.descriptors.shape[0] != k:
            raise ValueError(
                f"Features.descriptors must have shape ({k}, D), got {self.descriptors.shape}"
            )

    def __len__(self) -> int:
        return len(self.xy)

    @classmethod
    def empty(cls, image_size: tuple[int, int], scale_factor: float = 1.0) -> "Features":
        """No features (a uniform image): every array has length 0."""
        z = np.zeros((0,), np.float32)
        return cls(np.zeros((0, 2), np.float32), z, z.copy(), z.copy(),
                   np.zeros((0, 128), np.float32), image_size, scale_factor)


@dataclass
class RPMatrix:
    """A recurring pattern as an M x N matrix Omega of feature indices.

    Attributes
    ----------
    feature_index : (M, N) int64
        Row m = visual word, column n = RP instance; the entry is an index into the
        image's :class:`Features`, or -1 where the word has no feature in that instance.
    objective : float
        U(Omega) = 1/(M N) * sum of URP affinities, unitless.
    params : dict
        The parameters used (``P_d``, ``P_s``, ``P_theta`` ...).
    """

    feature_index: np.ndarray
    objective: float
    params: dict[str, float] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.feature_index.shape)  # type: ignore[return-value]


@dataclass
class Instance:
    """One RP instance: a box in original pixels.

    ``source`` is ``"stage1"`` (found by RESCU-I / GRASP), ``"stage2"`` (added by
    RESCU-II), ``"completion"`` (filled into an equally spaced row by the scene step,
    :mod:`rescu.scene.completion`), or for "count these" ``"example"`` (a box the user
    gave) and ``"prompt"`` (found like it, :func:`rescu.core.find_prompted`). ``score`` is a confidence in [0, 1].
    """

    bbox: BBox
    score: float = 1.0
    source: str = "stage1"

    def to_json(self) -> dict[str, Any]:
        return {"bbox": [round(float(v), 3) for v in self.bbox],
                "score": round(float(self.score), 6), "source": self.source}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "Instance":
        """Read ``{"bbox": [x, y, w, h], "score"?, "source"?}``; ValueError for a box that
        is not four finite numbers with ``w, h >= 0``."""
        b = d["bbox"]
        if not isinstance(b, (list, tuple)) or len(b) != 4:
            raise ValueError(f"bbox must be [x, y, width, height], got {b!r}")
        x, y, w, h = (float(v) for v in b)
        if not all(math.isfinite(v) for v in (x, y, w, h)) or w < 0 or h < 0:
            raise ValueError(f"bbox [x, y, width, height] must be finite with width, "
                             f"height >= 0, got {b!r}")
        return cls(bbox=(x, y, w, h),
                   score=float(d.get("score", 1.0)), source=str(d.get("source", "stage1")))


@dataclass
class VanishingPoint:
    """A vanishing point.

    Attributes
    ----------
    homogeneous : (3,) float
        ``(x, y, w)`` pixel point (original pixels when ``w != 0``), unit norm.
    inside_image : bool
        Whether the point lies inside the image rectangle.
    support : int
        Number of inlier lines (or line pairs) that voted for it.
    """

    homogeneous: np.ndarray
    inside_image: bool
    support: int = 0

    def to_json(self) -> dict[str, Any]:
        h = np.asarray(self.homogeneous, dtype=float)
        return {"homogeneous": [round(float(v), 9) for v in h],
                "inside_image": bool(self.inside_image), "support": int(self.support)}

    @classmethod
    def from_json(cls, d: dict[str, Any] | None) -> "VanishingPoint | None":
        if d is None:
            return None
        return cls(np.asarray(d["homogeneous"], float), bool(d["inside_image"]),
                   int(d.get("support", 0)))


@dataclass
class TranslationSymmetry:
    """Result of the 3D translation-symmetry test of one RP.

    ``cross_ratio`` is the robust (median) cross ratio of 4 consecutive instances;
    equals 4/3 for equally spaced instances in 3D. ``n_tuples`` 4-tuples were used.
    """

    detected: bool
    cross_ratio: float
    n_tuples: int = 0

    def to_json(self) -> dict[str, Any]:
        return {"detected": bool(self.detected), "cross_ratio": round(float(self.cross_ratio), 6),
                "n_tuples": int(self.n_tuples)}

    @classmethod
    def from_json(cls, d: dict[str, Any] | None) -> "TranslationSymmetry | None":
        if d is None:
            return None
        return cls(bool(d["detected"]), float(d["cross_ratio"]), int(d.get("n_tuples", 0)))


@dataclass
class Pattern:
    """One recurring pattern with its instances.

    Attributes
    ----------
    id : int
        Index of the pattern within the image.
    score : float
        Confidence (for stage I: the objective U(Omega)).
    instances : list of Instance
    feature_points : (M, N, 2) float or None
        Corresponding feature positions (original pixels) of the RP matrix, NaN where a
        visual word is missing in an instance; column n belongs to ``instances[n]``
        for the stage-I instances. Used by vanishing-point and symmetry estimation.
    vanishing_point, translation_symmetry : optional scene results.
    """

    id: int
    score: float
    instances: list[Instance]
    feature_points: np.ndarray | None = None
    vanishing_point: VanishingPoint | None = None
    translation_symmetry: TranslationSymmetry | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def count(self) -> int:
        return len(self.instances)

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "id": int(self.id), "score": round(float(self.score), 6), "count": self.count,
            "instances": [i.to_json() for i in self.instances],
            "vanishing_point": self.vanishing_point.to_json() if self.vanishing_point else None,
            "translation_symmetry": (self.translation_symmetry.to_json()
                                     if self.translation_symmetry else None),
        }
        if self.feature_points is not None:
            fp = np.asarray(self.feature_points, float)
            d["feature_points"] = [[None if not np.all(np.isfinite(p)) else
                                    [round(float(p[0]), 3), round(float(p[1]), 3)]
                                    for p in row] for row in fp]
        d.update(self.extra)
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "Pattern":
        fp = d.get("feature_points")
        arr = None
        if fp is not None:
            m = len(fp)
            n = len(fp[0]) if m else 0
            arr = np.full((m, n, 2), np.nan)
            for i, row in enumerate(fp):
                for j, p in enumerate(row):
                    if p is not None:
                        arr[i, j] = p
        known = {"id", "score", "count", "instances", "vanishing_point",
                 "translation_symmetry", "feature_points"}
        return cls(id=int(d["id"]), score=float(d.get("score", 0.0)),
                   instances=[Instance.from_json(i) for i in d.get("instances", [])],
                   feature_points=arr,
                   vanishing_point=VanishingPoint.from_json(d.get("vanishing_point")),
                   translation_symmetry=TranslationSymmetry.from_json(
                       d.get("translation_symmetry")),
                   extra={k: v for k, v in d.items() if k not in known})


@dataclass
class ImageResult:
    """Everything found in one image: the per-image JSON of ``../shared/README.md``.

    ``image`` is the path relative to the dataset folder (``images/<file>``); ``width``
    and ``height`` are original pixels in displayed orientation.
    """

    image: str
    width: int
    height: int
    method: str
    patterns: list[Pattern] = field(default_factory=list)
    dominant_pattern: int | None = None
    vanishing_point: VanishingPoint | None = None
    caption: dict[str, str] | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "image": self.image, "width": int(self.width), "height": int(self.height),
            "method": self.method, "patterns": [p.to_json() for p in self.patterns],
            "dominant_pattern": self.dominant_pattern,
            "vanishing_point": self.vanishing_point.to_json() if self.vanishing_point else None,
            "caption": self.caption,
        }
        d.update(self.extra)
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "ImageResult":
        known = {"image", "width", "height", "method", "patterns", "dominant_pattern",
                 "vanishing_point", "caption"}
        return cls(image=d["image"], width=int(d["width"]), height=int(d["height"]),
                   method=d.get("method", ""),
                   patterns=[Pattern.from_json(p) for p in d.get("patterns", [])],
                   dominant_pattern=d.get("dominant_pattern"),
                   vanishing_point=VanishingPoint.from_json(d.get("vanishing_point")),
                   caption=d.get("caption"),
                   extra={k: v for k, v in d.items() if k not in known})
