"""Command-line tools on top of the cores and nodes: the instrument job, study, report (the
benchmarks are in the repository's benchmarks/ folder, not in the package)."""
