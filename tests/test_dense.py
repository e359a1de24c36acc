"""The dense RP source (rescu.extension.dense), its combination with stage I
(rescu.discovery.sources) and its pipeline step."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from rescu import io, pipeline
from rescu.discovery.ablation import SOURCE_ROWS
from rescu.discovery.sources import DenseParams, combine_sources
from rescu.extension.boxmaps import box_contrast
from rescu.extension.dense import (central_colours, dense_candidates, dense_patterns,
                                  feature_blobs, find_dense, split_by_colour,
                                  touching_sides)
from rescu.extension.objects import colour_integrals
from rescu.types import ImageResult, Instance, Pattern


def _map(rng, objects):
    """An (8, 60, 80) unit feature map: background direction plus noise, and square
    objects ``(kind, y, x, side)`` painted with the kind's own direction."""
    dirs = np.eye(8)
    f = dirs[0][:, None, None] + 0.05 * rng.normal(size=(8, 60, 80))
    for kind, y, x, a in objects:
        f[:, y:y + a, x:x + a] = dirs[kind][:, None, None] + 0.05 * rng.normal(size=(8, a, a))
    f /= np.linalg.norm(f, axis=0, keepdims=True)
    return f.astype(np.float32)


OBJECTS = ([(1, 5, 5 + 15 * i, 3) for i in range(4)]          # kind 1: four 3 x 3 blobs
           + [(2, 40, 10 + 20 * i, 4) for i in range(3)])    # kind 2: three 4 x 4 blobs


def _params(**over):
    return DenseParams.from_dict({**DenseParams.from_dict(None).__dict__, **over})


def test_blobs_sit_on_the_objects_strongest_first():
    f = _map(np.random.default_rng(0), OBJECTS)
    cells, resp, emb = feature_blobs(f, (2, 3, 4, 5), 3, 50)
    assert np.all(np.diff(resp) <= 0) and emb.shape == (len(cells), 8)
    centres = {(y + a / 2, x + a / 2) for _, y, x, a in OBJECTS}
    top = cells[:len(OBJECTS)]
    for _, y, x in top:     # each of the strongest blobs lies on an object
        assert min(abs(y + 0.5 - cy) + abs(x + 0.5 - cx) for cy, cx in centres) <= 2.0


def test_blobs_stay_inside_the_map():
    # objects cut by the left and top edges: no blob window may leave the map (its ring
    # would be reflected features); the whole objects inside are still found
    f = _map(np.random.default_rng(3), OBJECTS + [(3, 20, 0, 3), (3, 0, 40, 2)])
    sizes = (2, 3, 4, 5)
    cells, _, _ = feature_blobs(f, sizes, 3, 300)
    a = np.array([sizes[s] for s in cells[:, 0]]) / 2.0
    assert np.all(cells[:, 1] + 0.5 - a >= 0) and np.all(cells[:, 2] + 0.5 - a >= 0)
    assert np.all(cells[:, 1] + 0.5 + a <= f.shape[1])
    assert np.all(cells[:, 2] + 0.5 + a <= f.shape[2])
    centres = [(y + k / 2, x + k / 2) for _, y, x, k in OBJECTS]
    for cy, cx in centres:
        assert any(abs(y + 0.5 - cy) + abs(x + 0.5 - cx) <= 2.0 for _, y, x in cells[:10])


def test_dense_patterns_group_each_kind_into_one_rp():
    f = _map(np.random.default_rng(1), OBJECTS)
    rps = dense_patterns(f, 8.0, _params(sizes=(2, 3, 4, 5), max_patterns=5))
    assert sorted(len(b) for _, b in rps[:2]) == [3, 4], [len(b) for _, b in rps]
    # what else groups (the background's noise) ranks far below the objects
    assert all(s < 0.2 * rps[1][0] for s, _ in rps[2:])
    for _, boxes in rps[:2]:  # the box centres, in cells, are on one kind's objects
        cy = (boxes[:, 1] + boxes[:, 3] / 2) / 8.0
        kinds = {k for k, y, x, a in OBJECTS for c in cy if abs(c - (y + a / 2)) < 2}
        assert len(kinds) == 1


def test_touching_sides_counts_abutting_neighbours():
    grid = np.array([[10.0 * c, 10.0 * r, 10, 10] for r in range(3) for c in range(3)])
    sides = touching_sides(grid, 0.35)
    assert sides[4] == 4 and sides[0] == 2 and sides[1] == 3   # centre, corner, edge
    spaced = grid * [2, 2, 1, 1]                                 # gaps of one box side
    assert touching_sides(spaced, 0.35).sum() == 0
    assert touching_sides(grid[:1], 0.35).tolist() == [0.0]


def test_dense_patterns_drop_a_group_that_tiles_the_plane():
    # a 3 x 8 block of kind-3 tiles with one-cell joints, beside the spaced objects
    tiles = [(3, 20 + 5 * r, 10 + 5 * c, 4) for r in range(3) for c in range(8)]
    f = _map(np.random.default_rng(3), OBJECTS + tiles)
    keep_all = dense_patterns(f, 8.0, _params(sizes=(2, 3, 4, 5), max_patterns=5,
                                             max_touching=4.0))
    tiled = [b for _, b in keep_all if touching_sides(b, 0.35).mean() > 0.5]
    assert len(tiled) == 1 and len(tiled[0]) >= 20           # the tiles group ...
    kept = dense_patterns(f, 8.0, _params(sizes=(2, 3, 4, 5), max_patterns=5))
    assert len(kept) == len(keep_all) - 1                    # ... is what the default drops
    assert sorted(len(b) for _, b in kept[:2]) == [3, 4]


def test_central_colours_are_those_of_the_box_centre():
    # a white image with a black 20 x 20 square whose box has white corners: the mean
    # over the central half is the square's, not a mixture
    rgb = np.full((60, 60, 3), 255, np.uint8)
    rgb[20:40, 20:40] = 0
    lab = central_colours(colour_integrals(rgb), np.array([[15.0, 15, 30, 30],
                                                           [0.0, 0, 10, 10]]))
    assert lab.shape == (2, 3)
    assert lab[0, 0] == 0 and lab[1, 0] == 255
    # boxes cut by the border are clipped, never empty
    edge = central_colours(colour_integrals(rgb), np.array([[-10.0, -10, 8, 8]]))
    assert np.isfinite(edge).all()


def test_split_by_colour_leaves_one_coloured_groups_alone():
    labels = np.array([1, 1, 1, 2, 2, 2])
    colours = np.array([[10, 128, 128], [30, 128, 128], [20, 120, 130],
                        [200, 128, 128], [210, 128, 128], [30, 128, 128]], float)
    # group 1 is one colour (spread 20): kept; group 2 holds two light and one dark blob
    out = split_by_colour(labels, colours, 60.0, 2)
    assert len(set(out[:3])) == 1
    assert out[3] == out[4] and out[5] != out[3] and out[5] not in out[:3]
    # groups too small to be an RP are not split
    assert split_by_colour(labels, colours, 60.0, 4).tolist() == labels.tolist()


def test_dense_candidates_split_alike_features_of_two_colours():
    # one kind of object in the feature map (the backbone sees them alike), painted
    # dark and light in the image: with max_colour_distance one group per colour
    objects = [(1, 5 + 25 * (i // 4), 5 + 18 * (i % 4), 4) for i in range(8)]
    f = _map(np.random.default_rng(4), objects)
    rgb = np.full((60 * 8, 80 * 8, 3), 128, np.uint8)
    for i, (_, y, x, a) in enumerate(objects):
        rgb[y * 8:(y + a) * 8, x * 8:(x + a) * 8] = 30 if i % 2 else 230
    params = _params(sizes=(2, 3, 4, 5), min_instances=3)

    def colour_of(boxes):
        return central_colours(colour_integrals(rgb), boxes)

    # the objects' groups rank first (best score first); the background's noise after
    whole = dense_candidates(f, 8.0, params)
    assert len(whole[0].boxes) == 8
    split = dense_candidates(f, 8.0, _params(sizes=(2, 3, 4, 5), min_instances=3,
                                             max_colour_distance=60.0), colour_of=colour_of)
    assert [len(c.boxes) for c in split[:2]] == [4, 4]
    for c in split[:2]:                  # each group holds one colour
        assert np.ptp(colour_of(c.boxes)[:, 0]) < 60
    # without colour_of (or at 0) the groups are those of the features alone
    assert [len(c.boxes) for c in dense_candidates(
        f, 8.0, _params(sizes=(2, 3, 4, 5), min_instances=3, max_colour_distance=60.0))[:1]] == [8]


def test_box_contrast_is_high_on_objects_and_low_on_background():
    f = _map(np.random.default_rng(2), OBJECTS)
    on = box_contrast(f, np.array([[40.0, 40.0, 24, 24]]), 8.0)   # the first kind-1 object
    off = box_contrast(f, np.array([[300.0, 200.0, 24, 24]]), 8.0)
    assert on[0] > 0.5 > 0.1 > off[0]


def test_params_are_checked():
    for bad in ({"mode": "sparse"}, {"surround": 4}, {"sizes": []}, {"min_similarity": 1.0},
                {"min_instances": 1}, {"overlap_iod": 1.5}, {"max_side": 10},
                {"max_touching": 5}, {"touch_tolerance": 0.5}, {"min_side": 2000},
                {"objectness_crops": -1}, {"objectness_px": 16}, {"objectness_context": 0.5}):
        with pytest.raises(ValueError):
            _params(**bad)
    with pytest.raises(ValueError, match="unknown"):
        DenseParams.from_dict({"nonsense": 1})


def _pattern(boxes, source=None):
    return Pattern(id=9, score=1.0, instances=[Instance(bbox=tuple(b)) for b in boxes],
                   extra={"source": source} if source else {})


def test_combine_sources_drops_dense_instances_on_stage1_ones():
    sparse = [_pattern([(0, 0, 10, 10), (20, 0, 10, 10)])]
    dense = [_pattern([(1, 1, 8, 8), (50, 50, 10, 10), (70, 50, 10, 10), (90, 50, 10, 10)],
                      "dense"),
             _pattern([(2, 2, 6, 6), (21, 1, 8, 8), (100, 0, 10, 10)], "dense")]
    both = combine_sources(sparse, dense, _params(mode="both", min_instances=3))
    assert [p.id for p in both] == [0, 1] and both[1].count == 3
    assert both[1].extra["source"] == "dense"
    only = combine_sources(sparse, dense, _params(mode="dense"))
    assert [p.count for p in only] == [4, 3] and [p.id for p in only] == [0, 1]


def test_combine_sources_keeps_one_box_per_object_of_a_dense_rp():
    # a plain and a turned box on one coin: each covers over part_cover (0.5) of the
    # other while their IoU is under 0.5; the weaker goes, the rest of the RP stays
    coin = [Instance(bbox=(0, 0, 40, 40), score=0.9), Instance(bbox=(10, -10, 24, 60), score=0.6)]
    rest = [Instance(bbox=(60 * k, 0, 40, 40), score=0.8) for k in (1, 2, 3)]
    rp = Pattern(id=0, score=1.0, instances=coin + rest, extra={"source": "dense"})
    out = combine_sources([], [rp], _params(mode="objects", min_instances=3))
    assert [i.bbox for i in out[0].instances] == [(0, 0, 40, 40)] + [i.bbox for i in rest]
    assert out[0].extra == rp.extra and len(rp.instances) == 5  # the input unchanged
    # too few left: the RP goes; an RP without such pairs is passed on as it is
    pair = Pattern(id=1, score=1.0, instances=coin, extra={"source": "dense"})
    assert combine_sources([], [pair], _params(mode="objects", min_instances=2)) == []
    alone = Pattern(id=2, score=1.0, instances=rest, extra={"source": "dense"})
    assert combine_sources([], [alone], _params(mode="objects"))[0] is alone


def _photo(rng):
    """A grey noisy floor with five red discs and four blue squares (40 px)."""
    img = np.clip(150 + rng.normal(0, 8, (360, 480, 3)), 0, 255).astype(np.uint8)
    truth = []
    for i in range(5):
        x, y = 40 + 90 * i, 70
        cv2.circle(img, (x + 20, y + 20), 20, (200, 30, 30), -1)
        truth.append((x, y, 40, 40))
    for i in range(4):
        x, y = 60 + 100 * i, 240
        img[y:y + 40, x:x + 40] = (30, 40, 190)
    return img, np.array(truth, float)


def test_turned_maps_make_objects_lengthwise_and_crosswise_alike():
    """With ``rotations`` 2 (4) a map is the mean of the maps of the image turned by 0 and
    90 degrees (every right angle), turned back: bars lying along x and along y, alike
    only when turned, get closer features; the map keeps the plain map's cells (the image
    padded to a multiple of 16 pixels first), and 1 is the plain map itself."""
    from rescu.extension.backbone import FrozenBackbone
    from rescu.extension.boxmaps import box_features
    from rescu.extension.dense import hypercolumn

    img = np.full((203, 250, 3), 170, np.uint8)          # odd sizes: padded to 208 x 256
    along = [(20 + 60 * i, 40, 48, 16) for i in range(3)]          # x, y, w, h
    across = [(30 + 60 * i, 120, 16, 48) for i in range(3)]
    for x, y, w, h in along + across:
        img[y:y + h, x:x + w] = (40, 60, 160)
        img[y + h // 4:y + 3 * h // 4, x + w // 4:x + 3 * w // 4] = (220, 200, 60)
    bb = FrozenBackbone("efficientnet-lite0", feature_stride=16)
    plain = hypercolumn(bb, img)
    f8, _ = bb.multiscale_maps(img)
    assert plain.shape[1:] == tuple(f8.shape[2:])
    sims = {}
    for r in (1, 2, 4):
        f = plain if r == 1 else hypercolumn(bb, img, r)
        assert f.shape == plain.shape and f.dtype == np.float32
        n = np.linalg.norm(f, axis=0)   # the stride-16 half is interpolated between cells
        assert n.max() < 1 + 1e-5 and n.min() > 0.75
        e = box_features(f, 8.0, np.array(along + across, float))
        sims[r] = float((e[:3] @ e[3:].T).mean())
    assert sims[2] > sims[1] + 0.05 and sims[4] > sims[1] + 0.05, sims
    assert np.array_equal(hypercolumn(bb, img, 1), plain)
    with pytest.raises(ValueError, match="rotations"):
        hypercolumn(bb, img, 3)
    with pytest.raises(ValueError, match="rotations"):
        _params(rotations=3)


def test_completion_finds_the_objects_lying_the_other_way():
    """The prototype of bars lying along x, correlated over the turned map
    (:func:`turned_map`: the image turned by 90 degrees, its map turned back onto the
    same cells), finds the bars lying along y, with their boxes turned; on the plain map
    alone they are not found."""
    from rescu.extension.backbone import FrozenBackbone
    from rescu.extension.turned import complete_turned, hypercolumn, turned_map
    from rescu.extension.objects import complete_group

    img = np.full((203, 250, 3), 170, np.uint8)          # odd sizes: padded to 208 x 256
    along = [(20 + 70 * i, 30, 48, 16) for i in range(3)]          # x, y, w, h
    across = [(30 + 70 * i, 110, 16, 48) for i in range(3)]
    for x, y, w, h in along + across:
        img[y:y + h, x:x + w] = (40, 60, 160)
        img[y + h // 4:y + 3 * h // 4, x + w // 4:x + 3 * w // 4] = (220, 200, 60)
    bb = FrozenBackbone("efficientnet-lite0", feature_stride=16)
    f = hypercolumn(bb, img)
    t = turned_map(bb, img)
    assert t.shape == f.shape and t.dtype == np.float32
    assert np.linalg.norm(t, axis=0).min() > 0.75
    seeds = np.array(along, float)
    plain = complete_group(f, 8.0, seeds, 0.1, 0.55)[0]
    boxes, sims, is_turned = complete_turned(f, t, 8.0, seeds, 0.1, 0.55)
    assert len(plain) == 3 and np.array_equal(boxes[~is_turned], plain)
    assert is_turned.sum() == 3 and (np.diff(sims) <= 0).all()
    found = boxes[is_turned]
    assert (found[:, 2:] == [16, 48]).all()               # turned: 2 x 6 cells
    for x, y, w, h in across:            # one box on each bar across, within a cell or so
        cx, cy = found[:, 0] + found[:, 2] / 2, found[:, 1] + found[:, 3] / 2
        assert ((abs(cx - (x + w / 2)) <= 12) & (abs(cy - (y + h / 2)) <= 12)).sum() == 1
    with pytest.raises(ValueError, match="shape"):
        complete_turned(f, t[:, 1:], 8.0, seeds, 0.1, 0.55)


def test_find_dense_finds_the_discs_in_original_pixels():
    img, truth = _photo(np.random.default_rng(3))
    p = _params(max_patterns=4)                  # 480 px: upscaled to min_side = 960
    native = _params(max_patterns=4, min_side=240)
    down = _params(max_patterns=4, min_side=240, max_side=400)
    pats = find_dense(img, p)
    assert pats and all(q.extra["source"] == "dense" for q in pats)
    small = cv2.resize(img, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    # 240 px at its own size: the 20-px discs' boxes (15 px after the extent) span about
    # 30 px of the fine map (2x), more than min_map_px (one stride-16 cell): found; a
    # gate of two cells drops them
    tiny = find_dense(small, _params(max_patterns=4, min_side=240, min_map_px=32),
                      scale_factor=0.5)
    assert not any(np.median([i.bbox[2] for i in q.instances]) < 35 for q in tiny)
    runs = [pats, find_dense(small, p, scale_factor=0.5),   # processed = original x 0.5
            find_dense(img, native), find_dense(img, down),
            find_dense(small, native, scale_factor=0.5)]
    for found in runs:
        best = 0
        for q in found:
            b = np.array([i.bbox for i in q.instances])
            cx, cy = b[:, 0] + b[:, 2] / 2, b[:, 1] + b[:, 3] / 2
            on = [(abs(cx - (t[0] + 20)) < 20) & (abs(cy - (t[1] + 20)) < 20) for t in truth]
            best = max(best, int(np.any(on, 1).sum()) if len(on) else 0)
        assert best >= 4, best
    with pytest.raises(ValueError, match="uint8"):
        find_dense(img.astype(float), p)


def test_dense_step_and_rescu_i_with_it(tmp_path):
    img, _ = _photo(np.random.default_rng(4))
    photo = tmp_path / "floor.png"
    cv2.imwrite(str(photo), img[:, :, ::-1])
    w = lambda n: str(tmp_path / n)  # noqa: E731
    from rescu.config import load_config

    cfg = load_config(stage2=False)
    assert pipeline.prepare(str(photo), w("p.png"), w("m.json"), image_name="floor.png",
                            max_side=cfg["image"]["max_side"],
                            min_side=cfg["image"]["min_side"]) is None
    pipeline.features(w("p.png"), w("m.json"), w("f.h5"), cfg["features"])
    assert pipeline.dense(w("p.png"), w("m.json"), w("d.json"), cfg["dense"]) is None
    found = ImageResult.from_json(io.read_json(w("d.json")))
    assert found.method == "dense" and found.patterns
    pipeline.stage1(w("f.h5"), w("m.json"), w("s.json"), w("s.h5"), cfg["stage1"],
                    png=w("p.png"), dense_json=w("d.json"), dense_params=cfg["dense"])
    res = ImageResult.from_json(io.read_json(w("s.json")))
    n_dense = sum(p.extra.get("source") == "dense" for p in res.patterns)
    assert n_dense >= 1 and res.extra["n_dense_patterns"] == n_dense
    # an unreadable prepared image: the dense step records the failure, RESCU-I keeps
    # stage I's RPs and says the dense source failed
    (tmp_path / "bad.png").write_bytes(b"not a png")
    f = pipeline.dense(w("bad.png"), w("m.json"), w("d2.json"), cfg["dense"])
    assert f is not None and "bad.png" in f["message"]
    assert json.loads((tmp_path / "d2.json").read_text())["patterns"] == []
    pipeline.stage1(w("f.h5"), w("m.json"), w("s2.json"), w("s2.h5"), cfg["stage1"],
                    png=w("p.png"), dense_json=w("d2.json"), dense_params=cfg["dense"])
    res2 = ImageResult.from_json(io.read_json(w("s2.json")))
    assert "dense_failure" in res2.extra and "failure" not in res2.extra
    assert all(p.extra.get("source") != "dense" for p in res2.patterns)
    # mode dense: the stage-I search is not run (its RPs would be dropped); with a failed
    # dense step it is, and its RPs stay
    only = dict(cfg["dense"], mode="dense")
    pipeline.stage1(w("f.h5"), w("m.json"), w("s3.json"), w("s3.h5"), cfg["stage1"],
                    png=w("p.png"), dense_json=w("d.json"), dense_params=only)
    res3 = ImageResult.from_json(io.read_json(w("s3.json")))
    assert res3.extra["chosen_by"] == "skipped" and io.read_h5(w("s3.h5"))[1]["n_rps"] == 0
    assert [len(p.instances) for p in res3.patterns] == \
        [len(p.instances) for p in found.patterns]
    assert all(p.extra.get("source") == "dense" for p in res3.patterns)
    pipeline.stage1(w("f.h5"), w("m.json"), w("s4.json"), w("s4.h5"), cfg["stage1"],
                    png=w("p.png"), dense_json=w("d2.json"), dense_params=only)
    res4 = ImageResult.from_json(io.read_json(w("s4.json")))
    assert res4.extra["chosen_by"] != "skipped" and "dense_failure" in res4.extra
    assert [p.to_json() for p in res4.patterns] == [p.to_json() for p in res2.patterns]
    # the stage-I ablation's source rows: stage I alone, the dense RPs alone, both; with a
    # failed dense step the dense-only row is empty and the both row is stage I's
    rows = {n: w(f"a_{i}.json") for i, n in enumerate(["all", *SOURCE_ROWS])}
    assert pipeline.ablation(w("f.h5"), w("m.json"), rows, cfg["stage1"],
                             {"all": ["P_d", "P_s", "P_theta"]}, png=w("p.png"),
                             dense_json=w("d.json"), dense_params=cfg["dense"]) is None
    got = {n: ImageResult.from_json(io.read_json(p)) for n, p in rows.items()}
    assert got["sparse-only"].method == "rescu-i[sparse-only]"
    assert [p.to_json() for p in got["sparse-only"].patterns] == \
        [p.to_json() for p in got["all"].patterns]           # the same parameters, reused
    assert [len(p.instances) for p in got["dense-only"].patterns] == \
        [len(p.instances) for p in found.patterns]
    both = dict(cfg["dense"], mode="both")
    pipeline.stage1(w("f.h5"), w("m.json"), w("s5.json"), w("s5.h5"), cfg["stage1"],
                    png=w("p.png"), dense_json=w("d.json"), dense_params=both)
    res5 = ImageResult.from_json(io.read_json(w("s5.json")))
    assert [p.to_json() for p in got["sparse+dense"].patterns] == \
        [p.to_json() for p in res5.patterns]          # = RESCU-I with the source, mode both
    assert pipeline.ablation(w("f.h5"), w("m.json"), rows, cfg["stage1"],
                             {"all": ["P_d", "P_s", "P_theta"]}, png=w("p.png"),
                             dense_json=w("d2.json"), dense_params=cfg["dense"]) is None
    got = {n: ImageResult.from_json(io.read_json(p)) for n, p in rows.items()}
    assert got["dense-only"].patterns == [] and "dense_failure" in got["dense-only"].extra
    assert [p.to_json() for p in got["sparse+dense"].patterns] == \
        [p.to_json() for p in got["sparse-only"].patterns]
    # an unreadable dense result costs the source rows only, never the variants' results
    (tmp_path / "d3.json").write_text("{not json")
    assert pipeline.ablation(w("f.h5"), w("m.json"), rows, cfg["stage1"],
                             {"all": ["P_d", "P_s", "P_theta"]}, png=w("p.png"),
                             dense_json=w("d3.json"), dense_params=cfg["dense"]) is None
    got = {n: ImageResult.from_json(io.read_json(p)) for n, p in rows.items()}
    assert "failure" not in got["all"].extra and got["all"].patterns
    assert got["dense-only"].extra["dense_failure"]["stage"] == "dense"
    # ... and RESCU-I falls back to stage I, as for a failed dense step, naming the file
    for mode in ("both", "dense"):
        assert pipeline.stage1(w("f.h5"), w("m.json"), w("s5.json"), w("s5.h5"),
                               cfg["stage1"], png=w("p.png"), dense_json=w("d3.json"),
                               dense_params=dict(cfg["dense"], mode=mode)) is None
        res5 = ImageResult.from_json(io.read_json(w("s5.json")))
        assert "failure" not in res5.extra and "d3.json" in res5.extra["dense_failure"]["message"]
        assert [p.to_json() for p in res5.patterns] == [p.to_json() for p in res2.patterns]


class _Classifier:
    """A stand-in backbone with two classes: the top-class probability of a crop is
    0.5 + 0.5 x its mean brightness / 255, and every batch it is given is kept."""

    def __init__(self):
        self.batches = []

    def class_probabilities(self, crops):
        self.batches.append(np.asarray(crops))
        top = 0.5 + 0.5 * np.asarray(crops, float).mean((1, 2, 3)) / 255.0
        return np.stack([top, 1.0 - top], 1)


def test_objectness_crops_the_first_instances_with_context():
    from rescu.extension.dense import objectness

    img = np.zeros((100, 200, 3), np.uint8)
    img[20:40, 20:40] = 255                       # a bright object, a dark one beside it
    net = _Classifier()
    p = _params(objectness_crops=2, objectness_px=32, objectness_context=1.0)
    boxes = np.array([[20, 20, 20, 20], [120, 20, 20, 20], [20, 20, 20, 20]], float)
    assert objectness(net, img, boxes, p) == pytest.approx(0.75)  # (1 + 0.5) / 2: 2 crops
    assert net.batches[-1].shape == (2, 32, 32, 3)
    # with context 2 the bright crop is a quarter object; a box at the border is cut
    assert objectness(net, img, boxes[:1], _params(objectness_crops=2, objectness_context=2.0,
                                                   objectness_px=32)) \
        == pytest.approx(0.625, abs=0.01)
    assert 0 <= objectness(net, img, np.array([[190, 90, 30, 30]], float), p) <= 1
    assert objectness(net, img, boxes, _params(objectness_crops=0)) == 1.0
    assert objectness(net, img, np.zeros((0, 4)), p) == 1.0


def test_rank_candidates_multiplies_the_score_by_objectness():
    from rescu.extension.dense import DenseCandidate, rank_candidates

    a = DenseCandidate(boxes=np.array([[0, 0, 8, 8.]]), score=0.4, touching=0.0)
    b = DenseCandidate(boxes=np.array([[50, 0, 8, 8.]]), score=0.3, touching=0.0)
    assert [c.score for c in rank_candidates([b, a], None)] == [0.4, 0.3]
    got = rank_candidates([a, b], lambda boxes: 0.5 if boxes[0, 0] == 0 else 1.0)
    assert [c.score for c in got] == [0.3, 0.2] and got[0].boxes[0, 0] == 50
    # with top: the same first ones, and no classification of a candidate that cannot enter
    rng = np.random.default_rng(0)
    many = [DenseCandidate(boxes=np.array([[float(i), 0, 8, 8]]), score=float(v), touching=0.0)
            for i, v in enumerate(rng.random(30))]
    obj = dict(enumerate(rng.random(30)))
    seen = []

    def of(boxes):
        seen.append(int(boxes[0, 0]))
        return obj[int(boxes[0, 0])]

    full = rank_candidates(many, lambda boxes: obj[int(boxes[0, 0])])
    for top in (1, 3, 30):
        seen.clear()
        cut = rank_candidates(many, of, top)
        assert [(c.score, c.boxes[0, 0]) for c in cut] == \
            [(c.score, c.boxes[0, 0]) for c in full[:top]]
        assert top == 30 or len(seen) < 30


def test_iter_level_candidates_ranks_both_maps_and_classifies_only_what_it_yields(
        monkeypatch):
    from rescu.extension import dense as D

    rng = np.random.default_rng(1)
    per_level = [[D.DenseCandidate(boxes=np.array([[float(i), float(k), 8, 8]]),
                                   score=float(v), touching=0.0, level=k)
                  for i, v in enumerate(rng.random(20))] for k in range(2)]
    obj = {(k, i): float(v) for k in range(2) for i, v in enumerate(rng.random(20))}
    seen = []

    def objectness_for(rgb, s, params, backbone):
        def of(boxes):
            key = (int(boxes[0, 1]), int(boxes[0, 0]))
            seen.append(key)
            return obj[key]
        return of

    monkeypatch.setattr(D, "_flat_candidates",
                        lambda f, params, sizes=None, level=0, colour_of=None:
                        per_level[level])
    monkeypatch.setattr(D, "objectness_for", objectness_for)
    levels = [(np.zeros((1, 4, 4), np.float32), 1.0), (np.zeros((1, 8, 8), np.float32), 2.0)]
    params = _params(max_candidates=12)
    # every group classified and sorted by the final score (ties: level, top, left)
    expect = sorted(((c.score * obj[(k, int(c.boxes[0, 0]))], k, int(c.boxes[0, 0]))
                     for k in range(2) for c in per_level[k]),
                    key=lambda t: (-t[0], t[1], 0.0, t[2]))[:12]
    got = D.level_candidates(levels, None, params)
    assert [(c.score, c.level, int(c.boxes[0, 0])) for c in got] == expect
    assert len(seen) < 40           # the groups that cannot enter the first 12 are not classified
    # a reader that stops after two groups classifies fewer still, and gets the same two
    seen.clear()
    it = D.iter_level_candidates(levels, None, params)
    first = [next(it), next(it)]
    assert [(c.score, c.level, int(c.boxes[0, 0])) for c in first] == expect[:2]
    n_two = len(seen)
    seen.clear()
    D.level_candidates(levels, None, params)
    assert n_two < len(seen)


def test_find_dense_with_and_without_objectness():
    img, truth = _photo(np.random.default_rng(3))
    on, off = find_dense(img, _params(max_patterns=4)), \
        find_dense(img, _params(max_patterns=4, objectness_crops=0))
    assert on and off and all(0 < q.score for q in on)
    # objectness is a probability: it can only lower a group's score
    assert max(q.score for q in on) <= max(q.score for q in off) + 1e-12


def test_rescu_i_scores_on_the_map_the_dense_step_kept(tmp_path, monkeypatch):
    """The dense step stores its coarse map; RESCU-I's scoring reads it instead of passing
    the backbone over the image again, with the same result. A map made with other
    settings, or one that cannot be read, is made again; a failed dense step keeps none."""
    from rescu.config import load_config
    from rescu.extension import dense as D

    img, _ = _photo(np.random.default_rng(4))
    cv2.imwrite(str(tmp_path / "floor.png"), img[:, :, ::-1])
    w = lambda n: str(tmp_path / n)  # noqa: E731
    cfg = load_config(stage2=False)
    pipeline.prepare(w("floor.png"), w("p.png"), w("m.json"), image_name="floor.png",
                     max_side=cfg["image"]["max_side"], min_side=cfg["image"]["min_side"])
    pipeline.features(w("p.png"), w("m.json"), w("f.h5"), cfg["features"])
    assert pipeline.dense(w("p.png"), w("m.json"), w("d.json"), cfg["dense"], w("d.h5")) is None
    dp = DenseParams.from_dict(cfg["dense"])
    f, s = D.load_map(w("d.h5"), dp)
    rgb, _ = pipeline.read_prepared(w("p.png"), w("m.json"))
    f0, s0 = D.dense_map(rgb, dp)
    assert s == s0 and np.array_equal(f, f0)      # in memory = stored (half precision)

    def run(name, **kw):
        pipeline.stage1(w("f.h5"), w("m.json"), w(f"{name}.json"), w(f"{name}.h5"),
                        cfg["stage1"], png=w("p.png"), dense_json=w("d.json"),
                        dense_params=cfg["dense"], **kw)
        res = io.read_json(w(f"{name}.json"))
        return res["patterns"], res.get("candidate_patterns")

    D._LAST_MAP.clear()
    made = run("made")                            # no stored map: one backbone pass
    assert any("confidence" in p and p.get("source") != "dense"
               for p in made[0] + (made[1] or []))  # stage I's RPs were scored
    D._LAST_MAP.clear()
    passes = []
    real = D.hypercolumn
    monkeypatch.setattr(D, "hypercolumn", lambda *a: passes.append(1) or real(*a))
    assert run("read", dense_map_h5=w("d.h5")) == made and passes == []
    assert D.load_map(w("d.h5"), DenseParams.from_dict({**cfg["dense"], "max_side": 1200})) \
        is None                                   # other settings: not this map
    (tmp_path / "bad.h5").write_bytes(b"not hdf5")
    with pytest.raises(io.InputError, match="bad.h5"):
        D.load_map(w("bad.h5"), dp)
    D._LAST_MAP.clear()
    assert run("bad", dense_map_h5=w("bad.h5")) == made and passes == [1]
    (tmp_path / "bad.png").write_bytes(b"not a png")
    assert pipeline.dense(w("bad.png"), w("m.json"), w("d2.json"), cfg["dense"],
                          w("d2.h5")) is not None
    assert D.load_map(w("d2.h5"), dp) is None


def test_feature_blobs_embeddings_are_the_unit_window_means():
    """Each blob's embedding is its window's unit mean feature, bit for bit, though only
    the means at each size's in-plane peaks are kept."""
    from rescu.extension.dense import box_means, feature_blobs

    rng = np.random.default_rng(3)
    f = rng.normal(size=(6, 40, 50)).astype(np.float32)
    f /= np.linalg.norm(f, axis=0, keepdims=True)
    sizes = (3, 4, 6)
    cells, resp, emb = feature_blobs(f, sizes, 3, 50)
    assert len(cells) == 50 and np.all(np.diff(resp) <= 0)
    for (s, y, x), e in zip(cells, emb):
        m = box_means(f, sizes[s])
        assert np.array_equal(e, m[:, y, x] / (np.linalg.norm(m, axis=0)[y, x] + 1e-9))


def test_the_dense_step_reads_none_of_the_keys_it_runs_under_fixed_values():
    # the workflow's dense rule gets dense_step_section(config["dense"]): the keys it
    # fixes besides enabled and mode are RESCU-I's selection, which the step must not
    # read, or a change of them would have to rerun it
    from rescu.discovery.sources import DENSE_STEP_FIXED, dense_step_section

    img, _ = _photo(np.random.default_rng(3))
    base = dense_step_section({**DenseParams.from_dict(None).__dict__, "max_patterns": 4})
    other = {"confidence_stage1_score_scale": 0.7, "min_separation": 0.3,
             "min_object_separation": 0.2, "checkerboard_min_corners": 9,
             "checkerboard_border": 1, "checkerboard_min_alternation": 0.9,
             "checkerboard_seed": 5}
    assert set(other) == set(DENSE_STEP_FIXED) - {"enabled", "mode"}
    a = find_dense(img, DenseParams.from_dict(base))
    b = find_dense(img, DenseParams.from_dict({**base, **other}))
    assert a and [p.to_json() for p in a] == [p.to_json() for p in b]
