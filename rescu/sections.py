"""A configuration section becomes its frozen parameter object here, and only here.

:data:`SECTIONS` is the registry: each section (a dotted key path of the configuration)
names the dataclass of its parameters and the class's builder from the section's mapping.
:func:`section_params` builds one; :func:`rescu.config.typed_config` builds them all, and
:func:`rescu.config.check_params` checks a configuration by building them.

The registry names the classes by module (imported when a section is first built), so
that a step that asks for one section depends on that section's module alone: the
workflow reruns a step when a module it imports changes
(:func:`rescu_workflow.code_deps.step_dependencies`), and each step imports the modules
of the sections it uses itself.
"""

from __future__ import annotations

import importlib
from typing import Any, Mapping

SECTIONS: dict[str, tuple[str, str, str]] = {
    "features": ("rescu.discovery.features", "FeatureParams", "from_dict"),
    "stage1": ("rescu.discovery.stage1", "Stage1Params", "from_dict"),
    "grasp": ("rescu.discovery.grasp", "GraspParams", "from_dict"),
    "dense": ("rescu.discovery.sources", "DenseParams", "from_dict"),
    "prompt": ("rescu.extension.prompted", "PromptParams", "from_dict"),
    "stage2": ("rescu.extension.params", "Stage2Params", "from_dict"),
    "scene": ("rescu.scene.analyse", "SceneParams", "from_config"),
    "scene.completion": ("rescu.scene.completion", "CompletionParams", "from_dict"),
    "scene.image_vp": ("rescu.scene.vp.manhattan", "ImageVPParams", "from_dict"),
    "scene.claims": ("rescu.scene.claims", "ClaimParams", "from_dict"),
    "caption": ("rescu.captions.caption", "CaptionParams", "from_dict"),
    "synthetic": ("rescu.data.synth", "SynthParams", "from_dict"),
    "evaluation": ("rescu.params", "EvaluationParams", "from_dict"),
}
"""Section (dotted key path) -> (module, parameter dataclass, its builder from the
section's mapping)."""


def section_class(name: str) -> type:
    """The parameter dataclass of the section ``name`` (:data:`SECTIONS`).

    >>> section_class("scene.claims").__name__
    'ClaimParams'
    """
    if name not in SECTIONS:
        raise ValueError(f"no parameters for a configuration section {name!r}; "
                         f"known: {', '.join(SECTIONS)}")
    module, cls, _ = SECTIONS[name]
    return getattr(importlib.import_module(module), cls)


def section_params(name: str, value: Any = None) -> Any:
    """The parameters of the configuration section ``name`` (one of :data:`SECTIONS`):
    built from its mapping (None: the defaults), or ``value`` itself when it is already
    that section's parameter dataclass. The one place a section's mapping becomes a
    frozen parameter object; the steps take the objects. Raises ValueError naming an
    unknown section, an unknown key or a bad value.

    >>> section_params("dense", {"min_instances": 3}).min_instances
    3
    >>> p = section_params("stage1")
    >>> section_params("stage1", p) is p
    True
    >>> section_params("scene.claims").min_rows
    2
    """
    cls = section_class(name)
    if isinstance(value, cls):
        return value
    return getattr(cls, SECTIONS[name][2])(value)


def stage2_variant(base: Mapping[str, Any], override: Mapping[str, Any] | None) -> Any:
    """The ``stage2`` parameters of an ablation variant: the section ``base`` (a mapping)
    with the variant's keys ``override`` merged in, nested
    (:meth:`rescu.extension.params.Stage2Params.variant`).

    >>> stage2_variant({}, {"head": {"lr": 0.01}}).head.lr
    0.01
    """
    return section_class("stage2").variant(base, override)


def section_at(config: Mapping[str, Any], name: str) -> Any:
    """The value at the dotted key path ``name`` of ``config`` (None where absent).

    >>> section_at({"scene": {"claims": {"min_rows": 3}}}, "scene.claims")
    {'min_rows': 3}
    >>> section_at({"scene": {}}, "scene.claims") is None
    True
    """
    d: Any = config
    for k in name.split("."):
        d = d.get(k) if isinstance(d, Mapping) else None
    return d
