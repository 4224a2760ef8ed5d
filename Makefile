# `make demo` and `make test` each bootstrap .venv on a fresh machine (Python 3.11),
# and reinstall only when pyproject.toml changes.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp

.PHONY: demo test bench protos clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	$(BIN)/lelsonar warm-up
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/lelsonar demo --out out

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/lelsonar bench all

protos: $(STAMP)
	$(BIN)/python -m lelsonar.tools.gen_protos

clean:
	rm -rf out build *.egg-info .pytest_cache .hypothesis services/signal/__pycache__/numba-*
