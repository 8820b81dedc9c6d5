# Two entry points on a fresh clone:  `make demo`  and  `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin

.PHONY: install system-packages demo test bench
install: $(VENV)/.installed

# The exact tested versions come from constraints.txt; pyproject.toml only states compatible ranges.
$(VENV)/.installed: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q -c constraints.txt --upgrade pip
	$(BIN)/pip install -q -c constraints.txt -e ".[test]"
	touch $@

# Debian packages for headless MuJoCo rendering (EGL on the CPU); needs root or sudo.
system-packages:
	bash .ci/system-packages.sh

# The main job: a short SAC-MC training on FetchReach at the thesis' network sizes (a few minutes on 2 cores).
demo: install
	$(BIN)/mcrl train

# One worker per core, a test file per worker (files share module-scoped fixtures): about half the time on 2 cores.
# --no-loadscope-reorder: files go out in tests/conftest.py's order (longest first), not by their number of tests.
test: system-packages install
	$(BIN)/python -m pytest -n auto --dist loadfile --no-loadscope-reorder

bench: install
	$(BIN)/pip install -q -c constraints.txt -e ".[bench]"
	$(BIN)/python benchmarks/bench.py --json benchmarks/results.json
