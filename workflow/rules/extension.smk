# Stage II: proposals + pooled frozen-backbone features (HDF5) and the per-image head
# (checkpoint) in one job, then the RESCU-II instances (JSON).


rule stage2_features:
    # proposals and pooled backbone features, then the per-image head trained on them, in
    # one job: both read the same stage2_upstream() parameters (a change of either reruns
    # both anyway), and one process imports torch once instead of twice (about 1.5 s of a
    # job's start per image)
    input:
        **prepared(),
        stage1=f"{RESULTS}/{{dataset}}/rescu-i/{{image}}.json",
        code=step_code("stage2_features"),
    output:
        h5=f"{RESULTS}/{{dataset}}/stage2/{{image}}.feats.h5",
        ckpt=f"{RESULTS}/{{dataset}}/stage2/{{image}}.head.h5",
    params:
        **step_params(
            "stage2_features",
            stage2=stage2_upstream(),
            threads=config["threads"]["stage2_features"],
            head_threads=config["threads"]["stage2_head"],
        ),
    threads: max(config["threads"]["stage2_features"], config["threads"]["stage2_head"])
    resources:
        mem_mb=4000,
    priority: PRIORITY["stage2_features"]
    log:
        LOGS + "/{dataset}/stage2_features/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/stage2_features/{{image}}.tsv"
    shell:
        STEP_SHELL


rule stage2_predict:
    input:
        unpack(dense_map_input),
        feats=f"{RESULTS}/{{dataset}}/stage2/{{image}}.feats.h5",
        ckpt=f"{RESULTS}/{{dataset}}/stage2/{{image}}.head.h5",
        stage1=f"{RESULTS}/{{dataset}}/rescu-i/{{image}}.json",
        meta=f"{RESULTS}/{{dataset}}/prepared/{{image}}.meta.json",
        code=step_code("stage2_predict"),
    output:
        json=f"{RESULTS}/{{dataset}}/rescu-ii/{{image}}.json",
    params:
        **step_params(
            "stage2_predict",
            stage2=config["stage2"],
            dense=config["dense"] if DENSE else None,
            threads=config["threads"]["stage2_head"],
        ),
    threads: config["threads"]["stage2_head"]
    log:
        LOGS + "/{dataset}/stage2_predict/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/stage2_predict/{{image}}.tsv"
    shell:
        STEP_SHELL


# prediction-only variants (stage2_ablation.predict_variants, and the variants that change
# nothing but prediction): no rule when there are none
if stage2_predict_variants():

    rule stage2_predict_ablation:
        input:
            unpack(dense_map_input),
            feats=f"{RESULTS}/{{dataset}}/stage2/{{image}}.feats.h5",
            ckpt=f"{RESULTS}/{{dataset}}/stage2/{{image}}.head.h5",
            stage1=f"{RESULTS}/{{dataset}}/rescu-i/{{image}}.json",
            meta=f"{RESULTS}/{{dataset}}/prepared/{{image}}.meta.json",
            code=step_code("stage2_predict_ablation"),
        output:
            expand(
                f"{RESULTS}/{{{{dataset}}}}/stage2-ablation/{{variant}}/{{{{image}}}}.json",
                variant=stage2_predict_variants(),
            ),
        params:
            **step_params(
                "stage2_predict_ablation",
                stage2=config["stage2"],
                dense=config["dense"] if DENSE else None,
                variants=stage2_predict_variants(),
                threads=config["threads"]["stage2_head"],
            ),
        threads: config["threads"]["stage2_head"]
        log:
            LOGS + "/{dataset}/stage2_predict_ablation/{image}.log",
        benchmark:
            f"{RESULTS}/benchmarks/{{dataset}}/stage2_predict_ablation/{{image}}.tsv"
        shell:
            STEP_SHELL


# variants with features and a head of their own; those that change only prediction go to
# stage2_predict_ablation above (common.smk: _stage2_ablation_split)
if stage2_ablation_variants():

    rule stage2_ablation:
        input:
            unpack(dense_map_input),
            **prepared(),
            stage1=f"{RESULTS}/{{dataset}}/rescu-i/{{image}}.json",
            code=step_code("stage2_ablation"),
        output:
            expand(
                f"{RESULTS}/{{{{dataset}}}}/stage2-ablation/{{variant}}/{{{{image}}}}.json",
                variant=stage2_ablation_variants(),
            ),
        params:
            **step_params(
                "stage2_ablation",
                stage2=config["stage2"],
                dense=config["dense"] if DENSE else None,
                variants=stage2_ablation_variants(),
                threads=config["threads"]["stage2_features"],
            ),
        threads: config["threads"]["stage2_features"]
        resources:
            mem_mb=4000,
        priority: PRIORITY["stage2_ablation"]
        log:
            LOGS + "/{dataset}/stage2_ablation/{image}.log",
        benchmark:
            f"{RESULTS}/benchmarks/{{dataset}}/stage2_ablation/{{image}}.tsv"
        shell:
            STEP_SHELL
