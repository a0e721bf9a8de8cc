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

# Debian packages for the tc-backend VM tests (tests/vm/), needed only where the host kernel has
# no sch_netem. INITRD=No: the kernel is only booted by qemu, so no initramfs/grub update.
VM_DEBS := qemu-system-x86 linux-image-amd64 busybox-static
.PHONY: sysdeps test-netem chromium tshark iperf3 ray report-screenshot

help:
	@echo "make scenario   set up (first time) and run $(SCENARIO)"
	@echo "make test       set up (first time) and run the tests (needs root for namespaces)"
	@echo "make test-netem the tc backend with real netem (in a qemu VM if this kernel has none)"
	@echo "make smoke      run the smoke scenario"
	@echo "make bench      print benchmark figures (includes a 10-minute soak)"
	@echo "make report-screenshot  render a report in headless Chromium -> report-screenshot.png"
	@echo "make model      retrain the localization DNN (deterministic; weights are committed)"
	@echo "make lint       ruff, and the import layers (lint-imports)"
	@echo "make clean      remove leftovers of crashed runs, caches"

# The interfaces build checks its own source hash, so it runs every time (0.1 s when current).
setup: $(STAMP)
	@$(BIN)/python -m nodes.ros.build --prefix $(VENV) -q

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

# Prints its own wall time, set-up included: the first run on a fresh machine installs
# everything, a second one only checks the stamp.
scenario:
	@t0=$$(date +%s); $(MAKE) --no-print-directory setup && $(BIN)/testbed run $(SCENARIO); \
	rc=$$?; echo "make scenario: $$(( $$(date +%s) - t0 )) s wall, set-up included (exit $$rc)"; \
	exit $$rc

smoke: setup
	$(BIN)/testbed run scenarios/smoke.yaml

# Three passes. First, one at a time, the tests that need the machine to themselves: rate and
# timing measurements, the VM, Ray clusters and whatever compares the whole host before and
# after (conftest sorts the measurements first, onto a fresh machine). Then, two at a time, the
# other tests with namespaces (root), ROS, whole scenarios (e2e) or long replays (slow): each
# has its own run id, namespaces, state dir and ROS domain. Last, the unit tests on every core.
# Every pass always runs; a failure in any fails.
ALONE_TESTS  := alone or measure or netem_vm
SHARED_TESTS := (root or ros or e2e or slow) and not ($(ALONE_TESTS))
UNIT_TESTS   := not (root or ros or e2e or slow or $(ALONE_TESTS))
test: setup sysdeps chromium tshark iperf3 ray
	@rc=0; \
	$(BIN)/python -m pytest -q -m "$(ALONE_TESTS)" || rc=$$?; \
	$(BIN)/python -m pytest -q -n 2 -m "$(SHARED_TESTS)" || rc=$$?; \
	$(BIN)/python -m pytest -q -n auto -m "$(UNIT_TESTS)" || rc=$$?; \
	exit $$rc

# Installs $(VM_DEBS) when this kernel lacks sch_netem and they are missing (root only).
sysdeps: setup
	@if $(BIN)/python -c 'import sys; from testbed.check import netem_available as n; sys.exit(0 if n() else 1)' 2>/dev/null; then exit 0; fi; \
	missing=$$(for p in $(VM_DEBS); do dpkg-query -W -f='$${db:Status-Status}' $$p 2>/dev/null | grep -qx installed || echo $$p; done); \
	if [ -z "$$missing" ]; then exit 0; fi; \
	if [ "$$(id -u)" != 0 ]; then echo "sysdeps: the tc-backend VM tests need" $$missing "- run 'sudo make sysdeps'"; exit 0; fi; \
	echo "sysdeps: installing" $$missing "from Debian (for the tc-backend test VM)"; \
	apt-get update -q && DEBIAN_FRONTEND=noninteractive INITRD=No apt-get install -y -q --no-install-recommends $$missing

# tc backend with real netem: on this host if its kernel has sch_netem, else in a qemu VM.
test-netem: setup sysdeps
	$(BIN)/python -m pytest -q tests/test_tc_root.py tests/vm/guest_checks.py tests/test_netem_vm_root.py

# $(call debian_tool,NAME,WHAT SKIPS WITHOUT IT): Debian's package NAME (also the command's
# name) installed when missing, by root; anyone else is told what will skip.
debian_tool = command -v $(1) >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] \
	  && apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q $(1) \
	  || echo "$(1): not installed (needs root: sudo make $(1)); $(2)"; }

# Debian's headless Chromium: the report test renders report.html in it (root installs it; a
# user without root gets the test's skip reason instead).
chromium:
	@$(call debian_tool,chromium,the report browser test will skip)

# Debian's tshark: the GTP-U tests dissect what crosses N3 with Wireshark's own dissector (root
# installs it; a user without root gets those tests' skip reason instead).
tshark:
	@$(call debian_tool,tshark,the GTP-U dissection tests will skip)

# Debian's iperf3: the cross-traffic tests compare our generator (nodes/traffic) with it (root
# installs it; a user without root gets those tests' skip reason instead).
iperf3:
	@$(call debian_tool,iperf3,the iperf3 comparisons of the traffic tests will skip)

# Ray, the optional extra of `testbed sweep --engine ray`: installed for its tests only.
ray: setup
	@$(BIN)/python -c 'import ray' 2>/dev/null || $(BIN)/pip install --disable-pip-version-check -q -e '.[test,ray]'

report-screenshot: setup chromium
	REPORT_SCREENSHOT=$(CURDIR)/report-screenshot.png $(BIN)/python -m pytest -q tests/test_report_browser.py
	@echo "wrote report-screenshot.png"

bench: setup
	$(BIN)/python tests/bench/run.py $(BENCH)

model: setup
	$(BIN)/python -m nodes.edgeloc.train --out nodes/edgeloc/weights

# The layer check: pyproject's import-linter contract (testbed > nodes.ros | reports >
# netem | nodes.edgeloc | nodes.recording); tests/test_layers.py checks that it bites.
lint: setup
	$(BIN)/ruff check testbed netem nodes reports tests
	$(BIN)/ruff format --check testbed netem nodes reports tests
	$(BIN)/lint-imports --no-cache

clean:
	-@test -x $(BIN)/testbed && $(BIN)/testbed clean
	rm -rf .pytest_cache .ruff_cache build *.egg-info
	rm -rf "$${EDGELOC_CACHE_DIR:-$${XDG_CACHE_HOME:-$$HOME/.cache}/edgeloc-testbed}"
