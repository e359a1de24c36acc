"""Names that several parts of the package share, each written once.

This module imports nothing, so the command line reads its choices from here without
loading NumPy. Enumerations owned by one stage live beside it (``ORIENTATION_MODES`` in
:mod:`rescu.discovery.urp`, ``MODES`` of the dense source in
:mod:`rescu.discovery.sources`, ``BACKBONES`` in :mod:`rescu.extension.backbone`, ...);
``tests/test_config_values.py`` checks every one against the enumerations of the
configuration's JSON Schema, which cannot import Python.
"""

from __future__ import annotations

METHODS: tuple[str, ...] = ("rescu-ii", "rescu-i", "grasp")
"""The discovery methods: ``rescu discover --method``, ``rescu.discover(method=...)``,
``ImageResult.method`` and the result folders the paper's tables compare, the default
first. RESCU-II is stage I extended by stage II, RESCU-I stage I alone, GRASP the
baseline."""

METHOD_LABELS: dict[str, str] = {"rescu-ii": "RESCU-II", "rescu-i": "RESCU-I",
                                 "grasp": "GRASP"}
"""The name of each of :data:`METHODS` in tables and reports."""

DRAW_MODES: tuple[str, ...] = ("boxes", "full")
"""What an overlay picture shows (``report.overlay`` in the configuration): ``boxes``:
instances, labels, legend and caption; ``full``: also the vanishing points."""

OVERLAY_MODES: tuple[str, ...] = DRAW_MODES + ("none",)
"""What ``rescu discover --overlay`` may ask for: a :data:`DRAW_MODES` picture, or
``none``: no picture (the callers write none)."""
