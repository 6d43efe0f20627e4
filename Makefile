# Two commands on a fresh machine with Python 3.11+ and pip:
#   make demo   creates/reuses .venv, installs vqtouch, runs the main job
#   make test   creates/reuses .venv, installs vqtouch with the test, clip and metrics extras, lints, runs the tests
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.vqtouch-installed
# The quick start's demo: the `tour` scene, every stage once (tokenizer, real-frame reconstructions,
# sensor families, few-shot adaptation, a generator from each condition).  DEMO_ARGS="--scene NAME" runs another.
DEMO_ARGS ?= --scene tour
PYTEST_ARGS ?=

.PHONY: install demo lint test clean

# constraints.txt pins the verified torch/torchvision pair (pyproject.toml has lower bounds only);
# the clip extra (open_clip) and the metrics extra (torch-fidelity) are installed so the tests cover the clip
# conditioner, LPIPS, FID and KID.  tacto is
# installed for one data file, DIGIT's published design (config_digit.yml, read by sensors/digit.py),
# with --no-deps: its own dependencies (pyrender, OpenGL, pybullet) serve its simulator, never imported.
$(STAMP): pyproject.toml setup.py constraints.txt
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "vqtouch needs Python >= 3.11; set PYTHON=python3.11")'
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip "setuptools>=77"
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[test,clip,metrics]'
	$(BIN)/python -m pip install --quiet --no-deps -c constraints.txt tacto
	@touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/vqtouch demo --overwrite --out runs/demo $(DEMO_ARGS)

# ruff's rules and the packages' import layers (import-linter) are in pyproject.toml.
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/lint-imports --no-cache

test: lint
	$(BIN)/python -m pytest $(PYTEST_ARGS)

clean:
	rm -rf build dist *.egg-info runs/demo .pytest_cache
