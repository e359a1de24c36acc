"""Each bound of a configuration key is written once, in the schema.

The parameter dataclasses (``@config_section``) check their fields against the schema
(:func:`rescu.params.check_schema_fields`); their own ``__post_init__`` checks only what
one key alone cannot say (relations between keys, conversions). These tests find every
such class in ``rescu`` and read its ``__post_init__``'s code.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import pkgutil
import textwrap

import pytest

import rescu
from rescu.params import _deref, schema_at, schema_enum

BOUND_KEYWORDS = {"minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum", "enum",
                  "const", "minItems", "maxItems", "type"}


def _sections() -> list[tuple[type, tuple[str, ...], object]]:
    """(class, schema path, the class's own ``__post_init__`` or None) of every
    ``@config_section`` dataclass of the library."""
    out, seen = [], set()
    for m in pkgutil.walk_packages(rescu.__path__, "rescu."):
        mod = importlib.import_module(m.name)
        for cls in vars(mod).values():
            if not isinstance(cls, type) or cls in seen or cls.__module__ != m.name:
                continue
            seen.add(cls)
            wrapper = cls.__dict__.get("__post_init__")
            cells = {type(c.cell_contents).__name__: c.cell_contents
                     for c in (getattr(wrapper, "__closure__", None) or ())}
            if "tuple" not in cells:  # not made by config_section
                continue
            own = cells.get("function")
            out.append((cls, cells["tuple"], own))
    return out


SECTIONS = _sections()
CASES = [pytest.param(*s, id=f"{s[0].__module__}.{s[0].__name__}") for s in SECTIONS]


def _bounded(sub: dict) -> bool:
    sub = _deref(sub)
    return bool(BOUND_KEYWORDS & set(sub)) or ("items" in sub and _bounded(sub["items"]))


def _self_fields(node: ast.AST) -> set[str]:
    return {a.attr for a in ast.walk(node) if isinstance(a, ast.Attribute)
            and isinstance(a.value, ast.Name) and a.value.id == "self"}


def _literal_names(loop: ast.For) -> set[str]:
    """The string constants a ``for name in ("a", "b")`` loop runs over."""
    it = loop.iter
    if isinstance(it, (ast.Tuple, ast.List)):
        return {e.value for e in it.elts if isinstance(e, ast.Constant)
                and isinstance(e.value, str)}
    return set()


def _restated_bounds(cls: type, path: tuple[str, ...], fn: object) -> list[str]:
    """Comparisons in ``fn`` of one schema-bounded field of ``cls`` with a constant (or a
    loop over such fields), each as ``"<field>: <source line>"``."""
    props = schema_at(*path).get("properties") or {}
    bounded = {k for k, v in props.items() if _bounded(v)}
    lines, _ = inspect.getsourcelines(fn)
    src = textwrap.dedent("".join(lines))
    tree = ast.parse(src)
    text = src.splitlines()
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            used = _self_fields(node)
            if len(used) == 1 and used <= bounded:  # one key against constants
                out.append(f"{used.pop()}: {text[node.lineno - 1].strip()}")
        if isinstance(node, ast.For):
            names = _literal_names(node) & bounded
            has_check = any(isinstance(x, ast.Raise) for x in ast.walk(node))
            if names and has_check:
                out.append(f"{sorted(names)}: {text[node.lineno - 1].strip()}")
    return out


def test_the_library_has_its_sections():
    names = {c.__name__ for c, _, _ in SECTIONS}
    assert {"Stage1Params", "DenseParams", "Stage2Params", "SceneParams", "CaptionParams",
            "EvaluationParams", "SynthParams", "CompletionParams", "PromptParams"} <= names
    assert len(SECTIONS) >= 20


@pytest.mark.parametrize("cls,path,fn", [c for c, s in zip(CASES, SECTIONS)
                                         if s[2] is not None])
def test_no_bound_is_written_twice(cls, path, fn):
    """A ``__post_init__`` does not compare a key the schema bounds with a constant:
    the schema holds that bound (cross-key relations such as ``min <= max`` stay)."""
    assert _restated_bounds(cls, path, fn) == [], (
        f"{cls.__name__}.__post_init__ restates bounds of rescu/defaults/config.schema.yaml "
        f"at {'.'.join(path)}: write them once, in the schema")


def test_the_finder_sees_a_restated_bound():
    """The check above finds what it looks for."""
    def __post_init__(self):
        if not 0 < self.max_nested_cover <= 1:
            raise ValueError("x")
        for k in ("sigma_s", "sigma_theta"):
            if getattr(self, k) < 0:
                raise ValueError(k)
        if self.min_instances > self.max_cols:  # a relation: allowed
            raise ValueError("y")

    from rescu.discovery.stage1 import Stage1Params

    found = _restated_bounds(Stage1Params, ("stage1",), __post_init__)
    assert sorted(f.split(":")[0] for f in found) == ["['sigma_s', 'sigma_theta']",
                                                      "max_nested_cover"]


@pytest.mark.parametrize("cls,path,fn", CASES)
def test_a_value_out_of_the_schema_is_refused_by_the_dataclass(cls, path, fn):
    """Built directly (not from a checked configuration), a dataclass refuses a value its
    schema refuses, naming the class, the field and the configuration key."""
    props = schema_at(*path).get("properties") or {}
    base = cls()
    for f in dataclasses.fields(cls):
        sub = _deref(props.get(f.name, {}))
        bad = None
        if "minimum" in sub:
            bad = sub["minimum"] - 1
        elif "exclusiveMinimum" in sub:
            bad = sub["exclusiveMinimum"]
        elif "maximum" in sub:
            bad = sub["maximum"] + 1
        elif "enum" in sub and all(isinstance(v, str) for v in sub["enum"]):
            bad = "no such value"
        if bad is None:
            continue
        with pytest.raises(ValueError) as e:
            dataclasses.replace(base, **{f.name: bad})
        key = ".".join(path + (f.name,))
        assert f"{cls.__name__}.{f.name} (configuration key {key})" in str(e.value)


def test_the_code_reads_its_lists_of_names_from_the_schema():
    from rescu.captions.caption import CAPTIONERS
    from rescu.discovery.sources import MODES
    from rescu.discovery.stage1 import ADAPTIVE_NAMES
    from rescu.discovery.urp import ORIENTATION_MODES
    from rescu.params import TS_WHICH

    assert MODES == schema_enum("dense", "mode") == ("both", "dense", "objects")
    assert ADAPTIVE_NAMES == ("P_d", "P_s", "P_theta")
    assert ORIENTATION_MODES == schema_enum("stage1", "orientation_mode")
    assert CAPTIONERS == schema_enum("caption", "captioner")
    assert TS_WHICH == schema_enum("evaluation", "ts_which")


def test_a_numpy_value_and_a_tuple_are_checked_as_the_configuration_holds_them():
    import numpy as np

    from rescu.discovery.sources import DenseParams

    p = DenseParams(min_instances=np.int64(3), sizes=(2, 3))
    assert p.min_instances == 3
    with pytest.raises(ValueError, match=r"DenseParams\.sizes .*dense\.sizes"):
        DenseParams(sizes=(0, 3))


def test_the_schema_restates_no_default_value():
    """A schema ``default`` only where the default configuration has no value (the keys
    of a user's dataset entry); every other default is the YAML's, written once."""
    from rescu.params import _schema, config_defaults

    found = []

    def walk(node: dict, value: object, path: tuple[str, ...]) -> None:
        node = _deref(node)
        if "default" in node and value is not _ABSENT:
            found.append(".".join(path))
        for key, sub in (node.get("properties") or {}).items():
            inner = value.get(key, _ABSENT) if isinstance(value, dict) else _ABSENT
            walk(sub, inner, path + (key,))

    walk(_schema(), config_defaults(), ())
    assert found == []


_ABSENT = object()


BUILDERS = {"from_dict", "from_config", "variant"}


def _builder_calls(path) -> list[str]:
    """Calls of a section's builder (``X.from_dict``, ``X.from_config``, ``X.variant``)
    in the file ``path`` outside the builders' own definitions, as ``"line: text"``."""
    text = path.read_text()
    tree = ast.parse(text)
    lines = text.splitlines()
    inside: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef) and node.name in BUILDERS:
            inside.update(range(node.lineno, node.end_lineno + 1))
    return [f"{n.lineno}: {lines[n.lineno - 1].strip()}" for n in ast.walk(tree)
            if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute)
            and n.func.attr in BUILDERS and n.lineno not in inside]


def test_sections_become_parameters_only_in_the_config_loader():
    """No step rebuilds its parameters from a mapping itself: the drivers (``rescu.core``,
    ``rescu.pipeline``, the workflow's scripts) ask ``rescu.sections.section_params`` (the
    registry of sections) and the library's functions take the built objects."""
    from pathlib import Path

    root = Path(rescu.__file__).resolve().parents[1]
    files = sorted((root / "rescu").rglob("*.py")) + sorted((root / "workflow").rglob("*.py"))
    loader = {root / "rescu" / "config.py", root / "rescu" / "sections.py"}
    found = {str(p.relative_to(root)): c for p in files if p not in loader
             for c in [_builder_calls(p)] if c}
    assert found == {}
    smk = [f"{p.name}: {line.strip()}" for p in sorted((root / "workflow").rglob("*.smk"))
           + [root / "Snakefile"] for line in p.read_text().splitlines()
           if any(f".{b}(" in line for b in BUILDERS)]
    assert smk == []


def test_section_params_is_the_registry_of_every_section():
    from rescu.config import SECTIONS, load_config, section_params

    cfg = load_config(stage2=False)
    for name in SECTIONS:
        at = cfg
        for k in name.split("."):
            at = at[k]
        p = section_params(name, at)
        assert dataclasses.is_dataclass(p) and section_params(name, p) is p
    with pytest.raises(ValueError, match="no parameters for a configuration section 'x'"):
        section_params("x")
    with pytest.raises(ValueError, match="bogus"):
        section_params("dense", {"bogus": 1})
