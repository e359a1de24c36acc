"""The runnable examples in the docstrings of the public API (on tiny synthetic images)."""

import doctest
import importlib

import pytest

MODULES = ["rescu", "rescu.api", "rescu.config", "rescu.data.example", "rescu.discovery.features",
           "rescu.discovery.stage1", "rescu.evaluation.core",
           "rescu.evaluation.metrics", "rescu.scene.analyse"]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    res = doctest.testmod(importlib.import_module(name), report=True,
                          optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert res.failed == 0
    assert res.attempted > 0, f"{name}: no example ran"
