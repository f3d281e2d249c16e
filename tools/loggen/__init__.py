"""Camera logs made to order: the sample-log generator, the container writers, and the tools
that pack, shrink and compare logs (tools/README.md). Importable with `tools` on the path (the
tests' pytest `pythonpath`); each module with a command line runs, from the repository root, as
`PYTHONPATH=tools python -m loggen.MODULE`."""
