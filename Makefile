# Two entry points (see README): `make demo` runs the main job, `make test` runs the tests;
# CI (.ci/run) runs `make test` and `make api`.
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

# The API reference (pdoc, offline) into site/; fails on a pdoc error or warning (an
# unresolvable name in __all__, a module that does not import), which pdoc itself only prints.
api: $(STAMP)
	rm -rf site && mkdir -p site
	$(BIN)/pdoc --docformat google -o site torchpvs envs training 2> site/pdoc.log; \
	  status=$$?; cat site/pdoc.log >&2; \
	  if [ $$status -ne 0 ] || grep -q "Warn" site/pdoc.log; then \
	    echo "make api: pdoc failed or warned (above)" >&2; exit 1; fi
	rm -f site/pdoc.log

lint: $(STAMP)
	$(BIN)/ruff check torchpvs envs training tests benchmarks examples

clean:
	rm -rf $(VENV) build *.egg-info site
