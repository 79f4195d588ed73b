"""``python -m ablate.report``: render every published table under ``results/`` from its run records
(``results/runs/<table>.csv``, :mod:`ablate.tables.records`) alone, with no store; ``python -m ablate.report
experiment=chinet_table2`` just one. A table without records is left as it is, with one line saying so. Last, the
results summary (one line per paper table, :mod:`ablate.tables.index`) is rewritten in ``results/README.md`` and in
``README.md`` where they hold its markers.

``python -m ablate.report --publish [experiment=<table>]`` publishes from the store (``logger.tracking_uri=...`` and
other ``key=value`` overrides apply): each table's records are written from the store's runs, then the table from
them. Nothing else writes under ``results/``: a sweep writes its table into its own folder (``publish=true``
publishes it too). ``python -m ablate.report --load [experiment=<table>]`` loads the published records into your
store, marked as imported, so that ``mlflow ui`` shows the runs behind the published tables. ``python -m ablate.report
--extend experiment=<table>`` loads them as the table's own jobs instead, where this machine and today's code make
their numbers, so that the table's sweep races on from its next look (:mod:`ablate.analysis.extend`).

``python -m ablate.report --reproduce experiment=<table> row=<row> [seed=N]`` reruns one seed of a row here and says
whether it holds (:mod:`ablate.analysis.reproduce`). ``python -m ablate.report --parity experiment=<table> row=<row>``
writes that row's section of ``results/precision_parity.md`` from its fp32 and bf16 runs
(:mod:`ablate.tables.parity`).

Each table's records are sealed (``results/runs/<table>.seal.json``, :mod:`ablate.tables.seal`): a records file cut
short, reordered, with a line repeated or edited by hand or a column lost is one error naming the file and the line,
and that table is not rendered (the others are; the status is 1). After an intended edit, ``python -m ablate.report
--seal [experiment=<table>]`` checks that each of the table's records files parses and seals them again."""

from ablate import cli


def main(argv: list[str] | None = None) -> int:
    """Read the arguments (:func:`ablate.cli.report`: ``--help`` and a bad option end the process there, status 0
    and 2) before MLflow, torch and the tables are imported, then do the work (:func:`ablate.analysis.report.run`):
    status 0, or 1 for a store that refuses this client or does not answer, an override that does not compose, or
    broken records."""
    args = cli.report(__doc__, argv)
    from ablate.analysis.report import run

    return run(args)


if __name__ == "__main__":
    raise SystemExit(main())
