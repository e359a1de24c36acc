"""Tests of the GRASP baseline (rescu.discovery.grasp)."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_stage1 import make_scene  # noqa: E402

from rescu.discovery.features import FeatureParams, extract_features  # noqa: E402
from rescu.discovery.grasp import GraspParams, discover_grasp  # noqa: E402
from rescu.evaluation.metrics import score_image  # noqa: E402
from rescu.discovery.stage1 import rps_to_patterns  # noqa: E402
from rescu.types import Features  # noqa: E402

SIFT = FeatureParams(upsample_below=0)  # SIFT on the image as given (the old default)

P = GraspParams(iterations=2, max_steps=15, max_candidates=15, max_patterns=1)


def test_grasp_finds_the_row_of_squares():
    img, gt = make_scene()
    f = extract_features(img, SIFT)
    out = discover_grasp(f, P)
    pats = rps_to_patterns(f, out.rps)
    s = score_image([[i.bbox for i in p.instances] for p in pats], gt)
    assert s.rp_recall == 1.0 and s.instance_precision == 1.0
    assert s.instance_recall >= 0.8
    assert out.chosen == {"P_d": 0.2, "P_s": 0.5, "P_theta": 30.0}


def test_grasp_deterministic_and_empty():
    img, _ = make_scene(n=3)
    f = extract_features(img, SIFT)
    a = discover_grasp(f, P)
    b = discover_grasp(f, P)
    assert [r.feature_index.tolist() for r in a.rps] == [r.feature_index.tolist() for r in b.rps]
    assert discover_grasp(Features.empty((50, 50)), P).rps == []
    with pytest.raises(ValueError, match="bogus"):
        GraspParams.from_dict({"bogus": 1})


def test_grasp_keypoint_cap_keeps_indices_valid():
    img, gt = make_scene()
    f = extract_features(img, SIFT)
    cap = GraspParams(iterations=2, max_steps=15, max_candidates=15, max_patterns=1,
                      max_keypoints=len(f) // 2)
    out = discover_grasp(f, cap)
    for rp in out.rps:
        assert rp.feature_index.max() < len(f) // 2
    assert GraspParams.from_dict({"max_keypoints": 10}).max_keypoints == 10
