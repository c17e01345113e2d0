# `make demo` and `make test` set up everything themselves on a bare machine (Python 3.11).
VENV   ?= .venv
JOBS   ?= 2
CONFIG ?= config/config.yaml
BIN    := $(abspath $(VENV))/bin
export PATH := $(BIN):$(PATH)

STAMP := $(VENV)/.installed

.PHONY: demo test test-fast lint report clean

$(BIN)/python:
	python3 -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/pip install --quiet -e ".[train,slurm,test]"
	touch $@

demo: $(STAMP)  ## build the default dataset with snakemake -j2
	$(BIN)/snakemake -j$(JOBS) --configfile $(CONFIG)

test: $(STAMP)  ## the whole test suite, system-level tests included
	$(BIN)/python -m pytest

test-fast: $(STAMP)  ## unit tests only
	$(BIN)/python -m pytest -m "not slow and not workflow"

lint: $(STAMP)
	$(BIN)/snakemake --lint

report: $(STAMP)
	$(BIN)/snakemake --configfile $(CONFIG) --report report.html

clean:
	rm -rf results .snakemake
