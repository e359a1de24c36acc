# Captions (base + enhanced) into the final per-image JSON, and the overlay picture.


rule caption:
    input:
        **prepared(),
        result=f"{RESULTS}/{{dataset}}/scene-joint/{{image}}.json",
        code=step_code("caption"),
    output:
        json=f"{RESULTS}/{{dataset}}/final/{{image}}.json",
    params:
        **step_params(
            "caption",
            caption=config["caption"],
            claims=config["scene"]["claims"],
        ),
    log:
        LOGS + "/{dataset}/caption/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/caption/{{image}}.tsv"
    shell:
        STEP_SHELL


rule overlay:
    input:
        **prepared(),
        result=f"{RESULTS}/{{dataset}}/final/{{image}}.json",
        code=step_code("overlay"),
    output:
        png=f"{RESULTS}/{{dataset}}/overlay/{{image}}.png",
    params:
        **step_params(
            "overlay",
            mode=config["report"]["overlay"],
        ),
    log:
        LOGS + "/{dataset}/overlay/{image}.log",
    shell:
        STEP_SHELL
