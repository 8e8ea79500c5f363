# Quick start: `make run` (set up + main job on a bundled default), `make test` (set up + all checks).
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test setup lint typecheck pytest reproduce clean

$(STAMP): requirements.lock pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -r requirements.lock
	$(BIN)/python -m pip install --quiet --no-deps -e .
	touch $(STAMP)

setup: $(STAMP)

run: $(STAMP)
	$(BIN)/physfuse estimate recordings/humanoid_push.mcap --config configs/humanoid_push.toml --out out/humanoid_push

test: lint typecheck pytest

lint: $(STAMP)
	$(BIN)/ruff format --check .
	$(BIN)/ruff check .

typecheck: $(STAMP)
	$(BIN)/mypy

pytest: $(STAMP)
	$(BIN)/pytest

reproduce: $(STAMP)
	$(BIN)/physfuse reproduce fig2 --out out/fig2
	$(BIN)/physfuse reproduce fig3 --out out/fig3

clean:
	rm -rf $(VENV) out
