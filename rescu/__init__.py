"""RESCU: recurrence-based 3D scene understanding from a single image.

Stage I (RESCU-I) discovers recurring patterns (RPs) from SIFT features with a
unit-recurring-pattern search; stage II (RESCU-II) extends each RP with region proposals
and a per-image classifier; the scene module turns RPs into vanishing points, 3D
translation symmetry and counts; the caption module says so in words.
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
