"""Building the parameter dataclasses (``XxxParams``) from configuration mappings, and
the one home of their defaults.

Every default value lives once, in the shipped default configuration
(``rescu/defaults/config.yaml``; the checkout's ``config/config.yaml`` holds only
overrides). A
parameter dataclass reads its field defaults from there with :func:`config_section`,
so each tunable is named once in the code::

    @dataclass(frozen=True)
    @config_section("stage1")
    class Stage1Params:
        P_d: float

A field named unlike its configuration key takes an explicit default from
:func:`config_defaults` (``k: int = config_defaults("stage1")["match_k"]``).
"""

from __future__ import annotations

import copy
import functools
from dataclasses import dataclass, fields
from typing import Any, Callable, Mapping, TypeVar

T = TypeVar("T")


def checked_mapping(cls: type, d: Mapping[str, Any] | None, label: str = "key") -> dict[str, Any]:
    """A copy of ``d`` whose keys are all fields of the dataclass ``cls``.

    Raises ValueError ``"<cls>: unknown <label>(s) [...]; known: [...]"`` otherwise, so a
    typo in the configuration is named instead of silently ignored.
    """
    out = dict(d or {})
    names = {f.name for f in fields(cls)}
    unknown = sorted(set(out) - names)
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown {label}(s) {unknown}; known: {sorted(names)}")
    return out


def params_from_dict(cls: type[T], d: Mapping[str, Any] | None) -> T:
    """``cls(**d)`` after :func:`checked_mapping`."""
    return cls(**checked_mapping(cls, d))


MAX_CONFIG_NODES = 100_000
"""The most values (mappings, lists and scalars, each alias counted where it is used) a
configuration may expand to: the defaults have about 1,000. A YAML alias bomb (anchors
nested a few levels) expands to billions and is refused after this many."""
MAX_CONFIG_TEXT = 100_000
"""The most characters one configuration string or key may have."""


def config_value_problem(value: Any, max_nodes: int = MAX_CONFIG_NODES,
                         max_text: int = MAX_CONFIG_TEXT) -> str | None:
    """What makes a configuration value unusable, in one line naming its key path, or
    None: over ``max_nodes`` values once its aliases are expanded, a string or key over
    ``max_text`` characters, or a number that is not finite (NaN, inf). Visits at most
    ``max_nodes`` values, so a bomb costs milliseconds, not its expansion.

    >>> config_value_problem({"stage1": {"sigma_s": float("nan")}})
    'stage1.sigma_s = nan: not a finite number'
    >>> bomb = ["x"] * 10
    >>> for _ in range(9):
    ...     bomb = [bomb] * 10
    >>> config_value_problem({"stage1": {"max_patterns": bomb}})
    'stage1.max_patterns: more than 100000 values (a YAML alias bomb?)'
    >>> config_value_problem({"a": [1, 2.5, None, "ok"]}) is None
    True
    """
    import math

    stack: list[tuple[tuple[str, ...], Any]] = [((), value)]
    seen = 0
    while stack:
        path, v = stack.pop()
        seen += 1
        where = ".".join(path) or "(top level)"
        if seen > max_nodes:
            top = ".".join(path[:2]) or "(top level)"
            return f"{top}: more than {max_nodes} values (a YAML alias bomb?)"
        if isinstance(v, Mapping):
            for k, x in reversed(list(v.items())):
                if isinstance(k, str) and len(k) > max_text:
                    return f"{where}: a key of {len(k)} characters (at most {max_text})"
                stack.append((path + (str(k)[:60],), x))
        elif isinstance(v, (list, tuple)):
            for i in range(len(v) - 1, -1, -1):
                stack.append((path + (str(i),), v[i]))
        elif isinstance(v, str):
            if len(v) > max_text:
                return f"{where}: a value of {len(v)} characters (at most {max_text})"
        elif isinstance(v, float) and not math.isfinite(v):
            return f"{where} = {v}: not a finite number"
    return None


def short_repr(value: Any, limit: int = 200) -> str:
    """``repr(value)`` cut to ``limit`` characters (a message never prints a huge value)."""
    import reprlib

    r = reprlib.Repr()
    r.maxstring = r.maxother = limit
    r.maxlist = r.maxdict = r.maxtuple = r.maxset = 8
    r.maxlevel = 3
    text = r.repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def load_yaml(text: str) -> Any:
    """The YAML document in ``text``, read as ``yaml.safe_load`` reads it.

    With PyYAML's C parser (``yaml.CSafeLoader``, present in PyYAML's wheels) when it is
    there: the same values (the constructor is the safe loader's) in a tenth of the time.
    Every pipeline job reads the 37-KB default configuration once: 0.04-0.06 s with the
    pure-Python parser, 0.004-0.005 s with the C one on an idle 2-core machine. Raises
    ``yaml.YAMLError`` on malformed text, as ``safe_load``.

    >>> load_yaml("a: [1, 2.5, null]")
    {'a': [1, 2.5, None]}
    """
    import yaml

    return yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))


@functools.cache
def _default_config() -> dict[str, Any]:
    """The shipped default configuration, parsed once per process."""
    import importlib.resources

    return load_yaml((importlib.resources.files("rescu") / "defaults" / "config.yaml")
                     .read_text())


def config_defaults(*path: str) -> dict[str, Any]:
    """A copy of the default configuration's mapping at ``path``.

    ``config_defaults("stage1")`` is the ``stage1`` section, ``config_defaults("scene",
    "completion")`` a nested one. YAML lists stay lists (:func:`config_section` makes
    them tuples). Raises KeyError naming the path when it is absent.
    """
    d: Any = _default_config()
    for i, k in enumerate(path):
        if not isinstance(d, dict) or k not in d:
            raise KeyError(f"default configuration has no {'.'.join(path[:i + 1])!r}")
        d = d[k]
    return copy.deepcopy(d)


def config_section(*path: str) -> Callable[[type[T]], type[T]]:
    """Class decorator, under ``@dataclass``: every annotated field of the class without a
    default gets the value of the same name in the default configuration's mapping at
    ``path`` (:func:`config_defaults`); a YAML list becomes a tuple (tuple-typed fields).

    Fields with a default (or ``field(...)``) keep it. Raises KeyError naming a field that
    has neither a default nor a key at ``path``.

    >>> from dataclasses import dataclass
    >>> @dataclass(frozen=True)
    ... @config_section("evaluation")
    ... class P:
    ...     iod_h: float
    ...     h_curve: tuple[float, ...]
    ...     label: str = "x"
    >>> P().iod_h, P().h_curve[:2], P().label
    (0.5, (0.1, 0.2), 'x')
    """
    section = config_defaults(*path)

    def decorate(cls: type[T]) -> type[T]:
        for name, ann in cls.__dict__.get("__annotations__", {}).items():
            if name in cls.__dict__ or str(ann).startswith(("ClassVar", "typing.ClassVar")):
                continue
            if name not in section:
                raise KeyError(f"{cls.__name__}.{name}: default configuration has no "
                               f"{'.'.join(path + (name,))!r}")
            v = section[name]
            setattr(cls, name, tuple(v) if isinstance(v, list) else v)
        own = getattr(cls, "__post_init__", None)

        def __post_init__(self: Any) -> None:
            check_schema_fields(self, path)
            if own is not None:
                own(self)

        __post_init__.__doc__ = (f"Every field the schema has at {'.'.join(path)!r} checked "
                                 f"against it (:func:`check_schema_fields`), then "
                                 f"{'the checks of ' + cls.__name__ if own else 'nothing more'}.")
        cls.__post_init__ = __post_init__  # type: ignore[attr-defined]
        return cls

    return decorate


@functools.cache
def _schema() -> dict[str, Any]:
    """The configuration's JSON Schema (``rescu/defaults/config.schema.yaml``), parsed once
    per process."""
    import importlib.resources

    return load_yaml((importlib.resources.files("rescu") / "defaults" / "config.schema.yaml")
                     .read_text())


def schema_at(*path: str) -> dict[str, Any]:
    """The schema of the configuration mapping at ``path`` (its ``$ref`` followed).

    >>> sorted(schema_at("scene", "completion")["properties"])[:2]
    ['cr_tolerance', 'enabled']
    >>> schema_at("stage1")["properties"]["max_nested_cover"]
    {'type': 'number', 'exclusiveMinimum': 0, 'maximum': 1}
    """
    node = _deref(_schema())
    for i, key in enumerate(path):
        props = node.get("properties") or {}
        if key not in props:
            raise KeyError(f"the configuration's schema has no {'.'.join(path[:i + 1])!r}")
        node = _deref(props[key])
    return node


def schema_enum(*path: str) -> tuple[Any, ...]:
    """The values the schema allows for the key at ``path`` (its ``enum``, or its items'
    for a list of names), in the schema's order: the code's tuples of names read them
    here, so each list of allowed values is written once.

    >>> schema_enum("dense", "mode")
    ('both', 'dense', 'objects')
    >>> schema_enum("stage1", "adaptive")
    ('P_d', 'P_s', 'P_theta')
    """
    node = schema_at(*path)
    if "enum" not in node and "items" in node:
        node = _deref(node["items"])
    return tuple(node["enum"])


def _deref(node: dict[str, Any]) -> dict[str, Any]:
    """``node`` with its ``$ref`` (a JSON pointer into the schema, ``#/...``) followed."""
    while "$ref" in node:
        target: Any = _schema()
        for part in node["$ref"].lstrip("#/").split("/"):
            target = target[part]
        node = target
    return node


@functools.cache
def _field_validators(path: tuple[str, ...]) -> dict[str, Any]:
    """One JSON Schema validator per leaf key (not a mapping) of the section at ``path``."""
    import jsonschema

    defs = _schema().get("$defs", {})
    out = {}
    for name, sub in (schema_at(*path).get("properties") or {}).items():
        leaf = _deref(sub)
        if leaf.get("type") == "object" or "properties" in leaf:
            continue  # a nested section: its own dataclass checks it
        out[name] = jsonschema.Draft202012Validator({**sub, "$defs": defs})
    return out


def _plain(value: Any) -> Any:
    """``value`` as the configuration holds it: tuples as lists, NumPy scalars as Python's."""
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "item") and getattr(value, "ndim", None) == 0:
        return value.item()
    return value


def check_schema_fields(obj: Any, path: tuple[str, ...],
                        key_of: Mapping[str, str] | None = None) -> None:
    """Check each field of the dataclass instance ``obj`` that the configuration's schema
    has at ``path`` against the schema: its type, bounds, allowed values and list lengths.

    The bounds of a key are written once, in the schema; the dataclasses'
    ``__post_init__`` check only what one key alone cannot say (relations between keys).
    :func:`config_section` runs this first in every ``__post_init__``; a dataclass whose
    fields are named unlike the keys passes ``key_of`` (field -> key). Raises ValueError
    ``"<Class>.<field> (configuration key <path>.<field>) = <value>: <what is wrong>"``.

    >>> from rescu.discovery.stage1 import Stage1Params
    >>> Stage1Params(max_nested_cover=1.5)
    Traceback (most recent call last):
    ...
    ValueError: Stage1Params.max_nested_cover (configuration key stage1.max_nested_cover) = 1.5: 1.5 is greater than the maximum of 1
    """
    path = tuple(path)
    validators = _field_validators(path)
    for f in fields(obj):
        name = (key_of or {}).get(f.name, f.name)
        if name not in validators:
            continue
        value = _plain(getattr(obj, f.name))
        try:
            err = _field_error(path, name, _frozen(value))
        except TypeError:  # unhashable (a mapping): checked without the memo
            err = _field_error.__wrapped__(path, name, value)
        if err is not None:
            key = ".".join(path + (name,))
            raise ValueError(f"{type(obj).__name__}.{f.name} (configuration key {key}) = "
                             f"{short_repr(value)}: {err}")


def _frozen(value: Any) -> Any:
    """A list as a hashable tuple, tagged so that ``[1]`` and ``1`` stay two keys."""
    if isinstance(value, list):
        return ("__list__",) + tuple(_frozen(v) for v in value)
    return (type(value).__name__, value)


def _thawed(value: Any) -> Any:
    if value[0] == "__list__":
        return [_thawed(v) for v in value[1:]]
    return value[1]


@functools.lru_cache(maxsize=4096)
def _field_error(path: tuple[str, ...], name: str, value: Any) -> str | None:
    """What the schema says is wrong with ``value`` (:func:`_frozen`) at ``path.name``, or
    None; memoised: the same values are checked again each time a stage builds its
    parameters (0.3 ms a section unmemoised)."""
    if isinstance(value, tuple):  # frozen (a plain value is never a tuple: _plain)
        value = _thawed(value)
    err = next(iter(_field_validators(path)[name].iter_errors(value)), None)
    return None if err is None else _short(err.message)


def _short(text: str, limit: int = 200) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


def deep_merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """``base`` updated recursively with ``override`` (a new dict; inputs unchanged).

    Used for configuration overrides (``--set``, ``--config``, config files) and for
    nested parameter variants (a stage-II variant overrides keys inside its sections).
    """
    out = copy.deepcopy(base)
    for k, v in override.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


# ------------------------------------------------------------------ evaluation section
TS_WHICH: tuple[str, ...] = schema_enum("evaluation", "ts_which")
"""Which RPs decide an image's translation symmetry (``evaluation.ts_which``): any
pattern, or the dominant one."""


@dataclass(frozen=True)
@config_section("evaluation")
class EvaluationParams:
    """Parameters of the evaluation (config section ``evaluation``).

    They live here, below the stages and the evaluation, so that checking a
    configuration (:func:`rescu.config.check_params`) does not import
    :mod:`rescu.evaluation`; ``rescu.evaluation.core.EvaluationParams`` is this class.

    Attributes
    ----------
    iod_h : float
        IOD threshold h of an acceptable detection, (0, 1).
    min_rp_precision : float
        Precision a detected RP needs against its GT RP to be accepted, [0, 1].
    h_curve : tuple of float
        IOD thresholds of the metric-vs-h curves.
    significance_alpha : float
        Significance level of the Wilcoxon tests (italics in Markdown).
    vp_px_thresholds : tuple of float
        Point-error thresholds of the VPD success rate, pixels.
    vp_deg_thresholds : tuple of float
        Angle-error thresholds of the VPD success rate, degrees.
    vp_aa_thresholds : tuple of float
        Thresholds t of the VPD angular accuracy AA@t (area under the angle-accuracy
        curve from 0 to t degrees, divided by t), degrees.
    ts_t_fine, ts_t_coarse : tuple of float
        Cross-ratio tolerances t of the SR_ts sweeps over (0, 0.15] and (0, 1].
    ts_which : str
        ``"any"`` pattern or the ``"dominant"`` one decides an image's TS.
    decimals : int
        Decimals in Markdown tables.
    """

    iod_h: float
    min_rp_precision: float
    h_curve: tuple[float, ...]
    significance_alpha: float
    vp_px_thresholds: tuple[float, ...]
    vp_deg_thresholds: tuple[float, ...]
    vp_aa_thresholds: tuple[float, ...]
    ts_t_fine: tuple[float, ...]
    ts_t_coarse: tuple[float, ...]
    ts_which: str
    decimals: int

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "EvaluationParams":
        """Build from a config mapping; unknown keys raise ValueError naming them."""
        d = checked_mapping(cls, d, "evaluation parameter")
        for k in ("h_curve", "vp_px_thresholds", "vp_deg_thresholds", "ts_t_fine",
                  "ts_t_coarse"):
            if k in d:
                d[k] = tuple(float(x) for x in d[k])
        return cls(**d)
