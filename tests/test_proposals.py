"""Tests of rescu.extension.proposals: EdgeBoxes on computed edges and instance-scale windows."""

import numpy as np
import pytest

from rescu.evaluation.metrics import iod_matrix
from rescu.extension.proposals import (ProposalParams, edge_and_orientation, edgeboxes_proposals,
                                       instance_scale_proposals, lattice_proposals,
                                       proposal_params, propose)


def _squares_image(n=5, sz=24, gap=16, h=80, seed=0):
    rng = np.random.default_rng(seed)
    tex = rng.integers(0, 255, (sz, sz, 3), dtype=np.uint8)
    w = gap + n * (sz + gap)
    img = np.full((h, w, 3), 128, np.uint8)
    boxes = []
    for i in range(n):
        x, y = gap + i * (sz + gap), (h - sz) // 2
        img[y:y + sz, x:x + sz] = tex
        boxes.append([x, y, sz, sz])
    return img, np.array(boxes, np.float32)


def test_edge_maps_shape_and_range():
    img, _ = _squares_image()
    e, o = edge_and_orientation(img)
    assert e.shape == img.shape[:2] and o.shape == img.shape[:2]
    assert e.dtype == np.float32 and o.dtype == np.float32
    assert e.min() >= 0 and e.max() <= 1 and e.max() > 0.5
    assert o.min() >= 0 and o.max() < np.pi


def test_edgeboxes_inside_image():
    img, _ = _squares_image()
    b, s = edgeboxes_proposals(img, proposal_params(method="edgeboxes", max_boxes=200))
    h, w = img.shape[:2]
    assert len(b) > 0 and len(b) == len(s)
    assert np.all(b[:, 0] >= 0) and np.all(b[:, 1] >= 0)
    assert np.all(b[:, 0] + b[:, 2] <= w + 1e-3) and np.all(b[:, 1] + b[:, 3] <= h + 1e-3)
    assert np.all(b[:, 2] >= 8) and np.all(b[:, 3] >= 8)


def test_edgeboxes_of_the_same_image_are_run_once(monkeypatch):
    """A second call on the same pixels and parameters returns the first call's boxes
    without running the detector (the stage-II ablation's variants); other pixels or other
    parameters run it again, and changing a returned array leaves the kept one alone."""
    import cv2

    from rescu.extension import proposals as P

    img, _ = _squares_image()
    pp = proposal_params(method="edgeboxes", max_boxes=200)
    b0, s0 = edgeboxes_proposals(img, pp)
    calls = []
    real = cv2.ximgproc.createEdgeBoxes

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(cv2.ximgproc, "createEdgeBoxes", counting)
    b0[:] = -1
    b1, s1 = edgeboxes_proposals(img.copy(), pp)
    assert not calls and np.all(b1 >= 0)
    assert np.array_equal(b1, edgeboxes_proposals(img, pp)[0]) and np.array_equal(s1, s0)
    other = img.copy()
    other[0, 0] += 1
    edgeboxes_proposals(other, pp)
    assert len(calls) == 1
    edgeboxes_proposals(other, proposal_params(method="edgeboxes", max_boxes=50))
    assert len(calls) == 2 and len(P._LAST_EDGEBOXES) == 1


def test_instance_scale_covers_held_out_instance():
    img, boxes = _squares_image()
    held_out = boxes[4:5]
    q = instance_scale_proposals(boxes[:3], (img.shape[1], img.shape[0]))
    assert len(q) > 0
    assert iod_matrix(q, held_out).max() > 0.9
    h, w = img.shape[:2]
    assert np.all(q[:, 0] >= 0) and np.all(q[:, 0] + q[:, 2] <= w + 1e-3)


def test_instance_scale_cap_and_empty():
    q = instance_scale_proposals(np.array([[0, 0, 10, 10.]]), (1000, 1000),
                                 proposal_params(max_windows=300))
    assert 0 < len(q) <= 300
    assert instance_scale_proposals(np.zeros((0, 4)), (100, 100)).shape == (0, 4)


def test_propose_methods_and_bad_input():
    img, boxes = _squares_image()
    bi, _ = propose(img, [boxes[:3]], proposal_params(method="instance_scale"))
    be, _ = propose(img, [boxes[:3]], proposal_params(method="edgeboxes"))
    bb, sb = propose(img, [boxes[:3]], proposal_params(method="both"))
    assert len(bb) >= max(len(bi), len(be)) and len(bb) == len(sb)
    with pytest.raises(ValueError, match="rgb"):
        propose(img[..., 0], [], proposal_params())
    with pytest.raises(ValueError, match="method"):
        proposal_params(method="selective")
    with pytest.raises(ValueError, match="unknown proposal parameter"):
        ProposalParams.from_dict({"nope": 1})


def test_lattice_windows_at_missing_row_positions():
    # a row of 5 squares with the 2nd and 5th missing from stage I: the lattice of the
    # three found ones predicts both (gap of one -> halfway; end of row -> one step past)
    img, boxes = _squares_image()
    found = boxes[[0, 2, 3]]
    q = lattice_proposals(found, (img.shape[1], img.shape[0]))
    iou = iod_matrix(q, boxes[[1, 4]])
    assert iou[:, 0].max() > 0.99 and iou[:, 1].max() > 0.99
    # no window is centred inside a found instance; all inside the image
    c = q[:, :2] + q[:, 2:] / 2
    for x, y, w, h in found:
        assert not np.any((np.abs(c[:, 0] - x - w / 2) < w / 2) & (np.abs(c[:, 1] - y - h / 2) < h / 2))
    assert np.all(q[:, 0] >= 0) and np.all(q[:, 0] + q[:, 2] <= img.shape[1] + 1e-3)
    # exactly the lattice: 3 scales x the 2nd and 5th centres (x = 68 and 188)
    ok = (np.abs(c[:, 1] - 40) < 1e-3)
    assert ok.all()
    assert sorted(set(np.round(c[:, 0]).astype(int))) == [68, 188]


def test_lattice_windows_need_two_instances():
    assert lattice_proposals(np.array([[0, 0, 10, 10.]]), (100, 100)).shape == (0, 4)
    assert lattice_proposals(np.zeros((0, 4)), (100, 100)).shape == (0, 4)


def test_proposal_params_from_the_configuration_section():
    # one builder: the defaults are the stage2.proposals section of the shipped config,
    # spelled as the configuration spells them
    from rescu.extension.params import Stage2Params
    from rescu.params import config_defaults

    sec = config_defaults("stage2", "proposals")
    p = proposal_params()
    assert p == Stage2Params().proposals.proposal_params()
    assert (p.method, p.max_boxes, p.scales, p.stride_fraction, p.max_windows) == (
        sec["method"], sec["max_proposals"], tuple(sec["window_scales"]), sec["window_stride"],
        sec["max_windows"])
    assert proposal_params({"max_proposals": 50}, method="both").max_boxes == 50
    assert ProposalParams.from_dict({"scales": [1, 2]}).scales == (1.0, 2.0)
    with pytest.raises(ValueError, match="unknown proposal parameter"):
        proposal_params({"max_boxs": 5})
