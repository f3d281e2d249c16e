"""The scripts that rebuild the tables of docs/ and docs/research/, and the check that this
version's outputs equal an earlier one's (tools/reproduce/README.md). Each runs, from the
repository root, as `PYTHONPATH=tools python -m reproduce.MODULE`."""
