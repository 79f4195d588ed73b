"""The racing sweeper (``hydra/sweeper=racing``): a table's seeds look by look, :mod:`ablate.tables.racing`."""
