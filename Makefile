# The two commands of the README: `make demo` (main job) and `make test` (tests).
# Each creates .venv and installs the tested versions from constraints.txt.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench clean-spool recipe-cpu

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -c constraints.txt -e '.[test]'
	touch $(STAMP)

# Generate a small spool (2,000 samples kept, 3,000 published so it rotates) and draw a preview.
demo: $(STAMP)
	$(BIN)/cuboidgen run --spool data_spool --limit 2000 --max-samples 3000 --no-dashboard
	$(BIN)/cuboidgen inspect data_spool
	$(BIN)/cuboidgen preview data_spool --out preview.png
	@echo "preview written to preview.png"
	# A one-minute taste of training: a 64 px spool, phase 1 then phase 2, evaluated on clean masks.
	$(BIN)/cuboidgen run --spool runs/demo/spool --size 64 --limit 0 --max-samples 400 --seed 1 --no-dashboard
	$(BIN)/cuboidgen run --spool runs/demo/val --size 64 --scene paper-clean --limit 0 --max-samples 64 --seed 2 --no-dashboard
	$(BIN)/cuboidtrain run --phase 1 --spool runs/demo/spool --size 64 --batch-size 8 --steps 40 --out runs/demo/p1 --no-dashboard
	$(BIN)/cuboidtrain run --phase 2 --spool runs/demo/spool --size 64 --batch-size 8 --steps 10 --init runs/demo/p1/last.pt --out runs/demo/p2 --no-dashboard
	$(BIN)/cuboidtrain eval --checkpoint runs/demo/p2/last.pt --spool runs/demo/val
	# Inference on a mask of another size, with the picture of how the networks got there.
	$(BIN)/cuboidtrain infer examples/building.png --checkpoint runs/demo/p2/last.pt --explain runs/demo/explain --json runs/demo/infer.json
	@echo "records in runs/demo/infer.json; explanation panel runs/demo/explain/building.png (a one-minute model: expect a rough fit)"

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_generate.py
	$(BIN)/python benchmarks/bench_spool_read.py
	$(BIN)/python benchmarks/bench_train.py
	$(BIN)/python benchmarks/bench_infer.py --threads 2
	$(BIN)/python benchmarks/bench_infer.py --threads 1

clean-spool:
	find data_spool -mindepth 1 ! -name .gitkeep -delete

# The CPU recipe (recipes/cpu.sh): a 64 px box and twobox model, under an hour each on 2 cores.
recipe-cpu: $(STAMP)
	recipes/cpu.sh box
	recipes/cpu.sh twobox
