# Two commands: `make demo` (set up .venv, run the main job) and `make test` (set up, run every test).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export ROS_LOG_DIR ?= $(CURDIR)/.venv/ros_log

.PHONY: all demo test bench lint clean

all: test

$(STAMP): requirements.txt setup.py setup.cfg package.xml tools/build_tf2_msgs.py
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check --upgrade pip
	$(PY) -m pip install -q --disable-pip-version-check -r requirements.txt
	$(PY) -m pip install -q --disable-pip-version-check --no-deps -e .
	# tf2_msgs (for /tf_static) has no wheel: built from its one-line interface with the
	# wheels' rosidl generators (tools/build_tf2_msgs.py; ~1 s with gcc, g++). Without it the
	# node works and says once that TF is not published.
	$(PY) -c 'import tf2_msgs.msg' 2>/dev/null || $(PY) tools/build_tf2_msgs.py \
	  "$$($(PY) -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')" \
	  --build-dir $(VENV)/build/tf2_msgs >$(VENV)/tf2_msgs.log 2>&1 || \
	  echo 'WARNING: tf2_msgs not built ($(VENV)/tf2_msgs.log): no /tf_static (README, TF)'
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m armcal_ros.cli demo

# The tests without live ROS nodes on both cores (pytest-xdist, a module per worker, BLAS on
# one thread each), then the ones that run nodes over DDS one at a time (each replays a bag in
# real time and needs the cores it was sized for); the target fails if either part does.  The
# two runs share one folder for the recordings both use (test/conftest.py, SHARED_ENV).
test: $(STAMP)
	shared=$$(mktemp -d); export ARMCAL_TEST_SHARED=$$shared; \
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 \
	  $(PY) -m pytest -ra -n 2 --dist loadfile -m 'not ros' test; a=$$?; \
	$(PY) -m pytest -ra -m ros test; b=$$?; \
	rm -rf $$shared; test $$a -eq 0 && test $$b -eq 0

# Every benchmark script; each prints its table and rewrites its section of docs/BENCHMARKS.md.
bench: $(STAMP)
	$(PY) bench/solver.py
	$(PY) bench/auto_search.py
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
	$(PY) bench/changes_images.py
	$(PY) bench/node_changes.py
	$(PY) bench/realism.py
	$(PY) bench/realism.py --all-effects
	$(PY) bench/realism_effects.py
	$(PY) bench/arm_effects.py
	$(PY) bench/latency.py
	$(PY) bench/change_split.py
	$(PY) bench/real_data.py

clean:
	rm -rf $(VENV) build install log *.egg-info
