"""RESCU: recurrence-based 3D scene understanding from a single image.

Stage I (RESCU-I) discovers recurring patterns (RPs) from SIFT features with a
unit-recurring-pattern search; stage II (RESCU-II) extends each RP with region proposals
and a per-image classifier; the scene module turns RPs into vanishing points, 3D
translation symmetry and counts; the caption module says so in words.
"""

__version__ = "0.1.0"


def __getattr__(name: str):  # lazy: importing rescu stays cheap
    if name == "discover":
        from .api import discover

        return discover
    raise AttributeError(f"module 'rescu' has no attribute {name!r}")
