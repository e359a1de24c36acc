# SIFT features of every prepared image, to HDF5.


rule features:
    input:
        **prepared(),
        code=step_code("features"),
    output:
        h5=f"{RESULTS}/{{dataset}}/features/{{image}}.h5",
    params:
        **step_params(
            "features",
            features=config["features"],
        ),
    priority: PRIORITY["features"]
    log:
        LOGS + "/{dataset}/features/{image}.log",
    benchmark:
        f"{RESULTS}/benchmarks/{{dataset}}/features/{{image}}.tsv"
    shell:
        STEP_SHELL
