# Set-up and the two entry points shown in README.md.
#   make validate   -> the main job: `hemicube validate` on the embedded default rig and sample
#   make test       -> the test suite (what CI runs through .ci/run)
#   make test-fast  -> the same less the end-to-end files and the tests marked slow (below)
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
# torch first, so that pip never resolves a bare `torch` to a multi-GB CUDA build on a CPU machine:
# torch==2.13.0 is the CPU file on disk on our machines and the regular PyPI build elsewhere.
# Override with `make TORCH_SPEC="torch==2.x" setup`; an existing torch is never replaced.
TORCH_SPEC ?= torch==2.13.0
# The tests run in one process per core (pytest-xdist, at most 4), a test file per process: the Warp CPU kernels
# are single-threaded, so one process leaves the other cores of CI's two idle. PYTEST_WORKERS= runs them in one.
# --no-loadscope-reorder (xdist >= 3.8): the files in tests/conftest.py's order, the longest first; xdist's default
# order, by test count, queued the long files with few tests last.
PYTEST_WORKERS ?= -n auto --maxprocesses 4 --dist loadfile --no-loadscope-reorder
# --durations: the 25 slowest tests end every log, CI's included (what its time goes to: docs/performance.md)

export WARP_CACHE_PATH ?= $(CURDIR)/.cache/warp
export VTK_DEFAULT_OPENGL_WINDOW ?= vtkEGLRenderWindow
export MPLBACKEND ?= Agg
export DRJIT_CACHE_DIR ?= $(CURDIR)/.cache/drjit
export GENICAM_CACHE_V3_5 ?= $(CURDIR)/.cache/genicam

.PHONY: setup validate test test-fast api
setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -c "import torch" 2>/dev/null || $(BIN)/python -m pip install -q "$(TORCH_SPEC)"
	$(BIN)/python -m pip install -q -e ".[dev]"
	touch $@

validate: setup
	$(BIN)/hemicube validate

test: setup
	$(BIN)/python -m pytest -q --durations=25 $(PYTEST_WORKERS) $(PYTEST_ARGS)

# The fast tier: every test but those of the end-to-end files, which tests/conftest.py names (END_TO_END_FILES) and
# marks e2e: test_validate_suite, test_scaleout, test_hardware_capture, test_bench_pipeline, test_capture,
# test_alignment, test_readme_tour, test_validate, test_train, test_design, test_reconstruct_resume, test_calibration,
# test_calibration_colour, test_calibration_leds, test_distributed, test_notebooks; and but the tests marked slow
# in the other files (those of the main job's capture, the benches' whole runs, gradient checks).
FAST_MARKERS ?= not e2e and not slow
test-fast: setup
	$(BIN)/python -m pytest -q --durations=10 $(PYTEST_WORKERS) -m "$(FAST_MARKERS)" $(PYTEST_ARGS)

# the API reference from the docstrings, into api/ (not committed; tests/test_api.py builds it too)
api: setup
	$(BIN)/python -m hemicube.apidoc -o api
