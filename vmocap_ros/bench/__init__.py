"""Benchmarks and fault harnesses of the node graph (`vmocap bench graph|faults|soak`, the image
benchmark's graph run); not needed to run the graph."""
