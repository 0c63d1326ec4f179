# Two entry points: `make demo` (sample data end to end) and `make test` (the CI suite).
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO_OUT ?= demo_out

.PHONY: demo test test-all lint clean

$(STAMP): requirements.txt setup.py setup.cfg
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements.txt
	$(PY) -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e .
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/cusfm demo --out $(DEMO_OUT)

test: $(STAMP)
	$(PY) -m pytest -q -m "not slow and not gpu" -p no:cacheprovider test

test-all: $(STAMP)
	$(PY) -m pytest -q -m "not gpu" test

lint: $(STAMP)
	$(VENV)/bin/ruff check cusfm_ros test bench

clean:
	rm -rf $(VENV) $(DEMO_OUT) build *.egg-info
