# cosy: the two commands a fresh machine needs are `make demo` and `make test`.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
COSY := $(VENV)/bin/cosy
# One BLAS thread: multithreaded OpenBLAS on small matrices is 10-25x slower here.
export OPENBLAS_NUM_THREADS ?= 1
export OMP_WAIT_POLICY ?= PASSIVE
export PYOPENGL_PLATFORM ?= egl

.PHONY: all demo test test-latest lock sysdeps bench eval-sample clean-venv sample-data pyc

all: demo

# Debian packages for headless EGL rendering (Mesa software rasteriser). apt only when missing.
SYS_PKGS := libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 libglib2.0-0
sysdeps:
	@missing=""; for p in $(SYS_PKGS); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" -ne 0 ] && SUDO="sudo"; \
	  $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
	  $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $$missing; \
	fi

# The install is locked: requirements/lock.txt pins every package (transitive ones, pip and
# setuptools included) at the versions the tests last passed with. The venv gets exactly those
# (pip check verifies they agree), then cosy itself, editable and without dependencies of its own.
# A version in the lock that cannot be had fails here, with pip's message.
LOCK := requirements/lock.txt
# torch: the CPU build. `pip install torch==X` here finds it among the local wheels; elsewhere
# give pip PyTorch's CPU wheel index (PIP_EXTRA_INDEX_URL), or pip takes the multi-GB CUDA build.
TORCH_VERSION ?= 2.13.0
# pip prints errors only: a machine's pip configuration can add one "WARNING: Location ... is
# ignored" line per package and flood `make demo > log`. PIP_QUIET=-q shows pip's warnings again.
PIP_QUIET ?= -qq

$(VENV)/.installed: pyproject.toml $(LOCK)
	$(MAKE) sysdeps
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install $(PIP_QUIET) "$$(grep -E '^pip==' $(LOCK))"
	$(PY) -m pip install $(PIP_QUIET) -r $(LOCK)
	$(PY) -m pip install $(PIP_QUIET) --no-deps --no-build-isolation -e .
	$(PY) -m pip check
	$(MAKE) pyc
	touch $@

# Byte-compiles cosy's sources (pip does it for the packages it installs, not for an editable
# install): where PYTHONDONTWRITEBYTECODE is set, every command would otherwise compile them
# again at start-up (~0.25-0.7 s per process, measured on the 2-core machine). Stale files are
# harmless (Python recompiles a changed module in memory); demo and bench refresh them.
pyc:
	@$(PY) -m compileall -q src

$(VENV): $(VENV)/.installed

# Regenerates the lock from pyproject.toml in a fresh virtualenv: the newest releases within its
# ranges (torch: the CPU build TORCH_VERSION). Check it before committing: make clean-venv test demo.
LOCK_VENV := .venv-lock
lock:
	rm -rf $(LOCK_VENV)
	$(PYTHON) -m venv $(LOCK_VENV)
	$(LOCK_VENV)/bin/python -m pip install $(PIP_QUIET) --upgrade pip setuptools
	$(LOCK_VENV)/bin/python -m pip install $(PIP_QUIET) torch==$(TORCH_VERSION)
	$(LOCK_VENV)/bin/python -m pip install $(PIP_QUIET) '.[test]'
	mkdir -p $(dir $(LOCK))
	{ echo "# cosy's locked install: every package make installs, at the versions the tests passed with."; \
	  echo "# Made by 'make lock' (a fresh virtualenv, pyproject.toml's ranges, torch $(TORCH_VERSION) CPU build)"; \
	  echo "# with Python $$($(LOCK_VENV)/bin/python -c 'import platform; print(platform.python_version())')" \
	       "on $$(uname -m), $$(date -u +%Y-%m-%d). Check it with: make clean-venv test demo"; \
	  $(LOCK_VENV)/bin/python -m pip freeze --all --exclude cosy-cli | sed -E 's/^(torch==[^+]*)\+cpu$$/\1/' | LC_ALL=C sort -f -t= -k1,1; \
	} > $(LOCK).tmp
	mv $(LOCK).tmp $(LOCK)
	rm -rf $(LOCK_VENV)
	@echo "wrote $(LOCK): check it with 'make clean-venv test demo' (and 'make test-latest')"

# The newest release of everything, no lock (torch included: TORCH_SPEC, default the newest,
# which on PyPI is a CUDA build; TORCH_SPEC=torch==$(TORCH_VERSION) keeps the CPU build): the
# whole test suite and the demo in a fresh virtualenv. For maintainers, to see what the next
# lock will bring.
LATEST_VENV := .venv-latest
TORCH_SPEC ?= torch
test-latest:
	$(MAKE) sysdeps
	rm -rf $(LATEST_VENV)
	$(PYTHON) -m venv $(LATEST_VENV)
	$(LATEST_VENV)/bin/python -m pip install $(PIP_QUIET) --upgrade pip setuptools
	$(LATEST_VENV)/bin/python -m pip install $(PIP_QUIET) --upgrade --upgrade-strategy eager -e '.[test]' '$(TORCH_SPEC)'
	$(LATEST_VENV)/bin/python -m pip check
	$(LATEST_VENV)/bin/python -m pip freeze --all --exclude-editable > $(LATEST_VENV)/versions.txt
	touch $(LATEST_VENV)/.installed
	@echo "newest versions: $(LATEST_VENV)/versions.txt; differences from $(LOCK):"
	@diff <(grep -v '^#' $(LOCK) | LC_ALL=C sort -f -t= -k1,1) <(sed 's/+cpu$$//' $(LATEST_VENV)/versions.txt | LC_ALL=C sort -f -t= -k1,1) | grep '^[<>]' || echo "  none"
	$(MAKE) VENV=$(LATEST_VENV) DEMO_OUT=demo_out_latest test demo

DEMO_OUT ?= demo_out
# The shipped detector when there is one (then also a run on the visible GT boxes, the upper
# bound with perfect detections, in DEMO_OUT/with_gt_boxes), else the GT boxes.
HAVE_DETECTOR := $(wildcard src/cosy_cli/assets/detector.onnx)
demo: $(VENV)/.installed pyc
	$(COSY) validate --dataset data_samples --split test
	$(COSY) run --dataset data_samples --split test --out $(DEMO_OUT) $(if $(HAVE_DETECTOR),,--from-gt)
	$(if $(HAVE_DETECTOR),$(COSY) run --dataset data_samples --split test --out $(DEMO_OUT)/with_gt_boxes \
	  --from-gt --templates-dir $(DEMO_OUT)/templates --to evaluate)

# Single view vs. groups of 4 and 8 views on the sample data (the paper's table) -> results/
eval-sample: $(VENV)/.installed
	$(PY) benchmarks/eval_sample.py --out results/eval_sample.md

test: $(VENV)/.installed
	$(PY) -m pytest tests

bench: $(VENV)/.installed pyc
	mkdir -p results
	for b in benchmarks/*.py; do echo "== $$b"; $(PY) $$b | tee results/$$(basename $$b .py).txt; done

# Regenerates the shipped sample dataset (deterministic).
sample-data: $(VENV)/.installed
	$(COSY) synth --out data_samples --scenes 3 --views 8 --objects 8 --seed 0 --overwrite

clean-venv:
	rm -rf $(VENV)
