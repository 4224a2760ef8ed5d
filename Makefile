# `make demo` and `make test` each bootstrap .venv on a fresh machine (Python 3.11),
# and reinstall only when pyproject.toml changes.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp

.PHONY: demo test lint bench protos clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	$(BIN)/lelsonar warm-up
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/lelsonar demo --out out --overwrite

test: lint
	$(BIN)/python -m pytest -q

# ruff, import-linter and mypy; the last two find modules by folder, so they read a tree of links
# named as the package is imported (tools/package_tree.py).
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/python tools/package_tree.py build/package-tree >/dev/null
	PYTHONPATH=build/package-tree $(BIN)/lint-imports --no-cache
	cd build/package-tree && ../../$(BIN)/mypy --config-file ../../pyproject.toml -p lelsonar

bench: $(STAMP)
	$(BIN)/lelsonar bench all

protos: $(STAMP)
	$(BIN)/python -m lelsonar.tools.gen_protos

clean:
	rm -rf out build *.egg-info .pytest_cache .hypothesis services/signal/__pycache__/numba-*
