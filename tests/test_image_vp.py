"""Tests of the image's joint VP estimator: rescu.scene.vp.manhattan (Manhattan triplet and
focal length from several cues), rescu.scene.image_vp (the pipeline step's library call),
rescu.scene.vp.peers (lu-vp-detect) and the triplet / AA@t evaluation of rescu.evaluation.vpd."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rescu.evaluation import vpd as EV
from rescu.scene.image_vp import image_vanishing_points
from rescu.scene.vp.errors import vector_error
from rescu.scene.vp.lines import Lines
from rescu.scene.vp.manhattan import ImageVPParams, manhattan_vps
from rescu.scene.vp.peers import lu_available, lu_vanishing_points
from rescu.types import ImageResult, VanishingPoint

W, H, F = 640, 480, 600.0


def rotation(seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def scene_segments(r: np.ndarray, n_per: int = 40, noise_px: float = 0.3, clutter: int = 30,
                   seed: int = 0, f: float = F) -> np.ndarray:
    """Segments (L, 4) of 3D lines along the three columns of ``r`` (a box in front of a
    camera of focal ``f``, principal point at the centre), plus random clutter."""
    rng = np.random.default_rng(seed)
    k = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    segs = []
    for j in range(3):
        d = r[:, j]
        while sum(1 for s in segs if s[4] == j) < n_per:
            p = rng.uniform([-4, -3, 6], [4, 3, 14])
            a, b = p - d * rng.uniform(0.5, 1.5), p + d * rng.uniform(0.5, 1.5)
            if a[2] < 1 or b[2] < 1:
                continue
            pa, pb = k @ a, k @ b
            pa, pb = pa[:2] / pa[2], pb[:2] / pb[2]
            inside = all(0 <= q[0] < W and 0 <= q[1] < H for q in (pa, pb))
            if inside and np.linalg.norm(pb - pa) > 25:
                segs.append([*(pa + rng.normal(0, noise_px, 2)),
                             *(pb + rng.normal(0, noise_px, 2)), j])
    out = np.array(segs)[:, :4]
    junk = rng.uniform([0, 0, 0, 0], [W, H, W, H], size=(clutter, 4))
    return np.vstack([out, junk])


def truth(r: np.ndarray, f: float = F) -> list[np.ndarray]:
    k = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    return [k @ r[:, j] for j in range(3)]


def errors_to_truth(res, r: np.ndarray, f: float = F) -> list[float]:
    """Each true VP's angle error (degrees, true focal) to the closest estimated VP."""
    vps = [m.vanishing_point.homogeneous for m in res.vps]
    return [min(vector_error(v, t, (W, H), f) for v in vps) for t in truth(r, f)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_known_focal_recovers_the_three_directions(seed: int) -> None:
    r = rotation(seed)
    res = manhattan_vps([("lines", Lines.from_segments(scene_segments(r, seed=seed)), 1.0)],
                        (W, H), focal_px=F)
    assert len(res.vps) == 3 and not res.focal_estimated and res.focal_px == pytest.approx(F)
    # long random clutter segments within 2 degrees of a VP pull it by a few tenths
    assert max(errors_to_truth(res, r)) < 1.0
    clean = manhattan_vps([("lines", Lines.from_segments(scene_segments(r, seed=seed,
                                                                        clutter=0)), 1.0)],
                          (W, H), focal_px=F)
    assert max(errors_to_truth(clean, r)) < 0.3
    # directions: unit, camera frame, each the back-projection of its VP
    for m in res.vps:
        assert np.linalg.norm(m.direction) == pytest.approx(1.0)
        assert vector_error(m.vanishing_point.homogeneous,
                            np.array([F, F, 1.0]) * m.direction + np.r_[W / 2, H / 2, 0]
                            * m.direction[2], (W, H), F) < 1e-6
    # ordered by support; the cue counts add up to the support
    assert [m.weight for m in res.vps] == sorted((m.weight for m in res.vps), reverse=True)
    assert all(sum(m.cues.values()) == m.vanishing_point.support for m in res.vps)


@pytest.mark.parametrize("f_true", [450.0, 900.0])
def test_unknown_focal_is_estimated(f_true: float) -> None:
    r = rotation(7)
    res = manhattan_vps([("lines", Lines.from_segments(scene_segments(r, seed=3, f=f_true)),
                          1.0)], (W, H))
    assert res.focal_estimated
    assert res.focal_px == pytest.approx(f_true, rel=0.05)
    assert max(errors_to_truth(res, r, f_true)) < 1.5   # clutter included (see above)


def test_rp_rows_alone_give_a_vp_and_are_counted_as_their_cue() -> None:
    r = rotation(4)
    segs = scene_segments(r, n_per=12, clutter=0, seed=4)
    lines = Lines.from_segments(segs)
    res = manhattan_vps([("rp_rows", lines, 1.0), ("lines", Lines.empty(), 1.0)], (W, H),
                        focal_px=F)
    assert res.vps and all(set(m.cues) == {"rp_rows"} for m in res.vps)
    # weight 0 leaves a cue out: nothing left
    assert manhattan_vps([("rp_rows", lines, 0.0)], (W, H), focal_px=F) is None


def test_same_input_same_output_and_seed_matters_little() -> None:
    segs = Lines.from_segments(scene_segments(rotation(5), seed=5))
    a = manhattan_vps([("lines", segs, 1.0)], (W, H))
    b = manhattan_vps([("lines", segs, 1.0)], (W, H))
    assert [m.to_json() for m in a.vps] == [m.to_json() for m in b.vps]
    c = manhattan_vps([("lines", segs, 1.0)], (W, H), ImageVPParams(seed=1))
    assert max(vector_error(x.vanishing_point.homogeneous, y.vanishing_point.homogeneous,
                            (W, H), F) for x, y in zip(a.vps, c.vps)) < 0.5


def test_too_few_lines_and_bad_parameters() -> None:
    assert manhattan_vps([("lines", Lines.from_segments(np.zeros((0, 4))), 1.0)], (W, H)) is None
    two = Lines.from_segments(np.array([[0, 0, 10, 10], [5, 0, 5, 50.0]]))
    assert manhattan_vps([("lines", two, 1.0)], (W, H)) is None
    with pytest.raises(ValueError, match="image_size"):
        manhattan_vps([("lines", two, 1.0)], (0, H))
    with pytest.raises(ValueError, match="focal_range"):
        ImageVPParams(focal_range=(2.0, 1.0))
    with pytest.raises(ValueError, match="min_lines"):
        ImageVPParams(min_lines=1)
    with pytest.raises(ValueError, match="unknown"):
        ImageVPParams.from_dict({"focal": 3})


def render(segs: np.ndarray, scale: float = 1.0) -> np.ndarray:
    import cv2

    img = np.full((round(H * scale), round(W * scale), 3), 200, np.uint8)
    for x1, y1, x2, y2 in segs * scale:
        cv2.line(img, (int(round(x1)), int(round(y1))), (int(round(x2)), int(round(y2))),
                 (20, 20, 20), 2, cv2.LINE_AA)
    return img


def test_image_step_sets_the_dominant_vp_and_keeps_the_rp_one() -> None:
    r = rotation(0)
    segs = scene_segments(r, clutter=0, seed=0)
    rgb = render(segs, 0.5)                 # the processed image: half the original size
    rp_vp = VanishingPoint(np.array([1.0, 0.0, 0.0]), False, 3)
    src = ImageResult(image="x.png", width=W, height=H, method="rescu-ii",
                      vanishing_point=rp_vp)
    out = image_vanishing_points(rgb, 0.5, src, focal_px=F)
    assert src.extra == {} and src.vanishing_point is rp_vp      # input untouched
    listed = out.extra["vanishing_points"]
    assert 1 <= len(listed) <= 3
    assert out.vanishing_point.to_json() == {k: listed[0][k] for k in
                                             ("homogeneous", "inside_image", "support")}
    assert out.extra["rp_vanishing_point"] == rp_vp.to_json()
    assert out.extra["focal_px"] == pytest.approx(F) and out.extra["focal_estimated"] is False
    # VPs are in original pixels
    errs = [min(vector_error(np.asarray(v["homogeneous"]), t, (W, H), F) for t in truth(r))
            for v in listed]
    assert max(errs) < 1.5
    json.dumps(out.to_json())


def test_the_joint_step_takes_the_reported_rps_vp_as_its_point_hypothesis(monkeypatch) -> None:
    """Where the scene step's RP-only VP also read the rows of hidden stage-I RPs, the
    joint estimator is offered the VP of the reported RPs (``reported_rp_vanishing_point``,
    possibly none) instead; the RP-only VP is still kept as ``rp_vanishing_point``."""
    import rescu.scene.image_vp as IV

    offered: list[list[np.ndarray]] = []
    monkeypatch.setattr(IV, "manhattan_vps",
                        lambda *a, **k: offered.append(list(k["point_hypotheses"])))
    rgb = np.zeros((H // 2, W // 2, 3), np.uint8)
    with_hidden = VanishingPoint(np.array([0.0, 1.0, 0.0]), False, 9)
    reported = VanishingPoint(np.array([0.6, 0.0, 0.8]), True, 4)
    src = ImageResult(image="x.png", width=W, height=H, method="rescu-ii",
                      vanishing_point=with_hidden,
                      extra={"reported_rp_vanishing_point": reported.to_json()})
    out = image_vanishing_points(rgb, 0.5, src)
    assert out.extra["rp_vanishing_point"] == with_hidden.to_json()
    (point,) = offered[-1]
    np.testing.assert_allclose(np.cross(point, np.diag([0.5, 0.5, 1]) @ reported.homogeneous),
                               0, atol=1e-12)
    src.extra["reported_rp_vanishing_point"] = None
    image_vanishing_points(rgb, 0.5, src)
    assert offered[-1] == []
    del src.extra["reported_rp_vanishing_point"]
    image_vanishing_points(rgb, 0.5, src)
    assert len(offered[-1]) == 1


def test_image_step_on_a_blank_image_is_the_documented_empty_result() -> None:
    rp_vp = VanishingPoint(np.array([0.0, 1.0, 0.0]), False, 3)
    src = ImageResult(image="x.png", width=W, height=H, method="rescu-ii",
                      vanishing_point=rp_vp)
    out = image_vanishing_points(np.zeros((H, W, 3), np.uint8), 1.0, src)
    assert out.extra["vanishing_points"] == [] and out.extra["focal_px"] is None
    assert out.vanishing_point.to_json() == rp_vp.to_json()
    with pytest.raises(ValueError, match="rgb"):
        image_vanishing_points(np.zeros((H, W), np.uint8), 1.0, src)


@pytest.mark.skipif(not lu_available(), reason="lu-vp-detect is not installed "
                    "(pip install --no-deps lu-vp-detect==1.0.4)")
def test_lu_peer_finds_the_frame_of_a_rendered_scene() -> None:
    r = rotation(0)
    rgb = render(scene_segments(r, clutter=0, seed=0))
    vps = lu_vanishing_points(rgb, F)
    assert len(vps) == 3 and vps[0].weight >= vps[1].weight >= vps[2].weight
    errs = [min(vector_error(m.vanishing_point.homogeneous, t, (W, H), F) for m in vps)
            for t in truth(r)]
    assert max(errs) < 3.0


def test_angular_accuracy_and_the_triplet_frame(tmp_path: Path) -> None:
    assert EV.angular_accuracy([0.0, 5.0, float("inf")], 10.0) == pytest.approx(0.5)
    assert np.isnan(EV.angular_accuracy([], 10.0))
    r = rotation(1)
    gts = truth(r)
    ds = tmp_path / "ds"
    ds.mkdir()
    (ds / "vanishing_points.json").write_text(json.dumps({"images": [
        {"file_name": "images/a.png", "width": W, "height": H, "focal_px": F,
         "principal_point": [W / 2, H / 2],
         "vanishing_points": [{"homogeneous": list(g / np.linalg.norm(g))} for g in gts]}]}))
    one, three = tmp_path / "one", tmp_path / "three"
    for d, listed in ((one, gts[:1]), (three, gts)):
        d.mkdir()
        res = ImageResult(image="images/a.png", width=W, height=H, method="m",
                          vanishing_point=VanishingPoint(listed[0], False, 5))
        if len(listed) > 1:
            res.extra["vanishing_points"] = [VanishingPoint(v, False, 5).to_json()
                                             for v in listed]
        (d / "a.json").write_text(json.dumps(res.to_json()))
    tri = EV.vp_triplet_frame(ds, {"one": one, "three": three})
    assert len(tri) == 6
    t3 = tri[tri["method"] == "three"]
    assert (t3["angle_error_deg"] < 1e-4).all() and (t3["n_listed"] == 3).all()
    t1 = tri[tri["method"] == "one"].set_index("gt_index")["angle_error_deg"]
    assert t1[0] < 1e-4 and t1[1] > 45 and t1[2] > 45   # orthogonal to the one listed
    errors = EV.vp_frame(ds, {"one": one, "three": three})
    assert "angle_error_nominal_deg" in errors
    aa = EV.vp_aa_table(errors, tri, (3, 10))
    a = aa.set_index(["method", "target", "focal"])
    assert a.loc[("three", "triplet", "true"), "AA@10"] == pytest.approx(1.0, abs=1e-4)
    assert a.loc[("one", "triplet", "true"), "AA@10"] == pytest.approx(1 / 3, abs=1e-4)
    assert a.loc[("one", "dominant", "true"), "AA@3"] == pytest.approx(1.0, abs=1e-4)
    md = EV.vp_aa_markdown(aa)
    assert "| three | triplet | true | 3 | 1.00 | 1.00 |" in md and "AA@10" in md


def test_point_errors_at_infinity_get_a_sentence_not_a_table() -> None:
    import pandas as pd

    e = pd.DataFrame({"dataset": ["d", "d"], "image": ["a", "b"], "method": ["m", "m"],
                      "vp_missing": [False, False], "point_error_px": [np.inf, np.inf],
                      "angle_error_deg": [0.5, 1.0], "angle_error_nominal_deg": [0.5, 1.0],
                      "focal_px": [10.0, 10.0], "focal_source": ["assumed"] * 2,
                      "n_gt_vps": [2, 2]})
    md = EV.vp_markdown(EV.vp_success_table(e, (5,), (1, 5)), errors=e)
    assert "Point errors are undefined here" in md and "≤ 5 px" not in md
    assert "| m | 1.00 | 1.00 |" in md
