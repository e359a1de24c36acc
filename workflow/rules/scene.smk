# Scene understanding from the RPs: vanishing points, 3D translation symmetry, counts and
# rectified views; the explicit-line baseline and the no-angular-constraint variant for
# the VP evaluation.


def scene_params(**vp_overrides):
    """The scene section, with ``vp`` entries overridden (the no-AC variant)."""
    return {**config["scene"], "vp": {**config["scene"]["vp"], **vp_overrides}}


def scene_source(wildcards):
    return f"{RESULTS}/{wildcards.dataset}/{config['scene']['source']}/{wildcards.image}.json"


rule scene:
    input:
        **prepared(),
        result=scene_source,
        code=step_code("scene"),
    output:
        json=f"{RESULTS}/{{dataset}}/scene/{{image}}.json",
        rectified=directory(f"{RESULTS}/{{dataset}}/rectified/{{image}}"),
    params:
        **step_params(
            "scene",
            scene=scene_params(),
        ),
    log:
        LOGS + "/{dataset}/scene/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/scene/{{image}}.tsv"
    shell:
        STEP_SHELL


rule scene_no_ac:
    input:
        **prepared(),
        result=scene_source,
        code=step_code("scene"),
    output:
        json=f"{RESULTS}/{{dataset}}/scene-noac/{{image}}.json",
        rectified=temp(directory(f"{RESULTS}/{{dataset}}/rectified-noac/{{image}}")),
    params:
        **step_params(
            "scene",
            scene=scene_params(ac_threshold_deg=0.0),
        ),
    log:
        LOGS + "/{dataset}/scene_no_ac/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/scene_no_ac/{{image}}.tsv"
    shell:
        STEP_SHELL


rule line_vp:
    input:
        **prepared(),
        code=step_code("line_vp"),
    output:
        json=f"{RESULTS}/{{dataset}}/vp-lsd/{{image}}.json",
    params:
        **step_params(
            "line_vp",
            scene={"vp": config["scene"]["vp"]},  # the baseline needs only the VP parameters
        ),
    log:
        LOGS + "/{dataset}/line_vp/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/line_vp/{{image}}.tsv"
    shell:
        STEP_SHELL


def vp_ground_truth(wildcards):
    return str(DATASETS[wildcards.dataset]["vp_truth"])


rule image_vp:
    # the image's VPs: RP rows and LSD lines in one estimator (the final JSON's VP)
    input:
        **prepared(),
        result=f"{RESULTS}/{{dataset}}/scene/{{image}}.json",
        code=step_code("image_vp"),
    output:
        json=f"{RESULTS}/{{dataset}}/scene-joint/{{image}}.json",
    params:
        **step_params(
            "image_vp",
            scene=config["scene"],
        ),
    log:
        LOGS + "/{dataset}/image_vp/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/image_vp/{{image}}.tsv"
    shell:
        STEP_SHELL


rule image_vp_true_focal:
    # the same with the dataset's true focal length (a row of the VPD table)
    input:
        **prepared(),
        result=f"{RESULTS}/{{dataset}}/scene/{{image}}.json",
        gt=vp_ground_truth,
        code=step_code("image_vp"),
    output:
        json=f"{RESULTS}/{{dataset}}/scene-joint-f/{{image}}.json",
    params:
        **step_params(
            "image_vp",
            scene=config["scene"],
        ),
    log:
        LOGS + "/{dataset}/image_vp_true_focal/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/image_vp_true_focal/{{image}}.tsv"
    shell:
        STEP_SHELL


rule peer_vp:
    # lu-vp-detect (Lu et al. 2017) with the dataset's true focal length: a peer's row
    input:
        **prepared(),
        gt=vp_ground_truth,
        code=step_code("peer_vp"),
    output:
        json=f"{RESULTS}/{{dataset}}/vp-lu/{{image}}.json",
    params:
        **step_params(
            "peer_vp",
            peer=config["scene"]["peer_vp"],
        ),
    log:
        LOGS + "/{dataset}/peer_vp/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/peer_vp/{{image}}.tsv"
    shell:
        STEP_SHELL
