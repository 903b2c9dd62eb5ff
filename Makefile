# lfcal-station: the two commands that do everything on a fresh Debian machine.
#   make demo   -> install, then run a calibration on the simulated station
#   make test   -> install, then run the whole test suite
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
APT_PACKAGES := gir1.2-aravis-0.8 aravis-tools libgirepository1.0-dev libcairo2-dev pkg-config gcc python3-dev chromium chromium-driver postgresql
APT_STAMP := $(VENV)/.apt-stamp
PIP_STAMP := $(VENV)/.pip-stamp
SUDO := $(shell [ "$$(id -u)" = "0" ] || echo sudo)

.PHONY: setup demo test lint bench clean

setup: $(PIP_STAMP)

$(APT_STAMP): Makefile
	@mkdir -p $(VENV)
	@if command -v apt-get >/dev/null 2>&1; then \
	  missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	  if [ -n "$$missing" ]; then echo "apt: installing$$missing"; \
	    $(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq --no-install-recommends $$missing >/dev/null; fi; \
	else echo "apt-get not found: install $(APT_PACKAGES) by hand"; fi
	@touch $@

$(PIP_STAMP): $(APT_STAMP) pyproject.toml
	@[ -x $(BIN)/python ] || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e ".[dev,aravis]"
	@touch $@

demo: setup
	$(BIN)/lfcal demo --config config/simulated.toml

test: setup
	$(BIN)/ruff check .
	$(BIN)/lint-imports
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 \
		$(BIN)/python -m pytest -n 3 --dist loadfile -q --durations=15

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/lint-imports

bench: setup
	$(BIN)/python -m bench

clean:
	rm -rf $(VENV) out var
