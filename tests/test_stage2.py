"""Tests of RESCU-II (rescu.extension: params, augment, features, examples, train,
predict) on tiny synthetic images."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rescu import io  # noqa: E402
from rescu.evaluation.metrics import iod_matrix  # noqa: E402
from rescu.extension.augment import occlude_instances  # noqa: E402
from rescu.extension.examples import (cluster_centres, dbscan_labels,  # noqa: E402
                                      select_examples)
from rescu.extension.proposal_features import compute_stage2_features, finetune_record  # noqa: E402
from rescu.extension.params import Stage2Params  # noqa: E402
from rescu.params import deep_merge as merged  # noqa: E402
from rescu.extension.predict import (impute_half, predict_stage2,  # noqa: E402
                                     score_features, visible_half_features)
from rescu.extension.train import load_checkpoint, save_checkpoint, train_heads  # noqa: E402
from rescu.types import ImageResult, Instance, Pattern  # noqa: E402

FAST = {"head": {"max_epochs": 20}, "examples": {"n_augment": 2, "n_aug_proposals": 200}}


def fast(**sections) -> Stage2Params:
    """FAST with the nested ``sections`` merged in."""
    return Stage2Params.from_dict(merged(FAST, sections))


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """One torch thread, set before the module-scoped fixtures compute anything (the
    float sums of a backbone pass depend on the thread count; tests compare runs)."""
    torch.set_num_threads(1)


def squares(n=6, sz=40, gap=24, h=160, seed=0):
    """A row of n identical textured squares on grey; returns (img, boxes)."""
    rng = np.random.default_rng(seed)
    tex = rng.integers(0, 255, (sz, sz, 3), dtype=np.uint8)
    tex[: sz // 2, : sz // 2] = [255, 0, 0]
    w = gap + n * (sz + gap)
    img = np.full((h, w, 3), 128, np.uint8)
    boxes = []
    for i in range(n):
        x, y = gap + i * (sz + gap), (h - sz) // 2
        img[y:y + sz, x:x + sz] = tex
        boxes.append((float(x), float(y), float(sz), float(sz)))
    return img, boxes


def result(img, rps, name="images/t.png"):
    return ImageResult(name, img.shape[1], img.shape[0], "rescu-i",
                       [Pattern(k, 1.0, [Instance(b) for b in rp]) for k, rp in enumerate(rps)])


@pytest.fixture(scope="module")
def six():
    img, boxes = squares()
    s1 = result(img, [boxes[:4]])
    p = fast()
    feats = compute_stage2_features(img, 1.0, s1, p)
    ckpt, info = train_heads(feats, s1, p)
    out = predict_stage2(feats, ckpt, s1, p)
    return img, boxes, s1, p, feats, ckpt, info, out


def test_adds_the_missing_squares(six):
    img, boxes, s1, p, feats, ckpt, info, out = six
    assert out.method == "rescu-ii"
    insts = out.patterns[0].instances
    assert [i.source for i in insts[:4]] == ["stage1"] * 4
    assert [i.bbox for i in insts[:4]] == boxes[:4]
    new = np.array([i.bbox for i in insts if i.source == "stage2"])
    assert len(new) == 2
    iod = iod_matrix(new, np.array(boxes[4:]))
    assert np.all(iod.max(0) > 0.5) and np.all(iod.max(1) > 0.5)
    assert out.extra["stage2"]["backbone"] == "efficientnet-lite0"
    assert out.patterns[0].extra["stage2_added"] == 2
    assert info["status"] == "trained" and 1 <= info["epochs"] <= 20


def test_feature_dict_shapes(six):
    img, boxes, s1, p, feats, *_ = six
    P = len(feats["proposals"])
    D = feats["proposal_features"].shape[1]
    assert feats["proposal_features"].shape == (P, D) and feats["proposal_scores"].shape == (P,)
    assert feats["instance_features"].shape == (4, D)
    assert feats["aug_instance_features"].shape == (2, 4, D)
    assert "merge_instance_features" not in feats        # no box refinement recorded
    assert bytes(feats["backbone"]).decode() == "efficientnet-lite0"
    h, w = img.shape[:2]
    b = feats["proposals"]
    assert np.all(b[:, 0] >= 0) and np.all(b[:, 0] + b[:, 2] <= w + 1e-3)


def test_positive_selection_under_ten_percent(six):
    feats = six[4]
    sel = select_examples(feats, Stage2Params.from_dict({"examples": {"top_p": 40}}))
    P = len(sel["proposal_label"])
    n_pos = int((sel["proposal_label"] > 0).sum())
    assert 0 < n_pos < 0.1 * P
    assert sel["n_negative"] > 0


def test_nothing_added_on_plain_background():
    img, boxes = squares(n=4)
    img2 = np.full((160, 520, 3), 128, np.uint8)     # the 4 squares, then plain grey
    img2[:, : img.shape[1]] = img
    s1 = result(img2, [boxes])
    p = fast()
    feats = compute_stage2_features(img2, 1.0, s1, p)
    ckpt, _ = train_heads(feats, s1, p)
    out = predict_stage2(feats, ckpt, s1, p)
    assert [i.source for i in out.patterns[0].instances] == ["stage1"] * 4


def test_deterministic(six, tmp_path):
    img, boxes, s1, p, feats, ckpt, info, out = six
    feats2 = compute_stage2_features(img, 1.0, s1, p)
    for k in feats:
        assert np.array_equal(np.asarray(feats[k]), np.asarray(feats2[k])), k
    ckpt2, _ = train_heads(feats2, s1, p)
    for k, v in ckpt["state_dict"].items():
        assert np.array_equal(v, ckpt2["state_dict"][k]), k
    assert predict_stage2(feats2, ckpt2, s1, p).to_json() == out.to_json()


def test_features_before_the_box_refinement_for_the_merge(six):
    """A stage-I RP that records RESCU-I's box refinement gets the features of its
    boxes before it too (``merge_instance_features``, what the merge compares)."""
    img, boxes, s1, p, feats, *_ = six
    from rescu.discovery.edge_extent import transform_boxes

    for t in ([0.25, 0.0, 1.0, 1.0],            # moved right: the same backbone scale
              [0.25, 0.0, 0.5, 0.5]):           # and halved: a scale of their own
        moved = result(img, [transform_boxes(np.array(boxes[:4]), t, img.shape[1::-1])])
        moved.patterns[0].extra["box_transform"] = t
        got = compute_stage2_features(img, 1.0, moved, p)
        assert got["merge_instance_features"].shape == got["instance_features"].shape
        # the unrefined boxes are s1's: their features are s1's instance features
        assert np.allclose(got["merge_instance_features"], feats["instance_features"],
                           atol=1e-5)
        assert not np.allclose(got["instance_features"], feats["instance_features"], atol=1e-3)


def test_occluders_cover_a_band_of_chosen_boxes_only():
    img, boxes = squares(n=4)
    before = img.copy()
    same = occlude_instances(img, np.array(boxes), 0.0, (0.2, 0.5), np.random.default_rng(0))
    assert np.array_equal(same, img)
    out = occlude_instances(img, np.array(boxes), 1.0, (0.3, 0.3), np.random.default_rng(0))
    assert np.array_equal(img, before)                   # the input is not changed
    changed = np.any(out != img, axis=2)
    inside = np.zeros(changed.shape, bool)
    for x, y, w, h in boxes:
        x, y, w, h = int(x), int(y), int(w), int(h)
        inside[y:y + h, x:x + w] = True
        share = changed[y:y + h, x:x + w].mean()
        assert 0.25 <= share <= 0.31                     # a 30 % band (a few pixels may match)
    assert not changed[~inside].any()
    again = occlude_instances(img, np.array(boxes), 1.0, (0.3, 0.3), np.random.default_rng(0))
    assert np.array_equal(out, again)
    with pytest.raises(ValueError, match="occlude_prob"):
        Stage2Params.from_dict({"examples": {"occlude_prob": 1.5}})
    with pytest.raises(ValueError, match="occlude_fraction"):
        Stage2Params.from_dict({"examples": {"occlude_fraction": [0.5, 0.2]}})


def test_occlusion_changes_only_the_augmented_copies(six):
    img, boxes, s1, p, feats, *_ = six
    occ = compute_stage2_features(img, 1.0, s1, fast(examples={"occlude_prob": 1.0}))
    assert np.array_equal(occ["instance_features"], feats["instance_features"])
    assert np.array_equal(occ["proposal_features"], feats["proposal_features"])
    d = np.linalg.norm(occ["aug_instance_features"] - feats["aug_instance_features"], axis=2)
    assert np.all(d > 1e-3)                              # every instance covered in each copy


def test_h5_and_checkpoint_round_trip(six, tmp_path):
    img, boxes, s1, p, feats, ckpt, info, out = six
    io.write_h5(tmp_path / "f.h5", feats)
    back, _ = io.read_h5(tmp_path / "f.h5")
    save_checkpoint(tmp_path / "c.h5", {"head": ckpt, "info": info})
    c = load_checkpoint(tmp_path / "c.h5")
    assert c["info"] == info and c["head"]["rp_index"] == ckpt["rp_index"]
    for k, v in ckpt["state_dict"].items():
        assert np.array_equal(c["head"]["state_dict"][k], v), k
    sel = c["head"]["selection"]                       # the selection the head was trained on
    assert sel["distance"].shape == (len(feats["proposals"]), len(ckpt["rp_index"]))
    res = predict_stage2(back, c["head"], s1, p)
    assert res.to_json() == out.to_json()
    assert not list(tmp_path.glob(".*tmp*"))


def test_no_rp_and_small_rp_unchanged(tmp_path):
    img, boxes = squares(n=3)
    for s1, m in ((result(img, []), 2), (result(img, [boxes[:1]]), 2),
                  (result(img, [boxes[:2]]), 3)):
        p = Stage2Params.from_dict({**FAST, "min_instances": m})
        feats = compute_stage2_features(img, 1.0, s1, p)
        assert len(feats["proposals"]) == 0 and len(feats["rp_index"]) == 0
        ckpt, info = train_heads(feats, s1, p)
        assert info["status"] == "no_rp" and ckpt["state_dict"] == {}
        out = predict_stage2(feats, ckpt, s1, p)
        assert out.method == "rescu-ii" and out.extra["stage2"]["status"] == "no_rp"
        assert [pt.to_json() for pt in out.patterns] == [pt.to_json() for pt in s1.patterns]
        io.write_h5(tmp_path / "e.h5", feats)          # empty arrays are writable
        back, _ = io.read_h5(tmp_path / "e.h5")
        assert predict_stage2(back, ckpt, s1, p).to_json() == out.to_json()


def test_rp_without_proposals_gets_no_new_instance(tmp_path):
    """The empty case of real photos (York Urban): an RP whose instances are smaller than
    ``min_box_side`` (8 px) gets neither instance-scale nor lattice windows, so the image
    has RPs, a trained head and no proposal at all. Prediction used to fail with "cannot
    reshape array of size 0 into shape (0,newaxis)" (score_features on (0, D))."""
    rng = np.random.default_rng(0)
    img = np.full((64, 96, 3), 128, np.uint8)
    boxes = [(10.0, 20.0, 5.0, 5.0), (30.0, 20.0, 5.0, 5.0), (50.0, 20.0, 5.0, 5.0)]
    tex = rng.integers(0, 255, (5, 5, 3), dtype=np.uint8)
    for x, y, w, h in boxes:
        img[int(y):int(y + h), int(x):int(x + w)] = tex
    s1 = result(img, [boxes])
    p = Stage2Params.from_dict({"head": {"max_epochs": 3}, "examples": {"n_augment": 1}})
    feats = compute_stage2_features(img, 1.0, s1, p)
    D = feats["instance_features"].shape[1]
    assert len(feats["rp_index"]) == 1 and feats["proposal_features"].shape == (0, D)
    ckpt, info = train_heads(feats, s1, p)
    assert info["status"] == "trained" and info["n_proposals"] == 0
    assert score_features(feats["proposal_features"], ckpt).shape == (0, 2)
    io.write_h5(tmp_path / "e.h5", feats)                # as the pipeline reads it back
    back, _ = io.read_h5(tmp_path / "e.h5")
    for q in (p, Stage2Params.from_dict({"head": {"max_epochs": 3}, "examples": {"n_augment": 1},
                                         "predict": {"visible_half": True}})):
        out = predict_stage2(back, ckpt, s1, q)
        assert out.extra["stage2"]["status"] == "no_proposals"
        assert out.extra["stage2"]["added"] == 0 and out.patterns[0].extra["stage2_added"] == 0
        assert [i.bbox for i in out.patterns[0].instances] == boxes
        assert [i.source for i in out.patterns[0].instances] == ["stage1"] * 3


def test_two_instance_rp_extended_along_its_row():
    # min_instances 2: two found squares of a row of three give the third (lattice step)
    img, boxes = squares(n=3)
    s1 = result(img, [boxes[:2]])
    p = fast()
    feats = compute_stage2_features(img, 1.0, s1, p)
    assert feats["proposal_lattice"].shape == (len(feats["proposals"]),)
    assert feats["proposal_lattice"].sum() > 0
    ckpt, _ = train_heads(feats, s1, p)
    out = predict_stage2(feats, ckpt, s1, p)
    new = np.array([i.bbox for i in out.patterns[0].instances if i.source == "stage2"])
    assert len(new) == 1
    assert iod_matrix(new, np.array(boxes[2:])).max() > 0.5


def test_lattice_only_needs_lattice_windows(six):
    # with lattice_only, no lattice window means nothing new (off-lattice proposals only
    # train the head)
    img, boxes, s1, *_ = six
    p = fast(proposals={"lattice_windows": False})
    feats = compute_stage2_features(img, 1.0, s1, p)
    assert feats["proposal_lattice"].sum() == 0
    ckpt, _ = train_heads(feats, s1, p)
    out = predict_stage2(feats, ckpt, s1, p)
    assert [i.source for i in out.patterns[0].instances] == ["stage1"] * 4


def test_whole_object_rps_are_extended_from_any_proposal(six):
    # the same four squares, no lattice window: a stage-I RP gets nothing new (lattice
    # only), an RP of whole objects (the dense source's) gets the two missing squares
    # from instance-scale windows (stage2.predict.whole_objects); with that section
    # disabled it is treated like any other RP
    import copy

    from rescu.extension.predict import rp_gates

    img, boxes, s1, *_ = six
    p = fast(proposals={"lattice_windows": False})
    feats = compute_stage2_features(img, 1.0, s1, p)
    ckpt, _ = train_heads(feats, s1, p)
    dense = copy.deepcopy(s1)
    dense.patterns[0].extra["source"] = "dense"
    assert rp_gates(s1.patterns[0], p) == (False, 0.7, True)
    assert rp_gates(dense.patterns[0], p) == (True, 3.0, False)
    out = predict_stage2(feats, ckpt, dense, p)
    new = np.array([i.bbox for i in out.patterns[0].instances if i.source == "stage2"])
    assert len(new) == 2 and out.patterns[0].extra["stage2_added"] == 2
    iod = iod_matrix(new, np.array(boxes[4:]))
    assert np.all(iod.max(0) > 0.5) and np.all(iod.max(1) > 0.5)
    off = fast(proposals={"lattice_windows": False},
               predict={"whole_objects": {"enabled": False}})
    assert rp_gates(dense.patterns[0], off) == (False, 0.7, True)
    out = predict_stage2(feats, ckpt, dense, off)
    assert [i.source for i in out.patterns[0].instances] == ["stage1"] * 4
    with pytest.raises(ValueError, match="whole_objects"):
        fast(predict={"whole_objects": {"score_threshold": 1.5}})
    with pytest.raises(ValueError, match="unknown stage2.predict.whole_objects parameter"):
        fast(predict={"whole_objects": {"threshold": 0.5}})


def test_spacing_suppression():
    from rescu.boxes import suppress

    own = np.array([[0, 0, 10, 10], [40, 0, 10, 10]], float)
    cand = np.array([[80, 0, 10, 10], [86, 2, 10, 10], [60, 0, 10, 10]], float)
    order = np.arange(3)
    # boxes 0 and 1 overlap little (IoU 0.19, cover 0.32): both survive plain NMS
    assert suppress(cand, order, own, own[:0], 0.3).tolist() == [0, 1, 2]
    # lattice spacing 40, fraction 0.6: centres closer than 24 px clash (1 with 0 at
    # 6.3 px, 2 with the stage-I instance at x = 45 at 20 px)
    assert suppress(cand, order, own, own[:0], 0.3, 24.0).tolist() == [0]


def test_cluster_centres_and_params():
    x = np.array([[1, 0], [0.99, 0.1], [0, 1], [0.1, 0.99], [-1, 0]], np.float32)
    c, lab = cluster_centres(x, eps=0.2, min_samples=2)
    assert len(c) == 3 and lab[0] == lab[1] and lab[2] == lab[3] and lab[4] not in lab[:4]
    with pytest.raises(ValueError, match="unknown stage2.head parameter"):
        Stage2Params.from_dict({"head": {"lr": 1e-3, "learning_rate": 1}})
    with pytest.raises(ValueError, match="unknown stage2 parameter"):
        Stage2Params.from_dict({"lr": 1e-3})          # a section key at the top level
    with pytest.raises(ValueError, match="stage2.head must be a mapping"):
        Stage2Params.from_dict({"head": 3})
    assert Stage2Params.from_dict({"backbone": {"input_scales": [1, 1.5]}}
                                  ).backbone.input_scales == (1.0, 1.5)
    with pytest.raises(ValueError, match="hidden_sizes"):
        Stage2Params.from_dict({"head": {"hidden_sizes": [8]}})


def test_dbscan_labels_are_scikit_learns():
    sklearn_cluster = pytest.importorskip("sklearn.cluster")
    rng = np.random.default_rng(0)
    for trial in range(300):
        n = int(rng.integers(1, 40))
        k = int(rng.integers(1, 5))
        centres = rng.normal(size=(k, 16))
        x = centres[rng.integers(0, k, n)] + rng.normal(scale=0.3, size=(n, 16))
        x = (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)
        eps = float(rng.uniform(0.05, 1.0))
        ms = int(rng.integers(1, 5))
        want = sklearn_cluster.DBSCAN(eps=eps, min_samples=ms).fit_predict(x)
        np.testing.assert_array_equal(dbscan_labels(x, eps, ms), want, err_msg=f"trial {trial}")
    assert dbscan_labels(np.zeros((0, 3), np.float32), 0.5, 2).shape == (0,)


def test_bad_inputs():
    img, boxes = squares(n=3)
    s1 = result(img, [boxes])
    with pytest.raises(ValueError, match="rgb"):
        compute_stage2_features(img[..., 0], 1.0, s1)
    with pytest.raises(ValueError, match="scale_factor"):
        compute_stage2_features(img, 0.0, s1)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal without CUDA")
def test_cuda_device_refused_without_cuda():
    img, boxes = squares(n=3)
    with pytest.raises(RuntimeError, match="cuda"):
        compute_stage2_features(img, 1.0, result(img, [boxes]),
                                Stage2Params.from_dict({"backbone": {"device": "cuda"}}))


def test_finetune_pools_from_the_finetuned_backbone(six):
    """finetune=True (run on the CPU here, tiny image): same boxes, features from a
    backbone trained end to end, and the rest of stage II runs on them unchanged."""
    img, boxes, s1, p, feats, _, _, _ = six
    pf = fast(backbone={"finetune": True}, head={"max_epochs": 2})
    ft = compute_stage2_features(img, 1.0, s1, pf)
    info = finetune_record(ft)
    assert info is not None and info["status"] == "finetuned" and 1 <= info["epochs"] <= 2
    assert finetune_record(feats) is None  # frozen backbone: no record
    for k in ("proposals", "instance_boxes", "jitter_boxes", "hard_negative_boxes"):
        assert np.array_equal(ft[k], feats[k]), k
    for k in ("proposal_features", "instance_features", "aug_proposal_features"):
        assert ft[k].shape == feats[k].shape and not np.allclose(ft[k], feats[k]), k
    ckpt, tinfo = train_heads(ft, s1, pf)
    assert tinfo["status"] == "trained"
    out = predict_stage2(ft, ckpt, s1, pf)
    assert out.patterns[0].count >= 4


def test_impute_half_keeps_the_named_half():
    c, n = 3, 2
    x = np.arange(n * c * 4, dtype=np.float32).reshape(n, c * 4) + 1
    fill = -np.ones(c * 4, np.float32)
    grid = x.reshape(n, c, 2, 2)
    for side, kept, hidden in ((0, (slice(None), 0), (slice(None), 1)),
                               (1, (slice(None), 1), (slice(None), 0)),
                               (2, (0, slice(None)), (1, slice(None))),
                               (3, (1, slice(None)), (0, slice(None)))):
        g = impute_half(x, fill, side, 2)
        assert g.shape == x.shape
        assert np.allclose(np.linalg.norm(g, axis=1), 1.0)
        raw = np.concatenate([grid[(slice(None), slice(None)) + kept].reshape(n, -1),
                              -np.ones((n, c * 2), np.float32)], 1)
        gg = g.reshape(n, c, 2, 2)
        scale = np.linalg.norm(raw, axis=1)[:, None, None]
        assert np.allclose(gg[(slice(None), slice(None)) + kept] * scale,
                           grid[(slice(None), slice(None)) + kept]), side
        assert np.allclose(gg[(slice(None), slice(None)) + hidden] * scale, -1.0), side
    with pytest.raises(ValueError, match="pool_size"):
        impute_half(x, fill, 0, 3)
    with pytest.raises(ValueError, match="pool_size"):
        Stage2Params.from_dict({"predict": {"visible_half": True}, "backbone": {"pool_size": 3}})


def _template_head(t: np.ndarray, gain: float, bias: float) -> dict:
    """A checkpoint whose head gives P(RP 0) = sigmoid(gain * <t, x> - bias) (2 classes)."""
    d = len(t)
    w1 = np.stack([t, -t]).astype(np.float32)
    sd = {"0.weight": w1, "0.bias": np.zeros(2, np.float32),
          "2.weight": np.eye(2, dtype=np.float32), "2.bias": np.zeros(2, np.float32),
          "4.weight": np.array([[0.0, 0.0], [gain, -gain]], np.float32),
          "4.bias": np.array([0.0, -bias], np.float32)}
    return {"state_dict": sd, "mean": np.zeros(d, np.float32), "std": np.ones(d, np.float32),
            "in_dim": d,
            "hidden_sizes": [2, 2], "n_classes": 2, "rp_index": [0],
            "backbone": "efficientnet-lite0"}


def test_visible_half_scores_half_hidden_lattice_windows_only():
    """A lattice window showing one half of the RP's template (the other half noise) is
    scored on that half when it lies inside the RP's span; windows that already pass,
    windows past the row's end and windows that match nothing keep their own feature."""
    rng = np.random.default_rng(0)
    c = 16
    t = rng.standard_normal(c * 4).astype(np.float32)
    t /= np.linalg.norm(t)
    inst_f = np.stack([t + 0.01 * rng.standard_normal(c * 4).astype(np.float32)
                       for _ in range(4)])
    half = t.reshape(c, 2, 2).copy()
    half[:, :, 1] = rng.standard_normal((c, 2)).astype(np.float32) * 0.1  # right half hidden
    half = half.reshape(-1) / np.linalg.norm(half)
    noise = rng.standard_normal(c * 4).astype(np.float32)
    noise /= np.linalg.norm(noise)
    inst_boxes = np.array([[0, 0, 10, 10], [20, 0, 10, 10], [60, 0, 10, 10],
                           [80, 0, 10, 10]], np.float32)
    props = np.array([[40, 0, 10, 10],     # the gap in the row, half hidden -> replaced
                      [40, 0, 10, 10],     # the gap, matching nothing -> kept
                      [120, 0, 10, 10],    # past the row's end, half hidden -> kept
                      [40, 0, 10, 10],     # the gap, already passing -> kept
                      [40, 0, 10, 10]],    # the gap, half hidden, not a lattice window
                     np.float32)
    feats = {"proposal_features": np.stack([half, noise, half, t, half]),
             "proposal_lattice": np.array([1, 1, 1, 1, 0], np.int8),
             "proposals": props, "rp_index": np.array([0]),
             "instance_features": inst_f, "instance_rp": np.zeros(4, np.int64),
             "instance_boxes": inst_boxes}
    ckpt = _template_head(t, gain=20.0, bias=12.0)
    p = Stage2Params.from_dict({"predict": {"visible_half": True}})
    own = score_features(feats["proposal_features"], ckpt)[:, 1]
    assert 0.2 <= own[0] < 0.95 and own[1] < 0.2 and own[3] >= 0.95   # the setting holds
    pf, replaced = visible_half_features(feats, ckpt, p)
    assert replaced.tolist() == [True, False, False, False, False]
    assert score_features(pf[:1], ckpt)[0, 1] >= 0.99
    assert np.array_equal(pf[1:], feats["proposal_features"][1:])
    # the kept (left) half is the window's own, up to the norm
    g, h = pf[0].reshape(c, 2, 2), half.reshape(c, 2, 2)
    assert np.allclose(g[:, :, 0] / np.linalg.norm(g[:, :, 0]),
                       h[:, :, 0] / np.linalg.norm(h[:, :, 0]), atol=1e-5)
    # margin 0: the gap still lies inside the span; a stricter threshold replaces nothing
    assert visible_half_features(feats, ckpt, Stage2Params.from_dict(
        {"predict": {"visible_half": True, "visible_half_margin": 0.0}}))[1][0]
    assert not visible_half_features(feats, ckpt, Stage2Params.from_dict(
        {"predict": {"visible_half": True, "visible_half_threshold": 1.0}}))[1].any()


def test_visible_half_in_prediction(six):
    img, boxes, s1, p, feats, ckpt, info, out = six
    pv = fast(predict={"visible_half": True})
    out_v = predict_stage2(feats, ckpt, s1, pv)
    n = out_v.extra["stage2"]["added_by_visible_half"]
    assert 0 <= n <= out_v.extra["stage2"]["added"]
    assert "added_by_visible_half" not in out.extra["stage2"]
    assert out_v.patterns[0].count >= 4


def test_a_variant_that_changes_only_prediction_is_told_apart():
    """as_predict_variant: a variant whose other keys equal the base's is prediction-only
    (its predict keys kept), one that changes any other key is not."""
    from rescu.extension.params import as_predict_variant
    from rescu.params import config_defaults

    base = config_defaults("stage2")
    assert base["proposals"]["method"] == "instance_scale"
    same = {"proposals": {"method": "instance_scale"}, "predict": {"lattice_only": False}}
    assert as_predict_variant(base, same) == {"predict": {"lattice_only": False}}
    assert as_predict_variant(base, {"predict": {"visible_half": True}}) == \
        {"predict": {"visible_half": True}}
    assert as_predict_variant(base, {}) == {}
    assert as_predict_variant(base, {"proposals": {"method": "edgeboxes"},
                                     "predict": {"lattice_only": False}}) is None
    assert as_predict_variant(base, {"head": {"lr": 0.5}}) is None
    assert as_predict_variant(base, {"new_section": 1}) is None
    assert as_predict_variant(base, "edgeboxes") is None
    # the variant's dict is not shared with the result
    out = as_predict_variant(base, same)
    out["predict"]["lattice_only"] = True
    assert same["predict"]["lattice_only"] is False
