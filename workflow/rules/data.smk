# Data: the synthetic benchmark and the package-shipped photos (generated once), and the
# per-image preparation (orientation, mode, downscale) every later step reads.


rule generate_synthetic:
    output:
        images=expand(
            f"{RESULTS}/{SYNTHETIC_DIR}/images/{{name}}",
            name=synthetic_image_names(
                config["synthetic"]["n_images"]
            ),
        ),
        annotations=f"{RESULTS}/{SYNTHETIC_DIR}/annotations.json",
        vps=f"{RESULTS}/{SYNTHETIC_DIR}/vanishing_points.json",
        truth=f"{RESULTS}/{SYNTHETIC_DIR}/truth.json",
    input:
        step_code("generate_synthetic"),
    params:
        synth=config["synthetic"],
    log:
        LOGS + "/data/generate_synthetic.log",
    benchmark:
        f"{RESULTS}/benchmarks/data/generate_synthetic.tsv"
    script:
        "../scripts/generate_synthetic.py"


rule export_photos:
    output:
        images=expand(
            f"{RESULTS}/{PHOTOS_DIR}/images/{{name}}", name=config["package_photos"]["names"]
        ),
    input:
        step_code("export_photos"),
    params:
        names=config["package_photos"]["names"],
    log:
        LOGS + "/data/export_photos.log",
    benchmark:
        f"{RESULTS}/benchmarks/data/export_photos.tsv"
    script:
        "../scripts/export_photos.py"


rule rectified_vp_truth:
    # VP ground truth of a dataset of rectified photos (`vp_truth: rectified`): derived
    input:
        annotations=lambda wildcards: f"{DATASETS[wildcards.dataset]['root']}/annotations.json",
        code=step_code("vp_truth"),
    output:
        f"{RESULTS}/{{dataset}}/vanishing_points.json",
    log:
        LOGS + "/data/vp_truth_{dataset}.log",
    script:
        "../scripts/vp_truth.py"


rule prepare:
    input:
        image=source_image,
        code=step_code("prepare"),
    output:
        png=f"{RESULTS}/{{dataset}}/prepared/{{image}}.png",
        meta=f"{RESULTS}/{{dataset}}/prepared/{{image}}.meta.json",
    params:
        **step_params(
            "prepare",
            image_name=lambda w: DATASETS[w.dataset]["names"][w.image],
            max_side=config["image"]["max_side"],
            min_side=config["image"]["min_side"],
            max_pixels=config["image"]["max_pixels"],
        ),
    priority: PRIORITY["prepare"]
    log:
        LOGS + "/{dataset}/prepare/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/prepare/{{image}}.tsv"
    shell:
        STEP_SHELL
