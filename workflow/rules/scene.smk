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
        scene=scene_params(),
    log:
        LOGS + "/{dataset}/scene/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/scene/{{image}}.tsv"
    script:
        "../scripts/scene.py"


rule scene_no_ac:
    input:
        **prepared(),
        result=scene_source,
        code=step_code("scene"),
    output:
        json=f"{RESULTS}/{{dataset}}/scene-noac/{{image}}.json",
        rectified=temp(directory(f"{RESULTS}/{{dataset}}/rectified-noac/{{image}}")),
    params:
        scene=scene_params(ac_threshold_deg=0.0),
    log:
        LOGS + "/{dataset}/scene_no_ac/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/scene_no_ac/{{image}}.tsv"
    script:
        "../scripts/scene.py"


rule line_vp:
    input:
        **prepared(),
        code=step_code("line_vp"),
    output:
        json=f"{RESULTS}/{{dataset}}/vp-lsd/{{image}}.json",
    params:
        scene={"vp": config["scene"]["vp"]},  # the baseline needs only the VP parameters
    log:
        LOGS + "/{dataset}/line_vp/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/line_vp/{{image}}.tsv"
    script:
        "../scripts/line_vp.py"
