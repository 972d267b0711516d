# The two commands of the README: `make demo` (main job) and `make test` (tests).
# Each creates .venv and installs the tested versions from constraints.txt.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench clean-spool recipe-cpu recipe-shipped

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -c constraints.txt -e '.[test,web]'
	touch $(STAMP)

# Generate a small spool (2,000 samples kept, 3,000 published so it rotates) and draw a preview,
# then fit a real-sized mask with the shipped models and score them on fresh noisy masks.
demo: $(STAMP)
	$(BIN)/cuboidgen run --spool data_spool --limit 2000 --max-samples 3000 --no-dashboard
	$(BIN)/cuboidgen inspect data_spool
	$(BIN)/cuboidgen preview data_spool --out preview.png
	@echo "preview written to preview.png"
	$(BIN)/cuboidtrain models
	# The shipped models on a mask of another size, with the picture of how the networks got there.
	mkdir -p runs/demo  # --json writes into a folder that exists (a missing one is an error, not made)
	$(BIN)/cuboidtrain infer examples/building.png --explain runs/demo/explain --json runs/demo/infer.json
	# And on 200 fresh noisy, occluded 256 px street masks, as `eval` scores them (drawn afresh:
	# the same seed into a spool that has them would add the same 200 again).
	rm -rf runs/demo/val
	$(BIN)/cuboidgen run --spool runs/demo/val --scene street --limit 0 --max-samples 200 --seed 3 --workers 1 --no-dashboard
	$(BIN)/cuboidtrain eval --spool runs/demo/val
	@echo "records in runs/demo/infer.json; explanation panel runs/demo/explain/building.png"

# Two workers (pytest-xdist), as the machine it is timed on has two cores: most tests wait on a
# process they started (a daemon, torchrun, a lease), and the other core runs another test meanwhile.
# loadfile: a worker takes whole files, so a module's costly fixture (a lease, torchrun's model)
# is built once, not once a worker.
test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

bench: $(STAMP)
	$(BIN)/python benchmarks/speed/bench_generate.py
	$(BIN)/python benchmarks/speed/bench_spool_read.py
	$(BIN)/python benchmarks/speed/bench_train.py
	$(BIN)/python benchmarks/speed/bench_infer.py --threads 2
	$(BIN)/python benchmarks/speed/bench_infer.py --threads 1

clean-spool:
	find data_spool -mindepth 1 ! -name .gitkeep -delete

# The CPU recipe (recipes/cpu.sh): the paper's arch at 64 px, box and twobox, under an hour each on 2 cores.
recipe-cpu: $(STAMP)
	recipes/cpu.sh box
	recipes/cpu.sh twobox

# The shipped models (recipes/shipped.sh): both shapes side by side, one thread each, about 1 h 50 min.
recipe-shipped: $(STAMP)
	recipes/shipped.sh box & recipes/shipped.sh twobox & wait
