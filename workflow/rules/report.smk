# The HTML report: per dataset the headline figures beside overlay pictures, then each
# evaluation as a compact table next to its curve, the ablations and diagnostics.


def report_samples():
    """Every image: the report picks the photos of its first screen from all of them and
    shows each in its pictures section."""
    return {d: images(d) for d in DATASETS}


def sample_files(pattern):
    return [pattern.format(dataset=d, image=i) for d, imgs in report_samples().items() for i in imgs]


rule report:
    input:
        tables=rules.rp_tables.output
        + (rules.ablation_tables.output + rules.stage2_ablation_tables.output if PAPER else [])
        + rules.counting_tables.output
        + rules.vp_tables.output
        + rules.ts_tables.output
        + rules.result_tables.output,
        overlays=sample_files(f"{RESULTS}/{{dataset}}/overlay/{{image}}.png"),
        finals=sample_files(f"{RESULTS}/{{dataset}}/final/{{image}}.json"),
        rectified=sample_files(f"{RESULTS}/{{dataset}}/rectified/{{image}}"),
        summary=f"{TABLES}/summary.md",
        code=step_code("report"),
    output:
        html=report(
            f"{RESULTS}/report/index.html",
            caption="../report/report.rst",
            category="RESCU report",
        ),
    params:
        samples=report_samples(),
        skipped=SKIPPED,
        results=RESULTS,
        evaluation=config["evaluation"],
        report=config["report"],
    log:
        LOGS + "/report.log",
    script:
        "../scripts/report.py"


# On a cluster (profiles/slurm) the tables and the report run on the submitting host.
localrules: rp_tables, ablation_tables, stage2_ablation_tables, counting_tables, vp_tables, ts_tables, result_tables, summary, report
