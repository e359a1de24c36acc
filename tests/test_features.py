"""Tests of SIFT feature extraction and storage (rescu.discovery.features)."""

import numpy as np
import pytest

from rescu.discovery.features import FeatureParams, extract_features, load_features, save_features

# the shipped default upsamples images below 700 px; these tests use SIFT on the image as
# given (FeatureParams' old default, upsample_below=0)
SIFT = FeatureParams(upsample_below=0)


def _image(seed=0, h=120, w=160):
    import cv2
    g = np.random.default_rng(seed).integers(0, 256, (h // 8, w // 8)).astype(np.uint8)
    g = cv2.resize(g, (w, h), interpolation=cv2.INTER_NEAREST)
    return np.dstack([g] * 3)


def test_extract_shapes_order_and_scale_factor():
    f = extract_features(_image(), FeatureParams(n_features=50, upsample_below=0), scale_factor=0.5)
    k = len(f)
    assert 0 < k <= 50
    assert f.xy.shape == (k, 2) and f.descriptors.shape == (k, 128)
    assert f.image_size == (160, 120) and f.scale_factor == 0.5
    assert np.all(np.diff(f.response) <= 0)           # sorted by response
    assert np.all((f.angle >= 0) & (f.angle < 360))
    assert np.all(f.scale >= FeatureParams().min_size)


def test_deterministic_and_uniform_image_is_empty():
    a = extract_features(_image(), SIFT)
    b = extract_features(_image(), SIFT)
    assert np.array_equal(a.xy, b.xy) and np.array_equal(a.descriptors, b.descriptors)
    e = extract_features(np.full((64, 64, 3), 128, np.uint8), SIFT)
    assert len(e) == 0 and e.image_size == (64, 64)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="rgb"):
        extract_features(np.zeros((10, 10, 4), np.uint8))
    with pytest.raises(ValueError, match="uint8"):
        extract_features(np.zeros((10, 10, 3), np.float32))
    with pytest.raises(ValueError, match="n_feat"):
        FeatureParams.from_dict({"n_feat": 3})


def test_save_load_roundtrip(tmp_path):
    f = extract_features(_image(), SIFT, scale_factor=0.25)
    save_features(tmp_path / "f.h5", f)
    g = load_features(tmp_path / "f.h5")
    assert g.image_size == f.image_size and g.scale_factor == 0.25
    for name in ("xy", "scale", "angle", "response", "descriptors"):
        assert np.array_equal(getattr(g, name), getattr(f, name))


def test_upsampling_keeps_original_pixels_consistent():
    img = _image(3)
    p = FeatureParams(upsample_below=200, upsample_factor=2.0)
    f = extract_features(img, p, scale_factor=0.5)
    assert f.image_size == (320, 240) and f.scale_factor == 1.0   # 0.5 * 2
    base = extract_features(img, SIFT, scale_factor=0.5)
    assert base.image_size == (160, 120) and base.scale_factor == 0.5
    assert len(f) > len(base)                         # small texture: more keypoints
    # every upsampled keypoint (in original pixels) lies in the original image
    orig = f.xy / f.scale_factor
    assert np.all((orig >= -1) & (orig <= np.array([320, 240]) + 1))
    # a strong keypoint is found at the same original position in both
    bo = base.xy[:10] / base.scale_factor
    d = np.hypot(*(bo[:, None] - orig[None]).transpose(2, 0, 1)).min(1)
    assert np.median(d) < 2.0
    # not upsampled at or above the threshold
    g = extract_features(img, FeatureParams(upsample_below=160), scale_factor=0.5)
    assert g.image_size == (160, 120) and g.scale_factor == 0.5
    with pytest.raises(ValueError, match="upsample_factor"):
        FeatureParams(upsample_factor=0.5)


def test_empty_features_round_trip(tmp_path):
    """A uniform image has no features; they save and load as an empty set."""
    from rescu.discovery.features import load_features, save_features
    from rescu.types import Features

    save_features(tmp_path / "f.h5", Features.empty((320, 240), 0.5))
    back = load_features(tmp_path / "f.h5")
    assert len(back) == 0 and back.descriptors.shape == (0, 128)
    assert back.image_size == (320, 240) and back.scale_factor == 0.5
