"""Rows of the stage-I ablation table (the rule ``ablation``, ``make paper``): which of
P_d, P_s, P_theta are adaptive and the orientation mode (config ``ablation.variants``),
and which RP sources RESCU-I uses (config ``ablation.sources``)."""

from __future__ import annotations

from typing import Any

from ..types import Pattern
from .sources import DenseParams, combine_sources

#: Rows of the stage-I ablation that compare the sources (config ``ablation.sources``):
#: row name -> :func:`combine_sources` mode (None: stage I's RPs alone).
SOURCE_ROWS: dict[str, str | None] = {"sparse-only": None, "dense-only": "dense",
                                      "sparse+dense": "both"}


def ablation_overrides(spec: Any) -> dict[str, Any]:
    """Stage-I parameter overrides of one ablation variant.

    A variant is either a list of the adaptive parameters (``[P_d, P_s]``) or a mapping
    ``{adaptive: [...], orientation_mode: paper}`` of ``stage1`` keys to override
    (``adaptive`` and ``orientation_mode`` only).
    """
    if isinstance(spec, (list, tuple)):
        return {"adaptive": list(spec)}
    if isinstance(spec, dict):
        unknown = sorted(set(spec) - {"adaptive", "orientation_mode"})
        if unknown:
            raise ValueError(f"ablation variant keys {unknown} not allowed "
                             "(adaptive, orientation_mode)")
        if "adaptive" not in spec:
            raise ValueError("an ablation variant mapping needs 'adaptive'")
        return {k: (list(v) if k == "adaptive" else v) for k, v in spec.items()}
    raise ValueError(f"an ablation variant must be a list or a mapping, got {spec!r}")


def source_rows(sparse: list[Pattern], dense: list[Pattern], params: DenseParams,
                failure: dict[str, Any] | None = None
                ) -> dict[str, tuple[list[Pattern], dict[str, Any]]]:
    """The stage-I ablation's source rows (:data:`SOURCE_ROWS`) of one image.

    Parameters
    ----------
    sparse : stage I's RPs (RESCU-I without the dense source)
    dense : the dense step's RPs
    params : DenseParams (``mode`` is ignored: each row has its own)
    failure : the dense step's failure record, if it failed

    Returns
    -------
    row name -> (RPs, extra): deep copies, inputs untouched. With ``failure`` the
    dense-only row has no RP, the both row stage I's, and both extras
    ``{"dense_failure": failure}``.
    """
    import copy
    import dataclasses

    out: dict[str, tuple[list[Pattern], dict[str, Any]]] = {}
    for name, mode in SOURCE_ROWS.items():
        extra: dict[str, Any] = {"ablation": {"source": name}}
        if mode is None or (failure and mode == "both"):
            pats = copy.deepcopy(sparse)
        elif failure:
            pats = []
        else:       # combine_sources renumbers the patterns it is given: copies
            pats = combine_sources(copy.deepcopy(sparse), copy.deepcopy(dense),
                                   dataclasses.replace(params, mode=mode))
        out[name] = (pats, {**extra, "dense_failure": failure} if failure and mode else extra)
    return out
