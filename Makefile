# ctrplan: the two commands are `make demo` and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# The CPU build of torch. Where the PyTorch CPU wheel index is reachable, use e.g.
#   make test TORCH_INDEX="--extra-index-url https://download.pytorch.org/whl/cpu"
TORCH_REQ ?= torch==2.13.0+cpu
TORCH_INDEX ?=
PYTEST_ARGS ?=

.PHONY: demo test test-stat install lint bench clean

# The package and its run-time dependencies (all `make demo` needs) ...
$(VENV)/.base: pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q $(TORCH_INDEX) "$(TORCH_REQ)"
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
test-stat: install
	$(PY) -m pytest -q -m statistical $(PYTEST_ARGS)

lint: install
	$(VENV)/bin/ruff check ctrplan tests benchmarks examples

bench: install
	$(VENV)/bin/ctrplan bench --out benchmarks/results --readme README.md

clean:
	rm -rf $(VENV) demo_out .pytest_cache
