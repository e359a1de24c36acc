"""Tests of the URP affinity (rescu.discovery.urp)."""

import numpy as np
import pytest

from rescu.discovery.urp import (AffinityParams, Gates, MatchParams, match_candidates, objective,
                                 root_sift, urp_affinity, wrap_deg)


def _aff(mode: str) -> AffinityParams:
    return AffinityParams(orientation_mode=mode)


def _quad(ds=1.0, dtheta=0.0, base_angle=(10.0, 200.0)):
    """Features f11, f21 in instance 1 and their copies f12, f22 in instance 2
    (translated by (100, 0)); the copies' scales are multiplied by ``ds`` and their
    orientations rotated by ``dtheta``. Returns xy, scale, angle and indices."""
    xy = np.array([[10.0, 10.0], [110.0, 10.0], [30.0, 15.0], [130.0, 15.0]])
    scale = np.array([8.0, 8.0 * ds, 6.0, 6.0 * ds])
    angle = np.array([base_angle[0], base_angle[0] + dtheta, base_angle[1],
                      base_angle[1] + dtheta]) % 360.0
    return xy, scale, angle, (0, 1, 2, 3)


@pytest.mark.parametrize("mode", ["wrapped", "relative", "paper"])
def test_affinity_is_one_for_translated_copy(mode):
    xy, s, a, (f11, f12, f21, f22) = _quad()
    u = urp_affinity(xy, s, a, f11, f12, f21, f22, affinity=_aff(mode))
    assert u == pytest.approx(1.0, abs=1e-12)


def test_affinity_decreases_with_scale_mismatch():
    vals = []
    for ds in (1.0, 1.2, 1.5, 2.0):
        xy, s, a, f = _quad(ds=ds)
        vals.append(float(urp_affinity(xy, s, a, *f)))
    assert vals[0] == pytest.approx(1.0)
    assert all(x > y for x, y in zip(vals, vals[1:]))


def test_scaled_instance_keeps_affinity_one():
    # instance 2 is instance 1 scaled by 2 (positions and keypoint sizes): r = 1/2
    xy = np.array([[10.0, 10.0], [200.0, 10.0], [30.0, 10.0], [240.0, 10.0]])
    s = np.array([8.0, 16.0, 6.0, 12.0])
    a = np.zeros(4)
    assert urp_affinity(xy, s, a, 0, 1, 2, 3) == pytest.approx(1.0)


@pytest.mark.parametrize("mode", ["wrapped", "paper"])
def test_affinity_decreases_with_orientation_mismatch(mode):
    vals = []
    for dt in (0.0, 10.0, 45.0, 90.0):
        xy, s, a, f = _quad(dtheta=dt)
        vals.append(float(urp_affinity(xy, s, a, *f, affinity=_aff(mode))))
    assert vals[0] == pytest.approx(1.0)
    assert all(x > y for x, y in zip(vals, vals[1:]))


def test_relative_mode_ignores_common_rotation_but_not_inconsistent_rotation():
    xy, s, a, f = _quad(dtheta=60.0)
    assert urp_affinity(xy, s, a, *f, affinity=_aff("relative")) == pytest.approx(1.0)
    assert urp_affinity(xy, s, a, *f, affinity=_aff("wrapped")) < 0.9
    a2 = a.copy()
    a2[3] = (a2[3] + 40.0) % 360.0  # word 2 rotates differently from word 1
    assert urp_affinity(xy, s, a2, *f, affinity=_aff("relative")) < 0.99


def test_wrapped_mode_handles_the_360_wrap_and_paper_mode_does_not():
    # orientations 359 deg and 1 deg are 2 degrees apart
    xy, s, a, f = _quad(dtheta=2.0, base_angle=(359.0, 359.0))
    assert urp_affinity(xy, s, a, *f, affinity=_aff("wrapped")) > 0.999
    assert urp_affinity(xy, s, a, *f, affinity=_aff("paper")) < 0.5


def test_gates_zero_the_affinity():
    xy, s, a, f = _quad(dtheta=40.0)
    assert urp_affinity(xy, s, a, *f, gates=Gates(1000.0, 0.5, 30.0)) == 0.0
    assert urp_affinity(xy, s, a, *f, gates=Gates(1000.0, 0.5, 90.0)) > 0.0
    assert urp_affinity(xy, s, a, *f, gates=Gates(5.0, 0.5, 90.0)) == 0.0  # P_d


def test_missing_entries_and_bad_mode():
    xy, s, a, f = _quad()
    assert urp_affinity(xy, s, a, -1, 1, 2, 3) == 0.0
    with pytest.raises(ValueError, match="orientation_mode"):
        urp_affinity(xy, s, a, *f, affinity=_aff("bogus"))


def test_objective_of_perfect_3x3_matrix():
    # 3 words x 3 instances, translated copies: U = (3 row pairs * 3 col pairs) / 9 = 1
    base = np.array([[0.0, 0.0], [20.0, 5.0], [7.0, 30.0]])
    xy = np.vstack([base + [100.0 * j, 0.0] for j in range(3)])
    s = np.tile([5.0, 7.0, 9.0], 3)
    a = np.tile([10.0, 100.0, 300.0], 3)
    om = np.arange(9).reshape(3, 3).T  # rows = words, columns = instances
    assert objective(xy, s, a, om) == pytest.approx(1.0)
    assert objective(xy, s, a, om[:1]) == 0.0
    with pytest.raises(ValueError, match="omega"):
        objective(xy, s, a, np.arange(3))


def test_wrap_and_rootsift():
    assert np.allclose(wrap_deg([0.0, 190.0, -190.0, 360.0]), [0.0, -170.0, 170.0, 0.0])
    d = root_sift(np.array([[1.0, 3.0], [0.0, 0.0]]))
    assert np.allclose(np.linalg.norm(d[0]), 1.0) and np.allclose(d[1], 0.0)


def test_match_candidates_excludes_self_and_far_descriptors():
    rng = np.random.default_rng(0)
    d = rng.random((4, 128)).astype(np.float32)
    d[1] = d[0]  # a copy of feature 0
    xy = np.array([[0.0, 0.0], [50.0, 0.0], [100.0, 0.0], [150.0, 0.0]])
    nbr, dist = match_candidates(d, xy, np.full(4, 5.0), MatchParams(k=2, max_dist=0.05))
    assert nbr[0, 0] == 1 and nbr[1, 0] == 0
    assert nbr[2, 0] == -1 and np.isinf(dist[2, 0])


def test_match_candidates_equals_brute_force_reference():
    """Top k by (RootSIFT distance, index) under the distance limit, excluding copies
    closer than min_sep keypoint radii (exact, with ties)."""
    rng = np.random.default_rng(3)
    k_feat = 60
    d = rng.random((k_feat, 128)).astype(np.float32)
    d[10:20] = d[0]                                   # exact ties in distance
    d[30:35] = d[5] + 0.01 * rng.random((5, 128)).astype(np.float32)
    xy = rng.random((k_feat, 2)).astype(np.float32) * 200
    xy[11] = xy[0] + 1.0                              # an overlapping copy: excluded
    scale = (rng.random(k_feat) * 6 + 2).astype(np.float32)
    nbr, dist = match_candidates(d, xy, scale, MatchParams(5, 0.3, 1.0), block=64)
    rs = root_sift(d)
    full = np.maximum(2.0 - 2.0 * (rs @ rs.T), 0.0)   # the same product as one block
    for i in range(k_feat):
        d2 = full[i]
        sep = np.maximum(scale[i], scale) / 2.0
        ok = (d2 <= 0.3 * 0.3) & (((xy - xy[i]) ** 2).sum(1) > sep * sep)
        cand = sorted(np.flatnonzero(ok), key=lambda j: (d2[j], j))[:5]
        assert nbr[i, :len(cand)].tolist() == cand
        assert (nbr[i, len(cand):] == -1).all() and np.isinf(dist[i, len(cand):]).all()
        assert np.allclose(dist[i, :len(cand)], np.sqrt(d2[cand]))
    assert 11 not in nbr[0].tolist() and nbr[0].tolist()[:4] == [10, 12, 13, 14]
    # smaller blocks: the same ranks for the exact copies (rows 0 and 10..19)
    nb16, _ = match_candidates(d, xy, scale, MatchParams(5, 0.3, 1.0), block=16)
    assert np.array_equal(nb16[[0] + list(range(10, 20))], nbr[[0] + list(range(10, 20))])


def test_affinity_parts_gate_like_urp_affinity_and_pairs_cache():
    from rescu.discovery.urp import pairs
    rng = np.random.default_rng(1)
    xy = rng.random((30, 2)) * 300
    s = rng.random(30) * 10 + 2
    a = rng.random(30) * 360
    f = [rng.integers(-1, 30, (7, 1, 5)), rng.integers(-1, 30, (1, 4, 5)),
         rng.integers(-1, 30, (7, 4, 1)), rng.integers(0, 30, (7, 4, 5))]
    parts = urp_affinity(xy, s, a, *f, return_parts=True)
    assert np.array_equal(parts.gated(None), urp_affinity(xy, s, a, *f))
    for g in (Gates(50.0, 0.2, 30.0), Gates(300.0, 0.5, 180.0), Gates(120.0, 0.1, 90.0)):
        assert np.array_equal(parts.gated(g), urp_affinity(xy, s, a, *f, gates=g))
    i, j = pairs(6)
    assert np.array_equal(np.stack([i, j]), np.stack(np.triu_indices(6, 1)))
    assert pairs(6)[0] is i and not i.flags.writeable
