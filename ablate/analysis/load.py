"""``python -m ablate.report --load [experiment=<table>]``: a published table's records in a store, readable in
``mlflow ui``.

Each table's records become FINISHED runs of kind ``imported`` (:func:`ablate.tables.records.load_records`), grouped
under one parent run per table, named ``<table> (published)``: it carries the table's markdown, its records (CSV)
and its figures as artifacts, and one metric per row, ``<row>/<primary>``, the row's mean over its seeds, so that
the rows sit side by side on one line. Each loaded run gets the params of its config composed today from its
table, row, seed, scale and recorded tuned values (:func:`ablate.analysis.reproduce.recorded_config`; records keep no
config: where today's config hash differs from the recorded one, the tag ``params_from`` says so), the generated
dataset it names as its dataset input, and its source (the records file, the recorded commit). The experiment gets
the project's saved view (:meth:`ablate.store.Tracker.share_table_view`) with the primary metric and the parent's
row metrics as columns. Loading again adds nothing twice, and completes runs loaded before parents were made.
"""

from __future__ import annotations

import copy
import hashlib
from pathlib import Path

import pandas as pd
from omegaconf import DictConfig, OmegaConf

from ablate.analysis.reproduce import recorded_config
from ablate.config import compose
from ablate.store import Tracker, config_hash
from ablate.tables import published, table_spec
from ablate.tables.collect import under_condition
from ablate.tables.records import IMPORTED, KIND_IMPORTED, load_records, read_records

#: The suffix of a loaded table's parent run's name.
PARENT = " (published)"


def load_table(tracker: Tracker, name: str) -> tuple[int, str]:
    """Load table ``name``'s published records into ``tracker``'s store under its parent run; (runs loaded now,
    the address of its runs in the MLflow UI)."""
    path = published.records(name)
    base = [f"experiment={name}"]
    table = table_spec(compose(base))
    records = read_records(path)
    exp = tracker.experiment_id(name)
    loaded = load_records(tracker, path)
    parent = parent_run(tracker, exp, name, table, path, records)
    config = recorded_config(records, base)
    by_id = records.set_index("run_id")
    for run in tracker.runs(exp, f"tags.kind = '{KIND_IMPORTED}'"):
        origin = run.data.tags.get(IMPORTED, "")
        if run.info.run_id == parent or run.data.tags.get("mlflow.parentRunId") == parent or "#" not in origin:
            continue
        recorded = origin.rsplit("#", 1)[1]
        if recorded in by_id.index:
            complete(tracker, run.info.run_id, parent, config(recorded), by_id.loc[recorded], path)
    primary = str(table.primary)
    rows = [f"{row}/{primary}" for row in dict.fromkeys(records["row"])]
    return loaded, tracker.share_table_view(exp, [primary, *rows])


def parent_run(tracker: Tracker, exp: str, name: str, table: DictConfig, path: Path, records: pd.DataFrame) -> str:
    """The table's parent run (made once, found by its origin tag): the table's files as artifacts, and per row its
    primary metric's mean over seeds as ``<row>/<primary>``."""
    origin = f"{path.as_posix()}#table"
    found = tracker.runs(exp, f"tags.{IMPORTED} = '{origin}'")
    if found:
        return str(found[0].info.run_id)
    values = under_condition(records, table)
    primary = str(table.primary)
    metrics = {f"{row}/{primary}": float(sel[primary].mean()) for row, sel in values.groupby("row", sort=False)}
    tags = {
        "kind": KIND_IMPORTED,
        IMPORTED: origin,
        "table": name,
        "mlflow.source.name": path.as_posix(),
        "mlflow.source.type": "LOCAL",
        "mlflow.note.content": f"{table.title}: the published table, its records and figures (results/)",
    }
    start, end = int(records["started"].min()), int(records["ended"].max())
    run = tracker.import_run(exp, f"{name}{PARENT}", tags, metrics, start, end)
    results = path.parent.parent
    for file in [results / f"{name}.md", path, *sorted(results.glob(f"{name}*.png"))]:
        if file.is_file():
            tracker.log_artifact(run, file, "table")
    return run


def complete(tracker: Tracker, run_id: str, parent: str, cfg: DictConfig, record: pd.Series, path: Path) -> None:
    """A loaded run's parent, params (its config at its recorded precision and threads), dataset input and
    source."""
    from ablate.data import DEFAULT_SYNTH
    from ablate.data.datamodule import synth_dir  # the generated data's folder name, without generating it
    from ablate.jobs.tags import params_of

    cfg = copy.deepcopy(cfg)
    for key, column in (("trainer.precision", "made_precision"), ("trainer.threads", "made_threads")):
        if pd.notna(record.get(column)) and str(record.get(column)):  # the recorded numerics, not this machine's
            OmegaConf.update(cfg, key, int(record[column]) if key.endswith("threads") else str(record[column]))
    same = config_hash(cfg) == str(record.get("config_hash", ""))
    tags = {
        "mlflow.parentRunId": parent,
        "mlflow.source.name": path.as_posix(),
        "mlflow.source.type": "LOCAL",
        "mlflow.source.git.commit": str(record.get("git_commit", "")),
        "params_from": "the recorded config" if same else "today's config of its row (its hash differs)",
    }
    tracker.set_tags(run_id, tags)
    tracker.log_params(run_id, params_of(cfg))
    data = cfg.data
    if data.get("root") is None:
        params = OmegaConf.to_container(data.synth, resolve=True)
        assert isinstance(params, dict)
        folder = synth_dir(str(data.data_dir), {**DEFAULT_SYNTH, **params})  # as ensure_synth names it
        digest = hashlib.sha1(folder.name.encode()).hexdigest()[:12]
        tracker.log_dataset(run_id, folder.name, digest, str(folder), {"frames": int(data.synth.frames)})
