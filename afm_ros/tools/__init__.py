"""Command-line tools on top of the cores and nodes: the instrument job, study, report, benchmarks."""
