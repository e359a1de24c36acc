"""Tests of rescu.scene.counting: counts, dominant RP, count errors."""

from __future__ import annotations

import numpy as np
import pytest

from rescu.scene import counting as C
from rescu.evaluation.metrics import score_image
from rescu.types import Instance, Pattern


def pat(i: int, n: int, score: float = 0.5) -> Pattern:
    return Pattern(id=i, score=score,
                   instances=[Instance((10.0 * k, 0.0, 5.0, 5.0)) for k in range(n)])


def test_counts_and_dominant():
    ps = [pat(0, 3), pat(1, 5, 0.1), pat(2, 4)]
    assert C.pattern_counts(ps) == [3, 5, 4]
    assert C.dominant_pattern(ps) == 1


def test_dominant_ties_higher_score_then_first():
    assert C.dominant_pattern([pat(0, 4, 0.2), pat(1, 4, 0.9)]) == 1
    assert C.dominant_pattern([pat(0, 4, 0.5), pat(1, 4, 0.5)]) == 0
    assert C.dominant_pattern([]) is None
    assert C.dominant_pattern([pat(0, 0)]) is None


def test_count_pairs_one_per_gt_rp():
    # det 0 -> gt 1, det 1 -> None, det 2 -> gt 1 (larger), det 3 -> gt 0
    pairs = C.count_pairs([4, 7, 6, 2], [3, 5], [1, None, 0, 0])
    assert pairs == [(6, 3), (4, 5)]
    assert C.count_pairs([], [3], []) == []
    with pytest.raises(ValueError, match="assignment"):
        C.count_pairs([1, 2], [3], [0])
    with pytest.raises(ValueError, match="ground-truth RP index"):
        C.count_pairs([1], [3], [2])


def test_count_errors():
    e = C.count_errors([(5, 5), (4, 6), (8, 6)])
    assert e["count_mae"] == pytest.approx(4 / 3)
    assert e["count_exact_rate"] == pytest.approx(1 / 3)
    assert e["count_mean_relative_error"] == pytest.approx((0 + 2 / 6 + 2 / 6) / 3)
    assert e["n_pairs"] == 3
    empty = C.count_errors([])
    assert np.isnan(empty["count_mae"]) and empty["n_pairs"] == 0


def test_count_pairs_with_metrics_assignment():
    gt = [[(0.0, 0, 10, 10), (20, 0, 10, 10), (40, 0, 10, 10)],
          [(0.0, 50, 10, 10), (20, 50, 10, 10)]]
    det = [[(0.0, 50, 10, 10), (20, 50, 10, 10), (40, 50, 10, 10)],  # 2 of 3 on gt 1
           [(0.0, 0, 10, 10), (20, 0, 10, 10), (40, 0, 10, 10)]]
    s = score_image(det, gt)
    assert s.rp_assignment == [1, 0]
    pairs = C.count_pairs([len(d) for d in det], [len(g) for g in gt], s.rp_assignment)
    assert pairs == [(3, 3), (3, 2)]
