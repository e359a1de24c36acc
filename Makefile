# Two commands on a fresh machine with only Python (3.11+) installed:
#   make run    the main job: the pipeline on the default config (synthetic benchmark,
#               package photos, and ../shared/data when present) -> results/
#   (make paper: every table of the paper, ablations and full datasets -> results/paper/)
#   make test   the test suite
# Both create .venv and install the pinned dependencies when needed.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
CORES  ?= 2
# On your own machine, CPU-only torch wheels: make setup TORCH_INDEX=https://download.pytorch.org/whl/cpu
TORCH_INDEX ?=

.PHONY: setup run paper holdout realdev stress test report clean cluster-test

setup: $(STAMP)

$(STAMP): requirements.txt pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(if $(TORCH_INDEX),$(BIN)/python -m pip install --quiet torch==2.14.1 torchvision==0.29.1 --index-url $(TORCH_INDEX))
	$(BIN)/python -m pip install --quiet -r requirements.txt
	$(BIN)/python -m pip install --quiet --no-deps --no-build-isolation -e .
	# the VPD table's peer (optional; --no-deps: its wheel asks for opencv-contrib-python,
	# which would replace the pinned headless OpenCV)
	-$(BIN)/python -m pip install --quiet --no-deps lu-vp-detect==1.0.4
	touch $(STAMP)

# a quiet terminal: a progress line, warnings and failures, the report's path and a
# one-line summary (rescu_workflow/runlog.py; full output in results/logs/run.log);
# make run V=1: Snakemake's full output
V ?=
run: setup
	PATH="$(CURDIR)/$(BIN):$$PATH" $(BIN)/python -m rescu_workflow.runlog $(if $(V),--verbose) -- \
	  $(BIN)/snakemake --cores $(CORES)

# every table of the paper: the main methods and the ablations on every image of each
# dataset (config/paper.yaml) -> results/paper/
paper: setup
	PATH="$(CURDIR)/$(BIN):$$PATH" $(BIN)/snakemake --cores $(CORES) --configfile config/paper.yaml

# the synthetic benchmark again with another seed (config/holdout.yaml) -> results/holdout/;
# make holdout SEED=11 -> that seed, in results/holdout-11/
SEED ?=
holdout: setup
	PATH="$(CURDIR)/$(BIN):$$PATH" $(BIN)/snakemake --cores $(CORES) --configfile config/holdout.yaml \
	  $(if $(SEED),--config 'synthetic={seed: $(SEED)}' results_dir=results/holdout-$(SEED))

# every image of the real RP datasets in ../shared/data up to the RP discovery table
# (config/realdev.yaml) -> results/realdev/tables/rp_discovery.md
realdev: setup
	@for d in cmp_facade spb_facades aerial_cars chess; do test -f ../shared/data/$$d/annotations.json \
	  || { echo "realdev: ../shared/data/$$d/annotations.json not found (see ../shared/README.md)"; exit 2; }; done
	PATH="$(CURDIR)/$(BIN):$$PATH" $(BIN)/snakemake --cores $(CORES) --configfile config/realdev.yaml \
	  -- results/realdev/tables/rp_discovery.md

# stage II under heavy occlusion (config/stress.yaml) -> results/stress/tables/
# stage2_ablation.md (RESCU-I vs RESCU-II) and counting.md; make stress SEED=202 ->
# results/stress-202/
STRESS_DIR = results/stress$(if $(SEED),-$(SEED))
stress: setup
	PATH="$(CURDIR)/$(BIN):$$PATH" $(BIN)/snakemake --cores $(CORES) --configfile config/stress.yaml \
	  $(if $(SEED),--config 'synthetic={seed: $(SEED)}' results_dir=$(STRESS_DIR)) \
	  -- $(STRESS_DIR)/tables/stage2_ablation.md $(STRESS_DIR)/tables/counting.md

report: setup
	PATH="$(CURDIR)/$(BIN):$$PATH" $(BIN)/snakemake --cores $(CORES) --report results/snakemake-report.html

test: setup
	PATH="$(CURDIR)/$(BIN):$$PATH" $(BIN)/python -m pytest -q

# profiles/slurm on a real one-node SLURM cluster on this machine (tests/cluster/start_slurm.sh
# installs slurm-wlm + munge when root, and starts it), outputs compared with a local run
cluster-test: setup
	PATH="$(CURDIR)/$(BIN):$$PATH" RESCU_CLUSTER_TEST=1 $(BIN)/python -m pytest -q -rs -m slurm tests/test_slurm.py

clean:
	rm -rf results/* logs .snakemake
