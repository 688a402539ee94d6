# dali: set-up, tests, benchmarks and the pipeline's iterations.
#   make demo   create the venv, install, run a small synthetic source -> target adaptation
#   make test   create the venv, install, run the test suite (its slow end-to-end cases: make test-slow)
SHELL := /bin/bash
# the recursive makes' flags: this file, so that `make -f PATH/Makefile` run from another
# directory keeps using it ($(MAKE) stays literal in each recipe, so `make -n` still recurses)
SELF  := $(abspath $(firstword $(MAKEFILE_LIST)))
SUBMAKE_FLAGS := -f "$(SELF)" --no-print-directory
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
# frames of the synthesized source (default FRAMES, as many as the target's)
SOURCE_FRAMES ?= $(FRAMES)
SEED       ?= 0
EPOCHS     ?= 1
SOURCE     ?= $(RUN)/data/source
TARGET     ?= $(RUN)/data/target
TARGET_VAL ?= $(RUN)/data/target_val
LIBRARY    ?= $(RUN)/library

.PHONY: help install test test-slow demo bench pareto pareto-quick lint format clean clean-runs models

help:
	@echo "make demo        - install, then adapt the shipped source to a small synthetic target (a few minutes)"
	@echo "make test        - install and run the test suite, without its slow end-to-end cases"
	@echo "make test-slow   - the slow end-to-end tests (CI runs both: make -j2 test test-slow)"
	@echo "make tiny        - one DALI iteration on 16 synthetic target frames from 32 source frames (runs/tiny), with what each step kept"
	@echo "make iter0, iter1, iter2 ... iter5 RUN=DIR - the pipeline's iterations (variables: top of the Makefile)"
	@echo "make x1-long, iter2-st, controls (controls-x1, controls-x2), baselines (baseline-sn, baseline-ros,"
	@echo "     baseline-oracle, ablation-rc, ablation-cf), cross-domain, compare RUN=DIR - the rows DALI is read against"
	@echo "make report RUN=DIR - the AP table, sizes and plots of a run"
	@echo "make experiment  - the full synthetic benchmark (docs/RESULTS.md)"
	@echo "make real-kitti  - adapt to real KITTI drives over seeds: every row on labelled real frames (docs/data.md)"
	@echo "make real-kitti-holdout - the same, adapted without REAL_DRIVE: rows judged on a drive never seen"
	@echo "make real-kitti-beams BEAMS=16 - adapt models/kitti-hdl64e to the drives at 32 or 16 beams (docs/data.md)"
	@echo "make models      - rebuild models/waymo-like-source, kitti-hdl64e, kitti-16beam and kitti-32beam with their cards"
	@echo "make models-beams BEAMS=16 - only the sparse model models/kitti-<BEAMS>beam (docs/models.md)"
	@echo "make models-round - models/kitti-hdl64e adapted one round further on REAL_DRIVES, gated (docs/models.md)"
	@echo "make bench       - run the benchmarks (results in bench/results/*.json)"
	@echo "make pareto      - run time vs error of every stage's speed knobs (docs/pareto.md; pareto-quick: smoke test)"
	@echo "make lint        - ruff check + format check"
	@echo "make clean       - remove caches and build leftovers (the venv and runs/ stay)"
	@echo "make clean-runs  - remove runs/, every run's artifacts (the venv stays)"

# caches and build leftovers of the tools (pytest, ruff, setuptools, Python); never runs/ or data
clean:
	rm -rf .pytest_cache .ruff_cache .hypothesis build *.egg-info bench/results/tmp
	find dali_cli stages tests bench -name __pycache__ -type d -prune -exec rm -rf {} +
# every run directory (make's and dali's artifacts under runs/)
clean-runs:
	rm -rf runs

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	@# torch first, pinned: on these machines 2.13.0 is a local CPU wheel; other specs pull CUDA.
	$(BIN)/pip install --quiet --disable-pip-version-check torch==2.13.0
	@# .[ray]: the optional Ray engine, installed so the test suite runs its tests on a local Ray;
	@# .[onnx], .[view]: the ONNX export with onnxruntime and Rerun recordings, tested the same way
	$(BIN)/pip install --quiet --disable-pip-version-check -e '.[dev,ray,onnx,view]'
	@touch $(STAMP)

install: $(STAMP)

# the suite but its slow end-to-end cases (marker `slow`: the pipeline through make, torchrun,
# Ray, training to convergence); test-slow runs those. CI runs both side by side: make -j2
# --output-sync=target test test-slow. Measured on a 2-core VM shared with other jobs (load 7-11):
# make test 4.5 min of pytest (190 CPU seconds), the whole suite 8.6 min (405). pytest runs
# without this make's flags (MAKEFLAGS), so the tests' own `make` calls plan and run as from a
# shell, not inside a -j2 job server
PYTEST = env -u MAKEFLAGS -u MFLAGS -u MAKELEVEL $(BIN)/python -m pytest
test: install
	$(PYTEST) -m "not slow"
test-slow: install
	$(PYTEST) -m slow

lint: install
	$(BIN)/ruff check dali_cli stages tests bench
	$(BIN)/ruff format --check dali_cli stages tests bench

format: install
	$(BIN)/ruff format dali_cli stages tests bench
	$(BIN)/ruff check --fix dali_cli stages tests bench

# the benchmarks (each writes bench/results/*.json; SCRIPT:ARG runs `bench/SCRIPT ARG`). The other
# scripts in bench/ are analysis tools that take run directories (ablation_table, paired_rows,
# pseudo_labels; docs/RESULTS.md shows their commands)
BENCHMARKS = detector.py:speed eval.py frameset_read.py hostile_inputs.py importers.py pareto.py \
    ppcg.py ptsn.py raycast.py registration.py scale.py scale_training.py synth.py waymo_import.py \
    numerical_stability.py
bench: install
	@mkdir -p bench/results
	@for run in $(BENCHMARKS); do echo "== bench/$${run/:/ }"; $(BIN)/python bench/$${run/:/ } || exit 1; done

# run time against error (bench/pareto.py, part of `make bench`): bench/results/pareto.json and
# docs/pareto/*.png; builds a small model under runs/bench_pareto when none is given, and trains
# the pillar front's models there (4 detectors, ~7 min on an idle 2-core VM; reused when up to date)
pareto: install
	nice -n 5 $(BIN)/python bench/pareto.py
pareto-quick: install
	$(BIN)/python bench/pareto.py --quick

# ---------------------------------------------------------------------------------------------
# The pipeline. Every step's target is its artifact's manifest.json (written last, atomically), so an
# interrupted `make iter2` resumes where it stopped and `make -n iter2` shows the plan. Each dali stage
# also skips itself when its inputs (by content hash) and parameters are unchanged.
#
#   iter0: pretrain on SOURCE; eval source-only (s = 1) and PTSN-only (s from iter1/ptsn)
#   iterN: ptsn-sweep (model N-1) -> pseudo-label -> ppcg-rc -> ppcg-cf -> retrain -> eval (PTSN)
MINUTES        ?=
RETRAIN_EPOCHS ?= $(EPOCHS)
# per-iteration retraining budgets: 2 x RETRAIN_EPOCHS in all, a quarter in iteration 1 (half of
# RETRAIN_EPOCHS, at least 1) and the rest in iteration 2, on iteration 2's better labels
# (docs/RESULTS.md); e.g. RETRAIN_EPOCHS_1=6 RETRAIN_EPOCHS_2=6 for the paper's even split
ifneq ($(shell echo '$(RETRAIN_EPOCHS)' | grep -Exc '[1-9][0-9]*'),1)
$(error RETRAIN_EPOCHS must be a whole number of epochs >= 1, got '$(RETRAIN_EPOCHS)')
endif
RETRAIN_EPOCHS_1 ?= $(shell echo $$(( $(RETRAIN_EPOCHS) / 2 > 0 ? $(RETRAIN_EPOCHS) / 2 : 1 )))
RETRAIN_EPOCHS_2 ?= $(shell echo $$(( 2 * $(RETRAIN_EPOCHS) - $(RETRAIN_EPOCHS_1) )))
# extra pretrain/retrain flags, e.g. TRAIN_FLAGS="--threads 1" for `make -j2` on a 2-core machine
TRAIN_FLAGS    ?=
# extra flags of pretraining alone (every model trained from scratch), e.g.
# PRETRAIN_FLAGS="--detector-config FILE.json" with {"direction": false}: a detector without the direction head
PRETRAIN_FLAGS ?=
# NPROC=N: pretrain, retrain and self-train run as N data-parallel processes under torchrun
# (DDP: gloo on the CPU, nccl on GPUs; --batch-size frames per process; rank 0 writes the model).
# Unset: one process, as before. DEVICE=cuda (or cpu, cuda:N) is passed to every model stage.
# PRECISION=bf16: bf16 autocast in every model stage (training and inference; CUDA GPUs with bf16,
# CPUs with AVX512-BF16 or AMX: 1.4x training, 1.5x inference on a Zen 4 VM, docs/detector.md).
NPROC          ?=
DEVICE         ?=
PRECISION      ?=
TRAIN_DALI      = $(if $(NPROC),$(BIN)/torchrun --standalone --nproc-per-node $(NPROC) $(DALI),$(DALI))
# THREADS=N: torch threads of every model stage (training and inference; unset: every core the
# stage may use). The float sums, so a model's and the boxes' last bits, follow the thread count:
# the same SEED and THREADS give the same artifacts, another THREADS other last bits, and four
# epochs carry those into other figures (docs/RESULTS.md, "The tiny run")
THREADS        ?=
DEVICE_FLAG     = $(if $(DEVICE),--device $(DEVICE)) $(if $(PRECISION),--precision $(PRECISION))$(if $(THREADS), --threads $(THREADS))
# --minutes makes results depend on the machine and its load; epochs (the default) do not
TRAIN_BUDGET    = $(if $(MINUTES),--minutes $(MINUTES),--epochs $(EPOCHS))
RETRAIN_BUDGET  = $(if $(MINUTES),--minutes $(MINUTES),--epochs $(or $(RETRAIN_EPOCHS_$(1)),$(RETRAIN_EPOCHS)))
EXPECTED       ?= sn
LIBRARY_MODELS ?= 24
# synth's worker processes: the cores this make may use (taskset-pinned lanes get their share)
SYNTH_WORKERS  ?= $(shell nproc)
# engine of the per-frame stages (synth, pseudo-label, ppcg-rc, ppcg-cf, eval): local or ray
# (docs/scale-out.md); WORKERS: their workers (empty: each stage's default), RAY_ADDRESS: a Ray
# cluster (empty: a local Ray instance per stage)
EXECUTOR       ?= local
WORKERS        ?=
RAY_ADDRESS    ?=
EXEC_FLAGS      = --executor $(EXECUTOR)$(if $(WORKERS), --workers $(WORKERS))$(if $(RAY_ADDRESS), --ray-address $(RAY_ADDRESS))
SYNTH_FLAGS     = --executor $(EXECUTOR) --workers $(or $(WORKERS),$(SYNTH_WORKERS))$(if $(RAY_ADDRESS), --ray-address $(RAY_ADDRESS))
VAL_FRAMES     ?= $(FRAMES)
SCORE_MIN      ?= 0.3
# pseudo-label options, e.g. PSEUDO_FLAGS=--no-fit-points (the paper's boxes, not moved onto
# their points)
PSEUDO_FLAGS   ?=
# options of both ppcg-rc and ppcg-cf, e.g. PPCG_FLAGS="--no-orient-models --point-margin-m 0"
# (the paper's PPCG: car models as the detector's heading has them, the points in the box only)
PPCG_FLAGS     ?=
# retrain options (iterations and x1 long), e.g. RETRAIN_FLAGS="--mix 1:7"
RETRAIN_FLAGS  ?=
# evaluation: all boxes and range bands of the front region (90 deg FOV, detection range, as ST3D
# evaluates KITTI), AP at IoU 0.7 and 0.5
EVAL_FLAGS     ?= --protocol range --front-only --iou 0.7 --iou 0.5 --size-score-min $(SCORE_MIN)

$(RUN)/data/source/manifest.json: | install
	$(DALI) synth --sensor $(SOURCE_SENSOR) --cars $(SOURCE_SENSOR) --frames $(SOURCE_FRAMES) --seed $(SEED) $(SYNTH_FLAGS) --out $(@D)
$(RUN)/data/source_val/manifest.json: | install
	$(DALI) synth --sensor $(SOURCE_SENSOR) --cars $(SOURCE_SENSOR) --frames $(VAL_FRAMES) --seed $$(( $(SEED) + 3000 )) $(SYNTH_FLAGS) --out $(@D)
$(RUN)/data/target/manifest.json: | install
	$(DALI) synth --sensor $(SENSOR) --cars $(SENSOR) --frames $(FRAMES) --seed $$(( $(SEED) + 1000 )) $(SYNTH_FLAGS) --out $(@D)
$(RUN)/data/target_val/manifest.json: | install
	$(DALI) synth --sensor $(SENSOR) --cars $(SENSOR) --frames $(VAL_FRAMES) --seed $$(( $(SEED) + 2000 )) $(SYNTH_FLAGS) --out $(@D)
$(RUN)/library/manifest.json: | install
	$(DALI) library build --procedural $(LIBRARY_MODELS) --seed $$(( $(SEED) + 4000 )) --out $(@D)

data: $(SOURCE)/manifest.json $(TARGET)/manifest.json $(TARGET_VAL)/manifest.json

# iteration 0: the source-only detector, pretrained on SOURCE; or, with SOURCE_MODEL=DIR, a trained
# model directory the iterations start from instead (the demo: models/waymo-like-source, no
# pretraining; the other rows that retrain from iter0 still pretrain it)
SOURCE_MODEL ?=
iter_model = $(if $(and $(filter 0,$(1)),$(SOURCE_MODEL)),$(SOURCE_MODEL),$(RUN)/iter$(1)/model)
iter_model_target = $(if $(and $(filter 0,$(1)),$(SOURCE_MODEL)),$(SOURCE_MODEL)/model.json,$(RUN)/iter$(1)/model/manifest.json)
# a model named by its directory in the run (iter2/model): iter0/model is SOURCE_MODEL when given
run_model = $(if $(filter iter0/model,$(1)),$(call iter_model,0),$(RUN)/$(1))
$(RUN)/iter0/model/manifest.json: $(SOURCE)/manifest.json
	$(TRAIN_DALI) pretrain --source $(SOURCE) --seed $(SEED) $(TRAIN_BUDGET) $(TRAIN_FLAGS) $(PRETRAIN_FLAGS) $(DEVICE_FLAG) --out $(@D)
$(RUN)/iter0/eval/manifest.json: $(call iter_model_target,0) $(TARGET_VAL)/manifest.json
	$(DALI) eval $(DEVICE_FLAG) --model $(call iter_model,0) --data $(TARGET_VAL) --scale 1.0 $(EVAL_FLAGS) $(EXEC_FLAGS) --out $(@D)
$(RUN)/iter0/eval_ptsn/manifest.json: $(RUN)/iter1/ptsn/manifest.json $(TARGET_VAL)/manifest.json
	$(DALI) eval $(DEVICE_FLAG) --model $(call iter_model,0) --data $(TARGET_VAL) --scale-from $(RUN)/iter1/ptsn $(EVAL_FLAGS) $(EXEC_FLAGS) --out $(@D)
iter0: $(RUN)/iter0/eval/manifest.json $(RUN)/iter0/eval_ptsn/manifest.json
# direct transfer: a SOURCE_MODEL that ships its test-time scale (scale.json: models/kitti-hdl64e)
# at that scale
$(RUN)/iter0/eval_direct/manifest.json: $(call iter_model_target,0) $(TARGET_VAL)/manifest.json
	$(DALI) eval $(DEVICE_FLAG) --model $(call iter_model,0) --data $(TARGET_VAL) --scale-from $(call iter_model,0) $(EVAL_FLAGS) $(EXEC_FLAGS) --out $(@D)

# SOURCE_SIZE=sn (default): retraining shifts the source cars to the sweep's label-free E_est,
# so source and PPCG labels agree on the target's size (docs/method.md); SOURCE_SIZE=init keeps the initial model's sizes (the paper's).
SOURCE_SIZE ?= sn
SOURCE_SIZE_FLAGS = --size-norm $(SOURCE_SIZE)$(if $(filter sn,$(SOURCE_SIZE)), --target-size-from $(RUN)/iter$(1)/ptsn)

# ptsn-sweep N uses model N-1 (ITER_PTSN), iteration N builds model N (ITER)
define ITER_PTSN
$(RUN)/iter$(1)/ptsn/manifest.json: $(call iter_model_target,$(2)) $(TARGET)/manifest.json
	$(DALI) ptsn-sweep $(DEVICE_FLAG) --model $(call iter_model,$(2)) --data $(TARGET) --target-size $(EXPECTED) --score-min $(SCORE_MIN) --seed $(SEED) --out $$(@D)
endef
define ITER
$(RUN)/iter$(1)/pseudo/manifest.json: $(RUN)/iter$(1)/ptsn/manifest.json
	$(DALI) pseudo-label $(DEVICE_FLAG) --model $(call iter_model,$(2)) --data $(TARGET) --scale-from $(RUN)/iter$(1)/ptsn --score-min $(SCORE_MIN) $(PSEUDO_FLAGS) $(EXEC_FLAGS) --out $$(@D)
$(RUN)/iter$(1)/rc/manifest.json: $(RUN)/iter$(1)/pseudo/manifest.json $(LIBRARY)/manifest.json
	$(DALI) ppcg-rc --data $(TARGET) --boxes $(RUN)/iter$(1)/pseudo --library $(LIBRARY) --target-profile $(SENSOR) --seed $(SEED) $(PPCG_FLAGS) $(EXEC_FLAGS) --out $$(@D)
$(RUN)/iter$(1)/cf/manifest.json: $(RUN)/iter$(1)/pseudo/manifest.json $(LIBRARY)/manifest.json
	$(DALI) ppcg-cf --data $(TARGET) --boxes $(RUN)/iter$(1)/pseudo --library $(LIBRARY) --target-profile $(SENSOR) --seed $(SEED) $(PPCG_FLAGS) $(EXEC_FLAGS) --out $$(@D)
$(RUN)/iter$(1)/model/manifest.json: $(RUN)/iter$(1)/rc/manifest.json $(RUN)/iter$(1)/cf/manifest.json $(SOURCE)/manifest.json
	$(TRAIN_DALI) retrain --init $(call iter_model,$(2)) --source $(SOURCE) --ppcg $(RUN)/iter$(1)/rc $(RUN)/iter$(1)/cf $(call SOURCE_SIZE_FLAGS,$(1)) --seed $(SEED) $(call RETRAIN_BUDGET,$(1)) $(RETRAIN_FLAGS) $(TRAIN_FLAGS) $(DEVICE_FLAG) --out $$(@D)
$(RUN)/iter$(1)/eval/manifest.json: $(RUN)/iter$(3)/ptsn/manifest.json $(TARGET_VAL)/manifest.json
	$(DALI) eval $(DEVICE_FLAG) --model $(RUN)/iter$(1)/model --data $(TARGET_VAL) --scale-from $(RUN)/iter$(3)/ptsn $(EVAL_FLAGS) $(EXEC_FLAGS) --out $$(@D)
iter$(1): iter$(2) $(RUN)/iter$(1)/eval/manifest.json
.PHONY: iter$(1)
endef
$(foreach n,1 2 3 4 5 6,$(eval $(call ITER_PTSN,$(n),$(shell echo $$(( $(n) - 1 ))))))
$(foreach n,1 2 3 4 5,$(eval $(call ITER,$(n),$(shell echo $$(( $(n) - 1 ))),$(shell echo $$(( $(n) + 1 ))))))

# x1 long: one retraining of x2's retraining frames (RETRAIN_EPOCHS_1 + RETRAIN_EPOCHS_2 epochs)
# on iteration 1's PPCG frames, then its own sweep; the same budget as x2 and its control. On an
# equal budget the better use of the frames than a second iteration (docs/RESULTS.md, "Does a
# second iteration pay on an equal budget?")
X1_LONG_BUDGET = $(if $(MINUTES),--minutes $$(( 2 * $(MINUTES) )),--epochs $$(( $(RETRAIN_EPOCHS_1) + $(RETRAIN_EPOCHS_2) )))
$(RUN)/x1_long/model/manifest.json: $(RUN)/iter1/rc/manifest.json $(RUN)/iter1/cf/manifest.json $(SOURCE)/manifest.json
	$(TRAIN_DALI) retrain --init $(RUN)/iter0/model --source $(SOURCE) --ppcg $(RUN)/iter1/rc $(RUN)/iter1/cf $(call SOURCE_SIZE_FLAGS,1) --seed $(SEED) $(X1_LONG_BUDGET) $(RETRAIN_FLAGS) $(TRAIN_FLAGS) $(DEVICE_FLAG) --out $(@D)
$(RUN)/x1_long/ptsn/manifest.json: $(RUN)/x1_long/model/manifest.json $(TARGET)/manifest.json
	$(DALI) ptsn-sweep $(DEVICE_FLAG) --model $(RUN)/x1_long/model --data $(TARGET) --target-size $(EXPECTED) --score-min $(SCORE_MIN) --seed $(SEED) --out $(@D)
$(RUN)/x1_long/eval/manifest.json: $(RUN)/x1_long/ptsn/manifest.json $(TARGET_VAL)/manifest.json
	$(DALI) eval $(DEVICE_FLAG) --model $(RUN)/x1_long/model --data $(TARGET_VAL) --scale-from $(RUN)/x1_long/ptsn $(EVAL_FLAGS) $(EXEC_FLAGS) --out $(@D)
x1-long: iter0 $(RUN)/x1_long/eval/manifest.json
.PHONY: x1-long

# Baselines and ablations for the results table (make experiment)
$(RUN)/baselines/sn/model/manifest.json: $(SOURCE)/manifest.json
	$(TRAIN_DALI) pretrain --source $(SOURCE) --size-norm sn --target-profile $(SENSOR) --seed $(SEED) $(TRAIN_BUDGET) $(TRAIN_FLAGS) $(PRETRAIN_FLAGS) $(DEVICE_FLAG) --out $(@D)
$(RUN)/baselines/ros/model/manifest.json: $(SOURCE)/manifest.json
	$(TRAIN_DALI) pretrain --source $(SOURCE) --size-norm ros --seed $(SEED) $(TRAIN_BUDGET) $(TRAIN_FLAGS) $(PRETRAIN_FLAGS) $(DEVICE_FLAG) --out $(@D)
$(RUN)/baselines/oracle/model/manifest.json: $(TARGET)/manifest.json
	$(TRAIN_DALI) pretrain --source $(TARGET) --seed $(SEED) $(TRAIN_BUDGET) $(TRAIN_FLAGS) $(PRETRAIN_FLAGS) $(DEVICE_FLAG) --out $(@D)
$(RUN)/baselines/rc_only/model/manifest.json: $(RUN)/iter1/rc/manifest.json $(SOURCE)/manifest.json
	$(TRAIN_DALI) retrain --init $(RUN)/iter0/model --source $(SOURCE) --ppcg $(RUN)/iter1/rc $(call SOURCE_SIZE_FLAGS,1) --seed $(SEED) $(call RETRAIN_BUDGET,1) $(TRAIN_FLAGS) $(DEVICE_FLAG) --out $(@D)
$(RUN)/baselines/cf_only/model/manifest.json: $(RUN)/iter1/cf/manifest.json $(SOURCE)/manifest.json
	$(TRAIN_DALI) retrain --init $(RUN)/iter0/model --source $(SOURCE) --ppcg $(RUN)/iter1/cf $(call SOURCE_SIZE_FLAGS,1) --seed $(SEED) $(call RETRAIN_BUDGET,1) $(TRAIN_FLAGS) $(DEVICE_FLAG) --out $(@D)
$(RUN)/baselines/%/eval/manifest.json: $(RUN)/baselines/%/model/manifest.json $(TARGET_VAL)/manifest.json
	$(DALI) eval $(DEVICE_FLAG) --model $(RUN)/baselines/$*/model --data $(TARGET_VAL) --scale 1.0 $(EVAL_FLAGS) $(EXEC_FLAGS) --out $(@D)
$(RUN)/baselines/%/ptsn/manifest.json: $(RUN)/baselines/%/model/manifest.json $(TARGET)/manifest.json
	$(DALI) ptsn-sweep $(DEVICE_FLAG) --model $(RUN)/baselines/$*/model --data $(TARGET) --target-size $(EXPECTED) --score-min $(SCORE_MIN) --seed $(SEED) --out $(@D)
$(RUN)/baselines/%/eval_ptsn/manifest.json: $(RUN)/baselines/%/ptsn/manifest.json $(TARGET_VAL)/manifest.json
	$(DALI) eval $(DEVICE_FLAG) --model $(RUN)/baselines/$*/model --data $(TARGET_VAL) --scale-from $(RUN)/baselines/$*/ptsn $(EVAL_FLAGS) $(EXEC_FLAGS) --out $(@D)
# the controls at their strongest: their own test-time PTSN predictions resized per dimension by
# their sweep's E_est / E_pred(ŝ) (label-free; `dali eval --size-correction per-dim`), the bias one
# isotropic scale leaves (docs/RESULTS.md: +2.0 ± 0.4 AP_3D@0.7 at 600 frames)
$(RUN)/baselines/%/eval_ptsn_sized/manifest.json: $(RUN)/baselines/%/eval_ptsn/manifest.json
	$(DALI) eval --pred $(RUN)/baselines/$*/eval_ptsn/predictions.parquet --gt $(TARGET_VAL) --scale-from $(RUN)/baselines/$*/ptsn --size-correction per-dim $(EVAL_FLAGS) --out $(@D)
# controls: as many training frames as DALI's models saw (pretrain E epochs, retrain N 2 x
# RETRAIN_EPOCHS_N epochs of source + PPCG): source only with x1's budget (+ test-time PTSN),
# oracle with x2's
X1_BUDGET = $(if $(MINUTES),--minutes $$(( 2 * $(MINUTES) )),--epochs $$(( $(EPOCHS) + 2 * $(RETRAIN_EPOCHS_1) )))
X2_BUDGET = $(if $(MINUTES),--minutes $$(( 3 * $(MINUTES) )),--epochs $$(( $(EPOCHS) + 2 * ($(RETRAIN_EPOCHS_1) + $(RETRAIN_EPOCHS_2)) )))
$(RUN)/baselines/source_x1_budget/model/manifest.json: $(SOURCE)/manifest.json
	$(TRAIN_DALI) pretrain --source $(SOURCE) --seed $(SEED) $(X1_BUDGET) $(TRAIN_FLAGS) $(PRETRAIN_FLAGS) $(DEVICE_FLAG) --out $(@D)
$(RUN)/baselines/oracle_x2_budget/model/manifest.json: $(TARGET)/manifest.json
	$(TRAIN_DALI) pretrain --source $(TARGET) --seed $(SEED) $(X2_BUDGET) $(TRAIN_FLAGS) $(PRETRAIN_FLAGS) $(DEVICE_FLAG) --out $(@D)
# self-training (the paper's ‡): fine-tune x2 on the target with its own pseudo labels at its PTSN
# scale (iter3/ptsn, iter3/pseudo), in that scaled frame, and evaluate at the same scale
ST_EPOCHS ?= $(RETRAIN_EPOCHS)
ST_FLAGS  ?= --lr 1e-3
ST_BUDGET  = $(if $(MINUTES),--minutes $(MINUTES),--epochs $(ST_EPOCHS))
# a self-trained row: its directory, the model it starts from, its pseudo labels, their PTSN scale
# and the name of its budget's variable (default ST_BUDGET)
define SELF_TRAIN
$(RUN)/$(1)/model/manifest.json: $(RUN)/$(3)/manifest.json $(TARGET)/manifest.json
	$(TRAIN_DALI) self-train --init $(call run_model,$(2)) --data $(TARGET) --pseudo $(RUN)/$(3) --seed $(SEED) $$($(or $(5),ST_BUDGET)) $(ST_FLAGS) $(TRAIN_FLAGS) $(DEVICE_FLAG) --out $$(@D)
$(RUN)/$(1)/eval/manifest.json: $(RUN)/$(1)/model/manifest.json $(TARGET_VAL)/manifest.json
	$(DALI) eval $(DEVICE_FLAG) --model $(RUN)/$(1)/model --data $(TARGET_VAL) --scale-from $(RUN)/$(4) $(EVAL_FLAGS) $(EXEC_FLAGS) --out $$(@D)
endef
$(eval $(call SELF_TRAIN,iter2_st,iter2/model,iter3/pseudo,iter3/ptsn))
# the control self-trained the same way (control + ST): the x2-budget control pseudo-labels the
# target at its own PTSN scale with iteration N's pseudo-label settings, then self-trains on them
$(RUN)/baselines/%/pseudo/manifest.json: $(RUN)/baselines/%/ptsn/manifest.json
	$(DALI) pseudo-label $(DEVICE_FLAG) --model $(RUN)/baselines/$*/model --data $(TARGET) --scale-from $(RUN)/baselines/$*/ptsn --score-min $(SCORE_MIN) $(PSEUDO_FLAGS) $(EXEC_FLAGS) --out $(@D)
$(eval $(call SELF_TRAIN,baselines/source_x2_budget_st,baselines/source_x2_budget/model,baselines/source_x2_budget/pseudo,baselines/source_x2_budget/ptsn))
# tracked self-training (docs/tracks.md): the same self-training on labels that persist over the
# target's scans. The model pseudo-labels the target with a low cut (TRACK_PSEUDO_MIN: the tracks
# do the filtering), `dali track-pseudo` keeps one box per parked car in every scan that holds it
# and the moving tracks, in the world frame of the scans' LiDAR poses by scan registration
# (`dali register`, once per target: TARGET_POSES); x2 + tracked ST and control + tracked ST
TRACK_PSEUDO_MIN ?= 0.1
TARGET_POSES = $(TARGET)_poses
$(TARGET_POSES)/manifest.json: $(TARGET)/manifest.json
	$(DALI) register --data $(TARGET) --out $(@D)
# tracked labels in (1) by the model (2) at its PTSN scale (3)
define TRACKED_LABELS
$(RUN)/$(1)/pseudo_low/manifest.json: $(RUN)/$(3)/manifest.json
	$(DALI) pseudo-label $(DEVICE_FLAG) --model $(call run_model,$(2)) --data $(TARGET) --scale-from $(RUN)/$(3) --score-min $(TRACK_PSEUDO_MIN) $(PSEUDO_FLAGS) $(EXEC_FLAGS) --out $$(@D)
$(RUN)/$(1)/tracked/manifest.json: $(RUN)/$(1)/pseudo_low/manifest.json $(TARGET_POSES)/manifest.json
	$(DALI) track-pseudo --pseudo $(RUN)/$(1)/pseudo_low --data $(TARGET) --poses $(TARGET_POSES) --out $$(@D)
endef
$(eval $(call TRACKED_LABELS,iter3,iter2/model,iter3/ptsn))
$(eval $(call TRACKED_LABELS,baselines/source_x2_budget,baselines/source_x2_budget/model,baselines/source_x2_budget/ptsn))
$(eval $(call SELF_TRAIN,iter2_tst,iter2/model,iter3/tracked,iter3/ptsn))
$(eval $(call SELF_TRAIN,baselines/source_x2_budget_tst,baselines/source_x2_budget/model,baselines/source_x2_budget/tracked,baselines/source_x2_budget/ptsn))
# a second round (control + tracked ST x2): control + tracked ST pseudo-labels the target again at
# its own PTSN scale, its labels are tracked the same way and it self-trains on them, from itself
$(eval $(call TRACKED_LABELS,baselines/source_x2_budget_tst,baselines/source_x2_budget_tst/model,baselines/source_x2_budget_tst/ptsn))
$(eval $(call SELF_TRAIN,baselines/source_x2_budget_tst2,baselines/source_x2_budget_tst/model,baselines/source_x2_budget_tst/tracked,baselines/source_x2_budget_tst/ptsn))
# the x2-budget control (baselines/source_x2_budget/model). CONTROL=pretrain (default): the source
# model trained from scratch on SOURCE as long as iter0 and x2's retrainings together (X2_BUDGET).
# CONTROL=tracked-st, for a trained SOURCE_MODEL that adapts further (make real-kitti-beams): such
# a model has no labelled source frames of its own domain to be trained longer on (models/kitti-hdl64e
# was adapted to its KITTI drives without a label; the synthetic frames it started from would undo
# that), so the control is the label-free alternative to DALI on the same target with x2's
# training: SOURCE_MODEL self-trained on its own pseudo labels of the target at its PTSN scale
# (iter1/ptsn, iteration 1's), kept by track-pseudo as for x2 + tracked ST, for as many frames as
# x2's two retrainings see (CONTROL_ST_BUDGET); it then gets its own sweep (eval_ptsn) like the
# pretrained control, so control + tracked ST and the comparisons with x2 stay as they are
CONTROL ?= pretrain
ifeq ($(filter pretrain tracked-st,$(CONTROL)),)
$(error CONTROL must be pretrain or tracked-st, got '$(CONTROL)')
endif
# x2's retrainings in self-training epochs: 2 x (RETRAIN_EPOCHS_1 + RETRAIN_EPOCHS_2) x |SOURCE|
# frames (a retraining epoch: the source frames and as many PPCG frames, --mix 1:1), a
# self-training epoch |TARGET| frames; both counts from the frame sets' manifests, when it runs
CONTROL_ST_BUDGET = $(if $(MINUTES),--minutes $$(( 2 * $(MINUTES) )),--epochs $$($(BIN)/python -c \
    'import json, sys; s, t = (json.load(open(f"{d}/manifest.json"))["outputs"]["counts"]["frames"] for d in sys.argv[2:]); print(int(sys.argv[1]) * s / t)' \
    $$(( 2 * ($(RETRAIN_EPOCHS_1) + $(RETRAIN_EPOCHS_2)) )) $(SOURCE) $(TARGET)))
ifeq ($(CONTROL),tracked-st)
$(eval $(call TRACKED_LABELS,iter1,iter0/model,iter1/ptsn))
$(eval $(call SELF_TRAIN,baselines/source_x2_budget,iter0/model,iter1/tracked,iter1/ptsn,CONTROL_ST_BUDGET))
$(RUN)/baselines/source_x2_budget/model/manifest.json: $(SOURCE)/manifest.json
else
$(RUN)/baselines/source_x2_budget/model/manifest.json: $(SOURCE)/manifest.json
	$(TRAIN_DALI) pretrain --source $(SOURCE) --seed $(SEED) $(X2_BUDGET) $(TRAIN_FLAGS) $(PRETRAIN_FLAGS) $(DEVICE_FLAG) --out $(@D)
endif
# KITTI easy / moderate / hard of the same predictions (synthetic labels carry KITTI's columns)
KITTI_EVAL_FLAGS ?= --protocol kitti --iou 0.7 --iou 0.5 --size-score-min $(SCORE_MIN)
$(RUN)/%/metrics_kitti.json: $(RUN)/%/manifest.json
	$(DALI) eval --pred $(RUN)/$*/predictions.parquet --gt $(TARGET_VAL) $(KITTI_EVAL_FLAGS) --out $@
# cross-domain check: every model on the source validation set at s = 1
$(RUN)/%/eval_source/manifest.json: $(RUN)/%/model/manifest.json $(RUN)/data/source_val/manifest.json
	$(DALI) eval $(DEVICE_FLAG) --model $(RUN)/$*/model --data $(RUN)/data/source_val --scale 1.0 $(EVAL_FLAGS) $(EXEC_FLAGS) --out $(@D)
# a model retrained with the source at the target's size (SOURCE_SIZE=sn) outputs target-sized
# cars, so its forgetting check also runs on the source validation set shifted the same way
$(RUN)/%/source_val_sized/manifest.json: $(RUN)/%/model/manifest.json $(RUN)/data/source_val/manifest.json
	$(DALI) size-norm --data $(RUN)/data/source_val --like-model $(RUN)/$*/model --out $(@D)
$(RUN)/%/eval_source_sized/manifest.json: $(RUN)/%/source_val_sized/manifest.json
	$(DALI) eval $(DEVICE_FLAG) --model $(RUN)/$*/model --data $(RUN)/$*/source_val_sized --scale 1.0 $(EVAL_FLAGS) $(EXEC_FLAGS) --out $(@D)

# phony goals (evaluated inside the sub-make, so they follow its RUN)
baseline-sn: $(RUN)/baselines/sn/eval/manifest.json
baseline-ros: $(RUN)/baselines/ros/eval/manifest.json
baseline-oracle: $(RUN)/baselines/oracle/eval/manifest.json
ablation-rc: $(RUN)/baselines/rc_only/eval_ptsn/manifest.json
ablation-cf: $(RUN)/baselines/cf_only/eval_ptsn/manifest.json
baselines: baseline-sn baseline-ros baseline-oracle ablation-rc ablation-cf
cross-domain: $(RUN)/iter0/eval_source/manifest.json $(RUN)/iter2/eval_source/manifest.json \
    $(if $(filter sn,$(SOURCE_SIZE)),$(RUN)/iter2/eval_source_sized/manifest.json)
# equal-budget controls (standard rows of `make experiment`; "gap closed" is measured against
# them): source only with x1's and with x2's training frames + test-time PTSN, each also with the
# test-time size correction (eval_ptsn_sized), oracle with x2's frames (docs/RESULTS.md)
controls: controls-x1 controls-x2
controls-x1: $(RUN)/baselines/source_x1_budget/eval_ptsn/manifest.json \
    $(RUN)/baselines/source_x1_budget/eval_ptsn_sized/manifest.json
controls-x2: $(RUN)/baselines/source_x2_budget/eval_ptsn/manifest.json \
    $(RUN)/baselines/source_x2_budget/eval_ptsn_sized/manifest.json \
    $(RUN)/baselines/oracle_x2_budget/eval/manifest.json
iter2-st: iter2 $(RUN)/iter2_st/eval/manifest.json
# every target evaluation of the run also under KITTI's easy / moderate / hard
KITTI_ROWS = iter0/eval iter0/eval_ptsn iter1/eval iter2/eval iter2_st/eval x1_long/eval baselines/sn/eval \
    baselines/ros/eval baselines/oracle/eval baselines/rc_only/eval_ptsn baselines/cf_only/eval_ptsn \
    baselines/source_x1_budget/eval_ptsn baselines/source_x2_budget/eval_ptsn baselines/oracle_x2_budget/eval \
    baselines/source_x1_budget/eval_ptsn_sized baselines/source_x2_budget/eval_ptsn_sized
kitti-protocol:
	@for row in $(KITTI_ROWS); do \
	    if [ -f $(RUN)/$$row/metrics.json ]; then $(MAKE) $(SUBMAKE_FLAGS) $(RUN)/$$row/metrics_kitti.json || exit 1; fi; \
	done
# the main rows against the x2-budget control on the same validation frames: `dali compare` (a
# paired bootstrap over the frames, COMPARE_SAMPLES draws) on KITTI's R40 and on the fine recall
# grid R400, which has no R40 steps (docs/evaluation.md); `dali report RUN1 RUN2 ...`
# aggregates RUN/compare_r400.json and RUN/compare_r40.json over the runs. Builds every row it compares.
COMPARE_SAMPLES ?= 400
COMPARE_ROWS = control:baselines/source_x2_budget/eval_ptsn x2:iter2/eval x1-long:x1_long/eval \
    control-sized:baselines/source_x2_budget/eval_ptsn_sized oracle:baselines/oracle_x2_budget/eval
$(RUN)/compare_r%.json: $(foreach row,$(COMPARE_ROWS),$(RUN)/$(lastword $(subst :, ,$(row)))/manifest.json)
	$(DALI) compare --gt $(TARGET_VAL) $(foreach row,$(COMPARE_ROWS),--pred $(firstword $(subst :, ,$(row)))=$(RUN)/$(lastword $(subst :, ,$(row)))/predictions.parquet) \
	    --protocol range --front-only --iou 0.7 --recall-positions $* --samples $(COMPARE_SAMPLES) --seed $(SEED) --no-progress --out $@
compare: $(RUN)/compare_r40.json $(RUN)/compare_r400.json
.PHONY: baseline-sn baseline-ros baseline-oracle ablation-rc ablation-cf baselines cross-domain controls \
    controls-x1 controls-x2 iter2-st kitti-protocol compare

# ---------------------------------------------------------------------------------------------
# The real target: KITTI drives (make real-kitti). The demo's source model (DEMO_FRAMES synthetic
# Waymo-like frames, DEMO_EPOCHS epochs) adapted to one unlabeled target made of the scans of every
# drive of REAL_DRIVES, once per seed of SEEDS (REAL_RUN-s<seed>; data seeds and training seeds
# follow the seed). REAL_DRIVES holds raw synced drives (.../YYYY_MM_DD_drive_NNNN_sync, the calib
# files in the date folder above) and KITTI odometry sequences (.../sequences/NN), each imported
# without labels into REAL_DATA/drives/<name> (raw: the drive without _sync; odometry:
# odometry_NN), then merged (dali merge) into REAL_DATA/target, frame ids <name>-<frame>.
# The evaluation sets are camera field of view, and so is the target: raw drives and sequences with
# a calib.txt are cropped to camera 2's image (--crop-fov); a sequence without calib (odometry 00
# of the sample data) to the front REAL_FRONT_DEG degrees of azimuth, the image's width, which
# also keeps the near ground below the image (docs/data.md).
# Every row is evaluated with KITTI's protocol on REAL_DRIVE's tracklets (TARGET_VAL:
# REAL_DATA/drive_labels) and on the labelled KITTI object frames of REAL_OBJECTS, at the scale the
# row's drive evaluation used: with a frames table (REAL_FRAMES_TABLE, KITTI devkit's mapping of
# each object frame to its raw drive: columns id, raw_drive) split into the frames of the target's
# drives (REAL_DATA/objects_adapted, transductive) and of other drives (objects_other, inductive);
# without one, all of them (objects). Rows: source only, PTSN only, x1, x2, x2 + ST, the x2-budget
# control (source only + test-time PTSN), control + ST (the control pseudo-labelling the target at
# its own PTSN scale and self-trained like x2 + ST), x2 + tracked ST and control + tracked ST
# (the same self-training on `dali track-pseudo`'s labels) and the sim oracle (labelled synthetic
# KITTI-like frames, x2's budget); x2 against the control, x2 + ST against control + ST and x2 +
# tracked ST against control + tracked ST also with `dali compare` (a paired bootstrap over each
# set's frames). REAL_REPORT/real-kitti.md: the
# mean ± std over the seeds per row and set, each row minus the control paired by seed
# (bench/real_kitti_table.py). The source trainings (iter0, the control, the sim oracle) are
# the targets of `make RUN=REAL_RUN-s<seed> SEED=<seed> FRAMES=48 EPOCHS=6` as well: those built
# that way are reused. Nothing is fetched (docs/data.md). Only `dali eval`, `dali compare` and
# the bench scripts read the tracklets and the object labels.
REAL_DRIVE   ?= data/kitti_raw/2011_09_26/2011_09_26_drive_0001_sync
REAL_DRIVES  ?= $(REAL_DRIVE)
REAL_OBJECTS ?= tests/fixtures/real/kitti/training
REAL_FRAMES_TABLE ?= $(firstword $(wildcard $(REAL_OBJECTS)/frames.tsv $(REAL_OBJECTS)/../frames.tsv))
REAL_FRONT_DEG ?= 82
REAL_RUN     ?= runs/real-kitti
# BEAMS=32 or 16: the target's drives, the labelled drive and the object frames imported thinned to
# that many beams (`dali import ... --beams`, docs/data.md; sensor kitti-<BEAMS>), into a data
# directory of their own (REAL_RUN-<BEAMS>beams-data); 64: every point, as before
BEAMS        ?= 64
ifeq ($(filter 64 32 16,$(BEAMS)),)
$(error BEAMS must be 64, 32 or 16, got '$(BEAMS)')
endif
beams_suffix  = $(if $(filter-out 64,$(BEAMS)),-$(BEAMS)beams)
BEAMS_FLAG    = $(if $(filter-out 64,$(BEAMS)), --beams $(BEAMS))
REAL_DATA    ?= $(REAL_RUN)$(beams_suffix)-data
REAL_REPORT  ?= $(REAL_RUN)$(beams_suffix)-report
REAL_EVAL_FLAGS = --protocol kitti --iou 0.7 --iou 0.5 --size-score-min $(SCORE_MIN)
# the real target's variables for the recursive makes, with its data directory (1)
real_vars = FRAMES=$(DEMO_FRAMES) EPOCHS=$(DEMO_EPOCHS) EVAL_FLAGS="$(REAL_EVAL_FLAGS)" REAL_DATA=$(1) \
    TARGET=$(1)/target TARGET_VAL=$(1)/drive_labels$(if $(beams_suffix), BEAMS=$(BEAMS) SENSOR=kitti-$(BEAMS))
REAL_VARS = $(call real_vars,$(REAL_DATA))
# KITTI odometry devkit: the raw drive of each sequence (for the object frames' split)
ODOMETRY_RAW_DRIVES ?= 00=2011_10_03_drive_0027 01=2011_10_03_drive_0042 02=2011_10_03_drive_0034 \
    03=2011_09_26_drive_0067 04=2011_09_30_drive_0016 05=2011_09_30_drive_0018 06=2011_09_30_drive_0020 \
    07=2011_09_30_drive_0027 08=2011_09_30_drive_0028 09=2011_09_30_drive_0033 10=2011_09_30_drive_0034
real_dir = $(patsubst %/,%,$(1))
is_raw_drive = $(filter %_sync,$(call real_dir,$(1)))
# a drive's name in the target's frame ids, and its raw drive as the frames table names it
drive_name = $(if $(call is_raw_drive,$(1)),$(patsubst %_sync,%,$(notdir $(call real_dir,$(1)))),odometry_$(notdir $(call real_dir,$(1))))
raw_drive_of = $(if $(call is_raw_drive,$(1)),$(notdir $(call real_dir,$(1))),$(addsuffix _sync,$(patsubst $(notdir $(call real_dir,$(1)))=%,%,$(filter $(notdir $(call real_dir,$(1)))=%,$(ODOMETRY_RAW_DRIVES)))))
REAL_DRIVE_NAMES = $(foreach drive,$(REAL_DRIVES),$(call drive_name,$(drive)))
REAL_TARGET_RAW_DRIVES = $(foreach drive,$(REAL_DRIVES),$(call raw_drive_of,$(drive)))
# the ids of the table's frames in (1) or not in (0) the target's drives
real_object_ids = awk -F'\t' -v drives=' $(REAL_TARGET_RAW_DRIVES) ' -v inside=$(1) \
    'NR > 1 && (index(drives, " " $$2 " ") > 0) == inside { print $$1 }' $(REAL_FRAMES_TABLE)
REAL_OBJECT_SETS = $(if $(REAL_FRAMES_TABLE),$(if $(shell $(call real_object_ids,1)),objects_adapted) \
    $(if $(shell $(call real_object_ids,0)),objects_other),objects)
# a target drive's import (unlabeled, camera field of view)
define REAL_DRIVE_IMPORT
$(REAL_DATA)/drives/$(call drive_name,$(1))/manifest.json: | install
	$(if $(call is_raw_drive,$(1)),$(DALI) import kitti-raw $(1) --no-labels --crop-fov,$(DALI) import kitti-odometry $(1) $(if $(wildcard $(1)/calib.txt),--crop-fov,--crop-front-deg $(REAL_FRONT_DEG)))$(BEAMS_FLAG) --out $$(@D)
endef
$(foreach drive,$(REAL_DRIVES),$(eval $(call REAL_DRIVE_IMPORT,$(drive))))
$(REAL_DATA)/target/manifest.json: $(foreach name,$(REAL_DRIVE_NAMES),$(REAL_DATA)/drives/$(name)/manifest.json)
	$(DALI) merge $(foreach name,$(REAL_DRIVE_NAMES),--in $(name)=$(REAL_DATA)/drives/$(name)) --no-labels --out $(@D)
# the drive's tracklets, its frame ids named as in the target (for the pseudo-label diagnostic)
$(REAL_DATA)/drive_tracklets/manifest.json: | install
	$(DALI) import kitti-raw $(REAL_DRIVE) --crop-fov$(BEAMS_FLAG) --out $(@D)
$(REAL_DATA)/drive_labels/manifest.json: $(REAL_DATA)/drive_tracklets/manifest.json
	$(DALI) merge --in $(call drive_name,$(REAL_DRIVE))=$(REAL_DATA)/drive_tracklets --out $(@D)
$(REAL_DATA)/objects/manifest.json: | install
	$(DALI) import kitti $(REAL_OBJECTS) --crop-fov$(BEAMS_FLAG) --out $(@D)
$(REAL_DATA)/objects_adapted.txt $(REAL_DATA)/objects_other.txt: $(REAL_FRAMES_TABLE)
	@mkdir -p $(@D)
	$(call real_object_ids,$(if $(findstring adapted,$(@F)),1,0)) > $@.tmp && mv $@.tmp $@
$(REAL_DATA)/objects_%/manifest.json: $(REAL_DATA)/objects_%.txt | install
	$(DALI) import kitti $(REAL_OBJECTS) --ids $< --crop-fov$(BEAMS_FLAG) --out $(@D)
# the sim oracle: the oracle of the x2 budget trained on the synthetic KITTI-like frames
$(RUN)/baselines/sim_oracle_x2_budget/model/manifest.json: $(RUN)/data/target/manifest.json
	$(TRAIN_DALI) pretrain --source $(RUN)/data/target --seed $(SEED) $(X2_BUDGET) $(TRAIN_FLAGS) $(PRETRAIN_FLAGS) $(DEVICE_FLAG) --out $(@D)
# the rows: name, model, drive evaluation, the scale flag of that evaluation; REAL_ROW_NAMES are
# built (direct: only with a SOURCE_MODEL that ships its scale.json, make real-kitti-beams)
REAL_ROW_NAMES ?= source ptsn x1 x2 x2_st control control_st x2_tst control_tst control_tst2 oracle
REAL_ROWS = $(foreach name,$(REAL_ROW_NAMES),$(filter $(name):%,$(REAL_ROW_TABLE)))
REAL_ROW_TABLE = source:iter0/model:iter0/eval:--scale=1.0 \
    direct:iter0/model:iter0/eval_direct:--scale-from=$(call iter_model,0) \
    ptsn:iter0/model:iter0/eval_ptsn:--scale-from=$(RUN)/iter1/ptsn \
    x1:iter1/model:iter1/eval:--scale-from=$(RUN)/iter2/ptsn \
    x2:iter2/model:iter2/eval:--scale-from=$(RUN)/iter3/ptsn \
    x2_st:iter2_st/model:iter2_st/eval:--scale-from=$(RUN)/iter3/ptsn \
    control:baselines/source_x2_budget/model:baselines/source_x2_budget/eval_ptsn:--scale-from=$(RUN)/baselines/source_x2_budget/ptsn \
    control_st:baselines/source_x2_budget_st/model:baselines/source_x2_budget_st/eval:--scale-from=$(RUN)/baselines/source_x2_budget/ptsn \
    x2_tst:iter2_tst/model:iter2_tst/eval:--scale-from=$(RUN)/iter3/ptsn \
    control_tst:baselines/source_x2_budget_tst/model:baselines/source_x2_budget_tst/eval:--scale-from=$(RUN)/baselines/source_x2_budget/ptsn \
    control_tst2:baselines/source_x2_budget_tst2/model:baselines/source_x2_budget_tst2/eval:--scale-from=$(RUN)/baselines/source_x2_budget_tst/ptsn \
    oracle:baselines/sim_oracle_x2_budget/model:baselines/sim_oracle_x2_budget/eval:--scale=1.0 \
    dense_tst:dense_tst/model:dense_tst/eval:--scale-from=$(SOURCE_MODEL)
row_field = $(word $(2),$(subst :, ,$(1)))
# a row (1) on an object set (2): the row's model at the scale its drive evaluation used
define OBJECTS_ROW
$(RUN)/$(2)/$(call row_field,$(1),1)/manifest.json: $(RUN)/$(call row_field,$(1),3)/manifest.json $(REAL_DATA)/$(2)/manifest.json
	$(DALI) eval $(DEVICE_FLAG) --model $(call run_model,$(call row_field,$(1),2)) --data $(REAL_DATA)/$(2) $(subst =, ,$(call row_field,$(1),4)) $(EVAL_FLAGS) $(EXEC_FLAGS) --out $$(@D)
endef
$(foreach set,$(REAL_OBJECT_SETS),$(foreach row,$(REAL_ROWS),$(eval $(call OBJECTS_ROW,$(row),$(set)))))
# x2 against the control and x2 + ST against control + ST on each set: a paired bootstrap over its
# frames (KITTI R40, IoU 0.7); the predictions are the rows' evaluations'. Only the pairs whose
# two rows are among REAL_ROW_NAMES (real_pairs): fewer rows build no other row for a comparison
REAL_PAIRS = x2:control x2_st:control_st x2_tst:control_tst
real_pairs = $(foreach pair,$(REAL_PAIRS),$(if $(and $(filter $(call row_field,$(pair),1),$(REAL_ROW_NAMES)),$(filter $(call row_field,$(pair),2),$(REAL_ROW_NAMES))),$(pair)))
real_eval_dir = $(if $(filter drive,$(2)),$(call row_field,$(filter $(1):%,$(REAL_ROW_TABLE)),3),$(2)/$(1))
real_truth = $(if $(filter drive,$(1)),$(TARGET_VAL),$(REAL_DATA)/$(1))
define REAL_COMPARE
$(RUN)/compare_real/$(2)-$(call row_field,$(1),1).json: $(RUN)/$(call real_eval_dir,$(call row_field,$(1),1),$(2))/manifest.json $(RUN)/$(call real_eval_dir,$(call row_field,$(1),2),$(2))/manifest.json
	@mkdir -p $$(@D)
	$(DALI) compare --gt $(call real_truth,$(2)) --pred $(call row_field,$(1),2)=$(RUN)/$(call real_eval_dir,$(call row_field,$(1),2),$(2))/predictions.parquet \
	    --pred $(call row_field,$(1),1)=$(RUN)/$(call real_eval_dir,$(call row_field,$(1),1),$(2))/predictions.parquet \
	    --protocol kitti --iou 0.7 --recall-positions 40 --samples $(COMPARE_SAMPLES) --seed $(SEED) --no-progress --out $$@
endef
$(foreach set,drive $(REAL_OBJECT_SETS),$(foreach pair,$(real_pairs),$(eval $(call REAL_COMPARE,$(pair),$(set)))))
real-kitti-data: $(REAL_DATA)/target/manifest.json $(REAL_DATA)/drive_labels/manifest.json \
    $(foreach set,$(REAL_OBJECT_SETS),$(REAL_DATA)/$(set)/manifest.json)
real-kitti-rows: $(foreach row,$(REAL_ROWS),$(RUN)/$(call row_field,$(row),3)/manifest.json) \
    $(foreach set,$(REAL_OBJECT_SETS),$(foreach row,$(REAL_ROWS),$(RUN)/$(set)/$(call row_field,$(row),1)/manifest.json)) \
    $(foreach set,drive $(REAL_OBJECT_SETS),$(foreach pair,$(real_pairs),$(RUN)/compare_real/$(set)-$(call row_field,$(pair),1).json))
# pseudo-label quality on the drive's frames (cars with >= 5 points, BEV IoU >= 0.5): the pseudo
# labels the rows of REAL_ROW_NAMES self-train on (row:labels), so that fewer rows build no more
REAL_PSEUDO_TABLE = x1:iter1/pseudo x2:iter2/pseudo x2_st:iter3/pseudo \
    control_st:baselines/source_x2_budget/pseudo x2_tst:iter3/tracked \
    control_tst:baselines/source_x2_budget/tracked
REAL_PSEUDO = $(foreach name,$(REAL_ROW_NAMES),$(patsubst $(name):%,%,$(filter $(name):%,$(REAL_PSEUDO_TABLE))))
# (REAL_PSEUDO empty, e.g. BEAMS_PSEUDO= for the first rows only: nothing to measure)
real-kitti-pseudo: $(foreach dir,$(REAL_PSEUDO),$(RUN)/$(dir)/manifest.json) $(TARGET_VAL)/manifest.json
	$(if $(strip $(REAL_PSEUDO)),$(BIN)/python bench/pseudo_labels.py --target $(TARGET_VAL) \
	    --pseudo $(foreach dir,$(REAL_PSEUDO),$(RUN)/$(dir)) --iou 0.5 --min-points 5 --out $(RUN)/pseudo_labels.json)
# the data once, then every seed's rows, then the table over the seeds
real-kitti: install
	$(MAKE) $(SUBMAKE_FLAGS) real-kitti-data $(REAL_VARS)
	@for seed in $(SEEDS); do \
	    $(MAKE) $(SUBMAKE_FLAGS) real-kitti-rows real-kitti-pseudo RUN=$(REAL_RUN)$(beams_suffix)-s$$seed SEED=$$seed $(REAL_VARS) || exit 1; \
	done
	@mkdir -p $(REAL_REPORT)
	$(BIN)/python bench/real_kitti_table.py $(foreach seed,$(SEEDS),$(REAL_RUN)$(beams_suffix)-s$(seed)) --data $(REAL_DATA) \
	    --sets drive $(REAL_OBJECT_SETS) --out $(REAL_REPORT)/real-kitti.md
.PHONY: real-kitti real-kitti-data real-kitti-rows real-kitti-pseudo
# The yardstick for choosing a recipe (make real-kitti-holdout, same variables): every row adapted
# on REAL_DRIVES without REAL_DRIVE, so that REAL_DRIVE's tracklets, and the object frames of every
# drive but those adapted on, judge models on drives they never saw (REAL_RUN-holdout-*: data,
# runs, report); the winner then ships adapted on every drive (make models)
real_holdout_drives = $(foreach drive,$(REAL_DRIVES),$(if $(filter $(call real_dir,$(REAL_DRIVE)),$(call real_dir,$(drive))),,$(drive)))
real-kitti-holdout: install
	$(if $(filter-out $(words $(REAL_DRIVES)),$(words $(real_holdout_drives))),,$(error REAL_DRIVES must hold REAL_DRIVE for make real-kitti-holdout, which adapts on the others))
	$(MAKE) $(SUBMAKE_FLAGS) real-kitti REAL_RUN=$(REAL_RUN)-holdout REAL_DRIVES="$(real_holdout_drives)" REAL_PSEUDO=
.PHONY: real-kitti-holdout

# KITTI at fewer beams (make real-kitti-beams BEAMS=16 SEEDS="0 1 2" REAL_DRIVE=... REAL_DRIVES=...
# REAL_OBJECTS=...; docs/data.md): the shipped 64-beam model BEAMS_SOURCE_MODEL
# (models/kitti-hdl64e, adapted without a label, with its scale.json) as SOURCE_MODEL, adapted to
# the drives of REAL_DRIVES imported at BEAMS beams (REAL_RUN-<BEAMS>beams-data) and evaluated on
# REAL_DRIVE's tracklets and the object frames at BEAMS beams, once per seed (BEAMS_RUN-s<seed>:
# REAL_RUN-<BEAMS>beams-kitti-hdl64e-s<seed>), through real-kitti-rows' targets. Rows (BEAMS_ROWS):
# direct (the model at its scale.json), ptsn (at its PTSN scale on the sparse target), x1 and x2
# (DALI from the model; the labelled source of their retrainings is SOURCE, the 48 synthetic
# Waymo-like frames per seed the model's own training started from, shifted to the target's size),
# control (CONTROL=tracked-st above: the model self-trained on its tracked pseudo labels for x2's
# frames), control + tracked ST, x2 + tracked ST; PPCG ray-casts with the thinned profile
# (REAL_VARS: SENSOR=kitti-<BEAMS>). Then the upper reference, once (REAL_RUN-reference): the direct
# row on the 64-beam sets of REAL_RUN-data, the data directory of `make real-kitti`. Row dense_tst,
# the dense teacher: the model's pseudo labels of the same drives' full scans (DENSE_DATA, every
# beam) at its own scale, kept by track-pseudo over the full scans' registration, and the model
# self-trained on the thinned frames with them (dali self-train --pseudo-from; the thinned
# frames share the full scans' frame ids): the 64-beam model labels what the 16-beam one sees
BEAMS_SOURCE_MODEL ?= models/kitti-hdl64e
BEAMS_RUN    = $(REAL_RUN)$(beams_suffix)-$(notdir $(BEAMS_SOURCE_MODEL))
BEAMS_ROWS  ?= direct ptsn x1 x2 control control_tst x2_tst dense_tst
BEAMS_PAIRS ?= x2:control x2_tst:control_tst dense_tst:control_tst
BEAMS_PSEUDO = iter1/pseudo iter2/pseudo iter1/tracked iter3/tracked baselines/source_x2_budget/tracked \
    $(if $(filter dense_tst,$(BEAMS_ROWS)),dense/tracked)
DENSE_DATA  ?= $(REAL_RUN)-data
# the sub-make's goals and variables that import and register the full scans (every beam), run
# where the rows hold the dense teacher ($(MAKE) stays in the recipes: make -n recurses into it)
DENSE_DATA_GOALS = real-kitti-data $(DENSE_DATA)/target_poses/manifest.json $(call real_vars,$(DENSE_DATA)) BEAMS=64
ifneq ($(DENSE_DATA),$(REAL_DATA))
$(DENSE_DATA)/target/manifest.json $(DENSE_DATA)/target_poses/manifest.json:
	@test -f $@ || { echo "$@ is missing: make real-kitti-beams imports and registers the full scans first" >&2; exit 1; }
endif
$(RUN)/dense/pseudo_low/manifest.json: $(DENSE_DATA)/target/manifest.json
	$(DALI) pseudo-label $(DEVICE_FLAG) --model $(SOURCE_MODEL) --data $(DENSE_DATA)/target --scale-from $(SOURCE_MODEL) --score-min $(TRACK_PSEUDO_MIN) $(PSEUDO_FLAGS) $(EXEC_FLAGS) --out $(@D)
$(RUN)/dense/tracked/manifest.json: $(RUN)/dense/pseudo_low/manifest.json $(DENSE_DATA)/target_poses/manifest.json
	$(DALI) track-pseudo --pseudo $(RUN)/dense/pseudo_low --data $(DENSE_DATA)/target --poses $(DENSE_DATA)/target_poses --out $(@D)
$(RUN)/dense_tst/model/manifest.json: $(RUN)/dense/tracked/manifest.json $(TARGET)/manifest.json
	$(TRAIN_DALI) self-train --init $(SOURCE_MODEL) --data $(TARGET) --pseudo $(RUN)/dense/tracked --pseudo-from $(DENSE_DATA)/target --seed $(SEED) $(ST_BUDGET) $(ST_FLAGS) $(TRAIN_FLAGS) $(DEVICE_FLAG) --out $(@D)
$(RUN)/dense_tst/eval/manifest.json: $(RUN)/dense_tst/model/manifest.json $(TARGET_VAL)/manifest.json
	$(DALI) eval $(DEVICE_FLAG) --model $(RUN)/dense_tst/model --data $(TARGET_VAL) --scale-from $(SOURCE_MODEL) $(EVAL_FLAGS) $(EXEC_FLAGS) --out $(@D)
BEAMS_VARS = SOURCE_MODEL=$(BEAMS_SOURCE_MODEL) CONTROL=tracked-st \
    REAL_ROW_NAMES="$(BEAMS_ROWS)" REAL_PAIRS="$(BEAMS_PAIRS)" REAL_PSEUDO="$(BEAMS_PSEUDO)"
ifneq ($(and $(filter real-kitti-beams models-beams,$(MAKECMDGOALS)),$(filter 64,$(BEAMS))),)
$(error make $(filter real-kitti-beams models-beams,$(MAKECMDGOALS)) needs BEAMS=32 or 16 (64: make real-kitti, make models))
endif
real-kitti-beams: install
	$(MAKE) $(SUBMAKE_FLAGS) real-kitti-data $(REAL_VARS)
	$(if $(filter dense_tst,$(BEAMS_ROWS)),$(MAKE) $(SUBMAKE_FLAGS) $(DENSE_DATA_GOALS))
	@for seed in $(SEEDS); do \
	    $(MAKE) $(SUBMAKE_FLAGS) real-kitti-rows real-kitti-pseudo RUN=$(BEAMS_RUN)-s$$seed SEED=$$seed \
	        $(REAL_VARS) $(BEAMS_VARS) || exit 1; \
	done
	$(MAKE) $(SUBMAKE_FLAGS) real-kitti-rows RUN=$(REAL_RUN)-reference $(call real_vars,$(REAL_RUN)-data) BEAMS=64 \
	    SOURCE_MODEL=$(BEAMS_SOURCE_MODEL) REAL_ROW_NAMES=direct REAL_PAIRS=
.PHONY: real-kitti-beams

# The shipped models (make models; docs/models.md): models/waymo-like-source, the source model of
# the real benchmark's seed MODELS_SEED that the recipe starts from (MODELS_SOURCE), and
# models/kitti-hdl64e, the recipe's model (the REAL_ROWS row MODELS_ROW) adapted to the real
# target without a label, with its test-time scale. Each card (bench/model_card.py) holds the
# model's evaluations: the source on synthetic Waymo-like validation frames; the adapted model
# on the labelled drive, the object frames of the target's drives and of other drives, and the
# repository's test frame (tests/test_models.py reruns that one); with the recipe's mean ± std
# over the seeds of SEEDS (`make models SEEDS="0 1 2"`). Builds what is missing of the
# benchmark's seed MODELS_SEED and the recipe's row on every other seed of SEEDS (resumable like
# it: the same targets as `make real-kitti`), then writes the two directories.
MODELS_SEED   ?= 0
MODELS_ROW    ?= control_tst2
MODELS_SOURCE ?= baselines/source_x2_budget
MODELS_FIXTURE = tests/fixtures/real/kitti/training
models_row = $(filter $(MODELS_ROW):%,$(REAL_ROWS))
recipe_control_st = the equal-budget control (the source trained as long as x2, at its PTSN scale) self-trained on its own pseudo labels (control + ST)
recipe_control_tst = the equal-budget control (the source trained as long as x2, at its PTSN scale) self-trained on its pseudo labels kept by dali track-pseudo over the registered scans (control + tracked ST)
recipe_control_tst2 = the equal-budget control (the source trained as long as x2, at its PTSN scale) self-trained twice on its pseudo labels kept by dali track-pseudo over the registered scans, the second time on the labels of the first self-trained model at its own PTSN scale (control + tracked ST x2)
recipe_x2_st = two DALI iterations then self-training on x2's pseudo labels (x2 + ST)
recipe_x2_tst = two DALI iterations then self-training on x2's pseudo labels kept by dali track-pseudo (x2 + tracked ST)
# the recipe's evaluation directories, relative to a run: on the drive, then on each object set
models_eval_dirs = $(foreach set,drive $(REAL_OBJECT_SETS),$(call real_eval_dir,$(MODELS_ROW),$(set)))
models_evals = $(foreach set,drive $(REAL_OBJECT_SETS),$(set)=$(RUN)/$(call real_eval_dir,$(MODELS_ROW),$(set)))
# the runs of the recipe's seeds, less -s<seed>: the real benchmark's, or at BEAMS the beams task's
models_runs = $(if $(beams_suffix),$(BEAMS_RUN),$(REAL_RUN))
models_recipe = $(foreach set,drive $(REAL_OBJECT_SETS),$(set)=$(subst $(space),$(comma),$(foreach seed,$(SEEDS),$(models_runs)-s$(seed)/$(call real_eval_dir,$(MODELS_ROW),$(set)))))
comma := ,
space := $(subst ,, )
$(REAL_DATA)/fixture/manifest.json: | install
	$(DALI) import kitti $(MODELS_FIXTURE) --crop-fov$(BEAMS_FLAG) --out $(@D)
$(RUN)/fixture/$(MODELS_ROW)/manifest.json: $(RUN)/$(call row_field,$(models_row),3)/manifest.json $(REAL_DATA)/fixture/manifest.json
	$(DALI) eval $(DEVICE_FLAG) --model $(RUN)/$(call row_field,$(models_row),2) --data $(REAL_DATA)/fixture $(subst =, ,$(call row_field,$(models_row),4)) $(EVAL_FLAGS) $(EXEC_FLAGS) --out $(@D)
# (after the gate: a model it refuses leaves the source as well as the model that names it as they were)
models/waymo-like-source/card.json: $(RUN)/$(MODELS_SOURCE)/eval_source/manifest.json $(RUN)/model_gate.json bench/model_card.py models-always
	$(BIN)/python bench/model_card.py --model $(RUN)/$(MODELS_SOURCE)/model --name waymo-like-source \
	    --title "a car detector trained on the calibrated synthetic Waymo-like world" \
	    --summary "A source detector to adapt: trained on $(SOURCE_FRAMES) synthetic frames of the Waymo-like world (dali synth, seed $(SEED)), no real data, with a direction head so that its boxes face the car's way. \`make demo\` and models/kitti-hdl64e's recipe start from it (pillars, CenterPoint head, IoU refinement; Car)." \
	    --eval synthetic_waymo_like_val=$(RUN)/$(MODELS_SOURCE)/eval_source \
	    --limit "Trained on $(SOURCE_FRAMES) frames on a 2-core CPU: where more frames stop helping was not measured." \
	    --out $(@D)
# the other seeds' evaluations of the recipe that exist: their card line follows them
models_recipe_done = $(wildcard $(foreach seed,$(SEEDS),$(foreach dir,$(models_eval_dirs),$(models_runs)-s$(seed)/$(dir)/manifest.json)))
# the gate (bench/model_gate.py): the rebuilt model against the shipped models/kitti-hdl64e on
# every developer set (the drive's tracklets, the object sets), paired over their frames; a fall
# of AP_3D@0.7 beyond the noise on any set stops make models before anything is replaced
# (MODEL_GATE_FLAGS=--report-only: replace it anyway, the card still shows the comparison)
# At BEAMS the model replaced is models/kitti-<BEAMS>beam, or before the first one ships, direct
# transfer: BEAMS_SOURCE_MODEL at its own scale on the same thinned frames.
MODEL_GATE_FLAGS ?=
models_gate_sets = $(foreach set,drive $(REAL_OBJECT_SETS),--set $(set)=$(call real_truth,$(set)))
models_scale_from = $(lastword $(subst =, ,$(call row_field,$(models_row),4)))
SPARSE_MODEL = models/kitti-$(BEAMS)beam
models_shipped = $(if $(beams_suffix),$(if $(wildcard $(SPARSE_MODEL)/model.pt),$(SPARSE_MODEL),$(BEAMS_SOURCE_MODEL)),models/kitti-hdl64e)
models_gate_note = $(if $(and $(beams_suffix),$(filter $(BEAMS_SOURCE_MODEL),$(models_shipped))),--note "No $(BEAMS)-beam model shipped before: the model it replaces is direct transfer$(comma) $(BEAMS_SOURCE_MODEL) at its own scale on the same $(BEAMS)-beam frames.")
$(RUN)/model_gate.json: bench/model_gate.py $(foreach dir,$(models_eval_dirs),$(RUN)/$(dir)/manifest.json)
	$(BIN)/python bench/model_gate.py --shipped $(models_shipped) $(models_gate_note) \
	    --candidate $(RUN)/$(call row_field,$(models_row),2) --candidate-scale-from $(models_scale_from) \
	    $(models_gate_sets) --work $(RUN)/model_gate --out $@ $(MODEL_GATE_FLAGS)
# an adapted model's card: what it needs, and the arguments every adapted model's card has
models_card_inputs = bench/model_card.py models-always $(foreach dir,$(models_eval_dirs),$(RUN)/$(dir)/manifest.json) \
    $(RUN)/fixture/$(MODELS_ROW)/manifest.json $(models_recipe_done) $(RUN)/model_gate.json
models_card = $(BIN)/python bench/model_card.py --model $(RUN)/$(call row_field,$(models_row),2) \
    --scale-from $(models_scale_from) --gate $(RUN)/model_gate.json --fixture-eval $(RUN)/fixture/$(MODELS_ROW) \
    $(foreach pair,$(models_evals),--eval $(pair)) $(foreach pair,$(models_recipe),--recipe $(pair)) --out $(@D)
# models/kitti-hdl64e's card: what it is for (both ways it is made: make models, make models-round)
kitti_hdl64e_card = --name kitti-hdl64e --title "a KITTI HDL-64E car detector no real label went into" \
    --limit "Other drives' frames are harder than the adapted drives': see the accuracy table and docs/RESULTS.md."
kitti_hdl64e_use = Finds cars in KITTI's HDL-64E LiDAR scans (camera field of view, LiDAR frame, scaled by its scale.json): \`dali detect\` on your own scans, or a start for adapting further.
models/kitti-hdl64e/card.json: $(models_card_inputs)
	$(models_card) $(kitti_hdl64e_card) \
	    --summary "$(kitti_hdl64e_use) It is models/waymo-like-source adapted by $(recipe_$(MODELS_ROW)) to $(words $(REAL_DRIVES)) unlabeled real KITTI drives ($(REAL_DRIVE_NAMES)) without any real label."
# The sparse models (MODELS_BEAMS, after kitti-hdl64e, from it): models/kitti-<N>beam, the row
# SPARSE_MODELS_ROW of `make real-kitti-beams BEAMS=N` (its runs, resumable the same way) on seed
# MODELS_SEED, with the row over SEEDS on its card and the gate against the model it replaces
MODELS_BEAMS      ?= 16 32
SPARSE_MODELS_ROW ?= dense_tst
recipe_dense_tst = the dense teacher: its pseudo labels of the same drives' full 64-beam scans, kept by dali track-pseudo over their registration, trained into it on the scans thinned to $(BEAMS) beams (dali self-train --pseudo-from)
$(SPARSE_MODEL)/card.json: $(models_card_inputs)
	$(models_card) --name kitti-$(BEAMS)beam --title "a car detector for KITTI's scans at $(BEAMS) beams, no real label went into" \
	    --summary "Finds cars in $(BEAMS)-beam LiDAR scans of KITTI's kind (the HDL-64E's thinned to $(BEAMS) beams by dali import --beams $(BEAMS), camera field of view, LiDAR frame, scaled by its scale.json): \`dali detect\` on such scans. It is $(BEAMS_SOURCE_MODEL) adapted by $(recipe_$(MODELS_ROW)) on $(words $(REAL_DRIVES)) unlabeled real KITTI drives ($(REAL_DRIVE_NAMES)) without any real label." \
	    --limit "Thinned HDL-64E scans stand in for a $(BEAMS)-beam sensor: a real one's beam pattern, mount and intensities differ; not measured on one."
models-beams: MODELS_ROW = $(SPARSE_MODELS_ROW)
models-beams: install
	$(MAKE) $(SUBMAKE_FLAGS) real-kitti-data $(REAL_DATA)/fixture/manifest.json $(REAL_VARS)
	$(if $(filter dense_tst,$(SPARSE_MODELS_ROW)),$(MAKE) $(SUBMAKE_FLAGS) $(DENSE_DATA_GOALS))
	@for seed in $(filter-out $(MODELS_SEED),$(SEEDS)) $(MODELS_SEED); do \
	    $(MAKE) $(SUBMAKE_FLAGS) $(addprefix $(BEAMS_RUN)-s$$seed/,$(addsuffix /manifest.json,$(models_eval_dirs))) \
	        RUN=$(BEAMS_RUN)-s$$seed SEED=$$seed MODELS_ROW=$(MODELS_ROW) $(REAL_VARS) $(BEAMS_VARS) || exit 1; \
	done
	$(MAKE) $(SUBMAKE_FLAGS) $(SPARSE_MODEL)/card.json RUN=$(BEAMS_RUN)-s$(MODELS_SEED) SEED=$(MODELS_SEED) \
	    MODELS_ROW=$(MODELS_ROW) $(REAL_VARS) $(BEAMS_VARS)
models: install
	$(MAKE) $(SUBMAKE_FLAGS) real-kitti-data $(REAL_DATA)/fixture/manifest.json $(REAL_VARS)
	@for seed in $(filter-out $(MODELS_SEED),$(SEEDS)); do \
	    $(MAKE) $(SUBMAKE_FLAGS) $(addprefix $(REAL_RUN)-s$$seed/,$(addsuffix /manifest.json,$(models_eval_dirs))) \
	        RUN=$(REAL_RUN)-s$$seed SEED=$$seed $(REAL_VARS) || exit 1; \
	done
	$(MAKE) $(SUBMAKE_FLAGS) models/waymo-like-source/card.json models/kitti-hdl64e/card.json \
	    RUN=$(REAL_RUN)-s$(MODELS_SEED) SEED=$(MODELS_SEED) $(REAL_VARS)
	@for beams in $(MODELS_BEAMS); do \
	    $(MAKE) $(SUBMAKE_FLAGS) models-beams BEAMS=$$beams MODELS_ROW=$(SPARSE_MODELS_ROW) || exit 1; \
	done
# models/kitti-hdl64e adapted one round further (make models-round; docs/models.md): the shipped
# model sweeps its own PTSN scale on REAL_DRIVES' target, pseudo-labels it there (low cut), dali
# track-pseudo keeps the labels over the registered scans, and it self-trains on them from itself
# (seed MODELS_SEED, the tracked rows' budget), in ROUND_RUN, resumable like the rows; then the
# gate against the shipped model on every developer set, and only if it passes the card replaces
# it (the recipe line: control_tst2's evaluations of REAL_RUN's seeds, where they exist). A
# later make models-round starts from the model it shipped: each run is one more round.
ROUND_RUN  ?= $(REAL_RUN)-round
ROUND_BASE  = models/kitti-hdl64e
round_evals = $(foreach set,drive $(REAL_OBJECT_SETS),--eval $(set)=$(ROUND_RUN)/eval/$(set))
round_recipe = $(foreach set,drive $(REAL_OBJECT_SETS),$(if $(call round_recipe_dirs,$(set)),--recipe $(set)=$(subst $(space),$(comma),$(strip $(call round_recipe_dirs,$(set))))))
round_recipe_dirs = $(patsubst %/metrics.json,%,$(wildcard $(foreach seed,$(SEEDS),$(REAL_RUN)-s$(seed)/$(call real_eval_dir,control_tst2,$(1))/metrics.json)))
$(ROUND_RUN)/ptsn/manifest.json: $(ROUND_BASE)/model.pt $(TARGET)/manifest.json
	$(DALI) ptsn-sweep $(DEVICE_FLAG) --model $(ROUND_BASE) --data $(TARGET) --target-size $(EXPECTED) --score-min $(SCORE_MIN) --seed $(SEED) --out $(@D)
$(ROUND_RUN)/pseudo_low/manifest.json: $(ROUND_RUN)/ptsn/manifest.json
	$(DALI) pseudo-label $(DEVICE_FLAG) --model $(ROUND_BASE) --data $(TARGET) --scale-from $(ROUND_RUN)/ptsn --score-min $(TRACK_PSEUDO_MIN) $(PSEUDO_FLAGS) $(EXEC_FLAGS) --out $(@D)
$(ROUND_RUN)/tracked/manifest.json: $(ROUND_RUN)/pseudo_low/manifest.json $(TARGET_POSES)/manifest.json
	$(DALI) track-pseudo --pseudo $(ROUND_RUN)/pseudo_low --data $(TARGET) --poses $(TARGET_POSES) --out $(@D)
$(ROUND_RUN)/model/manifest.json: $(ROUND_RUN)/tracked/manifest.json
	$(TRAIN_DALI) self-train --init $(ROUND_BASE) --data $(TARGET) --pseudo $(ROUND_RUN)/tracked --seed $(SEED) $(ST_BUDGET) $(ST_FLAGS) $(TRAIN_FLAGS) $(DEVICE_FLAG) --out $(@D)
# the round's model evaluated into (1) on the frame set (2)
define ROUND_EVAL
$(ROUND_RUN)/$(1)/manifest.json: $(ROUND_RUN)/model/manifest.json $(2)/manifest.json
	$(DALI) eval $(DEVICE_FLAG) --model $(ROUND_RUN)/model --data $(2) --scale-from $(ROUND_RUN)/ptsn $(EVAL_FLAGS) $(EXEC_FLAGS) --out $$(@D)
endef
$(eval $(call ROUND_EVAL,fixture,$(REAL_DATA)/fixture))
$(foreach set,drive $(REAL_OBJECT_SETS),$(eval $(call ROUND_EVAL,eval/$(set),$(call real_truth,$(set)))))
$(ROUND_RUN)/model_gate.json: bench/model_gate.py $(ROUND_RUN)/model/manifest.json
	$(BIN)/python bench/model_gate.py --shipped $(ROUND_BASE) --candidate $(ROUND_RUN)/model --candidate-scale-from $(ROUND_RUN)/ptsn \
	    $(models_gate_sets) --work $(ROUND_RUN)/model_gate --out $@ $(MODEL_GATE_FLAGS)
models-round: install
	$(MAKE) $(SUBMAKE_FLAGS) real-kitti-data $(REAL_DATA)/fixture/manifest.json $(REAL_VARS)
	$(MAKE) $(SUBMAKE_FLAGS) $(ROUND_RUN)/model_gate.json $(ROUND_RUN)/fixture/manifest.json \
	    $(foreach set,drive $(REAL_OBJECT_SETS),$(ROUND_RUN)/eval/$(set)/manifest.json) SEED=$(MODELS_SEED) $(REAL_VARS)
	$(BIN)/python bench/model_card.py --model $(ROUND_RUN)/model --scale-from $(ROUND_RUN)/ptsn \
	    --gate $(ROUND_RUN)/model_gate.json --fixture-eval $(ROUND_RUN)/fixture $(round_evals) $(round_recipe) \
	    --recipe-note "control_tst2 rebuilt from the source on each seed; this model is the shipped one's round, not one of them" \
	    $(kitti_hdl64e_card) \
	    --summary "$(kitti_hdl64e_use) It is the previous models/kitti-hdl64e adapted one round further by tracked self-training on its own labels at its own PTSN scale (make models-round), on $(words $(REAL_DRIVES)) unlabeled real KITTI drives ($(REAL_DRIVE_NAMES)) without any real label: models/waymo-like-source adapted by $(recipe_control_tst2)." \
	    --out $(ROUND_BASE)
.PHONY: models-round

# the cards are committed: with every run target secondary (.SECONDARY below) a card newer than
# bench/model_card.py would pass for up to date on a clone without the runs, so they are always
# rewritten (a second or two) after make has built what they need
models-always:
.PHONY: models models-beams models-always

report: | install
	$(DALI) report $(RUN)

# the source recipe of the real benchmark and of models/waymo-like-source: 48 synthetic
# Waymo-like frames, 6 epochs (x2's budget for the control)
DEMO_FRAMES ?= 48
DEMO_EPOCHS ?= 6
# the demo: one DALI iteration from the shipped source (models/waymo-like-source, no pretraining)
# on DEMO_TARGET_FRAMES synthetic KITTI-like target frames, and the rows it is read against
# (source only, PTSN only), then `dali report`; a few minutes on a 2-core VM (README.md). Its
# model stages run on DEMO_THREADS torch threads, not on every core, so that its figures do not
# depend on the machine's core count (empty: every core, faster on a larger machine)
DEMO_RUN ?= runs/demo
DEMO_TARGET_FRAMES ?= 48
DEMO_RETRAIN_EPOCHS ?= 4
DEMO_THREADS ?= 2
demo: install
	$(MAKE) $(SUBMAKE_FLAGS) iter1 RUN=$(DEMO_RUN) SOURCE_MODEL=models/waymo-like-source \
	    FRAMES=$(DEMO_TARGET_FRAMES) EPOCHS=$(DEMO_RETRAIN_EPOCHS) LIBRARY_MODELS=8 THREADS=$(DEMO_THREADS)
	$(DALI) report $(DEMO_RUN)
	@echo
	@echo "This was the demo ($(DEMO_RUN)): DALI's first iteration from models/waymo-like-source."
	@echo "Your own scans: dali detect SCANS --model models/kitti-hdl64e --out OUT (dali: .venv/bin/dali)"
	@echo "The full synthetic benchmark: make experiment"

# the tiny run: one DALI iteration on TINY_FRAMES target frames from a source of TINY_SOURCE_FRAMES,
# enough training that PTSN finds a scale, pseudo-label keeps boxes at the default score cut and
# RC and CF replace them; then what each step kept. Every model stage on TINY_THREADS torch threads: a model and its boxes are
# byte-reproducible for a fixed thread count and CPU kernel path only (tests/test_repeat_run.py:
# two runs, one result). TINY_EPOCHS=12, not 4: at 4 the source's boxes all scored 0.3-0.4, on
# the cut, and another CPU's rounding moved the pseudo boxes from 175 to 237; at 12 the counts
# stay within 4 % over the kernel paths (docs/RESULTS.md "Numerical stability"; the README's
# ranges, tests/test_readme.py). TINY_SOURCE_FRAMES=32, not 16: from 16 frames the source's size
# bias, and so ŝ, moved by 0.028 over the kernel paths (a training seed's worth), from 32 by 0.009
TINY_RUN    ?= runs/tiny
TINY_FRAMES ?= 16
TINY_SOURCE_FRAMES ?= 32
TINY_EPOCHS ?= 12
TINY_THREADS ?= 1
tiny: install
	$(MAKE) $(SUBMAKE_FLAGS) iter1 RUN=$(TINY_RUN) FRAMES=$(TINY_FRAMES) SOURCE_FRAMES=$(TINY_SOURCE_FRAMES) VAL_FRAMES=8 \
	    EPOCHS=$(TINY_EPOCHS) LIBRARY_MODELS=8 THREADS=$(TINY_THREADS)
	@$(BIN)/python bench/tools/run_counts.py $(TINY_RUN)
	@echo "next: dali report $(TINY_RUN)"
.PHONY: tiny

# the full synthetic benchmark (docs/RESULTS.md): 600 frames per training set, 200 validation frames,
# 4 epochs of pretraining (2,400 frames seen) and 2 x 2 of retraining (source + PPCG 1:1, 1,200
# frames an epoch: 1 epoch in iteration 1, 3 in iteration 2; x1 long the 4 in one), once per seed of SEEDS, each its own resumable RUN (runs/experiment-s<seed>: data seeds and
# training seeds follow SEED), the equal-budget controls included; then `dali report` of every
# seed and the mean ± std over the seeds (runs/experiment-report), with x1, x2 and x1 long paired
# against their equal-budget controls. EXPERIMENT_GOALS (every seed) adds e.g. iter2-st; the baselines and
# ablations (SN, ROS, oracle on the pretraining budget, RC only, CF only) run on the first seed of
# SEEDS only (EXPERIMENT_FIRST_SEED_GOALS): that keeps a further seed at ~2 h.
# SOURCE_SENSOR=nuscenes gives the paper's second task (runs/experiment-nuscenes-s<seed>), with
# x2 + ST on every seed: the paper's self-training step (‡) belongs to that task.
SEEDS ?= 0
EXPERIMENT_FRAMES ?= 600
EXPERIMENT_VAL_FRAMES ?= 200
EXPERIMENT_EPOCHS ?= 4
EXPERIMENT_RETRAIN_EPOCHS ?= 2
EXPERIMENT_GOALS ?= iter2 x1-long controls cross-domain compare $(if $(filter nuscenes,$(SOURCE_SENSOR)),iter2-st)
EXPERIMENT_FIRST_SEED_GOALS ?= baselines
EXPERIMENT_PREFIX = runs/experiment$(if $(filter-out waymo,$(SOURCE_SENSOR)),-$(SOURCE_SENSOR))
# EXPERIMENT_LANES=2: each seed's data first, then its training rows as two make processes side by
# side, each pinned (taskset) to one half of the machine's cores, so that every stage in a lane
# (training, inference, ray casting) sees only its own cores and no two stages fight over one:
# lane 1 the DALI chain and the rows built on it (and SN, ROS), lane 2 the controls and the
# pretraining-budget oracle (no stage in both lanes, tests/test_makefile_lanes.py);
# then the rest (forgetting, compare, KITTI protocol, reports) on every core. Needs Linux's taskset
# and the whole machine. docs/RESULTS.md has its time for one seed with every row.
EXPERIMENT_LANES ?= 1
LANE_DATA_ONLY = controls controls-x1 controls-x2
# (first seed, 600 frames: lane 1 19,200 training frames and most of the inference, lane 2 20,400)
lane_1_goals = $(filter-out $(LANE_DATA_ONLY) baselines compare cross-domain,$(1)) \
    $(if $(filter baselines,$(1)),ablation-rc ablation-cf baseline-ros baseline-sn)
lane_2_goals = $(filter $(LANE_DATA_ONLY),$(1)) $(if $(filter baselines,$(1)),baseline-oracle)
experiment: install
	@case "$(EXPERIMENT_LANES)" in 1|2) ;; *) echo "EXPERIMENT_LANES must be 1 or 2, got '$(EXPERIMENT_LANES)'" >&2; exit 1;; esac
	@if [ "$(EXPERIMENT_LANES)" = 2 ] && { [ $$(nproc) -lt 2 ] || [ $$(nproc) != $$(nproc --all) ]; }; then \
	    echo "EXPERIMENT_LANES=2 pins its lanes to cores 0..N-1: it needs the whole machine and at least 2 cores (this process may use $$(nproc) of $$(nproc --all))" >&2; exit 1; fi
	@first=$(firstword $(SEEDS)); for seed in $(SEEDS); do \
	    goals="$(EXPERIMENT_GOALS)"; lane1="$(call lane_1_goals,$(EXPERIMENT_GOALS))"; lane2="$(call lane_2_goals,$(EXPERIMENT_GOALS))"; \
	    if [ $$seed = $$first ]; then goals="$$goals $(EXPERIMENT_FIRST_SEED_GOALS)"; \
	        lane1="$(call lane_1_goals,$(EXPERIMENT_GOALS) $(EXPERIMENT_FIRST_SEED_GOALS))"; \
	        lane2="$(call lane_2_goals,$(EXPERIMENT_GOALS) $(EXPERIMENT_FIRST_SEED_GOALS))"; fi; \
	    vars="RUN=$(EXPERIMENT_PREFIX)-s$$seed SEED=$$seed SOURCE_SENSOR=$(SOURCE_SENSOR) FRAMES=$(EXPERIMENT_FRAMES) \
	        VAL_FRAMES=$(EXPERIMENT_VAL_FRAMES) EPOCHS=$(EXPERIMENT_EPOCHS) RETRAIN_EPOCHS=$(EXPERIMENT_RETRAIN_EPOCHS)"; \
	    if [ "$(EXPERIMENT_LANES)" = 2 ]; then \
	        n=$$(nproc); half=$$((n / 2)); \
	        $(MAKE) $(SUBMAKE_FLAGS) data $$vars || exit 1; \
	        echo "seed $$seed: lane 1 (cores 0-$$((half - 1))): $$lane1; lane 2 (cores $$half-$$((n - 1))): $$lane2"; \
	        taskset -c 0-$$((half - 1)) $(MAKE) $(SUBMAKE_FLAGS) $$lane1 $$vars & one=$$!; \
	        taskset -c $$half-$$((n - 1)) $(MAKE) $(SUBMAKE_FLAGS) $$lane2 $$vars & two=$$!; \
	        wait $$one || { wait $$two; exit 1; }; wait $$two || exit 1; \
	    fi; \
	    $(MAKE) $(SUBMAKE_FLAGS) $$goals kitti-protocol $$vars || exit 1; \
	done
	for seed in $(SEEDS); do $(DALI) report $(EXPERIMENT_PREFIX)-s$$seed > /dev/null || exit 1; done
	$(DALI) report $(foreach seed,$(SEEDS),$(EXPERIMENT_PREFIX)-s$(seed)) --out $(EXPERIMENT_PREFIX)-report

.PHONY: data iter0 report experiment
# keep every artifact of a pattern chain (e.g. baselines/*/ptsn): make must not delete manifests
.SECONDARY:
