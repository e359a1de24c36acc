# Stage I: RESCU-I (URP search, adaptive parameters), the GRASP baseline, and the
# ablation of the adaptive parameters and orientation modes (all variants in one job per image, reusing
# features and affinities).


rule dense:
    # the second RP source (rescu.extension.dense): recurring blobs in the frozen CNN's
    # feature map; when dense.enabled (for RESCU-I) or ablation.sources (paper runs)
    input:
        meta=f"{RESULTS}/{{dataset}}/prepared/{{image}}.meta.json",
        png=f"{RESULTS}/{{dataset}}/prepared/{{image}}.png",
        code=step_code("dense"),
    output:
        json=f"{RESULTS}/{{dataset}}/dense/{{image}}.json",
        # its coarse feature map (half precision), so that scoring in rescu_i needs no pass
        map=f"{RESULTS}/{{dataset}}/dense/{{image}}.map.h5",
    params:
        **step_params(
            "dense",
            dense=DENSE_STEP,
            threads=config["threads"]["stage2_features"],
        ),
    threads: config["threads"]["stage2_features"]
    priority: PRIORITY["dense"]  # an image's longest job: first (common.smk)
    log:
        LOGS + "/{dataset}/dense/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/dense/{{image}}.tsv"
    shell:
        STEP_SHELL


rule rescu_i:
    input:
        unpack(dense_input),
        features=f"{RESULTS}/{{dataset}}/features/{{image}}.h5",
        meta=f"{RESULTS}/{{dataset}}/prepared/{{image}}.meta.json",
        png=f"{RESULTS}/{{dataset}}/prepared/{{image}}.png",
        code=step_code("stage1"),
    output:
        json=f"{RESULTS}/{{dataset}}/rescu-i/{{image}}.json",
        h5=f"{RESULTS}/{{dataset}}/rescu-i/{{image}}.rp.h5",
    params:
        **step_params(
            "stage1",
            stage1=config["stage1"],
            dense=config["dense"] if DENSE else None,
        ),
    priority: PRIORITY["rescu_i"]
    log:
        LOGS + "/{dataset}/rescu-i/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/rescu-i/{{image}}.tsv"
    shell:
        STEP_SHELL


rule grasp:
    input:
        features=f"{RESULTS}/{{dataset}}/features/{{image}}.h5",
        meta=f"{RESULTS}/{{dataset}}/prepared/{{image}}.meta.json",
        code=step_code("grasp"),
    output:
        json=f"{RESULTS}/{{dataset}}/grasp/{{image}}.json",
        h5=f"{RESULTS}/{{dataset}}/grasp/{{image}}.rp.h5",
    params:
        **step_params(
            "grasp",
            grasp=config["grasp"],
        ),
    log:
        LOGS + "/{dataset}/grasp/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/grasp/{{image}}.tsv"
    shell:
        STEP_SHELL


rule ablation:
    input:
        unpack(ablation_dense_input),
        features=f"{RESULTS}/{{dataset}}/features/{{image}}.h5",
        meta=f"{RESULTS}/{{dataset}}/prepared/{{image}}.meta.json",
        png=f"{RESULTS}/{{dataset}}/prepared/{{image}}.png",
        code=step_code("ablation"),
    output:
        expand(
            f"{RESULTS}/{{{{dataset}}}}/ablation/{{variant}}/{{{{image}}}}.json",
            variant=ablation_variants(),
        ),
    params:
        **step_params(
            "ablation",
            stage1=config["stage1"],
            variants=config["ablation"]["variants"],
            rows=ablation_variants(),
            dense=DENSE_STEP if ABLATION_SOURCES else None,
        ),
    priority: PRIORITY["ablation"]
    log:
        LOGS + "/{dataset}/ablation/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/ablation/{{image}}.tsv"
    shell:
        STEP_SHELL
