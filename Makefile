# Set-up on a fresh machine is `make demo` or `make test`: both create .venv once and
# reuse it; pip runs again only when pyproject.toml changes.

PYTHON ?= $(shell for p in python3.12 python3 python; do \
	command -v $$p >/dev/null 2>&1 && $$p -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))' 2>/dev/null \
	&& echo $$p && break; done)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= out/demo

.PHONY: test demo bench clean-venv

$(STAMP): pyproject.toml
	@test -n "$(PYTHON)" || { echo "error: Python 3.12 not found (drake 1.58 wheels need it); install it, e.g. 'pyenv install 3.12' (the repo's .python-version selects it)"; exit 1; }
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip
	$(BIN)/python -m pip install -e ".[dev,distributed]"
	touch $(STAMP)

# Tests run on TEST_WORKERS processes (pytest-xdist); 0 runs them in this one.
TEST_WORKERS ?= 2

test: $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist worksteal

demo: $(STAMP)
	$(BIN)/reachwatch run --scenario scenarios/demo.yaml --out $(OUT)
	@echo "open $(OUT)/report.html (or read $(OUT)/report.md)"

bench: $(STAMP)
	$(BIN)/python benchmarks/render.py

clean-venv:
	rm -rf $(VENV)
