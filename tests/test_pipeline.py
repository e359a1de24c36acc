"""Pipeline helpers that need no workflow: ablation variant specs."""
from __future__ import annotations

import pytest

from rescu.discovery.ablation import ablation_overrides
from rescu.discovery import stage1


def test_ablation_variant_list_and_mapping() -> None:
    assert ablation_overrides([]) == {"adaptive": []}
    assert ablation_overrides(["P_d", "P_s"]) == {"adaptive": ["P_d", "P_s"]}
    over = ablation_overrides({"adaptive": ["P_theta"], "orientation_mode": "paper"})
    assert over == {"adaptive": ["P_theta"], "orientation_mode": "paper"}
    p = stage1.Stage1Params.from_dict(over)
    assert p.orientation_mode == "paper" and tuple(p.adaptive) == ("P_theta",)


@pytest.mark.parametrize("spec, match", [
    ({"adaptive": [], "sigma_s": 0.3}, "not allowed"),
    ({"orientation_mode": "paper"}, "needs 'adaptive'"),
    ("all", "list or a mapping"),
])
def test_ablation_variant_errors(spec, match) -> None:
    with pytest.raises(ValueError, match=match):
        ablation_overrides(spec)


def test_retain_freed_memory_on_glibc():
    import platform

    from rescu.pipeline import retain_freed_memory

    got = retain_freed_memory()
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        assert got is True
    else:
        assert got in (True, False)
