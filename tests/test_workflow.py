"""The pipeline end to end, as a user runs it: Snakemake in a fresh folder on three tiny
synthetic images. Checks outputs exist and parse, a second run does nothing, and a
parameter change reruns only the jobs that depend on it."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = Path(sys.executable).parent / "snakemake"

pytestmark = pytest.mark.slow


def tiny_config(tmp: Path, **overrides) -> Path:
    """A config that processes only three small synthetic images, fast settings."""
    default = yaml.safe_load((REPO / "rescu" / "defaults" / "config.yaml").read_text())
    datasets = {name: {"enabled": False} for name in default["datasets"]}
    datasets["synthetic"] = {"kind": "synthetic", "enabled": True}
    cfg = {
        "paper": True,  # the ablations too: every rule of the pipeline runs
        "datasets": datasets,
        "synthetic": {"n_images": 3, "sizes": [[480, 360]]},
        "ablation": {"datasets": ["synthetic"]},
        "stage2": {"head": {"max_epochs": 2}, "proposals": {"max_proposals": 200}},
        "report": {"samples_per_dataset": 2},
    }
    for key, value in overrides.items():
        section, field = key.split(".", 1)
        cfg.setdefault(section, {})
        node = cfg[section]
        parts = field.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    path = tmp / "config.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def snakemake(workdir: Path, configfile: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [str(SNAKEMAKE), "-s", str(REPO / "Snakefile"), "--directory", str(workdir),
           "--configfile", str(configfile), "--cores", "2", *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1200)
    if proc.returncode != 0:
        raise AssertionError(f"snakemake failed ({proc.returncode}):\n{proc.stdout[-4000:]}\n"
                             f"{proc.stderr[-6000:]}")
    return proc


def assert_outputs_under(proc: subprocess.CompletedProcess, out_dir: str) -> None:
    """Every output and log path a dry run plans lies under ``out_dir``."""
    text = proc.stdout + proc.stderr
    outs = re.findall(r"^\s+(?:output|log): (.*)$", text, re.M)
    paths = [p.strip() for line in outs for p in line.split(",")]
    assert paths and all(p.startswith(out_dir) for p in paths), \
        [p for p in paths if not p.startswith(out_dir)][:5]


def planned_jobs(proc: subprocess.CompletedProcess) -> dict[str, int]:
    """Job counts per rule from a dry run's 'Job stats' table ({} when nothing to do)."""
    text = proc.stdout + proc.stderr
    if "Nothing to be done" in text:
        return {}
    m = re.search(r"Job stats:\n(.*?)\n\s*\n", text, re.S)
    assert m, f"no job stats in dry run output:\n{text[-3000:]}"
    jobs = {}
    for line in m.group(1).splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[1].isdigit() and parts[0] not in ("job", "total"):
            jobs[parts[0]] = int(parts[1])
    return jobs


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    work = tmp_path_factory.mktemp("wf")
    cfg = tiny_config(work)
    snakemake(work, cfg)
    return work, cfg


def test_outputs_exist_and_parse(finished_run):
    work, _ = finished_run
    res = work / "results"
    finals = sorted((res / "synthetic" / "final").glob("*.json"))
    assert len(finals) == 3
    for f in finals:
        d = json.loads(f.read_text())
        for key in ("image", "width", "height", "method", "patterns", "dominant_pattern",
                    "vanishing_point", "caption"):
            assert key in d, f"{f}: missing {key}"
        assert d["method"] == "rescu-ii"
        assert "failure" not in d, d.get("failure")
        assert d["caption"]["base"] and d["caption"]["enhanced"]
        # the image's VPs (joint step) beside the RP-only one
        assert isinstance(d["vanishing_points"], list) and "rp_vanishing_point" in d
        assert "focal_px" in d and "focal_estimated" in d
    assert len(list((res / "synthetic" / "overlay").glob("*.png"))) == 3
    assert len(list((res / "synthetic" / "features").glob("*.h5"))) == 3
    assert len(list((res / "synthetic" / "stage2").glob("*.head.h5"))) == 3
    for table in ("rp_discovery", "ablation", "stage2_ablation", "counting", "vpd", "ts",
                  "captions", "failures", "vpd_aa", "vpd_triplet_errors"):
        assert (res / "tables" / f"{table}.tsv").exists(), table
    assert "RESCU joint" in (res / "tables" / "vpd.md").read_text()
    # every ablation variant has its per-image JSONs and a row in its table
    default = yaml.safe_load((REPO / "rescu" / "defaults" / "config.yaml").read_text())
    abl = (res / "tables" / "ablation.tsv").read_text()
    s2 = (res / "tables" / "stage2_ablation.tsv").read_text()
    for v in default["ablation"]["variants"]:
        assert len(list((res / "synthetic" / "ablation" / v).glob("*.json"))) == 3, v
        assert f"\t{v}\t" in abl, v
    for v in default["stage2_ablation"]["variants"]:
        assert len(list((res / "synthetic" / "stage2-ablation" / v).glob("*.json"))) == 3, v
        assert f"RESCU-II[{v}]" in s2, v
    summary = (res / "tables" / "summary.md").read_text()
    assert "Stage-II backbone: **efficientnet-lite0**" in summary, summary[:300]
    # per-step logs live with their results (a second results folder keeps its own)
    assert len(list((res / "logs" / "synthetic" / "scene").glob("*.log"))) == 3
    assert not (work / "logs").exists()
    html = (res / "report" / "index.html").read_text()
    assert "<img" in html and "RESCU" in html


def test_second_run_does_nothing(finished_run):
    work, cfg = finished_run
    assert planned_jobs(snakemake(work, cfg, "-n")) == {}


def test_parameter_change_reruns_only_dependants(finished_run, tmp_path):
    work, _ = finished_run
    # the changed config beside this test, never over the run's own (later tests read it)
    changed = tiny_config(tmp_path, **{"scene.symmetry.threshold": 0.05})
    jobs = planned_jobs(snakemake(work, changed, "-n"))
    assert jobs, "a changed scene parameter must rerun something"
    assert jobs.get("scene") == 3 and jobs.get("caption") == 3
    for upstream in ("prepare", "features", "rescu_i", "grasp", "ablation", "stage2_features",
                     "stage2_predict", "stage2_ablation", "generate_synthetic",
                     "line_vp"):
        assert upstream not in jobs, f"{upstream} must not rerun after a scene change: {jobs}"


def test_code_change_reruns_its_steps_only(finished_run, tmp_path):
    """A rule's code input is one stamp per workflow script listing the library files the
    script runs with their SHA-256, rewritten while the workflow is read when one of them
    changes (no job). An edit of one library file reruns the steps that run it, nothing
    upstream (the edit made in a copy of the checkout, whose Snakefile then runs)."""
    import os

    work, cfg = finished_run
    assert planned_jobs(snakemake(work, cfg, "-n")) == {}
    stamp = work / "results" / ".code" / "scene.txt"
    listed = stamp.read_text()
    assert "rescu/scene/completion.py" in listed and "rescu/discovery/" not in listed
    times = (stamp.stat().st_atime, stamp.stat().st_mtime)
    copy = tmp_path / "edited"  # the checkout with one library file edited
    copy.mkdir()
    for part in ("Snakefile", "workflow", "config", "rescu"):
        if (REPO / part).is_dir():
            shutil.copytree(REPO / part, copy / part,
                            ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(REPO / part, copy / part)
    edited = copy / "rescu" / "scene" / "completion.py"  # run by the scene step alone
    edited.write_text(edited.read_text() + "\n# an edit\n")
    cmd = [str(SNAKEMAKE), "-s", str(copy / "Snakefile"), "--directory", str(work),
           "--configfile", str(cfg), "--cores", "2", "-n"]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        rewritten = stamp.read_text()
    finally:
        stamp.write_text(listed)
        os.utime(stamp, times)  # as it was: the later tests see a finished run
    assert proc.returncode == 0, proc.stderr[-3000:]
    jobs = planned_jobs(proc)
    assert jobs.get("scene") == 3 and jobs.get("caption") == 3, jobs
    changed = set(rewritten.splitlines()) ^ set(listed.splitlines())
    assert {line.split()[1] for line in changed} == {"rescu/scene/completion.py"}, changed
    for upstream in ("prepare", "features", "rescu_i", "grasp",
                     "stage2_features", "stage2_predict",
                     "generate_synthetic", "line_vp"):
        assert upstream not in jobs, f"{upstream} must not rerun after a scene code edit: {jobs}"
    assert planned_jobs(snakemake(work, cfg, "-n")) == {}


def test_stage2_gate_change_reruns_prediction_only(finished_run, tmp_path):
    work, _ = finished_run
    changed = tiny_config(tmp_path, **{"stage2.predict.lattice_score_threshold": 0.9})
    jobs = planned_jobs(snakemake(work, changed, "-n"))
    assert jobs.get("stage2_predict") == 3, jobs
    for upstream in ("features", "rescu_i", "stage2_features"):
        assert upstream not in jobs, f"{upstream} must not rerun after a gate change: {jobs}"


def test_stage2_features_do_not_depend_on_cores(finished_run, tmp_path):
    """The stage-II torch threads come from the config's ``threads``, not the job's share
    of ``--cores``: features made again under ``--cores 1`` equal the ``--cores 2`` run's
    (float sums depend on the thread count, e.g. ~3e-7 on a chess photo's features)."""
    import h5py

    work, cfg = finished_run
    copy = tmp_path / "wf"
    shutil.copytree(work, copy, symlinks=True)
    h5 = sorted((work / "results" / "synthetic" / "stage2").glob("*.feats.h5"))[0]
    target = h5.relative_to(work)
    snakemake(copy, cfg, "--cores", "1", "--force", str(target))
    with h5py.File(h5, "r") as a, h5py.File(copy / target, "r") as b:
        assert sorted(a) == sorted(b)
        for k in a:
            assert np.array_equal(a[k][()], b[k][()]), k


@pytest.mark.parametrize("seed", [None, 11])
def test_holdout_config_plans_only_the_reseeded_synthetic_set(tmp_path, seed):
    """config/holdout.yaml (``make holdout``): the synthetic benchmark with another seed,
    every other dataset off, everything (logs included) under results/holdout.
    ``make holdout SEED=11`` passes the seed on the command line (a nested --config
    value, which snakemake gives as a string and the Snakefile retypes)."""
    extra = () if seed is None else (
        "--config", f"synthetic={{seed: {seed}}}", f"results_dir=results/holdout-{seed}",
        "datasets={cmp_facade: {max_images: null}}")
    out_dir = "results/holdout/" if seed is None else f"results/holdout-{seed}/"
    proc = snakemake(tmp_path, REPO / "config" / "holdout.yaml", "-n", *extra)
    jobs = planned_jobs(proc)
    holdout = yaml.safe_load((REPO / "config" / "holdout.yaml").read_text())
    n = yaml.safe_load((REPO / "rescu" / "defaults" / "config.yaml").read_text())["synthetic"]["n_images"]
    assert holdout["synthetic"]["seed"] != 0 and holdout["results_dir"] == "results/holdout"
    assert holdout["run_datasets"] == ["synthetic"]
    assert jobs.get("generate_synthetic") == 1 and jobs.get("scene") == n, jobs
    assert "export_photos" not in jobs, jobs
    assert_outputs_under(proc, out_dir)


def test_default_run_has_no_ablation_and_paper_run_has_every_table(tmp_path):
    """``make run`` plans the main methods only; ``make paper`` (config/paper.yaml) adds
    the ablations on every image of each dataset, into results/paper/."""
    cfg = tiny_config(tmp_path)
    cfg.write_text(cfg.read_text().replace("paper: true", "paper: false"))
    jobs = planned_jobs(snakemake(tmp_path, cfg, "-n"))
    for main in ("rescu_i", "grasp", "stage2_predict", "scene", "line_vp", "summary", "report"):
        assert jobs.get(main), (main, jobs)
    for absent in ("ablation", "stage2_ablation", "stage2_predict_ablation", "scene_no_ac",
                   "ablation_tables", "stage2_ablation_tables"):
        assert absent not in jobs, jobs
    paper = yaml.safe_load((REPO / "config" / "paper.yaml").read_text())
    assert paper["paper"] is True and paper["results_dir"] == "results/paper"
    assert all(d["max_images"] is None for d in paper["datasets"].values())
    proc = snakemake(tmp_path, REPO / "config" / "paper.yaml", "-n")
    jobs = planned_jobs(proc)
    for name in ("ablation", "stage2_ablation", "scene_no_ac", "ablation_tables",
                 "stage2_ablation_tables", "summary"):
        assert jobs.get(name), (name, jobs)
    # the dense step runs once per image (the default's whole objects; the ablation's
    # source rows read the same result)
    assert jobs.get("dense") == jobs["rescu_i"] >= jobs["ablation"], jobs
    assert re.search(r"output: [^\n]*ablation/sparse\+dense/\S+\.json", proc.stdout)
    assert_outputs_under(proc, "results/paper/")


def test_dense_source_adds_its_step_before_rescu_i_and_a_table_row(tmp_path):
    """dense.enabled (the default): one `dense` job per image, RESCU-I reads it (its
    params change only then), and the RP table gets the dense source's own row; off:
    none."""
    off = tiny_config(tmp_path, **{"dense.enabled": False})
    off.write_text(off.read_text().replace("paper: true", "paper: false"))
    assert "dense" not in planned_jobs(snakemake(tmp_path, off, "-n"))
    on = tiny_config(tmp_path)
    on.write_text(on.read_text().replace("paper: true", "paper: false"))
    proc = snakemake(tmp_path, on, "-n", "--", "results/tables/rp_discovery.md")
    jobs = planned_jobs(proc)
    assert jobs.get("dense") == 3 and jobs.get("rescu_i") == 3, jobs
    assert re.search(r"input: [^\n]*results/synthetic/dense/\S+\.json", proc.stdout)


def test_stress_config_plans_the_occluded_set_up_to_the_stage2_tables(tmp_path):
    """config/stress.yaml (``make stress``): every synthetic image hard, more and larger
    occluders than the default set, its own seed and folder; ``make stress`` asks for the
    stage-II and counting tables only (no GRASP, no stage-I ablation)."""
    stress = yaml.safe_load((REPO / "config" / "stress.yaml").read_text())
    default = yaml.safe_load((REPO / "rescu" / "defaults" / "config.yaml").read_text())["synthetic"]
    holdout = yaml.safe_load((REPO / "config" / "holdout.yaml").read_text())["synthetic"]
    syn = stress["synthetic"]
    assert syn["seed"] not in (default["seed"], holdout["seed"])
    assert syn["hard_fraction"] == 1.0
    assert syn["occluded_instances"][0] > default["occluded_instances"][0]
    assert syn["occlusion_fraction"][1] > default["occlusion_fraction"][1]
    assert stress["run_datasets"] == ["synthetic"] and stress["results_dir"] == "results/stress"
    out_dir = "results/stress/"
    proc = snakemake(tmp_path, REPO / "config" / "stress.yaml", "-n", "--",
                     out_dir + "tables/stage2_ablation.md", out_dir + "tables/counting.md")
    jobs = planned_jobs(proc)
    n = default["n_images"]
    assert jobs.get("generate_synthetic") == 1 and jobs.get("stage2_predict") == n, jobs
    assert jobs.get("stage2_ablation") == n and jobs.get("scene") == n, jobs
    for absent in ("grasp", "ablation", "export_photos", "line_vp", "prepare_photos"):
        assert absent not in jobs, jobs
    assert_outputs_under(proc, out_dir)


def test_stage2_misses_gives_every_missed_instance_one_cause(finished_run):
    """benchmarks/studies/stage2_misses.py on a finished run: one row per GT instance that no
    RESCU-II instance covers (IOD >= 0.5), each with one of its causes; a GT RP with
    nothing found has only 'rp not found' rows, the others never."""
    sys.path.insert(0, str(REPO / "benchmarks" / "studies"))
    import stage2_misses as SM

    from rescu.evaluation.core import load_predictions
    from rescu.io import load_coco_rps
    from rescu.evaluation.metrics import iod_matrix

    work, _ = finished_run
    res = work / "results"
    data = res / "data" / "synthetic"
    stage2 = yaml.safe_load((REPO / "rescu" / "defaults" / "config.yaml").read_text())["stage2"]
    df = SM.classify_misses(data, res, "synthetic", stage2)
    gt = load_coco_rps(data / "annotations.json")
    preds = load_predictions(res / "synthetic" / "rescu-ii", gt.keys())
    expected = 0
    for f, gts in gt.items():
        det = np.array([i.bbox for p in preds[f].patterns for i in p.instances],
                       float).reshape(-1, 4)
        for g, rp in enumerate(gts):
            G = np.asarray(rp.boxes, float).reshape(-1, 4)
            found = (iod_matrix(det, G) >= 0.5).any(0) if len(det) else np.zeros(len(G), bool)
            expected += int((~found).sum())
            rows = df[(df["image"] == f) & (df["gt_rp"] == g)]
            assert len(rows) == int((~found).sum())
            if len(rows):
                assert (rows["cause"] == "rp not found").all() == (not found.any())
    assert len(df) == expected
    assert set(df["cause"]) <= set(SM.CAUSES)
    assert df["occluded_fraction"].notna().all()  # the synthetic truth knows every one


def test_predict_only_variants_reuse_the_runs_features_and_head(finished_run, capsys):
    """A prediction-only stage-II variant gives the same instances whether the pipeline's
    stage2_predict_ablation rule or benchmarks/studies/stage2_variants.py computes it, and the
    script then reuses the run's features and head instead of recomputing them."""
    sys.path.insert(0, str(REPO / "benchmarks" / "studies"))
    import stage2_variants as SV

    work, _ = finished_run
    res = work / "results"
    pv = yaml.safe_load((REPO / "rescu" / "defaults" / "config.yaml").read_text())[
        "stage2_ablation"]["predict_variants"]
    assert pv["visible-half"] == {"predict": {"visible_half": True}}
    sets = [f"predict.{k}={str(v).lower()}" for k, v in pv["visible-half"]["predict"].items()]
    out = work / "sv-visible-half"
    argv = [str(res), "--out", str(out), "--name", "vh"]
    for s in sets:
        argv += ["--set", s]
    assert SV.main(argv) == 0
    assert "3 of 3 images from the run's own features and head" in capsys.readouterr().out
    for f in sorted((res / "synthetic" / "stage2-ablation" / "visible-half").glob("*.json")):
        a, b = json.loads(f.read_text()), json.loads((out / f.name).read_text())
        assert a["method"] == "rescu-ii[visible-half]"
        assert a["patterns"] == b["patterns"], f.name
        assert "added_by_visible_half" in a["stage2"]["prediction"]


def test_vp_ac_sweep_reproduces_the_pipelines_vp_at_its_own_settings(finished_run, capsys):
    """benchmarks/studies/vp_ac_sweep.py recomputes the image VP from the scene step's input: at
    the config's budget and seed with the AC on, its errors are the pipeline's own
    (scene/), and without the AC those of scene-noac/; every variant has one row per
    image with a GT VP."""
    sys.path.insert(0, str(REPO / "benchmarks" / "studies"))
    import vp_ac_sweep as AS

    from rescu.config import load_config
    from rescu.evaluation.vpd import vp_frame

    work, cfg_path = finished_run
    res = work / "results"
    cfg = load_config(cfg_path)
    vp_cfg = cfg["scene"]["vp"]
    df = AS.sweep(res, cfg, ["synthetic"], [2, vp_cfg["ransac_iterations"]], 2)
    data = res / "data" / "synthetic"
    frame = vp_frame(data, {"on": res / "synthetic" / "scene",
                            "off": res / "synthetic" / "scene-noac"})
    assert len(frame) > 0
    n = len(frame) // 2
    assert len(df) == n * 2 * 2 * 2  # budgets x seeds x AC
    own = df[(df["budget"] == vp_cfg["ransac_iterations"]) & (df["seed"] == vp_cfg["seed"])]
    for ac, name in ((True, "on"), (False, "off")):
        mine = own[own["ac"] == ac].set_index("image")["err"].sort_index()
        theirs = frame[frame["method"] == name].set_index("image")["angle_error_deg"]
        # the JSONs keep 9 decimals of the unit homogeneous VP: ~1e-6 degrees
        np.testing.assert_allclose(mine.to_numpy(), theirs.sort_index().to_numpy(),
                                   rtol=0, atol=1e-4)
    table = AS.summarise(df, [5.0])
    assert set(table["AC"]) == {"on", "off"} and len(table) == 4
    assert table["success@5deg"].between(0, 1).all()
    # usage errors and a folder without a run
    with pytest.raises(SystemExit):
        AS.main([str(res), "--budgets", "0"])
    assert "at least 1" in capsys.readouterr().err
    assert AS.main([str(work / "nothing"), "--datasets", "synthetic"]) == 2
    assert "run the pipeline first" in capsys.readouterr().err


def test_rp_image_vp_study_recomputes_the_scene_steps_image_vp(finished_run, capsys):
    """benchmarks/studies/rp_image_vp.py at the config's settings gives every image the VP
    of the run's scene/ JSON, and prints one row per dataset."""
    sys.path.insert(0, str(REPO / "benchmarks" / "studies"))
    import rp_image_vp as RV

    from rescu import io
    from rescu.config import load_config
    from rescu.scene.analyse import SceneParams

    work, cfg_path = finished_run
    res = work / "results"
    params = SceneParams.from_config(load_config(cfg_path)["scene"])
    n = 0
    for f in sorted((res / "synthetic" / "scene").glob("*.json")):
        src = io.read_result(f)
        vp = RV.image_vp(src, params, "track")
        if src.vanishing_point is None:
            assert vp is None, f.name
        else:
            n += 1
            np.testing.assert_allclose(vp.homogeneous, src.vanishing_point.homogeneous,
                                       atol=1e-8, err_msg=f.name)
    assert n > 0
    assert RV.main([str(res), "--datasets", "synthetic", "--weights", "one"]) == 0
    assert "synthetic" in capsys.readouterr().out


def test_completion_variant_of_the_configs_settings_is_the_runs_scene(finished_run, capsys):
    """benchmarks/studies/completion_variants.py with no override recomputes exactly the run's
    scene/ JSONs, prints both rows, and refuses its folder for other settings."""
    sys.path.insert(0, str(REPO / "benchmarks" / "studies"))
    import completion_variants as CV

    work, cfg_path = finished_run
    res = work / "results"
    out = work / "cv-config"
    base = [str(res), "--config", str(cfg_path), "--out", str(out)]
    assert CV.main(base + ["--workers", "2"]) == 0
    text = capsys.readouterr().out
    assert "3 images in" in text and "run " in text and "exact_rate" in text
    for f in sorted((res / "synthetic" / "scene").glob("*.json")):
        a, b = json.loads(f.read_text()), json.loads((out / f.name).read_text())
        assert a == b, f.name
    assert CV.main(base + ["--set", "end_instances=2"]) == 2
    assert "other settings" in capsys.readouterr().err


def test_variant_that_changes_only_prediction_reuses_the_run_features_and_head(
        finished_run, tmp_path):
    """A stage2_ablation variant that, merged into the run's stage2, changes prediction only
    (the default instance-scale sets the proposal method the run already has) is computed
    from the run's own features and head (rule stage2_predict_ablation, no backbone pass),
    and gives the instances the whole variant run (features, head, prediction) gives."""
    from rescu import pipeline
    from rescu.config import load_config
    from rescu.extension.params import as_predict_variant

    work, cfg = finished_run
    res = work / "results"
    conf = load_config(cfg)
    over = conf["stage2_ablation"]["variants"]["instance-scale"]
    assert as_predict_variant(conf["stage2"], over) == {"predict": over["predict"]}
    for other in ("edgeboxes", "both"):
        assert as_predict_variant(conf["stage2"], conf["stage2_ablation"]["variants"][other]) \
            is None
    proc = snakemake(work, cfg, "-n", "--forcerun", "stage2_predict_ablation")
    text = proc.stdout + proc.stderr
    assert re.search(r"rule stage2_predict_ablation:.*?output: [^\n]*stage2-ablation/"
                     r"instance-scale/", text, re.S), text[-3000:]
    blocks = [b for b in text.split("\nrule ") if b.startswith("stage2_ablation:")]
    assert not [b for b in blocks if "instance-scale" in b.split("log:")[0]], blocks[:1]
    # the same instances as the whole variant run, image by image
    pipeline.limit_threads(conf["threads"]["stage2_features"], torch=True)
    for s1 in sorted((res / "synthetic" / "rescu-i").glob("*.json")):
        stem, prep = s1.stem, res / "synthetic" / "prepared"
        out = tmp_path / f"{stem}.json"
        pipeline.stage2_ablation(str(prep / f"{stem}.png"), str(prep / f"{stem}.meta.json"),
                                 str(s1), {"instance-scale": str(out)}, conf["stage2"],
                                 {"instance-scale": over})
        a = json.loads((res / "synthetic" / "stage2-ablation" / "instance-scale"
                        / f"{stem}.json").read_text())
        b = json.loads(out.read_text())
        assert a["method"] == b["method"] == "rescu-ii[instance-scale]"
        boxes = [[np.round(i["bbox"], 3).tolist() for i in p["instances"]]
                 for p in a["patterns"]]
        assert boxes == [[np.round(i["bbox"], 3).tolist() for i in p["instances"]]
                         for p in b["patterns"]], stem


def test_a_local_run_switches_the_job_rate_limiter_off(tmp_path):
    """The Snakefile's onstart hook finds Snakemake's job rate limiter and switches it off
    for local runs (its 1-s re-scheduling timers pile up, one more per finished job, and kept
    Snakemake's own process busy on a core in make paper). Fails when a Snakemake release
    moves what the hook reaches for, instead of the hook quietly doing nothing."""
    cfg = tiny_config(tmp_path)
    proc = snakemake(tmp_path, cfg, "--verbose", "--", "results/data/synthetic/truth.json")
    text = proc.stdout + proc.stderr
    assert "rescu: job rate limiter off (local run)" in text, text[-2000:]
    # the workflow's own profile (scheduler-subsample) is read without being named
    assert re.search(r"Using workflow specific profile \S*profiles/default", text), text[:2000]
    assert re.search(r"Finished job|steps \(100%\) done", text), text[-2000:]


def test_predict_variant_of_an_upstream_key_is_refused(tmp_path):
    cfg = tiny_config(tmp_path, **{"stage2_ablation.predict_variants": {
        "x": {"examples": {"top_p": 5}}}})
    with pytest.raises(AssertionError,
                       match=r"predict_variants\.x: \['examples'\] are not the predict section"):
        snakemake(tmp_path, cfg, "-n")


def test_photo_only_dataset_runs_to_the_report(tmp_path):
    """A dataset of photos without annotations (the README's "or just photos") runs to the
    report: the tables that need ground truth say so instead of failing (before: the
    `ts_tables` job declared `figures/ts_sweep.png` and wrote none, MissingOutputException)."""
    from test_cli import shelf_photo

    photos = tmp_path / "mine"
    photos.mkdir()
    shelf_photo(photos / "a.png")
    shelf_photo(photos / "b.png")
    default = yaml.safe_load((REPO / "rescu" / "defaults" / "config.yaml").read_text())
    cfg = tmp_path / "config.yaml"
    cfg.write_text(yaml.safe_dump({
        "datasets": {**{n: {"enabled": False} for n in default["datasets"]},
                     "mine": {"path": str(photos)}},
        "run_datasets": ["mine"], "results_dir": str(tmp_path / "res"),
        "stage2": {"head": {"max_epochs": 2}, "proposals": {"max_proposals": 100}},
    }))
    snakemake(tmp_path, cfg)
    res = tmp_path / "res"
    assert len(list((res / "mine" / "final").glob("*.json"))) == 2
    assert (res / "report" / "index.html").is_file()
    for table in ("rp_discovery", "counting", "ts", "vpd"):
        assert "no ground truth" in (res / "tables" / f"{table}.md").read_text(), table


def test_run_step_hands_the_script_what_script_directive_would(tmp_path):
    """workflow/run_step.py runs an adapter with a ``snakemake`` object built from the
    job's JSON: named and positional inputs and outputs (a named list as a list), ``get``
    with a default, parameters, wildcards, threads and the log; nothing of Snakemake is
    imported in the job."""
    script = tmp_path / "adapter.py"
    script.write_text(
        "import json, sys\n"
        "s = snakemake\n"
        "out = {'png': s.input.png, 'first': s.input[0], 'many': s.input.many,\n"
        "       'missing': s.input.get('dense', 'none'), 'n_in': len(s.input),\n"
        "       'outs': list(s.output), 'json': s.output.json, 'p': s.params.stage,\n"
        "       'f': s.params.name, 'w': s.wildcards.image, 'threads': s.threads,\n"
        "       'log': s.log[0], 'snakemake_imported': 'snakemake' in sys.modules}\n"
        "open(s.output.json, 'w').write(json.dumps(out))\n")
    job = {"input": {"items": ["a.png", "m1", "m2"], "names": {"png": [0, None],
                                                           "many": [1, 3]}},
           "output": {"items": [str(tmp_path / "o.json")], "names": {"json": [0, None]}},
           "params": {"stage": {"k": [1, 2.5, None]}, "name": "x y"}, "threads": 2,
           "wildcards": {"dataset": "d", "image": "im"}}
    subprocess.run([sys.executable, str(REPO / "workflow" / "run_step.py"), str(script),
                    json.dumps(job), str(tmp_path / "log.txt")], check=True)
    got = json.loads((tmp_path / "o.json").read_text())
    assert got == {"png": "a.png", "first": "a.png", "many": ["m1", "m2"],
                   "missing": "none", "n_in": 3, "outs": [str(tmp_path / "o.json")],
                   "json": str(tmp_path / "o.json"), "p": {"k": [1, 2.5, None]},
                   "f": "x y", "w": "im", "threads": 2, "log": str(tmp_path / "log.txt"),
                   "snakemake_imported": False}
