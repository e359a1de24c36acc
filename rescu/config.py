"""Loading and validating the pipeline configuration outside Snakemake (the CLI, tests).

The configuration lives in ``config/config.yaml`` beside the package's source checkout
and is validated against ``config/config.schema.yaml`` (JSON Schema, Draft 2020-12), the
same schema the Snakefile uses.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Mapping

from .io import InputError

CONFIG_DIR = Path(__file__).resolve().parents[1] / "config"
DEFAULT_CONFIG = CONFIG_DIR / "config.yaml"
SCHEMA = CONFIG_DIR / "config.schema.yaml"


def _read_yaml(path: Path) -> Any:
    import yaml

    try:
        return yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except yaml.YAMLError as e:
        raise InputError(f"{path}: malformed YAML ({e})") from None


def deep_merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """``base`` updated recursively with ``override`` (a new dict; inputs unchanged)."""
    out = copy.deepcopy(base)
    for k, v in override.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


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
    import yaml

    if isinstance(overrides, Mapping):
        return {k: typed_cli_overrides(v) for k, v in overrides.items()}
    if isinstance(overrides, (list, tuple)):
        return [typed_cli_overrides(v) for v in overrides]
    if isinstance(overrides, str):
        try:
            v = yaml.safe_load(overrides)
        except yaml.YAMLError:
            return overrides
        if v is None or isinstance(v, (bool, int, float)):
            return v
    return overrides


def validate_config(config: dict[str, Any], source: str = "config") -> dict[str, Any]:
    """Validate ``config`` against the schema; raise :class:`InputError` naming the field."""
    import jsonschema

    schema = _read_yaml(SCHEMA)
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(config), key=lambda e: list(e.absolute_path))
    if errors:
        e = errors[0]
        where = ".".join(str(p) for p in e.absolute_path) or "(top level)"
        raise InputError(f"{source}: field '{where}': {e.message}")
    return config


def load_config(path: str | Path | None = None,
                overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The default configuration, updated with the YAML file ``path`` and ``overrides``.

    Raises :class:`InputError` naming the file and field when anything is invalid.
    """
    cfg = _read_yaml(DEFAULT_CONFIG)
    source = str(DEFAULT_CONFIG)
    if path is not None:
        user = _read_yaml(Path(path))
        if not isinstance(user, dict):
            raise InputError(f"{path}: top level must be a mapping of sections")
        cfg = deep_merge(cfg, user)
        source = str(path)
    if overrides:
        cfg = deep_merge(cfg, overrides)
    return validate_config(cfg, source)
