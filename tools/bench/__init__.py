"""Benchmarks of the package: time and memory of `annotate`, its stages and kernels, and the
machine's own speed (tools/bench/README.md). Each runs, from the repository root, as
`PYTHONPATH=tools python -m bench.MODULE`."""
