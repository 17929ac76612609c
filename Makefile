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
CAPTURE   := $(SUBJECT)/capture/manifest.json
CHARACTER := $(SUBJECT)/character/manifest.json
PREVIEWS  := $(SUBJECT)/previews

# simulated lightstage + HMD capture with ground truth (a real capture converted to DESIGN Sec. 5 fits here)
$(CAPTURE): $(STAMP)
	$(EGO) $(EGOFLAGS) synth --out $(SUBJECT)/capture

$(CHARACTER): $(STAMP)
	$(EGO) $(EGOFLAGS) character default --out $(SUBJECT)/character

$(PREVIEWS)/character.png: $(CHARACTER)
	@mkdir -p $(PREVIEWS)
	$(EGO) $(EGOFLAGS) character preview $(SUBJECT)/character --out $@

# ---------------------------------------------------------------- ik (not in `subject` until egopose exists)
IK_MODEL := $(SUBJECT)/models/ik/manifest.json
# Training motions for `train ik` (motion artifacts); empty: the character's default model.
IK_TRAIN_MOTIONS ?=
# Ground truth for the ik metrics, e.g. $(SUBJECT)/capture/groundtruth/$(SEQ); empty: none.
IK_GT ?=

$(IK_MODEL): $(CHARACTER) $(IK_TRAIN_MOTIONS)
	$(EGO) $(EGOFLAGS) train ik $(IK_TRAIN_MOTIONS) --character $(SUBJECT)/character --out $(SUBJECT)/models/ik

$(SUBJECT)/motion/$(SEQ)/manifest.json: $(SUBJECT)/keypoints/$(SEQ)/manifest.json $(CHARACTER) $(IK_MODEL)
	$(EGO) $(EGOFLAGS) ik --in $(SUBJECT)/keypoints/$(SEQ) --character $(SUBJECT)/character \
		--model $(SUBJECT)/models/ik $(if $(IK_GT),--gt $(IK_GT)) --out $(SUBJECT)/motion/$(SEQ)

subject: $(CAPTURE) $(CHARACTER) $(PREVIEWS)/character.png

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
