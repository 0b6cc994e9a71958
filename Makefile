# The two README commands: `make demo` (set up, then run the main job) and `make test`.
.PHONY: setup demo test bench

setup:
	bash scripts/setup.sh

# End-to-end demo on the Pose2Sim videos (fetched from PyPI): node graph + CNN, report in reports/demo/
demo: setup
	.venv/bin/vmocap demo --overwrite

test: setup
	bash scripts/test.sh

# Benchmarks: figures on stdout (add --json to any of them for machine-readable output)
bench: setup
	.venv/bin/vmocap bench accuracy --plots reports/accuracy
	.venv/bin/vmocap bench speed
	.venv/bin/vmocap bench pcm
	ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST .venv/bin/vmocap bench graph
	.venv/bin/vmocap eval shelf
