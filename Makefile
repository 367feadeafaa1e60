# The two commands of the README: `make demo` and `make test`. Both set everything up first.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
# Discovery stays on loopback; the Fast DDS profile enlarges shared memory for image topics.
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
export FASTRTPS_DEFAULT_PROFILES_FILE ?= $(CURDIR)/config/fastdds_profile.xml
export PYTHONUNBUFFERED := 1

.PHONY: setup demo test test-slow lint colcon clean

setup:
	@bash scripts/setup.sh

demo: setup
	$(PY) -m pssnet_ros.demo --out demo_output

# pytest exits 5 when it collects no test: that is a failure here, like any other non-zero exit.
test: setup
	$(VENV)/bin/ruff check pssnet_core pssnet_ros test benchmarks scripts
	$(VENV)/bin/pytest -q

test-slow: setup
	$(VENV)/bin/pytest -q -m slow

# Builds both packages with colcon, as on a regular ROS 2 workspace (install/ appears at the root).
colcon: setup
	source $(VENV)/bin/activate && CMAKE_PREFIX_PATH=$(CURDIR)/$(VENV) AMENT_PREFIX_PATH=$(CURDIR)/$(VENV) \
	  colcon build --base-paths . msg_schemas --cmake-args -G Ninja -DPython3_EXECUTABLE=$(CURDIR)/$(PY) -DBUILD_TESTING=OFF

clean:
	rm -rf build install log
