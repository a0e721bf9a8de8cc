# edgeloc-testbed. `make scenario` and `make test` set everything up themselves.
# A second `make setup` only checks a stamp and returns.

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.stamp-setup
SCENARIO ?= scenarios/default.yaml

# ROS 2 Jazzy: a sourced apt install wins; otherwise the PyPI `ros-jazzy-*` wheels.
ROS_WHEELS := ros-jazzy-rclpy[fastrtps] ros-jazzy-std-msgs ros-jazzy-geometry-msgs \
              ros-jazzy-nav-msgs ros-jazzy-sensor-msgs ros-jazzy-builtin-interfaces
HAVE_APT_ROS := $(shell [ "$$ROS_DISTRO" = jazzy ] && $(PYTHON) -c 'import rclpy' 2>/dev/null && echo yes)

.PHONY: setup scenario test smoke bench lint clean help model

help:
	@echo "make scenario   set up (first time) and run $(SCENARIO)"
	@echo "make test       set up (first time) and run the tests (needs root for namespaces)"
	@echo "make smoke      run the smoke scenario"
	@echo "make bench      print benchmark figures"
	@echo "make model      retrain the localization DNN (deterministic; weights are committed)"
	@echo "make lint       ruff"
	@echo "make clean      remove leftovers of crashed runs, caches"

# The interfaces build checks its own source hash, so it runs every time (0.1 s when current).
setup: $(STAMP)
	@$(BIN)/python -m nodes.ros_build --prefix $(VENV) -q

$(STAMP): pyproject.toml Makefile
	@test -x $(BIN)/python || $(PYTHON) -m venv $(if $(HAVE_APT_ROS),--system-site-packages) $(VENV)
	$(BIN)/pip install --disable-pip-version-check -q -e '.[test]'
ifeq ($(HAVE_APT_ROS),yes)
	@echo "using the sourced ROS 2 Jazzy ($(shell $(PYTHON) -c 'import rclpy,os;print(os.path.dirname(rclpy.__file__))'))"
else
	$(BIN)/pip install --disable-pip-version-check -q $(ROS_WHEELS)
endif
	$(BIN)/pip install --disable-pip-version-check -q torch
	@$(BIN)/python -c 'import rclpy, torch, pyroute2, mcap; print("setup ok: torch", torch.__version__)'
	@touch $@

scenario: setup
	$(BIN)/testbed run $(SCENARIO)

smoke: setup
	$(BIN)/testbed run scenarios/smoke.yaml

test: setup
	$(BIN)/python -m pytest -q

bench: setup
	$(BIN)/python tests/bench/run.py $(BENCH)

model: setup
	$(BIN)/python -m nodes.edgeloc.train --out nodes/edgeloc/weights

lint: setup
	$(BIN)/ruff check testbed netem nodes reports tests
	$(BIN)/ruff format --check testbed netem nodes reports tests

clean:
	-@test -x $(BIN)/testbed && $(BIN)/testbed clean
	rm -rf .pytest_cache .ruff_cache build *.egg-info
