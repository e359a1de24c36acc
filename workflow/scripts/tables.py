"""Snakemake adapter: the evaluation tables (rescu.evaluation.tables), one function per rule."""
from rescu.evaluation import tables as T
from rescu.sections import section_params
from rescu.evaluation.core import write_markdown, write_tsv
from rescu.pipeline import setup_logging

setup_logging(snakemake.log[0])
out, p = snakemake.output, snakemake.params
rule = snakemake.rule
if rule == "result_tables":
    captions, failures = T.result_rows(p.datasets)
    write_tsv(captions, out.captions)
    write_tsv(failures, out.failures)
    write_markdown(T.failures_markdown(failures), out.md)
elif rule == "summary":
    inp = snakemake.input  # the ablation tables only in `paper` runs
    parts = [("RP discovery", inp.rp), ("Stage-I ablation", inp.get("ablation")),
             ("Stage-II ablation", inp.get("stage2_ablation")), ("Counting", inp.counting),
             ("Vanishing points", inp.vpd), ("Translation symmetry", inp.ts),
             ("Failures", inp.failures)]
    parts = [(heading, path) for heading, path in parts if path]
    write_markdown(T.summary_markdown(parts, T.summary_header(p.backbone)), out.md)
else:
    refs = T.dataset_refs(p.datasets, list(p.datasets))
    ev = section_params("evaluation", p.evaluation)
    figures = p.get("figures")
    if rule == "rp_tables":
        T.rp_tables(refs, p.results, ev, out.tsv, out.md, out.scores, out.curves, figures,
                    dict(p.methods))
    elif rule == "ablation_tables":
        T.ablation_tables(refs, p.results, p.variants, ev, out.tsv, out.md)
    elif rule == "stage2_ablation_tables":
        T.stage2_ablation_tables(refs, p.results, p.variants, ev, out.tsv, out.md)
    elif rule == "counting_tables":
        T.counting_tables(refs, p.results, ev, out.tsv, out.md)
    elif rule == "vp_tables":
        T.vp_tables(refs, p.results, ev, out.tsv, out.md, out.errors, out.tests, figures,
                    dict(p.methods), out.aa, out.triplet)
    elif rule == "ts_tables":
        T.ts_tables(refs, p.results, ev, out.tsv, out.md, figures)
    else:
        raise ValueError(f"tables.py does not handle rule {rule!r}")
