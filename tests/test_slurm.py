"""profiles/slurm on a real SLURM cluster: a one-node cluster on this machine
(tests/cluster/start_slurm.sh: Debian slurm-wlm + munge, no accounting) runs two synthetic
images up to their final JSONs (and one table, a local rule) through the profile, each
image's steps as one group job; the same targets run locally (--cores 2) must give
byte-identical JSONs. Without a cluster, the profile's `groups` are checked against the
rules: every per-image rule, and nothing else, is in the group `image`.

About 3 minutes on 2 cores (local ~25 s, SLURM ~125 s: each submission starts snakemake
again on the node, and the status checks wait between rounds), too long for ``make test``: it runs only with RESCU_CLUSTER_TEST=1,
which ``make cluster-test`` sets. Then tests/cluster/start_slurm.sh installs slurm-wlm and
munge when missing (root, apt-get) and starts the cluster, or reuses the one it started
before; the test skips, saying why, where that cannot be done (not root, no apt-get,
daemons fail, a node too small for the profile's resources)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from test_workflow import tiny_config

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
SNAKEMAKE = BIN / "snakemake"
START = REPO / "tests" / "cluster" / "start_slurm.sh"
PREFIX = "rescutest"  # SLURM job names: <PREFIX>_<run uuid>


def _script(*args: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(START), *args], capture_output=True, text=True,
                          timeout=900, env={**os.environ, **env})


def _reason(proc: subprocess.CompletedProcess) -> str:
    lines = (proc.stderr or proc.stdout).strip().splitlines()
    return lines[-1] if lines else f"exit {proc.returncode}"


@pytest.fixture(scope="module")
def slurm_env():
    """The environment of a snakemake that submits to the cluster (SLURM_CONF, .venv/bin
    first on PATH: sbatch --export=ALL gives it to the jobs); the cluster is stopped
    afterwards when this fixture started it."""
    if os.environ.get("RESCU_CLUSTER_TEST") != "1":
        pytest.skip("a real SLURM cluster, ~3 min: make cluster-test runs it")
    if shutil.which("bash") is None:
        pytest.skip("no bash")
    running = _script("status").returncode == 0
    proc = _script("start")
    if proc.returncode != 0:
        pytest.skip(f"no SLURM cluster here: {_reason(proc)}")
    conf = re.search(r"export SLURM_CONF=(\S+)", proc.stdout).group(1)
    env = {**os.environ, "SLURM_CONF": conf, "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}"}
    node = subprocess.run(["sinfo", "-h", "-N", "-o", "%c %m"], capture_output=True,
                          text=True, env=env).stdout.split()
    profile = _profile()
    res = [profile["default-resources"], *profile["set-resources"].values()]
    # a group job asks for at most `cores` CPUs, and memory summed over at most that
    # many jobs side by side
    cpus = max([profile.get("cores", 1), *(r.get("cpus_per_task", 1) for r in res)])
    mem = cpus * max(r.get("mem_mb", 0) for r in res)
    if int(node[0]) < cpus or int(node[1]) < mem:
        pytest.skip(f"the SLURM node has {node[0]} CPUs and {node[1]} MB; profiles/slurm "
                    f"asks for up to {cpus} CPUs and {mem} MB")
    yield env
    _cancel_own_jobs(env)
    if not running:
        _script("stop")


def _profile() -> dict:
    return yaml.safe_load((REPO / "profiles" / "slurm" / "config.yaml").read_text())


def _grouped() -> dict[str, str]:
    """``{rule: group}`` of the profile's ``groups`` list."""
    return dict(g.split("=", 1) for g in _profile().get("groups", []))


def _rules_with_image_wildcard() -> tuple[set[str], set[str]]:
    """``(per_image, other)``: the workflow's rules whose outputs carry the ``{image}``
    wildcard, and the rest (read from the rule files, outputs up to the next section)."""
    per_image, other = set(), set()
    for smk in [REPO / "Snakefile", *sorted((REPO / "workflow" / "rules").glob("*.smk"))]:
        for m in re.finditer(r"^ *rule (\w+):\n(.*?)(?=^ *rule \w+:|\Z)", smk.read_text(),
                             re.M | re.S):
            out = re.search(r"^\s*output:\n(.*?)(?=^\s*\w+:\s*$|^\s*\w+:\s*\S)",
                            m.group(2), re.M | re.S)
            text = out.group(1) if out else ""
            (per_image if "{image}" in text.replace("{{", "{").replace("}}", "}")
             else other).add(m.group(1))
    return per_image, other


def test_profile_groups_every_per_image_rule():
    per_image, other = _rules_with_image_wildcard()
    assert {"prepare", "dense", "stage2_features", "caption"} <= per_image  # the parse works
    assert {"generate_synthetic", "rp_tables", "report"} <= other
    grouped = _grouped()
    assert set(grouped.values()) == {"image"}
    assert set(grouped) == per_image, (sorted(per_image - set(grouped)),
                                       sorted(set(grouped) - per_image))


def _cancel_own_jobs(env: dict) -> None:
    out = subprocess.run(["squeue", "-h", "-o", "%i %j"], capture_output=True, text=True,
                         env=env).stdout
    ids = [i for i, name in (line.split(None, 1) for line in out.splitlines())
           if name.startswith(PREFIX + "_")]
    if ids:
        subprocess.run(["scancel", *ids], env=env)


def _run(cmd: list[str], cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=1200, env=env)
    if proc.returncode != 0:
        logs = sorted((cwd / ".snakemake" / "slurm_logs").rglob("*.log"))
        tails = "".join(f"\n--- {p}\n{p.read_text()[-1500:]}" for p in logs[-3:])
        raise AssertionError(f"{cmd[0]} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n"
                             f"{proc.stderr[-6000:]}{tails}")
    return proc


def _jsons(results: Path) -> dict[str, bytes]:
    """Every per-image JSON of the synthetic set (steps' outputs, final included)."""
    base = results / "synthetic"
    return {str(p.relative_to(base)): p.read_bytes() for p in sorted(base.rglob("*.json"))}


@pytest.mark.slurm
@pytest.mark.slow
def test_profile_on_slurm_equals_local_run(slurm_env, tmp_path):
    cfg = tiny_config(tmp_path, **{"synthetic.n_images": 2})
    targets = [f"results/synthetic/final/synth_{i:04d}.json" for i in range(2)]
    targets.append("results/tables/captions.tsv")  # result_tables: a local rule
    common = [str(SNAKEMAKE), "-s", str(REPO / "Snakefile"), "--configfile", str(cfg)]
    local, cluster = tmp_path / "local", tmp_path / "slurm"
    local.mkdir(), cluster.mkdir()

    t0 = time.monotonic()
    _run([*common, "--directory", str(local), "--cores", "2", *targets], local,
         env={**os.environ, "PATH": slurm_env["PATH"]})
    t1 = time.monotonic()
    proc = _run([*common, "--directory", str(cluster), "--profile", str(REPO / "profiles/slurm"),
                 "--slurm-jobname-prefix", PREFIX, "--slurm-init-seconds-before-status-checks",
                 "2", "--latency-wait", "5", *targets], cluster, env=slurm_env)
    t2 = time.monotonic()
    print(f"local {t1 - t0:.0f} s, slurm {t2 - t1:.0f} s")

    text = proc.stdout + proc.stderr
    submitted = re.findall(r"has been submitted with SLURM jobid (\d+)", text)
    stats = text[text.index("Job stats:"):].split("total", 1)[0]
    counts = {r: int(n) for r, n in re.findall(r"^(\w+)\s+(\d+)\s*$", stats, re.M)}
    assert submitted and counts, text[-3000:]
    local_jobs = re.findall(r"^localrule (\w+):", text, re.M)
    assert "result_tables" in local_jobs, text[-3000:]
    groups = re.findall(r"^\S.*Group job image\b", text, re.M)
    assert len(groups) == 2, text[-3000:]  # one submission per image
    # every other job of the plan but its local rules (localrules: the tables) went
    # through sbatch on its own: counted from the run's own output, not a constant
    grouped = _grouped()
    alone = sum(n for r, n in counts.items() if r not in grouped) - len(local_jobs)
    assert len(set(submitted)) == len(groups) + alone, (submitted, counts, local_jobs)
    assert "Falling back to 'sacct'" not in text  # job states came from squeue

    a, b = _jsons(local / "results"), _jsons(cluster / "results")
    assert sorted(a) == sorted(b)
    assert {f"final/synth_{i:04d}.json" for i in range(2)} <= set(a)
    differ = [k for k in a if a[k] != b[k]]
    assert not differ, f"SLURM and local JSONs differ: {differ}"
    assert (local / "results/tables/captions.tsv").read_bytes() == \
        (cluster / "results/tables/captions.tsv").read_bytes()
