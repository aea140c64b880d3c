# glossrt: `make demo`, `make view` and `make test` do all set-up on a fresh machine.
# They create .venv (Python 3.11 when available), install glossrt into it, make sure a
# libLLVM >= 16 is usable (installing Debian's libllvm19 when run as root; `make test` also
# Debian's chromium for the viewer's browser tests), then run.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.glossrt-installed
DEMO_OUT ?= demo-out

.PHONY: demo test check view llvm chromium bench clean-venv

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

llvm: $(STAMP)
	@bash scripts/ensure-llvm.sh $(BIN)/python

chromium:
	@bash scripts/ensure-chromium.sh

# the whole suite (what CI runs), the 25 slowest tests listed at the end
test: llvm chromium
	bash scripts/run-tests.sh $(BIN)/python --durations=25

# the quick tier for the inner loop: every test not marked slow (docs/TESTING.md)
check: llvm
	bash scripts/run-tests.sh $(BIN)/python -m "not slow"

# the live viewer on the built-in polygon-light scene: open the URL it prints; Ctrl-C stops
VIEW_SCENE ?= polygon-light
view: llvm
	$(BIN)/glossrt view $(VIEW_SCENE)

demo: llvm
	$(BIN)/glossrt demo --out $(DEMO_OUT)

bench: llvm
	$(BIN)/glossrt bench --json bench.json

clean-venv:
	rm -rf $(VENV)
