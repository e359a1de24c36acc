"""Overlay pictures (rescu.visualize): visible boxes at any size, labels with a background
that neither overlap nor leave the picture, a legend with count and confidence."""

from __future__ import annotations

import numpy as np
import pytest

from rescu import visualize as V
from rescu.types import ImageResult, Instance, Pattern, VanishingPoint


def crowded(n_patterns: int = 6, per: int = 12, seed: int = 0) -> ImageResult:
    """Many small RPs packed into a small image, all wanting their label at the top."""
    rng = np.random.default_rng(seed)
    pats = []
    for k in range(n_patterns):
        xy = rng.uniform(0, 150, (per, 2))
        p = Pattern(k, 0.5, [Instance((x, y, 3, 2)) for x, y in xy])
        p.vanishing_point = VanishingPoint(np.array([1.0, 0.2, 0.0]), False, 9)
        if k % 2:
            p.extra["confidence"] = 0.25 + 0.1 * k
        pats.append(p)
    vps = [{"homogeneous": [80.0, 10.0, 1.0]}, {"homogeneous": [0.0, 1.0, 0.0]}]
    return ImageResult("images/x.png", 160, 160, "rescu-ii", pats,
                       caption={"base": "b", "enhanced": "Twelve similar objects."},
                       extra={"vanishing_points": vps})


@pytest.mark.parametrize("mode", ["full", "boxes"])
@pytest.mark.parametrize("seed", [0, 1])
def test_labels_inside_and_not_overlapping(mode: str, seed: int) -> None:
    res = crowded(seed=seed)
    img, labels = V.draw_overlay(np.full((160, 160, 3), 90, np.uint8), 1.0, res, mode=mode)
    assert len(labels) >= 4
    for i, a in enumerate(labels):
        assert 0 <= a.x0 < a.x1 <= 160 and 0 <= a.y0 < a.y1 <= 160, a
        for b in labels[i + 1:]:
            assert not a.overlaps(b), (a, b)
    assert any(lab.text.startswith("VP") for lab in labels) == (mode == "full")
    assert img.shape[1] == 160 and img.shape[0] > 160 + 6 * 15  # legend + caption band


def test_tiny_boxes_stay_visible_and_legend_shows_confidence(monkeypatch) -> None:
    p = Pattern(0, 0.7, [Instance((50, 50, 1, 1)), Instance((100, 50, 1, 1))])
    p.extra["confidence"] = 0.83
    res = ImageResult("images/x.png", 200, 120, "rescu-ii", [p])
    img = V.overlay(np.zeros((120, 200, 3), np.uint8), 1.0, res, mode="boxes")
    red = (img[:120] == V.PALETTE[0]).all(axis=2)
    ys, xs = np.nonzero(red[:, :80])
    assert xs.max() - xs.min() >= V.MIN_BOX_PX - 1  # a 1-px box drawn 8 px wide
    assert V.legend_entries(res)[0][1] == "RP0: 2 instances, confidence 0.83"
    q = Pattern(1, 0.61, [Instance((0, 0, 5, 5))] * 3)
    assert V.legend_entries(ImageResult("x", 9, 9, "m", [q]))[0][1] == \
        "RP1: 3 instances, score 0.61"
    with pytest.raises(ValueError, match="mode"):
        V.draw_overlay(np.zeros((10, 10, 3), np.uint8), 1.0, res, mode="none")


def test_every_vp_mark_has_its_legend_entry_saying_what_supports_it() -> None:
    """A VP arrow on a photo without RPs is explained, not left bare (full mode only)."""
    vps = [{"homogeneous": [5000.0, 40.0, 1.0], "inside_image": False,
            "cues": {"lines": 64, "rp_rows": 0}},
           {"homogeneous": [30.0, 30.0, 1.0], "inside_image": True,
            "cues": {"lines": 12, "rp_rows": 3}}]
    res = ImageResult("x", 160, 120, "m", [], extra={"vanishing_points": vps})
    full = V.legend_entries(res, "full")
    assert [t for _, t in full] == [
        "VP1: vanishing point of 64 lines, outside the image (arrow towards it)",
        "VP2: vanishing point of 12 lines and 3 RP rows, inside the image (ring)"]
    assert V.legend_entries(res, "boxes") == []       # no VP drawn: none explained
    rgb = np.full((120, 160, 3), 128, np.uint8)
    a = V.overlay(rgb, 1.0, res, mode="full")
    b = V.overlay(rgb, 1.0, res, mode="boxes")
    assert a.shape[0] > b.shape[0]                      # the legend lines are drawn
