"""Building the parameter dataclasses (``XxxParams``) from configuration mappings."""

from __future__ import annotations

from dataclasses import fields
from typing import Any, Mapping, TypeVar

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
