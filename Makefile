# egorelight — two commands on a fresh machine: `make demo` and `make test`.
#
# Subject rules form a DAG over artifact manifests: each target is an artifact's manifest.json
# and depends on the manifests of its inputs, so `make -j2 SUBJECT=subjects/demo` re-runs exactly
# what is stale and `make -n` shows the plan. Every stage also skips itself when its cache key
# (stage, config, input digests) is unchanged, so re-running a rule is cheap.

PYTHON  ?= python3
VENV    ?= .venv
BIN     := $(VENV)/bin
EGO     := $(BIN)/egorelight
SUBJECT ?= subjects/demo
PRESET  ?= cpu
SEQ     ?= test
STAMP   := $(VENV)/.installed-stamp
EGOFLAGS ?= --preset $(PRESET)

.PHONY: all venv demo test bench clean distclean subject

all: demo

# ---------------------------------------------------------------- environment
$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	@touch $@

venv: $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python bench/run.py

# ---------------------------------------------------------------- subject DAG
CHARACTER := $(SUBJECT)/character/manifest.json
PREVIEWS  := $(SUBJECT)/previews

$(CHARACTER): $(STAMP)
	$(EGO) $(EGOFLAGS) character default --out $(SUBJECT)/character

$(PREVIEWS)/character.png: $(CHARACTER)
	@mkdir -p $(PREVIEWS)
	$(EGO) $(EGOFLAGS) character preview $(SUBJECT)/character --out $@

subject: $(CHARACTER) $(PREVIEWS)/character.png

demo: subject
	@echo
	@echo "egorelight demo finished (preset $(PRESET)). Results in $(SUBJECT)/:"
	@for m in $$(find $(SUBJECT) -name manifest.json | sort); do echo "  $$(dirname $$m)"; done
	@echo "Previews:"
	@find $(SUBJECT) -name '*.png' -path '*preview*' | sort | sed 's/^/  /'
	@echo "Inspect any artifact with: $(EGO) inspect <path>"

clean:
	rm -rf $(SUBJECT)

distclean: clean
	rm -rf $(VENV) src/*.egg-info .pytest_cache
