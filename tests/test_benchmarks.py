"""The benchmark scripts' own argument handling (their figures come from finished runs)."""

import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def load(name):
    sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location(name, BENCH / "studies" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_stage2_variants_sets_and_refusals(tmp_path, capsys):
    sv = load("stage2_variants")
    sets = sv.parse_sets(["examples.occlude_prob=0.5", "backbone.finetune=true",
                          "proposals.window_scales=[1, 1.2]", "backbone.device=cuda"])
    assert sv.nested(sets) == {"examples": {"occlude_prob": 0.5},
                               "backbone": {"finetune": True, "device": "cuda"},
                               "proposals": {"window_scales": [1, 1.2]}}
    with pytest.raises(ValueError, match="KEY=VALUE"):
        sv.parse_sets(["occlude_prob"])
    # an unknown or invalid stage2 key is a usage error naming it
    with pytest.raises(SystemExit):
        sv.main([str(tmp_path), "--set", "no_such_key=1"])
    assert "no_such_key" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        sv.main([str(tmp_path), "--set", "examples.occlude_prob=3"])
    assert "occlude_prob" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        sv.main([str(tmp_path), "--set", "occlude_prob=0.5"])   # not in its section
    assert "occlude_prob" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        sv.main([str(tmp_path), "--set", "examples.occlude_prob=0.5", "--threads", "0"])
    assert "--threads must be at least 1" in capsys.readouterr().err
    # a results folder without a run: a clear message, exit 2, nothing written
    assert sv.main([str(tmp_path), "--set", "examples.occlude_prob=0.5"]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    assert not (tmp_path / "benchmarks").exists()


def test_stage2_variants_refuses_a_folder_of_other_settings(tmp_path, capsys):
    sv = load("stage2_variants")
    for d in ("prepared", "rescu-i", "rescu-ii"):
        (tmp_path / "synthetic" / d).mkdir(parents=True)
    (tmp_path / "data" / "synthetic").mkdir(parents=True)
    (tmp_path / "data" / "synthetic" / "annotations.json").write_text(
        '{"images": [], "annotations": [], "categories": []}')
    assert sv.main([str(tmp_path), "--name", "v", "--set", "examples.occlude_prob=0.5"]) == 0
    assert "no image" in capsys.readouterr().out
    assert (tmp_path / "benchmarks" / "stage2-variants" / "v" / "params.json").is_file()
    assert sv.main([str(tmp_path), "--name", "v", "--set", "examples.occlude_prob=0.5"]) == 0
    assert sv.main([str(tmp_path), "--name", "v", "--set", "examples.occlude_prob=0.3"]) == 2
    assert "other settings" in capsys.readouterr().err


def test_stage2_misses_without_a_run(tmp_path, capsys):
    sm = load("stage2_misses")
    assert sm.main([str(tmp_path)]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    # a run whose RESCU-II found everything: no row, a count of 0
    (tmp_path / "synthetic" / "rescu-ii").mkdir(parents=True)
    (tmp_path / "data" / "synthetic").mkdir(parents=True)
    (tmp_path / "data" / "synthetic" / "annotations.json").write_text(
        '{"images": [], "annotations": [], "categories": []}')
    assert sm.main([str(tmp_path)]) == 0
    assert "0 GT instances missed" in capsys.readouterr().out


def test_completion_variants_refusals(tmp_path, capsys):
    cv = load("completion_variants")
    with pytest.raises(SystemExit):
        cv.main([str(tmp_path), "--set", "no_such_key=1"])
    assert "no_such_key" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cv.main([str(tmp_path), "--set", "max_step_ratio=0.5"])
    assert "max_step_ratio" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cv.main([str(tmp_path), "--workers", "0"])
    assert "--workers must be at least 1" in capsys.readouterr().err
    assert cv.main([str(tmp_path), "--set", "end_instances=2"]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    assert not (tmp_path / "benchmarks").exists()


def test_stage1_variants_refusals(tmp_path, capsys):
    s1 = load("stage1_variants")
    with pytest.raises(SystemExit):          # not a stage1 key
        s1.main([str(tmp_path), "--set", "no_such_key=1"])
    assert "no_such_key" in capsys.readouterr().err
    with pytest.raises(SystemExit):          # not a dense key
        s1.main([str(tmp_path), "--set", "dense.no_such_key=1"])
    assert "no_such_key" in capsys.readouterr().err
    with pytest.raises(SystemExit):          # a value DenseParams refuses
        s1.main([str(tmp_path), "--set", "dense.confidence_stage1_score_scale=-1"])
    assert "confidence_stage1_score_scale" in capsys.readouterr().err
    with pytest.raises(SystemExit):          # not a dataset of the config
        s1.main([str(tmp_path), "--dataset", "nowhere", "--set", "max_patterns=8"])
    assert "nowhere" in capsys.readouterr().err
    assert s1.main([str(tmp_path), "--set", "max_patterns=8"]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    assert not (tmp_path / "benchmarks").exists()


def test_dense_variants_refusals(tmp_path, capsys):
    dv = load("dense_variants")
    with pytest.raises(SystemExit):          # not a dense key
        dv.main([str(tmp_path), "--set", "no_such_key=1"])
    assert "no_such_key" in capsys.readouterr().err
    with pytest.raises(SystemExit):          # a value DenseParams refuses
        dv.main([str(tmp_path), "--set", "max_touching=9"])
    assert "max_touching" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        dv.main([str(tmp_path), "--dataset", "nowhere"])
    assert "nowhere" in capsys.readouterr().err
    assert dv.main([str(tmp_path), "--set", "max_touching=4"]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    assert not (tmp_path / "benchmarks").exists()


def test_precision_breakdown_without_a_run_and_on_an_empty_one(tmp_path, capsys):
    pb = load("precision_breakdown")
    assert pb.main([str(tmp_path)]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    (tmp_path / "synthetic" / "rescu-ii").mkdir(parents=True)
    (tmp_path / "data" / "synthetic").mkdir(parents=True)
    (tmp_path / "data" / "synthetic" / "annotations.json").write_text(
        '{"images": [], "annotations": [], "categories": []}')
    assert pb.main([str(tmp_path)]) == 0
    assert "0 images, 0 detected instances" in capsys.readouterr().out
    assert pb.main([str(tmp_path), "--by-category"]) == 0
    assert "category" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        pb.main([str(tmp_path), "--dataset", "no_such_set"])


def test_dense_oracle_refusals_and_a_small_run(tmp_path, capsys):
    import json

    import cv2
    import numpy as np

    from rescu import pipeline
    from rescu.config import load_config

    do = load("dense_oracle")
    with pytest.raises(SystemExit):          # a value DenseParams refuses
        do.main([str(tmp_path), "--set", "max_touching=9"])
    assert "max_touching" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        do.main([str(tmp_path), "--dataset", "nowhere"])
    assert "nowhere" in capsys.readouterr().err
    assert do.main([str(tmp_path)]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    # one photo of five red discs on a grey floor, annotated as one GT RP
    rng = np.random.default_rng(3)
    img = np.clip(150 + rng.normal(0, 8, (360, 480, 3)), 0, 255).astype(np.uint8)
    boxes = []
    for i in range(5):
        x, y = 40 + 90 * i, 150
        cv2.circle(img, (x + 20, y + 20), 20, (200, 30, 30), -1)
        boxes.append([x, y, 40, 40])
    data = tmp_path / "data" / "synthetic"
    (data / "images").mkdir(parents=True)
    cv2.imwrite(str(data / "images" / "floor.png"), img[:, :, ::-1])
    (data / "images" / "broken.png").write_bytes(b"not a png")
    (data / "annotations.json").write_text(json.dumps({
        "images": [{"id": 1, "file_name": "images/floor.png", "width": 480, "height": 360},
                   {"id": 2, "file_name": "images/broken.png", "width": 480, "height": 360}],
        "annotations": [{"id": k + 1, "image_id": 1, "category_id": 0, "bbox": b}
                        for k, b in enumerate(boxes)],
        "categories": [{"id": 0, "name": "disc"}]}))
    prep = tmp_path / "synthetic" / "prepared"
    prep.mkdir(parents=True)
    cfg = load_config(stage2=False)
    assert pipeline.prepare(str(data / "images" / "floor.png"), str(prep / "floor.png"),
                            str(prep / "floor.meta.json"), image_name="images/floor.png",
                            max_side=cfg["image"]["max_side"],
                            min_side=cfg["image"]["min_side"]) is None
    # an image the run could not prepare is skipped with a message, the rest scored
    assert pipeline.prepare(str(data / "images" / "broken.png"), str(prep / "broken.png"),
                            str(prep / "broken.meta.json"), image_name="images/broken.png",
                            max_side=cfg["image"]["max_side"],
                            min_side=cfg["image"]["min_side"]) is not None
    assert do.main([str(tmp_path)]) == 0
    cap = capsys.readouterr()
    out = cap.out
    assert "synthetic/broken: skipped" in cap.err
    assert "## synthetic: 1 images" in out and "| oracle, every good |" in out
    rows = (tmp_path / "benchmarks" / "dense-oracle" / "synthetic.tsv").read_text()
    lines = rows.strip().split("\n")
    assert lines[0].split("\t") == ["image", "rank", "n", "score", "touching", "precision",
                                    "selected"]
    prec = [float(r.split("\t")[5]) for r in lines[1:]]
    assert max(prec) == 1.0              # a candidate lies on the discs and only on them
    # the oracle's best group finds the discs: its row has precision 1
    best = next(r for r in out.splitlines() if r.startswith("| oracle, best one |"))
    assert float(best.split("|")[2]) == 1.0
    every = next(r for r in out.splitlines() if r.startswith("| every candidate |"))
    assert float(every.split("|")[3]) == 1.0
    # with a method's RPs: one on the discs, the other image has no result (said, counted
    # as none)
    (tmp_path / "synthetic" / "mine").mkdir()
    from rescu import io
    from rescu.types import ImageResult, Instance, Pattern
    io.write_json(tmp_path / "synthetic" / "mine" / "floor.json", ImageResult(
        image="images/floor.png", width=480, height=360, method="mine", patterns=[Pattern(
            id=0, score=1.0, instances=[Instance(bbox=tuple(b)) for b in boxes])]).to_json())
    assert do.main([str(tmp_path), "--with", "mine"]) == 0
    out = capsys.readouterr().out
    row = next(r for r in out.splitlines() if r.startswith("| every candidate + mine |"))
    assert float(row.split("|")[3]) == 1.0
    row = next(r for r in out.splitlines() if r.startswith("| every good + good of mine |"))
    # every disc found; the good groups' other blobs and the discs found twice cost
    # precision (whole RPs are kept, no instance removed)
    assert float(row.split("|")[3]) == 1.0 and 0 < float(row.split("|")[2]) < 1.0


def test_compare_folders_refusals_and_a_comparison(tmp_path, capsys):
    import json

    cf = load("compare_folders")
    with pytest.raises(SystemExit):
        cf.main([str(tmp_path), "before"])
    assert "LABEL=FOLDER" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cf.main([str(tmp_path), f"a={tmp_path}", f"a={tmp_path}"])
    assert "given twice" in capsys.readouterr().err
    assert cf.main([str(tmp_path), f"a={tmp_path}"]) == 2
    assert "annotations.json: not found" in capsys.readouterr().err
    # one image, one GT RP of two boxes; folder a finds both, folder b one and a stray
    (tmp_path / "annotations.json").write_text(json.dumps({
        "images": [{"id": 1, "file_name": "images/x.png", "width": 100, "height": 100}],
        "annotations": [{"id": 1, "image_id": 1, "category_id": 0, "bbox": [0, 0, 10, 10]},
                        {"id": 2, "image_id": 1, "category_id": 0, "bbox": [20, 0, 10, 10]}],
        "categories": [{"id": 0, "name": "o"}]}))

    from rescu.types import ImageResult, Instance, Pattern

    for name, boxes in (("a", [(0, 0, 10, 10), (20, 0, 10, 10)]),
                        ("b", [(0, 0, 10, 10), (60, 60, 10, 10)])):
        res = ImageResult(image="images/x.png", width=100, height=100, method="m",
                          patterns=[Pattern(id=0, score=1.0, instances=[
                              Instance(bbox=b, score=1.0) for b in boxes])])
        (tmp_path / name).mkdir()
        (tmp_path / name / "x.json").write_text(json.dumps(res.to_json()))
    assert cf.main([str(tmp_path), f"a={tmp_path / 'a'}", f"b={tmp_path / 'b'}"]) == 0
    out = capsys.readouterr().out
    row = {r.split("|")[1].strip(): r.split("|") for r in out.splitlines() if r.startswith("| a ")
           or r.startswith("| b ")}
    assert "1.000" in row["a"][3] and "0.500" in row["b"][3]     # instance precision
    assert "p_value" in out


def test_stage2_gates_funnel_and_refusals(tmp_path, capsys):
    import numpy as np

    from rescu.extension.params import Stage2Params

    sg = load("stage2_gates")
    assert sg.main([str(tmp_path)]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    params = Stage2Params.from_dict({"predict": {"score_threshold": 0.9,
                                                 "lattice_score_threshold": 0.8,
                                                 "max_distance_ratio": 1.0,
                                                 "lattice_distance_ratio": 1.0}})
    own = np.array([[0, 0, 10, 10], [20, 0, 10, 10]], float)
    missing = np.array([[40, 0, 10, 10], [60, 0, 10, 10], [80, 0, 10, 10]], float)
    # proposals: on GT 0 a lattice window that passes everything; on GT 1 a plain window
    # whose class is another RP's; on GT 2 a plain window 1.4 x too large (IOD 0.51), which
    # passes all but the size gate (tolerance 1.35)
    boxes = np.array([[40, 0, 10, 10], [60, 0, 10, 10], [78, 0, 14, 14]], float)
    lattice = np.array([True, False, False])
    prob = np.array([[0.05, 0.95, 0.0], [0.0, 0.1, 0.9], [0.0, 0.95, 0.05]])
    dist = np.array([0.5, 0.5, 0.5])
    f = sg.gate_funnel(missing, 0, own, boxes, lattice, prob, dist, 1.0, params, True)
    assert f == {"missing": 3, "covered": 3, "allowed": 1, "argmax": 1, "score": 1,
                 "distance": 1, "size": 1}
    f = sg.gate_funnel(missing, 0, own, boxes, lattice, prob, dist, 1.0, params, False)
    assert [f[s] for s in sg.STAGES] == [3, 3, 3, 2, 2, 2, 1]
    # the feature-distance gate: every proposal too far from the RP's centres
    f = sg.gate_funnel(missing, 0, own, boxes, lattice, prob, dist * 4, 1.0, params, False)
    assert (f["score"], f["distance"], f["size"]) == (2, 0, 0)


def test_feature_probe_split_probe_and_refusal(tmp_path, capsys):
    import numpy as np

    fp = load("feature_probe")
    assert fp.main([str(tmp_path)]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    for bad in (["--min-instances", "1"], ["--precision", "0"], ["--precision", "1.5"],
                ["--iod", "1"]):
        with pytest.raises(SystemExit):
            fp.main([str(tmp_path), *bad])
        assert "must be" in capsys.readouterr().err
    assert fp.recall_at_precision(np.array([1, 1, 0, 1]), np.array([4., 3., 2., 1.]), 0.7) == 1.0
    assert fp.recall_at_precision(np.array([1, 0, 0, 1]), np.array([4., 3., 2., 1.]), 0.7) == 0.5
    # 8 GT boxes in a row; proposals: each GT box exactly, and 40 background boxes below
    gt = np.array([[20 * i, 0, 10, 10] for i in range(8)], float)
    bg = np.array([[7 * i, 100 + 3 * (i % 5), 10, 10] for i in range(40)], float)
    props = np.concatenate([gt, bg])
    rng = np.random.default_rng(0)
    x = rng.normal(size=(len(props), 6)).astype(np.float32)
    x[:8, 0] += 6.0                       # the objects differ in one direction
    split = fp.probe_split(props, gt, None, np.random.default_rng(1))
    pos, neg, test, y, cover = split
    assert cover.shape == (len(test), 4) and (cover.any(1) == (y == 1)).all()
    assert set(pos) | set(test[y == 1]) == set(range(8)) and not set(pos) & set(test)
    assert len(pos) == 4 and y.sum() == 4 and set(neg) <= set(range(8, 48))
    assert not set(neg) & set(test)
    assert fp.probe(x, split, 0.7) == (1.0, 1.0, 1.0)
    # trained on two of the boxes (stage I's RP): the rest of the GT is the test set
    split = fp.probe_split(props, gt, gt[:2], np.random.default_rng(1))
    assert split is not None and set(split[0]) <= {0, 1} and not set(split[0]) & set(split[2])
    res = fp.image_probes({"f": x}, props, [gt.tolist()], [gt[:3].tolist()], (0, 0))
    assert len(res["f"]) == 1 and len(res["f stage I"]) == 1
    assert res["f"][0] == (1.0, 1.0, 1.0)
    # no GT RP large enough: nothing probed
    assert fp.image_probes({"f": x}, props, [gt[:3].tolist()], [], (0, 0)) == {
        "f": [], "f stage I": []}


def test_feature_probe_crop_descriptors():
    import numpy as np

    fp = load("feature_probe")
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (60, 80, 3), dtype=np.uint8)
    # boxes inside, across the border and thinner than a pixel all give finite unit rows
    boxes = np.array([[5, 5, 20, 30], [70, 50, 30, 30], [10.2, 10.2, 0.3, 0.3]], float)
    for variant, dim in (("hog", 900), ("pixels", 432)):
        x = fp.fresh_features(variant, rgb, boxes, 1.0, {})
        assert x.shape == (3, dim) and x.dtype == np.float32 and np.isfinite(x).all()
        assert np.allclose(np.linalg.norm(x, axis=1)[:2], 1.0, atol=1e-5)
    # the same crop gives the same row, wherever the box lies
    rgb[:] = 0
    rgb[10:20, 10:20] = 255
    rgb[30:40, 50:60] = 255
    x = fp.fresh_features("hog", rgb, np.array([[5, 5, 20, 20], [45, 25, 20, 20]], float), 1.0, {})
    assert np.allclose(x[0], x[1], atol=1e-6)


def test_blob_probe_split_extension_and_refusal(tmp_path, capsys):
    import numpy as np

    bp = load("blob_probe")
    with pytest.raises(SystemExit):
        bp.main([str(tmp_path), "--threshold", "1.5"])
    assert "must be in [0, 1]" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        bp.main([str(tmp_path), "--dataset", "nowhere"])
    assert "not in the config" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        bp.main([str(tmp_path), "--set", "objectness_crops=-1"])
    assert "objectness_crops" in capsys.readouterr().err
    # 8 GT boxes in a row, a blob inside each and 30 background blobs below
    gt = np.array([[20 * i, 0, 10, 10] for i in range(8)], float)
    blobs = np.concatenate([gt + [2, 2, -4, -4],
                            np.array([[7 * i, 100, 6, 6] for i in range(30)], float)])
    split = bp.blob_split(blobs, gt, None, np.random.default_rng(1))
    pos, neg, test, y, cover = split
    assert len(pos) == 4 and y.sum() == 4 and cover.shape == (len(test), 4)
    assert (cover.any(1) == (y == 1)).all() and not set(pos) & set(test)
    assert set(neg) <= set(range(8, 38)) and not set(neg) & set(test) and len(neg) == 15
    # trained on a dense RP of three of the blobs: the rest of the row is tested
    train = np.zeros(len(blobs), bool)
    train[:3] = True
    pos, _, test, y, _ = bp.blob_split(blobs, gt, train, np.random.default_rng(1))
    assert set(pos) <= {0, 1, 2} and not set(pos) & set(test[y == 1])
    # no blob on the GT: nothing to probe
    assert bp.blob_split(blobs[8:], gt, None, np.random.default_rng(1)) is None
    # the extension: separable blobs join their group, a claimed blob stays put
    rng = np.random.default_rng(0)
    emb = rng.normal(size=(40, 3))
    emb[:10, 0] += 8.0
    emb[10:20, 1] += 8.0
    out = bp.crossfit_extend(emb, [np.arange(3), np.arange(10, 13)], 0.5)
    for got, kind in zip(out, (range(10), range(10, 20))):
        # the unlabelled blobs of the kind are negatives for the other parts' models,
        # so one may stay out; none of another kind comes in
        assert set(got[:3]) <= set(kind) and set(got) <= set(kind) and len(got) >= 8
    assert bp.crossfit_extend(emb, [np.arange(3)], 1.0)[0].tolist() == [0, 1, 2]


def test_compare_runs_tells_run_specific_parts_from_changes(tmp_path, capsys):
    sys.path.insert(0, str(BENCH))
    import compare_runs as CR

    from rescu import io

    a, b = tmp_path / "a", tmp_path / "b"
    for root in (a, b):
        (root / "d" / "prepared").mkdir(parents=True)
        (root / "d" / "final").mkdir()
        (root / "logs").mkdir()
        io.write_json(root / "d" / "prepared" / "x.meta.json", {"image": "x", "source": str(root)})
        io.write_h5(root / "d" / "x.rp.h5", {"rp": [1, 2]}, attrs={"timings": str(root)})
        (root / "logs" / "x.log").write_text(str(root))
    io.write_json(a / "d" / "final" / "x.json", {"patterns": [1]})
    io.write_json(b / "d" / "final" / "x.json", {"patterns": [1]})
    assert CR.main([str(a), str(b)]) == 0
    out = capsys.readouterr().out
    assert "3 files in both runs: 1 byte-identical, 2 with equal content" in out
    io.write_json(b / "d" / "final" / "x.json", {"patterns": [2]})
    (b / "d" / "final" / "y.json").write_text("{}")
    assert CR.main([str(a), str(b)]) == 1
    out = capsys.readouterr().out
    assert "different: d/final/x.json" in out and "in one run only: d/final/y.json" in out


def _one_gt_rp(root, boxes, width, height):
    """``root/data/synthetic/annotations.json``: one image ``images/x.png`` whose
    ``boxes`` (``[x, y, w, h]``, one category) form one GT RP."""
    import json

    data = root / "data" / "synthetic"
    data.mkdir(parents=True)
    (data / "annotations.json").write_text(json.dumps({
        "images": [{"id": 1, "file_name": "images/x.png", "width": width, "height": height}],
        "annotations": [{"id": k + 1, "image_id": 1, "category_id": 0, "bbox": list(b)}
                        for k, b in enumerate(boxes)],
        "categories": [{"id": 0, "name": "o"}]}))


def _rp(boxes, **extra):
    """A :class:`rescu.types.Pattern` of ``boxes`` with ``extra``."""
    from rescu.types import Instance, Pattern

    return Pattern(id=0, score=1.0, extra=extra,
                   instances=[Instance(bbox=b, score=1.0) for b in boxes])


def test_rp_sources_by_source_reason_and_dominant(tmp_path, capsys):
    """One image, one GT RP of two boxes: a reported stage-I RP on both, a dense RP on
    neither, an RP set aside as one structure; the dominant (most confident) RP covers
    the GT RP and counts it right."""
    import json

    from rescu.types import ImageResult

    rs = load("rp_sources")
    assert rs.main([str(tmp_path)]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    _one_gt_rp(tmp_path, [(0, 0, 10, 10), (20, 0, 10, 10)], 100, 100)
    res = ImageResult(image="images/x.png", width=100, height=100, method="m", patterns=[
        _rp([(0, 0, 10, 10), (20, 0, 10, 10)], confidence=0.7),
        _rp([(60, 60, 10, 10), (80, 60, 10, 10), (60, 80, 10, 10)], confidence=0.35,
            source="dense")])
    res.extra["candidate_patterns"] = [dict(_rp([(40, 40, 5, 5), (50, 40, 5, 5)],
                                               confidence=0.5).to_json(), dropped="one structure")]
    (tmp_path / "synthetic" / "rescu-ii").mkdir(parents=True)
    (tmp_path / "synthetic" / "rescu-ii" / "x.json").write_text(json.dumps(res.to_json()))
    assert rs.main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "synthetic / rescu-ii: 1 images" in out
    import re

    def has(line):                       # the words of ``line``, any spacing
        return re.search(r"\s+".join(map(re.escape, line.split())), out) is not None

    assert has("reported dense 1 RPs 3 instances on GT 0.000")
    assert has("reported stage1 1 RPs 2 instances on GT 1.000")
    assert has("confidence 0.6-1.0 1 RPs 2 instances on GT 1.000")
    assert has("set aside, one structure 1 RPs 2 instances on GT 0.000")
    assert "covers 1.000, precision 1.000, relative count error 0.000, within 0.35 on 1.00" in out
    assert rs.main([str(tmp_path), "--touching"]) == 0   # boxes two sides apart: none abut
    out = capsys.readouterr().out
    assert has("reported dense abutting sides 0.00-0.25 1 RPs 3 instances on GT 0.000")
    assert rs.touching([[0, 0, 10, 10], [10, 0, 10, 10], [0, 10, 10, 10.0]], 0.35) == 4 / 3
    assert rs.main([str(tmp_path), "--dominant", "count"]) == 0      # the 3 boxes off GT
    assert ("dominant RP (count) vs the largest GT RP (1 images): covers 0.000, precision "
            "0.000, relative count error 0.500, within 0.35 on 0.00") in capsys.readouterr().out
    assert rs.main([str(tmp_path), "--dominant", "best"]) == 0      # the ground truth picks
    assert ("dominant RP (best) vs the largest GT RP (1 images): covers 1.000, precision "
            "1.000, relative count error 0.000, within 0.35 on 1.00") in capsys.readouterr().out
    with pytest.raises(SystemExit):
        rs.main([str(tmp_path), "--dataset", "no_such_set"])


def test_rp_objectness_scores_every_reported_rp_and_leaves_out_stage1_below(tmp_path, capsys):
    """One image, one GT RP of two boxes: a stage-I RP on both and a dense RP on
    neither. Every RP gets an objectness in (0, 1]; at threshold 0 nothing is left out
    (precision 0.4: 2 of 5 boxes); at 1.01 the stage-I RP is, and the precision is 0."""
    import json

    import cv2
    import numpy as np

    from rescu.types import ImageResult

    ro = load("rp_objectness")
    _one_gt_rp(tmp_path, [(8, 8, 24, 24), (48, 8, 24, 24)], 128, 96)
    prep = tmp_path / "synthetic" / "prepared"
    prep.mkdir(parents=True)
    img = np.full((96, 128, 3), 200, np.uint8)
    for x in (8, 48):
        cv2.circle(img, (x + 12, 20), 10, (30, 60, 160), -1)
    cv2.imwrite(str(prep / "x.png"), img)
    (prep / "x.meta.json").write_text(json.dumps({"scale_factor": 1.0}))

    res = ImageResult(image="images/x.png", width=128, height=96, method="m", patterns=[
        _rp([(8, 8, 24, 24), (48, 8, 24, 24)], confidence=0.7),
        _rp([(8, 60, 20, 20), (40, 60, 20, 20), (72, 60, 20, 20)], source="dense")])
    (tmp_path / "synthetic" / "rescu-ii").mkdir()
    (tmp_path / "synthetic" / "rescu-ii" / "x.json").write_text(json.dumps(res.to_json()))
    assert ro.main([str(tmp_path), "--crops", "2", "--threshold", "0",
                    "--threshold", "1.01"]) == 0
    out = capsys.readouterr().out
    assert "synthetic      stage1      1 RPs, on GT 1.000" in out
    assert "synthetic      dense       1 RPs, on GT 0.000" in out
    assert "below 0.00 left out (0): any-RP P / R synthetic 0.400 / 1.000" in out
    assert "below 1.01 left out (1): any-RP P / R synthetic 0.000 / 0.000" in out
    import re
    med = [float(v) for v in re.findall(r"median objectness ([0-9.]+)", out)]
    assert len(med) == 2 and all(0 < v <= 1 for v in med)
    with pytest.raises(SystemExit):
        ro.main([str(tmp_path), "--crops", "0"])


def test_rp_separation_of_objects_and_of_a_band(tmp_path, capsys):
    """One image with a stored map: a dense RP of objects with wall between them (on the
    two GT boxes) keeps its separation, a dense RP along a band of the same stuff falls
    below the threshold; a stage-I RP is not counted with ``--source dense``."""
    import json

    import numpy as np

    from rescu.discovery.sources import DenseParams
    from rescu.extension.dense import save_map
    from rescu.types import ImageResult, Instance, Pattern

    rs = load("rp_separation")
    data = tmp_path / "data" / "synthetic"
    data.mkdir(parents=True)
    boxes = [[8.0 + 32 * k, 8, 16, 16] for k in range(3)]   # 2 cells, 2 apart
    (data / "annotations.json").write_text(json.dumps({
        "images": [{"id": 1, "file_name": "images/x.png", "width": 96, "height": 64}],
        "annotations": [{"id": k + 1, "image_id": 1, "category_id": 0, "bbox": b}
                        for k, b in enumerate(boxes[:2])],
        "categories": [{"id": 0, "name": "o"}]}))
    f = np.zeros((2, 8, 12), np.float32)
    f[0] = 1.0
    for x0 in (1, 5, 9):                                  # objects every 4 cells
        f[:, 1:3, x0:x0 + 2] = np.array([0.0, 1.0])[:, None, None]
    f[:, 5:7, :] = np.array([0.0, 1.0])[:, None, None]   # one band, rows 5-6
    run = tmp_path / "synthetic"
    for sub in ("dense", "prepared", "rescu-i"):
        (run / sub).mkdir(parents=True)
    save_map(run / "dense" / "x.map.h5", (f, 1.0), DenseParams.from_dict(None))
    (run / "prepared" / "x.meta.json").write_text(json.dumps({"scale_factor": 1.0}))

    def rp(bs, source):
        return Pattern(id=0, score=1.0, extra={"source": source},
                       instances=[Instance(bbox=tuple(b)) for b in bs])

    band = [[b[0], 40, 16, 16] for b in boxes]
    res = ImageResult(image="images/x.png", width=96, height=64, method="rescu-i",
                      patterns=[rp(boxes, "dense"), rp(band, "dense"), rp(band, "stage1")])
    (run / "rescu-i" / "x.json").write_text(json.dumps(res.to_json()))
    assert rs.main([str(tmp_path), "--probe", "1", "--threshold", "0.01"]) == 0
    out = capsys.readouterr().out
    assert "dense RPs, probe 1.000: 2 RPs, 6 instances, on GT 0.333" in out
    assert "below +0.010:    1 RPs      3 instances  on GT 0.000" in out
    with pytest.raises(SystemExit):
        rs.main([str(tmp_path), "--probe", "0"])


def test_extent_fit_on_a_generated_set(tmp_path, capsys):
    """extent_fit.py on a labelled set of one generated photo of discs: the thin ring
    grows the half-size squares to the discs (the unit test's case, through the script);
    a missing set is a message and exit 2."""
    import json

    import cv2
    import numpy as np

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from test_objects import _discs

    ef = load("extent_fit")
    img, truth = _discs(np.random.default_rng(3))
    (tmp_path / "discs" / "images").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "discs" / "images" / "d.png"), img[..., ::-1])
    coco = {"images": [{"id": 1, "file_name": "images/d.png", "width": 640, "height": 480}],
            "annotations": [{"id": k, "image_id": 1, "category_id": 0, "bbox": b.tolist()}
                            for k, b in enumerate(truth)],
            "categories": [{"id": 0, "name": "disc"}]}
    (tmp_path / "discs" / "annotations.json").write_text(json.dumps(coco))
    assert ef.main(["--data", str(tmp_path), "--dataset", "discs", "--ring", "0.5",
                    "--ring", "0.25", "--side", "640"]) == 0
    out = capsys.readouterr().out
    assert "discs: 1 images, 1 GT RPs" in out
    row = out.strip().splitlines()[-1]
    wide = float(row.split("ring 0.5: ")[1].split()[0])
    thin = float(row.split("ring 0.25: ")[1].split()[0])
    assert wide < 0.7 < 0.9 < thin, row
    # the edge term grows them to the discs against the wide ring too
    assert ef.main(["--data", str(tmp_path), "--dataset", "discs", "--ring", "0.5",
                    "--edges", "1", "--side", "640"]) == 0
    out = capsys.readouterr().out
    assert "(edges 1)" in out
    assert float(out.strip().splitlines()[-1].split("ring 0.5: ")[1].split()[0]) > 0.9
    with pytest.raises(SystemExit):
        ef.main(["--data", str(tmp_path), "--dataset", "discs", "--edges", "-1"])
    assert ef.main(["--data", str(tmp_path), "--dataset", "nothing"]) == 2
    assert "not found" in capsys.readouterr().err
    sq = ef.squares(np.array([[10.0, 20.0, 40.0, 10.0]]), 0.5)
    assert np.allclose(sq, [[25.0, 20.0, 10.0, 10.0]])   # side sqrt(40 x 10) / 2, same centre


def test_box_fit_counts_boxes_and_the_share_of_the_object_they_cover(tmp_path, capsys):
    """box_fit.py on one labelled image and a run's JSON: which instances pass IOD > 0.5,
    which lie on an object with the wrong box, the median share of the object the boxes
    on objects cover, and ``--source`` keeping one source's RPs; a missing set is exit 2."""
    import json

    bf = load("box_fit")
    (tmp_path / "data" / "set").mkdir(parents=True)
    coco = {"images": [{"id": 1, "file_name": "images/x.png", "width": 200, "height": 100}],
            "annotations": [{"id": k, "image_id": 1, "category_id": 0, "bbox": b}
                            for k, b in enumerate([[0, 0, 40, 40], [100, 0, 40, 40]])],
            "categories": [{"id": 0, "name": "thing"}]}
    (tmp_path / "data" / "set" / "annotations.json").write_text(json.dumps(coco))
    run = tmp_path / "run" / "set" / "rescu-ii"
    run.mkdir(parents=True)
    inst = lambda *boxes: [{"bbox": list(b)} for b in boxes]  # noqa: E731
    res = {"patterns": [
        {"source": "dense", "instances": inst((10, 10, 20, 20), (100, 0, 40, 40))},
        {"instances": inst((0, 0, 60, 60), (150, 50, 10, 10))}]}
    (run / "x.json").write_text(json.dumps(res))
    args = [str(tmp_path / "run"), "--data", str(tmp_path / "data"), "--dataset", "set",
            "--folder", "rescu-ii"]
    assert bf.main(args) == 0
    out = capsys.readouterr().out
    # the 60-px box holds the first object's centre, 2.25 times its area: on it, failing
    assert "hold 4 instances: 2 pass IOD > 0.5, 1 more have their centre" in out
    assert "3 have their centre on a GT object; median area / the object's: 1.00" in out
    assert bf.main(args + ["--source", "dense"]) == 0
    out = capsys.readouterr().out
    assert "hold 2 instances: 2 pass" in out
    assert "median area / the object's: 0.62" in out       # 0.25 and 1
    assert bf.main([str(tmp_path / "run"), "--data", str(tmp_path), "--dataset", "set"]) == 2
    assert "not found" in capsys.readouterr().err


def test_dense_cost_times_a_variant_beside_the_defaults(capsys):
    """``dense_cost.py --against``: both settings on each image, alternating; a bad variant
    is a usage error naming the key."""
    sys.path.insert(0, str(BENCH / "speed"))
    spec = importlib.util.spec_from_file_location("dense_cost", BENCH / "speed" / "dense_cost.py")
    dc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(dc)
    with pytest.raises(SystemExit):
        dc.main(["--per-set", "0", "--against", "objectness_crops=-1"])
    assert "objectness_crops" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        dc.main(["--per-set", "0", "--against", "objectness_crops"])
    assert "KEY=VALUE" in capsys.readouterr().err
    # no photo (--per-set 0): the synthetic rendering, at 0.1 MP, once with each setting
    assert dc.main(["--per-set", "0", "--megapixels", "0.1", "--repeats", "1", "--threads", "1",
                    "--against", "objectness_crops=0"]) == 0
    out = capsys.readouterr().out
    assert "synthetic" in out and "variant: objectness_crops=0" in out


def test_camera_speed_times_every_stage_of_a_small_photo(capsys):
    import importlib.util as iu

    from rescu.data.photos import package_photo_dir

    spec = iu.spec_from_file_location("camera_speed", BENCH / "speed" / "camera_speed.py")
    mod = iu.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--photo", str(package_photo_dir() / "brick.png"), "--mp", "0.05",
                     "--method", "rescu-i"]) == 0
    out = capsys.readouterr().out
    line = [ln for ln in out.splitlines() if ln.startswith("brick.png")][0]
    for stage in ("prepare", "features", "dense", "rescu-i", "scene"):
        assert f"{stage} " in line, line
    assert "peak" in line and "| brick.png | 0.05 |" in out


def test_tree_memory_counts_a_child_and_a_step_server_outside_the_tree(tmp_path, capsys):
    """``tree_memory.py``: the memory of the command's children, and of a step server in a
    session of its own, which /usr/bin/time does not see."""
    import json
    import subprocess

    spec = importlib.util.spec_from_file_location("tree_memory", BENCH / "speed" / "tree_memory.py")
    tm = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tm)
    with pytest.raises(SystemExit):
        tm.main([])
    assert "no command" in capsys.readouterr().err
    hold = ("import sys, time; b = bytearray(int(sys.argv[1]) << 20); "
            "b[::4096] = b'x' * len(b[::4096]); time.sleep(3)")
    # a "step server" started in its own session before the command: counted
    server = subprocess.Popen([sys.executable, "-c", hold, "150", "rescu_workflow.step_server"],
                              start_new_session=True)
    try:
        out = tmp_path / "m.json"
        code = tm.main(["--interval", "0.1", "--json", str(out), "--", sys.executable, "-c",
                        "import subprocess, sys; subprocess.run([sys.executable, '-c', "
                        f"{hold!r}, '100'])"])
    finally:
        server.kill()
        server.wait()
    got = json.loads(out.read_text())
    assert code == 0 and got["exit"] == 0 and got["most_processes"] >= 3
    assert got["peak_sum_pss_mib"] >= 240 and got["peak_sum_rss_mib"] >= 240
    assert 140 <= got["peak_process_rss_mib"] <= 220


def test_complete_dominant_seeds():
    """complete_dominant.py's examples: the dominant RP's instances, or (oracle) the
    instances on ground-truth objects of the RP that has the most of them."""
    import numpy as np

    cd = load("complete_dominant")
    inst = lambda *xs: [{"bbox": [x, 0.0, 10.0, 10.0]} for x in xs]  # noqa: E731
    d = {"dominant_pattern": 0, "patterns": [{"id": 0, "instances": inst(0, 100, 200)},
                                             {"id": 1, "instances": inst(300, 400, 500, 900)}]}
    k, ex = cd.seeds(None, d, "dominant", None)
    assert k == 0 and [e["bbox"][0] for e in ex] == [0, 100, 200]
    # objects (centres) under the second RP's first three boxes: the centre rule
    gt = (np.array([[300, 0, 10, 10], [400, 0, 10, 10], [500, 0, 10, 10]], float), 20.0)
    k, ex = cd.seeds(None, d, "oracle", gt)
    assert k == 1 and [e["bbox"][0] for e in ex] == [300, 400, 500]
    assert cd.seeds(None, d, "oracle", None) is None
    assert cd.seeds(None, dict(d, dominant_pattern=None), "dominant", None) is None
