# Two entry points for a fresh machine: `make demo` and `make test`.
# Each creates its own virtual environment in .venv (Python 3.10+ as python3).
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: demo test venv clean mrcal-env multical-env blender

$(BIN)/stereo-bench: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	# torch first and pinned: the CPU build; an unpinned torch would pull CUDA packages.
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e ".[test]"
	# aniposelib, to read anipose files back in the tests and to calibrate in compare-tools
	# (its triangulation imports jax): without its dependencies, since it asks for
	# opencv-contrib-python, which would replace the headless OpenCV in the same cv2.
	$(BIN)/python -m pip install --quiet pandas tqdm toml "jax[cpu]==0.10.2"
	$(BIN)/python -m pip install --quiet --no-deps aniposelib==0.8.0
	# caliscope, to read camera_array.toml files back in the tests and to calibrate in
	# compare-tools: its camera array and calibration need only rtoml and platformdirs (and
	# pandas, above); without its dependencies for the same reason (opencv-python) and because
	# its video stack (av) and GUI are not used.
	$(BIN)/python -m pip install --quiet rtoml platformdirs
	$(BIN)/python -m pip install --quiet --no-deps caliscope==0.11.8
	# mrcal, to read .cameramodel files back in the tests and to run mrcal-calibrate-cameras in
	# compare-tools, has no wheel for Python < 3.12: a small environment of its own when a
	# python3.12 or newer is found (else those tests and that tool skip, saying why).
	-$(MAKE) --no-print-directory mrcal-env
	touch $@

MRCAL_PYTHON ?= $(firstword $(foreach v,3.12 3.13,$(shell ls $(HOME)/.pyenv/versions/$(v)*/bin/python$(v) /usr/local/bin/python$(v) /usr/bin/python$(v) 2>/dev/null)))
# multical's command line runs on Python 3.10 only: it dies at import on 3.11+ (a dataclass
# field with a mutable default), and the numpy it needs has no wheels past 3.11.
MULTICAL_PYTHON ?= $(firstword $(shell ls $(HOME)/.pyenv/versions/3.10*/bin/python3.10 /usr/local/bin/python3.10 /usr/bin/python3.10 2>/dev/null))


# The Blender worker environment (bpy 5.0.1, mediapipe 0.10.21, numpy<2; about 2 GB): the
# photoreal backend and the 2D pose detector run there (docs/photoreal.md). Without it their
# tests skip, saying why.
blender: venv
	$(BIN)/stereo-bench blender-setup

mrcal-env:
	@if [ -z "$(MRCAL_PYTHON)" ]; then echo "no python3.12+ found: mrcal tests will skip"; exit 0; fi; \
	$(MRCAL_PYTHON) -m venv $(VENV)/mrcal && \
	$(VENV)/mrcal/bin/python -m pip install --quiet numpy scipy numpysane gnuplotlib pyyaml \
		opencv-python-headless && \
	$(VENV)/mrcal/bin/python -m pip install --quiet --no-deps mrcal==2.5.2.post1

# multical, run by compare-tools as `multical calibrate` on the rendered images (650 MB:
# its OpenCV 4.6 and numba; not part of `make venv`). The pins: numpy < 1.24 (multical uses
# np.bool) and the last scipy, matplotlib, numba, numpy-quaternion and contourpy that take that
# numpy; multical itself pins opencv-contrib-python <= 4.7 (4.6.0.66, built against numpy 1.x).
multical-env:
	@if [ -z "$(MULTICAL_PYTHON)" ]; then echo "no python3.10 found: the multical tool will skip"; exit 0; fi; \
	$(MULTICAL_PYTHON) -m venv $(VENV)/multical && \
	$(VENV)/multical/bin/python -m pip install --quiet multical==0.4.0 "numpy<1.24" "scipy<1.12" \
		"matplotlib<3.9" "numba<0.59" "numpy-quaternion<2024" "contourpy<1.3"

venv: $(BIN)/stereo-bench

demo: venv
	$(BIN)/stereo-bench configs/quickstart.yaml --out out/quickstart
	$(BIN)/pose-eval --calib all --run out/quickstart --out out/quickstart/pose_eval

test: venv
	$(BIN)/python -m pytest -q

clean:
	rm -rf $(VENV) out
