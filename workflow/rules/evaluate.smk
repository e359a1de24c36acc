# Evaluation: the paper's tables (TSV + Markdown) and curves (PNG) over all datasets.
TABLES = f"{RESULTS}/tables"
FIGURES = f"{RESULTS}/figures"
EVAL_CODE = step_code("tables")


def dataset_params(names, vp=False):
    """Each dataset's root and image names (with ``vp``: its VP ground truth file too)."""
    out = {n: {"root": str(DATASETS[n]["root"]), "names": DATASETS[n]["names"]} for n in names}
    if vp:
        for n in names:
            out[n]["vp_truth"] = str(DATASETS[n]["vp_truth"])
    return out


def vp_methods():
    """VPD table rows: method name -> per-image folder (the no-AC variant with ``paper``;
    the peer ``lu-vp-detect`` where it is installed)."""
    from rescu.evaluation.tables import VP_METHODS
    from rescu.scene.vp.peers import LU_INSTALL, lu_available

    lu = lu_available()
    if not lu and vp_datasets():
        print(f"rescu: the VPD table has no lu-vp-detect row: {LU_INSTALL}", file=sys.stderr)
    return {k: v for k, v in VP_METHODS.items()
            if (PAPER or v != "scene-noac") and (lu or v != "vp-lu")}


VP_ROWS = vp_methods()


def ablation_tables():
    """The ablation tables (Markdown), which only ``paper`` runs make."""
    if not PAPER:
        return {}
    return {"ablation": f"{TABLES}/ablation.md",
            "stage2_ablation": f"{TABLES}/stage2_ablation.md"}


def gt_files(names, filename):
    return [f"{DATASETS[n]['root']}/{filename}" for n in names]


rule rp_tables:
    input:
        preds=per_image(
            f"{RESULTS}/{{dataset}}/{{method}}/{{image}}.json",
            rp_datasets(),
            method=list(rp_methods().values()),
        ),
        gt=gt_files(rp_datasets(), "annotations.json"),
        code=EVAL_CODE,
    output:
        tsv=f"{TABLES}/rp_discovery.tsv",
        md=f"{TABLES}/rp_discovery.md",
        scores=f"{TABLES}/rp_scores.tsv",
        curves=f"{TABLES}/rp_curves.tsv",
        figures=expand(f"{FIGURES}/rp_curves_{{ds}}.png", ds=rp_datasets()),
    params:
        results=RESULTS,
        figures=FIGURES,
        datasets=dataset_params(rp_datasets()),
        evaluation=config["evaluation"],
        methods=rp_methods(),
    log:
        LOGS + "/tables/rp_tables.log",
    script:
        "../scripts/tables.py"


rule ablation_tables:
    input:
        preds=per_image(
            f"{RESULTS}/{{dataset}}/ablation/{{variant}}/{{image}}.json",
            ablation_datasets(),
            variant=ablation_variants(),
        ),
        gt=gt_files(ablation_datasets(), "annotations.json"),
        code=EVAL_CODE,
    output:
        tsv=f"{TABLES}/ablation.tsv",
        md=f"{TABLES}/ablation.md",
    params:
        results=RESULTS,
        datasets=dataset_params(ablation_datasets()),
        evaluation=config["evaluation"],
        variants=ablation_variants(),
    log:
        LOGS + "/tables/ablation_tables.log",
    script:
        "../scripts/tables.py"


rule stage2_ablation_tables:
    input:
        preds=per_image(
            f"{RESULTS}/{{dataset}}/{{method}}/{{image}}.json",
            stage2_ablation_datasets(),
            method=["rescu-i", "rescu-ii"],
        ),
        ablation=per_image(
            f"{RESULTS}/{{dataset}}/stage2-ablation/{{variant}}/{{image}}.json",
            stage2_ablation_datasets(),
            variant=stage2_ablation_rows(),
        ),
        gt=gt_files(stage2_ablation_datasets(), "annotations.json"),
        code=EVAL_CODE,
    output:
        tsv=f"{TABLES}/stage2_ablation.tsv",
        md=f"{TABLES}/stage2_ablation.md",
    params:
        results=RESULTS,
        datasets=dataset_params(stage2_ablation_datasets()),
        evaluation=config["evaluation"],
        variants=stage2_ablation_rows(),
    log:
        LOGS + "/tables/stage2_ablation_tables.log",
    script:
        "../scripts/tables.py"


rule counting_tables:
    input:
        preds=per_image(
            f"{RESULTS}/{{dataset}}/{{method}}/{{image}}.json",
            rp_datasets(),
            method=["rescu-i", "final"],
        ),
        gt=gt_files(rp_datasets(), "annotations.json"),
        code=EVAL_CODE,
    output:
        tsv=f"{TABLES}/counting.tsv",
        md=f"{TABLES}/counting.md",
    params:
        results=RESULTS,
        datasets=dataset_params(rp_datasets()),
        evaluation=config["evaluation"],
    log:
        LOGS + "/tables/counting_tables.log",
    script:
        "../scripts/tables.py"


rule vp_tables:
    input:
        preds=per_image(
            f"{RESULTS}/{{dataset}}/{{method}}/{{image}}.json",
            vp_datasets(),
            method=list(VP_ROWS.values()),
        ),
        gt=[str(DATASETS[n]["vp_truth"]) for n in vp_datasets()],
        code=EVAL_CODE,
    output:
        tsv=f"{TABLES}/vpd.tsv",
        md=f"{TABLES}/vpd.md",
        errors=f"{TABLES}/vpd_errors.tsv",
        tests=f"{TABLES}/vpd_tests.tsv",
        aa=f"{TABLES}/vpd_aa.tsv",
        triplet=f"{TABLES}/vpd_triplet_errors.tsv",
        figures=expand(f"{FIGURES}/vpd_{{ds}}.png", ds=vp_datasets()),
    params:
        results=RESULTS,
        figures=FIGURES,
        datasets=dataset_params(vp_datasets(), vp=True),
        evaluation=config["evaluation"],
        methods=VP_ROWS,
    log:
        LOGS + "/tables/vp_tables.log",
    script:
        "../scripts/tables.py"


rule ts_tables:
    input:
        preds=per_image(f"{RESULTS}/{{dataset}}/final/{{image}}.json", rp_datasets()),
        gt=gt_files(rp_datasets(), "annotations.json"),
        code=EVAL_CODE,
    output:
        tsv=f"{TABLES}/ts.tsv",
        md=f"{TABLES}/ts.md",
        figure=f"{FIGURES}/ts_sweep.png",
    params:
        results=RESULTS,
        figures=FIGURES,
        datasets=dataset_params(rp_datasets()),
        evaluation=config["evaluation"],
    log:
        LOGS + "/tables/ts_tables.log",
    script:
        "../scripts/tables.py"


rule result_tables:
    input:
        preds=per_image(f"{RESULTS}/{{dataset}}/final/{{image}}.json"),
        code=EVAL_CODE,
    output:
        captions=f"{TABLES}/captions.tsv",
        failures=f"{TABLES}/failures.tsv",
        md=f"{TABLES}/failures.md",
    params:
        datasets={d: per_image(f"{RESULTS}/{{dataset}}/final/{{image}}.json", [d]) for d in DATASETS},
    log:
        LOGS + "/tables/result_tables.log",
    script:
        "../scripts/tables.py"


rule summary:
    input:
        rp=f"{TABLES}/rp_discovery.md",
        **ablation_tables(),
        counting=f"{TABLES}/counting.md",
        vpd=f"{TABLES}/vpd.md",
        ts=f"{TABLES}/ts.md",
        failures=f"{TABLES}/failures.md",
        code=EVAL_CODE,
    output:
        md=f"{TABLES}/summary.md",
    params:
        backbone=config["stage2"]["backbone"]["name"],
    log:
        LOGS + "/tables/summary.log",
    script:
        "../scripts/tables.py"
