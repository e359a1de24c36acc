"""Counting: instances per recurring pattern, the dominant RP, and count errors.

* The count of an RP is its number of instances.
* The *dominant* RP of an image is the most confident one when its RPs carry a
  confidence, else the one with the most instances; ties go to more instances, the
  higher score, then the lower pattern index (so the choice is deterministic;
  :func:`dominant_pattern`).
* Count errors are measured on *matched* RPs: :func:`count_pairs` turns the assignment
  of detected RPs to ground-truth RPs (``rescu.evaluation.metrics.score_image(...).rp_assignment``)
  into ``(predicted, ground-truth)`` count pairs, one per ground-truth RP that some
  detected RP is assigned to; when several detected RPs are assigned to the same
  ground-truth RP the one with the most instances is taken (ties: the first).
  Unmatched RPs enter the RP-level precision/recall, not the count error.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..types import Pattern


def pattern_counts(patterns: Sequence[Pattern]) -> list[int]:
    """Number of instances of each pattern.

    >>> from rescu.types import Instance, Pattern
    >>> pattern_counts([Pattern(id=0, score=1.0, instances=[Instance(bbox=(0, 0, 1, 1))] * 3)])
    [3]
    """
    return [p.count for p in patterns]


def dominant_pattern(patterns: Sequence[Pattern]) -> int | None:
    """Index (position in ``patterns``) of the dominant RP, None when there is none.

    The pattern of what the user's example boxes show (``extra["source"] == "prompt"``,
    :func:`rescu.core.find_prompted`) is dominant: it is what the user counts. Otherwise
    the dominant RP is the most confident one (``extra["confidence"]``,
    :func:`rescu.extension.objects.rp_confidence`) when the patterns carry confidences,
    else the one with the most instances; ties: more instances, higher score, then lower
    index. Patterns with no instance are never dominant.

    >>> from rescu.types import Instance, Pattern
    >>> box = Instance(bbox=(0, 0, 1, 1))
    >>> few = Pattern(id=0, score=0.9, instances=[box] * 3, extra={"confidence": 0.7})
    >>> many = Pattern(id=1, score=0.5, instances=[box] * 5, extra={"confidence": 0.4})
    >>> dominant_pattern([few, many]), dominant_pattern([]) is None
    (0, True)
    """
    for i, p in enumerate(patterns):
        if p.extra.get("source") == "prompt" and p.count:
            return i
    conf = any("confidence" in p.extra for p in patterns)
    best: tuple[float, int, float, int] | None = None
    for i, p in enumerate(patterns):
        if p.count == 0:
            continue
        key = (float(p.extra.get("confidence", 0.0)) if conf else 0.0, p.count,
               float(p.score), -i)
        if best is None or key > best:
            best = key
    return None if best is None else -best[3]


def count_pairs(det_counts: Sequence[int], gt_counts: Sequence[int],
                assignment: Sequence[int | None]) -> list[tuple[int, int]]:
    """``(predicted count, ground-truth count)`` pairs of one image's matched RPs.

    Parameters
    ----------
    det_counts : (D,) int
        Instances of each detected RP.
    gt_counts : (G,) int
        Instances of each ground-truth RP.
    assignment : (D,) int or None
        Ground-truth RP index assigned to each detected RP (None: unmatched).

    Returns
    -------
    list of (int, int)
        One pair per matched ground-truth RP, in ground-truth order (see module docstring).

    >>> count_pairs([5, 3, 8], [6, 9], [0, None, 1])
    [(5, 6), (8, 9)]
    """
    for d, g in enumerate(assignment):
        if g is not None and not 0 <= g < len(gt_counts):
            raise ValueError(f"assignment[{d}] = {g} is not a ground-truth RP index "
                             f"(0..{len(gt_counts) - 1})")
    best = counting_patterns(det_counts, assignment)
    return [(int(det_counts[best[g]]), int(gt_counts[g])) for g in sorted(best)]


def counting_patterns(det_counts: Sequence[int], assignment: Sequence[int | None]
                      ) -> dict[int, int]:
    """The detected RP that counts each matched ground-truth RP.

    Parameters
    ----------
    det_counts : (D,) int
        Instances of each detected RP.
    assignment : (D,) int or None
        Ground-truth RP index assigned to each detected RP (None: unmatched).

    Returns
    -------
    dict
        ``{ground-truth RP index: detected RP index}``: of the detected RPs assigned to a
        ground-truth RP, the one with the most instances (ties: the first).

    >>> counting_patterns([5, 7, 8], [0, 0, None])
    {0: 1}
    """
    if len(assignment) != len(det_counts):
        raise ValueError(f"assignment must have one entry per detected RP "
                         f"({len(det_counts)}), got {len(assignment)}")
    best: dict[int, int] = {}
    for d, g in enumerate(assignment):
        if g is not None and (g not in best or det_counts[d] > det_counts[best[g]]):
            best[g] = d
    return best


def count_errors(pairs: Sequence[tuple[int, int]]) -> dict[str, float]:
    """Mean absolute count error and exact-count rate over ``(pred, gt)`` pairs.

    Returns ``{"count_mae", "count_exact_rate", "count_mean_relative_error", "n_pairs"}``;
    the rates are NaN when there is no pair. The relative error is ``|pred - gt| / gt``.

    >>> e = count_errors([(5, 6), (8, 8)])
    >>> e["count_mae"], e["count_exact_rate"], round(e["count_mean_relative_error"], 4)
    (0.5, 0.5, 0.0833)
    """
    a = np.asarray(pairs, float).reshape(-1, 2)
    n = len(a)
    if n == 0:
        return {"count_mae": float("nan"), "count_exact_rate": float("nan"),
                "count_mean_relative_error": float("nan"), "n_pairs": 0}
    err = np.abs(a[:, 0] - a[:, 1])
    return {"count_mae": float(err.mean()), "count_exact_rate": float((err == 0).mean()),
            "count_mean_relative_error": float((err / np.maximum(a[:, 1], 1)).mean()),
            "n_pairs": n}
