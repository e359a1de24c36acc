"""Tests of the synthetic recurring-pattern benchmark (rescu.data.synth)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from rescu.io import load_coco_rps, load_image, load_vanishing_points
from rescu.data.camera import (camera_matrix, plane_homography, project_points, rotation_matrix,
                               row_vanishing_point)
from rescu.data.synth import (SynthParams, generate_dataset, render_synthetic_image,
                              synthetic_image_names)

SMALL = dict(sizes=[[640, 480]], n_images=4)


@pytest.fixture(scope="module")
def ds4(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("synth4")
    generate_dataset(out, SynthParams(seed=3, **SMALL))
    return out


@pytest.fixture(scope="module")
def truth12() -> list[dict]:
    p = SynthParams(seed=5, n_images=12, sizes=[[640, 480]])
    return [render_synthetic_image(p, i) for i in range(12)]


def _cr(a, b, c, d) -> float:
    a, b, c, d = (np.asarray(v, float) for v in (a, b, c, d))
    n = np.linalg.norm
    return n(a - c) * n(b - d) / (n(b - c) * n(a - d))


# ----------------------------------------------------------------------------- params
def test_params_from_dict_rejects_unknown_key() -> None:
    with pytest.raises(ValueError, match="unknown key.*'bogus'"):
        SynthParams.from_dict({"bogus": 1})
    p = SynthParams.from_dict({"n_images": 3, "sizes": [[700, 500]], "row_length": [4, 6]})
    assert p.sizes == ((700, 500),) and p.row_length == (4, 6) and p.n_images == 3


@pytest.mark.parametrize("bad", [{"projective_fraction": 1.5}, {"max_rps": 0},
                                 {"row_length": [6, 4]}, {"sizes": [[10, 10]]},
                                 {"instance_px": [40]}])
def test_params_validation(bad: dict) -> None:
    with pytest.raises(ValueError, match="SynthParams"):
        SynthParams.from_dict(bad)


def test_image_names() -> None:
    assert synthetic_image_names(3) == ["synth_0000.png", "synth_0001.png", "synth_0002.png"]
    assert synthetic_image_names(0) == []
    with pytest.raises(ValueError, match="n_images"):
        synthetic_image_names(-1)


# ----------------------------------------------------------------------------- geometry
def test_project_points_and_homography_agree() -> None:
    K = camera_matrix(800.0, 320.0, 240.0)
    R = rotation_matrix((0, 1, 0), math.radians(40)) @ rotation_matrix((0, 0, 1), 0.1)
    t = np.array([0.3, -0.2, 9.0])
    uv = np.array([[0.0, 0.0], [1.0, 2.0], [-3.0, 0.5]])
    px = project_points(K, R, t, uv)
    H = plane_homography(K, R, t)
    xh = np.column_stack([uv, np.ones(3)]) @ H.T
    np.testing.assert_allclose(px, xh[:, :2] / xh[:, 2:], atol=1e-9)
    np.testing.assert_allclose(px[0], (320 + 800 * 0.3 / 9, 240 - 800 * 0.2 / 9))
    with pytest.raises(ValueError, match="behind the camera"):
        project_points(K, R, np.array([0, 0, -1.0]), uv)
    with pytest.raises(ValueError, match=r"pts3d must have shape \(N, 3\)"):
        project_points(K, R, t, np.zeros((2, 4)))


def test_row_vanishing_point_frontal_is_at_infinity() -> None:
    K = camera_matrix(700.0, 400.0, 300.0)
    vp, d = row_vanishing_point(K, rotation_matrix((0, 0, 1), 0.2))
    assert vp[2] == 0.0 and abs(np.linalg.norm(vp) - 1) < 1e-12
    np.testing.assert_allclose(vp, [math.cos(0.2), math.sin(0.2), 0], atol=1e-12)


# ----------------------------------------------------------------------------- dataset
def test_layout_of_written_dataset(ds4: Path) -> None:
    names = sorted(p.name for p in (ds4 / "images").iterdir())
    assert names == synthetic_image_names(4)
    assert {p.name for p in ds4.iterdir()} == {"images", "annotations.json",
                                              "vanishing_points.json", "truth.json"}
    coco = json.loads((ds4 / "annotations.json").read_text())
    assert [im["file_name"] for im in coco["images"]] == [f"images/{n}" for n in names]
    assert all(a["iscrowd"] == 0 and a["area"] > 0 for a in coco["annotations"])
    assert len({c["id"] for c in coco["categories"]}) == len(coco["categories"])
    for im in coco["images"]:
        li = load_image(ds4 / im["file_name"])
        assert li.original_size == (im["width"], im["height"]) == (640, 480)


def test_annotations_match_truth(ds4: Path) -> None:
    rps = load_coco_rps(ds4 / "annotations.json")
    truth = json.loads((ds4 / "truth.json").read_text())["images"]
    assert len(truth) == 4
    for im in truth:
        gt = rps[im["file_name"]]
        assert 1 <= len(gt) <= 4
        assert len(gt) == len(im["patterns"])
        by_name = {g.category: g for g in gt}
        for pat in im["patterns"]:
            assert len(by_name[pat["category"]].boxes) == pat["count"]
            assert sum(len(r) for r in pat["rows"]) == pat["count"]
            assert pat["layout"] in ("row", "grid")
            assert pat["translation_symmetry"] == pat["equal_spacing"]
            assert all(4 <= len(r) for r in pat["rows"]) or pat["layout"] == "grid"


def test_instance_centre_inside_box_and_sizes(ds4: Path) -> None:
    coco = json.loads((ds4 / "annotations.json").read_text())
    boxes = {a["id"]: a["bbox"] for a in coco["annotations"]}
    truth = json.loads((ds4 / "truth.json").read_text())["images"]
    n = 0
    for im in truth:
        for pat in im["patterns"]:
            for inst in pat["instances"]:
                x, y, w, h = boxes[inst["id"]]
                cx, cy = inst["center"]
                assert x < cx < x + w and y < cy < y + h
                assert 0 <= x and 0 <= y and x + w <= im["width"] and y + h <= im["height"]
                assert 40 * 0.9 <= max(w, h) <= 140  # "roughly"
                n += 1
    assert n >= 8


def test_rps_do_not_overlap(truth12: list) -> None:
    for s in truth12:
        ext = []
        for pat in s.truth["patterns"]:
            ids = {i["id"] for i in pat["instances"]}
            b = np.array([a["bbox"] for a in s.annotations if a["id"] in ids])
            ext.append((b[:, 0].min(), b[:, 1].min(), (b[:, 0] + b[:, 2]).max(),
                        (b[:, 1] + b[:, 3]).max()))
        for i in range(len(ext)):
            for j in range(i + 1, len(ext)):
                a, b = ext[i], ext[j]
                assert a[2] <= b[0] or b[2] <= a[0] or a[3] <= b[1] or b[3] <= a[1]


def test_vanishing_point_is_where_rows_meet(truth12: list) -> None:
    n_checked = n_pairs = 0
    for s in truth12:
        for pat in s.truth["patterns"]:
            vp = np.asarray(pat["vanishing_point"], float)
            assert abs(np.linalg.norm(vp) - 1) < 1e-6
            cen = {i["id"]: np.asarray(i["center"], float) for i in pat["instances"]}
            lines = []
            for row in pat["rows"]:
                a, b = cen[row[0]], cen[row[-1]]
                ln = np.cross([*a, 1.0], [*b, 1.0])
                ln /= np.linalg.norm(ln[:2])
                lines.append(ln)
                if s.truth["subset"] == "projective":
                    assert vp[2] > 0
                    # every centre of the row lies on the line, and the line hits the VP
                    for c in row:
                        assert abs(ln @ [*cen[c], 1.0]) < 1e-3
                    assert abs(ln @ (vp / vp[2])) < 1.0
                    n_checked += 1
                else:
                    assert abs(vp[2]) < 1e-9
                    assert abs(ln[:2] @ vp[:2]) / np.linalg.norm(vp[:2]) < 1e-3
            if s.truth["subset"] == "projective" and len(lines) >= 2:
                x = np.cross(lines[0], lines[1])
                assert np.linalg.norm(x / x[2] - vp / vp[2]) < 1.0
                n_pairs += 1
    assert n_checked >= 3 and n_pairs >= 1


def test_cross_ratio_equal_vs_unequal(truth12: list) -> None:
    n_eq = n_uneq = 0
    for s in truth12:
        for pat in s.truth["patterns"]:
            cen = {i["id"]: np.asarray(i["center"], float) for i in pat["instances"]}
            for row in pat["rows"]:
                pts = [cen[c] for c in row]
                for k in range(len(pts) - 3):
                    cr = _cr(*pts[k:k + 4])
                    if pat["equal_spacing"]:
                        assert abs(cr - 4 / 3) < 1e-6
                        n_eq += 1
                    else:
                        assert abs(cr - 4 / 3) > 0.05
                        n_uneq += 1
    assert n_eq >= 5 and n_uneq >= 1


def test_subsets_and_hard_present(truth12: list) -> None:
    subsets = {s.truth["subset"] for s in truth12}
    assert subsets == {"frontal", "projective"}
    assert any(s.truth["hard"] for s in truth12) and not all(s.truth["hard"] for s in truth12)
    assert any(i["occluded_fraction"] > 0.1 for s in truth12 if s.truth["hard"]
               for p in s.truth["patterns"] for i in p["instances"])
    assert any(not p["equal_spacing"] for s in truth12 for p in s.truth["patterns"])


def test_vanishing_points_json(ds4: Path) -> None:
    vps = load_vanishing_points(ds4 / "vanishing_points.json")
    truth = {im["file_name"]: im for im in
             json.loads((ds4 / "truth.json").read_text())["images"]}
    assert set(vps) == set(truth)
    for name, v in vps.items():
        t = truth[name]
        assert v["focal_px"] == pytest.approx(t["K"][0][0])
        if t["subset"] == "frontal":
            assert v["vanishing_points"] == []
        else:
            assert 1 <= len(v["vanishing_points"]) <= len(t["patterns"])
            tv = [np.asarray(p["vanishing_point"]) for p in t["patterns"]]
            for h in v["vanishing_points"]:
                assert min(np.linalg.norm(h - x) for x in tv) < 1e-6


def test_deterministic_bytes(tmp_path: Path, ds4: Path) -> None:
    a = tmp_path / "a"
    generate_dataset(a, SynthParams(seed=3, **SMALL))
    for f in ["annotations.json", "truth.json", "vanishing_points.json",
              *[f"images/{n}" for n in synthetic_image_names(4)]]:
        assert (a / f).read_bytes() == (ds4 / f).read_bytes(), f
    b = tmp_path / "b"
    generate_dataset(b, SynthParams(seed=4, **SMALL))
    assert (b / "images/synth_0000.png").read_bytes() != (a / "images/synth_0000.png").read_bytes()
    assert (b / "truth.json").read_bytes() != (a / "truth.json").read_bytes()


def test_image_does_not_depend_on_n_images() -> None:
    p2 = SynthParams(seed=9, n_images=2, sizes=[[640, 480]])
    p7 = SynthParams(seed=9, n_images=7, sizes=[[640, 480]])
    a, b = render_synthetic_image(p2, 1), render_synthetic_image(p7, 1)
    assert np.array_equal(a.rgb, b.rgb) and a.truth == b.truth


def test_instances_are_textured_for_sift(truth12: list) -> None:
    import cv2

    sift = cv2.SIFT_create()
    s = next(x for x in truth12 if not x.truth["hard"])
    kp = sift.detect(cv2.cvtColor(s.rgb, cv2.COLOR_RGB2GRAY), None)
    xy = np.array([k.pt for k in kp])
    counts = []
    for a in s.annotations:
        x, y, w, h = a["bbox"]
        counts.append(int(((xy[:, 0] >= x) & (xy[:, 0] < x + w) & (xy[:, 1] >= y)
                           & (xy[:, 1] < y + h)).sum()))
    assert np.median(counts) >= 12
