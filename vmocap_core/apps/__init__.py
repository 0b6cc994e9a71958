"""Applications built on the method: the demo, offline processing, reports, benchmarks and
evaluations. Nothing in the method's packages imports from here."""
