""""Count these": example boxes, every instance found, bad boxes refused clearly."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rescu.data.example import example_image
from rescu.extension.prompted import (PromptParams, _negative_cells, check_examples, correlation,
                                      find_like, fit_photo_model, linear_map)

RESCU = Path(sys.executable).parent / "rescu"


@pytest.fixture(scope="module")
def backbone():
    from rescu.extension.backbone import FrozenBackbone

    return FrozenBackbone("efficientnet-lite0")


def test_check_examples_refuses_bad_boxes_naming_them():
    ok = check_examples([(10, 10, 20, 30), [0, 0, 100, 100]], 100, 100)
    assert ok.shape == (2, 4)
    # within a pixel of the border: clipped to the photo
    assert check_examples([(-0.5, 0, 10, 10)], 100, 100)[0, 0] == 0.0
    bad = {"leaves the 100 x 100 photo (x + w = 110 > 100)": [(90, 10, 20, 30)],
           "leaves the 100 x 100 photo (y = -5 < 0)": [(10, -5, 20, 30)],
           "at least 4 pixels": [(10, 10, 0, 30)],
           "at least 4 pixels ": [(10, 10, 20, -3)],
           "at least 4 pixels  ": [(10, 10, 3, 3)],
           "not finite": [(10, np.nan, 20, 30)],
           "four numbers x, y, w, h, got 3": [(10, 10, 20)],
           "four numbers": [("a", 1, 2, 3)],
           "no box given": []}
    for msg, boxes in bad.items():
        with pytest.raises(ValueError, match=msg.strip().replace("(", r"\(").replace(")", r"\)")
                           .replace("+", r"\+")):
            check_examples(boxes, 100, 100)
    with pytest.raises(ValueError, match=r"--example 2 \(1, 1, 2, 2\)"):
        check_examples([(1, 1, 20, 20), (1, 1, 2, 2)], 100, 100, where="--example")


def test_prompt_params_refuse_bad_values():
    with pytest.raises(ValueError, match="rounds"):
        PromptParams(**{**PromptParams().__dict__, "rounds": 3})
    with pytest.raises(ValueError, match="unknown"):
        PromptParams.from_dict({"no_such": 1})


def test_correlation_peaks_where_the_template_is():
    rng = np.random.default_rng(0)
    f = rng.normal(size=(8, 20, 30)).astype(np.float32)
    f /= np.linalg.norm(f, axis=0, keepdims=True)
    t = f[:, 5:9, 12:17].copy()        # a 4 x 5 window whose top-left cell is (5, 12)
    sim = correlation(f, t)
    assert sim.shape == (20, 30)
    assert np.unravel_index(np.argmax(sim), sim.shape) == (5 + 4 // 2, 12 + 5 // 2)
    assert sim.max() == pytest.approx(1.0, abs=1e-5) and sim.min() >= -1.0 - 1e-5


def test_photo_model_probability_map():
    """The per-photo model: a logistic regression of unit-norm windows, its probability
    laid out as the correlation's (the window whose top-left cell is ``(i - kh // 2, j -
    kw // 2)`` at ``(i, j)``), negatives on a grid kept half a window from positives."""
    rng = np.random.default_rng(1)
    f = rng.normal(size=(6, 18, 25)).astype(np.float32)
    pos_cells = np.array([[2, 3], [9, 15]])
    pos = np.stack([f[:, r:r + 3, q:q + 4] for r, q in pos_cells])
    neg_cells = _negative_cells((18, 25), 3, 4, pos_cells, 80)
    assert 40 <= len(neg_cells) <= 120
    for r, q in pos_cells:      # none within half a window of a positive
        assert np.all((np.abs(neg_cells[:, 0] - r) > 1.5) | (np.abs(neg_cells[:, 1] - q) > 2))
    inside = neg_cells[(neg_cells >= 0).all(1) & (neg_cells[:, 0] <= 15) & (neg_cells[:, 1] <= 21)]
    neg = np.stack([f[:, r:r + 3, q:q + 4] for r, q in inside])
    w, b = fit_photo_model(pos, neg, c=10.0)
    prob = linear_map(f, w, b)
    assert prob.shape == (18, 25) and prob.min() >= 0.0 and prob.max() <= 1.0
    r, q = pos_cells[1]
    x = f[:, r:r + 3, q:q + 4].ravel()
    manual = 1.0 / (1.0 + np.exp(-(w.ravel() @ x / np.linalg.norm(x) + b)))
    assert prob[r + 1, q + 2] == pytest.approx(manual, abs=1e-4)
    # the positives score above every negative window
    assert min(prob[r + 1, q + 2] for r, q in pos_cells) > max(
        prob[r + 1, q + 2] for r, q in inside)
    with pytest.raises(ValueError, match="positive and negative"):
        fit_photo_model(pos, neg[:0])


def test_find_like_finds_every_copy_from_one_example(backbone):
    img, boxes = example_image(n=5)
    found = find_like(img, np.array([boxes[2]]), backbone, PromptParams())
    assert found.count == 5 and found.is_example.tolist() == [True] + [False] * 4
    assert np.allclose(found.boxes[0], boxes[2]) and found.scores[0] == 1.0
    from rescu.evaluation.metrics import match_boxes

    assert len(match_boxes(found.boxes, np.array(boxes), 0.5)) == 5
    # two examples: the same five, both examples first
    two = find_like(img, np.array(boxes[:2]), backbone, PromptParams())
    assert two.count == 5 and two.is_example.sum() == 2
    # with the photo model (a score: the geometric mean of a cosine and a probability)
    model = find_like(img, np.array([boxes[2]]), backbone, PromptParams.from_dict(
        {**PromptParams().__dict__, "photo_model": True, "min_score": 0.55}))
    assert model.count == 5 and len(match_boxes(model.boxes, np.array(boxes), 0.5)) == 5
    assert model.scores.min() >= 0.55 and model.scores.max() <= 1.0


def test_find_like_turned_objects(backbone):
    """Bars lying both ways: the turned map finds the crosswise ones, boxes turned too."""
    rng = np.random.default_rng(3)
    img = np.full((240, 420, 3), 120, np.uint8) + rng.integers(0, 10, (240, 420, 3),
                                                               dtype=np.uint8)
    obj = rng.integers(0, 255, (4, 8, 3), dtype=np.uint8).repeat(8, 0).repeat(8, 1)  # 32x64
    lying = [(20, 30), (120, 30), (220, 30)]
    for x, y in lying:
        img[y:y + 32, x:x + 64] = obj
    standing = [(40, 120), (140, 120), (240, 120), (340, 120)]
    for x, y in standing:
        img[y:y + 64, x:x + 32] = np.rot90(obj)
    ex = np.array([[20, 30, 64, 32]], float)
    plain = find_like(img, ex, backbone, PromptParams.from_dict(
        {**PromptParams().__dict__, "turn": False}))
    turned = find_like(img, ex, backbone, PromptParams())
    assert turned.count == 7 and turned.turned.sum() == 4, (plain.count, turned.count)
    up = turned.boxes[turned.turned]
    assert np.allclose(up[:, 2:], [32, 64], atol=1.0)   # width and height swapped
    assert plain.count < turned.count


def test_find_like_half_turned_objects(backbone):
    """Bars facing both ways (a car park's two rows seen from above): the map of the photo
    turned by 180 degrees finds the reversed ones, with boxes where they are."""
    rng = np.random.default_rng(4)
    img = np.full((240, 420, 3), 120, np.uint8) + rng.integers(0, 10, (240, 420, 3),
                                                               dtype=np.uint8)
    obj = np.zeros((32, 64, 3), np.uint8)             # a red front, a chequered back
    obj[:, :32] = (220, 30, 30)
    obj[:, 32:] = ((np.indices((32, 32)).sum(0) // 4) % 2 * 255)[..., None]
    ahead = [(20, 30), (150, 30), (280, 30)]
    for x, y in ahead:
        img[y:y + 32, x:x + 64] = obj
    back = [(30, 150), (160, 150), (290, 150)]
    for x, y in back:
        img[y:y + 32, x:x + 64] = obj[::-1, ::-1]
    ex = np.array([[20, 30, 64, 32]], float)
    base = {**PromptParams().__dict__, "turn": False}
    one_way = find_like(img, ex, backbone, PromptParams.from_dict({**base, "half_turn": False}))
    both = find_like(img, ex, backbone, PromptParams.from_dict({**base, "half_turn": True}))
    from rescu.evaluation.metrics import match_boxes

    truth = np.array([(x, y, 64, 32) for x, y in ahead + back], float)
    assert len(match_boxes(both.boxes, truth, 0.5)) == 6 and both.count == 6, both.boxes
    assert len(match_boxes(one_way.boxes, truth, 0.5)) == 3    # the reversed ones missed
    assert not both.turned.any()          # not turned by a quarter: width and height kept
    assert np.allclose(both.boxes[:, 2:], [64, 32], atol=1.0)

def test_find_like_other_sizes(backbone):
    """Objects 0.6x the example's side: found on the map of the photo resized by 1 / 0.6
    when ``sizes`` holds 0.6, with boxes of their own size; without, boxes of the
    example's size hold them but are too large for them (IOD <= 0.5)."""
    rng = np.random.default_rng(5)
    img = np.full((300, 560, 3), 120, np.uint8) + rng.integers(0, 10, (300, 560, 3),
                                                               dtype=np.uint8)
    obj = rng.integers(0, 255, (4, 4, 3), dtype=np.uint8)
    big = [(20, 30), (140, 30), (260, 30)]
    for x, y in big:
        img[y:y + 48, x:x + 48] = obj.repeat(12, 0).repeat(12, 1)          # 48 x 48
    small = [(30, 160), (130, 160), (230, 160), (330, 160)]
    for x, y in small:
        img[y:y + 28, x:x + 28] = obj.repeat(7, 0).repeat(7, 1)            # 28 x 28
    ex = np.array([[20, 30, 48, 48]], float)
    base = {**PromptParams().__dict__, "turn": False}
    one = find_like(img, ex, backbone, PromptParams.from_dict(base))
    both = find_like(img, ex, backbone, PromptParams.from_dict({**base, "sizes": [0.6, 1.0]}))
    from rescu.evaluation.metrics import match_boxes

    truth = np.array([(x, y, 48, 48) for x, y in big] + [(x, y, 28, 28) for x, y in small],
                     float)
    assert len(match_boxes(both.boxes, truth, 0.5)) == 7 and both.count == 7, both.boxes
    assert len(match_boxes(one.boxes, truth, 0.5)) < 7
    assert np.allclose(both.boxes[both.boxes[:, 2] < 40][:, 2:], 28.8, atol=2.0)
    with pytest.raises(ValueError, match="sizes"):
        PromptParams.from_dict({**base, "sizes": [0.1]})


def test_api_prompted_pattern_first_and_dominant(tmp_path):
    import cv2

    from rescu.api import discover
    from rescu.core import ExampleError

    img, boxes = example_image(n=5)
    photo = tmp_path / "row.png"
    cv2.imwrite(str(photo), img[:, :, ::-1])
    res = discover(photo, tmp_path / "out", method="rescu-i", examples=[boxes[1]])
    p = res.patterns[0]
    assert p.extra["source"] == "prompt" and res.dominant_pattern == p.id and p.count == 5
    assert [i.source for i in p.instances].count("example") == 1
    assert p.instances[0].bbox == tuple(float(v) for v in boxes[1])
    assert res.caption["enhanced"].startswith("Five")
    saved = json.loads((tmp_path / "out" / "row.json").read_text())
    assert saved["patterns"][0]["source"] == "prompt" and saved["prompted"]["examples"] == 1
    with pytest.raises(ExampleError, match=r"row.png: example 1 \(200, 10, 400, 20\): leaves"):
        discover(photo, tmp_path / "out2", method="rescu-i", examples=[(200, 10, 400, 20)])
    assert not (tmp_path / "out2" / "row.json").exists()


def test_overlay_draws_examples_in_white_frames():
    from rescu.types import ImageResult, Instance, Pattern
    from rescu.visualize import draw_overlay, legend_entries

    img = np.zeros((200, 300, 3), np.uint8)
    pat = Pattern(0, 0.7, [Instance((50, 50, 40, 40), 1.0, "example"),
                           Instance((150, 50, 40, 40), 0.7, "prompt")],
                  extra={"source": "prompt", "examples": 1, "threshold": 0.5})
    res = ImageResult("x.png", 300, 200, "rescu-ii", [pat], 0)
    pic, _ = draw_overlay(img, 1.0, res, mode="boxes")
    white = (pic[:200] == 255).all(2)
    assert white[40:100, 40:100].any() and not white[40:100, 140:200].any()
    assert "like the 1 example box (white frame)" in legend_entries(res)[0][1]


def test_cli_example_and_examples_file(tmp_path):
    import cv2

    from rescu.cli import read_examples_file
    from rescu.io import InputError

    img, boxes = example_image(n=5)
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    cv2.imwrite(str(a), img[:, :, ::-1])
    cv2.imwrite(str(b), img[:, :, ::-1])
    x, y, w, h = boxes[0]
    # the file's errors, each naming the file and line
    csv = tmp_path / "ex.csv"
    cases = {"file,x,y,w\n": "header file,x,y,w,h",
             "file,x,y,w,h\n": "no box",
             f"file,x,y,w,h\na.png,{x},{y},{w}\n": "line 2: expected 5 fields",
             f"file,x,y,w,h\na.png,{x},{y},{w},abc\n": "line 2: expected X,Y,W,H",
             f"file,x,y,w,h\na.png,{x},{y},{w},{h}\nc.png,1,1,9,9\n":
                 "line 3: 'c.png' matches none"}
    for text, msg in cases.items():
        csv.write_text(text)
        with pytest.raises(InputError, match=msg):
            read_examples_file(csv, [a, b])
    with pytest.raises(InputError, match="cannot read"):
        read_examples_file(tmp_path / "missing.csv", [a])
    csv.write_text(f"file,x,y,w,h\na.png,{x},{y},{w},{h}\n{b},{x},{y},{w},{h}\n"
                   f"a.png,{boxes[1][0]},{y},{w},{h}\n")
    got = read_examples_file(csv, [a, b])
    assert len(got[a]) == 2 and len(got[b]) == 1
    # the command: a bad box for one photo fails that photo, the other is counted
    csv.write_text(f"file,x,y,w,h\na.png,{x},{y},{w},{h}\nb.png,1000,0,10,10\n")
    out = subprocess.run([str(RESCU), "discover", str(a), str(b), "--out", str(tmp_path / "o"),
                          "--method", "rescu-i", "--quiet", "--examples", str(csv)],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 1, out.stderr
    assert "b.png: FAILED: " in out.stdout and "leaves the" in out.stdout
    assert "a.png: 1 RP: 5 (like the example box)" in out.stdout
    assert not (tmp_path / "o" / "b.json").exists()
    # --example with a malformed box: usage error before any work
    bad = subprocess.run([str(RESCU), "discover", str(a), "--out", str(tmp_path / "p"),
                          "--example", "1,2,3"], capture_output=True, text=True, timeout=600)
    assert bad.returncode == 2 and "--example: expected X,Y,W,H" in bad.stderr
    assert not (tmp_path / "p").exists() or not any((tmp_path / "p").glob("*.json"))
