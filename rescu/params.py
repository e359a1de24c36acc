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
        return cls

    return decorate


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
TS_WHICH: tuple[str, ...] = ("any", "dominant")
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

    def __post_init__(self) -> None:
        if not 0.0 < self.iod_h < 1.0:
            raise ValueError(f"EvaluationParams.iod_h must be in (0, 1), got {self.iod_h}")
        if not 0.0 <= self.min_rp_precision <= 1.0:
            raise ValueError("EvaluationParams.min_rp_precision must be in [0, 1], got "
                             f"{self.min_rp_precision}")
        if not 0.0 < self.significance_alpha < 1.0:
            raise ValueError("EvaluationParams.significance_alpha must be in (0, 1), got "
                             f"{self.significance_alpha}")
        if self.ts_which not in TS_WHICH:
            raise ValueError(f"EvaluationParams.ts_which must be one of {TS_WHICH}, got "
                             f"{self.ts_which!r}")
        for name in ("h_curve", "vp_px_thresholds", "vp_deg_thresholds", "vp_aa_thresholds",
                     "ts_t_fine", "ts_t_coarse"):
            v = getattr(self, name)
            if len(v) == 0 or any(not (float(x) > 0) for x in v):
                raise ValueError(f"EvaluationParams.{name} must be a non-empty list of "
                                 f"positive numbers, got {v!r}")
        if any(float(x) >= 1 for x in self.h_curve):
            raise ValueError(f"EvaluationParams.h_curve values must be in (0, 1), got "
                             f"{self.h_curve!r}")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "EvaluationParams":
        """Build from a config mapping; unknown keys raise ValueError naming them."""
        d = checked_mapping(cls, d, "evaluation parameter")
        for k in ("h_curve", "vp_px_thresholds", "vp_deg_thresholds", "ts_t_fine",
                  "ts_t_coarse"):
            if k in d:
                d[k] = tuple(float(x) for x in d[k])
        return cls(**d)
