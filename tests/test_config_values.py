"""Allowed values written once: each enumeration of the configuration's JSON Schema (which
cannot import Python) equals the one constant the code checks against."""

from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
SCHEMA = yaml.safe_load((REPO / "rescu" / "defaults" / "config.schema.yaml").read_text())


def schema_at(*path: str):
    """The subschema at ``path``: each key names a property, else a plain key (``$defs``,
    ``items``); ``$ref`` is followed."""
    node = SCHEMA
    for key in path:
        while "$ref" in node:
            node = _ref(node["$ref"])
        node = node["properties"][key] if key in node.get("properties", {}) else node[key]
    while "$ref" in node:
        node = _ref(node["$ref"])
    return node


def _ref(ref: str):
    node = SCHEMA
    for part in ref.lstrip("#/").split("/"):
        node = node[part]
    return node


def _constants():
    from rescu.captions.caption import CAPTIONERS
    from rescu.discovery.sources import MODES
    from rescu.discovery.stage1 import ADAPTIVE_NAMES
    from rescu.discovery.urp import ORIENTATION_MODES
    from rescu.extension.backbone import BACKBONES
    from rescu.extension.proposals import PROPOSAL_METHODS
    from rescu.names import DRAW_MODES
    from rescu.params import TS_WHICH

    return [
        (("stage1", "orientation_mode"), ORIENTATION_MODES),
        (("grasp", "orientation_mode"), ORIENTATION_MODES),
        (("$defs", "affinity", "orientation_mode"), ORIENTATION_MODES),
        (("ablation", "variants"), None),          # checked below (oneOf)
        (("dense", "mode"), MODES),
        (("dense", "backbone"), BACKBONES),
        (("stage2", "backbone", "name"), BACKBONES),
        (("stage2", "proposals", "method"), PROPOSAL_METHODS),
        (("report", "overlay"), DRAW_MODES),
        (("evaluation", "ts_which"), TS_WHICH),
        (("caption", "captioner"), CAPTIONERS),
        (("$defs", "adaptive_list", "items"), ADAPTIVE_NAMES),
    ]


@pytest.mark.parametrize("path,constant", [c for c in _constants() if c[1] is not None],
                         ids=lambda v: ".".join(v) if isinstance(v[0], str) else "")
def test_schema_enum_is_the_constant(path, constant):
    assert schema_at(*path)["enum"] == list(constant), path


def test_ablation_variant_orientation_modes_and_scene_source():
    from rescu.discovery.urp import ORIENTATION_MODES
    from rescu.names import METHODS

    variant = schema_at("ablation", "variants")["additionalProperties"]["oneOf"][1]
    mode = variant["properties"]["orientation_mode"]
    assert _ref(mode["$ref"])["enum"] == list(ORIENTATION_MODES)
    assert set(schema_at("scene", "source")["enum"]) <= set(METHODS)


def test_command_line_choices_are_the_constants():
    from rescu.cli import build_parser
    from rescu.names import METHODS, OVERLAY_MODES

    sub = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    discover = sub.choices["discover"]
    opts = {a.dest: a for a in discover._actions}
    assert tuple(opts["method"].choices) == METHODS and opts["method"].default == METHODS[0]
    assert tuple(opts["overlay"].choices) == OVERLAY_MODES


def test_orientation_modes_are_written_once_in_the_code():
    hits = [p for p in (REPO / "rescu").rglob("*.py")
            if '"wrapped", "relative", "paper"' in p.read_text()]
    assert [p.relative_to(REPO).as_posix() for p in hits] == ["rescu/discovery/urp.py"]


@pytest.mark.parametrize("path", sorted(str(p.relative_to(REPO)) for p in
                                        [*(REPO / "rescu" / "defaults").glob("*.yaml"),
                                         *(REPO / "config").glob("*.yaml")]))
def test_fast_yaml_reader_gives_the_safe_loaders_values(path: str) -> None:
    """rescu.params.load_yaml (PyYAML's C parser where present) reads every shipped YAML
    file as yaml.safe_load does."""
    from rescu.params import load_yaml

    text = (REPO / path).read_text()
    assert load_yaml(text) == yaml.safe_load(text)


def test_a_configuration_is_checked_once_per_content(monkeypatch) -> None:
    # the CLI, discover and run_image each check what they are given: a batch of photos
    # costs one check, and a configuration changed in place after it is checked again
    import rescu.config as C

    calls = []
    real = C.schema_errors
    monkeypatch.setattr(C, "schema_errors", lambda c: calls.append(1) or real(c))
    monkeypatch.setattr(C, "_VALID", {})
    cfg = C.load_config(stage2=False)
    n = len(calls)
    for _ in range(3):
        assert C.validate_config(cfg, stage2=False) is cfg
    assert len(calls) == n + (0 if n else 1)
    cfg["grasp"]["rcl_size"] = 0
    with pytest.raises(C.InputError, match="grasp.rcl_size = 0"):
        C.validate_config(cfg, stage2=False)
    first = n + (0 if n else 1) + 1
    assert len(calls) == first
    cfg["grasp"]["rcl_size"] = C.load_config(stage2=False)["grasp"]["rcl_size"]
    C.validate_config(cfg, stage2=False)   # the content found valid before
    assert len(calls) == first
    cfg["grasp"]["rcl_size"] += 1          # new content: checked once
    C.validate_config(cfg, stage2=False)
    C.validate_config(cfg, stage2=False)
    assert len(calls) == first + 1


def test_the_users_config_lists_the_usual_keys_with_their_defaults():
    """config/config.yaml (the file a user edits) names the keys a user usually changes,
    commented out, with their values: each is the default's (the example dataset aside),
    and the file itself overrides nothing."""
    import yaml

    from rescu.params import config_defaults

    text = (Path(__file__).resolve().parents[1] / "config" / "config.yaml").read_text()
    assert yaml.safe_load(text) == {}
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("# results_dir:"))
    shown = yaml.safe_load("\n".join(line[2:] for line in lines[start:]
                                     if line.startswith("# ")))
    defaults = config_defaults()
    leaves = []

    def walk(d, ref, path):
        for k, v in d.items():
            assert k in ref, f"config/config.yaml shows {'.'.join(path + (k,))}: no such key"
            if isinstance(v, dict):
                walk(v, ref[k], path + (k,))
            else:
                leaves.append(".".join(path + (k,)))
                assert v == ref[k], (f"config/config.yaml shows {leaves[-1]} = {v!r}, "
                                     f"the default is {ref[k]!r}")

    shown.pop("datasets")  # an example entry, not a default
    walk(shown, defaults, ())
    assert 20 <= len(leaves) <= 60


def test_each_default_has_a_one_line_comment():
    """The default configuration's comments say what a key does in one line (at most 160
    characters with the key); why a value was chosen is in config/README.md and docs/."""
    from rescu.config import DEFAULT_CONFIG

    long = [f"{n}: {line[:60]}..." for n, line in
            enumerate(DEFAULT_CONFIG.read_text().splitlines(), 1) if len(line) > 160]
    assert long == []
