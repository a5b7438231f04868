# The two commands of the README:
#   make demo   installs iorthand into .venv and runs the whole system on this machine
#   make test   installs the test dependencies too (system packages when root) and runs the tests
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
PIP    := $(BIN)/python -m pip

.PHONY: demo test install install-test lint bench clean

# Debian's python3 has no venv module unless python3-venv is installed: fall back to virtualenv from PyPI.
$(BIN)/python:
	$(PYTHON) -m venv $(VENV) || { rm -rf $(VENV); $(PYTHON) -m pip install --quiet --user virtualenv && $(PYTHON) -m virtualenv $(VENV); }
	$(PIP) install --quiet --upgrade pip

$(VENV)/.installed: $(BIN)/python pyproject.toml edge/pyproject.toml cloud/pyproject.toml operator/pyproject.toml
	$(PIP) install --quiet -e . -e "edge[ur]" -e cloud -e operator
	touch $@

$(VENV)/.installed-test: $(VENV)/.installed
	$(PIP) install --quiet -e ".[test]"
	touch $@

install: $(VENV)/.installed

# LeRobot (iorthand export --format lerobot) is heavy (torch): best effort, its tests skip and say why without it.
$(VENV)/.installed-lerobot: $(VENV)/.installed-test
	scripts/install-lerobot.sh $(BIN)/python && touch $@ || true

install-test: $(VENV)/.installed-test $(VENV)/.installed-lerobot
	scripts/install-test-deps.sh

demo: install
	$(BIN)/iorthand demo

# The tests in two passes. First all but the serial ones, a file per worker, as many workers as CPUs up to two:
# they mostly wait on routers, processes and links (the suite uses about one core of two). Then the serial ones
# alone: they need the machine to themselves (pyproject.toml's markers say why). `pytest` alone runs every test
# in one pass.
test: install-test
	$(BIN)/python -m pytest -m "not serial" -n logical --maxprocesses 2 --dist loadfile; parallel=$$?; \
	$(BIN)/python -m pytest -m serial; serial=$$?; \
	[ $$parallel -ne 0 ] && exit $$parallel; exit $$serial

lint: install-test
	$(BIN)/ruff check .

bench: install-test
	$(BIN)/iorthand bench all

clean:
	rm -rf $(VENV) build *.egg-info */*.egg-info .pytest_cache .ruff_cache
