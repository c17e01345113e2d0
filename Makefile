# `make demo` and `make test` set up everything themselves on a bare machine (Python 3.11).
VENV   ?= .venv
JOBS   ?= 2
CONFIG ?= config/config.yaml
BIN    := $(abspath $(VENV))/bin
export PATH := $(BIN):$(PATH)

STAMP := $(VENV)/.installed
# Blender as a module (render.backend: cycles) needs numpy<2: its own venv. The render jobs find
# it at .venv-blender/bin/python, or wherever PSD_BLENDER_PYTHON points.
BLENDER_VENV  ?= .venv-blender
BLENDER_STAMP := $(BLENDER_VENV)/.installed

.PHONY: demo test test-fast lint report clean blender

$(BIN)/python:
	python3 -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/pip install --quiet -e ".[train,slurm,test]"
	touch $@

$(BLENDER_STAMP):
	python3 -m venv $(BLENDER_VENV)
	$(BLENDER_VENV)/bin/pip install --quiet --upgrade pip
	$(BLENDER_VENV)/bin/pip install --quiet "bpy==4.5.15" "numpy<2"
	$(BLENDER_VENV)/bin/python -c "import bpy; print('Blender', bpy.app.version_string)"
	touch $@

blender: $(BLENDER_STAMP)  ## the Blender environment of the cycles render backend

demo: $(STAMP) $(BLENDER_STAMP)  ## the default config with snakemake -j2 (Blender for the report's backend comparison)
	$(BIN)/snakemake -j$(JOBS) --configfile $(CONFIG)

test: $(STAMP) $(BLENDER_STAMP)  ## the whole test suite, system-level and Cycles tests included
	PSD_REQUIRE_BLENDER=1 $(BIN)/python -m pytest

test-fast: $(STAMP)  ## unit tests only
	$(BIN)/python -m pytest -m "not slow and not workflow"

lint: $(STAMP)  ## ruff (pyproject.toml's rule set), snakefmt --check on the workflow, snakemake --lint
	$(BIN)/ruff check src tests bench
	$(BIN)/snakefmt --check Snakefile rules
	$(BIN)/snakemake --lint

report: $(STAMP)
	$(BIN)/snakemake --configfile $(CONFIG) --report report.html

clean:
	rm -rf results .snakemake
