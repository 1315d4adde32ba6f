# cdmp_ros — the two commands: `make demo` and `make test` (see README).
SHELL := /bin/bash
PYTHON ?= python3.11
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

# Network rule: ROS processes started from here discover peers on localhost only,
# on a private domain id.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export ROS_DOMAIN_ID ?= 73
export AMENT_PREFIX_PATH := $(abspath $(VENV))
export PYTHONUNBUFFERED := 1
export MPLBACKEND := Agg

OUT ?= out/demo
PYTEST_ARGS ?=

.PHONY: demo test venv lint bench clean

$(STAMP): requirements.txt requirements-dev.txt setup.py
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip==26.3
	$(PY) -m pip install --quiet -r requirements-dev.txt
	$(PY) -m pip install --quiet --no-deps -e .
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/cdmp demo --out $(OUT)
	$(VENV)/bin/cdmp demo --kind promp --out $(OUT)_promp
	$(VENV)/bin/cdmp demo --kind dual --out $(OUT)_dual

test: $(STAMP)
	$(PY) -m pytest test $(PYTEST_ARGS)

lint: $(STAMP)
	$(PY) -m flake8 cdmp_ros test benchmarks scripts launch setup.py

bench: $(STAMP)
	$(PY) -m pytest test -m benchmark -p no:cacheprovider $(PYTEST_ARGS)

clean:
	rm -rf build install log out .pytest_cache
