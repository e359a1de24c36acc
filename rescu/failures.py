"""What a failed step leaves, the one rule of both drivers (:func:`rescu.core.run` in
memory and :mod:`rescu.pipeline` file to file; :mod:`rescu.core` re-exports every name).

A step that raises becomes a failure record (:func:`attempt`); a step that refines a
result and fails keeps that result, *degraded* (:func:`degraded_result`: the record says
whose patterns were kept), so the later steps still run on it; a failure that is not
degraded is *blocking* (:func:`blocking`): the steps after it do not run and leave a
result with no pattern (:func:`empty_result`). :func:`failed_output` chooses between the
two.
"""

from __future__ import annotations

import logging
import traceback
from typing import Any, Callable, TypeVar

from . import io
from .types import Failure, ImageResult, failure_record

__all__ = ["attempt", "blocking", "degraded_result", "empty_result", "failed_output",
           "is_degraded"]

log = logging.getLogger("rescu")

T = TypeVar("T")


def is_degraded(failure: Failure | None) -> bool:
    """True when ``failure`` is the record of a degraded result (a failed step whose
    output is the previous step's result): the image keeps patterns, and later steps
    run on it."""
    return bool(failure) and bool(failure.get("degraded_to"))


def blocking(failure: Failure | None) -> Failure | None:
    """The upstream failure that makes a step skip: ``failure`` unless it is degraded."""
    return None if not failure or is_degraded(failure) else failure


def degraded_result(kept: ImageResult, method: str, failure: Failure) -> ImageResult:
    """``kept`` (the previous step's result) as the output of a step that failed.

    A copy of ``kept`` with ``method`` set and ``extra["failure"]`` = ``failure`` plus
    ``"degraded_to"``: the method whose patterns were kept (``kept.method``, or the
    ``degraded_to`` of ``kept``'s own degraded record, which is then also kept under
    ``"upstream"``).
    """
    res = ImageResult.from_json(kept.to_json())
    prev = kept.extra.get("failure")
    rec: Failure = {**failure, "degraded_to": (prev or {}).get("degraded_to") or kept.method}
    if prev:
        rec["upstream"] = prev
    res.method = method
    res.extra["failure"] = rec
    return res


def failed_output(meta: dict[str, Any], kept: ImageResult | None, method: str,
                  failure: Failure) -> ImageResult:
    """What a step that refines ``kept`` (its input; stage I's result for stage II)
    leaves when it failed or a failure upstream stopped it, in both drivers (:func:`run`,
    :mod:`rescu.pipeline`): ``kept`` degraded (:func:`degraded_result`) when there is
    one to keep (not None, not itself :func:`blocking`), else :func:`empty_result`.

    >>> f = {"stage": "stage2-train", "message": "boom"}
    >>> s1 = ImageResult(image="a.png", width=8, height=8, method="rescu-i")
    >>> failed_output({}, s1, "rescu-ii", f).extra["failure"]["degraded_to"]
    'rescu-i'
    >>> failed_output({}, None, "rescu-ii", f).extra["failure"]
    {'stage': 'stage2-train', 'message': 'boom'}
    """
    if kept is None or blocking(kept.extra.get("failure")) is not None:
        return empty_result(meta, method, failure)
    return degraded_result(kept, method, failure)


def empty_result(meta: dict[str, Any], method: str, failure: Failure | None) -> ImageResult:
    """A result with no pattern for the image described by ``meta``."""
    w, h = meta.get("original_size", [0, 0])
    extra = {"failure": failure} if failure else {}
    return ImageResult(image=meta.get("image", ""), width=int(w), height=int(h),
                       method=method, extra=extra)


def attempt(stage: str, step: Callable[[], T]) -> tuple[T | None, Failure | None]:
    """``(step(), None)``, or ``(None, failure record)`` when ``step`` raised.

    Errors that are not the image's fault (memory, interrupt, a full disk) propagate;
    any other exception is logged with its traceback and becomes the record
    :func:`rescu.types.failure_record` of ``stage``.
    """
    try:
        return step(), None
    except (MemoryError, KeyboardInterrupt, io.DiskFullError):
        raise
    except Exception as e:  # noqa: BLE001 - isolation is the point
        log.error("%s failed: %s\n%s", stage, e, traceback.format_exc())
        return None, failure_record(stage, e)
