"""The runnable examples in the docstrings of the public API (on tiny synthetic images).

Every module's examples run with the suite (``--doctest-modules`` on ``rescu/`` in
pyproject.toml; ``pytest rescu`` runs them alone); here: the public modules have some."""

import doctest
import importlib

import pytest

MODULES = ["rescu", "rescu.api", "rescu.config", "rescu.data.example", "rescu.discovery.features",
           "rescu.discovery.stage1", "rescu.evaluation.core",
           "rescu.evaluation.metrics", "rescu.scene.analyse", "rescu.boxes"]


@pytest.mark.parametrize("name", MODULES)
def test_public_modules_have_examples(name):
    tests = doctest.DocTestFinder().find(importlib.import_module(name))
    assert sum(len(t.examples) for t in tests) > 0, f"{name}: no docstring example"


def test_the_suite_runs_the_examples(pytestconfig):
    assert pytestconfig.getini("doctest_optionflags")
    assert "rescu" in pytestconfig.getini("testpaths")
    assert "--doctest-modules" in " ".join(pytestconfig.getini("addopts"))
