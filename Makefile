# ctrplan: the two commands are `make demo` and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# torch, in order of preference (the first that installs wins; an installed torch is kept):
#   1. TORCH_REQ from the configured indexes (a local CPU wheel, a mirror, or TORCH_INDEX);
#   2. the newest CPU build from the PyTorch CPU index (TORCH_CPU_INDEX), where reachable;
#   3. plain PyPI `torch` (works everywhere; on Linux it pulls several GB of CUDA libraries).
TORCH_REQ ?= torch==2.13.0+cpu
TORCH_INDEX ?=
TORCH_CPU_INDEX ?= https://download.pytorch.org/whl/cpu
PYTEST_ARGS ?=

.PHONY: demo test test-stat fuzz-ci fuzz install lint bench wheel clean

# The package and its run-time dependencies (all `make demo` needs) ...
$(VENV)/.base: pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -c "import torch" 2>/dev/null \
	  || $(PY) -m pip install -q $(TORCH_INDEX) "$(TORCH_REQ)" 2>/dev/null \
	  || $(PY) -m pip install -q --retries 1 --timeout 20 --index-url $(TORCH_CPU_INDEX) "torch>=2.2" 2>/dev/null \
	  || { echo "make: no CPU build of torch reachable; installing PyPI's default torch (larger download)"; \
	       $(PY) -m pip install -q "torch>=2.2"; }
	$(PY) -m pip install -q -e .
	touch $@

# ... and the extras the tests exercise (dev tools, ray, scene generation).
$(VENV)/.installed: $(VENV)/.base
	$(PY) -m pip install -q -e ".[dev,ray,scenes]"
	touch $@

install: $(VENV)/.installed

demo: $(VENV)/.base
	$(VENV)/bin/ctrplan demo --out demo_out

test: install
	$(PY) -m pytest -q $(PYTEST_ARGS)

# The seeded statistical suites whose numbers the README quotes (run by .ci/run after `make test`).
# Two worker processes, one thread each (the CI machine has 2 cores); tests spread one by one,
# except files with module fixtures (one xdist_group each: computed once, on one worker); every
# test seeds its own randomness and counts budgets, so results do not depend on the split.
STAT_WORKERS ?= 2
test-stat: install
	OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMBA_NUM_THREADS=1 \
	  $(PY) -m pytest -q -m statistical -n $(STAT_WORKERS) --dist loadgroup $(PYTEST_ARGS)

# Hypothesis over every reader and the numeric options (tests/test_fuzz.py), seeded: `make test`
# runs it with a few dozen examples per reader, `fuzz-ci` (run by .ci/run) with 10,000 per reader,
# `fuzz` with 100,000 per reader (hours; run it before a release or after changing a reader).
fuzz-ci: install
	CTRPLAN_FUZZ=ci OMP_NUM_THREADS=1 $(PY) -m pytest -q -n $(STAT_WORKERS) tests/test_fuzz.py $(PYTEST_ARGS)

fuzz: install
	CTRPLAN_FUZZ=long $(PY) -m pytest -q tests/test_fuzz.py $(PYTEST_ARGS)

lint: install
	$(VENV)/bin/ruff check ctrplan tests benchmarks examples

bench: install
	$(VENV)/bin/ctrplan bench --out benchmarks/results --readme README.md

# A wheel with the robots, models and scenes inside (setup.py copies anatomy/ into the package).
wheel: $(VENV)/.base
	$(PY) -m pip wheel -q --no-deps -w dist .

clean:
	rm -rf $(VENV) demo_out .pytest_cache build dist
