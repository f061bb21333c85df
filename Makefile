# Two commands: `make demo` (set up .venv, run the main job) and `make test` (set up, run every test).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export ROS_LOG_DIR ?= $(CURDIR)/.venv/ros_log

.PHONY: all demo test bench lint clean

all: test

$(STAMP): requirements.txt setup.py setup.cfg package.xml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check --upgrade pip
	$(PY) -m pip install -q --disable-pip-version-check -r requirements.txt
	$(PY) -m pip install -q --disable-pip-version-check --no-deps -e .
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m armcal_ros.cli demo

test: $(STAMP)
	$(PY) -m pytest -ra test

# Every benchmark script; each prints its table and rewrites its section of docs/BENCHMARKS.md.
bench: $(STAMP)
	$(PY) bench/solver.py
	$(PY) bench/accuracy.py
	$(PY) bench/scaling.py
	$(PY) bench/bias.py
	$(PY) bench/pipeline.py
	$(PY) bench/bag_accuracy.py
	$(PY) bench/cells.py
	$(PY) bench/node.py
	$(PY) bench/uncertainty.py
	$(PY) bench/hyperparameters.py
	$(PY) bench/changes.py
	$(PY) bench/realism.py
	$(PY) bench/real_data.py

clean:
	rm -rf $(VENV) build install log *.egg-info
