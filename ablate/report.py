"""``python -m ablate.report``: render every published table under ``results/`` from its run records
(``results/runs/<table>.csv``, :mod:`ablate.tables.records`) alone, with no store; ``python -m ablate.report
experiment=chinet_table2`` just one. A table without records is left as it is, with one line saying so. Last, the
results summary (one line per paper table, :mod:`ablate.tables.index`) is rewritten in ``results/README.md`` and in
``README.md`` where they hold its markers.

``python -m ablate.report --publish [experiment=<table>]`` publishes from the store (``logger.tracking_uri=...`` and
other ``key=value`` overrides apply): each table's records are written from the store's runs, then the table from
them. Nothing else writes under ``results/``: a sweep writes its table into its own folder (``publish=true``
publishes it too). ``python -m ablate.report --load [experiment=<table>]`` loads the published records into your
store, marked as imported, so that ``mlflow ui`` shows the runs behind the published tables.

``python -m ablate.report --reproduce experiment=<table> row=<row> [seed=N]`` reruns one seed of a row here and says
whether it holds (:mod:`ablate.analysis.reproduce`). ``python -m ablate.report --parity experiment=<table> row=<row>``
writes that row's section of ``results/precision_parity.md`` from its fp32 and bf16 runs
(:mod:`ablate.tables.parity`)."""

from __future__ import annotations

import sys
import time
from argparse import Namespace
from collections.abc import Callable
from pathlib import Path

import pandas as pd
from hydra.errors import HydraException
from omegaconf import DictConfig

from ablate import cli
from ablate.analysis.reproduce import reproduce, tuned_config
from ablate.config import CONF, compose, composition_error
from ablate.jobs.spec import apply_draws
from ablate.store import AccessDenied, ServerUnreachable, Tracker
from ablate.tables import collect, render_records, table_spec, write_table
from ablate.tables.index import write_index
from ablate.tables.parity import parity, write_parity
from ablate.tables.records import load_records, records_path

#: Where published tables and their records live.
RESULTS = Path("results")


def fingerprint(cfg: DictConfig) -> dict[str, list[float]]:
    """Today's fingerprint of a row's job config (:func:`ablate.jobs.fingerprint.compute`), imported on first use: it
    builds models with torch and Lightning, which a table whose runs match today's code never needs."""
    from ablate.jobs.fingerprint import compute

    return compute(cfg)


def main(argv: list[str] | None = None) -> int:
    """Write the tables (and the results summary); a store that refuses this client or does not answer within
    ``logger.outage_s``, or an override that does not compose (``experiment=<unknown>``), is one error and status 1. The arguments are read by
    :func:`ablate.cli.report`: ``--help`` and a bad option end the process there (status 0 and 2)."""
    args = cli.report(__doc__, argv)
    try:
        return _main(args)
    except (AccessDenied, ServerUnreachable) as err:  # a store refusing or silent
        print(f"error: {err}", file=sys.stderr)
        return 1
    except HydraException as err:  # a bad override: experiment=<unknown>, a user's config without its search path
        print(f"error: {composition_error(err)}", file=sys.stderr)
        return 1


def _main(parsed: Namespace) -> int:
    args = list(parsed.overrides)
    if parsed.reproduce:
        return _reproduce(args)
    if parsed.parity:
        return _parity(args)
    named = [a.split("=", 1)[1] for a in args if a.startswith("experiment=")]
    rest = [a for a in args if not a.startswith("experiment=")]
    experiments = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
    if parsed.load:
        return _load(named or experiments, rest)
    code = _publish(named, rest) if parsed.publish else _from_records(named or experiments, rest)
    if code:
        return code
    for path in write_index(
        [table_spec(compose(rest + [f"experiment={n}"])) for n in experiments], RESULTS, "README.md"
    ):
        print(path)
    return 0


def _from_records(names: list[str], rest: list[str]) -> int:
    """Render each table from its run records; one line for each table that has none, and the time it took."""
    start, rendered = time.monotonic(), 0
    for name in names:
        base = rest + [f"experiment={name}"]
        paths = render_records(compose(base), RESULTS, fingerprint, lambda runs: recorded_config(runs, base))
        if paths is None:
            print(f"{name}: no run records yet ({records_path(RESULTS, name)}); its table is left as it is")
            continue
        rendered += 1
        for path in paths:
            print(path)
    minutes, seconds = divmod(round(time.monotonic() - start), 60)
    print(f"{rendered} table(s) rendered from their records in {minutes} min {seconds:02d} s", file=sys.stderr)
    return 0


def _load(names: list[str], rest: list[str]) -> int:
    """Load each table's published records into the configured store (:func:`ablate.tables.records.load_records`)."""
    tracker = Tracker.from_config(compose(rest))
    for name in names:
        path = records_path(RESULTS, name)
        if not path.exists():
            print(f"{name}: no run records yet ({path})")
            continue
        print(f"{name}: {load_records(tracker, path)} run(s) loaded from {path} into {tracker.uri}")
    print("`mlflow ui` here shows them (kind: imported)")
    return 0


def recorded_config(runs: pd.DataFrame, base: list[str]) -> Callable[[str], DictConfig]:
    """The config of a recorded run, composed today from its table, row, seed and scale, on the config a tuning
    phase chose for its row (the records' ``tuned_config``, applied as its job applied it): records keep no
    config; a row whose config changed since has another config hash, which the footer's fingerprint check sees."""
    by_id = runs.set_index("run_id")

    def config(run_id: str) -> DictConfig:
        run = by_id.loc[run_id]
        overrides = base + [f"row={run['row']}", f"seed={run['seed']}", f"scale={run['scale']}"]
        cfg = compose(overrides)
        tuned = tuned_config(runs[runs["row"] == run["row"]], cfg)
        if tuned:
            cfg = compose(overrides + tuned)
            apply_draws(cfg)
        return cfg

    return config


def source_sweep(tracker: Tracker, cfg: DictConfig) -> str | None:
    """The sweep's run a published table is attached to: the one sweep all its rows came from, else none (a table
    whose rows came from several sweeps belongs to none of them)."""
    sweeps = set(collect(tracker, str(cfg.table.name)).get("sweep_id", pd.Series(dtype=str)).fillna(""))
    return sweeps.pop() or None if len(sweeps) == 1 else None


def _publish(named: list[str], rest: list[str]) -> int:
    """Publish from the store: each table's records, then the table from them (the ad-hoc table too, unnamed)."""
    names = named or ["ablate"] + sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
    written = 0
    for name in names:
        cfg = compose(rest + ([] if name == "ablate" else [f"experiment={name}"]))
        tracker = Tracker.from_config(cfg)
        exp = tracker.find_experiment(cfg.table.name)
        if exp is None:
            if named:
                print(f"error: no runs for experiment '{name}' in {tracker.uri}", file=sys.stderr)
                return 1
            continue
        for path in write_table(
            cfg, tracker, source_sweep(tracker, cfg), RESULTS, fingerprint, publish=name != "ablate"
        ):
            print(path)
        written += 1
    if not written:
        print(f"No tables written: no runs in {Tracker.from_config(compose(rest)).uri}", file=sys.stderr)
    return 0


def _reproduce(args: list[str]) -> int:
    """Rerun one seed of a row and print whether it lies in the row's prediction interval; 0 inside, 2 outside
    (the verdict on stdout; a bad option, also 2, is an ``error:`` line on stderr instead)."""
    cfg = compose([a for a in args if not a.startswith(("row=", "seed="))])
    try:
        outcome = reproduce(cfg, args)
    except (ValueError, RuntimeError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print("\n".join(outcome.lines()))
    return 0 if outcome.inside else 2


def _parity(args: list[str]) -> int:
    """Write one row's bf16-against-fp32 section from the store's runs; a row without both is one error line."""
    rows = [a.split("=", 1)[1] for a in args if a.startswith("row=")]
    cfg = compose([a for a in args if not a.startswith("row=")])
    try:
        found = parity(Tracker.from_config(cfg), table_spec(cfg), rows[0])
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(write_parity(found, Path("results") / "precision_parity.md"))
    print(found.verdict())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
