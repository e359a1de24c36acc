# RESCU: recurrence-based 3D scene understanding from a single image.
# Table of contents: config + validation, one rule file per stage, the final targets.
import sys

from snakemake.utils import min_version, update_config

from rescu.config import DEFAULT_CONFIG, typed_cli_overrides, validate_config
from rescu.io import InputError

min_version("9.0")


# the defaults, once, inside the package (every key, documented in config/README.md);
# then the checkout's overrides; --configfile and --config go on top of both
configfile: str(DEFAULT_CONFIG)
configfile: os.path.join(workflow.basedir, "config", "config.yaml")


# --config values arrive as strings inside mappings/lists ({seed: 11} -> "11"): retype them;
# then every key of every section checked once, before any job (sizes and finite numbers,
# the package's schema, then the parameter classes): one line naming the key, its value
# and what is allowed, exit 2
try:
    update_config(config, typed_cli_overrides(workflow.config_settings.config))
    validate_config(config, ", ".join(map(str, workflow.configfiles)) or "config",
                    [("--config", workflow.config_settings.config)])
except InputError as e:
    print(f"rescu: error: {e}", file=sys.stderr)
    sys.exit(2)


include: "workflow/rules/common.smk"
include: "workflow/rules/data.smk"
include: "workflow/rules/features.smk"
include: "workflow/rules/discovery.smk"
include: "workflow/rules/extension.smk"
include: "workflow/rules/scene.smk"
include: "workflow/rules/caption.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/report.smk"


rule all:
    input:
        final_targets(),
    default_target: True


# Snakemake's job rate limiter (--max-jobs-per-timespan, 100 jobs per 1 s by default) ends
# every scheduling round by starting a timer that starts another round one timespan later,
# and each finished job starts a round of its own: one more perpetual 1-s timer per finished
# job. After a few hundred jobs Snakemake's own process re-schedules hundreds of times a
# second and takes most of a core from the jobs (make paper: 4974 jobs). A run on this
# machine submits nothing anywhere, so it has nothing to limit: the limiter is switched off
# before the first round (jobs still start as soon as a job ends or a core is free).
# Cluster runs (--profile profiles/slurm) keep it; `--no-hooks` skips this.
onstart:
    _scheduler = getattr(workflow, "scheduler", None)
    if workflow.local_exec and getattr(_scheduler, "job_rate_limiter", None) is not None:
        _scheduler.job_rate_limiter = None
        from snakemake.logging import logger as _logger

        _logger.debug("rescu: job rate limiter off (local run)")
