# Two entry points (see README): `make demo` runs the main job, `make test` runs the tests.
# Both create or refresh the local virtual environment .venv with torch pinned (constraints.txt).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-slow venv clean lint api

$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -c constraints.txt -e ".[rl,zoo,dev]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	MPLBACKEND=Agg $(BIN)/python -m training.demo

test: $(STAMP)
	$(BIN)/ruff check torchpvs envs training tests benchmarks examples
	MPLBACKEND=Agg $(BIN)/python -m pytest -q -m "not slow" -p no:cacheprovider

test-slow: $(STAMP)
	MPLBACKEND=Agg $(BIN)/python -m pytest -q -m slow -p no:cacheprovider

api: $(STAMP)
	$(BIN)/pdoc --docformat google -o site torchpvs envs training

lint: $(STAMP)
	$(BIN)/ruff check torchpvs envs training tests benchmarks examples

clean:
	rm -rf $(VENV) build *.egg-info site
