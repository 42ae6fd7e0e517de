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

.PHONY: all demo test sysdeps bench eval-sample clean-venv sample-data

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

$(VENV)/.installed: pyproject.toml
	$(MAKE) sysdeps
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[test]'
	touch $@

$(VENV): $(VENV)/.installed

DEMO_OUT ?= demo_out
# The shipped detector when there is one (then also a run on the visible GT boxes, the upper
# bound with perfect detections, in DEMO_OUT/with_gt_boxes), else the GT boxes.
HAVE_DETECTOR := $(wildcard src/cosy_cli/assets/detector.onnx)
demo: $(VENV)/.installed
	$(COSY) validate --dataset data_samples --split test
	$(COSY) run --dataset data_samples --split test --out $(DEMO_OUT) $(if $(HAVE_DETECTOR),,--from-gt)
	$(if $(HAVE_DETECTOR),$(COSY) run --dataset data_samples --split test --out $(DEMO_OUT)/with_gt_boxes \
	  --from-gt --templates-dir $(DEMO_OUT)/templates --to evaluate)

# Single view vs. groups of 4 and 8 views on the sample data (the paper's table) -> results/
eval-sample: $(VENV)/.installed
	$(PY) benchmarks/eval_sample.py --out results/eval_sample.md

test: $(VENV)/.installed
	$(PY) -m pytest tests

bench: $(VENV)/.installed
	mkdir -p results
	for b in benchmarks/*.py; do echo "== $$b"; $(PY) $$b | tee results/$$(basename $$b .py).txt; done

# Regenerates the shipped sample dataset (deterministic).
sample-data: $(VENV)/.installed
	$(COSY) synth --out data_samples --scenes 3 --views 8 --objects 8 --seed 0 --overwrite

clean-venv:
	rm -rf $(VENV)
