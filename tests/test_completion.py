"""Tests of rescu.scene.completion (row completion from 3D equal spacing)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from rescu.scene import completion as CO
from rescu.scene import lattice as LA
from rescu.types import ImageResult, Instance, Pattern

SIDE = 40  # object side, pixels (canvas)
H = np.array([[1.0, 0.05, 20.0], [0.02, 1.0, 10.0], [0.0004, 0.0, 1.0]])


def _scene(positions: list[float], erase: int | None = None
           ) -> tuple[np.ndarray, list[tuple[float, float, float, float]]]:
    """Grey image (H, W) uint8 with identical textured squares at x = positions (unit =
    1.6 object sides) on a row, warped by a homography; their boxes (projected corners'
    bounding boxes). ``erase``: that object is not drawn."""
    rng = np.random.default_rng(0)
    tex = cv2.resize(rng.integers(0, 256, (8, 8)).astype(np.uint8), (SIDE, SIDE),
                     interpolation=cv2.INTER_NEAREST)
    canvas = np.full((200, 700), 128, np.uint8)
    canvas = np.clip(canvas + rng.normal(0, 3, canvas.shape), 0, 255).astype(np.uint8)
    boxes = []
    for i, p in enumerate(positions):
        x0, y0 = int(round(30 + p * 1.6 * SIDE)), 80
        if i != erase:
            canvas[y0:y0 + SIDE, x0:x0 + SIDE] = tex
        q = np.array([[x0, y0], [x0 + SIDE, y0], [x0 + SIDE, y0 + SIDE], [x0, y0 + SIDE]],
                     np.float64)
        w = cv2.perspectiveTransform(q[None], H)[0]
        lo, hi = w.min(0), w.max(0)
        boxes.append((float(lo[0]), float(lo[1]), float(hi[0] - lo[0]), float(hi[1] - lo[1])))
    img = cv2.warpPerspective(canvas, H, (760, 260), flags=cv2.INTER_LINEAR,
                              borderValue=128)
    return img, boxes


def _result(boxes: list, keep: list[int]) -> ImageResult:
    pat = Pattern(id=0, score=1.0, instances=[Instance(boxes[i]) for i in keep])
    return ImageResult(image="images/x.png", width=760, height=260, method="rescu-ii",
                       patterns=[pat])


def test_interior_gap_completed() -> None:
    img, boxes = _scene([0, 1, 2, 3, 4, 5])
    res = _result(boxes, [0, 1, 3, 4, 5])
    out = CO.complete_rows(res, img, CO.CompletionParams())
    p = out.patterns[0]
    assert p.count == 6
    new = [i for i in p.instances if i.source == "completion"]
    assert len(new) == 1
    c_new = np.array(new[0].bbox[:2]) + np.array(new[0].bbox[2:]) / 2
    c_gt = np.array(boxes[2][:2]) + np.array(boxes[2][2:]) / 2
    assert np.linalg.norm(c_new - c_gt) < 0.2 * SIDE
    assert 0.5 <= new[0].score <= 1.0
    assert p.extra["completed_rows"] == [[0, 1, 5, 2, 3, 4]]
    # the input is not modified, the output is deterministic
    assert res.patterns[0].count == 5
    again = CO.complete_rows(res, img, CO.CompletionParams())
    assert again.to_json() == out.to_json()


def test_erased_gap_not_completed() -> None:
    img, boxes = _scene([0, 1, 2, 3, 4, 5], erase=2)
    out = CO.complete_rows(_result(boxes, [0, 1, 3, 4, 5]), img, CO.CompletionParams())
    assert out.patterns[0].count == 5


def test_unequal_row_not_completed() -> None:
    img, boxes = _scene([0, 1, 2, 3.5, 4.5])
    out = CO.complete_rows(_result(boxes, [0, 1, 2, 3, 4]), img, CO.CompletionParams())
    assert out.patterns[0].count == 5


def test_row_end_extended_and_switchable() -> None:
    img, boxes = _scene([0, 1, 2, 3, 4, 5])
    res = _result(boxes, [0, 1, 2, 3, 4])
    out = CO.complete_rows(res, img, CO.CompletionParams())
    assert out.patterns[0].count == 6
    assert out.patterns[0].instances[-1].source == "completion"
    off = CO.complete_rows(res, img, CO.CompletionParams(end_instances=0))
    assert off.patterns[0].count == 5
    disabled = CO.complete_rows(_result(boxes, [0, 1, 3, 4, 5]), img,
                                CO.CompletionParams(enabled=False))
    assert disabled.patterns[0].count == 5


def test_complete_row_of_equal_row_adds_nothing() -> None:
    img, boxes = _scene([0, 1, 2, 3, 4, 5])
    out = CO.complete_rows(_result(boxes, [0, 1, 2, 3, 4, 5]), img, CO.CompletionParams())
    assert out.patterns[0].count == 6
    assert out.patterns[0].extra["completed"] == 0


def test_projective_model_and_hypotheses() -> None:
    abc = np.array([50.0, 10.0, 0.05])
    k = np.array([0, 1, 3, 4, 5])
    got, rms = LA.fit_projective_row(k, LA.row_model(abc, k))
    assert rms < 1e-9 and np.allclose(got, abc)
    hyps = LA.gap_hypotheses(3, 2)
    assert [h.tolist() for h in hyps] == [[0, 2, 3], [0, 1, 3], [0, 3, 4], [0, 2, 4],
                                          [0, 1, 4]]


def test_params_and_input_checks() -> None:
    assert CO.CompletionParams.from_dict({"max_gaps": 1}).max_gaps == 1
    with pytest.raises(ValueError, match="bogus"):
        CO.CompletionParams.from_dict({"bogus": 1})
    with pytest.raises(ValueError, match="max_gaps"):
        CO.CompletionParams(max_gaps=0)
    img, boxes = _scene([0, 1, 2])
    with pytest.raises(ValueError, match="gray"):
        CO.complete_rows(_result(boxes, [0, 1, 2]), np.zeros((4, 4, 3)))
    with pytest.raises(TypeError, match="result"):
        CO.complete_rows("x", img)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- grids
def _grid_scene(cols: list[float], erase: tuple[int, int] | None = None
                ) -> tuple[np.ndarray, list[list[tuple[float, float, float, float]]]]:
    """Grey image with two rows of identical textured squares at x = ``cols`` (unit 1.6
    object sides), warped by ``H``; boxes per row.
    ``erase``: (row, column) not drawn."""
    rng = np.random.default_rng(0)
    tex = cv2.resize(rng.integers(0, 256, (8, 8)).astype(np.uint8), (SIDE, SIDE),
                     interpolation=cv2.INTER_NEAREST)
    canvas = np.full((260, 700), 128, np.uint8)
    canvas = np.clip(canvas + rng.normal(0, 3, canvas.shape), 0, 255).astype(np.uint8)
    boxes: list[list[tuple[float, float, float, float]]] = []
    for r, y0 in enumerate((40, 40 + int(1.6 * SIDE))):
        row = []
        for j, p in enumerate(cols):
            x0 = int(round(30 + p * 1.6 * SIDE))
            if (r, j) != erase:
                canvas[y0:y0 + SIDE, x0:x0 + SIDE] = tex
            q = np.array([[x0, y0], [x0 + SIDE, y0], [x0 + SIDE, y0 + SIDE], [x0, y0 + SIDE]],
                         np.float64)
            w = cv2.perspectiveTransform(q[None], H)[0]
            lo, hi = w.min(0), w.max(0)
            row.append((float(lo[0]), float(lo[1]), float(hi[0] - lo[0]), float(hi[1] - lo[1])))
        boxes.append(row)
    img = cv2.warpPerspective(canvas, H, (760, 320), flags=cv2.INTER_LINEAR, borderValue=128)
    return img, boxes


def _grid_result(boxes: list[list[tuple]], missing: tuple[int, int]) -> ImageResult:
    inst = [Instance(b) for r, row in enumerate(boxes) for j, b in enumerate(row)
            if (r, j) != missing]
    return ImageResult(image="images/g.png", width=760, height=320, method="rescu-ii",
                       patterns=[Pattern(id=0, score=1.0, instances=inst)])


def test_grid_cell_completed() -> None:
    cols = [0, 1, 2]  # a 2 x 3 grid; row 1 has two instances, too few for a row model
    img, boxes = _grid_scene(cols)
    res = _grid_result(boxes, (1, 2))
    out = CO.complete_rows(res, img, CO.CompletionParams())
    p = out.patterns[0]
    assert p.count == 6 and p.extra["grid_completed"] == 1 and p.extra["completed"] == 1
    new = p.instances[-1]
    assert new.source == "completion" and 0.5 <= new.score <= 1.0
    c_new = np.array(new.bbox[:2]) + np.array(new.bbox[2:]) / 2
    gt = boxes[1][2]
    assert np.linalg.norm(c_new - (np.array(gt[:2]) + np.array(gt[2:]) / 2)) < 0.25 * SIDE
    # switched off, or nothing in the image there: no instance is added
    off = CO.complete_rows(res, img, CO.CompletionParams(grid=False))
    assert off.patterns[0].count == 5 and off.patterns[0].extra["grid_completed"] == 0
    img_e, _ = _grid_scene(cols, erase=(1, 2))
    assert CO.complete_rows(res, img_e, CO.CompletionParams()).patterns[0].count == 5


def test_grid_missing_cells_and_lattice_fit() -> None:
    # row B one short: its columns are known up to a shift, so both ends are candidates
    assert LA.grid_missing_cells(np.array([0, 1, 2, 3]), np.array([0, 1, 2]), 2) == [
        (-1, 1), (3, 1)]
    assert LA.grid_missing_cells(np.array([0, 1, 2]), np.array([5, 6, 7]), 2) == []
    assert LA.grid_missing_cells(np.array([0, 1, 2, 3, 4]), np.array([0, 1]), 2) == []
    # exact projective lattice; row B has an empty cell between found instances
    Hm = np.array([[60.0, 8.0, 50.0], [2.0, 70.0, 40.0], [0.02, 0.001, 1.0]])
    ca = LA.lattice_map(Hm, np.array([[u, 0.0] for u in (0, 1, 2, 3)]))
    cb = LA.lattice_map(Hm, np.array([[u, 1.0] for u in (0, 2, 3)]))
    tol = np.full(4, 3.0)
    fit = LA.lattice_pair_fit(ca, cb, tol, tol[:3])
    assert fit is not None
    _, ua, ub = fit
    assert np.diff(ua).tolist() == [1, 1, 1] and np.diff(ub).tolist() == [2, 1]
    assert ub[0] - ua[0] in (0, -1, 1)  # aligned up to a shift
    # two points per row fit any lattice: no fit
    assert LA.lattice_pair_fit(ca[:2], cb[:2], tol[:2], tol[:2]) is None
    with pytest.raises(ValueError, match="grid_tolerance"):
        CO.CompletionParams(grid_tolerance=0.6)
