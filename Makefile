# Two entry points for a fresh machine: `make demo` and `make test`.
# Each creates its own virtual environment in .venv (Python 3.10+ as python3).
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: demo test venv clean

$(BIN)/stereo-bench: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	# torch first and pinned: the CPU build; an unpinned torch would pull CUDA packages.
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $@

venv: $(BIN)/stereo-bench

demo: venv
	$(BIN)/stereo-bench configs/quickstart.yaml --out out/quickstart
	$(BIN)/pose-eval --calib all --run out/quickstart --out out/quickstart/pose_eval

test: venv
	$(BIN)/python -m pytest -q

clean:
	rm -rf $(VENV) out
