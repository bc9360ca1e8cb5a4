# Two entry points for a fresh machine: `make demo` and `make test`. Both install what they need.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install lint demo test test-long proto bench clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[train,test,dev]'
	touch $(STAMP)

install: $(STAMP)
	@bash deploy/install-system-deps.sh

proto: $(STAMP)
	$(BIN)/python proto/gen.py

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: install lint
	MUJOCO_GL=$${MUJOCO_GL:-egl} $(BIN)/python -m pytest $(PYTEST_ARGS)

# The checks that take minutes (marker `long`): the overfit test (about 5 min) and the compose
# serve profile run for real (builds the 7 GB serving image with torch: about 2 min here).
test-long: install
	MUJOCO_GL=$${MUJOCO_GL:-egl} $(BIN)/python -m pytest -m long $(PYTEST_ARGS)

demo: install
	MUJOCO_GL=$${MUJOCO_GL:-egl} bash deploy/demo.sh

clean:
	rm -rf $(VENV) .pytest_cache
