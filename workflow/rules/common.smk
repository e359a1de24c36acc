# What every rule file needs: the image table built once from the config, wildcard
# constraints, the library files each rule depends on, and the final targets.
import sys
from pathlib import Path

from rescu.data.datasets import PHOTOS_DIR, SYNTHETIC_DIR, build_image_table
from rescu.extension.params import PREDICT_SECTION
from rescu.data.synth import synthetic_image_names

RESULTS = config["results_dir"]
PAPER = bool(config.get("paper", False))  # also the ablations and their tables (make paper)
LOGS = f"{RESULTS}/logs"  # per-step logs live with the results they belong to
BASEDIR = Path(workflow.basedir)

wildcard_constraints:
    dataset=r"[A-Za-z0-9_\-]+",
    image=r"[^/]+",
    method=r"grasp|rescu-i|rescu-ii",


# dataset name -> {"root": folder with images/ (+ ground truth), "images": {stem: path},
#                  "kind": ..., "has_rps": bool, "has_vps": bool}
DATASETS = build_image_table(config, results_dir=RESULTS, log=lambda m: print(m, file=sys.stderr))


def code(*modules):
    """The rescu/ source files a rule depends on (a code change reruns the rule).

    Each module is a path under rescu/ without ``.py`` ("scene/symmetry"); a package
    ("scene/vp") stands for all its ``.py`` files."""
    base = ["types", "io", "params", "pipeline"]
    out = []
    for m in dict.fromkeys(base + list(modules)):
        path = BASEDIR / "rescu" / m
        out += sorted(map(str, path.glob("*.py"))) if path.is_dir() else [f"{path}.py"]
    return out


def stage2_upstream():
    """The ``stage2`` sections of the features and training steps: all but ``predict``
    (:data:`rescu.extension.params.PREDICT_SECTION`, the keys that act only in prediction),
    so that a change of a prediction gate reruns prediction only."""
    return {k: v for k, v in config["stage2"].items() if k != PREDICT_SECTION}


def stage2_predict_variants():
    """``stage2_ablation.predict_variants`` (the ``predict`` section only, names other than those
    of ``stage2_ablation.variants``: checked once with the whole config by
    :func:`rescu.config.validate_config` in the Snakefile)."""
    return config["stage2_ablation"].get("predict_variants") or {}


def images(dataset):
    return sorted(DATASETS[dataset]["images"])


def source_image(wildcards):
    return DATASETS[wildcards.dataset]["images"][wildcards.image]


def per_image(pattern, datasets=None, **more):
    """Expand ``pattern`` (with {dataset}, {image} and the wildcards named in ``more``)
    over the chosen datasets' images."""
    out = []
    for ds in datasets if datasets is not None else DATASETS:
        out += expand(pattern, dataset=ds, image=images(ds), **more)
    return out


def rp_datasets():
    return [d for d, v in DATASETS.items() if v["has_rps"]]


def vp_datasets():
    return [d for d, v in DATASETS.items() if v["has_vps"]]


def ablation_datasets():
    return [d for d in config["ablation"]["datasets"] if d in DATASETS and DATASETS[d]["has_rps"]]


def stage2_ablation_datasets():
    return [d for d in config["stage2_ablation"]["datasets"]
            if d in DATASETS and DATASETS[d]["has_rps"]]


def prepared(wildcards=None):
    return {
        "png": f"{RESULTS}/{{dataset}}/prepared/{{image}}.png",
        "meta": f"{RESULTS}/{{dataset}}/prepared/{{image}}.meta.json",
    }


def final_targets():
    t = per_image(f"{RESULTS}/{{dataset}}/final/{{image}}.json")
    t += per_image(f"{RESULTS}/{{dataset}}/overlay/{{image}}.png")
    t += [f"{RESULTS}/tables/summary.md", f"{RESULTS}/report/index.html"]
    t += per_image(f"{RESULTS}/{{dataset}}/vp-lsd/{{image}}.json", vp_datasets())
    return t
