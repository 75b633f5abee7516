# Set-up and the two commands of the README. Everything installs into .venv with the
# versions pinned in constraints.txt (tested on Python 3.11).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup demo test test-slow bench lint

$(BIN)/lightfield-jax: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e ".[test,experiments]"
	touch $@

setup: $(BIN)/lightfield-jax

demo: setup
	$(BIN)/lightfield-jax demo --out demo_out

# Two processes, each test file in one (its module fixtures and compiled programs shared).
test: setup
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

test-slow: setup
	$(BIN)/python -m pytest -q -n 2 --dist loadfile -m slow

bench: setup
	$(BIN)/lightfield-jax bench --out bench.json

lint: setup
	$(BIN)/ruff check lightfield_jax tests experiments
