# Two commands on a fresh machine: `make demo` and `make test` (README.md).
PYTHON ?= python3.11
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
OUT    ?= out/demo

.PHONY: env demo test bench clean

# The environment: a virtualenv with the package (editable) and its dev extras, pinned by
# constraints.txt, plus the npm tools the tests use (Khronos glTF-Validator, three.js, playwright-core).
$(STAMP): pyproject.toml constraints.txt package.json package-lock.json
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e ".[dev,dask,render]"
	npm ci --no-audit --no-fund --loglevel=error
	touch $(STAMP)

env: $(STAMP)

demo: env
	$(BIN)/python -m rigmix.demo --out $(OUT)

test: env
	$(BIN)/python -m pytest -q -n 2 --timeout=1800

bench: env
	$(BIN)/python -m benchmarks.run

clean:
	rm -rf $(VENV) node_modules out
