# The two commands of the README: `make demo` and `make test`. Each creates .venv if it is missing
# and installs what it needs. On a machine without an NVIDIA GPU, the CPU build of PyTorch is
# installed first; set TORCH_PIP_ARGS (e.g. "--index-url https://download.pytorch.org/whl/cpu")
# where pip's default index would give a CUDA build.

PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.opt2skill-installed
GPU_EXTRA_STAMP := $(VENV)/.opt2skill-gpu-extra
TORCH_VERSION := 2.13.0
TORCH_PIP_ARGS ?=
PYTEST_ARGS ?=

.PHONY: demo test install bench clean

demo: $(STAMP)
	$(BIN)/opt2skill demo

test: $(STAMP) $(GPU_EXTRA_STAMP)
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest -n 2 $(PYTEST_ARGS)

install: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	@if command -v nvidia-smi >/dev/null 2>&1; then \
		echo "NVIDIA GPU found: pip chooses the PyTorch build"; \
	else \
		$(BIN)/python -m pip install --quiet "torch==$(TORCH_VERSION)" $(TORCH_PIP_ARGS); \
	fi
	$(BIN)/python -m pip install --quiet -e ".[test]"
	@# The optimizer's compiled parts (opt2skill.trajopt.native): built now so that tests and workers
	@# find them; without a C++ compiler the optimizer uses Python and Crocoddyl versions and this says why.
	$(BIN)/python -m opt2skill.trajopt.native || true
	@touch $(STAMP)

# The tests also install the GPU backend's extra: its equivalence with C MuJoCo runs on Warp's CPU
# device (tests/test_sim_warp.py), so the GPU path is tested on machines without a GPU. `make demo`
# and `make install` leave it out (about 400 MB; docs/dependencies.md).
$(GPU_EXTRA_STAMP): $(STAMP)
	$(BIN)/python -m pip install --quiet -e ".[gpu]"
	@touch $(GPU_EXTRA_STAMP)

bench: $(STAMP)
	@for script in $(wildcard benchmarks/*.py); do echo "== $$script"; OMP_NUM_THREADS=1 $(BIN)/python $$script || exit 1; done

clean:
	rm -rf $(VENV) .pytest_cache build src/*.egg-info
