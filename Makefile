# The two commands: `make demo` and `make test`. Both create .venv and install what they need.
# `make demo DIALECT=B`: the emulated L8121 speaks command dialect B (README, "The L8121's two dialects").
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
DEMO_OUT ?= out/demo
DIALECT ?= A

.PHONY: demo test lint bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

# Reinstall when the project's dependencies change. pip byte-compiles what it installs one file at a
# time (40 of the test install's 80 s); compileall on every core does the same in under half that.
# Skipping it is slower still: the suite's many subprocesses then compile on every import.
$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q --no-compile -e '.[sim]'
	$(BIN)/python -m compileall -q -j 0 $(VENV)/lib > /dev/null || true
	touch $@

$(VENV)/.installed-test: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q --no-compile -e '.[test]'
	$(BIN)/python -m compileall -q -j 0 $(VENV)/lib > /dev/null || true
	touch $@ $(VENV)/.installed

demo: $(VENV)/.installed
	$(BIN)/radiokit demo -o $(DEMO_OUT) --overwrite --dialect $(DIALECT)

# The linter, the formatter's check and the import contracts (radiokit never imports sim or acquisition)
# run before the suite. `ruff format .` applies the format.
lint: $(VENV)/.installed-test
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/lint-imports

# Bytecode is written during the suite even where the environment says not to (PYTHONDONTWRITEBYTECODE,
# set on CI's image): otherwise each of the eight workers compiles every module and rewrites every test
# file again (collection 10.5 CPU s a worker instead of 3.5), and each of the suite's hundreds of
# subprocesses compiles the modules it imports (~0.05-0.1 CPU s each). benchmarks/README.md, "The suite's wall time".
test: lint
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest

bench: $(VENV)/.installed-test
	$(BIN)/python benchmarks/bench_correct.py

clean:
	rm -rf $(VENV) out build *.egg-info .pytest_cache .hypothesis
