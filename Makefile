# Two commands a user needs: `make run` (the main job, default CPU configuration) and
# `make test`. Both create or refresh the repo-local .venv idempotently.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

.PHONY: run run-box test venv bench clean

venv: $(STAMP)

# torch==2.13.0 is installed first so pip takes the CPU build on disk instead of a CUDA build.
$(STAMP): setup.cfg pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

# The main job: the round-sinter calibration of the paper's Table 2 (profile=lab_round: the slot's width and the
# sinter's rolling, sliding and wall friction, the sinter's fines kept as sieved, on the box set of profile=lab_box)
# from its shipped campaign store (copied to the run directory; the shipped file is never written): it runs only
# what the store lacks, runs the verification's 5 replicates of the calibrated set again here (verification.fresh)
# and writes the report. Two one-thread workers, as the campaign ran; the last run takes both cores once the other
# worker is idle (bo/campaign/cores.py). A lab_round run holds 43,706 spheres, so the fresh verification takes
# 37-52 minutes on 2 cores, by host (README, "Results"). The campaigns it builds on, each from its own store:
# `make run-box` (profile=lab_box, about 14 minutes), profile=lab store_from=campaigns/table2/lab.sqlite; the first
# campaign, whose runs stopped 4 s after the gate opened: profile=lab_4s store_from=campaigns/table2/lab_4s.sqlite.
# The mini-box pipeline against its synthetic twin: torchdem-calibrate profile=cpu (profile=smoke in the tests).
FROM_STORE := OMP_NUM_THREADS=1 $(VENV)/bin/torchdem-calibrate verification.fresh=true executor=dask \
	executor.n_workers=2 executor.batch_size=1

run: $(STAMP)
	$(FROM_STORE) profile=lab_round store_from=campaigns/table2/lab_round.sqlite

run-box: $(STAMP)
	$(FROM_STORE) profile=lab_box store_from=campaigns/table2/lab_box.sqlite

# The C++ kernels are built (or found in torch's cache) before the tests start, on both cores,
# instead of inside the first test of each test worker. The 25 slowest tests are listed at the end,
# so a CI log says where the suite's time goes (it must stay under 20 minutes on 2 cores).
test: $(STAMP)
	$(PY) -c "from torchdem._ext import cpu_kernels; cpu_kernels()"
	$(PY) -m pytest -n 2 --dist loadgroup --durations=25

bench: $(STAMP)
	$(PY) scripts/bench_engine.py

clean:
	rm -rf $(VENV) outputs multirun
