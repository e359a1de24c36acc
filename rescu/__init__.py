"""RESCU: recurrence-based 3D scene understanding from a single image.

The subpackages follow the data: ``discovery`` (stage I, RESCU-I: recurring patterns
(RPs) from SIFT features with a unit-recurring-pattern search) -> ``extension`` (stage
II, RESCU-II: each RP extended with region proposals and a per-image classifier) ->
``scene`` (vanishing points, 3D translation symmetry, completion and counts) ->
``captions`` (the same in words); ``evaluation`` scores them over datasets and ``data``
makes the synthetic benchmark. Beneath them all: ``types``, ``params``, ``io`` and
``layout`` (row geometry); on top: ``core`` (the stages in memory, :func:`run`),
``pipeline`` (one step per file), ``api`` (:func:`discover`), ``cli`` (the ``rescu``
command) and ``config``.

The user API is importable from here (``__all__``), each name loaded on first use:

>>> import rescu
>>> from rescu import Stage1Params, discover, load_config
>>> discover is rescu.api.discover, Stage1Params().sigma_s
(True, 0.2)
"""

import logging as _logging

__version__ = "0.1.0"

# a library logs, the application decides where to: without a handler of the caller's,
# a failed step's record (with its traceback) stays in the result, not on stderr
_logging.getLogger("rescu").addHandler(_logging.NullHandler())


# the user API: ``from rescu import discover`` etc.; each name is imported on first use
_EXPORTS = {
    "run": "core",                              # one RGB array (or photo), in memory
    "discover": "api",                          # one photo, end to end, results written
    "load_config": "config",                    # the default configuration, checked
    "validate_config": "config",
    "InputError": "io",                         # bad input or configuration
    "ImageResult": "types",                     # the per-image result and its parts
    "Pattern": "types",
    "Instance": "types",
    "VanishingPoint": "types",
    "TranslationSymmetry": "types",
    "Features": "types",
    "RPMatrix": "types",
    "extract_features": "discovery.features",   # the steps, one by one
    "FeatureParams": "discovery.features",
    "Stage1Params": "discovery.stage1",
    "rps_to_patterns": "discovery.stage1",
    "score_image": "evaluation.metrics",        # evaluation: one image, a dataset folder
    "evaluate_rp_dataset": "evaluation.core",
    "example_image": "data.example",            # a tiny synthetic photo for examples
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str):  # lazy: importing rescu stays cheap
    if name in _EXPORTS:
        import importlib

        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'rescu' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
