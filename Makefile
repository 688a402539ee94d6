# dali: set-up, tests, benchmarks and the pipeline's iterations.
#   make demo   create the venv, install, run a small synthetic source -> target adaptation
#   make test   create the venv, install, run the test suite
SHELL := /bin/bash
.DEFAULT_GOAL := help

PYTHON   ?= python3
VENV     ?= .venv
BIN      := $(VENV)/bin
DALI     := $(BIN)/dali
STAMP    := $(VENV)/.installed

# Pipeline variables (see README "Running the pipeline"). When SOURCE, TARGET and TARGET_VAL are
# not given, they are synthesized under $(RUN)/data.
RUN        ?= runs/demo
SENSOR     ?= kitti
SOURCE_SENSOR ?= waymo
FRAMES     ?= 24
SEED       ?= 0
EPOCHS     ?= 1
SOURCE     ?= $(RUN)/data/source
TARGET     ?= $(RUN)/data/target
TARGET_VAL ?= $(RUN)/data/target_val
LIBRARY    ?= $(RUN)/library

.PHONY: help install test demo bench lint format clean-runs

help:
	@echo "make demo    - install and run a small synthetic adaptation end to end"
	@echo "make test    - install and run the test suite"
	@echo "make bench   - run the benchmarks (results in bench/results/*.json)"
	@echo "make lint    - ruff check + format check"

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	@# torch first, pinned: on these machines 2.13.0 is a local CPU wheel; other specs pull CUDA.
	$(BIN)/pip install --quiet --disable-pip-version-check torch==2.13.0
	$(BIN)/pip install --quiet --disable-pip-version-check -e '.[dev]'
	@touch $(STAMP)

install: $(STAMP)

test: install
	$(BIN)/python -m pytest

lint: install
	$(BIN)/ruff check dali_cli stages tests bench
	$(BIN)/ruff format --check dali_cli stages tests bench

format: install
	$(BIN)/ruff format dali_cli stages tests bench
	$(BIN)/ruff check --fix dali_cli stages tests bench

bench: install
	@mkdir -p bench/results
	@for script in bench/*.py; do echo "== $$script"; $(BIN)/python $$script || exit 1; done

# ---------------------------------------------------------------------------------------------
# Data (synthesized when not given)
$(RUN)/data/source/manifest.json: | install
	$(DALI) synth --sensor $(SOURCE_SENSOR) --cars $(SOURCE_SENSOR) --frames $(FRAMES) --seed $(SEED) --out $(RUN)/data/source
$(RUN)/data/target/manifest.json: | install
	$(DALI) synth --sensor $(SENSOR) --cars $(SENSOR) --frames $(FRAMES) --seed $$(( $(SEED) + 1000 )) --out $(RUN)/data/target
$(RUN)/data/target_val/manifest.json: | install
	$(DALI) synth --sensor $(SENSOR) --cars $(SENSOR) --frames $(FRAMES) --seed $$(( $(SEED) + 2000 )) --out $(RUN)/data/target_val

data: $(SOURCE)/manifest.json $(TARGET)/manifest.json $(TARGET_VAL)/manifest.json

demo: install
	@$(BIN)/python -m dali_cli.demo_status
	$(MAKE) --no-print-directory data RUN=$(RUN) FRAMES=$(FRAMES) SEED=$(SEED)

clean-runs:
	rm -rf runs
