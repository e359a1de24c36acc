"""The benchmark scripts' own argument handling (their figures come from finished runs)."""

import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def load(name):
    sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location(name, BENCH / "studies" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_stage2_variants_sets_and_refusals(tmp_path, capsys):
    sv = load("stage2_variants")
    sets = sv.parse_sets(["examples.occlude_prob=0.5", "backbone.finetune=true",
                          "proposals.window_scales=[1, 1.2]", "backbone.device=cuda"])
    assert sv.nested(sets) == {"examples": {"occlude_prob": 0.5},
                               "backbone": {"finetune": True, "device": "cuda"},
                               "proposals": {"window_scales": [1, 1.2]}}
    with pytest.raises(ValueError, match="KEY=VALUE"):
        sv.parse_sets(["occlude_prob"])
    # an unknown or invalid stage2 key is a usage error naming it
    with pytest.raises(SystemExit):
        sv.main([str(tmp_path), "--set", "no_such_key=1"])
    assert "no_such_key" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        sv.main([str(tmp_path), "--set", "examples.occlude_prob=3"])
    assert "occlude_prob" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        sv.main([str(tmp_path), "--set", "occlude_prob=0.5"])   # not in its section
    assert "occlude_prob" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        sv.main([str(tmp_path), "--set", "examples.occlude_prob=0.5", "--threads", "0"])
    assert "--threads must be at least 1" in capsys.readouterr().err
    # a results folder without a run: a clear message, exit 2, nothing written
    assert sv.main([str(tmp_path), "--set", "examples.occlude_prob=0.5"]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    assert not (tmp_path / "benchmarks").exists()


def test_stage2_variants_refuses_a_folder_of_other_settings(tmp_path, capsys):
    sv = load("stage2_variants")
    for d in ("prepared", "rescu-i", "rescu-ii"):
        (tmp_path / "synthetic" / d).mkdir(parents=True)
    (tmp_path / "data" / "synthetic").mkdir(parents=True)
    (tmp_path / "data" / "synthetic" / "annotations.json").write_text(
        '{"images": [], "annotations": [], "categories": []}')
    assert sv.main([str(tmp_path), "--name", "v", "--set", "examples.occlude_prob=0.5"]) == 0
    assert "no image" in capsys.readouterr().out
    assert (tmp_path / "benchmarks" / "stage2-variants" / "v" / "params.json").is_file()
    assert sv.main([str(tmp_path), "--name", "v", "--set", "examples.occlude_prob=0.5"]) == 0
    assert sv.main([str(tmp_path), "--name", "v", "--set", "examples.occlude_prob=0.3"]) == 2
    assert "other settings" in capsys.readouterr().err


def test_stage2_misses_without_a_run(tmp_path, capsys):
    sm = load("stage2_misses")
    assert sm.main([str(tmp_path)]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    # a run whose RESCU-II found everything: no row, a count of 0
    (tmp_path / "synthetic" / "rescu-ii").mkdir(parents=True)
    (tmp_path / "data" / "synthetic").mkdir(parents=True)
    (tmp_path / "data" / "synthetic" / "annotations.json").write_text(
        '{"images": [], "annotations": [], "categories": []}')
    assert sm.main([str(tmp_path)]) == 0
    assert "0 GT instances missed" in capsys.readouterr().out


def test_completion_variants_refusals(tmp_path, capsys):
    cv = load("completion_variants")
    with pytest.raises(SystemExit):
        cv.main([str(tmp_path), "--set", "no_such_key=1"])
    assert "no_such_key" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cv.main([str(tmp_path), "--set", "max_step_ratio=0.5"])
    assert "max_step_ratio" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cv.main([str(tmp_path), "--workers", "0"])
    assert "--workers must be at least 1" in capsys.readouterr().err
    assert cv.main([str(tmp_path), "--set", "end_instances=2"]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    assert not (tmp_path / "benchmarks").exists()


def test_stage1_variants_refusals(tmp_path, capsys):
    s1 = load("stage1_variants")
    with pytest.raises(SystemExit):          # not a stage1 key
        s1.main([str(tmp_path), "--set", "no_such_key=1"])
    assert "no_such_key" in capsys.readouterr().err
    with pytest.raises(SystemExit):          # not a dataset of the config
        s1.main([str(tmp_path), "--dataset", "nowhere", "--set", "max_patterns=8"])
    assert "nowhere" in capsys.readouterr().err
    assert s1.main([str(tmp_path), "--set", "max_patterns=8"]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    assert not (tmp_path / "benchmarks").exists()


def test_dense_variants_refusals(tmp_path, capsys):
    dv = load("dense_variants")
    with pytest.raises(SystemExit):          # not a dense key
        dv.main([str(tmp_path), "--set", "no_such_key=1"])
    assert "no_such_key" in capsys.readouterr().err
    with pytest.raises(SystemExit):          # a value DenseParams refuses
        dv.main([str(tmp_path), "--set", "max_touching=9"])
    assert "max_touching" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        dv.main([str(tmp_path), "--dataset", "nowhere"])
    assert "nowhere" in capsys.readouterr().err
    assert dv.main([str(tmp_path), "--set", "max_touching=4"]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    assert not (tmp_path / "benchmarks").exists()


def test_precision_breakdown_without_a_run_and_on_an_empty_one(tmp_path, capsys):
    pb = load("precision_breakdown")
    assert pb.main([str(tmp_path)]) == 2
    assert "run the pipeline first" in capsys.readouterr().err
    (tmp_path / "synthetic" / "rescu-ii").mkdir(parents=True)
    (tmp_path / "data" / "synthetic").mkdir(parents=True)
    (tmp_path / "data" / "synthetic" / "annotations.json").write_text(
        '{"images": [], "annotations": [], "categories": []}')
    assert pb.main([str(tmp_path)]) == 0
    assert "0 images, 0 detected instances" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        pb.main([str(tmp_path), "--dataset", "no_such_set"])
