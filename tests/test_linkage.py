"""rescu.extension.linkage and boxmaps.maximum_filter: NumPy forms of the scipy calls the
dense step made (importing scipy.cluster and scipy.ndimage cost a dense job 0.3-0.8 s)."""

import numpy as np
import pytest
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.ndimage import maximum_filter as scipy_maximum_filter

from rescu.extension.boxmaps import maximum_filter
from rescu.extension.linkage import average_linkage_labels, pairwise_distances


def _same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    pairs = set(zip(a.tolist(), b.tolist()))
    return len(pairs) == len(set(a.tolist())) == len(set(b.tolist()))


@pytest.mark.parametrize("metric", ["cosine", "euclidean"])
def test_average_linkage_is_scipys_partition(metric: str) -> None:
    for seed in range(60):
        r = np.random.default_rng(seed)
        n, dim, k = int(r.integers(2, 200)), int(r.choice([3, 32])), int(r.integers(1, 10))
        centres = r.normal(size=(k, dim))
        x = centres[r.integers(0, k, n)] + r.normal(scale=r.uniform(0.05, 1.5), size=(n, dim))
        t = (float(r.uniform(0.05, 0.9)) if metric == "cosine"
             else float(r.uniform(0.2, 3.0) * np.sqrt(dim)))
        ours = average_linkage_labels(x, t, metric)
        theirs = fcluster(linkage(x, method="average", metric=metric), t=t,
                          criterion="distance")
        assert _same_partition(ours, theirs), (seed, n, dim)
        # numbered from 1 in the order of each cluster's first item
        first = [ours[np.flatnonzero(ours == c)[0]] for c in np.unique(ours)]
        assert sorted(first) == list(range(1, len(first) + 1))
        assert ours[0] == 1 and np.all(np.diff(np.maximum.accumulate(ours)) <= 1)


def test_average_linkage_edges() -> None:
    assert average_linkage_labels(np.zeros((0, 3)), 1.0).tolist() == []
    assert average_linkage_labels(np.ones((1, 3)), 1.0).tolist() == [1]
    # identical rows are one cluster at any cut >= 0
    assert average_linkage_labels(np.ones((4, 2)), 0.0).tolist() == [1, 1, 1, 1]
    # a chain a-b-c at distance 1 whose ends are 2 apart: average linkage cuts at 1.2
    # into two clusters (single linkage would keep one)
    labels = average_linkage_labels(np.array([[0.0], [1.0], [2.1]]), 1.2)
    assert labels.tolist() == [1, 1, 2]
    with pytest.raises(ValueError, match="zero row"):
        pairwise_distances(np.array([[0.0, 0.0], [1.0, 0.0]]), "cosine")
    with pytest.raises(ValueError, match="non-finite"):
        pairwise_distances(np.array([[np.nan, 0.0]]))
    with pytest.raises(ValueError, match="metric"):
        pairwise_distances(np.ones((2, 2)), "cityblock")


def test_maximum_filter_is_scipys_nearest_mode() -> None:
    r = np.random.default_rng(0)
    for i in range(80):
        shape = tuple(int(s) for s in r.integers(1, 30, int(r.integers(1, 4))))
        a = r.normal(size=shape).astype(np.float32 if i % 2 else np.float64)
        if i % 3 == 0:
            a = np.round(a, 1)                 # ties
        size = tuple(int(2 * r.integers(0, 8) + 1) for _ in shape)
        got = maximum_filter(a, size)
        assert got.dtype == a.dtype
        np.testing.assert_array_equal(got, scipy_maximum_filter(a, size=size, mode="nearest"))
    np.testing.assert_array_equal(maximum_filter(np.arange(6.0).reshape(2, 3), 3),
                                  [[4.0, 5.0, 5.0], [4.0, 5.0, 5.0]])
    with pytest.raises(ValueError, match="odd"):
        maximum_filter(np.ones((3, 3)), 2)
