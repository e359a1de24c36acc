"""Tests of rescu.extension.merge: merging recurring patterns split by stage I."""

import numpy as np
import pytest

from rescu.extension.merge import MergeParams, line_residual, merge_split_patterns, pair_evidence
from rescu.extension.params import Stage2Params
from rescu.extension.predict import predict_stage2
from rescu.types import ImageResult, Instance, Pattern

D = 16


def drift_feats(start, n, base=0, drift=1, step=0.15):
    """(n, D) unit features drifting along a great circle (appearance changing along a
    foreshortened row): neighbours have similarity cos(step)."""
    t = (start + np.arange(n)) * step
    f = np.zeros((n, D))
    f[:, base] = np.cos(t)
    f[:, drift] = np.sin(t)
    return f


def row_boxes(start, n, y=50.0, size=20.0, pitch=40.0):
    return np.array([[10 + pitch * (start + i), y, size, size] for i in range(n)], float)


def pattern(pid, boxes, score, m_words=2, stage2=()):
    inst = [Instance(tuple(float(v) for v in b), 1.0, "stage1") for b in boxes]
    inst += [Instance(tuple(float(v) for v in b), 0.995, "stage2") for b in stage2]
    n = len(boxes)
    fp = np.stack([np.stack([boxes[:, 0] + 5 + 5 * m, boxes[:, 1] + 5], 1)
                   for m in range(m_words)])          # (M, N, 2)
    assert fp.shape == (m_words, n, 2)
    return Pattern(id=pid, score=score, instances=inst, feature_points=fp,
                   extra={"stage2_added": len(stage2)})


def image(patterns):
    return ImageResult(image="images/t.png", width=400, height=300, method="rescu-ii",
                       patterns=patterns, dominant_pattern=0)


def three_rps(b_y=50.0, c_feats=None, b_size=20.0):
    """A: row instances 0-2; B: the same row, instances 3-5 (drifted appearance);
    C: another row of other objects at y = 150."""
    a_b, b_b, c_b = row_boxes(0, 3), row_boxes(3, 3, y=b_y, size=b_size), row_boxes(0, 4, y=150)
    fa, fb = drift_feats(0, 3), drift_feats(3, 3)
    fc = drift_feats(0, 4, base=2, drift=3) if c_feats is None else c_feats
    res = image([pattern(0, a_b, 5.0), pattern(1, c_b, 4.0, m_words=3), pattern(2, b_b, 6.0)])
    boxes = np.concatenate([a_b, c_b, b_b])
    feats = np.concatenate([fa, fc, fb])
    rp = np.array([0] * 3 + [1] * 4 + [2] * 3)
    return res, boxes, feats, rp


def test_split_row_is_merged_other_row_kept():
    res, boxes, feats, rp = three_rps()
    out, log = merge_split_patterns(res, boxes, feats, rp, MergeParams())
    assert [p.id for p in out.patterns] == [0, 1]
    assert [p.count for p in out.patterns] == [6, 4]
    m = out.patterns[0]
    assert m.score == 6.0                                  # the better score
    assert m.extra["merged_from"] == [0, 2]
    assert log[0]["ids"] == [0, 2] and log[0]["merge"]
    # the better-scored part (B) comes first; feature points block-diagonal, (2+2, 6, 2)
    xs = [ins.bbox[0] for ins in m.instances]
    assert xs == [130.0, 170.0, 210.0, 10.0, 50.0, 90.0]
    assert m.feature_points.shape == (4, 6, 2)
    assert np.isfinite(m.feature_points[:2, :3]).all() and np.isnan(m.feature_points[:2, 3:]).all()
    assert np.isnan(m.feature_points[2:, :3]).all() and np.isfinite(m.feature_points[2:, 3:]).all()
    assert out.patterns[1].count == 4 and out.patterns[1].extra.get("merged_from") is None
    assert out.dominant_pattern == 0
    assert res.patterns[0].count == 3                      # input untouched


def test_nothing_to_merge_returns_an_equal_copy():
    res, boxes, feats, rp = three_rps()
    sub = image([res.patterns[0], res.patterns[1]])
    out, log = merge_split_patterns(sub, boxes[:7], feats[:7], rp[:7])
    assert log == [] and out.to_json() == sub.to_json() and out is not sub


def test_similar_objects_in_another_row_not_merged():
    # B has A's appearance but lies on a row 100 px below: geometry keeps them apart
    res, boxes, feats, rp = three_rps(b_y=150.0 + 100.0)
    out, _ = merge_split_patterns(res, boxes, feats, rp, MergeParams())
    assert [p.count for p in out.patterns] == [3, 4, 3]
    # ... and appearance alone (geometry off) would merge them
    out, _ = merge_split_patterns(res, boxes, feats, rp, MergeParams(max_line_residual=0.0))
    assert [p.count for p in out.patterns] == [6, 4]


def test_whole_objects_have_their_own_line_test():
    # B has A's appearance 100 px below A's row: two rows of stage I stay apart whatever
    # the objects' limit; two RPs of whole objects (the dense source's) are joined when
    # their line test is off, and kept apart by the default (the rows' limit)
    res, boxes, feats, rp = three_rps(b_y=150.0 + 100.0)
    off = MergeParams(max_object_line_residual=0.0)
    assert off.max_line_residual == MergeParams().max_line_residual > 0
    out, _ = merge_split_patterns(res, boxes, feats, rp, off)
    assert [p.count for p in out.patterns] == [3, 4, 3]
    for p in res.patterns:
        p.extra["source"] = "dense"
    out, _ = merge_split_patterns(res, boxes, feats, rp, MergeParams())
    assert [p.count for p in out.patterns] == [3, 4, 3]
    out, log = merge_split_patterns(res, boxes, feats, rp, off)
    assert [p.count for p in out.patterns] == [6, 4] and log[0]["line_residual"] == 0.0
    assert out.patterns[0].extra["source"] == "dense"
    ev = pair_evidence(feats[:3], feats[7:], boxes[:3], boxes[7:], off, objects=True)
    assert ev["merge"] and not pair_evidence(feats[:3], feats[7:], boxes[:3], boxes[7:],
                                             off)["merge"]
    with pytest.raises(ValueError, match="max_object_line_residual"):
        MergeParams(max_object_line_residual=-1.0)


def test_different_objects_in_the_same_row_not_merged():
    # C continues A's row (y = 50) with similar objects (cross similarity ~0.79 against
    # ~0.99 between neighbours within A and within C): only appearance can tell
    fc = 0.8 * drift_feats(3, 4)
    fc[:, 2] = 0.6
    res, boxes, feats, rp = three_rps(c_feats=fc)
    ev = pair_evidence(feats[:3], fc, boxes[:3], row_boxes(3, 4))
    assert 0.75 < ev["ratio"] < 0.85 and not ev["merge"]
    c = res.patterns[1]
    cb = row_boxes(3, 4)
    c.instances = [Instance(tuple(b), 1.0, "stage1") for b in cb]
    boxes[3:7] = cb
    res.patterns = [res.patterns[0], c]
    out, _ = merge_split_patterns(res, boxes[:7], feats[:7], rp[:7], MergeParams())
    assert [p.count for p in out.patterns] == [3, 4]


def test_size_gate():
    res, boxes, feats, rp = three_rps(b_size=80.0)
    boxes[7:] = [ins.bbox for ins in res.patterns[2].instances]
    out, log = merge_split_patterns(res, boxes, feats, rp, MergeParams(max_line_residual=0))
    assert [p.count for p in out.patterns] == [3, 4, 3] and log == []
    out, _ = merge_split_patterns(res, boxes, feats, rp,
                                  MergeParams(size_tolerance=4.5, max_line_residual=0,
                                              conflict_cover=1.0))
    assert [p.count for p in out.patterns] == [6, 4]


def test_duplicates_removed_stage2_kept_consistent():
    a_b = row_boxes(0, 3)
    b_b = row_boxes(2, 3) + np.array([2.0, 0, 0, 0])        # B's first = A's last (IoU > .5)
    res = image([pattern(0, a_b, 5.0, stage2=row_boxes(6, 1)), pattern(1, b_b, 4.0)])
    feats = np.concatenate([drift_feats(0, 3), drift_feats(2, 3)])
    out, _ = merge_split_patterns(res, np.concatenate([a_b, b_b]), feats,
                                  np.array([0, 0, 0, 1, 1, 1]), MergeParams())
    (m,) = out.patterns
    assert m.count == 6                                    # 3 + 3 - 1 duplicate + 1 stage II
    assert [i.source for i in m.instances] == ["stage1"] * 5 + ["stage2"]
    assert m.extra["stage2_added"] == 1
    assert m.feature_points.shape == (4, 5, 2)             # one column per stage-I instance
    assert m.instances[2].bbox == tuple(a_b[2])            # A (better score) keeps its box


def test_nested_boxes_conflict():
    a_b = row_boxes(0, 3)
    b_b = a_b + np.array([4.0, 4, -8, -8])                 # B nested inside A's boxes
    res = image([pattern(0, a_b, 5.0), pattern(1, b_b, 4.0)])
    feats = np.concatenate([drift_feats(0, 3), drift_feats(0, 3)])
    ev = pair_evidence(feats[:3], feats[3:], a_b, b_b)
    assert ev["conflicts"] == 3 and not ev["merge"]
    out, _ = merge_split_patterns(res, np.concatenate([a_b, b_b]), feats,
                                  np.array([0, 0, 0, 1, 1, 1]))
    assert len(out.patterns) == 2


def test_two_instance_rps_and_three_way_merge():
    parts = [row_boxes(0, 2), row_boxes(2, 2), row_boxes(4, 2)]
    res = image([pattern(i, b, float(i)) for i, b in enumerate(parts)])
    feats = np.concatenate([drift_feats(0, 2), drift_feats(2, 2), drift_feats(4, 2)])
    out, log = merge_split_patterns(res, np.concatenate(parts), feats,
                                    np.repeat([0, 1, 2], 2), MergeParams())
    assert [p.count for p in out.patterns] == [6] and len(log) == 2
    assert out.patterns[0].score == 2.0 and out.patterns[0].extra["merged_from"] == [0, 1, 2]


def test_pair_evidence_values():
    fa, fb = drift_feats(0, 3), drift_feats(3, 3)
    ev = pair_evidence(fa, fb, row_boxes(0, 3), row_boxes(3, 3))
    assert ev["s_aa"] == pytest.approx(np.cos(0.15))
    assert ev["s_ab"] == pytest.approx(np.cos(0.15))
    assert ev["ratio"] == pytest.approx(1.0) and ev["size_ratio"] == 1.0
    assert ev["line_residual"] == pytest.approx(0.0) and ev["merge"]
    # RPs with fewer than two featured instances give no evidence
    assert not pair_evidence(fa[:1], fb, row_boxes(0, 1), row_boxes(3, 3))["merge"]


def test_line_residual():
    assert line_residual(np.array([[0, 0], [1, 1], [2, 2]], float)) == pytest.approx(0.0)
    assert line_residual(np.array([[0, 0], [10, 0]], float)) == 0.0
    r = line_residual(np.array([[0, 0], [10, 0], [20, 0], [30, 6]], float))
    assert 1.0 < r < 6.0


def test_input_checks():
    res, boxes, feats, rp = three_rps()
    with pytest.raises(ValueError, match="inst_feats"):
        merge_split_patterns(res, boxes, feats[:5], rp)
    with pytest.raises(ValueError, match="inst_boxes"):
        merge_split_patterns(res, boxes[:, :3], feats, rp)
    with pytest.raises(ValueError, match="inst_pattern"):
        merge_split_patterns(res, boxes, feats, rp + 5)
    with pytest.raises(ValueError, match="feats_a"):
        pair_evidence(np.zeros((2, 3)), np.zeros((2, 4)), row_boxes(0, 2), row_boxes(2, 2))


def test_params():
    assert MergeParams.from_dict({"similarity_ratio": 0.9}).similarity_ratio == 0.9
    with pytest.raises(ValueError, match="simlarity_ratio"):
        MergeParams.from_dict({"simlarity_ratio": 0.9})
    with pytest.raises(ValueError, match="size_tolerance"):
        MergeParams(size_tolerance=0.5)
    p = Stage2Params.from_dict({"predict": {"merge": {"similarity_ratio": 0.8,
                                                      "max_line_residual": 0}}})
    assert p.predict.merge.merge_params() == MergeParams(similarity_ratio=0.8,
                                                         max_line_residual=0.0)
    with pytest.raises(ValueError, match="duplicate_iou"):
        Stage2Params.from_dict({"predict": {"merge": {"duplicate_iou": 0.0}}})
    with pytest.raises(ValueError, match="unknown stage2.predict.merge parameter"):
        Stage2Params.from_dict({"predict": {"merge": {"merge_duplicate_iou": 0.5}}})


def _stage2_inputs():
    res, boxes, feats, rp = three_rps()
    res.method = "rescu-i"
    feats_d = {"rp_index": np.array([0, 1, 2]), "backbone": np.frombuffer(b"x", np.uint8),
               "instance_rp": rp, "instance_boxes": boxes.astype(np.float32),
               "instance_features": feats.astype(np.float32)}
    ckpt = {"rp_index": [0, 1, 2], "state_dict": {}, "n_classes": 4}
    return res, feats_d, ckpt


def test_merge_compares_the_features_before_the_box_refinement():
    """RESCU-I's box refinement moves each RP's boxes by a transform of its own; the
    features step then also pools the boxes before it (``merge_instance_features``),
    and the merge's appearance test uses those: here the refined boxes' features of
    B look like nothing of A, the unrefined ones continue A's row."""
    res, feats_d, ckpt = _stage2_inputs()
    res.patterns[0].extra["box_transform"] = [0.0, 0.0, 1.0, 1.0]
    res.patterns[2].extra["box_transform"] = [0.0, 0.2, 1.0, 0.8]
    unrefined = feats_d["instance_features"].copy()
    refined = unrefined.copy()
    refined[7:] = drift_feats(0, 3, base=4, drift=5)      # B's refined crops: other features
    with_both = dict(feats_d, instance_features=refined.astype(np.float32),
                     merge_instance_features=unrefined)
    out = predict_stage2(with_both, ckpt, res, Stage2Params())
    assert [p.count for p in out.patterns] == [6, 4]
    # the parts' transforms differ: the merged RP records none; each instance keeps its box
    assert "box_transform" not in out.patterns[0].extra
    assert [i.bbox for i in out.patterns[0].instances] == (
        [i.bbox for i in res.patterns[2].instances] + [i.bbox for i in res.patterns[0].instances])
    only_refined = dict(feats_d, instance_features=refined.astype(np.float32))
    kept = predict_stage2(only_refined, ckpt, res, Stage2Params())
    assert [p.count for p in kept.patterns] == [3, 4, 3]


def test_tests_and_duplicates_on_the_boxes_before_the_refinement():
    """B's boxes were moved down half a box by RESCU-I's refinement; A's stage-II
    instance sits on B's first object at A's phase. On the moved boxes that pair is a
    conflict (half overlapping); with B's transform undone it is one object, counted once."""
    a_b, b_b = row_boxes(0, 3), row_boxes(3, 3, y=60.0)
    fa, fb = drift_feats(0, 3), drift_feats(3, 3)
    pa = pattern(0, a_b, 5.0, stage2=row_boxes(3, 1))
    pb = pattern(1, b_b, 6.0)
    rp = np.array([0] * 3 + [1] * 3)
    boxes, feats = np.concatenate([a_b, b_b]), np.concatenate([fa, fb])
    out, log = merge_split_patterns(image([pa, pb]), boxes, feats, rp)
    assert not log and [p.count for p in out.patterns] == [4, 3]
    pb.extra["box_transform"] = [0.0, 0.5, 1.0, 1.0]
    out, log = merge_split_patterns(image([pa, pb]), boxes, feats, rp)
    assert [p.count for p in out.patterns] == [6] and log[0]["conflicts"] == 0
    # B's stage-I instance won the duplicate and keeps its own (refined) box
    assert [i.source for i in out.patterns[0].instances] == ["stage1"] * 6
    assert out.patterns[0].instances[0].bbox == tuple(b_b[0])


def test_predict_stage2_merges_last():
    res, feats_d, ckpt = _stage2_inputs()
    out = predict_stage2(feats_d, ckpt, res, Stage2Params())
    assert [p.count for p in out.patterns] == [6, 4]
    assert out.extra["stage2"]["merged"] == [[0, 2]]
    off = predict_stage2(feats_d, ckpt, res,
                         Stage2Params.from_dict({"predict": {"merge": {"enabled": False}}}))
    assert [p.count for p in off.patterns] == [3, 4, 3] and "merged" not in off.extra["stage2"]
