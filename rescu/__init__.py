"""RESCU: recurrence-based 3D scene understanding from a single image.

The subpackages follow the data: ``discovery`` (stage I, RESCU-I: recurring patterns
(RPs) from SIFT features with a unit-recurring-pattern search) -> ``extension`` (stage
II, RESCU-II: each RP extended with region proposals and a per-image classifier) ->
``scene`` (vanishing points, 3D translation symmetry, completion and counts) ->
``captions`` (the same in words); ``evaluation`` scores them over datasets and ``data``
makes the synthetic benchmark. Beneath them all: ``types``, ``params``, ``io`` and
``layout`` (row geometry); on top: ``pipeline`` (one step per file), ``api``
(:func:`discover`), ``cli`` (the ``rescu`` command) and ``config``.
"""

import logging as _logging

__version__ = "0.1.0"

# a library logs, the application decides where to: without a handler of the caller's,
# a failed step's record (with its traceback) stays in the result, not on stderr
_logging.getLogger("rescu").addHandler(_logging.NullHandler())


def __getattr__(name: str):  # lazy: importing rescu stays cheap
    if name == "discover":
        from .api import discover

        return discover
    raise AttributeError(f"module 'rescu' has no attribute {name!r}")
