# `make test` and `make serve` work on a fresh machine: each creates .venv and installs what
# it needs first. Installs are re-run only when pyproject.toml changes.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
# `make serve HOST=… PORT=… MODEL=… CONFIG=…` passes those given on make's command line as
# options (which outrank OVERLAPMAMBA_* variables and a config file; an environment variable
# of those names, such as a shell's HOST, is not taken); those not given come from the
# settings, whose defaults are 127.0.0.1:8000 and the bundled default model (its card:
# models/README.md).
given = $(if $(filter command line,$(origin $(1))),$(2) "$($(1))")
SERVE_OPTIONS = $(call given,HOST,--host) $(call given,PORT,--port) \
	$(call given,MODEL,--model) $(call given,CONFIG,--config)

# torch is pinned to the CPU build. Use the local wheel where this machine has it; elsewhere
# ask PyTorch's CPU index, so pip never pulls the multi-GB CUDA build.
# (uv takes a package from the first index that has it; PyTorch's carries numpy, pillow and
# others at a few versions only, which the lock's pins may not be: best match across both)
TORCH_SOURCE := $(if $(wildcard /opt/wheels/torch-2.13.0*),--find-links /opt/wheels,--extra-index-url https://download.pytorch.org/whl/cpu --index-strategy unsafe-best-match)

# the town `make e2e` drives (tests/e2e_kit.py's HELD_OUT)
E2E_TOWN := data/synth/test/manifest.json

.PHONY: lock test e2e image image-test chromium lint format typecheck serve bench data data-sensors data-towns data-drift docs docs-site clean

# uv (from PyPI, into the venv) installs the same packages as pip in a tenth of the time:
# measured 10 s against ≈100 s for the full set on 2 cores.
UV := $(BIN)/uv pip install -q --python $(BIN)/python

# Python writes the bytecode of what it imports (.pyc, into the venv and __pycache__/) in
# every command make runs, even where the caller sets PYTHONDONTWRITEBYTECODE, as these
# development machines do: each of the suite's processes (workers, servers, CLIs, worker
# pools) would otherwise compile torch, FastAPI and the rest from source again (python
# benchmarks/bytecode.py times both ways). Compiled as imported, not at install: uv's
# --compile-bytecode compiles every module of every package, imported or not.
export PYTHONDONTWRITEBYTECODE :=

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q uv

# constraints.txt is the lock: the versions the suite passed with (deploy/lock.py). The
# installs take them, so a fresh machine tests and serves what was tested, not whatever was
# released since; `make lock` moves them to the newest releases pyproject.toml allows.
$(VENV)/.installed-all: pyproject.toml constraints.txt | $(BIN)/python
	$(UV) $(TORCH_SOURCE) -c constraints.txt -e '.[serve,train,client,dev]'
	@touch $@

$(VENV)/.installed-serve: pyproject.toml constraints.txt | $(BIN)/python
	$(UV) -c constraints.txt -e '.[serve]'
	@touch $@

# The newest releases pyproject.toml allows, into .venv, then their versions into
# constraints.txt; run `make test` before committing it.
lock: | $(BIN)/python
	$(UV) $(TORCH_SOURCE) --upgrade -e '.[serve,train,client,dev]'
	$(BIN)/python deploy/lock.py
	@touch $(VENV)/.installed-all

# The browser test drives Debian's chromium: installed first where this runs as root with apt.
# Two pytest-xdist workers, a test file each at a time: on 2 cores they fill the time one
# process leaves idle waiting on its servers (each computes on one thread: tests/conftest.py).
TEST_WORKERS ?= 2
# The static checks (`make lint docs-site`: ruff, mypy, the docs site) run beside the suite at
# a lower priority, their output printed when the suite ends: on a fresh clone mypy's cold
# run (one core) is the longest of them, and the suite's waits on its servers absorb it.
# Either failing fails `make test`; `make lint` alone answers first.
CHECKS_LOG := $(VENV)/checks.log
# (not spelled $(MAKE) in the recipe, which `make -n test` would run, the suite with it)
CHECKS := nice -n 10 $(MAKE) --no-print-directory lint docs-site

test: $(VENV)/.installed-all chromium
	@$(CHECKS) > $(CHECKS_LOG) 2>&1 & checks=$$!; \
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile --durations=15; tests=$$?; \
	wait $$checks; checked=$$?; echo "---- make lint docs-site (beside the suite):"; \
	cat $(CHECKS_LOG); [ $$checked = 0 ] || echo "make test: the static checks failed (above)"; \
	[ $$tests = 0 ] && [ $$checked = 0 ]

# End-to-end evidence at full size: load, crash, fuzz, browser, auth matrix (tests/test_e2e_*.py;
# `make test` runs them small). Figures and the dashboard screenshot go to reports/e2e/.
# The robots drive the held-out test town, made first where missing (`make data` makes it
# too; alone about 5 minutes on 2 cores). The image's runs are rendered into its table
# (reports/deploy/image.md), as `make image-test` does.
e2e: $(VENV)/.installed-all chromium image $(E2E_TOWN)
	OVERLAPMAMBA_E2E=full OVERLAPMAMBA_IMAGE_TEST=1 $(BIN)/python -m pytest -m e2e -p no:cacheprovider -v tests
	$(BIN)/python deploy/image.py report

# The container image, built here with podman (installed from Debian where missing) or docker:
# a bookworm base made with debootstrap when no registry answers, the dependencies from a
# wheelhouse of the tested venv's versions (deploy/image.py). image-test starts it and checks
# it against the venv (tests/test_image.py; figures in reports/deploy/).
image: $(VENV)/.installed-all
	$(BIN)/python deploy/image.py all

image-test: $(VENV)/.installed-all
	OVERLAPMAMBA_IMAGE_TEST=1 $(BIN)/python -m pytest -p no:cacheprovider -v tests/test_image.py
	$(BIN)/python deploy/image.py report

# Debian's chromium for the browser tests (playwright drives it; it downloads no browser).
chromium:
	@command -v chromium >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null \
	  && apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; } \
	  || echo "no chromium: the browser test will be skipped"

lint: $(VENV)/.installed-all
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

format: $(VENV)/.installed-all
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

# Maps live under ./data/maps; settings: `overlapmamba dump-config`, OVERLAPMAMBA_* variables,
# OVERLAPMAMBA_CONFIG or CONFIG=service.toml (HOST, PORT, MODEL: above).
# The selective-scan kernel is compiled here, at install, never at a request; without a
# compiler the service says so at start and serves the model's portable graph.
serve: $(VENV)/.installed-serve
	-$(BIN)/python -m overlapmamba.core.scan_kernel
	$(BIN)/overlapmamba serve $(SERVE_OPTIONS)

bench: $(VENV)/.installed-all
	$(BIN)/python benchmarks/projection.py
	$(BIN)/python benchmarks/simulator.py
	$(BIN)/python benchmarks/training.py
	$(BIN)/python benchmarks/encoder.py
	$(BIN)/python benchmarks/views.py
	$(BIN)/python benchmarks/place_recognition.py
	$(BIN)/python benchmarks/serving.py
	$(BIN)/python benchmarks/sizing.py
	$(BIN)/python benchmarks/registration.py

# The synthetic presets (≈38 GB, ≈105 min on 2 cores): four training towns, the validation
# town and a second drive through it, three test towns and a second drive through the first
# test town. Each is skipped when its manifest exists, so an interrupted `make data`
# resumes where it stopped.
DATA_PRESETS := train train-b train-c train-d val val-s1 test test-b test-c test-s1

$(E2E_TOWN): | $(VENV)/.installed-all
	$(BIN)/overlapmamba gen-data $(patsubst %/,%,$(dir $@)) --preset test -q
data: $(VENV)/.installed-all
	for p in $(DATA_PRESETS); do \
	  test -f data/synth/$$p/manifest.json || $(BIN)/overlapmamba gen-data data/synth/$$p --preset $$p; \
	done

# The sensor towns (overlapmamba.synth.presets, the longest data target): one validation and one test
# town rendered by every catalogue sensor on a car, the test town from a robot's, an AMR's
# and a backpack's sensor, and five second drives of it by other sensors. Resumable, as above.
data-sensors: $(VENV)/.installed-all
	for p in $$($(BIN)/python -c "from overlapmamba.synth.presets import SENSOR_PRESETS; print(*SENSOR_PRESETS)"); do \
	  test -f data/synth/$$p/manifest.json || $(BIN)/overlapmamba gen-data data/synth/$$p --preset $$p -q; \
	done

# The drawn training towns (overlapmamba.synth.presets.drawn_town: train-x00 … train-x11, 1,000
# scans each, the catalogue's sensors in turn on drawn mountings). Resumable, as above.
data-towns: $(VENV)/.installed-all
	for p in $$($(BIN)/python -c "from overlapmamba.synth.presets import DRAWN_PRESETS; print(*DRAWN_PRESETS)"); do \
	  test -f data/synth/$$p/manifest.json || $(BIN)/overlapmamba gen-data data/synth/$$p --preset $$p -q; \
	done

# The drifting towns (overlapmamba.synth.presets: val, test, test-b and test-c again, each scan's
# firings a random fraction of a spacing later, as a real head's drift; ≈ 8 min on 2 cores).
# Resumable, as above.
data-drift: $(VENV)/.installed-all
	for p in $$($(BIN)/python -c "from overlapmamba.synth.presets import DRIFT_PRESETS; print(*DRIFT_PRESETS)"); do \
	  test -f data/synth/$$p/manifest.json || $(BIN)/overlapmamba gen-data data/synth/$$p --preset $$p -q; \
	done

# The tables commands write under reports/ pasted into README.md and the model card where
# they include them (docs/render.py; tests/test_docs_figures.py fails on a stale copy).
docs: $(BIN)/python
	$(BIN)/python docs/render.py

# The documentation site (mkdocs.yml: README.md its home, docs/ its pages, the model card and
# reports/ beside them), built in strict mode: a broken link or anchor fails `make test`.
docs-site: $(VENV)/.installed-all
	$(BIN)/mkdocs build --strict --quiet

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache .hypothesis bench-results site
