# The two README commands: `make demo` (set up, then run the main job) and `make test`.
.PHONY: setup demo test bench

setup:
	bash scripts/setup.sh

demo: setup
	.venv/bin/vmocap bench accuracy --plots reports/accuracy

test: setup
	bash scripts/test.sh

bench: setup
	.venv/bin/vmocap bench accuracy --json
	.venv/bin/vmocap bench speed --json
