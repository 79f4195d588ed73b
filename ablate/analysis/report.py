"""The work of ``python -m ablate.report`` (:mod:`ablate.report` reads its arguments first, then imports this): each
table rendered from its committed records, or published from the store, through the one module that writes under
``results/`` (:mod:`ablate.tables.published`); the records loaded into a store, sealed again after an intended
edit, a row's seed rerun (:mod:`ablate.analysis.reproduce`) or its precision parity written
(:mod:`ablate.tables.parity`).

A table whose records are broken (:class:`~ablate.tables.seal.BrokenRecords`: cut short, reordered, a line
repeated or edited, a column lost, a seal missing) is one ``error:`` line naming the file, the line and what is
wrong; the other tables are rendered all the same, and the command ends with status 1 and the list of tables it
could not render. A table is never rendered from records that differ from what was published.
"""

from __future__ import annotations

import copy
import sys
import time
from argparse import Namespace

import pandas as pd
from hydra.errors import HydraException
from omegaconf import DictConfig

from ablate.analysis.load import PARENT, load_table
from ablate.analysis.reproduce import recorded_config, reproduce
from ablate.config import compose, composition_error
from ablate.store import AccessDenied, ServerUnreachable, Tracker, config_hash
from ablate.tables import collect, published, table_spec
from ablate.tables.parity import parity
from ablate.tables.seal import BrokenRecords

#: Fingerprints computed by this process, by config hash: tables share rows (ChiNet Tables II-V all hold the ChiNet
#: row), and a shared row's lowest seed has one config hash in each of them.
_fingerprints: dict[str, dict[str, list[float]]] = {}


def fingerprint(cfg: DictConfig) -> dict[str, list[float]]:
    """Today's fingerprint of a row's job config (:func:`ablate.jobs.fingerprint.compute`), once per config hash in a
    process, imported on first use: it builds models with torch and Lightning, which a table whose runs match
    today's code never needs."""
    from ablate.jobs.fingerprint import compute

    key = config_hash(cfg)
    if key not in _fingerprints:
        _fingerprints[key] = compute(cfg)
    return copy.deepcopy(_fingerprints[key])


def run(parsed: Namespace) -> int:
    """Do what the parsed arguments (:func:`ablate.cli.report`) ask; a store that refuses this client or does not
    answer within ``logger.outage_s``, or an override that does not compose (``experiment=<unknown>``), is one
    error and status 1."""
    try:
        return _run(parsed)
    except (AccessDenied, ServerUnreachable) as err:  # a store refusing or silent
        print(f"error: {err}", file=sys.stderr)
        return 1
    except HydraException as err:  # a bad override: experiment=<unknown>, a user's config without its search path
        print(f"error: {composition_error(err)}", file=sys.stderr)
        return 1


def _run(parsed: Namespace) -> int:
    args = list(parsed.overrides)
    if parsed.reproduce:
        return _reproduce(args)
    if parsed.parity:
        return _parity(args)
    named = [a.split("=", 1)[1] for a in args if a.startswith("experiment=")]
    rest = [a for a in args if not a.startswith("experiment=")]
    if parsed.load:
        return _load(named or published.experiments(), rest)
    if parsed.extend:
        return _extend(named[0], rest)
    if parsed.seal:
        return _seal(named or published.experiments())
    if parsed.publish:
        if code := _publish(named, rest):
            return code
        broken: list[str] = []
    else:
        broken = _from_records(named or published.experiments(), rest)
    for path in published.summary([table_spec(compose(rest + [f"experiment={n}"])) for n in published.with_tables()]):
        print(path)
    if broken:
        print(f"error: {len(broken)} table(s) not rendered, their records broken (above): {', '.join(broken)}",
              file=sys.stderr)  # fmt: skip
        return 1
    return 0


def _from_records(names: list[str], rest: list[str]) -> list[str]:
    """Render each table from its run records; one line for each table that has none, one error for each whose
    records are broken (the tables it could not render, returned), and the time it took."""
    start, rendered, broken = time.monotonic(), 0, []
    for name in names:
        base = rest + [f"experiment={name}"]
        try:
            paths = published.render(compose(base), fingerprint, lambda runs: recorded_config(runs, base))
        except BrokenRecords as err:
            print(f"error: {err}", file=sys.stderr)
            broken.append(name)
            continue
        if paths is None:
            print(f"{name}: no run records yet ({published.records(name)}); its table is left as it is")
            continue
        rendered += 1
        for path in paths:
            print(path)
    minutes, seconds = divmod(round(time.monotonic() - start), 60)
    print(f"{rendered} table(s) rendered from their records in {minutes} min {seconds:02d} s", file=sys.stderr)
    return broken


def _seal(names: list[str]) -> int:
    """Seal each table's records again (:func:`ablate.tables.published.seal`), once each file parses; a file that
    does not is one error, and status 1."""
    failed = []
    for name in names:
        try:
            sealed = published.seal(name)
        except BrokenRecords as err:
            print(f"error: {err}", file=sys.stderr)
            failed.append(name)
            continue
        print(sealed if sealed is not None else f"{name}: no run records ({published.records(name)}): nothing to seal")
    if failed:
        print(f"error: {len(failed)} table(s) not sealed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


def _load(names: list[str], rest: list[str]) -> int:
    """Load each table's published records into the configured store (:func:`ablate.tables.records.load_records`),
    those whose seal holds; broken records are one error each, and status 1."""
    tracker = Tracker.from_config(compose(rest))
    broken = 0
    for name in names:
        path = published.records(name)
        if not path.exists():
            print(f"{name}: no run records yet ({path})")
            continue
        try:
            published.check(name)
        except BrokenRecords as err:
            print(f"error: {err}", file=sys.stderr)
            broken += 1
            continue
        loaded, link = load_table(tracker, name)
        print(f"{name}: {loaded} run(s) loaded from {path} into {tracker.uri}, under the run '{name}{PARENT}': {link}")
    print("`mlflow ui` here shows them (kind: imported; each table's rows side by side on its parent run)")
    return 1 if broken else 0


def _extend(name: str, rest: list[str]) -> int:
    """Load table ``name``'s published records into the configured store as its own jobs where they stand in for
    them (:func:`ablate.analysis.extend.extend_table`); records that are not what was published, or a table with a
    tuning phase, are one error and status 1."""
    from ablate.analysis.extend import extend_table

    path = published.records(name)
    if not path.exists():
        print(f"error: {name} has no run records ({path}): nothing to race on from", file=sys.stderr)
        return 1
    try:
        published.check(name)
        tracker = Tracker.from_config(compose(rest + [f"experiment={name}"]))
        done = extend_table(tracker, name, path.parent.parent, fingerprint, rest + [f"experiment={name}"])
    except (BrokenRecords, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    for line in done.refused:
        print(f"not loaded, its job will train: {line}")
    print(
        f"{name}: {done.loaded} run(s) loaded from {path} into {tracker.uri} as its jobs"
        + (f", {done.held} already there" if done.held else "")
        + (f", {len(done.refused)} not loaded (above)" if done.refused else "")
        + f"; `python -m ablate -m experiment={name}` races on from its next look (a race its wall-time budget "
        "stopped needs a larger scale.race.budget_min: its earlier sweeps count)"
    )
    return 0


def source_sweep(tracker: Tracker, cfg: DictConfig) -> str | None:
    """The sweep's run a published table is attached to: the one sweep all its rows came from, else none (a table
    whose rows came from several sweeps belongs to none of them)."""
    sweeps = set(collect(tracker, str(cfg.table.name)).get("sweep_id", pd.Series(dtype=str)).fillna(""))
    return sweeps.pop() or None if len(sweeps) == 1 else None


def _publish(named: list[str], rest: list[str]) -> int:
    """Publish from the store: each table's records, then the table from them (the ad-hoc table too, unnamed)."""
    names = named or ["ablate", *published.experiments()]
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
        for path in published.publish(cfg, tracker, source_sweep(tracker, cfg), fingerprint, records=name != "ablate"):
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
    except (ValueError, RuntimeError) as err:  # BrokenRecords among them: the published records, named
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
    print(published.parity(found))
    print(found.verdict())
    return 0
