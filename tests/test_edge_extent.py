"""Box phase and extent from shared edges (rescu.discovery.edge_extent)."""

from __future__ import annotations

import numpy as np
import pytest

from rescu.discovery.edge_extent import (edge_box_transform, gradient_images, mean_gradient_frame,
                                    refine_pattern_boxes, transform_boxes, untransform_boxes)
from rescu.evaluation.metrics import iou_matrix
from rescu.types import Instance, Pattern

SHIFTS = np.round(np.linspace(-0.5, 0.5, 11), 3)
SCALES = (0.5, 0.6, 0.7, 0.85, 1.0, 1.2)


def _facade(rng):
    """A noisy wall with a 3 x 4 grid of dark 40 x 60 windows; their true boxes."""
    img = 180 + rng.normal(0, 6, (400, 500))
    truth = []
    for r in range(3):
        for c in range(4):
            x, y = 40 + 110 * c, 40 + 120 * r
            img[y:y + 60, x:x + 40] = 60 + rng.normal(0, 6, (60, 40))
            truth.append((x, y, 40, 60))
    return np.clip(img, 0, 255).astype(np.uint8), np.array(truth, float)


def test_boxes_straddling_two_objects_move_onto_the_objects():
    img, truth = _facade(np.random.default_rng(0))
    # stage I's boxes: the lower half of each window and the wall below it, a bit large
    found = truth + np.array([0, 30, 8, 10])
    pat = Pattern(id=0, score=1.0, instances=[Instance(bbox=tuple(b)) for b in found])
    before = np.diag(iou_matrix(found, truth))
    refine_pattern_boxes(img, 1.0, [pat], SHIFTS, SCALES)
    after = np.array([i.bbox for i in pat.instances])
    iou = np.diag(iou_matrix(after, truth))
    assert before.max() < 0.5 and iou.min() > 0.75
    # the transform is recorded, and undoing it gives stage I's boxes back (stage II's
    # merge compares the instances on those)
    t = pat.extra["box_transform"]
    assert len(t) == 4 and t != [0.0, 0.0, 1.0, 1.0]
    assert np.allclose(untransform_boxes(after, t), found)
    assert np.array_equal(untransform_boxes(after, None), after)
    for bad in ([0.0, 0.0, 0.0, 1.0], [0.1, 0.2, 1.0]):
        with pytest.raises(ValueError, match="box_transform"):
            untransform_boxes(after, bad)


def test_scale_factor_keeps_boxes_in_original_pixels():
    img, truth = _facade(np.random.default_rng(1))
    found = truth + np.array([0, 30, 8, 10])
    small = img[::2, ::2]                       # processed = original x 0.5
    pat = Pattern(id=0, score=1.0, instances=[Instance(bbox=tuple(b)) for b in found])
    refine_pattern_boxes(small, 0.5, [pat], SHIFTS, SCALES)
    after = np.array([i.bbox for i in pat.instances])
    assert np.diag(iou_matrix(after, truth)).min() > 0.7


def test_transform_identity_on_boxes_already_on_the_edges():
    img, truth = _facade(np.random.default_rng(2))
    gx, gy = gradient_images(img)
    ax, ay = mean_gradient_frame(gx, gy, truth)
    assert ax.shape == ay.shape == (64, 64)
    assert edge_box_transform(ax, ay, SHIFTS, SCALES) == (0.0, 0.0, 1.0, 1.0)


def test_transform_boxes_clips_to_the_image_and_degenerate_cases():
    b = np.array([[90.0, 0.0, 20.0, 10.0]])
    out = transform_boxes(b, (0.5, -0.5, 1.0, 1.0), (100, 50))
    assert np.allclose(out, [[100.0, 0.0, 0.0, 5.0]])
    # no candidate fits in the frame: no change
    flat = np.zeros((64, 64))
    assert edge_box_transform(flat, flat, [0.9], [2.0]) == (0.0, 0.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="gray"):
        gradient_images(np.zeros((4, 4, 3)))
    # an empty pattern list and a pattern with a zero-size box pass unchanged
    assert refine_pattern_boxes(np.zeros((10, 10), np.uint8), 1.0, [], SHIFTS, SCALES) == []
    p = Pattern(id=0, score=1.0, instances=[Instance(bbox=(1, 1, 0, 3)), Instance(bbox=(5, 1, 2, 3))])
    refine_pattern_boxes(np.zeros((10, 10), np.uint8), 1.0, [p], SHIFTS, SCALES)
    assert p.instances[0].bbox == (1, 1, 0, 3)


def test_stage1_params_refuse_bad_refine_settings():
    from rescu.config import load_config
    from rescu.discovery.stage1 import Stage1Params

    cfg = load_config()["stage1"]
    for bad in ({"refine_scales": [0.0, 1.0]}, {"refine_shifts": [2.0]}, {"refine_shifts": []}):
        with pytest.raises(ValueError, match="refine_"):
            Stage1Params.from_dict({**cfg, **bad})
